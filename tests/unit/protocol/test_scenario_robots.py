"""``--robots N`` on every built-in scenario: robots beyond a scenario's explicit start
list get free start poses and missions, and the tag scheme is compacted when it runs
out of IDs (protocol/robotfill.py)."""

from __future__ import annotations

import itertools
import logging
import math
from pathlib import Path

import msgspec
import pytest

from tagswarm.protocol import layout, robotfill, tags
from tagswarm.protocol import scenario as sc
from tagswarm.protocol.freespace import obstacle_clearance, segment_distance, wall_clearance
from tagswarm.protocol.scenario import ScenarioError, load_scenario
from tagswarm.world.config import build_config, resolve_render_workers

COUNTS = (1, 2, 5, 8, 16, 32, 64)


def _error(name: str, overrides: list[str]) -> str:
    with pytest.raises(ScenarioError) as exc:
        load_scenario(name, overrides)
    text = str(exc.value)
    assert "\n" not in text
    return text


@pytest.mark.parametrize("n", COUNTS)
@pytest.mark.parametrize("name", sc.builtin_names())
def test_every_builtin_takes_any_robot_count(name: str, n: int) -> None:
    own = load_scenario(name)
    s = load_scenario(name, [f"robots.count={n}"])
    assert s.robots.count == n and s.robot_ids == tuple(range(n))
    poses = layout.start_poses(s)
    assert len(poses) == n
    r = layout.footprint_radius(s.robot)
    for k, (x, y, yaw) in enumerate(poses):
        assert all(math.isfinite(v) for v in (x, y, yaw))
        assert wall_clearance((x, y), s.arena) >= r, f"robot {k} in a wall"
        assert obstacle_clearance((x, y), (x, y), s.arena) >= r, f"robot {k} on an obstacle"
    for (i, p), (j, q) in itertools.combinations(enumerate(poses), 2):
        assert math.dist(p[:2], q[:2]) >= 2 * r + (robotfill.MARGIN_M if j >= own.robots.count else 0.0), (i, j)
    # the scenario's own robots keep their poses and missions
    kept = min(n, own.robots.count)
    assert poses[:kept] == layout.start_poses(own)[:kept]
    assert all(s.mission(k) == own.mission(k) for k in range(kept))
    # every robot has a mission of its own, and the origin is one of the robots
    assert sorted(mi.robot for mi in s.missions) == list(range(n))
    assert s.map.origin_id < n
    # distinct tag IDs of the family, none of them a landmark's
    ids = [t for k in s.robot_ids for t in s.tag_ids(k)]
    assert len(set(ids)) == 6 * n
    assert all(0 <= t < tags.family_size(s.tags.family) for t in ids)
    assert not {lm.id for lm in s.landmarks} & set(ids)


@pytest.mark.parametrize("name", sc.builtin_names())
def test_placed_robots_face_a_robot_and_patrol_clear_lanes(name: str) -> None:
    own = load_scenario(name)
    s = load_scenario(name, ["robots.count=16"])
    r = layout.footprint_radius(s.robot)
    poses = layout.start_poses(s)
    given = [p[:2] for p in poses[:own.robots.count]]
    paths = [robotfill.mission_path(p[:2], s.mission(k)) for k, p in enumerate(poses)]
    for k in range(own.robots.count, 16):
        x, y, yaw = poses[k]
        # heading points straight at one of the scenario's robots
        assert any(abs(math.remainder(math.atan2(q[1] - y, q[0] - x) - yaw, math.tau)) < 1e-5 for q in given), k
        mi = s.mission(k)
        assert mi.kind in ("hold", "patrol")
        if mi.kind == "hold":
            continue
        (ax, ay), (bx, by) = mi.waypoints
        assert (ax, ay) == (x, y)
        assert 0.5 - 1e-6 <= math.hypot(bx - ax, by - ay) <= 0.8 + 1e-6
        assert abs(math.remainder(math.atan2(by - ay, bx - ax) - yaw, math.tau)) < 1e-5  # straight ahead
        assert wall_clearance((bx, by), s.arena) >= r + robotfill.MARGIN_M
        assert obstacle_clearance((ax, ay), (bx, by), s.arena) >= r + robotfill.MARGIN_M
        gap = 2 * r + robotfill.MARGIN_M + robotfill.PATROL_CLEARANCE_M
        for j, path in enumerate(paths):
            if j != k:
                assert min(segment_distance((ax, ay), (bx, by), c, d) for c, d in path) >= gap - 1e-9, (k, j)


