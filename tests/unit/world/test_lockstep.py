"""Who the lockstep world waits for (world/lockstep.py, pure logic)."""

from __future__ import annotations

from tagswarm.world.lockstep import AckTracker


def test_dead_participants_are_not_waited_for_and_undeclared_ones_are_ignored() -> None:
    t = AckTracker(["agent/0", "server/0"])
    assert t.missing() == {"agent/0", "server/0"} and t.pending(0) == set()
    assert t.set_alive("agent/0", True) and t.set_alive("server/0", True)
    assert not t.set_alive("agent/9", True) and not t.ack("agent/9", 0)
    assert t.pending(0) == {"agent/0", "server/0"}
    t.ack("agent/0", 0)
    assert t.pending(0) == {"server/0"}
    t.set_alive("server/0", False)  # killed: its token vanished
    assert t.pending(0) == set() and t.missing() == {"server/0"}


def test_a_participant_that_rejoins_is_required_from_the_next_tick_only() -> None:
    t = AckTracker(["agent/1", "agent/2"])
    t.set_alive("agent/1", True)
    t.set_alive("agent/2", True)
    for step in range(5):
        t.ack("agent/1", step)
        t.ack("agent/2", step)
    t.set_alive("agent/2", False)
    t.ack("agent/1", 5)
    assert t.pending(5) == set()
    # it comes back while the world waits on step 6, whose tick went out before it listened
    t.set_alive("agent/2", True, published_step=6)
    t.ack("agent/1", 6)
    assert t.pending(6) == set()  # it cannot have seen tick 6: not waited for
    assert t.pending(7) == {"agent/1", "agent/2"}
    t.ack("agent/2", 7)
    assert t.pending(7) == {"agent/1"}
    assert t.joins == {"agent/1": 1, "agent/2": 2}
    t.set_alive("agent/2", True, published_step=20)  # a repeated PUT is not a rejoin
    assert t.pending(8) == {"agent/1", "agent/2"} and t.joins["agent/2"] == 2


def test_an_alive_but_silent_participant_is_stalled_after_timeouts_in_a_row_until_it_acks() -> None:
    t = AckTracker(["agent/0", "agent/1"], stall_after=3)
    t.set_alive("agent/0", True)
    t.set_alive("agent/1", True)
    for step in range(2):  # agent/1 hangs in its step from step 0 on
        t.ack("agent/0", step)
        assert t.pending(step) == {"agent/1"} and not t.skip("agent/1", step)
    t.ack("agent/0", 2)
    assert t.pending(2) == {"agent/1"} and t.skip("agent/1", 2)  # the third in a row
    assert t.stalled == {"agent/1"} and t.stalls == 1
    for step in range(3, 10):  # not waited for any more
        t.ack("agent/0", step)
        assert t.pending(step) == set()
    t.ack("agent/1", 1)  # its step returned: it acknowledges the tick it was on
    assert t.stalled == set() and t.pending(10) == {"agent/0", "agent/1"}
    t.ack("agent/1", 10)
    assert not t.skip("agent/1", 11) and not t.skip("agent/1", 12)  # the count started again
    assert t.stalled == set() and t.stalls == 1


def test_timeouts_not_in_a_row_never_stall_and_stall_after_0_never_does() -> None:
    t = AckTracker(["agent/0"], stall_after=2)
    t.set_alive("agent/0", True)
    for step in range(0, 10, 2):  # every other step late: never two in a row
        assert not t.skip("agent/0", step)
        t.ack("agent/0", step + 1)
    assert t.stalled == set()
    never = AckTracker(["agent/0"])
    never.set_alive("agent/0", True)
    assert not any(never.skip("agent/0", step) for step in range(50)) and never.pending(50) == {"agent/0"}


def test_a_stalled_participant_that_rejoins_is_required_again() -> None:
    t = AckTracker(["agent/0"], stall_after=1)
    t.set_alive("agent/0", True)
    assert t.skip("agent/0", 0) and t.pending(1) == set()
    t.set_alive("agent/0", False)  # killed and restarted
    t.set_alive("agent/0", True, published_step=4)
    assert t.stalled == set() and t.pending(5) == {"agent/0"}
