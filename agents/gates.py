"""Narrow passages and who goes through first (pure code, no I/O).

The avoidance (:mod:`tagswarm.agents.avoid`) passes other robots where there is room to pass.  In a
passage narrower than two robots side by side there is none: two robots that meet in a door stand
face to face until one stalls and backs away (two rooms joined by a 1 m door, two patrols crossing it
in opposite directions: 12-34 s at the door, measured 2026-12-07).  So every gap between two walls or
obstacles that lets one robot through but not two is a :class:`Gate`, and a robot about to enter
one waits outside (:func:`must_wait`) while another robot is in it coming the other way, or is
coming to it from the other side with a lower id (the avoidance's priority for giving way).  Robots going the same way
follow each other through; a robot standing in a gate does not hold anyone up here (the avoidance's
stall, its way round the room and a station keeper's stepping aside deal with that).

Frames and units: map frame, metres, seconds.  Deterministic: gates in the order of their boxes.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from tagswarm.agents.avoidgeom import Box, Neighbour, box_corners, box_distance

#: a robot counts as moving (towards a gate, or through one) above this speed (m/s): the map's
#: velocities of a robot standing still scatter by a few mm/s
MOVING_M_S = 0.05
#: a moving robot this close to a gate's centre (m) and heading for it is coming to it
COMING_M = 1.5
#: a robot waits when its way enters a gate (or its mouth) within this distance (m): room for the one
#: coming out to pass it (at 0.8 m a robot that had just come out met the waiting one's neighbour on its
#: way, in the open, and they stood face to face)
LOOK_M = 1.5
STEP_M = 0.05


@dataclass(frozen=True)
class Gate:
    """The gap between boxes ``a`` and ``b``: ``gap_m`` wide at its narrowest, whose middle is ``centre``."""

    a: Box
    b: Box
    gap_m: float
    centre: tuple[float, float]


def _closest_on(b: Box, x: float, y: float) -> tuple[float, float]:
    """The point of box ``b`` nearest to (x, y)."""
    c, s = math.cos(b.yaw_rad), math.sin(b.yaw_rad)
    dx, dy = x - b.x_m, y - b.y_m
    lx = min(max(c * dx + s * dy, -b.half_x_m), b.half_x_m)
    ly = min(max(-s * dx + c * dy, -b.half_y_m), b.half_y_m)
    return b.x_m + c * lx - s * ly, b.y_m + s * lx + c * ly


def box_gap(a: Box, b: Box) -> tuple[float, tuple[float, float]]:
    """The distance (m) between two boxes that do not overlap, and the midpoint of their closest
    points (for two disjoint convex polygons the nearest pair has a corner of one of them)."""
    best = (math.inf, (0.0, 0.0))
    for one, other in ((a, b), (b, a)):
        for x, y in box_corners(one):
            d = float(box_distance(other, x, y))
            if d < best[0]:
                px, py = _closest_on(other, x, y)
                best = (d, ((x + px) / 2, (y + py) / 2))
    return best


def gates(boxes: Sequence[Box], foot_m: float, clearance_m: float) -> tuple[Gate, ...]:
    """The gaps between two of ``boxes`` (walls and obstacles) that a robot of footprint radius
    ``foot_m`` fits through but two passing each other with ``clearance_m`` between them and from the
    sides do not, and that no third box closes."""
    one, two = 2 * foot_m + 0.02, 4 * foot_m + 3 * clearance_m
    out = []
    for a, b in itertools.combinations(boxes, 2):
        gap, centre = box_gap(a, b)
        if not one < gap < two:
            continue
        if any(float(box_distance(o, *centre)) < foot_m for o in boxes if o is not a and o is not b):
            continue
        out.append(Gate(a, b, gap, centre))
    return tuple(out)


def in_gate(g: Gate, x: np.ndarray | float, y: np.ndarray | float, foot_m: float) -> np.ndarray:
    """Whether points (map frame) lie in the gate or its mouths: between its two boxes, where the
    distances to them add up to at most the gap and a footprint's diameter."""
    return np.asarray(box_distance(g.a, x, y) + box_distance(g.b, x, y) <= g.gap_m + 2 * foot_m)


def must_wait(gs: Sequence[Gate], pose: tuple[float, float, float], aim: tuple[float, float], robot_id: int,
              neighbours: Sequence[Neighbour], foot_m: float, reach_m: float = math.inf) -> Gate | None:
    """The gate a robot at ``pose`` heading for ``aim`` should wait outside of, or None.  It waits when
    its way enters a gate within ``LOOK_M`` (and it is not in it already) while another robot is in that
    gate moving against it, or came out of it and has not passed yet (moving against it, ahead, nearer
    than the gate and within the gate's half width and a footprint's diameter of its way), or is coming
    to it (moving, within ``COMING_M`` of its centre, heading for it, from the other side) with a lower id.
    Its way is the ray towards ``aim`` (a way's carrot may be nearer than the gate), as far as ``reach_m``
    (its goal's distance)."""
    px, py = pose[0], pose[1]
    length = math.hypot(aim[0] - px, aim[1] - py)
    if length < 1e-9:
        return None
    ux, uy = (aim[0] - px) / length, (aim[1] - py) / length
    steps = np.arange(0.0, min(reach_m, LOOK_M) + 1e-9, STEP_M)
    sx, sy = px + ux * steps, py + uy * steps
    for g in gs:
        if bool(in_gate(g, px, py, foot_m)) or not bool(np.any(in_gate(g, sx, sy, foot_m))):
            continue
        for nb in neighbours:
            speed = math.hypot(nb.vx_m_s, nb.vy_m_s)
            if speed <= MOVING_M_S:
                continue
            against = nb.vx_m_s * ux + nb.vy_m_s * uy < 0.0
            if bool(in_gate(g, nb.x_m, nb.y_m, foot_m)):
                if against:
                    return g  # in it, coming this way
                continue
            rx, ry = nb.x_m - px, nb.y_m - py
            if (against and rx * ux + ry * uy > 0.0 and math.hypot(rx, ry) < math.dist(g.centre, (px, py))
                    and abs(rx * uy - ry * ux) < g.gap_m / 2 + 2 * foot_m):
                # out of it on this way, between here and the gate, not past yet: two moving face to face stall
                # (one 1.9 m to the side going the other way held a patrol in the depot for 15 s)
                return g
            to_x, to_y = g.centre[0] - nb.x_m, g.centre[1] - nb.y_m
            if (against and nb.robot_id < robot_id and math.hypot(to_x, to_y) < COMING_M
                    and nb.vx_m_s * to_x + nb.vy_m_s * to_y > 0.0):
                return g  # coming to it from the other side, first by id
    return None
