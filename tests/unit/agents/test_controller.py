"""The controller API (tagswarm.agents.controller): commands and their units, error
containment, the collision guard on a user's command, the built-in behaviour as a
controller (and subclassed), and the inputs built from the agent's state."""

from __future__ import annotations

import logging
import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from tagswarm.agents.avoid import Box, Neighbour
from tagswarm.agents.behaviour import Behaviour, Mode
from tagswarm.agents.controller import (
    BehaviourController,
    ControlInput,
    Controller,
    ControllerConfig,
    ControllerRunner,
    GoalRequest,
    Twist,
    WheelSpeeds,
    control_input,
    gray,
    load_factory,
    make,
)
from tagswarm.agents.guard import CommandGuard
from tagswarm.protocol import messages as m
from tagswarm.protocol.geometry import Pose2
from tagswarm.protocol.layout import footprint_radius
from tagswarm.protocol.scenario import load_scenario

PAPER = load_scenario("paper")
EXAMPLE = Path(__file__).resolve().parents[3] / "examples" / "controllers" / "circle.py"


def _config(rid: int = 3, *overrides: str) -> ControllerConfig:
    s = load_scenario("paper", list(overrides)) if overrides else PAPER
    return ControllerConfig(rid, s)


def _inputs(pose: Pose2 = (0.0, 0.0, 0.0), *, localised: bool = True, t_s: float = 0.0,
            neighbours: tuple[Neighbour, ...] = (), goal: GoalRequest | None = None,
            fix: bool = False, moved: bool = False) -> ControlInput:
    cov = tuple(np.eye(3).ravel() * 1e-4)
    return ControlInput(robot_id=3, t_s=t_s, localised=localised, pose=pose, pose_cov=cov, odom=pose, odom_cov=cov,
                        distance_m=0.0, moved=moved, fix=fix, server_up=True, neighbours=neighbours, goal=goal)


class Fixed(Controller):
    def __init__(self, cmd: object) -> None:
        self.cmd = cmd
        self.calls = 0

    def step(self, inputs: ControlInput) -> Twist:
        self.calls += 1
        return self.cmd  # type: ignore[return-value]


class Raises(Controller):
    calls = 0

    def step(self, inputs: ControlInput) -> Twist:
        self.calls += 1
        if self.calls % 2:
            raise RuntimeError("boom")
        return Twist(0.1, 0.0)


def test_twist_and_wheel_speeds_are_the_same_command() -> None:
    robot = PAPER.robot
    r, b = robot.wheel_radius_m, robot.wheel_base_m
    twist = ControllerRunner(Fixed(Twist(0.1, 0.5)), _config()).command(_inputs())
    assert twist == pytest.approx(((0.1 - 0.5 * b / 2) / r, (0.1 + 0.5 * b / 2) / r))
    wheels = ControllerRunner(Fixed(WheelSpeeds(*twist)), _config()).command(_inputs())
    assert wheels == pytest.approx(twist)


def test_commands_beyond_the_wheel_limit_are_scaled_keeping_the_curvature() -> None:
    runner = ControllerRunner(Fixed(WheelSpeeds(40.0, 20.0)), _config())
    left, right = runner.command(_inputs())
    assert max(abs(left), abs(right)) == pytest.approx(PAPER.robot.max_wheel_speed_rad_s)
    assert left / right == pytest.approx(2.0)


def test_a_raising_controller_stops_the_robot_is_counted_and_logged_once(caplog: pytest.LogCaptureFixture) -> None:
    ctrl = Raises()
    runner = ControllerRunner(ctrl, _config())
    with caplog.at_level(logging.ERROR):
        out = [runner.command(_inputs()) for _ in range(6)]
    assert ctrl.calls == 6  # called again after a failure
    assert out[0::2] == [(0.0, 0.0)] * 3 and all(left > 0 and left == right for left, right in out[1::2])
    counters = runner.counters()
    assert counters.pop("controller_slow") in range(7)  # wall-clock: a loaded machine may stretch a step
    assert counters == {"controller_cycles": 6, "controller_errors": 3, "controller_filtered": 0, "fixes": 0,
                        "controller_hung": 0}
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and errors[0].exc_info is not None and "RuntimeError" in caplog.text


