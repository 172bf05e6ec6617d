"""``tagswarm record-run``: record a run started by others (compose) and write its run folder.

    tagswarm record-run --out-dir /runs --claims /run/secrets/zenoh_agents

A Zenoh client of the run (in compose as the ``recorder`` user) that records what
``tagswarm up`` records (:class:`tagswarm.recording.runrecorder.RunRecorder`: truth,
odometry, corrections, observations, statuses) and, when the run is over, writes the
same run folder: ``scenario.json``, ``run.json``, TUM trajectories, ``metrics.json``
and plots (:func:`tagswarm.evaluation.report.write_report`), into ``--out`` or a new
``--out-dir/<run>-<UTC time>/``.

It declares the liveliness token ``recorder/0`` once subscribed; list it in
``clock.observers`` (compose does) and the world waits for it before the first
tick, so the folder misses nothing.  The run is over when the world's token, once
seen, goes away at the end of the scenario's duration; then it waits (up to
``--linger`` s) for the agents and the server to leave, writes the folder and exits 0.
A world gone earlier is waited for ``--linger`` s (it may come back).  SIGTERM/SIGINT write what was recorded and
exit 130.

With ``--claims FILE`` (``agents.txt`` of ``tagswarm router --make-secrets``) it is
also the claim authority of ``tagswarm claim`` (tagswarm/deploy/claims.py): each
agent replica asks it for a robot id and gets that robot's credentials.
"""

from __future__ import annotations

import argparse
import logging
import threading
import time
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import msgspec

from tagswarm.deploy import acl, claims
from tagswarm.protocol.bus import Bus, Inbox, open_bus
from tagswarm.protocol.keys import Keys
from tagswarm.protocol.layout import pinned
from tagswarm.protocol.scenario import Scenario
from tagswarm.recording.runrecorder import RunRecorder
from tagswarm.runtime.config import ConfigError, Invocation, OneLineParser, add_common_args
from tagswarm.runtime.process import install_stop_signals, run_main, setup_logging

PROG = "tagswarm record-run"
log = logging.getLogger("tagswarm.record-run")


def parser() -> OneLineParser:
    p = OneLineParser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    out = p.add_mutually_exclusive_group()
    out.add_argument("--out", type=Path, metavar="DIR", help="the run folder to write")
    out.add_argument("--out-dir", type=Path, metavar="DIR",
                     help="write the run folder as DIR/<run>-<UTC time> (default: runs/)")
    p.add_argument("--claims", type=Path, metavar="FILE",
                   help="answer robot-id claims with the agents' passwords in FILE (agents.txt)")
    p.add_argument("--linger", type=float, default=10.0, metavar="SECONDS",
                   help="after the world left, wait this long at most for agents and server to leave (default 10)")
    p.add_argument("--no-report", action="store_true", help="do not compute metrics and plots at the end")
    add_common_args(p)
    return p


class RunWatch:
    """Presence of the run's processes, from liveliness: has the world come and gone,
    are agents or the server still there?"""

    def __init__(self, bus: Bus, keys: Keys) -> None:
        self.keys = keys
        self.inbox = bus.watch_liveliness(keys.alive_all())
        self.alive: set[str] = set()
        self.world_seen = False

    def poll(self) -> None:
        for change in self.inbox.drain():
            who = self.keys.participant_of(change.key)
            if who is None:
                continue
            if change.value:
                self.alive.add(who)
                self.world_seen |= who == "world/0"
            else:
                self.alive.discard(who)

    @property
    def world_gone(self) -> bool:
        return self.world_seen and "world/0" not in self.alive

    def workers_left(self) -> bool:
        return not any(p.startswith(("agent/", "server/")) for p in self.alive)


