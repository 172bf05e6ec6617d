"""The paper's self-calibrating behaviour and the mission controller (pure logic)."""

from __future__ import annotations

import math

from tagswarm.agents.avoid import Neighbour
from tagswarm.agents.behaviour import Behaviour, Mode, go_to, wheel_speeds
from tagswarm.protocol.geometry import se2_compose
from tagswarm.protocol.layout import footprint_radius
from tagswarm.protocol.scenario import Agent, Mission, Robot

CFG = Agent(fix_threshold=10, search_speed_rad_s=1.0, search_max_sweep_rad=6.3)
ROBOT = Robot()


def _moving(mission: Mission | None = None) -> Behaviour:
    return Behaviour(1, mission or Mission(robot=1, kind="waypoints", waypoints=((3.0, 0.0),)), CFG, ROBOT)


def test_counter_threshold_triggers_search_and_a_fix_resets_it() -> None:
    b = _moving()
    pose = (0.0, 0.0, 0.0)
    v, w = b.cycle(t_s=0, map_pose=pose, odom_yaw=0.0, moved=False, fix=True)
    assert b.mode == Mode.VISUAL and b.counter == 0 and v > 0
    for k in range(CFG.fix_threshold):
        v, w = b.cycle(t_s=k, map_pose=pose, odom_yaw=0.0, moved=True, fix=False)
        assert b.mode == (Mode.VISUAL if k < b.visual_hold else Mode.ODOMETRY) and v > 0
    v, w = b.cycle(t_s=11, map_pose=pose, odom_yaw=0.0, moved=True, fix=False)
    assert b.mode == Mode.SEARCHING and (v, w) == (0.0, CFG.search_speed_rad_s) and b.searches == 1
    b.cycle(t_s=12, map_pose=pose, odom_yaw=0.5, moved=True, fix=True)
    assert b.mode == Mode.VISUAL and b.counter == 0 and b.fixes == 2


def test_standing_still_does_not_count() -> None:
    b = _moving()
    b.cycle(t_s=0, map_pose=(0, 0, 0), odom_yaw=0.0, moved=False, fix=True)
    for k in range(100):
        b.cycle(t_s=k, map_pose=(0, 0, 0), odom_yaw=0.0, moved=False, fix=False)
    assert b.counter == 0 and b.mode == Mode.ODOMETRY and b.since_fix == 100


def test_full_sweep_without_tag_ends_lost_not_spinning() -> None:
    b = _moving()
    yaw, spins = 0.0, 0
    for k in range(400):
        v, w = b.cycle(t_s=k, map_pose=None, odom_yaw=yaw, moved=True, fix=False)
        yaw = math.remainder(yaw + w * 0.1, 2 * math.pi)
        spins += w != 0
    assert b.mode == Mode.LOST and b.lost_events == 1 and b.searches == 1
    assert 55 <= spins <= 70  # ~2*pi at 1 rad/s and 0.1 s steps, then it stops
    # lost and localised again later: it resumes the mission slowly
    v, w = b.cycle(t_s=500, map_pose=(0, 0, 0), odom_yaw=yaw, moved=True, fix=False)
    assert b.mode == Mode.LOST and 0 < v <= CFG.lost_speed_factor * CFG.max_speed_m_s + 1e-9


def test_the_origin_robot_holding_station_never_turns() -> None:
    b = Behaviour(0, Mission(robot=0, kind="hold"), CFG, ROBOT, anchor=True)
    for k in range(100):
        assert b.cycle(t_s=k, map_pose=(0, 0, 0), odom_yaw=0.0, moved=True, fix=False) == (0.0, 0.0)
    assert b.searches == 0 and b.look_arounds == 0


def _hold(b: Behaviour, steps: int, placed_from: int = 0, fixes: tuple[int, ...] = (),
          server_up: bool = True) -> tuple[list[tuple[float, float]], float]:
    """Run a station keeper at 0.1 s steps with ideal odometry; its commands and final heading."""
    yaw, commands = 0.0, []
    for k in range(steps):
        v, w = b.cycle(t_s=k * 0.1, map_pose=(1.0, 2.0, yaw) if k >= placed_from else None, odom_yaw=yaw,
                       moved=False, fix=k in fixes, server_up=server_up)
        yaw = math.remainder(yaw + w * 0.1, 2 * math.pi)
        commands.append((v, w))
    return commands, yaw


