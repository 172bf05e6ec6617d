"""Where things are: start poses, footprints, walls and the map frame of a
scenario (pure geometry on the types of :mod:`tagswarm.protocol.scenario_schema`;
:mod:`tagswarm.protocol.scenario` validates start poses with it)."""

from __future__ import annotations

import functools
import math

import msgspec
import numpy as np

from tagswarm.protocol.freespace import segment_box_distance, sight_blocked
from tagswarm.protocol.geometry import se2_compose, se2_inverse
from tagswarm.protocol.readrange import camera_range_m, reading_range_m
from tagswarm.protocol.scenario_schema import Arena, Robot, Scenario, StartPose


def footprint_radius(robot: Robot) -> float:
    """Radius (m) of the circle that holds a robot's chassis and cube."""
    half = max(robot.chassis_length_m, robot.cube_edge_m) / 2.0
    return math.hypot(half, max(robot.chassis_width_m, robot.cube_edge_m) / 2.0)


#: a robot counts as in a camera's view when its bearing is this far inside the image's edge
#: (its cube is some 0.1 m wide, and a face cut by the edge is not read)
VIEW_EDGE_MARGIN_DEG = 5.0


def start_poses(s: Scenario) -> list[tuple[float, float, float]]:
    """Initial (x_m, y_m, yaw_rad) of every robot in the arena frame; deterministic.

    ``grid`` and ``random`` draw each robot's heading, then turn the origin robot (when it
    anchors the map) to :func:`origin_heading`: the map frame is its first pose, and an origin
    that sees nobody leaves the map's heading to the others' views of its cube, whose faces
    tell it only to a few degrees -- a turned map (measured: a 10 x 6 m store room whose origin
    faced a wall, fused RMSE 10.2 cm and 53 % of the time localised; facing two of its
    neighbours, 1.2 cm and 95.7 %)."""
    return list(_start_poses(s))


def pinned(s: Scenario) -> Scenario:
    """``s`` with the start poses a ``grid`` or ``random`` placement draws written out as an
    ``explicit`` start list (any other scenario unchanged): a run folder's ``scenario.json`` and a
    recording then hold where the robots really started, so that re-evaluating or replaying them
    with a later version, whose draw may differ (the origin heading since 2026-12-06), keeps the
    map frame they ran in."""
    if s.robots.placement not in ("grid", "random"):
        return s
    start = tuple(StartPose(x_m=x, y_m=y, yaw_rad=yaw) for x, y, yaw in start_poses(s))
    return msgspec.structs.replace(s, robots=msgspec.structs.replace(s.robots, placement="explicit", start=start))


@functools.lru_cache(maxsize=32)  # a controller may ask for the map frame every step; scenarios are frozen
def _start_poses(s: Scenario) -> tuple[tuple[float, float, float], ...]:
    n = s.robots.count
    rng = np.random.default_rng(s.seed + 7919)
    pl = s.robots.placement
    if pl == "explicit":
        return tuple((p.x_m, p.y_m, p.yaw_rad) for p in s.robots.start)
    if pl == "ring":
        out = []
        for k in range(n):
            a = 2 * math.pi * k / n
            rr = s.robots.ring_radius_m
            out.append((rr * math.cos(a), rr * math.sin(a), _wrap(a + math.pi)))
        return tuple(out)
    margin = footprint_radius(s.robot) + s.arena.wall_thickness_m + 0.3
    wx, wy = s.arena.size_x_m / 2 - margin, s.arena.size_y_m / 2 - margin
    # clear of the obstacles (without it a 22nd robot of the warehouse scene landed on a pallet)
    min_clear = footprint_radius(s.robot) + 0.1
    if pl == "grid":
        return _origin_turned(s, [(x, y, float(rng.uniform(-math.pi, math.pi)))
                                  for x, y in _grid_cells(s, n, wx, wy, min_clear)])
    out = []
    min_gap = 2 * footprint_radius(s.robot) + 0.1
    for _ in range(n):
        for _attempt in range(10_000):
            x, y = float(rng.uniform(-wx, wx)), float(rng.uniform(-wy, wy))
            if all(math.dist((x, y), p[:2]) >= min_gap for p in out) and all(
                    segment_box_distance((x, y), (x, y), ob) >= min_clear for ob in s.arena.obstacles):
                break
        out.append((x, y, float(rng.uniform(-math.pi, math.pi))))
    return _origin_turned(s, out)


def _origin_turned(s: Scenario, poses: list[tuple[float, float, float]]) -> tuple[tuple[float, float, float], ...]:
    k = s.map.origin_id
    yaw = origin_heading(s, poses) if anchors_map(s, k) and 0 <= k < len(poses) else None
    return tuple((p[0], p[1], yaw) if i == k and yaw is not None else p for i, p in enumerate(poses))


def in_view(s: Scenario, poses: list[tuple[float, float, float]], k: int,
            yaw_rad: float | None = None) -> list[tuple[int, float]]:
    """The robots robot ``k`` sees from ``poses[k]`` (or from its position turned to ``yaw_rad``)
    with any of its cameras: in sight (nothing as tall as the cubes' centre between), within
    that camera's reading range and ``VIEW_EDGE_MARGIN_DEG`` inside its horizontal field of
    view (at most half of half of it).  Each as (robot, bearing off the axis of the nearest
    camera that sees it, radians).  Arena frame."""
    return _in_view(s, _reachable(s, poses, k), poses[k][2] if yaw_rad is None else yaw_rad)


def _in_view(s: Scenario, reachable: dict[int, tuple[float, float]], yaw: float) -> list[tuple[int, float]]:
    cams = [(math.radians(c.yaw_deg), math.radians(c.hfov_deg / 2.0 - min(VIEW_EDGE_MARGIN_DEG, c.hfov_deg / 4.0)),
             camera_range_m(s, c)) for c in s.robot.cameras]
    out = []
    for j, (bearing, d) in reachable.items():
        offs = [off for axis, half, reach in cams
                if d <= reach and (off := abs(_wrap(bearing - yaw - axis))) <= half]
        if offs:
            out.append((j, min(offs)))
    return out


def _reachable(s: Scenario, poses: list[tuple[float, float, float]], k: int) -> dict[int, tuple[float, float]]:
    """robot -> (bearing rad, distance m) of the robots within reading range of robot ``k``'s rig and in sight."""
    reach, tall = reading_range_m(s), s.robot.cube_center_z_m
    x, y, _ = poses[k]
    out = {}
    for j, (xj, yj, _) in enumerate(poses):
        d = math.dist((x, y), (xj, yj))
        if j != k and d <= reach and not sight_blocked((x, y), (xj, yj), s.arena, tall):
            out[j] = (math.atan2(yj - y, xj - x), d)
    return out


def origin_heading(s: Scenario, poses: list[tuple[float, float, float]]) -> float | None:
    """The heading (rad, arena frame) at which the origin robot's cameras see the most robots
    of ``poses`` (:func:`in_view`); among equals, the one that holds them nearest the cameras'
    axes (a cube at the image's edge is read less often), then the first from -pi.  None if no
    heading lets it see anyone: any heading is then as good."""
    if not s.robot.cameras:
        return None
    reachable = _reachable(s, poses, s.map.origin_id)
    best: tuple[tuple[int, float], float] | None = None
    for step in range(360):
        yaw = -math.pi + math.radians(step)
        seen = _in_view(s, reachable, yaw)
        score = (len(seen), -sum(off for _, off in seen))
        if score[0] and (best is None or score > best[0]):
            best = (score, yaw)
    return None if best is None else best[1]


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
