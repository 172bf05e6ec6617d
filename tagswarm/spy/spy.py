"""``tagswarm spy [KEYEXPR]``: live inspection of what flows on a running system's Zenoh bus.

Joins the network with the same flags and ``TAGSWARM_*`` variables as every
process (``--connect``, ``--zenoh-mode``, ``--run`` ...) as a passive
subscriber (it declares no liveliness token, so it never joins a lockstep) and
shows, per key: the message type (every payload is decoded once with
:func:`tagswarm.protocol.codec.decode_any`; undecodable ones are shown as
``undecodable:<kind>``, never raised), the Zenoh encoding of the newest sample
(``application/msgpack;<MessageType>`` for every tagswarm publication), how many
samples had an encoding that does not match their message (BAD_ENC; the total
is in the title), the rate, the bandwidth, the simulation time and a short view
of the newest message (images are summarised as ``320x240 mono8 robot 1 front``,
never dumped).  Liveliness tokens matching
KEYEXPR (``tagswarm/<run>/alive/...``) are listed below the table.

Modes:

- default: a live table (rich) on a terminal; plain-text snapshots every
  ``--window`` seconds when stdout is not a terminal.
- ``--once [--window S]``: sample for S seconds (default 2), print one snapshot
  (plain text unless stdout is a terminal) and exit 0.
- ``--echo``: print every message as one JSON line (``{"key", "size",
  "encoding", "msg"}``, bytes fields replaced by a summary, plus
  ``"encoding_mismatch": true`` when the encoding does not match the message;
  ``{"key", "size", "encoding", "error"}`` for an undecodable payload;
  ``{"key", "alive"}`` for a liveliness change).  With
  ``--once`` it stops after the window.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import TextIO

import msgspec
from rich.console import Console
from rich.live import Live
from rich.table import Table

from tagswarm.protocol.bus import Bus, open_bus
from tagswarm.protocol.keys import Keys
from tagswarm.runtime.config import ConfigError, Invocation, OneLineParser, add_common_args
from tagswarm.runtime.process import install_stop_signals, run_main, setup_logging
from tagswarm.spy.describe import decode, echo_line, image_summary, message_json, summarise, type_name

# (not in the docstring: it is the --help text) message views live in tagswarm.spy.describe,
# statistics and snapshots in tagswarm.spy.traffic; their public names are re-exported here
from tagswarm.spy.traffic import (
    LAST_WIDTH,
    KeyStats,
    Row,
    Traffic,
    encoding_mismatch,
    human_rate,
    plain_snapshot,
    rich_snapshot,
)

__all__ = [
    "INBOX_CAPACITY", "LAST_WIDTH", "PROG", "KeyStats", "Row", "Spy", "Traffic", "decode", "echo_line",
    "encoding_mismatch", "human_rate", "image_summary", "main", "message_json", "parser", "plain_snapshot",
    "rich_snapshot", "run_spy", "summarise", "type_name",
]

PROG = "tagswarm spy"
#: Items an unread subscription may hold before the oldest are dropped (and counted).
INBOX_CAPACITY = 20_000


class Spy:
    """Subscribes to ``keyexpr`` (and its liveliness tokens) and feeds a :class:`Traffic`."""

    def __init__(self, bus: Bus, keyexpr: str, window_s: float, *, alive: bool = True,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        self.traffic = Traffic(window_s, clock())
        try:
            self.inbox = bus.subscribe_encoded(keyexpr, capacity=INBOX_CAPACITY)
            self.alive_in = bus.watch_liveliness(keyexpr) if alive else None
        except Exception as exc:  # zenoh rejects malformed key expressions when declaring
            reason = " ".join(str(exc).split()).split(" at /", 1)[0]  # drop zenoh's Rust source location
            raise ConfigError(f"bad key expression {keyexpr!r}: {reason}") from None

    @property
    def dropped(self) -> int:
        return self.inbox.overflow

    def poll(self, echo: Callable[[str], None] | None = None) -> None:
        """Take in everything that arrived; ``echo`` gets one JSON line per event."""
        now = self.clock()
        if self.alive_in is not None:
            for change in self.alive_in.drain():
                self.traffic.liveliness(change.key, change.value)
                if echo is not None:
                    echo(msgspec.json.encode({"key": change.key, "alive": change.value}).decode())
        for item in self.inbox.drain():
            encoding, payload = item.value
            decoded = self.traffic.add(item.key, payload, now, encoding)
            if echo is not None:
                echo(echo_line(item.key, len(payload), decoded, encoding,
                               encoding_mismatch(encoding, payload, decoded)))


#: why a spy may hear nothing at all, said on stderr when it ends so
NOTHING_HEARD = ("is a run going on under this --run, and is this spy linked to it (--connect the endpoint "
                 "tagswarm up prints, or --zenoh-mode client against the run's router)?")


def absolute_keyexpr(expr: str, keys: Keys) -> str:
    """``expr`` as given when it starts with ``tagswarm/`` or a wildcard, else relative to the run
    (``robot/1/odometry`` -> ``tagswarm/<run>/robot/1/odometry``), as the testing fixture reads it."""
    if expr.startswith(("tagswarm/", "*", "$*")):
        return expr
    return keys.all()[:-2] + expr.lstrip("/")


def parser() -> OneLineParser:
    p = OneLineParser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("keyexpr", nargs="?", metavar="KEYEXPR",
                   help="Zenoh key expression to watch (default: every key of the run, tagswarm/<run>/**); "
                        "one that does not start with tagswarm/ or a wildcard is relative to the run, e.g. "
                        "robot/1/odometry")
    p.add_argument("--once", action="store_true", help="sample for --window seconds, print one snapshot, exit 0")
    p.add_argument("--window", type=float, default=2.0, metavar="SECONDS",
                   help="sampling window of --once and averaging window of the rates (default 2)")
    p.add_argument("--echo", action="store_true", help="print every message as a JSON line instead of the table")
    p.add_argument("--plain", action="store_true", help="plain-text snapshots even on a terminal")
    p.add_argument("--no-alive", action="store_true", help="do not list liveliness tokens")
    add_common_args(p, scenario="none")
    return p


def _writer(out: TextIO) -> Callable[[str], None]:
    def write(line: str) -> None:
        out.write(line + "\n")

    return write


def run_spy(spy: Spy, *, keyexpr: str, once: bool, window_s: float, echo: bool, plain: bool,
            stop: threading.Event, out: TextIO) -> int:
    """The loop: poll every 0.1 s; print per mode (see the module docstring)."""
    emit = _writer(out) if echo else None
    t0 = spy.clock()
    deadline = t0 + window_s if once else math.inf

    def title() -> str:
        now = spy.clock()
        return (f"tagswarm spy  {keyexpr}  {now - t0:.1f} s  {len(spy.traffic.keys)} key(s)  "
                f"{spy.traffic.total} msg(s)  {spy.traffic.mismatched} encoding mismatch(es)"
                + (f"  dropped {spy.dropped}" if spy.dropped else ""))

    strip = keyexpr[:-2] if keyexpr.endswith("/**") else ""  # "tagswarm/<run>/" for the default

    def snapshot_plain() -> None:
        out.write(plain_snapshot(spy.traffic.rows(spy.clock()), spy.traffic.alive, title()) + "\n")
        out.flush()

    def snapshot_rich(caption: str = "") -> Table:
        return rich_snapshot(spy.traffic.rows(spy.clock()), spy.traffic.alive, title(), caption, strip=strip)

    if echo or once or plain or not out.isatty():
        next_print = t0 + window_s
        while not stop.is_set():
            left = deadline - spy.clock()
            if left <= 0:
                break
            stop.wait(min(0.1, left))
            spy.poll(emit)
            if echo:
                out.flush()
            elif not once and spy.clock() >= next_print:
                snapshot_plain()
                next_print += window_s
        spy.poll(emit)
        if once and not echo:
            if plain or not out.isatty():
                snapshot_plain()
            else:
                Console(file=out).print(snapshot_rich())
        return 0
    console = Console(file=out)
    with Live(console=console, refresh_per_second=4, transient=False) as live:
        while not stop.is_set():
            stop.wait(0.25)
            spy.poll()
            live.update(snapshot_rich("Ctrl-C to quit"))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry for ``tagswarm spy``."""

    def body() -> int:
        inv = Invocation(parser(), argv)
        args = inv.args
        if not math.isfinite(args.window) or args.window <= 0:
            raise ConfigError("--window must be a positive number of seconds")
        setup_logging(inv.log_level("WARNING"), "spy")  # validates --log-level too
        keys = Keys(inv.pick("run", "default"))
        if args.keyexpr is not None and not args.keyexpr.strip():
            raise ConfigError("KEYEXPR must not be empty")
        keyexpr = keys.all() if args.keyexpr is None else absolute_keyexpr(args.keyexpr, keys)
        stop = threading.Event()
        install_stop_signals(stop)
        with open_bus(inv.bus()) as bus:
            spy = Spy(bus, keyexpr, args.window, alive=not args.no_alive)
            try:
                code = run_spy(spy, keyexpr=keyexpr, once=args.once, window_s=args.window, echo=args.echo,
                               plain=args.plain, stop=stop, out=sys.stdout)
                if spy.traffic.total == 0 and not spy.traffic.alive:
                    sys.stderr.write(f"{PROG}: heard nothing on {keyexpr}: {NOTHING_HEARD}\n")
                return code
            except BrokenPipeError:  # e.g. `tagswarm spy --echo | head`: stop quietly
                os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
                return 0

    return run_main(PROG, body)


if __name__ == "__main__":
    raise SystemExit(main())
