"""Slip evidence (agents/odometry.py SlipMonitor) against the world's real physics
(world/sim.py, no network): what a clean, a stalled and a pushed robot show."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from tagswarm.agents.odometry import DiffDriveOdometry, DiffDriveParams, SlipMonitor
from tagswarm.protocol.scenario import load_scenario
from tagswarm.world.sim import Sim

Command = Callable[[int, int], tuple[float, float]]  # (robot, tick) -> (left, right) rad/s


def run(starts: list[tuple[float, float, float]], command: Command, seconds: float, *, error_model: bool = True,
        late_ticks: int = 0, assumed_delay_ticks: int | None = None) -> tuple[dict[int, SlipMonitor], dict[int, float]]:
    """Drive robots in the physics, commands applied ``late_ticks`` ticks after they are sent; returns
    each robot's slip monitor and how far it really moved (m)."""
    s = load_scenario("paper", [f"robots.count={len(starts)}", 'robots.placement="explicit"',
                                "robots.start=[" + ",".join(f"{{x_m={x}, y_m={y}, yaw_rad={a}}}" for x, y, a in starts)
                                + "]", "seed=3", f"encoders.error_model={str(error_model).lower()}"])
    sim = Sim(s)
    tick_ns = sim.dt_ns
    delay = late_ticks if assumed_delay_ticks is None else assumed_delay_ticks
    mons = {r: SlipMonitor(s.robot.wheel_radius_m, s.encoders.ticks_per_rev, s.agent.odom_wheel_sigma,
                           delay_ns=delay * tick_ns, timeout_ns=round(s.clock.command_timeout_s * 1e9))
            for r in s.robot_ids}
    start = {r: (sim.robots[r].x_m, sim.robots[r].y_m) for r in s.robot_ids}
    sent: list[dict[int, tuple[float, float]]] = []
    for k in range(round(seconds * s.clock.tick_hz)):
        sent.append({})
        for r in s.robot_ids:
            mons[r].measured(sim.time_ns, *sim.encoder_ticks(r))
            left, right = command(r, k)
            mons[r].commanded(sim.time_ns, left, right)
            sent[-1][r] = (left, right)
        if k >= late_ticks:
            for r, (left, right) in sent[k - late_ticks].items():
                sim.set_command(r, left, right)
        sim.step()
    for r in s.robot_ids:
        mons[r].measured(sim.time_ns, *sim.encoder_ticks(r))
    moved = {r: math.dist(start[r], (sim.robots[r].x_m, sim.robots[r].y_m)) for r in s.robot_ids}
    sim.close()
    return mons, moved


def figure(_: int, k: int) -> tuple[float, float]:
    """Straight runs and curves at changing speeds: a clean drive clear of the walls."""
    return (8.0, 8.0) if k % 75 < 45 else (4.0, 9.0)


def shuttle(_: int, k: int) -> tuple[float, float]:
    """Full speed forwards and backwards: every change is a large step of the command."""
    return (10.0, 10.0) if k % 30 < 15 else (-10.0, -10.0)


@pytest.mark.parametrize("error_model", [True, False])
def test_clean_driving_gives_no_evidence(error_model: bool) -> None:
    mons, moved = run([(0.0, 0.0, 0.0)], figure, 20.0, error_model=error_model)
    assert moved[0] > 0.5 and mons[0].slip_m == 0.0 and mons[0].events == 0


def test_a_command_applied_a_tick_late_is_no_evidence_when_the_delay_is_allowed_for() -> None:
    mons, _ = run([(0.0, 0.0, 0.0)], shuttle, 10.0, late_ticks=1)
    assert mons[0].slip_m == 0.0
    # ... but it would be if the monitor assumed no delay: the window around each change matters
    mons, _ = run([(0.0, 0.0, 0.0)], shuttle, 10.0, late_ticks=1, assumed_delay_ticks=0)
    assert mons[0].slip_m > 0.05


def test_a_robot_pushed_while_standing_shows_the_push_on_both_wheels() -> None:
    # robot 1 drives into robot 0 from behind; robot 0 commands nothing, so every turn of its wheels is slip
    mons, moved = run([(0.0, 0.0, 0.0), (-0.6, 0.0, 0.0)], lambda r, k: (0.0, 0.0) if r == 0 else (6.0, 6.0), 4.0)
    assert moved[0] > 0.3
    assert mons[0].slip_m == pytest.approx(2 * moved[0], rel=0.1)
    # the pusher was slowed (it moved 0.75 of 1.2 m) but its wheels turned as commanded: no evidence
    assert moved[1] < 1.0 and mons[1].slip_m == 0.0


def test_a_sideways_push_does_not_turn_the_wheels_and_leaves_no_evidence() -> None:
    mons, moved = run([(0.0, 0.0, math.pi / 2), (-0.6, 0.0, 0.0)], lambda r, k: (0.0, 0.0) if r == 0 else (6.0, 6.0),
                      4.0)
    assert moved[0] > 0.3 and mons[0].slip_m < 0.01


def test_a_stalled_robot_leaves_evidence_only_if_its_wheels_stop() -> None:
    # driving into the east wall (x = 3.45): the world's error model lets blocked wheels spin at the
    # commanded speed, so the encoders agree with the command; exact encoders stop with the robot
    spinning, moved = run([(3.0, 0.0, 0.0)], lambda r, k: (6.0, 6.0), 4.0)
    assert moved[0] < 0.35 and spinning[0].slip_m == 0.0
    stopped, _ = run([(3.0, 0.0, 0.0)], lambda r, k: (6.0, 6.0), 4.0, error_model=False)
    commanded = 2 * 6.0 * 0.05 * 4.0
    assert stopped[0].slip_m > 0.6 * (commanded - 2 * moved[0])


def test_slip_widens_the_odometry_covariance() -> None:
    od = DiffDriveOdometry(DiffDriveParams(0.05, 0.22, 4096, 0.02))
    before = od.cov.copy()
    od.add_slip(0.1)
    assert np.allclose(np.diag(od.cov - before), [0.01, 0.01, 0.01 / 0.11 ** 2])


def test_a_replay_compares_the_recorded_wheels_with_the_recorded_commands_not_its_own() -> None:
    """In a replay the agent's own commands drive nothing: a changed setting or controller (here: shuttling
    instead of the recorded figure) must not read as slip once the recorded commands come in."""
    s = load_scenario("paper", ["robots.count=1", "seed=3"])
    sim = Sim(s)

    def monitor() -> SlipMonitor:
        return SlipMonitor(s.robot.wheel_radius_m, s.encoders.ticks_per_rev, s.agent.odom_wheel_sigma,
                           delay_ns=0, timeout_ns=round(s.clock.command_timeout_s * 1e9))

    replaying, naive = monitor(), monitor()
    for k in range(round(15.0 * s.clock.tick_hz)):
        ticks = sim.encoder_ticks(0)
        recorded, own = figure(0, k), shuttle(0, k)
        for mon in (replaying, naive):
            mon.measured(sim.time_ns, *ticks)
        replaying.commanded(sim.time_ns, *recorded, recorded=True)  # the node drains them with the encoders
        for mon in (replaying, naive):
            mon.commanded(sim.time_ns, *own)
        sim.set_command(0, *recorded)
        sim.step()
    sim.close()
    assert replaying.replaying and replaying.slip_m == 0.0 and replaying.events == 0
    assert naive.slip_m > 1.0 and naive.events > 10  # the defect: own commands against the recorded wheels
