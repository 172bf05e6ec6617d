"""What one robot's agent holds and takes in: the base of :class:`~tagswarm.agents.node.AgentNode`.

Its subscriptions (camera images, encoder ticks, recorded commands, the world clock,
corrections, goals, global maps, the liveliness of the server and of the world), the
state of one world run (odometry in the odom frame, map -> odom in metres and radians,
behaviour or a user's controller, priors; times in simulation ns), whom it hears
(presence), which world run it follows (a restart resets the run, a foreign run is
rejected), the server's last pose it resumes from, and the intake of encoder counts,
corrections, goals and frames.  What the agent does with them (vision, control, status,
the realtime and lockstep cycle) is :mod:`tagswarm.agents.node`; the faults it rides out
are listed there.
"""

from __future__ import annotations

import logging
import time
from collections import Counter

from tagswarm.agents.avoid import static_boxes
from tagswarm.agents.behaviour import Behaviour
from tagswarm.agents.config import AgentConfig
from tagswarm.agents.controller import (
    BehaviourController,
    ControllerConfig,
    ControllerRunner,
    GoalRequest,
    load_factory,
    make,
    mission_behaviour,
)
from tagswarm.agents.decoys import CopySites
from tagswarm.agents.intake import AgentIntake, sigma_lapsed
from tagswarm.agents.neighbours import NeighbourTracker
from tagswarm.agents.odometry import DiffDriveOdometry, DiffDriveParams, SlipMonitor
from tagswarm.agents.vision import Vision
from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import Bus, Inbox
from tagswarm.protocol.geometry import Pose2, se2_compose
from tagswarm.protocol.keys import Keys
from tagswarm.protocol.layout import anchors_map, arena_to_map, footprint_radius, map_to_arena_xy, stand_problem
from tagswarm.runtime import streams
from tagswarm.runtime.lockstep import Participant
from tagswarm.runtime.presence import Presence, silence_ns

log = logging.getLogger("tagswarm.agent")
LOCKSTEP_FRAME_QUEUE = 16  # per camera, lockstep only (bounded memory under a flood)
MAP_QUEUE = 64  # global maps waiting to be used (a few at 2 Hz; bounded under a flood)
REALTIME_CMD_DELAY_TICKS = 2  # a realtime world applies a command up to this many ticks after its stamp


class NodeState:
    """One robot's agent: its wiring, run state and inputs (see the module docstring);
    :class:`~tagswarm.agents.node.AgentNode` adds what it does with them."""

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
