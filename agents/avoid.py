"""Local collision avoidance for missions and run-time goals (pure code, no I/O).

Method: a dynamic-window sampler (Fox, Burgard & Thrun 1997).  Each control
cycle the path the go-to-goal controller is about to drive over ``horizon_s``
is simulated (closed loop) against the other robots, moving at their estimated
velocity for ``NEIGHBOUR_PREDICT_S`` and then standing, and against the static
boxes.  If it never comes closer than the clearance, the go-to-goal command is
used unchanged: robots that merely pass each other (the paper's patrols 0.9 m
apart) never swerve.  Otherwise a grid of constant (v, w) twists is rolled out;
twists whose path would come closer than the clearance (or closer than now,
when already inside it) are inadmissible, and the best of the rest is taken by
progress, room kept beyond the clearance (``SOFT_GAP_M``; never more than the
goal itself has), passing other robots on the preferred side, and smoothness.
While an obstacle stands on the straight way to the goal, progress is measured
towards a point past it on the preferred side (a tangent to its circle, or the
box's corner), so a robot drives around a robot or a shelf rather than creeping
up to it.  Turning in place is always admissible (the footprint is a circle
about ``base_link``), so nobody's searching rotation is ever stopped.

Deadlocks: every robot prefers to keep the others on its left (``side`` -1),
so two robots driving at each other head-on both veer right and pass; a robot whose
right side a wall or obstacle closes is passed on its left.  A robot
that makes no progress while avoiding for ``stall_s`` backs away for a while if
a robot with a lower id is close (priority by id: it goes first; after ``MAX_YIELDS``
at one place it stops giving way there: that robot is not leaving), else tries
the other side (or, given ``replan``, first looks for a way round the room: a shelf
whose near end a robot blocks is driven round its far end; :mod:`tagswarm.agents.route`).
The stall clock is restarted by progress, or by a way that stays clear for ``CLEAR_RESET_S``:
a go-to-goal turn that is clear and an avoiding turn back can alternate every cycle on the spot.
A goal that another robot stands on (or that lies inside a
wall's footprint) counts as reached as close as the clearance allows
(:meth:`Avoider.goal_slack`); near a goal that is itself close to a wall the
wall clearance shrinks to what the goal needs, so such a goal is reached.

Frames and units: everything in the map frame, metres, radians, seconds;
poses are (x_m, y_m, yaw_rad) of base_link.  Deterministic: no clocks, no
unordered iteration, ties go to the first candidate.

The obstacles (:class:`Box`, :class:`Neighbour`, :func:`static_boxes`, :func:`box_distance`)
and the paths rolled out (:func:`closed_loop`, :func:`rollout`) live in
:mod:`tagswarm.agents.avoidgeom`; this module re-exports them.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from tagswarm.agents.avoidgeom import Arr, Box, Neighbour, box_distance, closed_loop, rollout, static_boxes
from tagswarm.protocol.geometry import Pose2

__all__ = ["CLEAR_RESET_S", "MAX_SIGMA_MARGIN_M", "MAX_YIELDS", "NEIGHBOUR_PREDICT_S", "PASS_RANGE_M",
           "PROGRESS_EPS_M", "REROUTE_PLACE_M", "SOFT_GAP_M", "STATIC_MIN_GAP_M", "STEP_S", "YIELD_PLACE_M",
           "YIELD_SPEED_M_S",
           "Avoider", "Box", "Neighbour", "box_distance", "closed_loop", "rollout", "static_boxes"]

Mask = NDArray[np.bool_]
STEP_S = 0.1  # rollout resolution: at 0.6 m/s closing speed 6 cm between samples
SOFT_GAP_M = 0.1  # room beyond the clearance that alternatives try to keep
STATIC_MIN_GAP_M = 0.01  # a goal beside a wall may bring the footprint this close to it
PROGRESS_EPS_M = 0.05  # progress smaller than this over stall_s is a stall
PASS_RANGE_M = 0.5  # passing another robot closer than this (beyond the clearance) on the wrong side costs
# the own position sigma's multiple kept from walls and obstacles on top of the clearance is capped here: a robot
# lost by metres still fits through a 1.2 m door (2 x (footprint 0.19 + clearance 0.1 + 0.2) = 0.98 m)
MAX_SIGMA_MARGIN_M = 0.2
NEIGHBOUR_PREDICT_S = 1.0  # others keep their velocity this long, then stand (they turn at waypoints, avoid too)
YIELD_S = 2.5  # how long a stalled robot backs away from a jam for a robot with a lower id
YIELD_SPEED_M_S = 0.12
# giving way twice at one place without getting past it: the robot given way to is not leaving (it holds
# station), so the next stall looks for a way round instead (a store of 14 robots: a patrol backed away from a
# station keeper at a rack's end every 8.5 s for 50 s)
MAX_YIELDS = 2
YIELD_PLACE_M = 1.0  # moving this far from where it first gave way ends a robot's run of yields
# a clear way restarts the stall clock only once it has stayed clear this long: a go-to-goal turn whose path
# is clear and an avoiding turn back can alternate every cycle on the spot (test_avoid.py: a robot beside a door
# held by a station keeper did so from 10 s to the end, each clear cycle restarting the clock)
CLEAR_RESET_S = 1.0
# a stall within this of where the last stall found a way round: that way did not get the robot moving (a patrol
# on the clearance's edge beside a station keeper, its way round starting along that edge, where standing costs
# less than passing: an office's patrol stood there from 21 s to the end), so it flips side and goes assertive
REROUTE_PLACE_M = 0.2


@dataclass
class Avoider:
    """Per-robot avoidance state; :meth:`command` once per control cycle."""

    footprint_m: float
    clearance_m: float
    horizon_s: float = 2.0
    robot_id: int = 0
    stall_s: float = 6.0
    side: int = -1  # preferred turn while avoiding: -1 right (pass on the right), +1 left
    # walls and obstacles are kept this many of the robot's own position sigma farther (see command)
    sigma_k: float = 0.0
    # called on a stall before trying the other side: (pose, target, neighbours, boxes) -> whether it found a way
    # round (tagswarm.agents.route); the caller then steers by that way
    replan: Callable[[Pose2, tuple[float, float], Sequence[Neighbour], Sequence[Box]], bool] | None = field(
        default=None, repr=False)
    reroutes: int = 0
    avoiding: bool = False
    side_flips: int = 0
    yields: int = 0
    cycles_avoiding: int = 0
    _yield_streak: int = 0
    _yield_at: tuple[float, float] = (math.inf, math.inf)
    _rerouted_at: tuple[float, float] = (math.inf, math.inf)
    _yield_until: float = -math.inf
    _assertive_until: float = -math.inf
    _last_w: float = 0.0
    _best_dist: float = math.inf
    _best_t: float = 0.0
    _clear_since: float = math.inf
    _target: tuple[float, float] | None = field(default=None, repr=False)
    _margin_m: float = 0.0  # this cycle's extra room from walls and obstacles

    # ------------------------------------------------------------------ geometry
    def _required(self, nb: Neighbour) -> float:
        return self.footprint_m + nb.radius_m + self.clearance_m

    def _static_required(self, b: Box, goal: tuple[float, float]) -> float:
        """Room to keep from a box: footprint + clearance + this cycle's margin for the robot's own
        position uncertainty, less if the goal itself is closer to it."""
        full = self.footprint_m + self.clearance_m + self._margin_m
        at_goal = float(box_distance(b, goal[0], goal[1]))
        return max(self.footprint_m + STATIC_MIN_GAP_M, min(full, at_goal - STATIC_MIN_GAP_M))

    def goal_slack(self, goal: tuple[float, float], neighbours: Sequence[Neighbour], boxes: Sequence[Box]) -> float:
        """Extra goal tolerance (m) when the goal cannot be reached with the clearance kept: a robot
        stands on it (then the nearest admissible point is the goal) or it lies within a wall."""
        slack = 0.0
        for nb in neighbours:
            gap = math.hypot(goal[0] - nb.x_m, goal[1] - nb.y_m) - self._required(nb)
            if gap < 0:
                slack = max(slack, -gap + STATIC_MIN_GAP_M)
        for b in boxes:
            gap = float(box_distance(b, goal[0], goal[1])) - self.footprint_m - STATIC_MIN_GAP_M
            if gap < 0:
                slack = max(slack, -gap + STATIC_MIN_GAP_M)
        return slack

    def _gaps(self, x: Arr, y: Arr, times: Arr, pose: Pose2, goal: tuple[float, float],
              neighbours: Sequence[Neighbour], boxes: Sequence[Box], reach_m: float) -> tuple[Arr, Mask, Arr]:
        """For each rollout: how far (0..1 of SOFT_GAP_M) it cuts into the soft room beyond the
        clearance (never more than the goal itself needs: a goal near something is approached
        without penalty), whether it stays admissible (never inside the clearance, or never
        deeper inside than it is now), and how much (0..1, by closeness) it passes another
        robot on the side not preferred (``side`` -1: keep the others on the left)."""
        n = x.shape[0]
        tight: Arr = np.zeros(n)
        wrong_side: Arr = np.zeros(n)
        ok: Mask = np.ones(n, bool)
        gx, gy = goal[0] - pose[0], goal[1] - pose[1]
        norm = math.hypot(gx, gy)
        gx, gy = (gx / norm, gy / norm) if norm > 1e-9 else (math.cos(pose[2]), math.sin(pose[2]))
        rows = np.arange(n)

        def account(gap: Arr, gap0: float, gap_goal: float) -> None:
            nonlocal tight, ok
            soft = min(SOFT_GAP_M, max(gap_goal, 0.0))
            tight = np.asarray(np.maximum(tight, np.maximum(soft - gap, 0.0) / SOFT_GAP_M), np.float64)
            ok &= gap >= min(0.0, gap0) - 1e-6

        for nb in neighbours:
            req = self._required(nb)
            gap0 = math.hypot(pose[0] - nb.x_m, pose[1] - nb.y_m) - req
            if gap0 > reach_m + math.hypot(nb.vx_m_s, nb.vy_m_s) * NEIGHBOUR_PREDICT_S:
                continue  # cannot come near within the horizon
            ahead = np.minimum(times, NEIGHBOUR_PREDICT_S)
            qx, qy = nb.x_m + nb.vx_m_s * ahead, nb.y_m + nb.vy_m_s * ahead
            dist = np.hypot(x - qx[None, :], y - qy[None, :])
            closest = dist.argmin(axis=1)
            gap = dist[rows, closest] - req
            account(gap, gap0, math.hypot(goal[0] - nb.x_m, goal[1] - nb.y_m) - req)
            # which side of us it is at the closest approach, seen along the way to the goal
            cross = gx * (qy[closest] - y[rows, closest]) - gy * (qx[closest] - x[rows, closest])
            near = np.clip((PASS_RANGE_M - gap) / PASS_RANGE_M, 0.0, 1.0)
            wrong = (self.side * cross >= 0) & (closest > 0)  # closest at the start: it is behind us
            wrong_side = np.maximum(wrong_side, np.where(wrong, near, 0.0))
        for b in boxes:
            req = self._static_required(b, goal)
            gap0 = float(box_distance(b, pose[0], pose[1])) - req
            if gap0 > reach_m:
                continue
            account(box_distance(b, x, y).min(axis=1) - req, gap0, float(box_distance(b, goal[0], goal[1])) - req)
        return tight, ok, wrong_side

    # ------------------------------------------------------------------ control
    def command(self, *, pose: Pose2, target: tuple[float, float], steer: Callable[[Pose2], tuple[float, float]],
                v_max: float, w_max: float, neighbours: Sequence[Neighbour], boxes: Sequence[Box],
                t_s: float, pos_sigma_m: float | None = None, round_boxes: bool = True,
                round_robots: bool = True) -> tuple[float, float]:
        """The twist (v_m_s, w_rad_s) to drive towards ``target`` from ``pose``; ``steer`` is the
        go-to-goal controller (pose -> twist), whose command is kept whenever the path it is about
        to drive is clear (see the module docstring).  ``round_boxes`` False: a box on the straight
        way is not driven round by its corner (the target is a planned way's carrot, which already
        goes round it: the corner on the preferred side led a robot away from its way out of a pocket);
        ``round_robots`` False: nor a robot by its tangent, nor is passing one on the side not preferred
        charged (the carrot's way goes round the robots too: the tangent on the preferred side of a station
        keeper beside a wall pointed into the wall, and a patrol stood between them for 15 s).
        ``pos_sigma_m`` is the robot's own
        position sigma (m, None if unknown): walls and obstacles, whose geometry is known exactly,
        are kept ``sigma_k`` of it farther (at most ``MAX_SIGMA_MARGIN_M``), so a robot that slipped
        out of everyone's view does not drive into a shelf it believes 20 cm away.  The other
        robots are not: their poses come from the same map, and the swarm's margin to each other
        is what lets a crowd move."""
        sigma = pos_sigma_m if pos_sigma_m is not None and math.isfinite(pos_sigma_m) else 0.0
        self._margin_m = min(self.sigma_k * max(sigma, 0.0), MAX_SIGMA_MARGIN_M)
        times: Arr = np.arange(1, round(self.horizon_s / STEP_S) + 1, dtype=np.float64) * STEP_S
        dist = math.hypot(target[0] - pose[0], target[1] - pose[1])
        reach = v_max * self.horizon_s + SOFT_GAP_M
        nominal = steer(pose)
        v0, w0 = nominal
        xn, yn, thn = closed_loop(pose, steer, times)
        _, ok, _ = self._gaps(xn, yn, times, pose, target, neighbours, boxes, reach)
        if self._target != target:
            self._target, self._best_dist, self._best_t = target, dist, t_s
        if math.hypot(pose[0] - self._yield_at[0], pose[1] - self._yield_at[1]) > YIELD_PLACE_M:
            self._yield_streak, self._yield_at = 0, (math.inf, math.inf)
        if ok[0]:
            self.avoiding = False
            self._last_w = w0
            self._clear_since = min(self._clear_since, t_s)
            if t_s - self._clear_since >= CLEAR_RESET_S or dist < self._best_dist - PROGRESS_EPS_M:
                self._best_dist, self._best_t = dist, t_s
            return nominal
        self._clear_since = math.inf
        self.avoiding = True
        self.cycles_avoiding += 1
        if dist < self._best_dist - PROGRESS_EPS_M:
            self._best_dist, self._best_t = dist, t_s
        elif t_s - self._best_t > self.stall_s:
            # stuck: back away if a robot with a lower id is in the jam (it goes first), unless that was
            # tried MAX_YIELDS times here already; otherwise look for a way round, or try the other side,
            # ignoring the soft costs for a while
            if self._yield_streak < MAX_YIELDS and any(
                    nb.robot_id < self.robot_id and math.hypot(pose[0] - nb.x_m, pose[1] - nb.y_m)
                    - self._required(nb) < PASS_RANGE_M for nb in neighbours):
                self._yield_until = t_s + YIELD_S
                self.yields += 1
                if self._yield_streak == 0:
                    self._yield_at = (pose[0], pose[1])
                self._yield_streak += 1
            elif (self.replan is not None and math.hypot(pose[0] - self._rerouted_at[0], pose[1] - self._rerouted_at[1])
                  > REROUTE_PLACE_M and self.replan(pose, target, neighbours, boxes)):
                self.reroutes += 1
                self._rerouted_at = (pose[0], pose[1])
            else:
                self.side = -self.side
                self.side_flips += 1
                self._assertive_until = t_s + self.stall_s
            self._best_dist, self._best_t = math.inf, t_s  # a fresh stall_s from the next cycle
        if t_s < self._yield_until:
            return self._back_away(pose, neighbours, boxes, target, times, w_max, reach)
        v_top = min(v_max, 0.8 * dist)
        vs = np.linspace(0.0, v_top, 6)
        ws = np.linspace(-w_max, w_max, 13)
        v = np.concatenate([np.repeat(vs, len(ws)), [v0]])
        w = np.concatenate([np.tile(ws, len(vs)), [w0]])
        x, y, th = rollout(pose, v[:-1], w[:-1], times, dist)
        x, y, th = np.vstack([x, xn]), np.vstack([y, yn]), np.vstack([th, thn])
        tight, ok, wrong_side = self._gaps(x, y, times, pose, target, neighbours, boxes, reach)
        if self._margin_m > 0.0 and not ok[-1] and not np.any(ok[:-1] & (v[:-1] > 0.0)):
            # the margin leaves no way forward (a waypoint near a wall, the way along it bulging towards it on
            # the turn): drop it this cycle, the clearance itself still holds
            self._margin_m = 0.0
            tight, ok, wrong_side = self._gaps(x, y, times, pose, target, neighbours, boxes, reach)
        # turning in place never brings the footprint closer to anything (the last row is the
        # controller's path, which may turn first and drive later: it stays as judged)
        ok[:-1] |= v[:-1] == 0.0
        scale = max(v_max * self.horizon_s, 1e-6)
        aim = self._via(pose, target, neighbours if round_robots else (), boxes, reach, round_boxes) or target
        end_dist = np.hypot(aim[0] - x[:, -1], aim[1] - y[:, -1])
        off = np.arctan2(aim[1] - y[:, -1], aim[0] - x[:, -1]) - th[:, -1]
        heading = np.abs((off + math.pi) % (2.0 * math.pi) - math.pi)
        soft = 0.0 if t_s < self._assertive_until else 1.0
        cost = ((end_dist - math.hypot(aim[0] - pose[0], aim[1] - pose[1])) / scale  # progress to the goal
                + 0.1 * heading / math.pi
                + soft * 0.6 * tight  # room kept from everything
                # a carrot's way round the robots has chosen the side to pass each on: preferring the other one
                # left a patrol on the edge of a station keeper's clearance, its way round starting along it
                + soft * (0.3 if round_robots else 0.0) * wrong_side
                # turning to the unpreferred side while driving: turning on the spot passes nobody (with it, a patrol
                # facing away from its way round a station keeper beside a wall stood still rather than turn back)
                + 0.08 * np.maximum(0.0, -self.side * w) * (v > 0.0) / max(w_max, 1e-6)
                + 0.05 * np.abs(w - self._last_w) / max(w_max, 1e-6))
        cost = np.where(ok, cost, np.inf)
        best = int(np.argmin(cost))  # first minimum: ties resolve the same way every run
        self._last_w = float(w[best])
        return float(v[best]), float(w[best])

    def _side_free(self, nb: Neighbour, ux: float, uy: float, side: int, boxes: Sequence[Box]) -> bool:
        """Whether a robot going along (ux, uy) past ``nb`` on ``side`` keeps its clearance from the walls and
        obstacles there: a station keeper beside a wall is passed on its open side, whatever the preference."""
        r = self._required(nb)
        x, y = nb.x_m - side * r * uy, nb.y_m + side * r * ux
        return all(float(box_distance(b, x, y)) >= self.footprint_m + self.clearance_m for b in boxes)

    def _via(self, pose: Pose2, target: tuple[float, float], neighbours: Sequence[Neighbour],
             boxes: Sequence[Box], reach: float, round_boxes: bool = True) -> tuple[float, float] | None:
        """Where to head instead of the goal when the straight way to it is blocked within reach:
        past the first obstacle on it, on the preferred side (a tangent to the robot's circle, or
        the box's corner), so that a robot standing on the way or a shelf across it is driven
        around rather than approached head-on.  None when the way is clear, or the goal itself lies
        in the obstacle's room (it is approached as far as the clearance lets)."""
        px, py = pose[0], pose[1]
        gx, gy = target[0] - px, target[1] - py
        length = math.hypot(gx, gy)
        if length < 1e-9:
            return None
        ux, uy = gx / length, gy / length
        first, heading = math.inf, 0.0
        for nb in neighbours:
            rho = self._required(nb) + SOFT_GAP_M
            cx, cy = nb.x_m - px, nb.y_m - py
            if math.hypot(target[0] - nb.x_m, target[1] - nb.y_m) <= rho:
                continue
            along = cx * ux + cy * uy
            off = abs(cx * uy - cy * ux)
            if off >= rho or along < -rho or along > min(length, reach) + rho:
                continue
            entry = along - math.sqrt(rho * rho - off * off)
            if entry < first:
                d = math.hypot(cx, cy)
                bearing = math.atan2(cy, cx)
                side = self.side
                if not self._side_free(nb, ux, uy, side, boxes) and self._side_free(nb, ux, uy, -side, boxes):
                    side = -side
                # tangent on that side; from inside the room, along its edge
                heading = bearing + side * (math.asin(rho / d) if d > rho else math.pi / 2)
                first = entry
        steps: Arr = np.arange(0.0, min(length, reach) + 1e-9, 0.05, dtype=np.float64)
        sx, sy = px + ux * steps, py + uy * steps
        for b in boxes if round_boxes else ():
            rho = self._static_required(b, target) + SOFT_GAP_M
            if float(box_distance(b, target[0], target[1])) <= rho:
                continue
            hit = np.nonzero(box_distance(b, sx, sy) < rho)[0]
            if len(hit) == 0 or steps[hit[0]] >= first:
                continue
            first = float(steps[hit[0]])
            c, s_ = math.cos(b.yaw_rad), math.sin(b.yaw_rad)
            goal_bearing = math.atan2(gy, gx)
            # the corner furthest round on the preferred side (side -1: the right, clockwise, like the tangent
            # to a robot above): choosing the one furthest round the other way sent a robot going through a
            # door to the far end of the wall beside it, against the room's wall
            best_off = -math.inf
            for kx, ky in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
                lx, ly = kx * (b.half_x_m + rho), ky * (b.half_y_m + rho)
                cx, cy = b.x_m + c * lx - s_ * ly - px, b.y_m + s_ * lx + c * ly - py
                bearing = math.atan2(cy, cx)
                rel = (bearing - goal_bearing + math.pi) % (2 * math.pi) - math.pi
                if self.side * rel > best_off:
                    best_off, heading = self.side * rel, bearing
        if not math.isfinite(first):
            return None
        far = max(length, 0.5)
        return px + far * math.cos(heading), py + far * math.sin(heading)

    def _back_away(self, pose: Pose2, neighbours: Sequence[Neighbour], boxes: Sequence[Box],
                   target: tuple[float, float], times: Arr, w_max: float, reach: float) -> tuple[float, float]:
        """Yielding: the admissible twist (reversing allowed) that best opens the distance to the
        robots with a lower id."""
        ws = np.linspace(-w_max, w_max, 13)
        v = np.repeat(np.array([-YIELD_SPEED_M_S, -YIELD_SPEED_M_S / 2, YIELD_SPEED_M_S / 2, YIELD_SPEED_M_S]),
                      len(ws))
        w = np.tile(ws, 4)
        x, y, _ = rollout(pose, v, w, times, YIELD_SPEED_M_S * self.horizon_s)
        _, ok, _ = self._gaps(x, y, times, pose, target, neighbours, boxes, reach)
        gain = np.zeros(len(v))
        for nb in neighbours:
            if nb.robot_id < self.robot_id:
                d0 = math.hypot(pose[0] - nb.x_m, pose[1] - nb.y_m)
                gain += np.hypot(x[:, -1] - nb.x_m, y[:, -1] - nb.y_m) - d0
        cost = np.where(ok, -gain + 0.05 * np.abs(w) / max(w_max, 1e-6), np.inf)
        best = int(np.argmin(cost))
        if not np.isfinite(cost[best]):
            return 0.0, 0.0
        self._last_w = float(w[best])
        return float(v[best]), float(w[best])
