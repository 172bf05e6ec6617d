"""Presence: a token, and (realtime) silence on top of it."""

from __future__ import annotations

import logging

import pytest

from tagswarm.runtime.presence import Presence, RunEnd, silence_ns

S = 1_000_000_000


def test_token_alone_decides_when_silence_is_off() -> None:
    p: Presence[int] = Presence(0)
    p.token(3, True, 0)
    p.update(100 * S)
    assert p.alive(3) and p.alive_set() == {3}
    p.token(3, False, 100 * S)
    assert not p.alive(3) and p.alive_set() == set()


def test_a_silent_peer_is_gone_until_it_talks_again(caplog: pytest.LogCaptureFixture) -> None:
    p: Presence[int] = Presence(2 * S)
    p.token(1, True, 0)
    p.token(2, True, 0)
    for t in range(0, 10):
        p.heard(1, t * S // 2)
        p.heard(2, t * S // 2)
    p.update(int(4.5 * S))
    assert p.alive_set() == {1, 2}
    # robot 2 falls silent at 4.5 s; its token stays up
    for t in range(10, 20):
        p.heard(1, t * S // 2)
        with caplog.at_level(logging.INFO):
            p.update(t * S // 2, logging.getLogger("t"), "robot {}")
    assert p.alive(1) and not p.alive(2)
    assert p.silences == 1
    assert p.alive_set() == {1}
    assert sum("robot 2 has sent nothing" in r.getMessage() for r in caplog.records) == 1
    # exactly at the threshold it is still there: gone only beyond it
    q: Presence[str] = Presence(2 * S)
    q.token("s", True, 0)
    q.update(2 * S)
    assert q.alive("s")
    q.update(2 * S + 1)
    assert not q.alive("s")
    # it talks again
    p.heard(2, 10 * S)
    with caplog.at_level(logging.INFO):
        p.update(10 * S, logging.getLogger("t"), "robot {}")
    assert p.alive(2) and p.silences == 1
    assert any("robot 2 talks again" in r.getMessage() for r in caplog.records)


def test_a_new_token_restarts_the_silence_clock_and_a_lost_one_clears_it() -> None:
    p: Presence[int] = Presence(2 * S)
    p.token(5, True, 0)
    p.update(3 * S)
    assert not p.alive(5)
    p.token(5, False, 3 * S)
    assert 5 not in p.silent
    p.token(5, True, 10 * S)  # reconnected: heard from now on
    p.update(10 * S)
    p.update(11 * S)
    assert p.alive(5)
    p.update(12 * S + 1)
    assert not p.alive(5)


def test_a_jump_of_our_own_clock_is_no_silence_of_theirs() -> None:
    # an agent cut off from everything: its clock stood still, then jumps on the heal
    p: Presence[str] = Presence(2 * S)
    p.token("server", True, 0)
    for t in range(5):
        p.heard("server", t * S)
        p.update(t * S)
    p.update(9 * S)  # 5 s without anything, our clock too
    assert p.alive("server") and p.silences == 0
    p.update(10 * S)
    assert p.alive("server")
    p.update(11 * S + 1)  # but silence after the jump counts
    assert not p.alive("server") and p.silences == 1


def test_a_clock_that_went_back_is_a_new_run() -> None:
    p: Presence[int] = Presence(2 * S)
    p.token(0, True, 0)
    p.heard(0, 30 * S)
    p.update(30 * S)
    p.heard(0, 1 * S)  # the world restarted: times start again
    p.update(1 * S)
    p.update(2 * S)
    p.update(3 * S + 1)
    assert not p.alive(0)  # silent since 1 s of the new run, not since 30 s of the old one


def test_silence_is_a_lease_plus_the_margin_plus_the_delay() -> None:
    assert silence_ns(1500, 0.0, 0.5) == 2 * S
    assert silence_ns(1500, 250.0, 1.0) == int(2.75 * S)


def test_run_end_after_the_world_left_near_the_end_for_the_grace() -> None:
    end = RunEnd(end_ns=12_000_000_000)
    assert not end.over(11_900_000_000, world_alive=True, now=0.0)
    assert not end.over(11_900_000_000, world_alive=False, now=1.0)  # the grace starts
    assert not end.over(11_900_000_000, world_alive=False, now=2.9)
    assert end.over(11_900_000_000, world_alive=False, now=3.0)


def test_run_end_not_when_the_world_left_early_or_came_back() -> None:
    end = RunEnd(end_ns=12_000_000_000)
    assert not end.over(5_000_000_000, world_alive=False, now=0.0)
    assert not end.over(5_000_000_000, world_alive=False, now=100.0)  # mid-run: a restart is waited for
    assert not end.over(11_500_000_000, world_alive=False, now=100.0)
    assert not end.over(11_500_000_000, world_alive=True, now=101.0)  # back: the grace starts again
    assert not end.over(11_500_000_000, world_alive=False, now=102.0)
    assert end.over(11_500_000_000, world_alive=False, now=104.0)
