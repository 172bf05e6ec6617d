"""Narrow passages (agents/gates.py): which gaps are gates, and who waits outside one."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from tagswarm.agents.avoid import Box, Neighbour, box_distance
from tagswarm.agents.gates import LOOK_M, box_gap, gates, in_gate, must_wait

FOOT, CLEARANCE = 0.192, 0.1
ROOM = (Box(0.0, 3.0, 0.0, 5.0, 0.05), Box(0.0, -3.0, 0.0, 5.0, 0.05), Box(5.0, 0.0, 0.0, 0.05, 3.0),
        Box(-5.0, 0.0, 0.0, 0.05, 3.0))
# a wall at x = 0 with a 1 m door at y -0.5 .. 0.5
DOOR = (Box(0.0, -1.75, 0.0, 0.1, 1.25), Box(0.0, 1.75, 0.0, 0.1, 1.25))


def test_box_gap_is_the_distance_between_the_nearest_points() -> None:
    rng = np.random.default_rng(3)
    for _ in range(30):
        a = Box(0.0, 0.0, float(rng.uniform(-3, 3)), float(rng.uniform(0.1, 1)), float(rng.uniform(0.1, 1)))
        b = Box(float(rng.uniform(2.5, 4)), float(rng.uniform(-1, 1)), float(rng.uniform(-3, 3)),
                float(rng.uniform(0.1, 0.5)), float(rng.uniform(0.1, 0.5)))
        gap, centre = box_gap(a, b)
        # brute force: points on b's outline against a's distance field
        t = np.linspace(-1.0, 1.0, 401)
        c, s = math.cos(b.yaw_rad), math.sin(b.yaw_rad)
        lx = np.concatenate([t * b.half_x_m, t * b.half_x_m, np.full_like(t, b.half_x_m), np.full_like(t, -b.half_x_m)])
        ly = np.concatenate([np.full_like(t, b.half_y_m), np.full_like(t, -b.half_y_m), t * b.half_y_m, t * b.half_y_m])
        brute = float(np.min(box_distance(a, b.x_m + c * lx - s * ly, b.y_m + s * lx + c * ly)))
        assert gap == pytest.approx(brute, abs=2e-3)
        # the centre is halfway: as far from one box as from the other
        assert float(box_distance(a, *centre)) == pytest.approx(gap / 2, abs=1e-6)
        assert float(box_distance(b, *centre)) == pytest.approx(gap / 2, abs=1e-6)


def test_a_door_is_the_one_gate_of_two_rooms() -> None:
    found = gates((*ROOM, *DOOR), FOOT, CLEARANCE)
    assert len(found) == 1
    g = found[0]
    assert {id(g.a), id(g.b)} == {id(DOOR[0]), id(DOOR[1])}
    assert g.gap_m == pytest.approx(1.0) and g.centre == pytest.approx((0.0, 0.0), abs=0.11)
    # the gate and its mouths, not the rooms
    assert bool(in_gate(g, 0.0, 0.0, FOOT)) and bool(in_gate(g, -0.4, 0.1, FOOT))
    assert not bool(in_gate(g, -1.0, 0.0, FOOT)) and not bool(in_gate(g, 0.0, 2.0, FOOT))


@pytest.mark.parametrize(("gap_m", "gate"), [(0.3, False), (0.5, True), (1.0, True), (1.2, False), (2.4, False)])
def test_a_gap_is_a_gate_when_one_robot_fits_and_two_do_not(gap_m: float, gate: bool) -> None:
    wall = (Box(0.0, -1.5 - gap_m / 2, 0.0, 0.1, 1.5), Box(0.0, 1.5 + gap_m / 2, 0.0, 0.1, 1.5))
    assert len(gates(wall, FOOT, CLEARANCE)) == (1 if gate else 0)


def test_a_gap_a_third_box_closes_is_no_gate() -> None:
    plug = Box(0.0, 0.0, 0.0, 0.3, 0.3)
    assert gates((*DOOR, plug), FOOT, CLEARANCE) == ()


def _nb(rid: int, x: float, y: float, vx: float = 0.0, vy: float = 0.0) -> Neighbour:
    return Neighbour(rid, x, y, vx, vy, FOOT)


GATES = gates((*ROOM, *DOOR), FOOT, CLEARANCE)
EAST_MOUTH = (0.45 + LOOK_M - 0.1, 0.0, math.pi)  # heading west, the gate's mouth within LOOK_M
WEST = (-2.5, 0.0)


@pytest.mark.parametrize(("other", "waits"), [
    (_nb(1, 0.0, 0.0, 0.3, 0.0), True),  # in the door, coming this way
    (_nb(1, 0.0, 0.0, -0.3, 0.0), False),  # in the door, going the same way: follow it through
    (_nb(1, 0.0, 0.0), False),  # standing in the door: the avoidance's stall and make_way deal with it
    (_nb(1, -1.0, 0.1, 0.3, 0.0), True),  # coming from the other side, a lower id: it goes first
    (_nb(9, -1.0, 0.1, 0.3, 0.0), False),  # ... a higher id: it waits, this one goes
    (_nb(1, -1.0, 0.1, -0.3, 0.0), False),  # on the other side going away
    (_nb(9, 0.7, 0.2, 0.3, 0.0), True),  # out of it, between here and the door, not past yet
    (_nb(9, 0.7, 1.6, 0.3, 0.0), False),  # ... but 1.6 m to the side of this way: not on it
    (_nb(9, EAST_MOUTH[0] + 0.5, 0.3, 0.3, 0.0), False),  # out of it and past
])
def test_who_waits_outside_the_door(other: Neighbour, waits: bool) -> None:
    assert (must_wait(GATES, EAST_MOUTH, WEST, 5, (other,), FOOT) is not None) == waits


def test_nobody_waits_far_from_the_door_in_it_or_on_a_way_past_it() -> None:
    coming = (_nb(1, 0.0, 0.0, 0.3, 0.0),)
    assert must_wait(GATES, (2.5, 0.0, math.pi), WEST, 5, coming, FOOT) is None  # the mouth beyond LOOK_M
    assert must_wait(GATES, (0.3, 0.0, math.pi), WEST, 5, coming, FOOT) is None  # already in it
    assert must_wait(GATES, (2.0, -2.0, math.pi), (2.0, 2.0), 5, coming, FOOT) is None  # not going through
    assert must_wait((), EAST_MOUTH, WEST, 5, coming, FOOT) is None


def test_every_pair_of_the_room_s_own_walls_is_no_gate() -> None:
    # walls meet at the corners (no gap) or stand 6-10 m apart
    assert gates(ROOM, FOOT, CLEARANCE) == ()
    assert all(box_gap(a, b)[0] < 0.01 or box_gap(a, b)[0] > 5 for a, b in itertools.combinations(ROOM, 2))
