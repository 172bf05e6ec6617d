"""tagswarm.protocol.scenario: the built-in scenario, overrides, validation and start poses."""

from __future__ import annotations

import itertools
import math
from pathlib import Path
from typing import Any

import msgspec
import pytest

from tagswarm.protocol import layout
from tagswarm.protocol import scenario as sc
from tagswarm.protocol.scenario import ScenarioError, load_scenario

EXPLICIT_2 = ['robots.placement="explicit"', "robots.count=2"]


def _error(overrides: list[str], name: str = "paper") -> str:
    with pytest.raises(ScenarioError) as exc:
        load_scenario(name, overrides)
    text = str(exc.value)
    assert "\n" not in text
    return text


# --------------------------------------------------------------------------- the paper scenario


def test_paper_is_a_builtin() -> None:
    assert "paper" in sc.builtin_names()
    assert load_scenario() == load_scenario("paper")


def test_a_folder_named_like_a_builtin_does_not_hide_it(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # `tagswarm up --scenario nudge --out nudge` twice: the first run's folder made the second exit 2
    # ("cannot read scenario 'nudge': Is a directory")
    (tmp_path / "paper").mkdir()
    monkeypatch.chdir(tmp_path)
    assert load_scenario("paper").name == "paper"


def test_paper_scenario() -> None:
    s = load_scenario("paper")
    assert s.name == "paper"
    assert s.seed == 0
    assert s.robots.count == 4
    assert s.robot_ids == (0, 1, 2, 3)
    assert (s.arena.size_x_m, s.arena.size_y_m) == (7.0, 7.0)
    assert s.tags.family == "tag36h11"
    assert s.tags.size_m == 0.16
    assert s.robot.cube_edge_m == 0.20
    assert [c.name for c in s.robot.cameras] == ["front"]
    assert (s.robot.cameras[0].width, s.robot.cameras[0].height) == (320, 240)
    assert s.clock.mode == "realtime"
    assert s.render.workers == -1  # automatic: in-process in lockstep and for a few robots


def test_paper_tag_ids() -> None:
    s = load_scenario("paper")
    assert s.tag_ids(0) == (1, 2, 3, 4, 5, 6)
    assert s.tag_ids(1) == (11, 12, 13, 14, 15, 16)
    for k in s.robot_ids:
        assert s.tag_ids(k) == tuple(10 * k + f for f in range(1, 7))
    every = [t for k in s.robot_ids for t in s.tag_ids(k)]
    assert len(every) == len(set(every)) == 24


def test_paper_tag_fits_cube_exactly() -> None:
    # tag36h11: 8 black cells + 2 quiet-zone cells -> 0.16 * 10 / 8 = 0.20, the cube edge; allowed
    s = load_scenario("paper")
    assert math.isclose(sc.tags.min_face_for_tag(s.tags.family, s.tags.size_m), s.robot.cube_edge_m)


def test_cube_center_height() -> None:
    s = load_scenario("paper")
    assert math.isclose(s.robot.cube_center_z_m, 0.02 + 0.10 + 0.10)


# --------------------------------------------------------------------------- errors


def test_duplicate_tag_ids() -> None:
    text = _error(["tags.id_stride=3"])
    assert "tags" in text and "tag ID 4 is used twice" in text
    assert "robot 0" in text and "robot 1" in text


def test_tag_id_beyond_family() -> None:
    text = _error(['tags.family="tag16h5"', "tags.size_m=0.12", "robots.count=6"])
    assert "tag16h5" in text and "0..29" in text
    assert "tag ID 31" in text and "robot 3" in text


def test_tag16h5_fits_when_ids_fit() -> None:
    s = load_scenario("paper", ['tags.family="tag16h5"', "tags.size_m=0.12", "robots.count=3"])
    assert s.tag_ids(2) == (21, 22, 23, 24, 25, 26)


def test_negative_camera_width() -> None:
    text = _error(["robot.cameras=[{width=-5}]"])
    assert "robot.cameras[0].width" in text
    assert ">= 16" in text


def test_unknown_top_level_field() -> None:
    text = _error(["bogus=1"])
    assert "bogus" in text and "unknown field" in text


def test_unknown_nested_field() -> None:
    text = _error(["clock.tick_rate=10"])
    assert "'clock'" in text and "tick_rate" in text


@pytest.mark.parametrize(
    ("override", "field"),
    [
        ('clock.mode="sometimes"', "clock.mode"),
        ('tags.family="tag25h9"', "tags.family"),
        ('robots.placement="spiral"', "robots.placement"),
        ("clock.mode=3", "clock.mode"),
    ],
)
def test_bad_enum(override: str, field: str) -> None:
    text = _error([override])
    assert f"field '{field}'" in text


@pytest.mark.parametrize(
    ("override", "field"),
    [
        ("seed=-1", "seed"),
        ("seed=1.5", "seed"),
        ('robots.count="four"', "robots.count"),
        ("robots.count=0", "robots.count"),
        ("robots.count=201", "robots.count"),
        ("duration_s=0", "duration_s"),
        ("clock.tick_hz=-30", "clock.tick_hz"),
        ("render.workers=33", "render.workers"),
        ("encoders.error_model=3", "encoders.error_model"),
        ("robot.cameras=[{hfov_deg=170}]", "robot.cameras[0].hfov_deg"),
        ("arena.size_x_m=nan", "arena.size_x_m"),
    ],
)
def test_bad_types_and_ranges_name_the_field(override: str, field: str) -> None:
    assert f"field '{field}'" in _error([override])


def test_unknown_scenario_name() -> None:
    text = _error([], name="nope")
    assert "unknown scenario 'nope'" in text
    assert "paper" in text  # lists the built-ins


def test_tag_too_big_for_quiet_zone() -> None:
    text = _error(["tags.size_m=0.17"])
    assert "tags.size_m=0.17" in text and "quiet zone" in text
    assert "robot.cube_edge_m must be >= 0.213" in text


def test_bigger_cube_makes_room_for_bigger_tag() -> None:
    s = load_scenario("paper", ["tags.size_m=0.2", "robot.cube_edge_m=0.25"])
    assert s.tags.size_m == 0.2


def test_overlapping_explicit_start_poses() -> None:
    text = _error([*EXPLICIT_2, "robots.start=[{x_m=0.0, y_m=0.0}, {x_m=0.2, y_m=0.1}]"])
    assert "robots 0 and 1 start overlapping" in text


def test_explicit_start_list_shorter_than_count_is_filled() -> None:
    # robots.start used to have to match robots.count; now the missing robots get free poses
    s = load_scenario("paper", [*EXPLICIT_2, "robots.start=[{x_m=0.0, y_m=0.0}]"])
    poses = _inside_and_apart(s)
    assert poses[0] == (0.0, 0.0, 0.0)
    assert math.dist(poses[0][:2], poses[1][:2]) >= 1.0  # the widest lattice spacing had room
    assert s.robots.start[0] == sc.StartPose(x_m=0.0, y_m=0.0)


def test_validate_still_checks_the_start_count() -> None:
    s = load_scenario("paper")
    short = msgspec.structs.replace(s, robots=msgspec.structs.replace(s.robots, start=s.robots.start[:3]))
    with pytest.raises(ScenarioError) as exc:
        sc.validate(short)
    assert "robots.start has 3 poses" in str(exc.value) and "robots.count=4" in str(exc.value)


def test_start_on_an_obstacle() -> None:
    text = _error(["arena.obstacles=[{x_m=1.2, y_m=0.7, size_x_m=0.4, size_y_m=0.4}]"])
    assert "robot 1 starts on arena.obstacles[0]" in text


def test_explicit_start_outside_arena() -> None:
    text = _error([*EXPLICIT_2, "robots.start=[{x_m=0.0, y_m=0.0}, {x_m=3.4, y_m=0.0}]"])
    assert "robot 1" in text and "outside the arena" in text


def test_ring_too_big_for_arena() -> None:
    text = _error(['robots.placement="ring"', "robots.ring_radius_m=3.4"])
    assert "robot 0 starts at (3.40, 0.00), outside the arena" in text


def test_landmark_collides_with_robot_tag() -> None:
    text = _error(["landmarks=[{id=100, x_m=3.4, y_m=0.0}, {id=11, x_m=-3.4, y_m=0.0}]"])
    assert "landmarks[1].id" in text and "tag ID 11 is used twice" in text
    assert "robot 1 front" in text and "landmark 1" in text


def test_two_landmarks_share_an_id() -> None:
    text = _error(["landmarks=[{id=100, x_m=3.4, y_m=0.0}, {id=100, x_m=-3.4, y_m=0.0}]"])
    assert "landmarks[1].id" in text and "tag ID 100" in text


def test_landmark_beyond_family() -> None:
    text = _error(["landmarks=[{id=587, x_m=3.4, y_m=0.0}]"])
    assert "landmarks[0].id" in text and "0..586" in text


def test_landmark_far_outside_arena() -> None:
    text = _error(["landmarks=[{id=100, x_m=30.0, y_m=0.0}]"])
    assert "landmarks[0]" in text and "outside the arena" in text


@pytest.mark.parametrize(
    ("overrides", "needle"),
    [
        (['robot.cameras=[{name="a"}, {name="a"}]'], "camera names must be unique"),
        (["robot.cameras=[]"], "at least one camera"),
        (['robot.cameras=[{name="a/b"}]'], "robot.cameras[0].name"),
        (["robot.cameras=[{near_m=2.0, far_m=1.0}]"], "robot.cameras[0]: far_m must exceed near_m"),
        (["robot.cameras=[{rate_hz=60}]"], "robot.cameras[0].rate_hz=60.0 exceeds clock.tick_hz=30.0"),
        (["encoders.rate_hz=100"], "encoders.rate_hz=100.0 exceeds clock.tick_hz"),
        (["robot.wheel_base_m=0.01"], "robot.wheel_base_m"),
        (['clock.participants=["agent0"]'], "clock.participants"),
    ],
)
def test_cross_field_rules(overrides: list[str], needle: str) -> None:
    assert needle in _error(overrides)


def test_nan_explicit_start_pose_is_rejected() -> None:
    _error([*EXPLICIT_2, "robots.start=[{x_m=nan, y_m=0.0}, {x_m=nan, y_m=1.0}]"])


@pytest.mark.parametrize("name", ["caméra", "c" * 65])
def test_camera_name_that_cannot_be_a_key_is_rejected(name: str) -> None:
    _error([f'robot.cameras=[{{name="{name}"}}]'])


# --------------------------------------------------------------------------- overrides


@pytest.mark.parametrize(
    ("text", "value"),
    [
        ("3", 3),
        ("-4", -4),
        ("1.5", 1.5),
        ("1e3", 1000.0),
        ("true", True),
        ("false", False),
        ('"lockstep"', "lockstep"),
        ("lockstep", "lockstep"),
        ("'single'", "single"),
        ("[1, 2, 3]", [1, 2, 3]),
        ('["agent/0", "server/0"]', ["agent/0", "server/0"]),
        ("[{width=640, name=\"a\"}]", [{"width": 640, "name": "a"}]),
        ("{x_m=1.0, y_m=2}", {"x_m": 1.0, "y_m": 2}),
        ("agent/0", "agent/0"),
    ],
)
def test_parse_value(text: str, value: Any) -> None:
    out = sc.parse_value(text)
    assert out == value
    assert type(out) is type(value)


def test_apply_override_builds_nested_tables() -> None:
    table: dict[str, Any] = {"clock": {"mode": "realtime", "tick_hz": 30.0}}
    sc.apply_override(table, "clock.tick_hz=60")
    sc.apply_override(table, " clock . mode = lockstep ")
    sc.apply_override(table, "seed=9")
    sc.apply_override(table, "render.floor=true")
    sc.apply_override(table, "a.b.c=1.25")
    sc.apply_override(table, 'name="x=y"')
    sc.apply_override(table, "clock.participants=[\"agent/0\", \"server/0\"]")
    assert table == {
        "clock": {"mode": "lockstep", "tick_hz": 60, "participants": ["agent/0", "server/0"]},
        "seed": 9,
        "render": {"floor": True},
        "a": {"b": {"c": 1.25}},
        "name": "x=y",
    }


def test_apply_override_value_keeps_equals_signs() -> None:
    table: dict[str, Any] = {}
    sc.apply_override(table, "x=a=b")
    assert table == {"x": "a=b"}


@pytest.mark.parametrize("bad", ["seed", "", "a..b=1", ".a=1", "a.=1", "=1"])
def test_apply_override_syntax_errors(bad: str) -> None:
    table: dict[str, Any] = {}
    with pytest.raises(ScenarioError) as exc:
        sc.apply_override(table, bad)
    assert repr(bad) in str(exc.value)
    assert table == {}


def test_apply_override_into_non_section() -> None:
    table: dict[str, Any] = {"seed": 3}
    with pytest.raises(ScenarioError) as exc:
        sc.apply_override(table, "seed.x=1")
    assert "'seed' is not a section" in str(exc.value)
    assert table == {"seed": 3}


def test_overrides_apply_in_order_and_reach_the_scenario() -> None:
    s = load_scenario("paper", ["seed=1", "seed=2", 'clock.mode="lockstep"', "robots.count=2", "render.floor=true",
                                'clock.participants=["agent/0", "agent/1"]', "encoders.ticks_per_rev=1024"])
    assert s.seed == 2
    assert s.clock.mode == "lockstep"
    assert s.robots.count == 2
    assert s.render.floor is True
    assert s.clock.participants == ("agent/0", "agent/1")
    assert s.encoders.ticks_per_rev == 1024
    assert s.robot.cameras[0].width == 320  # untouched fields keep the TOML's values


def test_overrides_do_not_leak_between_loads() -> None:
    assert load_scenario("paper", ["seed=5"]).seed == 5
    assert load_scenario("paper").seed == 0


# --------------------------------------------------------------------------- start poses


def _inside_and_apart(s: sc.Scenario) -> list[tuple[float, float, float]]:
    poses = layout.start_poses(s)
    assert len(poses) == s.robots.count
    r = layout.footprint_radius(s.robot)
    half_x = s.arena.size_x_m / 2 - s.arena.wall_thickness_m / 2
    half_y = s.arena.size_y_m / 2 - s.arena.wall_thickness_m / 2
    for x, y, yaw in poses:
        assert all(math.isfinite(v) for v in (x, y, yaw))
        assert abs(x) + r <= half_x and abs(y) + r <= half_y
        assert -math.pi - 1e-9 <= yaw <= math.pi + 1e-9
    for p, q in itertools.combinations(poses, 2):
        assert math.dist(p[:2], q[:2]) >= 2 * r
    return poses


@pytest.mark.parametrize("placement", ["ring", "grid", "random"])
@pytest.mark.parametrize("count", [1, 2, 4, 9])
@pytest.mark.parametrize("seed", [0, 1, 12345])
def test_placements_keep_robots_inside_and_apart(placement: str, count: int, seed: int) -> None:
    s = load_scenario("paper", [f'robots.placement="{placement}"', f"robots.count={count}", f"seed={seed}",
                                "robots.ring_radius_m=2.0"])
    _inside_and_apart(s)


def test_explicit_placement_is_taken_verbatim() -> None:
    s = load_scenario("paper", ['robots.placement="explicit"', "robots.count=3",
                                "robots.start=[{x_m=-1.0, y_m=0.5, yaw_rad=0.25}, {x_m=1.0, y_m=0.5}, "
                                "{x_m=0.0, y_m=-2.0, yaw_rad=-3.0}]"])
    assert _inside_and_apart(s) == [(-1.0, 0.5, 0.25), (1.0, 0.5, 0.0), (0.0, -2.0, -3.0)]


def test_ring_faces_its_centre() -> None:
    s = load_scenario("paper", ['robots.placement="ring"'])
    poses = _inside_and_apart(s)
    for x, y, yaw in poses:
        assert math.isclose(math.hypot(x, y), 1.5)
        # heading points at the origin
        assert math.isclose(math.cos(yaw), -x / 1.5, abs_tol=1e-9)
        assert math.isclose(math.sin(yaw), -y / 1.5, abs_tol=1e-9)
    assert poses[0][:2] == (1.5, 0.0)


@pytest.mark.parametrize("placement", ["ring", "grid", "random"])
def test_start_poses_are_deterministic_for_a_seed(placement: str) -> None:
    over = [f'robots.placement="{placement}"', "robots.count=6", "seed=42"]
    a, b = load_scenario("paper", over), load_scenario("paper", over)
    assert layout.start_poses(a) == layout.start_poses(b)
    assert layout.start_poses(a) == layout.start_poses(a)


@pytest.mark.parametrize("placement", ["grid", "random"])
def test_seed_changes_seeded_placements(placement: str) -> None:
    a = load_scenario("paper", [f'robots.placement="{placement}"', "robots.count=6", "seed=1"])
    b = load_scenario("paper", [f'robots.placement="{placement}"', "robots.count=6", "seed=2"])
    assert layout.start_poses(a) != layout.start_poses(b)


def test_ring_ignores_seed() -> None:
    one, two = load_scenario("paper", ["seed=1"]), load_scenario("paper", ["seed=2"])
    assert layout.start_poses(one) == layout.start_poses(two)


def test_too_many_robots_for_the_arena() -> None:
    text = _error(['robots.placement="grid"', "robots.count=20", "arena.size_x_m=3.0", "arena.size_y_m=3.0"])
    assert "start overlapping" in text


def test_footprint_radius() -> None:
    r = layout.footprint_radius(load_scenario("paper").robot)
    assert math.isclose(r, math.hypot(0.15, 0.12))


# --------------------------------------------------------------------------- files


MINI_TOML = """
name = "mini"
seed = 3
duration_s = 5.0

[arena]
size_x_m = 4.0
size_y_m = 5.0

[robots]
count = 2
placement = "grid"

[clock]
mode = "lockstep"
tick_hz = 30.0
participants = ["agent/0", "agent/1"]

[[robot.cameras]]
name = "front"
rate_hz = 10.0

[[robot.cameras]]
name = "rear"
yaw_deg = 180.0
rate_hz = 5.0

[[landmarks]]
id = 100
x_m = 1.95
y_m = 0.0
yaw_rad = 3.14159
"""


def test_scenario_from_toml_path(tmp_path: Path) -> None:
    path = tmp_path / "mini.toml"
    path.write_text(MINI_TOML)
    s = load_scenario(str(path))
    assert s.name == "mini"
    assert s.seed == 3
    assert (s.arena.size_x_m, s.arena.size_y_m) == (4.0, 5.0)
    assert s.robots.count == 2 and s.robots.placement == "grid"
    assert s.clock.mode == "lockstep" and s.clock.participants == ("agent/0", "agent/1")
    assert [c.name for c in s.robot.cameras] == ["front", "rear"]
    assert s.robot.cameras[1].yaw_deg == 180.0
    assert s.robot.cameras[1].width == 320  # default
    assert s.landmarks[0].id == 100 and s.landmarks[0].z_m == 0.25
    assert s.tags == sc.TagScheme()  # all defaults
    _inside_and_apart(s)


def test_toml_path_with_overrides(tmp_path: Path) -> None:
    path = tmp_path / "mini.toml"
    path.write_text(MINI_TOML)
    s = load_scenario(str(path), ["robots.count=3", "clock.tick_hz=40"])
    assert s.robots.count == 3 and s.clock.tick_hz == 40.0


def test_empty_toml_gives_defaults(tmp_path: Path) -> None:
    path = tmp_path / "empty.toml"
    path.write_text("")
    s = load_scenario(str(path))
    assert s == sc.Scenario()
    assert s.name == "custom"


def test_unparsable_toml(tmp_path: Path) -> None:
    path = tmp_path / "broken.toml"
    path.write_text("[arena\nsize_x_m = ")
    with pytest.raises(ScenarioError) as exc:
        load_scenario(str(path))
    assert "cannot be parsed" in str(exc.value) and "broken.toml" in str(exc.value)
    assert "\n" not in str(exc.value)


def test_missing_toml_path(tmp_path: Path) -> None:
    with pytest.raises(ScenarioError) as exc:
        load_scenario(str(tmp_path / "absent.toml"))
    assert "cannot read scenario" in str(exc.value) and "absent.toml" in str(exc.value)


def test_invalid_toml_file_names_field(tmp_path: Path) -> None:
    path = tmp_path / "bad.toml"
    path.write_text("[clock]\nmode = 'warp'\n")
    with pytest.raises(ScenarioError) as exc:
        load_scenario(str(path))
    assert "field 'clock.mode'" in str(exc.value)
    assert "bad.toml" in str(exc.value)


def test_json_round_trip(tmp_path: Path) -> None:
    s = load_scenario("paper", [
        'clock.mode="lockstep"', 'clock.participants=["agent/0", "server/0"]', "render.workers=2", "seed=17",
        'robots.placement="random"', "arena.obstacles=[{x_m=0.0, y_m=2.6, size_x_m=0.5, size_y_m=0.5}]",
        "landmarks=[{id=200, x_m=-3.4, y_m=1.0, yaw_rad=0.0}]",
        'robot.cameras=[{name="front"}, {name="left", yaw_deg=90.0, width=160, height=120}]',
    ])
    path = tmp_path / "scenario.json"
    path.write_bytes(msgspec.json.encode(s))
    back = load_scenario(str(path))
    assert back == s
    assert back.robot.cameras[1].width == 160
    assert layout.start_poses(back) == layout.start_poses(s)


def test_broken_json(tmp_path: Path) -> None:
    path = tmp_path / "scenario.json"
    path.write_text("{not json")
    with pytest.raises(ScenarioError) as exc:
        load_scenario(str(path))
    assert "cannot be parsed" in str(exc.value)


def test_wall_boxes() -> None:
    walls = layout.wall_boxes(sc.Arena())
    assert len(walls) == 4
    centres = sorted(c for c, _ in walls)
    assert centres == sorted([(3.5, 0.0, 0.25), (-3.5, 0.0, 0.25), (0.0, 3.5, 0.25), (0.0, -3.5, 0.25)])
    for _, half in walls:
        assert half[2] == 0.25
        assert 0.05 in half[:2]


def test_a_start_list_without_placement_is_where_the_robots_start(tmp_path: Path) -> None:
    """A new user's file with start poses and no placement line: the default ring moved the robots away
    from them without a word (and a robot of the ring landed on an obstacle the user kept clear)."""
    path = tmp_path / "mine.toml"
    path.write_text('name = "mine"\n[arena]\nobstacles = [{x_m = 1.0, y_m = 1.0, size_x_m = 0.4, size_y_m = 0.4}]\n'
                    "[robots]\nstart = [{x_m = -3.0, y_m = 0.0}, {x_m = -2.0, y_m = 0.0, yaw_rad = 0.5}]\n")
    s = load_scenario(str(path))
    assert (s.robots.placement, s.robots.count) == ("explicit", 2)
    assert [(p.x_m, p.y_m) for p in s.robots.start] == [(-3.0, 0.0), (-2.0, 0.0)]
    assert load_scenario(str(path), ['robots.placement="grid"']).robots.placement == "grid"  # on purpose
    path.write_text(path.read_text().replace("[robots]\n", '[robots]\nplacement = "ring"\n'))
    with pytest.raises(ScenarioError, match=r'robots\.start is used only with robots\.placement = "explicit"'):
        load_scenario(str(path))


@pytest.mark.parametrize(("override", "says"), [
    ("arena.obstacles=[{x_m=20.0, y_m=0.0, size_x_m=0.5, size_y_m=0.5}]", r"arena.obstacles\[0\]: its centre"),
    ("landmarks=[{id=200, x_m=-8.0, y_m=0.0}]", r"landmarks\[0\]: \(-8.0, 0.0\) is outside the arena's walls"),
])
def test_obstacles_and_landmarks_beyond_the_walls_are_refused(override: str, says: str) -> None:
    with pytest.raises(ScenarioError, match=says):
        load_scenario("paper", [override])
    load_scenario("landmarks")  # its tags on the walls' faces stay fine