def test_a_step_that_does_not_return_is_reported_once_with_where_it_is(monkeypatch: pytest.MonkeyPatch,
                                                                      caplog: pytest.LogCaptureFixture) -> None:
    monkeypatch.setattr("tagswarm.agents.controller.HUNG_STEP_S", 0.2)

    class Stuck(Controller):
        def step(self, inputs: ControlInput) -> Twist:
            time.sleep(1.6)  # three looks of the watch: reported once all the same
            return Twist(0.0, 0.0)

    runner = ControllerRunner(Stuck(), _config())
    with caplog.at_level(logging.WARNING):
        runner.command(_inputs())
        runner.command(_inputs())  # a second stuck step is a second report
    runner.close()
    hung = [r for r in caplog.records if "has not returned" in r.getMessage()]
    assert len(hung) == 2 and runner.counters()["controller_hung"] == 2
    assert "in step" in hung[0].getMessage() and "time.sleep(1.6)" in hung[0].getMessage()


def test_fixes_and_slow_steps_are_counted_and_a_slow_one_logged_once(monkeypatch: pytest.MonkeyPatch,
                                                                      caplog: pytest.LogCaptureFixture) -> None:
    """A user's controller gets ``fixes`` counted as the built-in behaviour does (it stayed 0), and a
    step longer than the control period (1/30 s here) is counted as ``controller_slow``."""
    clock = [0.0]
    monkeypatch.setattr("tagswarm.agents.controller.time.perf_counter", lambda: clock[0])

    class Slow(Controller):
        def step(self, inputs: ControlInput) -> Twist:
            clock[0] += 0.05 if inputs.t_s >= 2 else 0.01  # 50 ms from the third cycle on, else 10 ms
            return Twist(0.0, 0.0)

    runner = ControllerRunner(Slow(), _config())
    with caplog.at_level(logging.WARNING, logger="tagswarm.agent.controller"):
        for k in range(5):
            runner.command(_inputs(t_s=float(k), fix=k in (1, 3, 4)))
    c = runner.counters()
    assert (c["fixes"], c["controller_slow"], c["controller_cycles"]) == (3, 3, 5)
    slow = [r for r in caplog.records if "control period" in r.getMessage()]
    assert len(slow) == 1 and "took 50 ms" in slow[0].getMessage() and "33 ms" in slow[0].getMessage()


@pytest.mark.parametrize("bad", [None, (0.1, 0.2), Twist(math.nan, 0.0), WheelSpeeds(1.0, math.inf)])
def test_anything_but_a_finite_command_is_an_error(bad: object) -> None:
    runner = ControllerRunner(Fixed(bad), _config())
    assert runner.command(_inputs()) == (0.0, 0.0)
    assert runner.errors == 1


def test_the_guard_keeps_a_clear_command_and_bends_one_into_a_robot() -> None:
    ahead = Neighbour(robot_id=1, x_m=0.7, y_m=0.0, vx_m_s=0.0, vy_m_s=0.0, radius_m=0.2)
    aside = Neighbour(robot_id=1, x_m=0.0, y_m=2.0, vx_m_s=0.0, vy_m_s=0.0, radius_m=0.2)
    runner = ControllerRunner(Fixed(Twist(0.2, 0.0)), _config())
    straight = runner.command(_inputs(neighbours=(aside,)))
    assert straight[0] == pytest.approx(straight[1]) and straight[0] > 0 and runner.guard.filtered == 0
    left, right = runner.command(_inputs(neighbours=(ahead,)))
    assert runner.guard.filtered == 1
    assert left != pytest.approx(right)  # it turns away (or stops) instead of driving on
    # the bent command keeps the clearance over the horizon
    r, b = PAPER.robot.wheel_radius_m, PAPER.robot.wheel_base_m
    v, w = r * (left + right) / 2, r * (right - left) / b
    guard = CommandGuard(footprint_radius(PAPER.robot), PAPER.agent.avoid_clearance_m, PAPER.agent.avoid_horizon_s)
    assert guard.admissible((0.0, 0.0, 0.0), np.array([v]), np.array([w]), (ahead,), ())[0]
    assert not guard.admissible((0.0, 0.0, 0.0), np.array([0.2]), np.array([0.0]), (ahead,), ())[0]


