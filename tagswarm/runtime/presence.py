"""Is a peer there?  Its Zenoh liveliness token, and in realtime whether it still talks.

A liveliness token vanishes when the router closes the peer's session, which is one lease
after the peer fell silent -- except when the router still holds unsent bytes for it: Zenoh
sets ``SO_LINGER`` to 10 s on its TCP links, so closing the socket of a peer cut off by a
silent partition (a cable pulled, a radio out of range) blocks for up to 10 s, and the
token goes only then (measured across network namespaces: 12.5 s with a 1.5 s lease;
upstream eclipse-zenoh/zenoh#2718).  A node therefore also calls a peer gone when nothing
has come from it for ``silence_ns`` of simulated time while its own clock moved on, and
back as soon as something arrives again.  A jump of the node's own clock by more than
``silence_ns`` (it was cut off itself, or a new run began) restarts every peer's silence:
nobody could have been heard meanwhile.  In lockstep the world waits for every
participant, so silence cannot arise there and only the token counts (determinism).

Pure code: times are the caller's simulated nanoseconds.
"""

from __future__ import annotations

import logging
from collections.abc import Hashable
from dataclasses import dataclass, field
from typing import Generic, TypeVar

K = TypeVar("K", bound=Hashable)


def silence_ns(lease_ms: int, delay_ms: float, margin_s: float) -> int:
    """Simulated ns of silence after which a peer with a token counts as gone: one Zenoh lease
    (what a router waits before it drops a silent session), ``margin_s`` for the peer's own
    publishing period, and the receive delay (``delay_ms``, injected network delay)."""
    return int((lease_ms / 1e3 + margin_s + delay_ms / 1e3) * 1e9)


@dataclass
class Presence(Generic[K]):
    """Token and last-heard time of each peer (keyed by anything hashable: a robot id, a role).

    ``silence_ns`` <= 0 turns the silence rule off (token only)."""

    silence_ns: int
    tokens: set[K] = field(default_factory=set)
    heard_ns: dict[K, int] = field(default_factory=dict)
    silent: set[K] = field(default_factory=set)
    silences: int = 0  # how often a peer with a token fell silent
    last_update_ns: int | None = None

    def token(self, peer: K, present: bool, now_ns: int) -> None:
        """The peer's liveliness token appeared (``present``) or vanished at ``now_ns``."""
        if present:
            self.tokens.add(peer)
            # a fresh token counts as hearing from it: silence is measured from here
            self.heard_ns[peer] = now_ns
        else:
            self.tokens.discard(peer)
            self.silent.discard(peer)

    def heard(self, peer: K, now_ns: int) -> None:
        """Something arrived from ``peer`` at ``now_ns`` (the newest call wins: a clock that went
        back is a new world run, whose times are the ones to compare with)."""
        self.heard_ns[peer] = now_ns

    def update(self, now_ns: int, logger: logging.Logger | None = None, what: str = "peer {}") -> None:
        """Re-judge silence at ``now_ns``; logs each change (``what`` formatted with the peer)."""
        if self.silence_ns <= 0:
            return
        if self.last_update_ns is not None and not 0 <= now_ns - self.last_update_ns <= self.silence_ns:
            # our own clock jumped (we were cut off ourselves, or a new run began): nobody could be
            # heard meanwhile, so silence counts from now
            for peer in self.tokens:
                self.heard_ns[peer] = now_ns
        self.last_update_ns = now_ns
        for peer in self.tokens:
            quiet = now_ns - self.heard_ns.get(peer, now_ns) > self.silence_ns
            if quiet and peer not in self.silent:
                self.silent.add(peer)
                self.silences += 1
                if logger is not None:
                    logger.warning("%s has sent nothing for %.1f s although its token is still up: "
                                   "treated as gone until it talks again", what.format(peer),
                                   (now_ns - self.heard_ns.get(peer, now_ns)) / 1e9)
            elif not quiet and peer in self.silent:
                self.silent.discard(peer)
                if logger is not None:
                    logger.info("%s talks again", what.format(peer))

    def alive(self, peer: K) -> bool:
        """Token up and not silent."""
        return peer in self.tokens and peer not in self.silent

    def alive_set(self) -> set[K]:
        """Every peer that is alive now."""
        return self.tokens - self.silent


@dataclass
class RunEnd:
    """Realtime: whether a node's run is over although its own clock stopped short of the end.

    A realtime agent or server ends when its clock (from the data it receives) reaches the
    run's duration.  The world's last messages can be lost when it closes at the end (its links
    stalled by packet loss: the router drops a blocked link after 0.5 s), and then that clock
    never gets there and the process would run on for ever.  So: once the world's token has
    been gone ``grace_s`` (wall) while this clock is within ``slack_ns`` of ``end_ns``, the run
    is over.  A world that comes back within the grace (restarted, or a partition healed)
    cancels it; one that leaves earlier in the run is waited for, as before.
    Times: ``end_ns`` / ``time_ns`` simulated ns, ``now`` wall (monotonic) seconds."""

    end_ns: int
    slack_ns: int = 1_000_000_000
    grace_s: float = 2.0
    _gone_since: float | None = field(default=None, repr=False)

    def over(self, time_ns: int, world_alive: bool, now: float) -> bool:
        if world_alive or time_ns < self.end_ns - self.slack_ns:
            self._gone_since = None
            return False
        if self._gone_since is None:
            self._gone_since = now
        return now - self._gone_since >= self.grace_s
