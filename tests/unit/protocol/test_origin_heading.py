"""The origin robot's start heading (protocol/layout.py): ``grid`` and ``random`` turn it to
see the most robots, since its first pose is the map frame and an origin that sees nobody
leaves the map's heading to the faces of its own cube; an explicit scene whose origin sees
nobody is told so once (protocol/robotfill.py)."""

from __future__ import annotations

import math
from pathlib import Path

import msgspec
import pytest

from tagswarm.protocol import layout, robotfill
from tagswarm.protocol.scenario import load_scenario
from tagswarm.protocol.scenario_schema import Scenario

# a user's store room: 10 robots on a grid, a partition and a column; with seed 23 the drawn
# heading of robot 0 faced the south wall (arena yaw -1.62) and the map came out turned by 1.4 deg
STOREROOM = """
name = "storeroom"
seed = 23
duration_s = 30.0
[arena]
size_x_m = 10.0
size_y_m = 6.0
[[arena.obstacles]]
x_m = 1.0
y_m = -1.6
size_x_m = 0.2
size_y_m = 2.8
size_z_m = 1.5
[[arena.obstacles]]
x_m = -2.5
y_m = 1.2
size_x_m = 0.5
size_y_m = 0.5
size_z_m = 2.0
[robots]
count = 10
placement = "%s"
"""


def _scene(tmp_path: Path, placement: str = "grid", *overrides: str) -> Scenario:
    path = tmp_path / "storeroom.toml"
    path.write_text(STOREROOM % placement)
    return load_scenario(str(path), list(overrides))


def _brute_best(s: Scenario, poses: list[tuple[float, float, float]]) -> int:
    k = s.map.origin_id
    return max(len(layout.in_view(s, poses, k, math.radians(d / 4))) for d in range(-720, 720))


@pytest.mark.parametrize("placement", ["grid", "random"])
def test_the_origin_faces_the_most_robots_and_only_it_turns(tmp_path: Path, placement: str) -> None:
    s = _scene(tmp_path, placement)
    poses = layout.start_poses(s)
    seen = layout.in_view(s, poses, 0)
    assert len(seen) >= 1 and len(seen) == _brute_best(s, poses)
    # with robot 1 as the origin, robot 0 keeps the heading drawn for it and robot 1 turns: every other
    # robot's pose is the same draw either way
    other = layout.start_poses(load_scenario(str(tmp_path / "storeroom.toml"), ["map.origin_id=1"]))
    assert [p for k, p in enumerate(poses) if k > 1] == [p for k, p in enumerate(other) if k > 1]
    assert poses[0][:2] == other[0][:2] and poses[1][:2] == other[1][:2]
    if placement == "grid":
        assert other[0][2] == pytest.approx(-1.62, abs=0.01)  # the drawn heading: at the wall, nobody in view
        assert layout.in_view(s, other, 0) == []
    assert robotfill.blind_origin_note(s) is None


@pytest.mark.parametrize("placement", ["grid", "random"])
def test_a_run_folder_keeps_the_drawn_poses_not_the_draw(tmp_path: Path, placement: str) -> None:
    # a run folder's scenario.json said "grid" and seed 23: re-evaluated or replayed after the origin heading
    # came in, the origin turned 2.3 rad and the map frame with it.  Pinned, it keeps the poses it ran with.
    s = _scene(tmp_path, placement)
    pinned = layout.pinned(s)
    assert pinned.robots.placement == "explicit" and len(pinned.robots.start) == s.robots.count
    path = tmp_path / "scenario.json"
    path.write_bytes(msgspec.json.encode(pinned))
    again = load_scenario(str(path))
    assert layout.start_poses(again) == layout.start_poses(s)  # exact: JSON floats round-trip
    assert layout.arena_to_map(again) == layout.arena_to_map(s)
    # the draw that a later version makes no longer matters: the file holds the poses themselves
    redrawn = load_scenario(str(path), ["seed=24"])
    assert layout.start_poses(redrawn) == layout.start_poses(s)
    assert layout.start_poses(load_scenario(str(tmp_path / "storeroom.toml"), ["seed=24"])) != layout.start_poses(s)
    for name in ("paper", "hall"):  # explicit scenes (and rings) are written as they are
        assert layout.pinned(load_scenario(name)) == load_scenario(name)