def test_a_station_keeper_first_looks_around_once_then_holds_at_its_heading() -> None:
    b = Behaviour(3, Mission(robot=3, kind="hold"), CFG, ROBOT)
    commands, yaw = _hold(b, 200)  # nobody seen on the way
    turning = [k for k, (v, w) in enumerate(commands) if w != 0.0]
    assert turning[0] == 0 and turning == list(range(len(turning))) and 62 <= len(turning) <= 65
    assert all(commands[k] == (0.0, CFG.search_speed_rad_s) for k in turning)  # on the spot, search speed
    assert abs(yaw) < 0.15 and all(c == (0.0, 0.0) for c in commands[turning[-1] + 1:])
    assert b.look_arounds == 1 and b.searches == 0 and b.lost_events == 0 and b.mode != Mode.LOST


def test_a_station_keeper_that_had_fixes_on_its_turn_ends_it_at_a_fix() -> None:
    # a wheel-base error scales every turn: ending at a fix leaves no net rotation since it
    b = Behaviour(3, Mission(robot=3, kind="hold"), CFG, ROBOT)
    commands, yaw = _hold(b, 300, fixes=(5, 45))  # fixes on the way do not stop the whole turn
    at_fix = math.remainder(45 * 0.1 * CFG.search_speed_rad_s, 2 * math.pi)  # the heading of the last fix
    turning = [k for k, (v, w) in enumerate(commands) if w != 0.0]
    assert turning == list(range(len(turning))) and 63 + 44 <= len(turning) <= 65 + 60  # on, never back
    assert all(v == 0.0 and w > 0.0 for v, w in commands[:len(turning)])
    assert abs(math.remainder(yaw - at_fix, 2 * math.pi)) < 0.02, (yaw, at_fix)
    assert all(c == (0.0, 0.0) for c in commands[turning[-1] + 1:])
    # a fix on the way on ends the turn there
    b2 = Behaviour(3, Mission(robot=3, kind="hold"), CFG, ROBOT)
    commands2, _ = _hold(b2, 300, fixes=(5, 45, 80))
    turning2 = [k for k, (v, w) in enumerate(commands2) if w != 0.0]
    assert turning2[-1] == 79 and all(c == (0.0, 0.0) for c in commands2[80:])
    # a last fix right at the start of the turn: the sweep's overshoot passed it, no second turn
    b3 = Behaviour(3, Mission(robot=3, kind="hold"), CFG, ROBOT)
    commands3, _ = _hold(b3, 300, fixes=(0,))
    assert len([c for c in commands3 if c[1] != 0.0]) <= 65


def test_no_look_around_when_switched_off_without_a_server_or_after_a_goal() -> None:
    off = Behaviour(3, Mission(robot=3, kind="hold"), Agent(look_around=False), ROBOT)
    assert all(c == (0.0, 0.0) for c in _hold(off, 100)[0]) and off.look_arounds == 0
    alone = Behaviour(3, Mission(robot=3, kind="hold"), CFG, ROBOT)
    assert all(c == (0.0, 0.0) for c in _hold(alone, 100, server_up=False)[0]) and alone.look_arounds == 0
    sent = Behaviour(3, Mission(robot=3, kind="hold"), CFG, ROBOT)
    sent.set_goal(1.0, 2.0, 0.05)  # already there: done at once, and it holds where it was sent
    assert all(c == (0.0, 0.0) for c in _hold(sent, 100)[0]) and sent.done and sent.look_arounds == 0


def test_a_station_keeper_not_placed_by_its_look_around_searches_once_more_later() -> None:
    cfg = Agent(fix_threshold=40, search_speed_rad_s=1.0, search_max_sweep_rad=6.3)
    b = Behaviour(5, Mission(robot=5, kind="hold"), cfg, ROBOT)
    wait = 3 * cfg.fix_threshold
    commands, _ = _hold(b, 300, placed_from=10_000)
    turning = [k for k, (v, w) in enumerate(commands) if w != 0.0]
    first = [k for k in turning if k < 100]
    second = [k for k in turning if k > 100]
    assert first[0] == 0 and 62 <= len(first) <= 65 and b.look_arounds == 1
    # never placed: the old rule (a sweep after 3 x fix_threshold unplaced cycles), then lost, standing still
    assert second[0] == wait and 62 <= len(second) <= 65
    assert b.searches == 1 and b.mode == Mode.LOST and commands[-1] == (0.0, 0.0)


