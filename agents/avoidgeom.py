"""The geometry collision avoidance works on (pure code, no I/O): the obstacles, other
robots (:class:`Neighbour`) and walls and obstacles (:class:`Box`, :func:`static_boxes`,
:func:`box_distance`), and the paths a robot would drive, following a controller
(:func:`closed_loop`) or at a constant twist (:func:`rollout`).  Used by
:mod:`tagswarm.agents.avoid` (which re-exports every name), :mod:`tagswarm.agents.guard`,
:mod:`tagswarm.agents.route` and :mod:`tagswarm.agents.makeway`.

Frames and units: everything in the map frame, metres, radians, seconds;
poses are (x_m, y_m, yaw_rad) of base_link.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tagswarm.protocol.geometry import Pose2
from tagswarm.protocol.geometry import se2_compose as compose
from tagswarm.protocol.layout import arena_to_map, wall_boxes
from tagswarm.protocol.scenario import Scenario

Arr = NDArray[np.float64]


@dataclass(frozen=True)
class Box:
    """A static obstacle: centre (x_m, y_m) and heading yaw_rad in the map frame, half extents in metres."""

    x_m: float
    y_m: float
    yaw_rad: float
    half_x_m: float
    half_y_m: float


@dataclass(frozen=True)
class Neighbour:
    """Another robot: map-frame position now, velocity (m/s, map frame) and the radius (m) of the
    circle it may occupy (footprint plus its pose uncertainty)."""

    robot_id: int
    x_m: float
    y_m: float
    vx_m_s: float
    vy_m_s: float
    radius_m: float


def static_boxes(s: Scenario) -> tuple[Box, ...]:
    """The arena's walls and ``arena.obstacles`` as map-frame boxes."""
    t = arena_to_map(s)
    out = []
    for (cx, cy, _), (hx, hy, _) in wall_boxes(s.arena):
        x, y, yaw = compose(t, (cx, cy, 0.0))
        out.append(Box(x, y, yaw, hx, hy))
    for ob in s.arena.obstacles:
        x, y, yaw = compose(t, (ob.x_m, ob.y_m, ob.yaw_rad))
        out.append(Box(x, y, yaw, ob.size_x_m / 2, ob.size_y_m / 2))
    return tuple(out)


def box_corners(b: Box) -> list[tuple[float, float]]:
    """The box's four corners (m, the boxes' frame)."""
    c, s = math.cos(b.yaw_rad), math.sin(b.yaw_rad)
    return [(b.x_m + c * kx * b.half_x_m - s * ky * b.half_y_m, b.y_m + s * kx * b.half_x_m + c * ky * b.half_y_m)
            for kx, ky in ((1, 1), (1, -1), (-1, 1), (-1, -1))]


def box_distance(b: Box, x: Arr | float, y: Arr | float) -> Arr:
    """Signed distance (m) from points to the box's boundary, negative inside."""
    c, s = math.cos(b.yaw_rad), math.sin(b.yaw_rad)
    dx, dy = np.asarray(x, float) - b.x_m, np.asarray(y, float) - b.y_m
    qx = np.abs(c * dx + s * dy) - b.half_x_m
    qy = np.abs(-s * dx + c * dy) - b.half_y_m
    outside = np.hypot(np.maximum(qx, 0.0), np.maximum(qy, 0.0))
    return np.asarray(outside + np.minimum(np.maximum(qx, qy), 0.0))


def closed_loop(pose: Pose2, steer: Callable[[Pose2], tuple[float, float]], times: Arr) -> tuple[Arr, Arr, Arr]:
    """Positions and headings (each (1, len(times))) of following the controller ``steer``
    (pose -> twist) from ``pose``: the path the go-to-goal command is about to drive."""
    x, y, th = pose
    out = np.empty((3, len(times)))
    t_prev = 0.0
    for j, t in enumerate(times):
        v, w = steer((x, y, th))
        dt = float(t) - t_prev
        t_prev = float(t)
        mid = th + w * dt / 2
        x, y, th = x + v * dt * math.cos(mid), y + v * dt * math.sin(mid), th + w * dt
        out[:, j] = (x, y, th)
    return out[0:1], out[1:2], out[2:3]


def rollout(pose: Pose2, v: Arr, w: Arr, times: Arr, max_travel_m: float) -> tuple[Arr, Arr, Arr]:
    """Positions and headings (each (len(v), len(times))) of constant twists (v m/s, w rad/s)
    from ``pose``; a path stops after ``max_travel_m`` (the robot stops at its goal)."""
    v2, w2, t2 = v[:, None], w[:, None], times[None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        te = np.where(v2 > 0, np.minimum(t2, max_travel_m / np.where(v2 > 0, v2, 1.0)), t2)
    th = pose[2] + w2 * te
    straight = np.abs(w2) < 1e-6
    safe_w = np.where(straight, 1.0, w2)
    x = np.where(straight, pose[0] + v2 * te * math.cos(pose[2]),
                 pose[0] + v2 / safe_w * (np.sin(th) - math.sin(pose[2])))
    y = np.where(straight, pose[1] + v2 * te * math.sin(pose[2]),
                 pose[1] - v2 / safe_w * (np.cos(th) - math.cos(pose[2])))
    return x, y, th