def test_the_origin_is_not_turned_when_landmarks_hold_the_map() -> None:
    s = load_scenario("landmarks", ['robots.placement="grid"'])
    plain = load_scenario("landmarks", ['robots.placement="grid"', "map.origin_id=1"])
    assert layout.start_poses(s) == layout.start_poses(plain)  # nobody anchors the map: nobody turns


def test_an_explicit_origin_that_sees_nobody_is_told_how_to_face_the_swarm(tmp_path: Path) -> None:
    grid = layout.start_poses(_scene(tmp_path, "grid", "map.origin_id=1"))  # robot 0 as drawn, at the wall
    starts = ", ".join(f"{{x_m = {x!r}, y_m = {y!r}, yaw_rad = {a!r}}}" for x, y, a in grid)
    path = tmp_path / "blind.toml"
    path.write_text(STOREROOM.replace('placement = "%s"', f"start = [{starts}]"))
    s = load_scenario(str(path))
    note = robotfill.blind_origin_note(s)
    assert note is not None and note.startswith("robot 0, the map's origin, starts with no robot in its cameras' view")
    assert "facing 2 robot(s), e.g. yaw_rad = 0.00" in note
    path.write_text(STOREROOM.replace('placement = "%s"', "start = [" + starts.replace(
        f"yaw_rad = {grid[0][2]!r}", "yaw_rad = 0.0", 1) + "]"))
    assert robotfill.blind_origin_note(load_scenario(str(path))) is None
    for name in ("paper", "hall", "crowd", "corridor", "kidnap"):
        assert robotfill.blind_origin_note(load_scenario(name)) is None, name


def _pair(*overrides: str) -> Scenario:
    """Robot 0 at the arena's centre facing +x, robot 1 2 m away at a bearing of 12 deg."""
    b = math.radians(12.0)
    return load_scenario("paper", ['robots.placement="explicit"', "robots.count=2", "missions=[]",
                                   f"robots.start=[{{x_m=0.0, y_m=0.0, yaw_rad=0.0}}, "
                                   f"{{x_m={2 * math.cos(b)}, y_m={2 * math.sin(b)}}}]", *overrides])


def test_each_camera_of_a_rig_sees_through_its_own_field_and_range() -> None:
    # 12 deg off the narrow camera's axis is outside its 10 deg half field; the wide one, turned 30 deg, holds it
    rig = _pair('robot.cameras=[{name="narrow", hfov_deg=20.0}, {name="wide", hfov_deg=100.0, yaw_deg=30.0}]')
    assert layout.in_view(rig, layout.start_poses(rig), 0) == [(1, pytest.approx(math.radians(18.0)))]
    assert layout.in_view(_pair('robot.cameras=[{hfov_deg=20.0}]'), layout.start_poses(_pair()), 0) == []
    # a 120 deg lens at 320x240 reads to about 2 m (protocol/readrange.py): robot 1 at 2.0 m is just beyond it,
    # though the rig's 640x480 camera reads farther
    wide_low = _pair('camera.preset="realistic"', 'robot.cameras=[{name="wide", hfov_deg=120.0}, '
                     '{name="far", width=640, height=480, hfov_deg=60.0, yaw_deg=180.0}]')
    assert layout.in_view(wide_low, layout.start_poses(wide_low), 0) == []


def test_an_obstacle_as_tall_as_the_cubes_hides_a_robot_a_low_one_does_not() -> None:
    mid = "x_m=1.0, y_m=0.21, size_x_m=0.1, size_y_m=0.4"
    tall = _pair(f"arena.obstacles=[{{{mid}, size_z_m=1.0}}]")
    low = _pair(f"arena.obstacles=[{{{mid}, size_z_m=0.05}}]")
    assert layout.in_view(tall, layout.start_poses(tall), 0) == []
    assert [j for j, _ in layout.in_view(low, layout.start_poses(low), 0)] == [1]


def test_a_field_of_view_narrower_than_twice_the_margin_still_sees_straight_ahead() -> None:
    s = _pair("robot.cameras=[{hfov_deg=6.0}]")
    assert layout.in_view(s, layout.start_poses(s), 0, math.radians(12.0)) == [(1, pytest.approx(0.0, abs=1e-9))]
    assert layout.in_view(s, layout.start_poses(s), 0) == []