def test_station_keeping_robot_never_placed_turns_around_once_then_holds() -> None:
    b = Behaviour(5, Mission(robot=5, kind="hold"), Agent(fix_threshold=10, search_speed_rad_s=1.0,
                                                          search_max_sweep_rad=6.3, look_around=False), ROBOT)
    wait = 3 * CFG.fix_threshold
    yaw, commands, placed_at = 0.0, [], wait + 20
    for k in range(200):
        placed = k >= placed_at  # seen (and placed) during its turn
        v, w = b.cycle(t_s=k, map_pose=(1.0, 2.0, yaw) if placed else None, odom_yaw=yaw, moved=False,
                       fix=k == placed_at)
        yaw = math.remainder(yaw + w * 0.1, 2 * math.pi)
        commands.append((v, w))
    # waits for a placement, then turns on the spot (never drives) a whole sweep, placed on the way or not
    assert all(c == (0.0, 0.0) for c in commands[:wait])
    turning = [k for k, (v, w) in enumerate(commands) if w != 0.0]
    assert all(commands[k][0] == 0.0 for k in turning) and turning[0] == wait
    # 6.3 rad at 0.1 rad a step, then on to the heading of its fix (2 rad into the turn) the short way
    assert turning == list(range(wait, wait + len(turning))) and 62 + 19 <= len(turning) <= 65 + 30
    assert abs(yaw - 20 * 0.1) < 0.02
    assert all(c == (0.0, 0.0) for c in commands[turning[-1] + 1:]) and b.searches == 1 and b.lost_events == 0


def test_wheel_speeds_respect_limit_and_keep_curvature() -> None:
    left, right = wheel_speeds(2.0, 4.0, ROBOT)
    assert max(abs(left), abs(right)) <= ROBOT.max_wheel_speed_rad_s + 1e-9
    r, b = ROBOT.wheel_radius_m, ROBOT.wheel_base_m
    v, w = r * (left + right) / 2, r * (right - left) / b
    assert math.isclose(w / v, 2.0, rel_tol=1e-9)


def _drive(b: Behaviour, pose: tuple[float, float, float], seconds: float, dt: float = 0.05) -> tuple:
    for k in range(int(seconds / dt)):
        v, w = b.cycle(t_s=k * dt, map_pose=pose, odom_yaw=pose[2], moved=True, fix=True)
        pose = se2_compose(pose, (v * dt, 0.0, w * dt))
    return pose


def test_go_to_reaches_waypoints_and_stops() -> None:
    b = _moving(Mission(robot=1, kind="waypoints", waypoints=((1.0, 1.0), (-1.0, 0.5))))
    end = _drive(b, (0.0, 0.0, 0.0), 40.0)
    assert b.done and math.dist(end[:2], (-1.0, 0.5)) < CFG.goal_tolerance_m + 0.02
    assert go_to(end, (-1.0, 0.5), CFG)[0] < 0.1


def test_run_time_goal_overrides_mission_in_map_frame() -> None:
    b = Behaviour(1, Mission(robot=1, kind="hold"), CFG, ROBOT, arena_to_map=(1.0, 0.0, 0.0))
    b.set_goal(0.5, -0.5, 0.05)
    end = _drive(b, (0.0, 0.0, 0.0), 20.0)
    assert math.dist(end[:2], (0.5, -0.5)) < 0.07 and b.goal is None


def test_patrol_turns_back_and_waypoints_are_in_the_arena_frame() -> None:
    # map frame = arena shifted by +1 m in x
    b = Behaviour(1, Mission(robot=1, kind="patrol", waypoints=((0.0, 0.0), (1.0, 0.0))), CFG, ROBOT,
                  arena_to_map=(1.0, 0.0, 0.0))
    pose = (1.0, 0.0, 0.0)
    xs = []
    for _ in range(40):
        pose = _drive(b, pose, 1.0)
        xs.append(pose[0])
    assert max(xs) > 1.85 and min(xs[10:]) < 1.15  # visits map x=2 and comes back to map x=1


