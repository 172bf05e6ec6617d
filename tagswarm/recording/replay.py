"""``tagswarm replay FILE.mcap``: republish a recording's raw tagswarm channels on Zenoh.

Payloads go out byte for byte as recorded, in simulation-time order (at one instant a
Tick always last, as the world sends it), on their recorded keys, or moved to another run
with ``--run`` (``tagswarm/<recorded run>/...`` -> ``tagswarm/<run>/...``).

Pacing:

- ``--speed X`` (default 1): X times the recorded simulation rate, by the wall clock;
- ``--lockstep``: as fast as the receivers acknowledge.  The replayer plays the world's
  part of the lockstep protocol (see ``world/node.py``): it waits for the participants to
  come up (liveliness), publishes one step's sensor messages and its Tick, then waits for
  a TickAck of that step from every participant that is alive (one that is late by
  ``clock.ack_timeout_s`` is skipped for that step, as the world does).  The participants
  are ``--participants``, else those of the scenario given with ``--scenario``, else those
  of the scenario stored in the recording, else whoever acknowledged ticks in it.
  ``--wait-for ROLE/ID`` names more processes to wait for before the first tick (only their
  liveliness, no acks), e.g. the run-folder writer of ``tagswarm up`` (``up/0``); it works
  with ``--speed`` too.  The ``clock.observers`` of a scenario named with ``--scenario``
  are waited for the same way (as the world does); the recorded run's are not.

What: ``--only world`` = the world's sensor streams (ticks, world status, camera images,
encoders, ground truth; the default with ``--lockstep``) or ``--only all`` (every raw
channel; the default otherwise; acks are never replayed in lockstep), narrowed further
by ``--keys KEYEXPR`` (repeatable).  Replaying the world into fresh agents and a fresh
server evaluates them on exactly the recorded data; their wheel commands go nowhere (the
robots' motion is in the recording).  The recorded wheel commands go out on
``robot/<id>/recorded_cmd`` (with either ``--only``): the agents compare the recorded
wheels with them, not with their own commands, so changed settings or another
controller do not show up as wheel slip.  ``tagswarm up --replay FILE`` does all of that and
writes a run folder.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import msgspec

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import Bus, open_bus
from tagswarm.protocol.keys import Keys, split_participant
from tagswarm.protocol.scenario import Clock, Scenario
from tagswarm.recording.mcapio import (
    META_RUN,
    RecordingError,
    is_ack,
    is_command,
    is_tick,
    is_world_stream,
    iter_raw,
    keyexpr_matches,
    raw_topics,
    read_metadata,
    recorded_command_key,
    remap_run,
    robot_id_of,
    run_of,
)
from tagswarm.runtime import streams
from tagswarm.runtime.config import (
    ConfigError,
    Invocation,
    OneLineParser,
    add_common_args,
    scenario_from,
)
from tagswarm.runtime.process import install_stop_signals, run_main, setup_logging
from tagswarm.world.lockstep import AckTracker

PROG = "tagswarm replay"
log = logging.getLogger("tagswarm.replay")


def recorded_scenario(path: Path) -> dict[str, Any] | None:
    """The resolved scenario stored in a recording's metadata (as a table), if any."""
    text = read_metadata(path).get(META_RUN, {}).get("scenario")
    if not text:
        return None
    table: dict[str, Any] = msgspec.json.decode(text)
    return table


def recorded_participants(path: Path) -> tuple[str, ...]:
    """Lockstep participants that acknowledged ticks in the recording (render workers
    excluded: they answer the world's render requests, which a replay does not send; and
    recorders: a replay reproduces the run, not its recording)."""
    found = set()
    for topic in raw_topics(path):
        if is_ack(topic):
            role, ident = topic.split("/")[-2:]
            if role not in ("render", "record"):
                found.add(f"{role}/{ident}")
    return tuple(sorted(found))


