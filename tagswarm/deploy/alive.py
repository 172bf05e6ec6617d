"""``tagswarm alive PARTICIPANT``: is a process of a running system up? (compose healthchecks)

    tagswarm alive world/0           exit 0 if the liveliness token tagswarm/<run>/alive/world/0
                                     is visible on the network, else 1
    tagswarm alive --heartbeat PATH  exit 0 if PATH (a router's heartbeat file) was touched in
                                     the last --max-age seconds, else 1

It joins the network with the same flags and ``TAGSWARM_*`` variables as every
process (``--connect``, ``--zenoh-mode``, ``--run`` ...), so in a compose
healthcheck it inherits the service's own environment.  It declares nothing.
Bad flags (or an unreachable router in client mode) exit 2 with one line.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from collections.abc import Sequence

from tagswarm.protocol.bus import open_bus
from tagswarm.protocol.keys import Keys, split_participant
from tagswarm.runtime.config import ConfigError, Invocation, OneLineParser, add_common_args
from tagswarm.runtime.process import run_main, setup_logging

PROG = "tagswarm alive"


def parser() -> OneLineParser:
    p = OneLineParser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("participant", nargs="?", metavar="PARTICIPANT",
                   help="role/id of the process: world/0, server/0, agent/3, router/0 ...")
    p.add_argument("--timeout", type=float, default=2.0, metavar="SECONDS",
                   help="how long to wait for the liveliness query's answers (default 2)")
    p.add_argument("--heartbeat", metavar="PATH", help="check a heartbeat file instead of a liveliness token")
    p.add_argument("--max-age", type=float, default=5.0, metavar="SECONDS",
                   help="with --heartbeat: the file must have been touched this recently (default 5)")
    add_common_args(p, scenario="none", faults=False)
    return p


def heartbeat_age(path: str, now: float | None = None) -> float | None:
    """Seconds since ``path`` was last modified, or None if it does not exist."""
    try:
        mtime = os.stat(path).st_mtime
    except FileNotFoundError:
        return None
    return (time.time() if now is None else now) - mtime


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry for ``tagswarm alive``: 0 alive, 1 not alive, 2 bad usage."""

    def body() -> int:
        inv = Invocation(parser(), argv)
        args = inv.args
        for name in ("timeout", "max_age"):
            value = getattr(args, name)
            if not math.isfinite(value) or value <= 0:
                raise ConfigError(f"--{name.replace('_', '-')} must be a positive number of seconds")
        setup_logging(inv.log_level("WARNING"), "alive")  # validates --log-level too
        if (args.participant is None) == (args.heartbeat is None):
            raise ConfigError("give either PARTICIPANT (e.g. world/0) or --heartbeat PATH")
        if args.heartbeat is not None:
            age = heartbeat_age(args.heartbeat)
            if age is None:
                sys.stderr.write(f"{PROG}: no heartbeat file {args.heartbeat}\n")
                return 1
            if age > args.max_age:
                sys.stderr.write(f"{PROG}: heartbeat {args.heartbeat} is {age:.1f} s old (> {args.max_age:g} s)\n")
                return 1
            print(f"heartbeat {args.heartbeat} is {max(age, 0.0):.1f} s old")
            return 0
        split_participant(args.participant)  # one-line KeyNameError -> exit 2
        run = inv.pick("run", "default")
        key = Keys(run).alive(args.participant)
        with open_bus(inv.bus()) as bus:
            tokens = bus.alive_now(key, args.timeout)
        if key in tokens:
            print(f"{args.participant} is alive ({key})")
            return 0
        sys.stderr.write(f"{PROG}: {args.participant} is not alive (no liveliness token {key})\n")
        return 1

    return run_main(PROG, body)


if __name__ == "__main__":
    raise SystemExit(main())
