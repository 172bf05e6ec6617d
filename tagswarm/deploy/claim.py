"""``tagswarm claim -- COMMAND [ARGS...]``: claim a free robot id, then become COMMAND.

    tagswarm claim -- tagswarm-agent          # compose: every `agent` replica runs this

Joins the network like every process (``--connect``, ``--run``, ``TAGSWARM_*``; in
compose as the ``claimant`` user), asks the claim authority (``tagswarm record-run
--claims``, see tagswarm/deploy/claims.py) for a robot id, writes that robot's password
to a private file in ``--state-dir`` (0600; with ``robot_id``, for the container's
healthcheck: ``tagswarm alive agent/$(cat /tmp/tagswarm-claim/robot_id)``) and
replaces itself with COMMAND (same PID, so signals reach it), adding to its environment
``TAGSWARM_ROBOT_ID=<k>``, ``TAGSWARM_ZENOH_USER=agent<k>`` and
``TAGSWARM_ZENOH_PASSWORD_FILE=<that file>``.

When every robot id is taken, or no authority answers within ``--timeout``, it exits
2 with one line.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from tagswarm.deploy import acl, claims
from tagswarm.protocol.bus import open_bus
from tagswarm.protocol.keys import Keys
from tagswarm.runtime.config import ConfigError, Invocation, OneLineParser, add_common_args
from tagswarm.runtime.process import run_main, setup_logging

PROG = "tagswarm claim"
DEFAULT_STATE_DIR = "/tmp/tagswarm-claim"
ROBOT_ID_FILE = "robot_id"
PASSWORD_FILE = "agent.password"


def parser() -> OneLineParser:
    p = OneLineParser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("command", nargs=argparse.REMAINDER, metavar="-- COMMAND [ARGS...]",
                   help="what to run once a robot id is claimed (e.g. tagswarm-agent)")
    p.add_argument("--timeout", type=float, default=60.0, metavar="SECONDS",
                   help="how long to keep asking while no claim authority answers (default 60)")
    p.add_argument("--state-dir", default=DEFAULT_STATE_DIR, metavar="DIR",
                   help=f"where the claimed id and password are written (default {DEFAULT_STATE_DIR})")
    add_common_args(p)
    return p


def ask(inv: Invocation, timeout_s: float) -> claims.ClaimReply:
    """Query the claim authority until it answers (it may still be starting)."""
    keys = Keys(inv.run())
    key = acl.claim_key(keys)
    deadline = time.monotonic() + timeout_s
    with open_bus(inv.bus()) as bus:
        while True:
            # one reply per query; a reply that does not decode is not an answer
            for item in bus.get(key, timeout_s=min(10.0, timeout_s)):
                reply = claims.decode(item.value)
                if reply is not None:
                    return reply
            if time.monotonic() >= deadline:
                raise ConfigError(f"no claim authority answered on {key} within {timeout_s:g} s")
            time.sleep(0.5)


def keep(reply: claims.ClaimReply, state_dir: Path) -> Path:
    """Write the claimed id and the password (0600) into ``state_dir``; the password file."""
    state_dir.mkdir(mode=0o700, parents=True, exist_ok=True)
    password = state_dir / PASSWORD_FILE
    fd = os.open(password, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as fh:
        fh.write(reply.password + "\n")
    (state_dir / ROBOT_ID_FILE).write_text(f"{reply.robot_id}\n")
    return password


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry for ``tagswarm claim``: execs COMMAND, or returns 2."""

    def body() -> int:
        inv = Invocation(parser(), argv)
        args = inv.args
        command = list(args.command)
        if command[:1] == ["--"]:
            command = command[1:]
        if not command:
            raise ConfigError("give the command to run after --, e.g. tagswarm claim -- tagswarm-agent")
        if not args.timeout > 0:
            raise ConfigError("--timeout must be a positive number of seconds")
        if "TAGSWARM_ROBOT_ID" in inv.env:
            raise ConfigError("TAGSWARM_ROBOT_ID is already set: claim picks the robot id itself")
        setup_logging(inv.log_level("WARNING"), "claim")
        reply = ask(inv, args.timeout)
        if not reply.granted:
            raise ConfigError(f"no robot for this agent: {reply.reason}")
        password = keep(reply, Path(args.state_dir))
        env = {**os.environ, "TAGSWARM_ROBOT_ID": str(reply.robot_id), "TAGSWARM_ZENOH_USER": reply.user,
               "TAGSWARM_ZENOH_PASSWORD_FILE": str(password)}
        sys.stderr.write(f"{PROG}: robot {reply.robot_id} of {reply.robots} (user {reply.user}): "
                         f"running {' '.join(command)}\n")
        sys.stderr.flush()
        try:
            os.execvpe(command[0], command, env)
        except OSError as exc:
            raise ConfigError(f"cannot run {command[0]!r}: {exc.strerror}") from None

    return run_main(PROG, body)


if __name__ == "__main__":
    raise SystemExit(main())