def scenario_for_replay(recording: Path, args: argparse.Namespace, env: dict[str, str],
                        resolve: Callable[[argparse.Namespace, dict[str, str]], Scenario]) -> Scenario:
    """The scenario for processes evaluated on ``recording`` (``tagswarm up --replay``): the
    one named by ``--scenario``/``TAGSWARM_SCENARIO`` if any, else the recorded one, with
    every other flag and variable applied on top by ``resolve`` as usual; lockstep unless
    ``--clock`` says otherwise."""
    if args.clock is None and "TAGSWARM_CLOCK" not in env:
        args.clock = "lockstep"
    try:
        topics = raw_topics(recording)
        table = None if args.scenario is not None or "TAGSWARM_SCENARIO" in env else recorded_scenario(recording)
    except RecordingError as exc:
        raise ConfigError(f"--replay: {exc}") from None
    if table is None:
        if args.scenario is None and "TAGSWARM_SCENARIO" not in env:
            raise ConfigError(f"--replay: {recording} holds no scenario; name it with --scenario")
        scenario = resolve(args, env)
    else:
        with tempfile.TemporaryDirectory(prefix="tagswarm-replay-") as tmp:
            path = Path(tmp) / "recorded-scenario.json"
            path.write_bytes(msgspec.json.encode(table))
            args.scenario = str(path)
            try:
                scenario = resolve(args, env)
            finally:
                args.scenario = None
    if scenario.clock.mode != "lockstep":
        raise ConfigError("--replay plays the recording in lockstep (its processes acknowledge every tick); "
                          f"clock.mode {scenario.clock.mode!r} cannot be replayed: leave --clock out, or play the "
                          "recording with tagswarm replay --speed X to processes of your own")
    recorded = sorted({rid for t in topics if is_world_stream(t) and t.endswith("/encoders")
                       for rid in [robot_id_of(t)] if rid is not None})
    if recorded and list(scenario.robot_ids) != recorded:
        raise ConfigError(f"--replay: the recording holds robots {', '.join(map(str, recorded))}, the scenario "
                          f"robots {', '.join(map(str, scenario.robot_ids))}: --robots and --scenario must "
                          "match the recording (its scenario is used when --scenario is left out)")
    return scenario


