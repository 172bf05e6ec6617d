"""Contact events (world/contacts.py) and placing robots by hand (Sim.place_robot), without any network."""

from __future__ import annotations

import math

import pytest

from tagswarm.protocol.scenario import load_scenario
from tagswarm.world.contacts import ContactCounter
from tagswarm.world.sim import PlacementError, Sim

TWO = ["robots.count=2", 'robots.placement="explicit"', "clock.command_timeout_s=1000",
       "robots.start=[{x_m=-1.0, y_m=0.0, yaw_rad=0.0}, {x_m=1.0, y_m=0.0, yaw_rad=3.14159}]"]
ONE = ["robots.count=1", 'robots.placement="explicit"', "clock.command_timeout_s=1000",
       "robots.start=[{x_m=2.0, y_m=0.0, yaw_rad=0.0}]"]


def run(sim: Sim, seconds: float, commands: dict[int, tuple[float, float]]) -> None:
    for _ in range(round(seconds * sim.s.clock.tick_hz)):
        for rid, (left, right) in commands.items():
            sim.set_command(rid, left, right)
        sim.step()


def totals(sim: Sim) -> tuple[int, int, int]:
    c = sim.contacts.as_counters()
    return c["contacts_robot_robot"], c["contacts_robot_obstacle"], c["contacts_robot_wall"]


# Without the release gap the glancing meeting and the wall below count 2: the solver pushes the bodies a
# fraction of a millimetre apart for a physics step, and they come back (measured).
@pytest.mark.parametrize(("start1", "cmd0", "cmd1"), [
    ("{x_m=1.0, y_m=0.0, yaw_rad=3.14159}", (6.0, 6.0), (6.0, 6.0)),  # head on, then pushing for 5 s
    ("{x_m=1.0, y_m=0.1, yaw_rad=3.0}", (6.0, 7.0), (6.0, 6.3)),  # at an angle: they slide past each other
])
def test_two_robots_driven_into_each_other_make_one_event(start1: str, cmd0: tuple[float, float],
                                                          cmd1: tuple[float, float]) -> None:
    s = load_scenario("paper", [*TWO, f"robots.start=[{{x_m=-1.0, y_m=0.0, yaw_rad=0.0}}, {start1}]"])
    with Sim(s) as sim:
        run(sim, 8.0, {0: cmd0, 1: cmd1})
        assert totals(sim) == (1, 0, 0)
        c = sim.contacts.as_counters()
        assert (c["contacts_robot_0"], c["contacts_robot_1"]) == (1, 1)


def test_a_robot_pushing_a_wall_for_seconds_is_one_event() -> None:
    with Sim(load_scenario("paper", [*ONE, "robots.start=[{x_m=2.5, y_m=1.0, yaw_rad=0.3}]"])) as sim:
        run(sim, 8.0, {0: (8.0, 8.5)})  # reaches the +x wall at an angle after ~2 s, keeps pushing along it
        assert sim.robots[0].x_m > 3.25
        assert totals(sim) == (0, 0, 1)
        assert sim.contacts.as_counters()["contacts_robot_0"] == 1


def test_touching_again_after_backing_off_is_a_second_event() -> None:
    with Sim(load_scenario("paper", ONE)) as sim:
        run(sim, 5.0, {0: (8.0, 8.0)})
        run(sim, 1.0, {0: (-8.0, -8.0)})  # 0.4 m back: far beyond the release gap
        assert totals(sim) == (0, 0, 1)
        run(sim, 2.0, {0: (8.0, 8.0)})
        assert totals(sim) == (0, 0, 2)


def test_robot_into_an_obstacle_counts_as_obstacle() -> None:
    s = load_scenario("paper", [*ONE, "robots.start=[{x_m=0.0, y_m=0.0, yaw_rad=0.0}]",
                                "arena.obstacles=[{x_m=1.5, y_m=0.0, size_x_m=0.4, size_y_m=0.4, yaw_rad=0.5}]"])
    with Sim(s) as sim:
        run(sim, 6.0, {0: (8.0, 8.0)})
        assert totals(sim) == (0, 1, 0)


def test_robots_that_stay_apart_have_no_contacts() -> None:
    s = load_scenario("paper", ["robots.count=4", "clock.command_timeout_s=1000"])
    with Sim(s) as sim:
        run(sim, 10.0, {rid: (2.0, 3.0) for rid in s.robot_ids})  # 0.55 m circles, 2.1 m apart on their ring
        assert totals(sim) == (0, 0, 0)
        assert all(v == 0 for v in sim.contacts.as_counters().values())
        assert set(sim.contacts.as_counters()) == {"contacts_robot_robot", "contacts_robot_obstacle",
                                                    "contacts_robot_wall", *(f"contacts_robot_{r}" for r in range(4))}


def test_broad_phase_misses_nothing() -> None:
    """A crowded run where robots bump walls and each other: watching only the broad phase's
    pairs gives the same events as watching every pair every physics step."""
    over = ["seed=11", "robots.count=12", 'robots.placement="grid"', "clock.command_timeout_s=1000",
            "arena.size_x_m=4", "arena.size_y_m=4",
            "arena.obstacles=[{x_m=0.0, y_m=-0.47, size_x_m=0.3, size_y_m=0.3, yaw_rad=0.7}]"]
    results = []
    for everything in (False, True):
        with Sim(load_scenario("paper", over)) as sim:
            if everything:
                sim.contacts._reach = 1e3  # every pair is a candidate every tick
            for k in range(600):
                for rid in sim.robots:
                    sim.set_command(rid, 8.0 * math.sin(k / 37.0 + rid), 8.0 * math.cos(k / 29.0 + 2 * rid))
                sim.step()
            results.append(sim.contacts.as_counters())
    assert results[0] == results[1]
    assert results[0]["contacts_robot_robot"] >= 10 and results[0]["contacts_robot_wall"] >= 3
    assert results[0]["contacts_robot_obstacle"] >= 1