def test_the_guard_stops_short_of_a_wall_and_turning_in_place_is_always_allowed() -> None:
    wall = Box(0.8, 0.0, 0.0, 0.05, 2.0)  # its face 0.75 m ahead: 0.6 m of driving leaves 0.15 m < 0.29 m
    guard = CommandGuard(0.19, 0.1, 2.0)
    v, w = guard.filter((0.0, 0.0, 0.0), 0.3, 0.0, (), (wall,), 1.2)
    assert (v, w) != (0.3, 0.0) and guard.filtered == 1
    assert guard.admissible((0.0, 0.0, 0.0), np.array([v]), np.array([w]), (), (wall,))[0]
    assert guard.filter((0.0, 0.0, 0.0), 0.0, 1.0, (), (wall,), 1.2) == (0.0, 1.0)


def test_opting_out_or_unlocalised_passes_the_command_unfiltered() -> None:
    ahead = Neighbour(robot_id=1, x_m=0.5, y_m=0.0, vx_m_s=0.0, vy_m_s=0.0, radius_m=0.2)

    class Reckless(Fixed):
        avoid = False

    for runner, localised in ((ControllerRunner(Reckless(Twist(0.2, 0.0)), _config()), True),
                              (ControllerRunner(Fixed(Twist(0.2, 0.0)), _config()), False),
                              (ControllerRunner(Fixed(Twist(0.2, 0.0)), _config(3, "agent.avoid=false")), True)):
        left, right = runner.command(_inputs(neighbours=(ahead,), localised=localised))
        assert left == pytest.approx(0.2 / PAPER.robot.wheel_radius_m) == pytest.approx(right)
        assert runner.guard.filtered == 0


def test_behaviour_controller_commands_exactly_what_the_behaviour_does() -> None:
    cfg = _config(1)
    ctrl = BehaviourController(cfg)
    ref = Behaviour(1, PAPER.mission(1), PAPER.agent, PAPER.robot, cfg.arena_to_map, (),
                    static_obstacles=cfg.static_obstacles)
    pose = (2.7, 0.9, math.pi)
    for k in range(60):
        fix = k % 7 == 0
        got = ctrl.step(_inputs(pose, t_s=k / 30, fix=fix, moved=True))
        want = ref.cycle(t_s=k / 30, map_pose=pose, odom_yaw=pose[2], moved=True, fix=fix, neighbours=())
        assert isinstance(got, Twist) and (got.v_m_s, got.w_rad_s) == want
        pose = (pose[0] + math.cos(pose[2]) * got.v_m_s / 30, pose[1] + math.sin(pose[2]) * got.v_m_s / 30,
                pose[2] + got.w_rad_s / 30)
    assert ctrl.mode == str(ref.mode) and ctrl.behaviour.fixes == ref.fixes > 0
    # no longer vouched for: both drive on slowly
    got = ctrl.step(replace(_inputs(pose, t_s=3.0, moved=True), vouched=False))
    want = ref.cycle(t_s=3.0, map_pose=pose, odom_yaw=pose[2], moved=True, fix=False, neighbours=(), vouched=False)
    assert isinstance(got, Twist) and (got.v_m_s, got.w_rad_s) == want and ctrl.behaviour.on_loose
    # unlocalised: the behaviour gets no map pose and searches
    fresh = BehaviourController(cfg)
    assert fresh.step(_inputs(localised=False)) == Twist(0.0, PAPER.agent.search_speed_rad_s)
    assert fresh.mode == Mode.SEARCHING


def test_behaviour_controller_takes_each_goal_once() -> None:
    ctrl = BehaviourController(_config(1))
    pose = (0.0, 0.0, 0.0)
    ctrl.step(_inputs(pose, goal=GoalRequest(1.0, 0.0, 0.1, 1), fix=True))
    assert ctrl.behaviour.goal == (1.0, 0.0)
    ctrl.behaviour.goal = None  # as if reached: the same goal (same number) is not set again
    ctrl.step(_inputs(pose, goal=GoalRequest(1.0, 0.0, 0.1, 1)))
    assert ctrl.behaviour.goal is None
    ctrl.step(_inputs(pose, goal=GoalRequest(1.0, 0.0, 0.1, 2)))
    assert ctrl.behaviour.goal == (1.0, 0.0)


def test_subclassing_the_behaviour_changes_only_where_it_goes() -> None:
    class ToOrigin(Behaviour):
        def target(self, pose: Pose2, t_s: float) -> tuple[float, float] | None:
            return (0.0, 0.0)

    class Mine(BehaviourController):
        behaviour_class = ToOrigin

    ctrl = Mine(_config(1))
    assert isinstance(ctrl.behaviour, ToOrigin)
    # facing away from the origin: the built-in go-to-goal turns on the spot towards it
    cmd = ctrl.step(_inputs((1.0, 0.0, 0.0), fix=True))
    assert isinstance(cmd, Twist) and cmd.v_m_s == 0.0 and abs(cmd.w_rad_s) == PAPER.agent.max_turn_rad_s


