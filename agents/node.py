"""The agent process of one robot (with its base :mod:`tagswarm.agents.nodestate`, the only I/O of ``agents``).

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
from collections.abc import Mapping, Sequence

from tagswarm.agents.avoid import Neighbour
from tagswarm.agents.behaviour import wheel_speeds
from tagswarm.agents.config import build_config
from tagswarm.agents.controller import control_input
from tagswarm.agents.cubepose import PoseEstimate
from tagswarm.agents.intake import CORRECTION_AHEAD_NS
from tagswarm.agents.nodestate import NodeState
from tagswarm.protocol import messages as m
from tagswarm.protocol.geometry import position_sigma_m, se2_compose
from tagswarm.runtime.presence import RunEnd
from tagswarm.runtime.process import serve_node

log = logging.getLogger("tagswarm.agent")


class AgentNode(NodeState):
    """One robot's agent; see the module docstring."""

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
                   avoid_gate_waits=b.gate_waits,
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
