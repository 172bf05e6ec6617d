"""Robots that start where no robot that can be placed sees them (pure geometry), and the line
that names them when a scenario is loaded."""

from __future__ import annotations

import logging

import pytest

from tagswarm.protocol import scenario as sc
from tagswarm.protocol.scenario import load_scenario
from tagswarm.protocol.sightlines import reading_range_m, unseen_at_start

# a 10 x 5 m room, origin robot 0 in the south-west corner, a 3 m wall-like shelf across the middle
ROOM = ["arena.size_x_m=10.0", "arena.size_y_m=5.0", 'robots.placement="explicit"', "missions=[]"]


def _room(starts: str, shelf_z: float = 1.5, *more: str) -> sc.Scenario:
    return load_scenario("paper", [*ROOM, f"robots.count={starts.count('x_m')}", f"robots.start=[{starts}]",
                                   f"arena.obstacles=[{{x_m=0.0, y_m=0.3, size_x_m=0.5, size_y_m=3.0, "
                                   f"size_z_m={shelf_z}}}]", *more])


def test_a_robot_behind_a_tall_shelf_is_unseen_and_a_low_one_hides_nobody() -> None:
    starts = "{x_m=-2.0, y_m=0.5}, {x_m=2.0, y_m=0.5}, {x_m=-3.0, y_m=-1.5}"
    assert unseen_at_start(_room(starts)) == [1]
    s = _room(starts, 0.1)  # a pallet below the cubes' centres
    assert s.arena.obstacles[0].size_z_m < s.robot.cube_center_z_m and unseen_at_start(s) == []


def test_a_chain_of_robots_in_sight_reaches_beyond_one_camera() -> None:
    s = load_scenario("paper", [*ROOM, "arena.size_x_m=14.0", "robots.count=4", "robots.start=[{x_m=-6.0, y_m=0.0}, "
                                "{x_m=-2.0, y_m=0.0}, {x_m=2.0, y_m=0.0}, {x_m=6.5, y_m=0.0}]"])
    reach = reading_range_m(s)
    assert 4.0 < reach < 4.4  # 320x240, 60 deg, 0.16 m tags, ideal camera: 10.5 px across a tag
    # 4 m links place robots 1 and 2 (robot 2 is 8 m from the origin robot); robot 3 is 4.5 m on
    assert unseen_at_start(s) == [3]


def test_the_realistic_camera_reads_nearer() -> None:
    starts = "{x_m=-2.0, y_m=-1.5}, {x_m=1.9, y_m=-1.5}"
    assert unseen_at_start(_room(starts, 0.1)) == []
    realistic = _room(starts, 0.1, "camera.preset=realistic")
    assert 3.0 < reading_range_m(realistic) < 3.8 and unseen_at_start(realistic) == [1]
    # a 120 deg lens at 320x240 (an equidistant fisheye through the realistic preset) reads to ~2 m
    # (bench/lens_range.py: 7 of 12 frames at 2.0 m), a 640x480 one twice as far (the rig)
    wide = _room(starts, 0.1, "camera.preset=realistic", "robot.cameras=[{hfov_deg=120.0}]")
    assert 1.7 < reading_range_m(wide) < 2.1
    assert 3.5 < reading_range_m(load_scenario("rig")) < 4.0


@pytest.mark.parametrize("name", sc.builtin_names())
def test_every_builtin_places_every_robot_from_the_start(name: str) -> None:
    assert unseen_at_start(load_scenario(name)) == []


def test_landmarks_and_the_line_logged_where_the_scenario_is_resolved(caplog: pytest.LogCaptureFixture) -> None:
    assert unseen_at_start(load_scenario("landmarks", ["robots.count=12"])) == []
    starts = "{x_m=-2.0, y_m=0.5}, {x_m=2.0, y_m=0.5}, {x_m=2.0, y_m=-0.5}, {x_m=-3.0, y_m=-1.5}"
    caplog.clear()  # the landmarks' own lines (robots filled in, tag IDs), if this worker logs INFO already
    with caplog.at_level(logging.INFO, logger="tagswarm.protocol.scenario"):
        _room(starts, 1.5, 'missions=[{robot=1, kind="hold"}, {robot=2, kind="hold"}, {robot=3, kind="hold"}]')
    lines = [r.getMessage() for r in caplog.records]
    assert lines[0] == (
        "robots 1-2: at the start no robot that can be placed in scenario 'paper' is within sight (a camera reads "
        "a cube to about 4.2 m here; obstacles as tall as the cubes hide one): unplaced until a mission brings one "
        "within sight of a placed robot, and time localised counts that time as lost")
    # robot 3, within its reach, stands behind it (protocol/robotfill.blind_origin_note)
    assert len(lines) == 2 and lines[1].startswith("robot 0, the map's origin, starts with no robot in its cameras'")