def test_control_input_is_the_map_pose_when_localised_else_odometry() -> None:
    odom_cov = np.diag([1e-4, 2e-4, 3e-4])
    obs = (m.RelativeObservation(seq=1, stamp_ns=5, robot_id=3, target_kind="robot", target_id=0, x_m=1.0, y_m=0.0,
                                 yaw_rad=0.0, cov=(1e-4, 0, 0, 0, 1e-4, 0, 0, 0, 1e-4),
                                 pose=m.Pose3(x_m=1.0, y_m=0.0, z_m=0.0, qx=0, qy=0, qz=0, qw=1),
                                 reprojection_rms_px=0.3, tag_ids=(1,), camera="front"),)
    common = dict(robot_id=3, time_ns=1_500_000_000, odom_pose=(1.0, 0.0, 0.0), odom_cov=odom_cov, distance_m=1.0,
                  moved=True, fix=False, server_up=True, observations=obs, neighbours=(), goal=None, images={})
    lost = control_input(map_odom=None, map_cov=None, **common)  # type: ignore[arg-type]
    assert not lost.localised and lost.pose == (1.0, 0.0, 0.0) and lost.t_s == 1.5
    assert lost.pose_cov == lost.odom_cov == tuple(odom_cov.ravel()) and lost.observations == obs
    map_cov = tuple(float(x) for x in np.eye(3).ravel() * 0.01)
    found = control_input(map_odom=(2.0, 1.0, math.pi / 2), map_cov=map_cov, **common)  # type: ignore[arg-type]
    assert found.localised and found.pose == pytest.approx((2.0, 2.0, math.pi / 2)) and found.pose_cov == map_cov
    assert found.odom == (1.0, 0.0, 0.0) and found.loose_pose is None and lost.loose_pose is None
    # placed by the server but not vouched for: not localised, the map's estimate as the loose pose
    loose = control_input(map_odom=None, map_cov=None, loose_map_odom=(2.0, 1.0, math.pi / 2),
                          **common)  # type: ignore[arg-type]
    assert not loose.localised and loose.pose == (1.0, 0.0, 0.0)
    assert loose.loose_pose == pytest.approx((2.0, 2.0, math.pi / 2))
    vouched = control_input(map_odom=(2.0, 1.0, 0.0), map_cov=map_cov, loose_map_odom=(9.0, 9.0, 0.0),
                            **common)  # type: ignore[arg-type]
    assert vouched.loose_pose is None and vouched.vouched and found.vouched and not lost.vouched
    # vouched for once, no longer now: localised on the map's estimate, flagged
    lapsed = control_input(map_odom=(2.0, 1.0, 0.0), map_cov=map_cov, vouched=False, **common)  # type: ignore[arg-type]
    assert lapsed.localised and not lapsed.vouched and lapsed.pose == pytest.approx((3.0, 1.0, 0.0))


def test_gray_is_the_frame_as_an_array() -> None:
    img = m.CameraImage(seq=1, stamp_ns=0, robot_id=3, camera="front", step=0, width=3, height=2, fx_px=100.0,
                        fy_px=100.0, cx_px=1.0, cy_px=1.0, mount=m.Pose3(x_m=0, y_m=0, z_m=0, qx=0, qy=0, qz=0, qw=1),
                        data=bytes(range(6)))
    a = gray(img)
    assert a.shape == (2, 3) and a.dtype == np.uint8 and a[1, 2] == 5


def test_the_example_circle_controller_turns_left_on_its_radius() -> None:
    factory = load_factory(str(EXAMPLE))
    ctrl = make(factory, _config(), str(EXAMPLE))
    cmd = ctrl.step(_inputs())
    assert isinstance(cmd, Twist) and cmd.v_m_s > 0 and cmd.w_rad_s > 0
    radius = cmd.v_m_s / cmd.w_rad_s
    slow = ctrl.step(_inputs(localised=False))
    assert isinstance(slow, Twist) and slow.v_m_s == pytest.approx(cmd.v_m_s / 2)
    assert slow.v_m_s / slow.w_rad_s == pytest.approx(radius)
    assert ctrl.mode == "circle" and ctrl.avoid and not ctrl.wants_images