def test_leapfrog_moves_only_on_its_turn() -> None:
    m = Mission(robot=2, kind="leapfrog", waypoints=((2.0, 0.0), (0.0, 0.0)), leapfrog_period_s=5.0)
    b = Behaviour(2, m, CFG, ROBOT, leapfrog_team=(1, 2))
    v0, _ = b.cycle(t_s=1.0, map_pose=(0, 0, 0), odom_yaw=0.0, moved=False, fix=True)   # robot 1's turn
    v1, _ = b.cycle(t_s=6.0, map_pose=(0, 0, 0), odom_yaw=0.0, moved=False, fix=True)   # robot 2's turn
    assert v0 == 0.0 and v1 > 0.0


def test_without_a_server_the_robot_keeps_its_mission_on_odometry_and_searches_once_it_is_back() -> None:
    b = _moving()
    pose = (0.0, 0.0, 0.0)
    b.cycle(t_s=0, map_pose=pose, odom_yaw=0.0, moved=False, fix=True)
    for k in range(3 * CFG.fix_threshold):  # long past the search threshold
        v, w = b.cycle(t_s=k, map_pose=pose, odom_yaw=0.0, moved=True, fix=False, server_up=False)
        assert v > 0 and b.mode in (Mode.VISUAL, Mode.ODOMETRY)
    assert b.mode == Mode.ODOMETRY and b.searches == 0
    v, w = b.cycle(t_s=99, map_pose=pose, odom_yaw=0.0, moved=True, fix=False, server_up=True)
    assert b.mode == Mode.SEARCHING and (v, w) == (0.0, CFG.search_speed_rad_s)
    # the server vanishes mid-search: stop the useless sweep, back to the mission
    v, w = b.cycle(t_s=100, map_pose=pose, odom_yaw=0.2, moved=True, fix=False, server_up=False)
    assert b.mode == Mode.ODOMETRY and v > 0


def test_never_localised_and_no_server_stands_still() -> None:
    b = _moving()
    for k in range(50):
        assert b.cycle(t_s=k, map_pose=None, odom_yaw=0.0, moved=False, fix=False, server_up=False) == (0.0, 0.0)
    assert b.mode == Mode.ODOMETRY and b.searches == 0


def test_run_time_goal_on_a_spot_another_robot_stands_on_is_done_at_the_clearance() -> None:
    foot = footprint_radius(ROBOT)
    b = Behaviour(1, Mission(robot=1, kind="hold"), CFG, ROBOT)
    b.set_goal(2.0, 0.0, 0.05)
    other = (Neighbour(2, 2.0, 0.0, 0.0, 0.0, foot),)
    pose = (0.0, 0.0, 0.0)
    for k in range(600):
        v, w = b.cycle(t_s=k * 0.05, map_pose=pose, odom_yaw=pose[2], moved=True, fix=True, neighbours=other)
        pose = se2_compose(pose, (v * 0.05, 0.0, w * 0.05))
    assert b.done and b.goal is None
    keep = 2 * foot + CFG.avoid_clearance_m
    assert keep - 0.01 <= math.dist(pose[:2], (2.0, 0.0)) <= keep + 0.05 + 0.02
    # without avoidance the same goal is driven onto
    plain = Behaviour(1, Mission(robot=1, kind="hold"), Agent(avoid=False), ROBOT)
    plain.set_goal(2.0, 0.0, 0.05)
    end = _drive(plain, (0.0, 0.0, 0.0), 30.0)
    assert math.dist(end[:2], (2.0, 0.0)) < 0.05


