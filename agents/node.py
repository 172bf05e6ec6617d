"""The agent process of one robot (the only I/O of ``agents``).

Subscribes to its own robot's camera images (newest-only per camera: a slow
detector skips frames, it never queues them), encoder ticks, the world clock,
the server's corrections, run-time goals and the server's global map (the other
robots, which missions and goals steer around: :mod:`tagswarm.agents.avoid`).  Publishes
relative observations, odometry (with slip evidence from commanded against
measured wheel rotation; in a replay, against the recorded commands on
``recorded_cmd``), wheel commands and status.  It never reads ground truth.

Realtime: each :meth:`AgentNode.step` handles what has arrived.  Lockstep:
for each world tick it waits (bounded) for that tick's frames, processes them,
publishes, then acknowledges the tick.  A lockstep agent steers by maps stamped
two ticks back or earlier, which the server sent before the correction it has
waited for, so the run does not depend on when a map arrives.

Faults it rides out:
- restart of this agent: it resumes from the server's last pose for its robot (a map query
  at start) and ignores corrections made before the server saw its new odometry;
- loss of the server (liveliness): it keeps its mission on odometry (mode
  ``odometry``, counter ``server_alive`` 0) and takes corrections again as soon
  as a server sends them;
- restart of the world: a tick with a new ``run_id`` after the world's
  liveliness token vanished starts a new run: odometry, behaviour, map pose and
  priors are reset.  A foreign ``run_id`` while the world is alive is rejected.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Mapping, Sequence

from tagswarm.agents.avoid import Neighbour, static_boxes
from tagswarm.agents.behaviour import Behaviour, wheel_speeds
from tagswarm.agents.config import AgentConfig, build_config
from tagswarm.agents.controller import (
    BehaviourController,
    ControllerConfig,
    ControllerRunner,
    GoalRequest,
    control_input,
    load_factory,
    make,
    mission_behaviour,
)
from tagswarm.agents.cubepose import PoseEstimate
from tagswarm.agents.decoys import CopySites
from tagswarm.agents.intake import CORRECTION_AHEAD_NS, AgentIntake, sigma_lapsed
from tagswarm.agents.neighbours import NeighbourTracker
from tagswarm.agents.odometry import DiffDriveOdometry, DiffDriveParams, SlipMonitor
from tagswarm.agents.vision import Vision
from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import Bus, Inbox
from tagswarm.protocol.geometry import Pose2, position_sigma_m, se2_compose
from tagswarm.protocol.keys import Keys
from tagswarm.protocol.layout import anchors_map, arena_to_map, footprint_radius, map_to_arena_xy, stand_problem
from tagswarm.runtime import streams
from tagswarm.runtime.lockstep import Participant
from tagswarm.runtime.presence import Presence, RunEnd, silence_ns
from tagswarm.runtime.process import serve_node

log = logging.getLogger("tagswarm.agent")
LOCKSTEP_FRAME_QUEUE = 16  # per camera, lockstep only (bounded memory under a flood)
MAP_QUEUE = 64  # global maps waiting to be used (a few at 2 Hz; bounded under a flood)
REALTIME_CMD_DELAY_TICKS = 2  # a realtime world applies a command up to this many ticks after its stamp


class AgentNode:
    """One robot's agent; see the module docstring."""

    def __init__(self, config: AgentConfig, bus: Bus) -> None:
        self.cfg = config
        self.s = s = config.scenario
        self.rid = rid = config.robot_id
        self.bus = bus
        self.keys = Keys(config.run)
        self.rejects = streams.RejectCounter(log)
        self.gaps = streams.GapCounter()  # messages lost on the way, per sender (lossy networks)
        self.counters: Counter[str] = Counter()
        self.vision = Vision(s, rid, self.counters, config.inject_frame_delay_s)
        self.intake = AgentIntake(rid, s.encoders.ticks_per_rev, self.rejects, self.counters)
        self.seq = streams.Sequencer()
        self.participant = Participant(bus, self.keys, config.participant, self.seq)  # lockstep acks
        self.lockstep = s.clock.mode == "lockstep"
        # realtime: newest-only, a slow detector skips frames.  Lockstep: the world waits for us, so nothing
        # queues, but a newest-only inbox would let one bad payload landing after a frame displace it (the
        # agent then waits frame_wait_s for a frame that never comes): a short FIFO keeps both
        self.images: dict[str, Inbox[bytes]] = {
            c.name: bus.subscribe(self.keys.image(rid, c.name), newest_only=not self.lockstep,
                                  capacity=LOCKSTEP_FRAME_QUEUE) for c in s.robot.cameras}
        self._frames_taken = 0  # frames drained from the newest-only inboxes (the rest were overwritten)
        # CPU seconds (this thread) handling frames, publishing included; the vision reports how much of it
        # went to the detector and the pose estimate: the status gives both for bench/speed.py's overhead ratio
        self._cpu_frames_s = 0.0
        self.enc_in = bus.subscribe(self.keys.encoders(rid))
        self.recorded_cmd_in = bus.subscribe(self.keys.recorded_cmd(rid))  # only a replay sends them
        # realtime: only encoders (a control cycle) and frames wake the loop; ticks, corrections, goals and maps
        # are read at the next wake-up, where they are used anyway (~60 passes a second less).  Lockstep waits on them
        wakes = self.lockstep
        self.tick_in = bus.subscribe(self.keys.tick(), wakes=wakes)
        self.corr_in = bus.subscribe(self.keys.correction(rid), wakes=wakes)
        self.goal_in = bus.subscribe(self.keys.goal(rid), wakes=wakes)
        self.map_in = bus.subscribe(self.keys.map(), capacity=MAP_QUEUE, wakes=wakes)
        self.static_obstacles = static_boxes(s)
        self.server_alive_in = bus.watch_liveliness(self.keys.alive_role("server"))
        self.world_alive_in = bus.watch_liveliness(self.keys.alive_role("world"))
        # the server's token, and (realtime) whether its corrections and maps keep coming
        # maps come at 2 Hz (corrections only while localised): a second beyond the lease is two missed maps
        self.server_presence: Presence[str] = Presence(
            0 if self.lockstep else silence_ns(config.bus.lease_ms, config.bus.delay_ms, 1.0))
        self.runs = streams.RunFollower()  # the world instance whose ticks we follow
        self.wait_for_server = any(p.startswith("server/") for p in s.clock.participants)
        # a user's controller (docs/controllers.md): made anew with every run, like the behaviour
        self._factory = None if config.agent_module is None else load_factory(config.agent_module)
        self._goals = 0
        self._reset_run()
        if config.fetch_map_timeout_s > 0:
            self._fetch_last_pose(config.fetch_map_timeout_s)
        bus.declare_token(self.keys.alive(config.participant))
        log.info("agent %d up: %d camera(s), %s, %s clock", rid, len(s.robot.cameras),
                 f"mission {self.behaviour.mission.kind}" if self.custom is None
                 else f"controller {config.agent_module}", s.clock.mode)

    # ------------------------------------------------------------------ helpers
    def _reset_run(self) -> None:
        """Everything that belongs to one world run: odometry, behaviour, map pose, priors, clocks."""
        s, a, rid = self.s, self.s.agent, self.rid
        self.odom = DiffDriveOdometry(DiffDriveParams(s.robot.wheel_radius_m, s.robot.wheel_base_m,
                                                      s.encoders.ticks_per_rev, a.odom_wheel_sigma))
        # map -> odom; the origin robot's first pose *is* the map frame (unless landmarks pin it)
        self.map_odom: Pose2 | None = (0.0, 0.0, 0.0) if anchors_map(s, rid) else None
        self.behaviour = mission_behaviour(Behaviour, s, rid, arena_to_map(s), self.static_obstacles)
        self.custom: ControllerRunner | None = None
        if self._factory is not None:
            ccfg = ControllerConfig(rid, s, self.cfg.run)
            self.custom = ControllerRunner(make(self._factory, ccfg, str(self.cfg.agent_module)), ccfg, log)
            if isinstance(self.custom.controller, BehaviourController):
                self.behaviour = self.custom.controller.behaviour  # its counters in the status
        self.map_cov: tuple[float, ...] | None = None  # of the newest correction
        self.vouched = True  # whether the newest correction vouched for map_odom
        self.loose_map_odom: Pose2 | None = None  # placed but not vouched for, before the first vouched correction
        self.goal: GoalRequest | None = None
        self._observed: list[m.RelativeObservation] = []  # since the last control cycle (for a controller)
        self._frames_seen: dict[str, m.CameraImage] = {}
        r = s.robot
        self.copy_sites = CopySites()
        self.neighbours = NeighbourTracker(rid, footprint_radius(r), r.max_wheel_speed_rad_s * r.wheel_radius_m)
        tick_ns = round(1e9 / s.clock.tick_hz)
        self.slip = SlipMonitor(r.wheel_radius_m, s.encoders.ticks_per_rev, a.odom_wheel_sigma,
                                delay_ns=0 if self.lockstep else REALTIME_CMD_DELAY_TICKS * tick_ns,
                                timeout_ns=round(s.clock.command_timeout_s * 1e9))
        self.time_ns = self.last_fix_ns = self._next_status_ns = 0
        self._moved = self._fix = False
        self.vision.reset()
        self.pending_frames: dict[str, m.CameraImage] = {}
        self.intake.reset()
        self.correction_stamp_ns = -1
        # our first odometry's stamp in this run: older corrections are in a previous process's or run's odom frame
        self._odom_since_ns: int | None = None
        self._last_step: int | None = None

    def _drain_presence(self) -> None:
        """Liveliness of the server (corrections possible?) and of the world (may a new run start?)."""
        was = self.server_alive
        for change in self.server_alive_in.drain():
            self.server_presence.token("server", change.value, self.time_ns)
        self.server_presence.update(self.time_ns)
        if was and not self.server_alive:
            self.counters["server_lost"] += 1
            how = (f"silent (no correction or map for {self.server_presence.silence_ns / 1e9:.1f} s)"
                   if "server" in self.server_presence.silent else "gone")
            log.warning("the map server is %s: running on odometry until it is back", how)
        elif self.server_alive and not was and self.counters["server_lost"]:
            log.info("a map server is back")
        for change in self.world_alive_in.drain():
            self.runs.world_presence(change.value)

    def _accept_tick(self, tick: m.Tick) -> bool:
        """Whether ``tick`` belongs to the run we follow; a new run_id after the world
        left starts a new run (reset), while the world is alive it is foreign."""
        self._drain_presence()
        previous = self.runs.run_id
        verdict = self.runs.accept(tick.run_id)
        if verdict == "foreign":
            self.rejects.reject("foreign_run", f"tick of run {tick.run_id!r} while {previous!r} is live")
            return False
        restart = verdict == "restart"
        if restart:
            log.warning("the world restarted (new run %s): resetting odometry, behaviour and map pose", tick.run_id)
            self.counters["world_restarts"] += 1
            self._reset_run()
            # a world killed mid-step leaves that step's sensor data queued, stamped after the new run's
            # first tick: take only what belongs to the new run; old corrections refer to old odometry
            self.corr_in.drain()
            self._handle_encoders(upto_ns=tick.stamp_ns)
            self._take_frames(upto_ns=tick.stamp_ns)
        return True

    def _publish(self, key: str, msg: m.Msg) -> None:
        self.bus.put(key, codec.encode(msg))

    @property
    def server_alive(self) -> bool:
        """A map server's token is up and (realtime) it keeps talking to us."""
        return self.server_presence.alive("server")

    @property
    def run_id(self) -> str | None:
        """The world run (Tick.run_id) this agent follows, None before the first tick."""
        return self.runs.run_id

    @property
    def map_pose(self) -> Pose2 | None:
        """Corrected pose of base_link in the map frame, None until localised."""
        return None if self.map_odom is None else se2_compose(self.map_odom, self.odom.pose())

    def _fetch_last_pose(self, timeout_s: float) -> None:
        """Late joiner / restart: start from the server's last pose for this robot."""
        def server_known() -> bool:
            self._drain_presence()
            return self.server_alive

        # a query only reaches queryables this session already knows of: wait until the server's
        # declarations (its token comes after its queryable) have reached us over the peer mesh
        t0 = time.monotonic()
        if not self.bus.wait_for(server_known, timeout_s):
            log.info("no map server within %.1f s: starting unlocalised", timeout_s)
            return
        try:
            replies = self.bus.get(self.keys.map(), max(0.2, timeout_s - (time.monotonic() - t0)))
        except Exception as exc:
            log.debug("map query failed: %s", exc)
            return
        for reply in replies:
            try:
                gmap = codec.decode(m.GlobalMap, reply.value)
            except codec.DecodeError as exc:
                self.rejects.reject(exc.kind, f"map reply: {exc.detail}")
                continue
            self.counters["map_entries_at_start"] = len(gmap.robots)
            for e in gmap.robots:
                if e.robot_id == self.rid:
                    self.counters["resumed_from_map"] = 1
                    # odometry restarts at zero, so map -> odom is the last known pose (loose if not vouched for)
                    pose = (e.x_m, e.y_m, e.yaw_rad)
                    self.map_odom, self.loose_map_odom = (pose, None) if e.localised else (None, pose)
                    log.info("resuming from the server's last pose (%.2f, %.2f, %.2f)", e.x_m, e.y_m, e.yaw_rad)

    # ------------------------------------------------------------------ inputs
    def _handle_encoders(self, upto_ns: int | None = None) -> None:
        """Integrate queued encoder counts; ``upto_ns``: drop any stamped later (see :meth:`_accept_tick`)."""
        for key, enc in self.intake.encoders(self.enc_in.drain(), upto_ns):
            self.gaps.seen(key, enc.seq, "encoders")
            ds, dth = self.odom.update(enc.left_ticks, enc.right_ticks)
            slip = self.slip.measured(enc.stamp_ns, enc.left_ticks, enc.right_ticks)
            if slip > 0:
                self.odom.add_slip(slip)
            self._moved = self._moved or abs(ds) > 1e-4 or abs(dth) > 1e-4
            self.time_ns = max(self.time_ns, enc.stamp_ns)
        for _, cmd in self.intake.own(self.recorded_cmd_in.drain(), m.WheelCommand):
            self.slip.commanded(cmd.stamp_ns, cmd.left_rad_s, cmd.right_rad_s, recorded=True)

    def _handle_corrections(self) -> None:
        for key, c in self.intake.own(self.corr_in.drain(), m.Correction):
            self.correction_stamp_ns = max(self.correction_stamp_ns, c.stamp_ns)
            self.server_presence.heard("server", self.time_ns)
            self.gaps.seen(key, c.seq, "corrections")
            if not self.intake.placement(c, self._odom_since_ns, self.time_ns):
                continue
            pose = (c.map_odom_x_m, c.map_odom_y_m, c.map_odom_yaw_rad)
            if not c.localised and (self.map_odom is None or not sigma_lapsed(c, self.s.server.claim_sigma_m)):
                # placed, never vouched for: a loose pose; vouched for before and now in dispute (its sigma small):
                # ignored, it drives on (the views that settle a dispute come from moving; intake.sigma_lapsed)
                self.loose_map_odom = pose if self.map_odom is None else self.loose_map_odom
                continue
            self.map_odom, self.map_cov, self.vouched = pose, c.cov, c.localised  # unvouched: driven on slowly
            self.counters["corrections"] += c.localised
            if c.localised and c.last_fix_ns > self.last_fix_ns:
                self.last_fix_ns = c.last_fix_ns
                self._fix = True
        for _, g in self.intake.own(self.goal_in.drain(), m.Goal):
            why = stand_problem(self.s, *map_to_arena_xy(self.s, g.x_m, g.y_m))
            self.counters["goals_refused" if why else "goals"] += 1
            if why:  # driving at it would end against a wall or an obstacle
                log.warning("goal (%.2f, %.2f) in the map frame refused: %s", g.x_m, g.y_m, why)
                continue
            self._goals += 1
            self.goal = GoalRequest(g.x_m, g.y_m, g.tolerance_m, self._goals)
            if self.custom is None:
                self.behaviour.set_goal(g.x_m, g.y_m, g.tolerance_m)
            log.info("new goal (%.2f, %.2f)", g.x_m, g.y_m)

    def _take_frames(self, upto_ns: int | None = None) -> None:
        """Move the newest frame of each camera into ``pending_frames``.  A frame not
        processed before a newer one arrives is skipped (counted), never queued."""
        for name, inbox in self.images.items():
            items = inbox.drain()
            self._frames_taken += len(items)
            for img in self.intake.frames(name, items, upto_ns):
                if name in self.pending_frames:
                    self.counters["frames_replaced"] += 1
                self.pending_frames[name] = img

    # ------------------------------------------------------------------ vision
    def _process_frames(self) -> None:
        if not self.pending_frames:
            return
        t0 = time.thread_time()
        try:
            frames = list(self.pending_frames.values())
            self.pending_frames.clear()
            if self.custom is not None and self.custom.wants_images:
                self._frames_seen.update((img.camera, img) for img in frames)
            stamp = max(img.stamp_ns for img in frames)
            estimates = self.vision.process(frames, self.time_ns, self._expected(stamp))
            self.time_ns = max(self.time_ns, stamp)
            me = self.map_pose
            if me is not None:
                self.copy_sites.remember(me, self.vision.estimator.copies_seen, stamp)
            for est in estimates:
                off_map = self._off_map(est)
                if off_map is not None and self.copy_sites.at(est.target_id, *off_map, stamp):
                    self.counters["sightings_at_copy_site"] += 1  # a copy we saw beside its robot, alone now
                    continue
                self._publish_observation(est, stamp)
                # a sighting corrects our pose only through a server, and not one our map contradicts (a
                # copy of a robot's cube elsewhere): then only the server's word (last_fix_ns) is a fix
                if self.server_alive and off_map is None:
                    self._fix = True
        finally:
            self._cpu_frames_s += time.thread_time() - t0

    def _expected(self, stamp_ns: int) -> dict[tuple[str, int], tuple[float, float, float]]:
        """Where the map in use has the other robots at ``stamp_ns``: (x_m, y_m, radius_m) in our base
        frame, the radius widened by both poses' uncertainty (an uncertain map picks no copy)."""
        me, sigma = self.map_pose, position_sigma_m(self.map_cov)
        return {} if me is None or sigma is None else self.neighbours.expected(me, stamp_ns, sigma)

    def _off_map(self, est: PoseEstimate) -> tuple[float, float] | None:
        """Where (map frame) a sighting puts its robot if our map has it far from there (an obstacle anyway)."""
        if est.target_kind != "robot" or (me := self.map_pose) is None:
            return None
        x, y, _ = se2_compose(me, (est.x_m, est.y_m, est.yaw_rad))
        self.neighbours.saw(est.target_id, x, y, self.time_ns)
        if not self.neighbours.contradicts(est.target_id, x, y, self.time_ns):
            return None
        self.counters["sightings_off_map"] += 1
        return x, y

    def _publish_observation(self, est: PoseEstimate, stamp_ns: int) -> None:
        key = self.keys.observation(self.rid)
        msg = est.to_message(self.rid, seq=self.seq.next(key), stamp_ns=stamp_ns)
        self._publish(key, msg)
        self.counters["observations"] += 1
        if self.custom is not None:
            self._observed.append(msg)

    # ------------------------------------------------------------------ control
    def _others(self) -> tuple[Neighbour, ...]:
        """The other robots now (map frame), from the newest usable global map."""
        for _, gmap in self.rejects.decoded(self.map_in.drain(), m.GlobalMap):
            if gmap.stamp_ns > self.time_ns + CORRECTION_AHEAD_NS:
                self.counters["stale_maps"] += 1  # of a previous world run
                continue
            self.server_presence.heard("server", self.time_ns)
            self.neighbours.offer(gmap.stamp_ns, gmap.robots)
        # lockstep: the map of tick k-2 left the server before its correction of tick k-1, which
        # we have waited for; a newer one may or may not be here yet
        usable = self.time_ns - 2 * round(1e9 / self.s.clock.tick_hz) if self.lockstep else None
        return self.neighbours.neighbours(self.time_ns, usable)

    def _control(self) -> None:
        if self.custom is None:
            v, w = self.behaviour.cycle(t_s=self.time_ns / 1e9, map_pose=self.map_pose, odom_yaw=self.odom.yaw_rad,
                                        moved=self._moved, fix=self._fix, server_up=self.server_alive,
                                        neighbours=self._others(), pos_sigma_m=position_sigma_m(self.map_cov),
                                        loose_pose=None if self.map_odom is not None or self.loose_map_odom is None
                                        else se2_compose(self.loose_map_odom, self.odom.pose()), vouched=self.vouched)
            left, right = wheel_speeds(v, w, self.s.robot)
        else:
            left, right = self.custom.command(control_input(
                robot_id=self.rid, time_ns=self.time_ns, map_odom=self.map_odom, map_cov=self.map_cov,
                odom_pose=self.odom.pose(), odom_cov=self.odom.cov, distance_m=self.odom.distance_m,
                moved=self._moved, fix=self._fix, server_up=self.server_alive, observations=tuple(self._observed),
                neighbours=self._others(), goal=self.goal, images=self._frames_seen,
                loose_map_odom=self.loose_map_odom, vouched=self.vouched))
            self._observed.clear()
            self._frames_seen.clear()
        self._moved = self._fix = False
        key = self.keys.cmd(self.rid)
        self._publish(key, m.WheelCommand(seq=self.seq.next(key), stamp_ns=self.time_ns, robot_id=self.rid,
                                          left_rad_s=left, right_rad_s=right))
        self.slip.commanded(self.time_ns, left, right)
        key = self.keys.odometry(self.rid)
        if self._odom_since_ns is None:
            self._odom_since_ns = self.time_ns
        self._publish(key, m.OdometryEstimate(
            seq=self.seq.next(key), stamp_ns=self.time_ns, robot_id=self.rid, x_m=self.odom.x_m, y_m=self.odom.y_m,
            yaw_rad=self.odom.yaw_rad, cov=tuple(float(v) for v in self.odom.cov.ravel()),
            distance_m=self.odom.distance_m, slip_m=self.slip.slip_m))
        if self.time_ns >= self._next_status_ns:
            self._publish_status()
            self._next_status_ns = self.time_ns + int(self.s.agent.status_period_s * 1e9)

    def status_counters(self) -> dict[str, int]:
        b = self.behaviour
        out = dict(self.counters)
        received = sum(inbox.received for inbox in self.images.values())
        out.update(fixes=b.fixes, searches=b.searches, lost_events=b.lost_events, look_arounds=b.look_arounds,
                   odometry_cycles=b.counter, localised=int(self.map_odom is not None and self.vouched),
                   server_alive=int(self.server_alive), avoiding_cycles=b.avoider.cycles_avoiding,
                   avoid_yields=b.avoider.yields, avoid_side_flips=b.avoider.side_flips,
                   avoid_reroutes=b.avoider.reroutes, avoid_steps_aside=b.make_way.steps_aside,
                   maps_used=self.neighbours.maps_adopted, slip_events=self.slip.events, frames_received=received,
                   slip_mm=round(self.slip.slip_m * 1000), cpu_frames_us=round(self._cpu_frames_s * 1e6),
                   cpu_detect_pose_us=round(self.vision.detect_pose_cpu_s * 1e6),
                   # overwritten in the newest-only inbox, or replaced while pending
                   frames_skipped=received - self._frames_taken + self.counters["frames_replaced"])
        out.update(self.rejects.as_counters())
        out.update(self.gaps.as_counters())
        if self.custom is not None:
            out.update(self.custom.counters())
        out.update(self.bus.fault_stats())
        out.update({f"pose_rejected_{k}": v for k, v in self.vision.estimator.rejects.items()})
        out["duplicates_resolved_by_map"] = self.vision.estimator.resolved_by_map
        return out

    def _publish_status(self) -> None:
        key = self.keys.robot_status(self.rid)
        self._publish(key, m.AgentStatus(seq=self.seq.next(key), stamp_ns=self.time_ns, robot_id=self.rid, role="agent",
                                         mode=str(self.behaviour.mode) if self.custom is None else self.custom.mode,
                                         counters=self.status_counters()))

    # ------------------------------------------------------------------ cycle
    def step(self) -> bool:
        """Handle what has arrived (realtime) or the next tick (lockstep).
        Returns True if anything was processed."""
        if self.lockstep:
            return self._step_lockstep()
        self._drain_presence()
        for _, tick in self.rejects.decoded(self.tick_in.drain(), m.Tick):
            self._accept_tick(tick)  # realtime needs ticks only to notice a world restart
        self._handle_corrections()
        had_enc = len(self.enc_in) > 0
        self._handle_encoders()
        self._take_frames()
        had_frames = bool(self.pending_frames)
        self._process_frames()
        if had_enc:
            self._control()
        return had_enc or had_frames

    def _step_lockstep(self) -> bool:
        ticks = self.tick_in.drain()
        accepted = (tick for _, tick in self.rejects.decoded(ticks, m.Tick) if self._new_step(tick))
        self.participant.serve(accepted, self._lockstep_tick)
        return bool(ticks)

    def _new_step(self, tick: m.Tick) -> bool:
        """Whether ``tick`` is of the run we follow and a step not acted on yet."""
        if not self._accept_tick(tick):
            return False
        if self._last_step is not None and tick.step <= self._last_step:
            self.counters["stale_ticks"] += 1  # a repeat: acting twice on one tick would break lockstep
            return False
        return True

    def _lockstep_tick(self, tick: m.Tick) -> bool:
        """One lockstep step: wait (bounded) for this robot's frames of ``tick`` and the server's
        correction of the step before, then odometry, frames, behaviour and the wheel command;
        False abandons the step."""
        self.time_ns = max(self.time_ns, tick.stamp_ns)
        mine = tick.cameras_of().get(self.rid, set())

        def frames_in() -> bool:
            self._take_frames()
            self._drain_presence()
            pending = self.pending_frames
            return self.runs.world_left or all(n in pending and pending[n].step >= tick.step for n in mine)

        if mine and not self.bus.wait_for(frames_in, self.s.agent.frame_wait_s):
            self.counters["frames_missing"] += 1
        if self.runs.world_left:
            # the world died mid-step: its run is over, nothing of this tick is wanted any more
            self.counters["ticks_abandoned"] += 1
            return False
        if self.wait_for_server and self._last_step is None:
            # first tick: the world started, so the server is up; wait for its token so that
            # the first corrections are waited for like every later one (determinism)
            def server_known() -> bool:
                self._drain_presence()
                return self.server_alive

            self.bus.wait_for(server_known, self.s.agent.frame_wait_s)
        elif self.wait_for_server and self._last_step == tick.step - 1:
            # the server corrected tick k-1 before acking it; wait for that correction so that the
            # run does not depend on which network path is faster (lockstep determinism).  Not after
            # a gap (we joined late or restarted): that correction may have gone out before we listened.
            prev = tick.stamp_ns - tick.dt_ns

            def corrected() -> bool:
                self._drain_presence()
                self._handle_corrections()
                return not self.server_alive or self.runs.world_left or self.correction_stamp_ns >= prev

            if not self.bus.wait_for(corrected, self.s.agent.frame_wait_s):
                self.counters["corrections_missing"] += 1
        self._handle_corrections()
        self._handle_encoders()
        self._process_frames()
        self._control()
        self._last_step = tick.step
        return True

    def run(self, stop_event: threading.Event) -> int:
        end_ns = int(self.s.duration_s * 1e9)
        end = RunEnd(end_ns)  # realtime: the world left at the end, its last counts lost on the way
        while not stop_event.is_set() and self.time_ns < end_ns:
            if not self.step():
                if not self.lockstep and end.over(self.time_ns, self.runs.world_alive, time.monotonic()):
                    log.warning("the world left at the end of the run (t=%.2f s here): stopping", self.time_ns / 1e9)
                    break
                self.bus.wait(0.1)
        self._publish_status()
        log.info("agent %d stopping at t=%.2f s: %s", self.rid, self.time_ns / 1e9, self.status_counters())
        return 0


def main(argv: Sequence[str] | None = None, environ: Mapping[str, str] | None = None) -> int:
    """Console script ``tagswarm-agent``."""
    return serve_node("tagswarm-agent", lambda: build_config(argv, environ), lambda c: f"agent{c.robot_id}",
                      AgentNode)


if __name__ == "__main__":
    raise SystemExit(main())
