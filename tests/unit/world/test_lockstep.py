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