def test_paper_with_eight_robots_logs_one_line(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.INFO, logger="tagswarm.protocol.scenario"):
        s = load_scenario("paper", ["robots.count=8"])
    lines = [rec.getMessage() for rec in caplog.records]
    assert len(lines) == 1
    assert lines[0].startswith("robots 4-7: no start pose/mission in scenario 'paper': placed at free poses")
    assert "facing robot 0" in lines[0] and "holding" in lines[0] and "patrolling" in lines[0]
    # placed a lattice spacing (1 m) away from every robot and every patrol lane of the scenario
    poses = layout.start_poses(s)
    paths = [robotfill.mission_path(p[:2], s.mission(k)) for k, p in enumerate(poses[:4])]
    for p in poses[4:]:
        assert min(segment_distance(p[:2], p[:2], c, d) for path in paths for c, d in path) >= 1.0 - 1e-9
    assert s.tags.id_stride == 10  # 8 robots fit the paper's ID scheme


def test_nothing_logged_when_the_scenario_places_every_robot(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.INFO, logger="tagswarm.protocol.scenario"):
        load_scenario("paper")
        load_scenario("paper", ["robots.count=2"])
    assert caplog.records == []


def test_robots_left_without_a_mission_are_named_once_where_the_scenario_is_resolved(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    over = ['robots.placement="random"', "robots.count=6", "missions=[]"]
    with caplog.at_level(logging.INFO, logger="tagswarm.protocol.scenario"):
        s = load_scenario("paper", over)
        one = load_scenario("paper", [*over, 'missions=[{robot = 3, kind = "patrol", waypoints = [[0.0, 0.0]]}]'])
    lines = [rec.getMessage() for rec in caplog.records]
    # the origin robot holding station is the map's reference, not an oversight
    assert lines == ["robots 1-5: no mission in scenario 'paper': holding station where they start (a [[missions]] "
                     'entry with kind = "patrol" or "waypoints" moves one)',
                     "robots 1-2, 4-5: no mission in scenario 'paper': holding station where they start (a "
                     '[[missions]] entry with kind = "patrol" or "waypoints" moves one)']
    assert one.mission(3).kind == "patrol" and s.mission(2).kind == "hold"
    caplog.clear()
    path = tmp_path / "scenario.json"
    path.write_bytes(msgspec.json.encode(s))
    with caplog.at_level(logging.INFO, logger="tagswarm.protocol.scenario"):
        assert load_scenario(str(path)) == s
    assert caplog.records == []  # every child process loads that copy: it says nothing again
    assert robotfill.idle_note(load_scenario("hall")) is None


def test_fewer_robots_than_the_list_keeps_the_first() -> None:
    s = load_scenario("paper", ["robots.count=2"])
    assert layout.start_poses(s) == layout.start_poses(load_scenario("paper"))[:2]
    assert [mi.robot for mi in s.missions] == [0, 1]


def test_robots_flag_environment_and_set_agree() -> None:
    # the world resolves the automatic render.workers for its machine
    want = resolve_render_workers(load_scenario("paper", ["robots.count=8"]))
    assert build_config(["--robots", "8"], {}).scenario == want
    assert build_config([], {"TAGSWARM_ROBOTS": "8"}).scenario == want
    assert build_config(["--set", "robots.count=8"], {}).scenario == want


def test_same_scenario_same_poses_and_a_resolved_copy_loads_unchanged(tmp_path: Path,
                                                                      caplog: pytest.LogCaptureFixture) -> None:
    a, b = load_scenario("crowd", ["robots.count=40"]), load_scenario("crowd", ["robots.count=40"])
    assert a == b
    path = tmp_path / "scenario.json"
    path.write_bytes(msgspec.json.encode(a))
    caplog.clear()  # the lines of the loads above, if this worker logs INFO already
    with caplog.at_level(logging.INFO, logger="tagswarm.protocol.scenario"):
        assert load_scenario(str(path)) == a
    assert caplog.records == []  # the resolved copy every child process loads is complete


def test_ring_and_grid_placements_are_left_alone() -> None:
    for placement in ("ring", "grid"):
        over = [f'robots.placement="{placement}"', "robots.count=6", "missions=[]"]
        s = load_scenario("paper", over)
        assert s.robots.start == load_scenario("paper").robots.start  # unused by these placements
        assert s.missions == ()


def test_a_placed_origin_robot_holds() -> None:
    s = load_scenario("paper", ["robots.count=8", "map.origin_id=6"])
    assert s.mission(6).kind == "hold"
    _error("paper", ["robots.count=4", "map.origin_id=6"])


def test_a_mission_given_for_a_placed_robot_is_kept() -> None:
    s = load_scenario("paper", ["robots.count=5",
                                'missions=[{robot=0}, {robot=4, kind="patrol", waypoints=[[2.5, 2.5], [2.5, -2.5]]}]'])
    assert s.mission(4).waypoints == ((2.5, 2.5), (2.5, -2.5))
    assert sorted(mi.robot for mi in s.missions) == [0, 4]


# --------------------------------------------------------------------------- too many robots


def test_too_many_robots_for_a_small_arena() -> None:
    text = _error("paper", ["robots.count=40", "arena.size_x_m=4.0", "arena.size_y_m=4.0"])
    assert text.startswith("robots.count=40: scenario 'paper' places 4 robots and has room for only ")
    most = int(text.split("room for only ")[1].split()[0])
    assert 0 < most < 36
    # and exactly that many more do fit
    fits = load_scenario("paper", [f"robots.count={4 + most}", "arena.size_x_m=4.0", "arena.size_y_m=4.0"])
    assert fits.robots.count == 4 + most


def test_two_hundred_robots_do_not_fit_the_paper_arena() -> None:
    assert _error("paper", ["robots.count=200"]).startswith("robots.count=200: scenario 'paper' places 4 robots")


def test_crowded_hall_puts_robots_in_lanes_only_when_it_must(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.INFO, logger="tagswarm.protocol.scenario"):
        load_scenario("hall", ["robots.count=40"])
        load_scenario("hall", ["robots.count=64"])
    first, second = (rec.getMessage() for rec in caplog.records if "no start pose" in rec.getMessage())
    assert "stand in other robots' paths" not in first
    assert "stand in other robots' paths (no room elsewhere)" in second


# --------------------------------------------------------------------------- tag IDs


def test_paper_ids_last_to_59_robots_then_compact(caplog: pytest.LogCaptureFixture) -> None:
    s59 = load_scenario("paper", ["robots.count=59"])
    assert (s59.tags.id_base, s59.tags.id_stride) == (1, 10)
    assert s59.tag_ids(58)[-1] == 586  # the family's last ID
    with caplog.at_level(logging.INFO, logger="tagswarm.protocol.scenario"):
        s60 = load_scenario("paper", ["robots.count=60"])
    assert (s60.tags.id_base, s60.tags.id_stride) == (1, 6)
    assert s60.tag_ids(0) == (1, 2, 3, 4, 5, 6) and s60.tag_ids(59) == tuple(range(355, 361))
    note = next(rec.getMessage() for rec in caplog.records if rec.getMessage().startswith("tags:"))
    assert "up to 596 but tag36h11 has 0..586" in note and "tags.id_stride=6" in note


def test_compact_ids_step_around_landmarks() -> None:
    # robot 10 would carry 101..106 at the paper's stride, three of them landmark IDs
    assert load_scenario("landmarks", ["robots.count=10"]).tags.id_stride == 10
    s = load_scenario("landmarks", ["robots.count=11"])
    assert (s.tags.id_base, s.tags.id_stride) == (1, 6)
    s = load_scenario("landmarks", ["robots.count=64"])  # 384 IDs: only above the landmarks
    assert (s.tags.id_base, s.tags.id_stride) == (104, 6)


def test_compact_ids_in_a_small_family() -> None:
    small = ['tags.family="tag16h5"', "tags.size_m=0.12", "tags.id_base=0", "tags.id_stride=6"]
    assert load_scenario("paper", [*small, "robots.count=5"]).tag_ids(4) == (24, 25, 26, 27, 28, 29)
    s = load_scenario("paper", ['tags.family="tag16h5"', "tags.size_m=0.12", "robots.count=3", "tags.id_stride=8",
                                'robots.placement="ring"'])
    assert s.tags.id_stride == 8  # 1..22 fit
    assert _error("paper", [*small, "robots.count=6"]) == (
        "robots.count=6: tag16h5 has 30 tag IDs, room for at most 5 robots at 6 IDs each (tags.family, robots.count)")
    # a stride of 7 holds the paper's 4 robots (1..27) but not a fifth (29..34): compacted from ID 0
    grown = load_scenario("paper", ['tags.family="tag16h5"', "tags.size_m=0.12", "tags.id_stride=7", "robots.count=5"])
    assert (grown.tags.id_base, grown.tags.id_stride) == (0, 6)
    text = _error("paper", ['tags.family="tag16h5"', "tags.size_m=0.12", "robots.count=6",
                            "landmarks=[{id=0, x_m=-3.4, y_m=0.0}]", "tags.id_stride=7"])
    assert "(1 used by landmarks), room for at most 4 robots" in text


def test_a_scheme_that_fails_the_scenarios_own_robots_is_not_rewritten() -> None:
    text = _error("paper", ["landmarks=[{id=11, x_m=-3.4, y_m=0.0}]"])
    assert "tag ID 11 is used twice" in text
    text = _error("paper", ["tags.id_stride=3", "robots.count=64"])
    assert "is used twice" in text


@pytest.mark.parametrize("name", ["hall", "warehouse", "corridor"])
@pytest.mark.parametrize("n", [2, 9, 16, 64])
def test_grid_placement_keeps_off_obstacles_in_any_arena(name: str, n: int) -> None:
    """A grid in a scene with shelves or pallets (or a 16 m x 2.5 m corridor) used to put robots on
    them, or on each other, and the scenario failed to load."""
    s = load_scenario(name, [f"robots.count={n}", 'robots.placement="grid"'])
    poses = layout.start_poses(s)
    r = layout.footprint_radius(s.robot)
    assert len(poses) == n
    for x, y, _ in poses:
        assert obstacle_clearance((x, y), (x, y), s.arena) >= r
    for a, b in itertools.combinations(poses, 2):
        assert math.dist(a[:2], b[:2]) >= 2 * r


def test_grid_in_an_open_square_arena_is_the_plain_lattice() -> None:
    s = load_scenario("paper", ["robots.count=8", 'robots.placement="grid"'])
    xy = [(round(x, 6), round(y, 6)) for x, y, _ in layout.start_poses(s)]
    w = s.arena.size_x_m / 2 - (layout.footprint_radius(s.robot) + s.arena.wall_thickness_m + 0.3)
    cells = [(round(-w + 2 * w * (c + 0.5) / 3, 6), round(-w + 2 * w * (r + 0.5) / 3, 6)) for r in range(3)
             for c in range(3)]
    assert xy == cells[:8]


@pytest.mark.parametrize(("waypoint", "needle"), [
    ("[10.0, 0.0]", "missions[1].waypoints[1]=(10, 0): a robot there would not be inside the arena walls"),
    ("[0.0, -3.4]", "missions[1].waypoints[1]=(0, -3.4): a robot there would not be inside the arena walls"),
])
def test_a_waypoint_a_robot_cannot_reach_is_refused_naming_it(waypoint: str, needle: str) -> None:
    with pytest.raises(ScenarioError) as exc:
        load_scenario("paper", [f'missions=[{{robot=0, kind="hold"}}, {{robot=1, kind="patrol", '
                                f'waypoints=[[0.0, 0.0], {waypoint}]}}]'])
    assert needle in str(exc.value)


def test_a_waypoint_on_an_obstacle_is_refused_naming_both() -> None:
    s = load_scenario("hall")
    ob = s.arena.obstacles[0]
    with pytest.raises(ScenarioError) as exc:
        load_scenario("hall", [f'missions=[{{robot=1, kind="patrol", waypoints=[[{ob.x_m}, {ob.y_m}]]}}]'])
    assert "missions[0].waypoints[0]" in str(exc.value) and "overlap arena.obstacles[0]" in str(exc.value)
