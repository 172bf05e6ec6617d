"""The built-in scenes as written: every one loads, says what it is in one line, starts
its robots clear of each other, the walls and the obstacles, and sends them only along
paths a robot fits through; and the hall, crowd and corridor scenes are what their
headers say."""

from __future__ import annotations

import itertools
import math

import pytest

from tagswarm.protocol import layout
from tagswarm.protocol import scenario as sc
from tagswarm.protocol.freespace import obstacle_clearance, segment_distance, sight_blocked, wall_clearance
from tagswarm.protocol.robotfill import mission_path
from tagswarm.protocol.scenario import Scenario, load_scenario

NEW = ("hall", "crowd", "corridor")
# room a driving robot keeps from walls and obstacles beyond its footprint (it steers
# to within agent.goal_tolerance_m of a waypoint, on an estimate that may be off)
WALL_MARGIN_M = 0.1


def _legs(s: Scenario, k: int) -> list[tuple[tuple[float, float], tuple[float, float]]]:
    x, y, _ = layout.start_poses(s)[k]
    return mission_path((x, y), s.mission(k))


def test_the_new_scenes_are_builtins_with_a_description() -> None:
    names = sc.builtin_names()
    assert set(NEW) <= set(names)
    desc = sc.builtin_descriptions()
    assert sorted(desc) == names
    for name, line in desc.items():
        assert 20 <= len(line) <= 120, name
        assert "\n" not in line
    assert desc["hall"].startswith("An 8 m x 6 m hall with two 1.6 m shelf blocks")


@pytest.mark.parametrize("name", sc.builtin_names())
def test_scene_starts_are_collision_free_and_inside(name: str) -> None:
    s = load_scenario(name)
    assert s.name == name
    r = layout.footprint_radius(s.robot)
    poses = layout.start_poses(s)
    assert len(poses) == s.robots.count
    for k, (x, y, _) in enumerate(poses):
        assert wall_clearance((x, y), s.arena) >= r + WALL_MARGIN_M, k
        assert obstacle_clearance((x, y), (x, y), s.arena) >= r + WALL_MARGIN_M, k
    for (i, p), (j, q) in itertools.combinations(enumerate(poses), 2):
        assert math.dist(p[:2], q[:2]) >= 2 * r + 0.1, (i, j)
    assert s.mission(s.map.origin_id).kind in ("hold", "patrol", "leapfrog")
    assert sorted(mi.robot for mi in s.missions) == list(s.robot_ids)


@pytest.mark.parametrize("name", sc.builtin_names())
def test_scene_waypoints_are_reachable(name: str) -> None:
    s = load_scenario(name)
    r = layout.footprint_radius(s.robot)
    for k in s.robot_ids:
        for a, b in _legs(s, k):
            assert wall_clearance(b, s.arena) >= r + WALL_MARGIN_M, (k, b)
            assert obstacle_clearance(a, b, s.arena) >= r + WALL_MARGIN_M, (k, a, b)


@pytest.mark.parametrize("name", NEW)
def test_new_scene_paths_never_run_through_a_standing_robot(name: str) -> None:
    s = load_scenario(name)
    r = layout.footprint_radius(s.robot)
    standing = [k for k in s.robot_ids if s.mission(k).kind == "hold"]
    for k in s.robot_ids:
        for h in standing:
            if h != k:
                p = layout.start_poses(s)[h][:2]
                assert min(segment_distance(a, b, p, p) for a, b in _legs(s, k)) >= 2 * r + 0.1, (k, h)


def test_hall() -> None:
    s = load_scenario("hall")
    assert (s.arena.size_x_m, s.arena.size_y_m, s.robots.count, s.duration_s) == (8.0, 6.0, 6, 90.0)
    shelves = s.arena.obstacles
    assert len(shelves) == 2
    mast = max(c.z_m for c in s.robot.cameras)
    for ob in shelves:
        assert max(ob.size_x_m, ob.size_y_m) == 1.6
        assert ob.size_z_m > mast  # they hide robots from the cameras
    assert s.map.origin_id == 0 and s.mission(0).kind == "hold"
    assert all(s.mission(k).kind != "hold" for k in range(1, 6))
    # the aisle patrol runs between the shelves; the loops go around one shelf each
    (ax, _), (bx, _) = s.mission(1).waypoints
    assert shelves[0].x_m < ax == bx < shelves[1].x_m
    for k, ob in ((2, shelves[0]), (3, shelves[1])):
        xs, ys = zip(*s.mission(k).waypoints, strict=True)
        assert s.mission(k).loop and min(xs) < ob.x_m < max(xs) and min(ys) < ob.y_m < max(ys)
    # a shelf stands between the origin and some of the patrols' waypoints
    origin = layout.start_poses(s)[0][:2]
    assert any(sight_blocked(origin, w, s.arena, s.robot.cube_center_z_m)
               for k in range(1, 6) for w in s.mission(k).waypoints)


def test_crowd() -> None:
    s = load_scenario("crowd")
    assert (s.arena.size_x_m, s.arena.size_y_m, s.robots.count) == (7.0, 7.0, 16)
    assert s.mission(s.map.origin_id).kind == "hold"
    movers = [k for k in s.robot_ids if k != s.map.origin_id]
    assert all(s.mission(k).kind == "patrol" for k in movers)
    for k in movers:
        (ax, ay), (bx, by) = s.mission(k).waypoints
        assert math.hypot(bx - ax, by - ay) <= 1.5  # short patrols
    # the lanes cross: all but one mover's lane crosses another mover's lane
    crossing = [k for k in movers if any(segment_distance(*s.mission(k).waypoints, *s.mission(j).waypoints) == 0.0
                                         for j in movers if j != k)]
    assert len(crossing) == len(movers) - 1


def test_corridor() -> None:
    s = load_scenario("corridor")
    assert (s.arena.size_x_m, s.arena.size_y_m) == (16.0, 2.5)
    poses = layout.start_poses(s)
    origin = poses[s.map.origin_id]
    assert origin[0] == min(p[0] for p in poses) and origin[0] < -s.arena.size_x_m / 2 + 1.0  # at one end
    kinds = {s.mission(k).kind for k in s.robot_ids if k != s.map.origin_id}
    assert kinds == {"hold", "patrol"}
    # a chain: ordered along the corridor, each robot within camera range of the next
    xs = sorted(p[0] for p in poses)
    assert all(b - a < s.agent.max_range_m for a, b in itertools.pairwise(xs))
    assert xs[-1] - xs[0] > s.agent.max_range_m  # and no robot sees from one end to the other
    for k in s.robot_ids:  # the patrols run along the corridor
        for a, b in _legs(s, k):
            assert a[1] == b[1]


def test_random_placement_keeps_clear_of_obstacles() -> None:
    s = load_scenario("warehouse", ['robots.placement="random"', "robots.count=40", "missions=[]"])
    r = layout.footprint_radius(s.robot)
    for k, (x, y, _) in enumerate(layout.start_poses(s)):
        assert obstacle_clearance((x, y), (x, y), s.arena) >= r + 0.1 - 1e-9, k
