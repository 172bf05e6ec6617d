"""A way round when local avoidance is stuck: A* on a grid of the known room (pure code, no I/O).

:mod:`tagswarm.agents.avoid` steers around what is near by rolling out twists over two
seconds.  That cannot see a way that first leads away from the goal: a robot whose
way is closed by the back wall of a pocket makes no progress on either side it tries
(unit test: a robot in a pocket never got out; a store of 14 robots had a patrol stuck at
a rack's end beside a station keeper).  Once the avoidance stalls with nobody to give way
to (or after giving way twice at one place), :func:`plan` searches the room itself: an 8-connected grid of
``RESOLUTION_M`` cells over the walls' extent, a cell closed where the robot's centre would
be nearer than ``keep_m`` (the caller's: footprint, clearance and a margin) to a wall, an
obstacle or another robot as the map has it now (each a disc of its radius).
The same search runs, without the robots, whenever the straight way to a goal runs into a wall or an
obstacle (:func:`blocked`; the caller's: :mod:`tagswarm.agents.behaviour`): the avoidance's preferred side
round a box cannot tell a door from a dead end (two rooms joined by a 1 m door: a robot going through it
avoided the robot coming the other way, then followed the dividing wall to the room's far wall).
The path found is followed through :class:`Route`, whose carrot (a point
``LOOKAHEAD_M`` along it) replaces the goal for the go-to-goal controller while the
avoidance still keeps the clearance.

Frames and units: map frame, metres.  Deterministic: ties in the open list go to the
cell pushed first.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from tagswarm.agents.avoid import Box, Neighbour, box_distance
from tagswarm.agents.avoidgeom import box_corners
from tagswarm.protocol.freespace import point_segment_distance

RESOLUTION_M = 0.1
LOOKAHEAD_M = 0.6  # the carrot: this far along the path from the nearest point not yet passed
MAX_CELLS = 250_000  # a room larger than 50 m x 50 m at 0.1 m is not planned (the avoidance alone steers)


@dataclass(frozen=True)
class Grid:
    """The room's cells: ``free`` (ny, nx) bool over [x0, x0 + nx·res) × [y0, y0 + ny·res), and
    ``clear`` (ny, nx) the distance (m) from each cell's centre to the nearest box."""

    x0: float
    y0: float
    res: float
    free: np.ndarray
    clear: np.ndarray

    def cell(self, x: float, y: float) -> tuple[int, int]:
        ny, nx = self.free.shape
        return (min(max(int((y - self.y0) / self.res), 0), ny - 1), min(max(int((x - self.x0) / self.res), 0), nx - 1))

    def centre(self, cell: tuple[int, int]) -> tuple[float, float]:
        return self.x0 + (cell[1] + 0.5) * self.res, self.y0 + (cell[0] + 0.5) * self.res


def static_grid(boxes: Sequence[Box], keep_m: float, res: float = RESOLUTION_M) -> Grid | None:
    """The cells where a robot's centre may be: farther than ``keep_m`` from every box; None if the
    boxes span too large a room to grid (or there are none)."""
    if not boxes:
        return None
    # the boxes' own corners: a circle round a long wall would grid four times its room
    corners = [p for b in boxes for p in box_corners(b)]
    xs, ys = [x for x, _ in corners], [y for _, y in corners]
    nx, ny = math.ceil((max(xs) - min(xs)) / res), math.ceil((max(ys) - min(ys)) / res)
    if nx * ny > MAX_CELLS:
        return None
    cx = min(xs) + (np.arange(nx) + 0.5) * res
    cy = min(ys) + (np.arange(ny) + 0.5) * res
    gx, gy = np.meshgrid(cx, cy)
    clear = np.full((ny, nx), np.inf)
    for b in boxes:
        clear = np.minimum(clear, box_distance(b, gx, gy))
    return Grid(min(xs), min(ys), res, clear > keep_m, clear)


def blocked(boxes: Sequence[Box], start: tuple[float, float], goal: tuple[float, float], keep_m: float,
            step_m: float = 0.05) -> bool:
    """Whether the straight way from ``start`` to ``goal`` (map frame, m) passes nearer than ``keep_m`` to
    a box anywhere but within ``keep_m`` of its two ends (a robot may start, and a goal may lie, beside a
    wall: the avoidance handles that room)."""
    length = math.dist(start, goal)
    if length <= 2.0 * keep_m or not boxes:
        return False
    t = np.arange(keep_m, length - keep_m + 1e-9, step_m, dtype=np.float64) / length
    x: np.ndarray = start[0] + t * (goal[0] - start[0])
    y: np.ndarray = start[1] + t * (goal[1] - start[1])
    return any(bool(np.any(box_distance(b, x, y) < keep_m)) for b in boxes)