def test_an_uncertain_position_starts_the_search_before_the_count_when_asked() -> None:
    cfg = Agent(fix_threshold=100, search_speed_rad_s=1.0, search_sigma_m=0.12)
    count_only = Agent(fix_threshold=100, search_speed_rad_s=1.0)
    pose = (0.0, 0.0, 0.0)
    # with the sigma rule: a second (2 x visual_hold = 30 cycles) after the fix, not before; without: the count
    for cfg_k, want in ((cfg, 31), (count_only, 101)):
        b = Behaviour(1, Mission(robot=1, kind="waypoints", waypoints=((3.0, 0.0),)), cfg_k, ROBOT)
        b.cycle(t_s=0, map_pose=pose, odom_yaw=0.0, moved=True, fix=True, pos_sigma_m=0.02)
        started = None
        for k in range(1, 200):
            sigma = 0.02 + 0.004 * k  # the fused sigma grows on odometry: past 0.12 m at k = 26
            b.cycle(t_s=k, map_pose=pose, odom_yaw=0.0, moved=True, fix=False, pos_sigma_m=sigma)
            if b.mode == Mode.SEARCHING:
                started = k
                break
        assert started == want, (started, cfg_k.search_sigma_m)
    # a certain pose never triggers it, and standing still never does
    b = Behaviour(1, Mission(robot=1, kind="waypoints", waypoints=((3.0, 0.0),)), cfg, ROBOT)
    b.cycle(t_s=0, map_pose=pose, odom_yaw=0.0, moved=True, fix=True)
    for k in range(1, 90):
        b.cycle(t_s=k, map_pose=pose, odom_yaw=0.0, moved=True, fix=False, pos_sigma_m=0.05)
        b.cycle(t_s=k, map_pose=pose, odom_yaw=0.0, moved=False, fix=False, pos_sigma_m=0.5)
    assert b.mode != Mode.SEARCHING and b.searches == 0


def test_a_robot_placed_but_not_vouched_for_searches_then_drives_its_mission_slowly_on_the_loose_pose() -> None:
    b = _moving()
    loose, yaw = (0.0, 0.0, 0.0), 0.0
    cmds = []
    for k in range(CFG.fix_threshold + 5):
        v, w = b.cycle(t_s=k, map_pose=None, odom_yaw=yaw, moved=False, fix=False, loose_pose=loose)
        yaw += w * 0.1
        cmds.append((v, w))
    # first as if not placed: no forward motion, it turns to look
    assert all(v == 0.0 for v, _ in cmds[:CFG.fix_threshold]) and cmds[0][1] == CFG.search_speed_rad_s
    # then on the loose pose, towards the waypoint at (3, 0), at the lost speed at most
    v, w = b.cycle(t_s=200, map_pose=None, odom_yaw=yaw, moved=True, fix=True, loose_pose=(0.0, 0.0, 0.0))
    assert b.on_loose and 0 < v <= CFG.lost_speed_factor * CFG.max_speed_m_s + 1e-9
    # without the loose pose it would still stand
    plain = _moving()
    for k in range(CFG.fix_threshold + 5):
        plain.cycle(t_s=k, map_pose=None, odom_yaw=0.0, moved=False, fix=False)
    assert plain.cycle(t_s=200, map_pose=None, odom_yaw=0.0, moved=True, fix=True)[0] == 0.0
    # a vouched pose wins over a loose one, at full speed
    v_full, _ = b.cycle(t_s=201, map_pose=(0.0, 0.0, 0.0), odom_yaw=yaw, moved=True, fix=True,
                        loose_pose=(5.0, 5.0, 0.0))
    assert not b.on_loose and v_full > CFG.lost_speed_factor * CFG.max_speed_m_s


def test_a_robot_the_server_no_longer_vouches_for_drives_on_slowly() -> None:
    b = _moving()
    v_full, _ = b.cycle(t_s=0.0, map_pose=(0.0, 0.0, 0.0), odom_yaw=0.0, moved=True, fix=True)
    assert not b.on_loose and v_full > CFG.lost_speed_factor * CFG.max_speed_m_s
    # its sigma grew past claim_sigma_m: the same mission, towards (3, 0), at the lost speed at most
    v, _ = b.cycle(t_s=0.1, map_pose=(0.0, 0.0, 0.0), odom_yaw=0.0, moved=True, fix=False, vouched=False)
    assert b.on_loose and 0 < v <= CFG.lost_speed_factor * CFG.max_speed_m_s + 1e-9, v
    # vouched for again: full speed
    v_again, _ = b.cycle(t_s=0.2, map_pose=(0.0, 0.0, 0.0), odom_yaw=0.0, moved=True, fix=True, vouched=True)
    assert not b.on_loose and v_again == v_full
