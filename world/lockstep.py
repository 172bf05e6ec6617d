"""Who must acknowledge a tick before the world may step (pure logic, no I/O)."""

from __future__ import annotations

from collections.abc import Iterable


class AckTracker:
    """Tracks declared lockstep participants: which are alive (from liveliness),
    and which acknowledged which step.

    A participant is *required* for a step while it is alive.  One that never
    came up or whose liveliness token vanished is not waited for, so a killed
    process cannot hang the world; one that comes back is required again, from
    the first tick published after it (re)joined: ticks sent before it listened
    can never be acknowledged by it.

    A participant alive but silent (a controller stuck in its step: the process
    and its liveliness token live on) is skipped after each timeout; after
    ``stall_after`` timeouts in a row it is *stalled*: not waited for at all until
    it acknowledges a step again, so one hung process costs the run a few
    timeouts rather than one per tick.  ``stall_after`` 0 never stalls anyone.
    """

    def __init__(self, participants: Iterable[str], stall_after: int = 0) -> None:
        self.declared: frozenset[str] = frozenset(participants)
        self.stall_after = stall_after
        self.alive: set[str] = set()
        self.last_ack: dict[str, int] = {}
        self.required_from: dict[str, int] = {}
        self.joins: dict[str, int] = {}  # how often each participant (re)joined
        self.missed: dict[str, int] = {}  # timeouts in a row
        self.stalled: set[str] = set()
        self.stalls = 0  # how often anyone was stalled

    def set_alive(self, participant: str, alive: bool, published_step: int = -1) -> bool:
        """Record a liveliness change; ``published_step`` is the newest step whose
        tick is already out (-1 before the first).  Returns True if it concerns a
        declared participant."""
        if participant not in self.declared:
            return False
        if alive:
            if participant not in self.alive:
                self.required_from[participant] = published_step + 1
                self.joins[participant] = self.joins.get(participant, 0) + 1
                self.missed.pop(participant, None)
                self.stalled.discard(participant)
            self.alive.add(participant)
        else:
            self.alive.discard(participant)
        return True

    def ack(self, participant: str, step: int) -> bool:
        """Record an ack; returns False (and ignores it) for undeclared participants."""
        if participant not in self.declared:
            return False
        if step > self.last_ack.get(participant, -1):
            self.last_ack[participant] = step
        self.missed.pop(participant, None)
        self.stalled.discard(participant)  # back: required again from the next step it has not acked
        return True

    def skip(self, participant: str, step: int) -> bool:
        """``participant`` did not acknowledge ``step`` in time: the world goes on without it for
        this step.  Returns True if that makes it stalled (see the class docstring)."""
        if step > self.last_ack.get(participant, -1):
            self.last_ack[participant] = step
        self.missed[participant] = self.missed.get(participant, 0) + 1
        if self.stall_after and self.missed[participant] >= self.stall_after and participant not in self.stalled:
            self.stalled.add(participant)
            self.stalls += 1
            return True
        return False

    def pending(self, step: int) -> set[str]:
        """Alive participants that have not acknowledged ``step`` yet (and must)."""
        return {p for p in self.alive - self.stalled
                if step >= self.required_from.get(p, 0) and self.last_ack.get(p, -1) < step}

    def missing(self) -> set[str]:
        """Declared participants that are not alive."""
        return set(self.declared - self.alive)
