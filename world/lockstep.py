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
    """

    def __init__(self, participants: Iterable[str]) -> None:
        self.declared: frozenset[str] = frozenset(participants)
        self.alive: set[str] = set()
        self.last_ack: dict[str, int] = {}
        self.required_from: dict[str, int] = {}
        self.joins: dict[str, int] = {}  # how often each participant (re)joined

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
        """Alive participants that have not acknowledged ``step`` yet (and must)."""
        return {p for p in self.alive
                if step >= self.required_from.get(p, 0) and self.last_ack.get(p, -1) < step}

    def missing(self) -> set[str]:
        """Declared participants that are not alive."""
        return set(self.declared - self.alive)