class Replayer:
    """Publishes a recording; see the module docstring.  ``speed=None`` means lockstep."""

    def __init__(self, bus: Bus, path: Path, *, accept: Callable[[str], bool], run: str | None,
                 speed: float | None, participants: tuple[str, ...] = (), clock: Clock | None = None,
                 end_s: float | None = None, wait_for: tuple[str, ...] = (),
                 echo_commands: bool = True) -> None:
        self.bus, self.path, self.accept, self.speed = bus, path, accept, speed
        self.echo_commands = echo_commands  # False: recorded commands go out on recorded_cmd only
        self.clock = clock or Clock()
        self.end_s = end_s
        self.lockstep = speed is None
        topics = [t for t in raw_topics(path) if accept(t)]
        runs = {r for r in map(run_of, topics) if r is not None}
        self.target_run = run
        if run is None and len(runs) == 1:
            self.target_run = next(iter(runs))
        self.presence = self.lockstep or bool(wait_for)
        if self.presence and self.target_run is None:
            raise ConfigError(f"{path} holds {len(runs)} runs ({', '.join(sorted(runs))}): pick one with --run")
        self.topics = topics
        self.counts: Counter[str] = Counter()
        self.rejects = streams.RejectCounter(log)
        self.ack_timeouts = 0
        self.tracker = AckTracker(participants, self.clock.ack_stall_after)
        self.joiners = AckTracker(wait_for)  # only their liveliness counts (before the first tick)
        self.keys = Keys(self.target_run) if self.target_run is not None else None
        if self.presence:
            assert self.keys is not None
            self.alive_in = bus.watch_liveliness(self.keys.alive_all())
            self.ack_in = bus.subscribe(self.keys.acks())
        if self.keys is not None and any(is_world_stream(t) for t in topics):
            bus.declare_token(self.keys.alive("world/0"))  # we play the world: tools that look for it see us

    def _key(self, recorded: str) -> str:
        return remap_run(recorded, self.target_run) if self.target_run is not None else recorded

    # ------------------------------------------------------------------ lockstep
    def _drain_presence(self) -> None:
        assert self.keys is not None
        for change in self.alive_in.drain():
            who = self.keys.participant_of(change.key)
            if who is None:
                continue
            self.joiners.set_alive(who, change.value)
            if self.tracker.set_alive(who, change.value):
                log.info("lockstep participant %s %s", who, "joined" if change.value else "left")
        for item, ack in self.rejects.decoded(self.ack_in.drain(), m.TickAck):
            who = self.keys.participant_of(item.key)
            if who is None or ack.participant != who:
                self.rejects.reject("spoofed", f"{item.key} carries participant {ack.participant!r}")
            elif not self.tracker.ack(who, ack.step):
                self.rejects.reject("unknown_participant", f"{who} is not a declared participant")

    def wait_for_participants(self, stop: threading.Event) -> bool:
        """Before the first message: wait until every participant (and ``wait_for``
        process) is alive, up to ``clock.join_timeout_s``."""

        def ready() -> bool:
            self._drain_presence()
            return stop.is_set() or not (self.tracker.missing() or self.joiners.missing())

        ok = self.bus.wait_for(ready, self.clock.join_timeout_s)
        if not ok:
            log.warning("starting without %s (not alive after %.1f s)",
                        ", ".join(sorted(self.tracker.missing() | self.joiners.missing())), self.clock.join_timeout_s)
        return ok

    def _wait_acks(self, step: int, stop: threading.Event) -> None:
        def done() -> bool:
            self._drain_presence()
            return stop.is_set() or not self.tracker.pending(step)

        if not self.bus.wait_for(done, self.clock.ack_timeout_s):
            late = sorted(self.tracker.pending(step))
            self.ack_timeouts += 1
            log.warning("%s did not acknowledge step %d within %.1f s; continuing without them", ", ".join(late),
                        step, self.clock.ack_timeout_s)
            for p in late:
                if self.tracker.skip(p, step):
                    log.warning("%s missed %d steps in a row (alive but silent); not waiting for it any more until "
                                "it acknowledges a step again", p, self.tracker.stall_after)

    # ------------------------------------------------------------------ loop
    def run(self, stop: threading.Event) -> int:
        """Publish the whole recording (or ``end_s`` simulated seconds of it); returns 0."""
        if self.presence:
            self.wait_for_participants(stop)
        t0 = time.monotonic()
        first: int | None = None
        last_log = t0
        sim_ns = 0
        chosen = set(self.topics)
        for raw in iter_raw(self.path, chosen.__contains__):
            if stop.is_set():
                break
            first = raw.log_time_ns if first is None else first
            if self.end_s is not None and raw.log_time_ns - first > self.end_s * 1e9:
                break
            if self.speed is not None:
                lag = t0 + (raw.log_time_ns - first) / 1e9 / self.speed - time.monotonic()
                if lag > 0 and stop.wait(lag):
                    break
            key = self._key(raw.key)
            if is_command(raw.key):
                # what drove the recorded wheels, for the fresh agents' slip check (their own commands drive
                # nothing here, and differ from these as soon as a setting or the controller does)
                self.bus.put(recorded_command_key(key), raw.data)
                self.counts["commands"] += 1
                if not self.echo_commands:
                    continue
            # lockstep: nothing may be lost (repeatability); timed: images may drop, as the world's do
            drop = not self.lockstep and "/camera/" in key
            self.bus.put(key, raw.data, drop=drop)
            self.counts["messages"] += 1
            sim_ns = raw.log_time_ns
            if is_tick(raw.key):
                self.counts["ticks"] += 1
                if self.lockstep:
                    try:
                        tick = codec.decode(m.Tick, raw.data)
                    except codec.DecodeError as exc:
                        self.rejects.reject(exc.kind, f"recorded tick: {exc.detail}")
                        continue
                    self._wait_acks(tick.step, stop)
            if time.monotonic() - last_log > 10:
                last_log = time.monotonic()
                log.info("t=%.1f s, %d messages", sim_ns / 1e9, self.counts["messages"])
        wall = time.monotonic() - t0
        span = 0.0 if first is None else (sim_ns - first) / 1e9
        log.info("replayed %d messages (%d ticks, %.1f simulated s) in %.1f s wall (x%.2f); %d ack timeout(s)",
                 self.counts["messages"], self.counts["ticks"], span, wall, span / max(wall, 1e-9), self.ack_timeouts)
        return 0


def _participants(args: argparse.Namespace, env: dict[str, str], path: Path) -> tuple[tuple[str, ...], Clock]:
    """Participants and clock settings (its ``observers`` are waited for like ``--wait-for``),
    in the precedence of the module docstring."""
    clock = Clock()
    given: tuple[str, ...] = ()
    if args.scenario is not None or "TAGSWARM_SCENARIO" in env:
        s = scenario_from(args, env)
        clock, given = s.clock, s.clock.participants
    else:
        table = recorded_scenario(path)
        if table is not None:
            try:
                s = msgspec.convert(table, Scenario)
            except msgspec.ValidationError as exc:
                raise ConfigError(f"{path}: the recorded scenario does not load ({exc}); "
                                  "name one with --scenario") from None
            # the original run's observers (its `up`, its recorder) are not part of this one
            clock, given = msgspec.structs.replace(s.clock, observers=()), s.clock.participants
    parts = _names(args.participants) or given or recorded_participants(path)
    return tuple(parts), clock


