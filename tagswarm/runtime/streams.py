"""Bookkeeping of the message streams a node receives and sends: rejected payloads per
kind (:class:`RejectCounter`), per-key sequence numbers (:class:`Sequencer`) and the gaps
they reveal (:class:`GapCounter`), and which world run a node follows
(:class:`RunFollower`).  Pure code, no Zenoh; the reject kinds are those of
:mod:`tagswarm.protocol.codec` plus the nodes' own (``spoofed``, ``foreign_run`` ...)."""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Iterable, Iterator
from typing import Any, Literal, TypeVar

from tagswarm.protocol import messages as m
from tagswarm.protocol.codec import DecodeError, decode

T = TypeVar("T", bound=m.Msg)

log = logging.getLogger(__name__)


class RejectCounter:
    """Counts rejected payloads per kind and logs the first of each kind once."""

    def __init__(self, logger: logging.Logger | None = None) -> None:
        self.counts: Counter[str] = Counter()
        self._log = logger or log

    def reject(self, kind: str, detail: str) -> None:
        """Record one rejected payload."""
        if self.counts[kind] == 0:
            self._log.warning("dropping bad payload (%s): %s; further ones are only counted", kind, detail)
        self.counts[kind] += 1

    def decoded(self, items: Iterable[Any], cls: type[T]) -> Iterator[tuple[Any, T]]:
        """Decode inbox items (``.key``, ``.value``) as ``cls``, yielding (item, message)
        and counting every payload that fails (the loop body never sees it)."""
        for item in items:
            try:
                yield item, decode(cls, item.value)
            except DecodeError as exc:
                self.reject(exc.kind, f"{item.key}: {exc.detail}")

    def total(self) -> int:
        """All rejects so far."""
        return sum(self.counts.values())

    def as_counters(self, prefix: str = "rejected_") -> dict[str, int]:
        """Counters for an :class:`~tagswarm.protocol.messages.AgentStatus`."""
        return {prefix + k: v for k, v in sorted(self.counts.items())}


class GapCounter:
    """Messages missing from each publisher's sequence, counted per label.

    Every publisher numbers its messages on one key 0, 1, 2...; a jump from
    ``n`` to ``n + k`` means ``k - 1`` messages were lost on the way (a lossy
    network, an overloaded queue).  A number at or below the last one seen is a
    restarted publisher (its sequencer began again) and restarts the count.
    Feed it only messages that passed validation, so forged numbers cannot
    inflate it beyond what a forger can do anyway.
    """

    def __init__(self) -> None:
        self._last: dict[str, int] = {}
        self.missing: Counter[str] = Counter()

    def seen(self, key: str, seq: int, label: str) -> int:
        """Record ``seq`` on ``key``; returns (and adds to ``missing[label]``) the gap before it."""
        last = self._last.get(key)
        self._last[key] = seq
        if last is None or seq <= last:
            return 0
        gap = seq - last - 1
        if gap:
            self.missing[label] += gap
        return gap

    def as_counters(self, prefix: str = "seq_gaps_") -> dict[str, int]:
        """Counters for a status message (only labels with losses appear)."""
        return {prefix + k: v for k, v in sorted(self.missing.items())}


class Sequencer:
    """Per-key sequence numbers of one publisher (receivers can count gaps)."""

    def __init__(self) -> None:
        self._seq: Counter[str] = Counter()

    def next(self, key: str) -> int:
        """The number for the next message on ``key``."""
        seq = self._seq[key]
        self._seq[key] += 1
        return seq

    def peek(self, key: str) -> int:
        """The number the next message on ``key`` will get, without taking it."""
        return self._seq[key]


class RunFollower:
    """Which world instance a node follows, from its ticks' ``run_id`` and the
    world's liveliness.  The first run seen is followed; a new ``run_id`` after the
    world's token vanished is a restarted world (the node resets); a new one while
    the world is alive is foreign (rejected, so a forged tick cannot hijack it).  The
    same world back after its token vanished (a partition healed, a router restarted)
    is followed again: its next tick, with the token alive, clears ``world_left``."""

    def __init__(self) -> None:
        self.run_id: str | None = None
        self.world_left = False
        self.world_alive = True

    def world_presence(self, alive: bool) -> None:
        """A liveliness change of the world's token."""
        self.world_alive = alive
        self.world_left = self.world_left or not alive

    def accept(self, run_id: str) -> Literal["same", "first", "restart", "foreign"]:
        """Classify a tick's ``run_id`` (and follow it unless foreign)."""
        if run_id == self.run_id:
            if self.world_alive:
                # the same world is back: without this, lockstep nodes kept abandoning its ticks after a
                # partition (2.5 simulated s in 30 s of wall time)
                self.world_left = False
            return "same"
        if self.run_id is not None and not self.world_left:
            return "foreign"
        verdict: Literal["first", "restart"] = "first" if self.run_id is None else "restart"
        self.run_id, self.world_left = run_id, False
        return verdict
