"""``tagswarm record [KEYEXPR] --out FILE.mcap``: record a running system to MCAP.

A read-only Zenoh client (like ``tagswarm spy``, by default no liveliness token and never
part of a lockstep; see ``--participant`` below) that writes every message on keys
matching KEYEXPR (default: every key of the run, ``tagswarm/<run>/**``) to an MCAP file
that Foxglove opens:

- one raw channel per key holding the payload bytes exactly as received (msgpack, with the
  JSON Schema of the message type's msgpack form and its Zenoh encoding, from the wire
  contract: see :mod:`tagswarm.recording.mcapio`), so ``tagswarm replay`` is byte-exact;
  log time is the message's simulation time, publish time the wall clock at reception;
- Foxglove views beside them (poses, frames, the map, camera images; see
  :mod:`tagswarm.recording.foxglove_views`), unless ``--no-foxglove``;
- camera images optionally downsampled (``--image-scale 0.5``: area-averaged, intrinsics
  scaled; such raw images are re-encoded, so a replay of them is no longer byte-exact) or
  skipped (``--no-images``).

Payloads that do not decode are still recorded raw, and counted.  Recording stops on
SIGINT/SIGTERM, after ``--duration`` simulated seconds, or when the world's liveliness
token goes away (its run ended); the file is always closed with its summary.

A recorder that joins a system already running misses what came before, and a passive one
cannot slow a lockstep world down.  ``--participant record/0`` (with ``record/0`` added to
``clock.participants``; ``tagswarm up --record`` does both) makes it a lockstep participant
instead: the world waits for it before the first tick and until it has received each step,
so the recording holds every message from step 0 on.  Zenoh peers deliver to each other
over direct links that form as they discover each other, so the recorder announces itself
only once it sees every process named by ``--wait-for`` (``up --record``: the world and
every participant), i.e. once it is linked to all of them.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import Bus, Received, open_bus
from tagswarm.protocol.keys import Keys, split_participant
from tagswarm.protocol.scenario import Scenario
from tagswarm.recording.mcapio import is_tick
from tagswarm.recording.mcaprecording import (
    RECORD_PARTICIPANT,
    RECORDER_NAME,
    McapRecording,
    RecordOptions,
    scale_image,
    with_recorder,
    without_recorders,
)
from tagswarm.runtime.config import (
    ConfigError,
    Invocation,
    OneLineParser,
    add_common_args,
)
from tagswarm.runtime.lockstep import Participant
from tagswarm.runtime.process import install_stop_signals, run_main, setup_logging

__all__ = [
    "INBOX_CAPACITY",
    "PROG",
    "QUIET_AFTER_WORLD_S",
    "RECORD_PARTICIPANT",
    "BackgroundRecording",
    "McapRecorder",
    "McapRecording",
    "RecordOptions",
    "declare_when_meshed",
    "main",
    "parser",
    "scale_image",
    "start_recording",
    "with_recorder",
    "without_recorders",
]

PROG = RECORDER_NAME
INBOX_CAPACITY = 200_000  # a safety net: the writer keeps up with the world by a wide margin (see README)
QUIET_AFTER_WORLD_S = 1.0  # after the world left, wait this long without traffic before closing
log = logging.getLogger("tagswarm.record")


def declare_when_meshed(bus: Bus, keys: Keys, name: str, peers: Sequence[str], timeout_s: float = 30.0,
                        stop: threading.Event | None = None) -> threading.Thread:
    """Declare ``name``'s liveliness token once every process in ``peers`` (``"role/id"``)
    is seen alive, on a background thread (or after ``timeout_s``, with a warning).

    Why: a peer's publications reach only the subscribers it already knows of, over a
    direct link.  Seeing a peer's token means that link is up and this session's
    subscriptions (declared before the call) went over it; announcing ourselves only then
    means whoever waits for our token (the world, a lockstep replay) starts when nothing
    can be missed any more."""
    wanted = set(peers) - {name}
    inbox = bus.watch_liveliness(keys.alive_all())
    seen: set[str] = set()

    def all_seen() -> bool:
        for change in inbox.drain():
            who = keys.participant_of(change.key)
            if who is not None:
                (seen.add if change.value else seen.discard)(who)
        return wanted <= seen or (stop is not None and stop.is_set())

    def run() -> None:
        if not bus.wait_for(all_seen, timeout_s):
            log.warning("%s: %s not seen within %.0f s; announcing anyway", name, ", ".join(sorted(wanted - seen)),
                        timeout_s)
        try:
            bus.declare_token(keys.alive(name))
        except Exception as exc:  # the session closed meanwhile (the run ended early): nothing to announce
            log.debug("not announcing %s: %s", name, exc)

    thread = threading.Thread(target=run, name=f"announce-{name}", daemon=True)
    thread.start()
    return thread


class McapRecorder:
    """Feeds a :class:`McapRecording` from the bus: one subscription to ``keyexpr`` plus
    the world's liveliness (to notice that its run ended).  With ``participant``
    (``"record/0"``) it also joins the lockstep of ``keys``' run: a liveliness token once
    subscribed and linked to ``peers``, and an ack for each tick once it is in hand."""

    def __init__(self, bus: Bus, keyexpr: str, recording: McapRecording, world_alive_key: str | None, *,
                 participant: str | None = None, keys: Keys | None = None, peers: Sequence[str] = (),
                 join_timeout_s: float = 30.0) -> None:
        self.bus = bus
        self.recording = recording
        try:
            self.inbox = bus.subscribe(keyexpr, capacity=INBOX_CAPACITY)
        except Exception as exc:  # zenoh rejects malformed key expressions when declaring
            reason = " ".join(str(exc).split()).split(" at /", 1)[0]
            raise ConfigError(f"bad key expression {keyexpr!r}: {reason}") from None
        self.world_in = bus.watch_liveliness(world_alive_key) if world_alive_key else None
        self.world_seen = False
        self.world_gone = False
        self.last_rx = time.monotonic()
        self.participant: Participant | None = None
        if participant is not None:
            if keys is None:
                raise ValueError("a lockstep participant needs the run's keys")
            self.participant = Participant(bus, keys, participant)
            # after subscribing, once linked to every peer: the world may start as soon as it sees this token
            declare_when_meshed(bus, keys, participant, peers, join_timeout_s)

    def poll(self) -> int:
        """Write everything that arrived; returns how many payloads."""
        if self.world_in is not None:
            for change in self.world_in.drain():
                self.world_seen = self.world_seen or change.value
                self.world_gone = self.world_seen and not change.value
        items = self.inbox.drain()
        now_ns = time.time_ns()  # reception ~ now: the inbox is drained every few ms
        if items:
            self.last_rx = time.monotonic()
        if self.participant is not None:
            self._ack(self.participant, items)
        for item in items:
            self.recording.add(item.key, item.value, now_ns)
        return len(items)

    @staticmethod
    def _ack(participant: Participant, items: list[Received[bytes]]) -> None:
        """Acknowledge the newest tick among ``items`` before writing them: everything the
        world sent before that tick is in hand (in order, in memory), so the world may go
        on while we write; one ack covers older steps (the world keeps the newest)."""
        newest: m.Tick | None = None
        for item in items:
            if is_tick(item.key):
                try:
                    tick = codec.decode(m.Tick, item.value)
                except codec.DecodeError:
                    continue  # counted when written
                if newest is None or tick.step > newest.step:
                    newest = tick
        if newest is not None:
            participant.ack(newest)

    def close(self) -> dict[str, int]:
        self.poll()
        return self.recording.close({"inbox_overflow": self.inbox.overflow})


class BackgroundRecording:
    """A :class:`McapRecorder` on its own thread sharing a process's bus (``tagswarm up --record``)."""

    def __init__(self, recorder: McapRecorder, bus: Bus) -> None:
        self.recorder = recorder
        self._stop = threading.Event()
        self._bus = bus
        self._thread = threading.Thread(target=self._loop, name="mcap-record", daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while not self._stop.is_set():
            self._bus.wait(0.05)
            self.recorder.poll()

    def stop(self) -> dict[str, int]:
        """Stop the thread, write what is left and close the file (safe after the bus
        closed: the inbox is plain memory)."""
        self._stop.set()
        self._thread.join()
        return self.recorder.close()


def start_recording(bus: Bus, keys: Keys, path: Path, scenario: Scenario | None = None,
                    options: RecordOptions | None = None) -> BackgroundRecording:
    """Record every key of ``keys``' run to ``path`` on a background thread, as the
    lockstep participant ``record/0`` if ``scenario`` lists it (see :func:`with_recorder`)."""
    rec = McapRecording(path, options or RecordOptions(), run=keys.run, keyexpr=keys.all(), scenario=scenario)
    joins = scenario is not None and scenario.clock.mode == "lockstep" and \
        RECORD_PARTICIPANT in scenario.clock.participants
    peers = (*scenario.clock.participants, "world/0") if scenario is not None else ()
    timeout = scenario.clock.join_timeout_s if scenario is not None else 30.0
    return BackgroundRecording(McapRecorder(bus, keys.all(), rec, None,
                                            participant=RECORD_PARTICIPANT if joins else None,
                                            keys=keys, peers=peers, join_timeout_s=timeout), bus)


def parser() -> OneLineParser:
    p = OneLineParser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("keyexpr", nargs="?", metavar="KEYEXPR",
                   help="Zenoh key expression to record (default: every key of the run, tagswarm/<run>/**)")
    p.add_argument("--out", "-o", type=Path, required=True, metavar="FILE.mcap", help="MCAP file to write")
    p.add_argument("--image-scale", type=float, default=1.0, metavar="S",
                   help="downsample camera images by S in (0, 1] (e.g. 0.5 = half width and height)")
    p.add_argument("--no-images", action="store_true", help="do not record camera images")
    p.add_argument("--no-foxglove", action="store_true", help="raw channels only, no Foxglove views")
    p.add_argument("--compression", choices=("zstd", "lz4", "none"), default="zstd",
                   help="MCAP chunk compression (default zstd)")
    p.add_argument("--participant", metavar="ROLE/ID",
                   help="join the lockstep as this participant (list it in clock.participants, e.g. record/0): "
                        "the world then waits for the recorder, so nothing is missed")
    p.add_argument("--wait-for", action="append", metavar="ROLE/ID,...", default=[],
                   help="with --participant: join only once these are alive (linked to us), e.g. "
                        "world/0,agent/0,server/0")
    add_common_args(p)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry for ``tagswarm record``."""

    def body() -> int:
        inv = Invocation(parser(), argv)
        args = inv.args
        env = inv.env
        setup_logging(inv.log_level("INFO"), "record")
        keys = Keys(inv.pick("run", "default"))
        keyexpr = args.keyexpr if args.keyexpr is not None else keys.all()
        if not keyexpr.strip():
            raise ConfigError("KEYEXPR must not be empty")
        duration = inv.pick("duration")
        duration_s = float(duration) if duration is not None else math.inf
        if not duration_s > 0:
            raise ConfigError("--duration must be > 0")
        # the scenario only tells the Foxglove views where the map frame is: use it when named
        given = args.scenario is not None or "TAGSWARM_SCENARIO" in env
        scenario = inv.scenario() if given else None
        options = RecordOptions(images=not args.no_images, image_scale=args.image_scale,
                                foxglove=not args.no_foxglove, compression=args.compression)
        if args.participant is not None:
            split_participant(args.participant)
        peers = tuple(p.strip() for chunk in args.wait_for for p in chunk.split(",") if p.strip())
        for peer in peers:
            split_participant(peer)
        if not args.out.parent.is_dir():
            raise ConfigError(f"--out: no such directory {str(args.out.parent)!r}")
        bus_cfg = inv.bus()
        recording = McapRecording(args.out, options, run=keys.run, keyexpr=keyexpr, scenario=scenario)
        stop = threading.Event()
        install_stop_signals(stop)
        stats: dict[str, int] = {}
        try:
            with open_bus(bus_cfg) as bus:
                rec = McapRecorder(bus, keyexpr, recording, keys.alive("world/0"), participant=args.participant,
                               keys=keys, peers=peers)
                log.info("recording %s to %s", keyexpr, args.out)
                while not stop.is_set():
                    bus.wait(0.05)
                    rec.poll()
                    if recording.sim_span_s >= duration_s:
                        log.info("recorded %.1f simulated seconds", recording.sim_span_s)
                        break
                    if rec.world_gone and time.monotonic() - rec.last_rx > QUIET_AFTER_WORLD_S:
                        log.info("the world left: its run ended")
                        break
                stats = rec.close()
        finally:
            recording.sink.close()  # a no-op after rec.close(); closes the file on any error
        size_mb = args.out.stat().st_size / 1e6
        sys.stderr.write(f"{PROG}: {stats.get('mcap_messages', 0)} messages, {recording.sim_span_s:.1f} simulated s, "
                         f"{size_mb:.1f} MB -> {args.out}"
                         + (f"; {recording.rejects.total()} undecodable" if recording.rejects.total() else "")
                         + "\n")
        return 0

    return run_main(PROG, body)


if __name__ == "__main__":
    raise SystemExit(main())
