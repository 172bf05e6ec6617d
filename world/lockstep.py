"""Who must acknowledge a tick before the world may step (pure logic, no I/O)."""

from __future__ import annotations

from collections.abc import Iterable


class AckTracker:
    """Tracks declared lockstep participants: which are alive (from liveliness),
    and which acknowledged which step.

    A participant is *required* for a step while it is alive.  One that never
    came up or whose liveliness token vanished is not waited for, so a killed
    process cannot hang the world; one that comes back is required again.
    """

    def __init__(self, participants: Iterable[str]) -> None:
        self.declared: frozenset[str] = frozenset(participants)
        self.alive: set[str] = set()
        self.last_ack: dict[str, int] = {}

    def set_alive(self, participant: str, alive: bool) -> bool:
        """Record a liveliness change; returns True if it concerns a declared participant."""
        if participant not in self.declared:
            return False
        if alive:
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
        return True

    def pending(self, step: int) -> set[str]:
        """Alive participants that have not acknowledged ``step`` yet."""
        return {p for p in self.alive if self.last_ack.get(p, -1) < step}

    def missing(self) -> set[str]:
        """Declared participants that are not alive."""
        return set(self.declared - self.alive)