def _names(flags: list[str] | None) -> tuple[str, ...]:
    """``role/id`` names from repeatable comma-separated flags, validated."""
    names = tuple(p.strip() for chunk in flags or [] for p in chunk.split(",") if p.strip())
    for p in names:
        split_participant(p)
    return names


def parser() -> OneLineParser:
    p = OneLineParser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("file", type=Path, metavar="FILE.mcap", help="a recording made by tagswarm record / up --record")
    pace = p.add_mutually_exclusive_group()
    pace.add_argument("--speed", type=float, default=None, metavar="X",
                      help="X times the recorded simulation rate (default 1)")
    pace.add_argument("--lockstep", action="store_true",
                      help="as fast as the lockstep participants acknowledge (replay plays the world)")
    p.add_argument("--only", choices=("world", "all"), default=None,
                   help="world = the world's sensor streams (default with --lockstep), all = every raw channel")
    p.add_argument("--keys", action="append", metavar="KEYEXPR", default=[],
                   help="only recorded keys matching this key expression (repeatable)")
    p.add_argument("--participants", action="append", metavar="ROLE/ID,...",
                   help="lockstep participants to wait for, e.g. agent/0,agent/1,server/0")
    p.add_argument("--wait-for", action="append", metavar="ROLE/ID,...",
                   help="wait for these to come up before the first message (their liveliness only, no acks)")
    add_common_args(p)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry for ``tagswarm replay``."""

    def body() -> int:
        inv = Invocation(parser(), argv)
        args = inv.args
        env = inv.env
        setup_logging(inv.log_level("INFO"), "replay")
        if args.speed is not None and not (math.isfinite(args.speed) and args.speed > 0):
            raise ConfigError("--speed must be a positive number")
        if not args.file.is_file():
            raise ConfigError(f"no such recording {str(args.file)!r}")
        duration = inv.pick("duration")
        end_s = float(duration) if duration is not None else None
        if end_s is not None and not end_s > 0:
            raise ConfigError("--duration must be > 0")
        run = inv.pick("run")
        if run is not None:
            Keys(run)
        for pattern in args.keys:
            if not pattern.strip() or "//" in pattern:
                raise ConfigError(f"--keys: bad key expression {pattern!r}")
        only = args.only or ("world" if args.lockstep else "all")
        lockstep = bool(args.lockstep)
        patterns = list(args.keys)
        target = run

        def accept(topic: str) -> bool:
            if only == "world" and not (is_world_stream(topic) or is_command(topic)):
                return False
            if lockstep and is_ack(topic):
                return False
            moved = remap_run(topic, target) if target else topic
            return not patterns or any(keyexpr_matches(p, topic) or keyexpr_matches(p, moved)
                                       for p in patterns)

        participants, clock = _participants(args, env, args.file) if lockstep else ((), Clock())
        wait_for = tuple(dict.fromkeys((*_names(args.wait_for), *clock.observers)))
        if lockstep and not participants:
            raise ConfigError("--lockstep: no participants to wait for; name them with --participants")
        stop = threading.Event()
        install_stop_signals(stop)
        with open_bus(inv.bus()) as bus:
            replayer = Replayer(bus, args.file, accept=accept, run=run,
                                speed=None if lockstep else (args.speed or 1.0), participants=participants,
                                clock=clock, end_s=end_s, wait_for=wait_for, echo_commands=only == "all")
            if not replayer.topics:
                raise ConfigError(f"{args.file}: no recorded channel matches the filter")
            log.info("replaying %d channel(s) of %s%s%s", len(replayer.topics), args.file,
                     f" into run {replayer.target_run!r}" if replayer.target_run else "",
                     f", lockstep with {', '.join(participants)}" if lockstep else f" at x{args.speed or 1.0:g}")
            if lockstep and not any("/camera/" in t for t in replayer.topics):
                log.warning("no camera images in what is replayed, but the recorded ticks announce frames: "
                            "lockstep agents will wait agent.frame_wait_s for each of them")
            code = replayer.run(stop)
        sys.stderr.write(f"{PROG}: {replayer.counts['messages']} messages, {replayer.counts['ticks']} ticks"
                         + (f", {replayer.ack_timeouts} ack timeout(s)" if lockstep else "") + "\n")
        return code

    return run_main(PROG, body)


if __name__ == "__main__":
    raise SystemExit(main())
