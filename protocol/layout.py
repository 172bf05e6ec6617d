"""Where things are: start poses, footprints, walls and the map frame of a
scenario (pure geometry on the types of :mod:`tagswarm.protocol.scenario_schema`;
:mod:`tagswarm.protocol.scenario` validates start poses with it)."""

from __future__ import annotations

import math

import numpy as np

from tagswarm.protocol.freespace import segment_box_distance
from tagswarm.protocol.geometry import se2_compose, se2_inverse
from tagswarm.protocol.scenario_schema import Arena, Robot, Scenario


def footprint_radius(robot: Robot) -> float:
    """Radius (m) of the circle that holds a robot's chassis and cube."""
    half = max(robot.chassis_length_m, robot.cube_edge_m) / 2.0
    return math.hypot(half, max(robot.chassis_width_m, robot.cube_edge_m) / 2.0)


def start_poses(s: Scenario) -> list[tuple[float, float, float]]:
    """Initial (x_m, y_m, yaw_rad) of every robot in the arena frame; deterministic."""
    n = s.robots.count
    rng = np.random.default_rng(s.seed + 7919)
    pl = s.robots.placement
    if pl == "explicit":
        return [(p.x_m, p.y_m, p.yaw_rad) for p in s.robots.start]
    if pl == "ring":
        out = []
        for k in range(n):
            a = 2 * math.pi * k / n
            rr = s.robots.ring_radius_m
            out.append((rr * math.cos(a), rr * math.sin(a), _wrap(a + math.pi)))
        return out
    margin = footprint_radius(s.robot) + s.arena.wall_thickness_m + 0.3
    wx, wy = s.arena.size_x_m / 2 - margin, s.arena.size_y_m / 2 - margin
    # clear of the obstacles (without it a 22nd robot of the warehouse scene landed on a pallet)
    min_clear = footprint_radius(s.robot) + 0.1
    if pl == "grid":
        return [(x, y, float(rng.uniform(-math.pi, math.pi))) for x, y in _grid_cells(s, n, wx, wy, min_clear)]
    out = []
    min_gap = 2 * footprint_radius(s.robot) + 0.1
    for _ in range(n):
        for _attempt in range(10_000):
            x, y = float(rng.uniform(-wx, wx)), float(rng.uniform(-wy, wy))
            if all(math.dist((x, y), p[:2]) >= min_gap for p in out) and all(
                    segment_box_distance((x, y), (x, y), ob) >= min_clear for ob in s.arena.obstacles):
                break
        out.append((x, y, float(rng.uniform(-math.pi, math.pi))))
    return out


def _grid_cells(s: Scenario, n: int, wx: float, wy: float, min_clear: float) -> list[tuple[float, float]]:
    """The first ``n`` cell centres (row by row) of the smallest lattice over [-wx, wx] x
    [-wy, wy] with ``n`` cells clear of every obstacle, starting from as many columns as the
    arena's aspect asks for.  Cells too close for two robots are not offered: the lattice
    stops growing there (validation then names the clash)."""
    # as many columns as the arena's aspect asks for (a square arena: ceil(sqrt(n)), as ever)
    cols = min(n, max(1, math.ceil(math.sqrt(n * wx / wy) - 1e-9)))
    rows = math.ceil(n / cols)
    min_gap = 2 * footprint_radius(s.robot)
    free: list[tuple[float, float]] = []
    while True:
        free = []
        for k in range(cols * rows):
            x = -wx + 2 * wx * ((k % cols) + 0.5) / cols
            y = -wy + 2 * wy * ((k // cols) + 0.5) / rows
            if all(segment_box_distance((x, y), (x, y), ob) >= min_clear for ob in s.arena.obstacles):
                free.append((x, y))
        if len(free) >= n:
            return free[:n]
        # grow the lattice along the axis whose cells are longer
        ncols, nrows = (cols + 1, rows) if wx / cols >= wy / rows else (cols, rows + 1)
        if min(2 * wx / ncols, 2 * wy / nrows) < min_gap:
            return (free + [(0.0, 0.0)] * n)[:n]  # no room: validation names the overlap
        cols, rows = ncols, nrows


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def wall_boxes(a: Arena) -> list[tuple[tuple[float, float, float], tuple[float, float, float]]]:
    """The four walls as (centre, half extents) boxes in the arena frame, metres."""
    t, h = a.wall_thickness_m, a.wall_height_m
    hx, hy = a.size_x_m / 2, a.size_y_m / 2
    return [
        ((hx, 0.0, h / 2), (t / 2, hy + t / 2, h / 2)),
        ((-hx, 0.0, h / 2), (t / 2, hy + t / 2, h / 2)),
        ((0.0, hy, h / 2), (hx + t / 2, t / 2, h / 2)),
        ((0.0, -hy, h / 2), (hx + t / 2, t / 2, h / 2)),
    ]


def anchors_map(s: Scenario, robot_id: int) -> bool:
    """Whether this robot's first pose *is* the map frame: the origin robot, unless
    landmark tags tie the map to the arena."""
    return robot_id == s.map.origin_id and not s.landmarks


def arena_to_map(s: Scenario) -> tuple[float, float, float]:
    """T_map_arena as (x_m, y_m, yaw_rad): the map frame is the origin robot's first
    pose, unless the scenario has landmark tags, which tie the map to the arena."""
    if s.landmarks:
        return (0.0, 0.0, 0.0)
    return se2_inverse(start_poses(s)[s.map.origin_id])


def stand_problem(s: Scenario, x_m: float, y_m: float) -> str | None:
    """Why a robot could not stand at (x_m, y_m) in the *arena* frame -- its footprint circle
    beyond the walls or over an obstacle -- or None if it can."""
    half_x = s.arena.size_x_m / 2 - s.arena.wall_thickness_m / 2
    half_y = s.arena.size_y_m / 2 - s.arena.wall_thickness_m / 2
    r = footprint_radius(s.robot)
    if abs(x_m) + r > half_x or abs(y_m) + r > half_y:
        return (f"a robot there would not be inside the arena walls (arena frame, |x| <= {half_x - r:.2f}, "
                f"|y| <= {half_y - r:.2f})")
    for k, ob in enumerate(s.arena.obstacles):
        if segment_box_distance((x_m, y_m), (x_m, y_m), ob) < r:
            return f"a robot there would overlap arena.obstacles[{k}]"
    return None


def map_to_arena_xy(s: Scenario, x_m: float, y_m: float) -> tuple[float, float]:
    """A point of the map frame in the arena frame."""
    x, y, _ = se2_compose(se2_inverse(arena_to_map(s)), (x_m, y_m, 0.0))
    return x, y
