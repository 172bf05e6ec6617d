"""Clearances on the arena floor: how far a point or a straight path is from the
walls, the obstacle boxes, a landmark tag or another robot's path (pure 2-D geometry).

Everything is in the arena frame, metres.  A robot is treated as the circle of
:func:`tagswarm.protocol.layout.footprint_radius` around its base; a path it drives along
a straight segment sweeps a capsule, so "robot A on path a never touches robot B
on path b" is ``segment_distance(a, b) >= 2 r``.  A standing robot is a segment
of length zero.
"""

from __future__ import annotations

import math

from tagswarm.protocol.scenario_schema import Arena, Obstacle

XY = tuple[float, float]


def point_segment_distance(p: XY, a: XY, b: XY) -> float:
    """Distance (m) from point ``p`` to the segment ``a``-``b`` (a point if a == b)."""
    dx, dy = b[0] - a[0], b[1] - a[1]
    n2 = dx * dx + dy * dy
    t = 0.0 if n2 == 0.0 else max(0.0, min(1.0, ((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / n2))
    return math.hypot(p[0] - a[0] - t * dx, p[1] - a[1] - t * dy)


def _cross(o: XY, a: XY, b: XY) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def _segments_cross(a: XY, b: XY, c: XY, d: XY) -> bool:
    """True if the segments properly intersect (touching counts as distance 0 below anyway)."""
    d1, d2, d3, d4 = _cross(c, d, a), _cross(c, d, b), _cross(a, b, c), _cross(a, b, d)
    return ((d1 > 0) != (d2 > 0)) and ((d3 > 0) != (d4 > 0)) and 0.0 not in (d1, d2, d3, d4)


def segment_distance(a: XY, b: XY, c: XY, d: XY) -> float:
    """Smallest distance (m) between segment ``a``-``b`` and segment ``c``-``d``."""
    if _segments_cross(a, b, c, d):
        return 0.0
    return min(point_segment_distance(a, c, d), point_segment_distance(b, c, d),
               point_segment_distance(c, a, b), point_segment_distance(d, a, b))


def _box_corners(ob: Obstacle) -> list[XY]:
    c, s = math.cos(ob.yaw_rad), math.sin(ob.yaw_rad)
    hx, hy = ob.size_x_m / 2, ob.size_y_m / 2
    return [(ob.x_m + c * u - s * v, ob.y_m + s * u + c * v) for u, v in ((hx, hy), (-hx, hy), (-hx, -hy), (hx, -hy))]


def _inside_box(p: XY, ob: Obstacle) -> bool:
    c, s = math.cos(ob.yaw_rad), math.sin(ob.yaw_rad)
    dx, dy = p[0] - ob.x_m, p[1] - ob.y_m
    return abs(c * dx + s * dy) <= ob.size_x_m / 2 and abs(-s * dx + c * dy) <= ob.size_y_m / 2


def segment_box_distance(a: XY, b: XY, ob: Obstacle) -> float:
    """Smallest distance (m) from segment ``a``-``b`` (or a point, a == b) to the
    obstacle's footprint rectangle; 0 if they overlap."""
    if _inside_box(a, ob) or _inside_box(b, ob):
        return 0.0
    corners = _box_corners(ob)
    edges = list(zip(corners, corners[1:] + corners[:1], strict=True))
    return min(segment_distance(a, b, c, d) for c, d in edges)


def wall_clearance(p: XY, arena: Arena) -> float:
    """Distance (m) from ``p`` to the nearest wall's inner face (negative outside)."""
    half_x = arena.size_x_m / 2 - arena.wall_thickness_m / 2
    half_y = arena.size_y_m / 2 - arena.wall_thickness_m / 2
    return min(half_x - abs(p[0]), half_y - abs(p[1]))


def obstacle_clearance(a: XY, b: XY, arena: Arena) -> float:
    """Distance (m) from segment ``a``-``b`` to the nearest obstacle (inf without obstacles)."""
    return min((segment_box_distance(a, b, ob) for ob in arena.obstacles), default=math.inf)


def sight_blocked(a: XY, b: XY, arena: Arena, min_height_m: float) -> bool:
    """True if an obstacle at least ``min_height_m`` tall stands on the straight line
    from ``a`` to ``b`` (a camera's view of a tag cube across the floor)."""
    return any(segment_box_distance(a, b, ob) == 0.0 for ob in arena.obstacles if ob.size_z_m >= min_height_m)
