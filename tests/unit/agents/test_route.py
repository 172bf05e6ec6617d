"""The way round the room after a stall (agents/route.py): A* on the known walls, obstacles and robots."""

from __future__ import annotations

import itertools
import math

from tagswarm.agents.avoid import Box, Neighbour, box_distance
from tagswarm.agents.route import RESOLUTION_M, Route, blocked, plan, static_grid

ROOM = (Box(0.0, 3.0, 0.0, 4.0, 0.05), Box(0.0, -3.0, 0.0, 4.0, 0.05), Box(4.0, 0.0, 0.0, 0.05, 3.0),
        Box(-4.0, 0.0, 0.0, 0.05, 3.0))
SHELF = Box(0.0, -0.25, 0.0, 0.3, 2.75)  # from the south wall to 0.45 m short of the north wall
KEEP = 0.35


def _length(points: list[tuple[float, float]]) -> float:
    return sum(math.dist(a, b) for a, b in itertools.pairwise(points))


def test_no_way_through_a_gap_narrower_than_the_room_asked_for() -> None:
    grid = static_grid((*ROOM, SHELF), KEEP)
    assert grid is not None
    assert plan(grid, (-2.0, -1.0), (2.0, -1.0), (), KEEP) is None  # a 0.45 m gap, 0.7 m needed
    wide = static_grid((*ROOM, SHELF), 0.2)  # 0.4 m needed: round the north end
    assert wide is not None
    path = plan(wide, (-2.0, -1.0), (2.0, -1.0), (), 0.2)
    assert path is not None and max(y for _, y in path) > 2.0
    assert min(float(box_distance(b, x, y)) for b in (*ROOM, SHELF) for x, y in path) > 0.2
    assert 9.0 < _length(path) < 11.0  # up 3.6 m, across, down 3.6 m: the short way


def test_robots_the_map_has_close_the_way_and_start_and_goal_stay_open() -> None:
    grid = static_grid(ROOM, 0.2)
    assert grid is not None
    free = plan(grid, (-2.0, 0.0), (2.0, 0.0), (), 0.2)
    assert free is not None and abs(_length(free) - 4.0) < 0.2  # straight across
    wall_of_robots = tuple(Neighbour(k, 0.0, y / 2, 0.0, 0.0, 0.2) for k, y in enumerate(range(-6, 7)))
    assert plan(grid, (-2.0, 0.0), (2.0, 0.0), wall_of_robots, 0.2) is None
    # a goal within the room asked for (beside a wall) stays open
    by_wall = plan(grid, (-2.0, 0.0), (3.8, 0.0), (), 0.2)
    assert by_wall is not None and math.dist(by_wall[-1], (3.8, 0.0)) < RESOLUTION_M


def test_the_carrot_runs_ahead_along_the_route_and_ends_near_the_goal() -> None:
    points = [(x / 10, 0.0) for x in range(0, 31)] + [(3.0, y / 10) for y in range(1, 21)]
    route = Route((3.0, 2.0), points)
    c = route.carrot(0.0, 0.05)
    assert c is not None and abs(c[0] - 0.6) < 0.11 and c[1] == 0.0
    for x in range(1, 29):  # driving along the first leg
        c = route.carrot(x / 10, 0.0)
    assert c is not None and c[0] == 3.0 and 0.2 < c[1] < 0.6  # round the corner: on the second leg
    for y in range(1, 15):
        assert route.carrot(3.0, y / 10) is not None
    assert route.carrot(3.0, 1.5) is None  # the end is nearer than the lookahead: head for the goal itself


def test_a_straight_way_is_blocked_where_it_passes_a_box_closer_than_asked_not_at_its_ends() -> None:
    keep = 0.29
    assert not blocked((*ROOM, SHELF), (-2.0, 2.7), (-2.0, -2.0), keep)  # along the west side, clear
    assert blocked((*ROOM, SHELF), (-2.0, -1.0), (2.0, -1.0), keep)  # through the shelf
    assert blocked((*ROOM, SHELF), (-1.0, 2.6), (1.0, 2.6), keep)  # past the shelf's end, 0.1 m from it
    assert not blocked(ROOM, (-1.0, 2.6), (1.0, 2.6), keep)  # 0.35 m from the room's wall
    # a robot that starts, and a goal that lies, beside a wall: the avoidance handles that room
    assert not blocked(ROOM, (-3.8, 0.0), (3.8, 0.0), keep)
    assert not blocked(ROOM, (0.0, 2.8), (0.0, 2.8 - 2 * keep), keep)  # too short to have a middle
    assert not blocked((), (-2.0, -1.0), (2.0, -1.0), keep)