def answer_claims(bus: Bus, inbox: Inbox[Any], book: claims.ClaimBook, key: str) -> None:
    """Reply to every pending claim query."""
    for item in inbox.drain():
        reply = book.claim()
        if reply.granted:
            log.info("robot %d claimed (%d of %d taken)", reply.robot_id, len(book.taken), len(book.robot_ids))
        else:
            log.warning("claim refused: %s", reply.reason)
        bus.reply(item.value, key, claims.encode(reply))


def record(inv: Invocation, scenario: Scenario, out: Path, book: claims.ClaimBook | None, linger_s: float,
           report: bool, stop: threading.Event) -> int:
    """Record until the run is over (or ``stop``), then write ``out``; the exit code."""
    keys = Keys(inv.run())
    t0 = time.monotonic()
    stopped = False
    with open_bus(inv.bus()) as bus:
        rec = RunRecorder(bus, keys, scenario)
        watch = RunWatch(bus, keys)
        claim_in = bus.queryable(acl.claim_key(keys)) if book is not None else None
        bus.declare_token(keys.alive(acl.RECORDER_PARTICIPANT))
        log.info("recording run %r (%d robots) to %s%s", keys.run, len(scenario.robot_ids), out,
                 "; answering robot-id claims" if book is not None else "")
        ended_at: float | None = None
        tick_ns = 1e9 / scenario.clock.tick_hz
        while True:
            bus.wait(0.25)
            rec.poll()
            watch.poll()
            if claim_in is not None and book is not None:
                answer_claims(bus, claim_in, book, acl.claim_key(keys))
            if stop.is_set():
                stopped = True
                break
            if not watch.world_gone:
                ended_at = None  # back (a lost lease, or a restarted world): the run goes on
                continue
            ended_at = ended_at if ended_at is not None else time.monotonic()
            waited = time.monotonic() - ended_at
            # a world gone before its duration may come back: only the linger ends that run
            finished = rec.sim_ns >= scenario.duration_s * 1e9 - tick_ns
            if waited > linger_s or (finished and watch.workers_left()):
                break
        rec.poll()
    wall = time.monotonic() - t0
    code = 130 if stopped else 0
    out.mkdir(parents=True, exist_ok=True)
    (out / "scenario.json").write_bytes(msgspec.json.format(msgspec.json.encode(scenario)))
    rec.write(out, {"wall_time_s": wall, "exit_code": code, "failure": None, "endpoint": ",".join(inv.bus().connect),
                    "exit_codes": {}, "recorder": PROG,
                    "claims": {"taken": book.taken, "refused": book.refused} if book is not None else None})
    if report:
        from tagswarm.evaluation.report import write_report

        write_report(out)
    log.info("run folder written: %s (%.1f simulated s in %.1f s wall)", out, rec.sim_ns / 1e9, wall)
    return code


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry for ``tagswarm record-run``."""

    def body() -> int:
        inv = Invocation(parser(), argv)
        args = inv.args
        if not args.linger >= 0:
            raise ConfigError("--linger must be >= 0 seconds")
        setup_logging(inv.log_level("INFO"), "record-run")
        run = inv.run()
        scenario = pinned(inv.scenario())  # scenario.json keeps the poses drawn today
        book = claims.ClaimBook(scenario.robot_ids, claims.read_passwords(args.claims)) if args.claims else None
        if args.out is not None:
            out: Path = args.out
        else:
            stamp = datetime.now(UTC).strftime("%Y%m%d-%H%M%S")
            out = (args.out_dir or Path("runs")) / f"{run}-{stamp}"
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ConfigError(f"cannot create {str(out.parent)!r}: {exc.strerror}") from None
        if acl.RECORDER_PARTICIPANT not in scenario.clock.observers:
            log.warning("%s is not in clock.observers: the world will not wait for this recorder",
                        acl.RECORDER_PARTICIPANT)
        stop = threading.Event()
        install_stop_signals(stop)
        return record(inv, scenario, out, book, args.linger, not args.no_report, stop)

    return run_main(PROG, body)


if __name__ == "__main__":
    raise SystemExit(main())
