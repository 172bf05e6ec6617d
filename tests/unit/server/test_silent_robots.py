"""Lockstep: the server stops waiting for the odometry of a robot whose agent is alive but
silent, after ``clock.ack_stall_after`` waits in a row ran out (server/intake.py, pure)."""

from __future__ import annotations

from tagswarm.server.intake import SilentRobots

ALIVE = {0, 1, 2}


def test_a_robot_late_three_ticks_in_a_row_is_not_waited_for_until_its_odometry_comes_again() -> None:
    s = SilentRobots(3)
    rx = {0: 100, 1: 100, 2: 40}  # robot 2's step hangs: its odometry stopped at 40
    for _ in range(2):
        s.release(rx)
        assert s.waited(ALIVE) == ALIVE and s.settled(ALIVE, {2}, rx) == []
    assert s.settled(ALIVE, {2}, rx) == [2] and s.waited(ALIVE) == {0, 1}
    s.release(rx)
    assert s.settled({0, 1}, set(), rx) == [] and s.waited(ALIVE) == {0, 1}  # still silent
    rx[2] = 41  # its step returned: odometry again
    s.release(rx)
    assert s.waited(ALIVE) == ALIVE and s.missed == {}
    assert s.settled(ALIVE, {2}, rx) == [] and s.missed == {2: 1}  # counting starts over


def test_late_ticks_not_in_a_row_never_stall_and_0_never_stalls() -> None:
    s = SilentRobots(2)
    rx = {0: 0, 1: 0, 2: 0}
    for k in range(10):
        assert s.settled(ALIVE, {1} if k % 2 else set(), rx) == []
    never = SilentRobots(0)
    assert all(never.settled(ALIVE, {1}, rx) == [] for _ in range(20)) and never.waited(ALIVE) == ALIVE


def test_a_robot_whose_agent_went_or_came_is_waited_for_again() -> None:
    s = SilentRobots(1)
    rx = {1: 500}
    assert s.settled(ALIVE, {1}, rx) == [1] and s.waited(ALIVE) == {0, 2}
    s.forget(1)  # its liveliness token vanished, or came back (a restarted agent counts odometry from 0)
    s.release({1: 0})
    assert s.waited(ALIVE) == ALIVE and s.missed == {}