def test_contact_counter_kinds_and_per_robot_sums() -> None:
    c = ContactCounter(-1, {5: 0, 6: 1}, [], radius_m=0.2, reach_m=0.1)
    c._kind_of.update({1: "wall", 9: "obstacle"})
    for pair in ((5, 6), (1, 5), (1, 6), (6, 9)):
        c._count(*pair)
    assert c.as_counters() == {"contacts_robot_robot": 1, "contacts_robot_obstacle": 1, "contacts_robot_wall": 2,
                               "contacts_robot_0": 2, "contacts_robot_1": 3}


# ---------------------------------------------------------------------------------------------- placing robots


def test_teleport_moves_the_robot_without_turning_its_wheels() -> None:
    with Sim(load_scenario("paper", TWO)) as sim:
        run(sim, 1.0, {0: (5.0, 6.0)})
        sim.set_command(0, 0.0, 0.0)
        ticks = sim.encoder_ticks(0)
        sim.place_robot(0, 0.5, 2.0, 1.0)
        st = sim.robots[0]
        assert (st.x_m, st.y_m) == (0.5, 2.0) and st.yaw_rad == pytest.approx(1.0, abs=1e-12)
        assert (st.v_m_s, st.omega_rad_s) == (0.0, 0.0)
        pos, _ = sim.base_pose(0)
        assert pos[:2] == (0.5, 2.0)
        sim.step()  # no command any more: it stays, and the encoders saw nothing
        assert sim.encoder_ticks(0) == ticks
        assert math.dist((st.x_m, st.y_m), (0.5, 2.0)) < 1e-4


def test_push_is_relative_to_the_current_pose_and_the_encoders_count_only_driving() -> None:
    s = load_scenario("paper", [*TWO, "encoders.error_model=false"])
    with Sim(s) as sim:
        st = sim.robots[1]
        x0, y0, yaw0 = st.x_m, st.y_m, st.yaw_rad
        ticks = sim.encoder_ticks(1)
        sim.place_robot(1, *(x0 + 0.3, y0 - 0.4, yaw0 + 0.5))
        assert (st.x_m, st.y_m) == pytest.approx((x0 + 0.3, y0 - 0.4), abs=1e-12)
        assert math.remainder(st.yaw_rad - (yaw0 + 0.5), 2 * math.pi) == pytest.approx(0.0, abs=1e-9)
        assert sim.encoder_ticks(1) == ticks
        # driving 1 s straight after the push: the wheels count that and nothing of the push
        run(sim, 1.0, {1: (6.0, 6.0)})
        travelled = math.dist((st.x_m, st.y_m), (x0 + 0.3, y0 - 0.4))
        per_rev = s.encoders.ticks_per_rev / (2 * math.pi * s.robot.wheel_radius_m)
        counted = (sim.encoder_ticks(1)[0] - ticks[0]) / per_rev
        assert travelled > 0.25 and counted == pytest.approx(travelled, abs=0.002)


@pytest.mark.parametrize(("pose", "why"), [
    ((3.4, 0.0, 0.0), "inside the arena walls"),   # box front 3.55 beyond the wall face at 3.45
    ((3.28, 0.0, 0.785), "inside the arena walls"),  # fits facing the wall (see below), not turned 45 degrees
    ((9.0, 0.0, 0.0), "inside the arena walls"),
    ((1.1, 0.0, 0.0), "overlap robot 1"),          # robot 1 sits at x=1.0
    ((0.0, 0.0, 0.0), "overlap obstacle 0"),
])
def test_placement_refused_leaves_the_robot_where_it_was(pose: tuple[float, float, float], why: str) -> None:
    s = load_scenario("paper", [*TWO, "arena.obstacles=[{x_m=0.0, y_m=0.0, size_x_m=0.4, size_y_m=0.4}]"])
    with Sim(s) as sim:
        st = sim.robots[0]
        before = (st.x_m, st.y_m, st.yaw_rad, sim.base_pose(0))
        with pytest.raises(PlacementError, match=why):
            sim.place_robot(0, *pose)
        assert (st.x_m, st.y_m, st.yaw_rad, sim.base_pose(0)) == before


def test_placement_flush_against_a_wall_or_robot_is_allowed() -> None:
    with Sim(load_scenario("paper", TWO)) as sim:
        sim.place_robot(0, 3.45 - 0.15, 0.0, 0.0)  # front face on the wall's inner face
        sim.place_robot(0, 3.28, 0.0, 0.0)
        sim.place_robot(0, 0.70, 0.0, 0.0)  # front face on robot 1's front face (both 0.30 long)
        with pytest.raises(PlacementError, match="robot 7 is not in the roster"):
            sim.place_robot(7, 0.0, 0.0, 0.0)
        with pytest.raises(PlacementError, match="not finite"):
            sim.place_robot(0, math.nan, 0.0, 0.0)
