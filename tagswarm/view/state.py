"""The live web view's state model (pure logic: no Zenoh, no sockets, no clock).

:class:`ViewState` folds decoded wire messages into what the page draws and
serialises it as JSON-ready dicts: :meth:`ViewState.scene` (the static arena,
sent once per connection) and :meth:`ViewState.snapshot` (everything that moves,
broadcast at a bounded rate).

Frames: every pose in a snapshot is in the MAP frame (the origin robot's first
pose, or the arena frame when the scenario has landmarks; see
:func:`tagswarm.protocol.layout.arena_to_map`).  Ground truth arrives in the arena frame
and is converted here; odometry arrives in each robot's ``odom`` frame and is
shown as dead reckoning started from the robot's start pose (what the recorder
writes as ``odom_<k>.tum``: pure drift).  The scene's walls, obstacles and
landmarks stay in the arena frame, and ``map_in_arena`` (T_arena_map) places the
map frame in it.  Metres, radians, nanoseconds of simulation time.

Covariances arrive in each robot's own axes (see :mod:`tagswarm.evaluation.covframe`); the
drawn ellipse is rotated into the map frame by the fused yaw.  Re-localisation
events and kidnaps (world commands) go to an :class:`~tagswarm.view.events.EventLog`;
each robot's share of time localised (see :mod:`tagswarm.evaluation.localised`) is counted
from the truth samples the view received.

Run changes: a :class:`~tagswarm.protocol.messages.Tick` with a new ``run_id`` (every
world start draws a new one) or a clock that goes back (a restarted system, a
replay started again) resets everything but the reject counts and bumps
``epoch``, so the page clears its trails.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any, Final

from tagswarm.evaluation.covframe import ELLIPSE_SCALE_95, covariance_ellipse
from tagswarm.evaluation.localised import LOCALISED_HOLD_S, LOCALISED_M
from tagswarm.protocol import messages as m
from tagswarm.protocol.geometry import Pose2, se2_compose, se2_inverse
from tagswarm.protocol.keys import Keys
from tagswarm.protocol.layout import arena_to_map, footprint_radius, start_poses, wall_boxes
from tagswarm.protocol.scenario import Scenario
from tagswarm.runtime import streams
from tagswarm.view.events import MARKER_TTL_S, EventLog
from tagswarm.view.robotview import RobotView, Sighting

__all__ = ["EDGE_TTL_NS", "ELLIPSE_SCALE_95", "MAX_ROBOTS", "RobotView", "ViewState", "covariance_ellipse"]

#: An observation older than this (simulation time) no longer draws a "sees" line.
EDGE_TTL_NS: Final = 1_000_000_000
#: Robots tracked at most: ids come from the wire, so garbage must not grow the state without bound.
MAX_ROBOTS: Final = 256
#: Wall-clock window (s) over which the real-time factor is measured.
RTF_WINDOW_S: Final = 3.0


def _num(x: float, digits: int = 6) -> float | None:
    """A JSON-safe float (``None`` for NaN/inf), rounded to ``digits`` decimals (1 µm for metres)."""
    return round(x, digits) if math.isfinite(x) else None


class ViewState:
    """Folds messages into the view's state; see the module docstring.

    ``keys`` is the run being watched: robot-keyed messages whose payload names
    another robot than their key are rejected (``mismatched_key``).  Every reject
    is counted in :attr:`rejects` (shared with the node's decode step).
    """

    def __init__(self, scenario: Scenario, keys: Keys, rejects: streams.RejectCounter | None = None) -> None:
        self.s = scenario
        self.keys = keys
        self.rejects = rejects or streams.RejectCounter()
        self.a2m: Pose2 = arena_to_map(scenario)
        starts = start_poses(scenario)
        #: Start pose of each scenario robot in the map frame: where its odom frame begins.
        self.start_map: dict[int, Pose2] = {rid: se2_compose(self.a2m, starts[i])
                                            for i, rid in enumerate(scenario.robot_ids)}
        self.epoch = 0
        self.version = 0
        self.resets = 0
        self._clear()

    # ------------------------------------------------------------------ lifecycle
    def _clear(self) -> None:
        self.run_id: str | None = None
        self.clock_mode: str | None = None
        self.step = -1
        self.tick_ns = -1
        self.sim_ns = 0
        self.map_stamp_ns = -1
        self.origin_id: int | None = None
        self.robots: dict[int, RobotView] = {}
        self.sightings: dict[tuple[int, str, int], Sighting] = {}
        self.processes: dict[str, dict[str, Any]] = {}
        self.events = EventLog()
        self._rtf_samples: deque[tuple[float, int]] = deque()

    def reset(self, why: str) -> None:
        """Forget the current run (a new one started); bumps :attr:`epoch`."""
        self._clear()
        self.epoch += 1
        self.resets += 1
        self.last_reset_reason = why
        self._changed()

    def _changed(self) -> None:
        self.version += 1

    def _robot(self, rid: int) -> RobotView | None:
        view = self.robots.get(rid)
        if view is None:
            if len(self.robots) >= MAX_ROBOTS:
                self.rejects.reject("too_many_robots", f"robot {rid}: already tracking {MAX_ROBOTS}")
                return None
            view = self.robots[rid] = RobotView(rid)
        return view

    def _key_matches(self, key: str | None, rid: int) -> bool:
        if key is None:
            return True
        if self.keys.robot_id_of(key) == rid:
            return True
        self.rejects.reject("mismatched_key", f"{key} carries robot {rid}")
        return False

    # ------------------------------------------------------------------ input
    def apply(self, msg: m.Msg, key: str | None = None, now_s: float = 0.0) -> None:
        """Fold one decoded message in.  ``key`` is the Zenoh key it came on (checked
        against the payload's robot id when given); ``now_s`` a monotonic wall time
        used only for the real-time factor."""
        if isinstance(msg, m.Tick):
            self._on_tick(msg, now_s)
        elif isinstance(msg, m.GroundTruthPose):
            self._on_truth(msg, key)
        elif isinstance(msg, m.Correction):
            self._on_correction(msg, key)
        elif isinstance(msg, m.GlobalMap):
            self._on_map(msg)
        elif isinstance(msg, m.OdometryEstimate):
            self._on_odometry(msg, key)
        elif isinstance(msg, m.RelativeObservation):
            self._on_observation(msg, key)
        elif isinstance(msg, m.AgentStatus):
            self._on_status(msg, key)
        elif isinstance(msg, m.Relocalisation):
            self._on_relocalisation(msg)
        elif isinstance(msg, m.WorldCommand):
            self._on_world_command(msg)
        else:
            self.rejects.reject("unexpected_type", f"{type(msg).__name__} on {key}")

    def _on_tick(self, t: m.Tick, now_s: float) -> None:
        if self.run_id is not None and t.run_id != self.run_id:
            self.reset(f"new run {t.run_id} (was {self.run_id})")
        elif self.tick_ns >= 0 and t.stamp_ns < self.tick_ns:
            self.reset(f"clock went back from {self.tick_ns} to {t.stamp_ns} ns")
        self.run_id, self.clock_mode, self.step = t.run_id, t.mode, t.step
        self.tick_ns = t.stamp_ns
        self.sim_ns = max(self.sim_ns, t.stamp_ns)
        self._rtf_samples.append((now_s, t.stamp_ns))
        while len(self._rtf_samples) > 2 and now_s - self._rtf_samples[1][0] >= RTF_WINDOW_S:
            self._rtf_samples.popleft()
        self._changed()

    def _on_truth(self, t: m.GroundTruthPose, key: str | None) -> None:
        if not self._key_matches(key, t.robot_id):
            return
        view = self._robot(t.robot_id)
        if view is None:
            return
        pose = se2_compose(self.a2m, (t.x_m, t.y_m, t.yaw_rad))
        view.truth = pose
        view.truth_history.append((t.stamp_ns, pose))
        error = self._fused_error(view, t.stamp_ns)
        view.localised_clock.add(t.stamp_ns, error is not None and error < LOCALISED_M)
        self._advance(t.stamp_ns)

    @staticmethod
    def _fused_error(view: RobotView, stamp_ns: int) -> float | None:
        """Position error (m) of the fused estimate standing at ``stamp_ns`` against the truth
        at its own stamp; None without one at most :data:`~tagswarm.evaluation.localised.LOCALISED_HOLD_S` old."""
        if view.fused is None or abs(stamp_ns - view.fused_stamp_ns) > LOCALISED_HOLD_S * 1e9:
            return None
        truth = view.truth_at(view.fused_stamp_ns)
        if truth is None:
            return None
        return math.hypot(view.fused[0] - truth[0], view.fused[1] - truth[1])

    def _on_correction(self, c: m.Correction, key: str | None) -> None:
        if not self._key_matches(key, c.robot_id):
            return
        view = self._robot(c.robot_id)
        if view is None:
            return
        # the pose's own time (Correction.pose_stamp_ns), against which its error is measured
        at_ns = c.pose_time_ns
        if at_ns < view.fused_stamp_ns or (at_ns == view.fused_stamp_ns and view.fused_source == "map"):
            return  # not newer than what is shown (on a tie the map's copy of the estimate stays)
        view.localised = c.localised
        if c.localised:
            view.fused = (c.x_m, c.y_m, c.yaw_rad)
            view.fused_cov = tuple(c.cov)
            view.fused_stamp_ns, view.fused_source = at_ns, "correction"
            view.last_fix_ns = max(view.last_fix_ns, c.last_fix_ns)
        self._advance(c.stamp_ns)

    def _on_map(self, g: m.GlobalMap) -> None:
        if self.tick_ns < 0 and 0 <= g.stamp_ns < self.map_stamp_ns:
            # without a world clock (e.g. a replay of the map alone) the map is the clock
            self.reset(f"map clock went back from {self.map_stamp_ns} to {g.stamp_ns} ns")
        if g.stamp_ns < self.map_stamp_ns:
            return  # a stale map (late delivery): never draw an older estimate over a newer one
        self.map_stamp_ns, self.origin_id = g.stamp_ns, g.origin_id
        for e in g.robots:
            view = self._robot(e.robot_id)
            if view is None:
                continue
            view.alive = e.alive
            if not e.localised:  # in the map, but the server does not vouch for it: not shown as localised
                view.localised = False
            elif e.pose_time_at(g.stamp_ns) >= view.fused_stamp_ns:  # on a tie the map wins: it is what
                view.fused = (e.x_m, e.y_m, e.yaw_rad)                      # the test compares with
                view.fused_cov = tuple(e.cov)
                view.fused_stamp_ns, view.fused_source = e.pose_time_at(g.stamp_ns), "map"
                view.localised = True
        self._advance(g.stamp_ns)

    def _on_odometry(self, o: m.OdometryEstimate, key: str | None) -> None:
        if not self._key_matches(key, o.robot_id):
            return
        view = self._robot(o.robot_id)
        if view is None:
            return
        start = self.start_map.get(o.robot_id)
        if start is not None:  # a robot the scenario does not know has no start pose to drift from
            view.odom = se2_compose(start, (o.x_m, o.y_m, o.yaw_rad))
        view.odom_distance_m = o.distance_m
        self._advance(o.stamp_ns)

    def _on_observation(self, ob: m.RelativeObservation, key: str | None) -> None:
        if not self._key_matches(key, ob.robot_id):
            return
        if self._robot(ob.robot_id) is None:
            return
        k = (ob.robot_id, ob.target_kind, ob.target_id)
        old = self.sightings.get(k)
        if old is None or ob.stamp_ns >= old.stamp_ns:
            if old is None and len(self.sightings) >= MAX_ROBOTS * 8:
                self.rejects.reject("too_many_sightings", f"observation of {ob.target_kind} {ob.target_id}")
                return
            self.sightings[k] = Sighting(ob.robot_id, ob.target_kind, ob.target_id, ob.stamp_ns, ob.x_m, ob.y_m)
        self._advance(ob.stamp_ns)

    def _on_status(self, st: m.AgentStatus, key: str | None) -> None:
        if st.role == "agent" and st.robot_id is not None:
            if not self._key_matches(key, st.robot_id):
                return
            view = self._robot(st.robot_id)
            if view is None:
                return
            view.mode = st.mode
            view.counters = dict(st.counters)
        else:
            self.processes[st.role] = {"mode": st.mode, "stamp_s": _num(st.stamp_ns / 1e9, 3),
                                       "counters": dict(st.counters)}
        self._advance(st.stamp_ns)

    def _on_relocalisation(self, r: m.Relocalisation) -> None:
        view = self._robot(r.robot_id)
        if view is None:
            return
        view.relocalisations += 1
        self.events.relocalisation(r)
        self._advance(r.stamp_ns)

    def _on_world_command(self, c: m.WorldCommand) -> None:
        view = self._robot(c.robot_id)
        if view is None:
            return
        # a tool that does not know the simulation time stamps 0: it happens now
        self.events.kidnap(c, c.stamp_ns if c.stamp_ns > 0 else self.sim_ns, self.a2m, view.truth)
        self._changed()

    def _advance(self, stamp_ns: int) -> None:
        if self.tick_ns < 0:  # no world clock seen: the newest stamp of anything is the time
            self.sim_ns = max(self.sim_ns, stamp_ns)
        self._changed()

    # ------------------------------------------------------------------ output
    @property
    def rtf(self) -> float | None:
        """Simulated seconds per wall second over the last ~:data:`RTF_WINDOW_S` (None until measurable)."""
        if len(self._rtf_samples) < 2:
            return None
        (w0, s0), (w1, s1) = self._rtf_samples[0], self._rtf_samples[-1]
        if w1 - w0 < 0.2:
            return None
        return (s1 - s0) / 1e9 / (w1 - w0)

    def sees(self) -> list[dict[str, Any]]:
        """Current "who sees whom": observations newer than :data:`EDGE_TTL_NS` before now."""
        out = []
        for sg in sorted(self.sightings.values(), key=lambda s: (s.observer, s.kind, s.target)):
            age = self.sim_ns - sg.stamp_ns
            if age <= EDGE_TTL_NS:
                out.append({"from": sg.observer, "kind": sg.kind, "to": sg.target, "age_s": _num(max(age, 0) / 1e9, 3),
                            "rel": [_num(sg.x_m), _num(sg.y_m)]})
        return out

    def _robot_json(self, v: RobotView) -> dict[str, Any]:
        fused = None
        error = None
        if v.fused is not None:
            a, b, ang = covariance_ellipse(v.fused_cov, yaw_rad=v.fused[2]) if len(v.fused_cov) == 9 \
                else (0.0, 0.0, 0.0)
            sigma_yaw = math.sqrt(max(v.fused_cov[8], 0.0)) if len(v.fused_cov) == 9 else 0.0
            fused = {"x": _num(v.fused[0]), "y": _num(v.fused[1]), "yaw": _num(v.fused[2]),
                     "stamp_ns": v.fused_stamp_ns, "source": v.fused_source,
                     "ellipse": [_num(a), _num(b), _num(ang)], "sigma_yaw": _num(sigma_yaw)}
            truth = v.truth_at(v.fused_stamp_ns)
            if truth is not None:
                error = _num(math.hypot(v.fused[0] - truth[0], v.fused[1] - truth[1]))
        fix_age = (self.sim_ns - v.last_fix_ns) / 1e9 if v.last_fix_ns > 0 else None
        return {
            "id": v.robot_id,
            "truth": None if v.truth is None else [_num(c) for c in v.truth],
            "fused": fused,
            "localised": v.localised,
            "odom": None if v.odom is None else [_num(c) for c in v.odom],
            "odom_distance_m": _num(v.odom_distance_m, 3),
            "error_m": error,
            "fix_age_s": None if fix_age is None else _num(max(fix_age, 0.0), 2),
            "mode": v.mode,
            "alive": v.alive,
            "frames": v.counters.get("frames_processed"),
            "fixes": v.counters.get("fixes"),
            "searches": v.counters.get("searches"),
            "time_localised": None if (share := v.localised_clock.share) is None else _num(share, 4),
            "relocalisations": v.relocalisations,
        }

    def snapshot(self) -> dict[str, Any]:
        """Everything that moves, JSON-ready (see docs in tagswarm/view/view.py for the page protocol)."""
        rtf = self.rtf
        return {
            "type": "state",
            "epoch": self.epoch,
            "version": self.version,
            "run": self.keys.run,
            "run_id": self.run_id,
            "clock": self.clock_mode,
            "step": self.step,
            "sim_ns": self.sim_ns,
            "rtf": None if rtf is None else _num(rtf, 3),
            "origin_id": self.origin_id,
            "map_stamp_ns": self.map_stamp_ns if self.map_stamp_ns >= 0 else None,
            "robots": [self._robot_json(self.robots[r]) for r in sorted(self.robots)],
            "sees": self.sees(),
            "events": self.events.to_json(self.sim_ns),
            "event_counts": {"relocalisations": self.events.relocalisations, "kidnaps": self.events.kidnaps},
            "processes": self.processes,
            "rejected": dict(sorted(self.rejects.counts.items())),
        }

    def scene(self) -> dict[str, Any]:
        """The static arena of the scenario (ARENA frame) and where the map frame sits in it."""
        a = self.s.arena
        r = self.s.robot
        walls = [[_num(c[0]), _num(c[1]), _num(h[0]), _num(h[1])] for c, h in wall_boxes(a)]
        obstacles = [[_num(o.x_m), _num(o.y_m), _num(o.yaw_rad), _num(o.size_x_m), _num(o.size_y_m)]
                     for o in a.obstacles]
        landmarks = [[lm.id, _num(lm.x_m), _num(lm.y_m), _num(lm.yaw_rad), _num(lm.size_m)] for lm in self.s.landmarks]
        return {
            "type": "scene",
            "scenario": self.s.name,
            "run": self.keys.run,
            "arena": {"size_x_m": a.size_x_m, "size_y_m": a.size_y_m, "wall_thickness_m": a.wall_thickness_m,
                      "walls": walls, "obstacles": obstacles},
            "landmarks": landmarks,
            "map_in_arena": [_num(c) for c in se2_inverse(self.a2m)],
            "robot": {"length_m": r.chassis_length_m, "width_m": r.chassis_width_m,
                      "radius_m": _num(footprint_radius(r))},
            "robot_ids": list(self.s.robot_ids),
            "origin_id": self.s.map.origin_id,
            "ellipse": "95 %",
            "localised_m": LOCALISED_M,
            "marker_ttl_s": MARKER_TTL_S,
        }
