"""A station keeper steps aside for a robot it blocks (pure code, no I/O).

A robot holding station stays where it stands, in a door too: the robots whose way it closes
give way, look for a way round the room (:mod:`tagswarm.agents.route`) and, where there is
none, stall in front of it for the rest of the run (two rooms joined by a 1.2 m door, a
station keeper in it: three patrols drove 3.2–9.4 m in 60 s).  Agents do not know each
other's missions, but a keeper sees the symptom in the map: a robot that came from afar
and has stayed near it, barely moving, for ``BLOCKED_S``.  It then steps aside to the
free spot nearest its station that leaves the line from that robot through the station
open (:func:`aside_spot`), waits there until the robot has gone, and returns to its
station and heading.

Frames and units: map frame, metres, seconds.  Deterministic: candidates are tried in a
fixed order, ties go to the first.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from tagswarm.agents.avoid import Box, Neighbour, box_distance
from tagswarm.protocol.freespace import point_segment_distance
from tagswarm.protocol.geometry import Pose2

log = logging.getLogger(__name__)

NEAR_M = 1.5  # a robot within this of the station may be one it blocks
BLOCKED_S = 10.0  # ... once it has stayed that near this long
STILL_M = 0.5  # ... within this of where it was all that time (a passing robot covers 3 m in 10 s)
TRYING_M = 0.1  # ... yet not parked: it moved this far in the second half of that time
CAME_FROM_M = 2.5  # ... having come from this far (a neighbouring station keeper never did)
HISTORY_S = 30.0  # how far back "came from" looks
APPROACH_RAD = math.radians(60)  # ... heading for the keeper within this (from its last far position)
SAMPLE_S = 0.5  # neighbour positions are kept at this spacing
RINGS_M = (0.7, 1.0, 1.4, 1.8)  # distances of the spots tried from the station, nearest first
BEARINGS = 16
GONE_M = NEAR_M + 0.5  # the robot given way to is gone once this far from the station ...
WAIT_MAX_S = 30.0  # ... or after this long aside: the station is taken again
REACHED_M = 0.05
HEADING_TOL_RAD = 0.05


@dataclass
class MakeWay:
    """One station keeper's stepping aside; :meth:`target` once per control cycle.

    ``keep_m`` is how far a spot must keep the keeper's centre from walls and obstacles (the
    route's keep: footprint, clearance, margin), ``path_m`` how far the way there must (the
    avoidance's: footprint and clearance); ``pass_m`` how far from the blocked robot's line the
    spot must be for it to pass (two footprints and the clearance, plus a margin)."""

    robot_id: int
    keep_m: float
    path_m: float
    pass_m: float
    station: Pose2 | None = None  # where it held, while away
    aside: tuple[float, float] | None = None
    blocked_id: int | None = None
    since_s: float = 0.0  # when it stepped aside
    returning: bool = False
    steps_aside: int = 0
    _history: dict[int, deque[tuple[float, float, float]]] = field(default_factory=dict, repr=False)
    _next_sample_s: float = field(default=-math.inf, repr=False)
    _next_check_s: float = field(default=-math.inf, repr=False)

    def cancel(self) -> None:
        """Forget the station left (a run-time goal sends the keeper elsewhere: it holds where sent)."""
        self.station = self.aside = self.blocked_id = None
        self.returning = False

    def watch(self, t_s: float, neighbours: Sequence[Neighbour]) -> None:
        """Keep the neighbours' positions every ``SAMPLE_S``; called every cycle, also while the keeper
        turns to look around (a robot that is to stall beside it is on its way then)."""
        if t_s < self._next_sample_s:
            return
        self._next_sample_s = t_s + SAMPLE_S
        for n in neighbours:
            h = self._history.setdefault(n.robot_id, deque())
            h.append((t_s, n.x_m, n.y_m))
            while h and h[0][0] < t_s - HISTORY_S:
                h.popleft()

    def blocked(self, t_s: float, here: tuple[float, float],
                neighbours: Sequence[Neighbour]) -> tuple[Neighbour, tuple[float, float]] | None:
        """The neighbour (lowest id first) this keeper at ``here`` blocks, and the unit direction it
        came in (map frame), if any: near it for ``BLOCKED_S``, still within ``STILL_M`` all that
        time though not parked (it moved ``TRYING_M`` in its second half), come from ``CAME_FROM_M`` away heading for
        the keeper (within ``APPROACH_RAD`` from its last far position to where it came within
        ``NEAR_M``), and not past it."""
        for n in sorted(neighbours, key=lambda n: n.robot_id):
            h = self._history.get(n.robot_id)
            if not h or math.dist(here, (n.x_m, n.y_m)) > NEAR_M or t_s - h[0][0] < BLOCKED_S:
                continue
            recent = [(x, y) for t, x, y in h if t >= t_s - BLOCKED_S]
            if any(math.dist(here, p) > NEAR_M or math.dist(p, (n.x_m, n.y_m)) > STILL_M for p in recent):
                continue
            late = [(x, y) for t, x, y in h if t >= t_s - BLOCKED_S / 2]
            if max(math.dist(p, late[0]) for p in late) < TRYING_M:
                continue  # parked: a stalled robot tries again (gives way, the other side) every avoid_stall_s
            points = [(x, y) for _, x, y in h]
            far = [i for i, p in enumerate(points) if math.dist(here, p) >= CAME_FROM_M]
            entry = next((p for p in points[far[-1]:] if math.dist(here, p) <= NEAR_M), None) if far else None
            if entry is None:
                continue
            ax, ay = entry[0] - points[far[-1]][0], entry[1] - points[far[-1]][1]
            bx, by = here[0] - entry[0], here[1] - entry[1]
            norm = math.hypot(ax, ay)
            # a robot that reached its goal beside a keeper was heading elsewhere, or got past it
            ahead = ax * bx + ay * by > math.cos(APPROACH_RAD) * norm * math.hypot(bx, by)
            if ahead and (n.x_m - here[0]) * ax + (n.y_m - here[1]) * ay < 0.0:
                return n, (ax / norm, ay / norm)
        return None

    def target(self, t_s: float, pose: Pose2, neighbours: Sequence[Neighbour],
               boxes: Sequence[Box]) -> tuple[float, float] | float | None:
        """Where this station keeper at ``pose`` goes now: a point (map frame) to drive to, a
        heading (rad) to turn to on the spot, or None to hold station as usual (the neighbours
        as given to :meth:`watch` this cycle)."""
        if self.station is None:
            if t_s < self._next_check_s:
                return None
            self._next_check_s = t_s + SAMPLE_S
            found = self.blocked(t_s, pose[:2], neighbours)
            spot = None if found is None else aside_spot(pose, found[1], neighbours, boxes, self.keep_m,
                                                           self.path_m, self.pass_m)
            if found is None or spot is None:
                return None
            self.station, self.aside, self.blocked_id, self.since_s = pose, spot, found[0].robot_id, t_s
            self.returning, self.steps_aside = False, self.steps_aside + 1
            log.info("robot %d steps aside from its station (%.2f, %.2f) to (%.2f, %.2f) at t=%.1f s: robot %d has "
                     "stalled beside it for %.0f s", self.robot_id, pose[0], pose[1], spot[0], spot[1], t_s,
                     self.blocked_id, BLOCKED_S)
        station = self.station
        if not self.returning:
            other = next((n for n in neighbours if n.robot_id == self.blocked_id), None)
            gone = other is None or math.dist(station[:2], (other.x_m, other.y_m)) > GONE_M
            if not (gone or t_s - self.since_s > WAIT_MAX_S):
                return self.aside
            self.returning, self.since_s = True, t_s
        if t_s - self.since_s > WAIT_MAX_S:
            station = pose  # somebody stands on the station: hold here
        if math.dist(pose[:2], station[:2]) > REACHED_M:
            return station[0], station[1]
        if abs(math.remainder(station[2] - pose[2], math.tau)) > HEADING_TOL_RAD:
            return station[2]
        log.info("robot %d holds station again at (%.2f, %.2f) at t=%.1f s", self.robot_id, pose[0], pose[1], t_s)
        self.cancel()
        return None


def _clear(boxes: Sequence[Box], a: tuple[float, float], b: tuple[float, float], path_m: float, end_m: float) -> bool:
    """Whether the straight way from ``a`` to ``b`` keeps ``path_m`` from every box once it has got that far
    (a keeper beside a wall may stand nearer), and ``b`` itself keeps ``end_m``."""
    if not boxes:
        return True
    n = max(2, math.ceil(math.dist(a, b) / 0.05) + 1)
    xs, ys = np.linspace(a[0], b[0], n, dtype=np.float64), np.linspace(a[1], b[1], n, dtype=np.float64)
    gap = np.min([box_distance(box, xs, ys) for box in boxes], axis=0)
    ok = gap >= path_m
    left = np.maximum.accumulate(ok)
    return bool(gap[-1] >= end_m and np.all(ok | ~left))


def _in_the_way(n: Neighbour, here: tuple[float, float], spot: tuple[float, float], path_m: float,
                pass_m: float) -> bool:
    """Whether robot ``n`` stands at ``spot`` (within ``pass_m / 2`` of its circle) or on the straight way
    there from ``here`` (within ``path_m``, or nearer than it already is): the avoidance would stop the
    keeper short."""
    p = (n.x_m, n.y_m)
    return (math.dist(spot, p) < n.radius_m + pass_m / 2
            or point_segment_distance(p, here, spot) < min(n.radius_m + path_m, math.dist(here, p) - 1e-6))


def aside_spot(pose: Pose2, way: tuple[float, float], neighbours: Sequence[Neighbour], boxes: Sequence[Box],
               keep_m: float, path_m: float, pass_m: float) -> tuple[float, float] | None:
    """The nearest spot (ring by ring, ``RINGS_M``) a keeper at ``pose`` can drive straight to
    (keeping ``path_m`` from the walls and obstacles ``boxes`` on the way) that leaves ``pass_m``
    between it and the line through the station along ``way`` (the unit direction the blocked
    robot came in), is not back against it, keeps ``keep_m`` from the boxes and ``pass_m`` from
    every other robot, and whose way there passes every robot's circle by ``path_m`` (or, for a
    robot nearer than that already, never comes nearer to it); on a ring,
    the one farthest from that line.  None if there is none."""
    here = (pose[0], pose[1])
    ux, uy = way
    for r in RINGS_M:
        best, best_side = None, -math.inf
        for k in range(BEARINGS):
            a = math.tau * k / BEARINGS
            c = (here[0] + r * math.cos(a), here[1] + r * math.sin(a))
            along = (c[0] - here[0]) * ux + (c[1] - here[1]) * uy
            side = abs((c[0] - here[0]) * uy - (c[1] - here[1]) * ux)
            if side < pass_m or along < -0.2 or side <= best_side:
                continue
            if any(_in_the_way(n, here, c, path_m, pass_m) for n in neighbours):
                continue
            if _clear(boxes, here, c, path_m, keep_m):
                best, best_side = c, side
        if best is not None:
            return best
    return None
