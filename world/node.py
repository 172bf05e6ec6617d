"""The world process: steps the simulation and talks Zenoh (the only I/O here).

One cycle (:meth:`WorldNode.step`): apply the wheel commands that arrived,
advance physics one tick, apply the teleports and pushes now due
(:class:`~tagswarm.protocol.messages.WorldCommand` messages and the scenario's
``[[events]]``, see :mod:`tagswarm.world.interventions`), publish ground truth, encoder
ticks and due camera frames, then the :class:`~tagswarm.protocol.messages.Tick`; in
lockstep mode wait until every live participant acknowledged it.  So the state
published for the first step whose time is >= an intervention's due time
already has the robot where it was put.

Status counters besides the rejects: ``world_commands`` / ``world_events``
(interventions applied from the network / the scenario), ``world_command_rejected``
(refused, either source: unknown robot, outside the arena, overlapping something,
queue full; each logged with why), the contact events of :mod:`tagswarm.world.contacts`
(``contacts_robot_robot``, ``contacts_robot_obstacle``, ``contacts_robot_wall``,
``contacts_robot_<id>``).
"""

from __future__ import annotations

import logging
import math
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections import Counter
from collections.abc import Mapping, Sequence
from pathlib import Path

import msgspec

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import Bus, open_bus
from tagswarm.protocol.keys import Keys
from tagswarm.protocol.scenario import Camera
from tagswarm.runtime import streams
from tagswarm.runtime.process import install_stop_signals, run_main, setup_logging
from tagswarm.world.config import (
    WorldConfig,
    build_config,
    lens_plan,
    render_load,
    render_pixels,
    resolve_render_workers,
)
from tagswarm.world.interventions import Schedule
from tagswarm.world.lockstep import AckTracker
from tagswarm.world.render import Renderer, image_message, pose_matrix
from tagswarm.world.sim import PlacementError, Sim

log = logging.getLogger("tagswarm.world")
MAX_REJECT_LOGS = 50  # refused interventions logged one by one, then only counted


def due(step: int, rate_hz: float, tick_hz: float, phase: float = 0.0) -> bool:
    """Whether a sensor at ``rate_hz`` fires at ``step`` of a ``tick_hz`` clock (always at
    step 0); ``phase`` in [0, 1) shifts its firings by that share of its period."""
    if step == 0:
        return True
    return (math.floor(step * rate_hz / tick_hz + phase + 1e-9)
            != math.floor((step - 1) * rate_hz / tick_hz + phase + 1e-9))