def plan(grid: Grid, start: tuple[float, float], goal: tuple[float, float], others: Sequence[Neighbour],
         keep_m: float) -> list[tuple[float, float]] | None:
    """Cell centres (map frame) from ``start`` to ``goal`` around the grid's closed cells and the
    discs of ``others`` (their radius plus ``keep_m``), or None if there is no way.  The start and
    goal cells are open whatever is there (the robot stands in the first; the goal may lie
    within a clearance, as a waypoint beside a wall does), and so are the cells within ``keep_m``
    of either that are no nearer to a box than it (within a cell): the way from the open room to
    a goal beside a wall (only its own cell open, it was cut off: the search then went through
    every cell of the room, 0.2 s in a 10 m x 10 m one)."""
    free = grid.free.copy()
    ny, nx = free.shape
    iy, ix = np.mgrid[0:ny, 0:nx]
    px, py = grid.x0 + (ix + 0.5) * grid.res, grid.y0 + (iy + 0.5) * grid.res
    s, g = grid.cell(*start), grid.cell(*goal)
    for end, cell in ((start, s), (goal, g)):
        free |= (np.hypot(px - end[0], py - end[1]) <= keep_m) & (grid.clear >= grid.clear[cell] - grid.res)
    for nb in others:
        free &= np.hypot(px - nb.x_m, py - nb.y_m) > nb.radius_m + keep_m
    free[s] = free[g] = True
    h = np.hypot(px - goal[0], py - goal[1]) / grid.res
    steps = [(-1, 0, 1.0), (1, 0, 1.0), (0, -1, 1.0), (0, 1, 1.0),
             (-1, -1, math.sqrt(2)), (-1, 1, math.sqrt(2)), (1, -1, math.sqrt(2)), (1, 1, math.sqrt(2))]
    cost = {s: 0.0}
    came: dict[tuple[int, int], tuple[int, int]] = {}
    heap = [(float(h[s]), 0, s)]
    pushed = 0
    expanded: set[tuple[int, int]] = set()
    while heap:
        _, _, c = heapq.heappop(heap)
        if c in expanded:
            continue  # a stale entry: reached again more cheaply since it was pushed
        expanded.add(c)
        if c == g:
            path = [c]
            while path[-1] in came:
                path.append(came[path[-1]])
            return [grid.centre(p) for p in reversed(path)]
        for dy, dx, step in steps:
            n = (c[0] + dy, c[1] + dx)
            if not (0 <= n[0] < ny and 0 <= n[1] < nx) or not free[n]:
                continue
            if dy and dx and not (free[c[0] + dy, c[1]] and free[c[0], c[1] + dx]):
                continue  # no corner cutting between two closed cells
            new = cost[c] + step
            if new < cost.get(n, math.inf):
                cost[n], came[n] = new, c
                pushed += 1
                heapq.heappush(heap, (new + float(h[n]), pushed, n))
    return None


@dataclass
class Route:
    """A planned way to ``goal`` being followed; :meth:`carrot` once per cycle.  ``around_robots``: planned
    round the robots the map had as well as the walls (after a stall); ``clear_of``: those robots as
    (x_m, y_m, centre distance the avoidance keeps) discs, which the straight way to the carrot stays out of."""

    goal: tuple[float, float]
    points: list[tuple[float, float]]
    index: int = field(default=0)
    around_robots: bool = False
    clear_of: tuple[tuple[float, float, float], ...] = ()

    def carrot(self, x_m: float, y_m: float) -> tuple[float, float] | None:
        """Where to head from (x_m, y_m): ``LOOKAHEAD_M`` along the path from its point nearest to
        the robot (searched a little ahead of the last one, so a path that passes close to itself
        is not short-cut); None once the path's end is nearer than that (head for the goal then)."""
        window = self.points[self.index:self.index + round(2 * LOOKAHEAD_M / RESOLUTION_M) + 1]
        near = min(range(len(window)), key=lambda i: math.dist(window[i], (x_m, y_m)))
        self.index += near
        along = 0.0
        prev = (x_m, y_m)
        for i in range(self.index, len(self.points)):
            p = self.points[i]
            along += math.dist(prev, p)
            prev = p
            if along >= LOOKAHEAD_M:
                return self._cut_back(x_m, y_m, i)
        return None

    def _cut_back(self, x_m: float, y_m: float, i: int) -> tuple[float, float]:
        """The path's point ``i``, or the farthest one before it (not before the nearest) that the straight way
        from (x_m, y_m) reaches without cutting into a ``clear_of`` disc deeper than the robot already is: the
        lookahead cuts the corner of a way round a robot, and a patrol on the edge of a station keeper's
        clearance, its carrot across it, could neither head there nor turn away (it stood 20 s)."""
        for j in range(i, self.index, -1):
            p = self.points[j]
            if all(point_segment_distance((cx, cy), (x_m, y_m), p) >= min(r, math.hypot(x_m - cx, y_m - cy)) - 1e-3
                   for cx, cy, r in self.clear_of):
                return p
        return self.points[min(self.index + 1, len(self.points) - 1)]