class WorldNode:
    """Owns the :class:`Sim` and publishes its sensors; see module docstring."""

    def __init__(self, config: WorldConfig, bus: Bus) -> None:
        self.cfg = config
        self.s = s = resolve_render_workers(config.scenario)
        self.bus = bus
        self.keys = Keys(config.run)
        self.instance = f"{config.run}-{uuid.uuid4().hex[:8]}"
        self.sim = Sim(s)
        self.renderer = Renderer(s) if s.render.workers == 0 else None
        self.tick_hz = s.clock.tick_hz
        self.lockstep = s.clock.mode == "lockstep"
        self.participants = AckTracker(s.clock.participants, s.clock.ack_stall_after)
        self.workers = AckTracker((f"render/{i}" for i in range(s.render.workers)), s.clock.ack_stall_after)
        self.observers_alive: set[str] = set()
        self.rejects = streams.RejectCounter(log)
        self.counters: Counter[str] = Counter()
        self.seq = streams.Sequencer()
        self.interventions = Schedule(s.events, tick_hz=s.clock.tick_hz, dt_ns=self.sim.dt_ns)
        self._started = False
        self._stepping_since: float | None = None  # monotonic s of the first step (real-time factor)
        self._published_step = -1  # newest step whose tick is out
        self._render_step = -1  # newest step whose render poses are out
        self._next_status_ns = 0
        # Robots are staggered, not a robot's cameras: a rig's frames must share one
        # instant so the agent's multi-camera refinement can combine them.
        n = len(s.robot_ids)
        self._camera_pairs = [(rid, cam, i / n if s.render.stagger_cameras else 0.0)
                              for i, rid in enumerate(s.robot_ids) for cam in s.robot.cameras]
        self.cmd_in = bus.subscribe(self.keys.cmd())
        self.world_cmd_in = bus.subscribe(self.keys.world_command())
        self.ack_in = bus.subscribe(self.keys.acks())
        self.alive_in = bus.watch_liveliness(self.keys.alive_all())
        bus.declare_token(self.keys.alive("world/0"))
        log.info("world %s: %d robots, %s clock at %g Hz, %d camera(s)/robot, render %s (the cameras ask for "
                 "~%.2f core of rendering)", self.instance, len(s.robot_ids), s.clock.mode, self.tick_hz,
                 len(s.robot.cameras), "in-process" if self.renderer else f"in {s.render.workers} worker(s)",
                 render_load(s))
        for cam in s.robot.cameras:
            p = lens_plan(cam, s.camera.preset)
            if p.maps is not None:  # a lens: say what it renders, the cost users see
                fv = p.fovea
                log.info("camera %s: %s lens %gdeg, rendered as %dx%d%s (%.1fx its %dx%d pixels)", cam.name,
                         p.lens.model, cam.hfov_deg, p.render_cam.width, p.render_cam.height,
                         "" if fv is None else f" + a {fv.render_cam.width}x{fv.render_cam.height} fovea at full "
                         "resolution", render_pixels(cam, s.camera.preset) / (cam.width * cam.height),
                         cam.width, cam.height)

    # ------------------------------------------------------------------ helpers
    def _publish(self, key: str, msg: m.Msg, *, drop: bool = False) -> None:
        self.bus.put(key, codec.encode(msg), drop=drop)

    @property
    def time_ns(self) -> int:
        return self.sim.time_ns

    # ------------------------------------------------------------------ inputs
    def _drain_commands(self) -> None:
        for item, cmd in self.rejects.decoded(self.cmd_in.drain(), m.WheelCommand):
            rid = self.keys.robot_id_of(item.key)
            if rid is None or cmd.robot_id != rid:
                self.rejects.reject("spoofed", f"{item.key} carries robot_id {cmd.robot_id}")
            elif rid not in self.sim.robots:
                self.rejects.reject("unknown_robot", f"{item.key}: robot {rid} is not in the roster")
            else:
                self.sim.set_command(rid, cmd.left_rad_s, cmd.right_rad_s)
        for _, wc in self.rejects.decoded(self.world_cmd_in.drain(), m.WorldCommand):
            if not self.interventions.add(wc):
                self._refuse(f"world command for robot {wc.robot_id}: {len(self.interventions)} already waiting")

    def _apply_interventions(self) -> None:
        """Teleports and pushes due at the current step (see module docstring)."""
        for iv in self.interventions.pop_due(self.time_ns):
            st = self.sim.robots.get(iv.robot_id)
            try:
                if st is None:
                    raise PlacementError(f"robot {iv.robot_id} is not in the roster")
                self.sim.place_robot(iv.robot_id, *iv.target(st.x_m, st.y_m, st.yaw_rad))
            except PlacementError as exc:
                self._refuse(f"{iv.describe()}: {exc}")
                continue
            self.counters["world_events" if iv.from_event else "world_commands"] += 1
            key = self.keys.world_applied()
            self._publish(key, m.WorldCommand(seq=self.seq.next(key), stamp_ns=self.time_ns, robot_id=iv.robot_id,
                                              action=iv.action, x_m=iv.x_m, y_m=iv.y_m, yaw_rad=iv.yaw_rad))
            log.info("t=%.3f s (step %d) %s: now at (%.3f, %.3f, %.3f rad)", self.time_ns / 1e9,
                     self.sim.step_index, iv.describe(), st.x_m, st.y_m, st.yaw_rad)

    def _refuse(self, why: str) -> None:
        self.counters["world_command_rejected"] += 1
        n = self.counters["world_command_rejected"]
        if n <= MAX_REJECT_LOGS:
            log.warning("t=%.3f s (step %d) refused %s%s", self.time_ns / 1e9, self.sim.step_index, why,
                        " (further refusals are only counted)" if n == MAX_REJECT_LOGS else "")

    def _drain_presence(self) -> None:
        for change in self.alive_in.drain():
            who = self.keys.participant_of(change.key)
            if who is None:
                continue
            if who in self.s.clock.observers:
                (self.observers_alive.add if change.value else self.observers_alive.discard)(who)
                continue
            worker = who.startswith("render/")
            tracker = self.workers if worker else self.participants
            # a (re)joining participant can only answer what is sent after it joined
            published = self._render_step if worker else self._published_step
            if tracker.set_alive(who, change.value, published):
                log.info("lockstep participant %s %s after step %d", who, "joined" if change.value else "left",
                         published)
                if not change.value:
                    self.counters["participants_left"] += 1
        for item, ack in self.rejects.decoded(self.ack_in.drain(), m.TickAck):
            who = self.keys.participant_of(item.key)
            if who is None or ack.participant != who:
                self.rejects.reject("spoofed", f"{item.key} carries participant {ack.participant!r}")
                continue
            worker = who.startswith("render/")
            tracker = self.workers if worker else self.participants
            published = self._render_step if worker else self._published_step
            if ack.step > published:  # else one forged ack would excuse a participant from every later step
                self.rejects.reject("inconsistent", f"{who} acknowledges step {ack.step}, newest sent is {published}")
                continue
            if not tracker.ack(who, ack.step):
                self.rejects.reject("unknown_participant", f"{who} is not a declared participant")

    def _wait_acks(self, tracker: AckTracker, step: int, what: str) -> None:
        """Wait until every live participant of ``tracker`` acked ``step``, or the timeout."""

        def done() -> bool:
            self._drain_presence()
            return not tracker.pending(step)

        if not self.bus.wait_for(done, self.s.clock.ack_timeout_s):
            late = sorted(tracker.pending(step))
            self.counters["ack_timeouts"] += 1
            log.warning("%s %s did not acknowledge step %d within %.1f s; continuing without them",
                        what, ", ".join(late), step, self.s.clock.ack_timeout_s)
            for p in late:  # skip them for this step, require them again from the next one
                if tracker.skip(p, step):
                    self.counters["ack_stalls"] += 1
                    log.warning("%s %s missed %d steps in a row (alive but silent: a step that hangs?); not waiting "
                                "for it any more until it acknowledges a step again", what, p, tracker.stall_after)

    def wait_for_participants(self, timeout_s: float | None = None) -> bool:
        """Before the first tick: wait until every declared participant, observer and
        render worker is alive (liveliness), up to ``clock.join_timeout_s``."""
        timeout = self.s.clock.join_timeout_s if timeout_s is None else timeout_s

        def ready() -> bool:
            self._drain_presence()
            return (not self.workers.missing() and (not self.lockstep or not self.participants.missing())
                    and self.observers_alive >= set(self.s.clock.observers))

        ok = self.bus.wait_for(ready, timeout)
        if not ok:
            missing = self.workers.missing() | self.participants.missing()
            log.warning("starting without %s (not alive after %.1f s)",
                        ", ".join(sorted(missing | (set(self.s.clock.observers) - self.observers_alive))), timeout)
        return ok

    # ------------------------------------------------------------------ outputs
    def _publish_state(self, step: int) -> list[str]:
        s, now = self.s, self.time_ns
        for rid, st in self.sim.robots.items():
            pos, quat = self.sim.base_pose(rid)
            key = self.keys.truth(rid)
            self._publish(key, m.GroundTruthPose(
                seq=self.seq.next(key), stamp_ns=now, robot_id=rid, step=step, x_m=st.x_m, y_m=st.y_m,
                yaw_rad=st.yaw_rad, v_m_s=st.v_m_s, omega_rad_s=st.omega_rad_s,
                pose=m.Pose3(x_m=pos[0], y_m=pos[1], z_m=pos[2], qx=quat[0], qy=quat[1], qz=quat[2], qw=quat[3])))
        if due(step, s.encoders.rate_hz, self.tick_hz):
            for rid in self.sim.robots:
                left, right = self.sim.encoder_ticks(rid)
                key = self.keys.encoders(rid)
                self._publish(key, m.EncoderTicks(seq=self.seq.next(key), stamp_ns=now, robot_id=rid,
                                                  left_ticks=left, right_ticks=right,
                                                  ticks_per_rev=s.encoders.ticks_per_rev))
        pairs = [(rid, cam) for rid, cam, phase in self._camera_pairs if due(step, cam.rate_hz, self.tick_hz, phase)]
        if not pairs:
            return []
        if self.renderer is not None:
            self._render_here(pairs, step)
        else:
            self._render_in_workers(pairs, step)
        return [f"{rid}/{cam.name}" for rid, cam in pairs]

    def _render_here(self, pairs: list[tuple[int, Camera]], step: int) -> None:
        assert self.renderer is not None
        bases = {}
        for rid in self.sim.robots:
            pos, quat = self.sim.base_pose(rid)
            self.renderer.set_pose(rid, pos, quat)
            bases[rid] = pose_matrix(pos, quat)
        for rid, cam in pairs:
            img = self.renderer.render(rid, cam, bases[rid])
            key = self.keys.image(rid, cam.name)
            # lockstep: BLOCK, or a subscriber busy for a few ms (a recorder taking every camera) loses frames
            self._publish(key, image_message(self.s, rid, cam, img, seq=self.seq.next(key), step=step,
                                             stamp_ns=self.time_ns), drop=not self.lockstep)
        self.counters["frames_rendered"] += len(pairs)

    def _render_in_workers(self, pairs: list[tuple[int, Camera]], step: int) -> None:
        ids, poses = [], []
        for rid in self.sim.robots:
            pos, quat = self.sim.base_pose(rid)
            ids.append(rid)
            poses.append(m.Pose3(x_m=pos[0], y_m=pos[1], z_m=pos[2], qx=quat[0], qy=quat[1], qz=quat[2], qw=quat[3]))
        k = self.s.render.workers
        for w in range(k):
            mine = tuple(f"{rid}/{cam.name}" for i, (rid, cam) in enumerate(pairs) if i % k == w)
            key = self.keys.render(w)
            self._publish(key, m.RenderPoses(seq=self.seq.next(key), stamp_ns=self.time_ns, step=step,
                                             robot_ids=tuple(ids), poses=tuple(poses), cameras=mine),
                          drop=not self.lockstep)
        self.counters["frames_requested"] += len(pairs)
        self._render_step = step
        if self.lockstep:
            self._wait_acks(self.workers, step, "render worker(s)")

    def _publish_status(self) -> None:
        counters = {"world_commands": 0, "world_events": 0, "world_command_rejected": 0, **self.counters}
        counters.update(self.sim.contacts.as_counters())
        counters["step"] = self.sim.step_index
        if self._stepping_since is not None:
            # wall time spent stepping, without start-up and shutdown: the real-time factor of the simulation
            counters["stepping_ms"] = round((time.monotonic() - self._stepping_since) * 1000)
        for st in self.sim.robots.values():
            for name, v in st.counters.items():
                counters[name] = counters.get(name, 0) + v
        if self.renderer is not None:
            counters["frames_rendered"] = self.renderer.frames_rendered
        counters.update(self.rejects.as_counters())
        counters.update(self.bus.fault_stats())
        key = self.keys.world_status()
        self._publish(key, m.AgentStatus(seq=self.seq.next(key), stamp_ns=self.time_ns, role="world",
                                         mode=self.s.clock.mode, counters=counters))

    # ------------------------------------------------------------------ cycle
    def step(self) -> None:
        """One cycle: commands in, physics one tick (except the very first call,
        which publishes the initial state), sensors and tick out, lockstep wait."""
        self._drain_presence()
        self._drain_commands()
        if self._started:
            self.sim.step()
        self._started = True
        self._apply_interventions()
        step = self.sim.step_index
        rendered = self._publish_state(step)
        key = self.keys.tick()
        self._publish(key, m.Tick(seq=self.seq.next(key), stamp_ns=self.time_ns, run_id=self.instance, step=step,
                                  dt_ns=self.sim.dt_ns, mode=self.s.clock.mode, cameras_rendered=tuple(rendered)))
        self._published_step = step
        if self.time_ns >= self._next_status_ns:
            self._publish_status()
            self._next_status_ns = self.time_ns + int(self.cfg.status_period_s * 1e9)
        if self.lockstep:
            self._wait_acks(self.participants, step, "participant(s)")

    def run(self, stop_event: threading.Event) -> int:
        """Step until ``duration_s`` of simulated time or ``stop_event``; returns 0."""
        end_ns = int(self.s.duration_s * 1e9)
        self.wait_for_participants()
        t0 = self._stepping_since = time.monotonic()
        wall_per_tick = self.sim.dt_ns / 1e9 / self.s.clock.speed
        while not stop_event.is_set():
            self.step()
            if self.time_ns >= end_ns:
                break
            if not self.lockstep:
                lag = t0 + self.sim.step_index * wall_per_tick - time.monotonic()
                if lag > 0:
                    stop_event.wait(lag)
                else:
                    self.counters["realtime_overruns"] += 1
        self._publish_status()
        wall = time.monotonic() - t0
        log.info("stopped at t=%.2f s after %.2f s wall (real-time factor %.2f)",
                 self.time_ns / 1e9, wall, (self.time_ns / 1e9) / max(wall, 1e-9))
        return 0

    def close(self) -> None:
        self.sim.close()
        if self.renderer is not None:
            self.renderer.close()


def spawn_render_workers(config: WorldConfig, folder: Path) -> list[subprocess.Popen[bytes]]:
    """Start the render workers (before this process opens its Zenoh session: never
    fork after opening one).  They get the resolved scenario as a JSON file."""
    s = resolve_render_workers(config.scenario)
    if s.render.workers == 0 or not config.spawn_render_workers:
        return []
    scen = folder / "scenario.json"
    scen.write_bytes(msgspec.json.encode(s))
    endpoints = [e for e in config.bus.listen if not e.endswith(":0")] + list(config.bus.connect)
    procs = []
    for i in range(s.render.workers):
        argv = [sys.executable, "-m", "tagswarm.world.render_worker", "--worker-index", str(i), "--scenario", str(scen),
                "--run", config.run, "--log-level", config.log_level]
        for e in endpoints:
            argv += ["--connect", e]
        if config.bus.multicast_scouting:
            argv.append("--multicast-scouting")
        procs.append(subprocess.Popen(argv))
    return procs


def main(argv: Sequence[str] | None = None, environ: Mapping[str, str] | None = None) -> int:
    """Console script ``tagswarm-world``."""

    def body() -> int:
        config = build_config(argv, environ)
        setup_logging(config.log_level, "world")
        stop = threading.Event()
        with tempfile.TemporaryDirectory(prefix="tagswarm-world-") as tmp:
            workers = spawn_render_workers(config, Path(tmp))
            try:
                with open_bus(config.bus) as bus:
                    node = WorldNode(config, bus)
                    try:
                        install_stop_signals(stop)
                        return node.run(stop)
                    finally:
                        node.close()
            finally:
                for p in workers:
                    p.terminate()
                for p in workers:
                    try:
                        p.wait(timeout=5)
                    except subprocess.TimeoutExpired:
                        p.kill()

    return run_main("tagswarm-world", body)


if __name__ == "__main__":
    raise SystemExit(main())
