"""A test's own subscription to a live run: decoded messages in arrival order."""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

from tagswarm.protocol import codec
from tagswarm.protocol.bus import Bus
from tagswarm.testing.errors import SwarmTimeout


@dataclass(frozen=True)
class Sample:
    """One message: the key it came on, the decoded message (a msgspec Struct of
    :mod:`tagswarm.protocol.messages`) and the payload as it was on the wire."""

    key: str
    msg: Any
    payload: bytes


class Subscription:
    """Messages on a key expression since :meth:`tagswarm.testing.live.LiveSwarm.subscribe`.

    Payloads are decoded whatever their type (every message names its type on the wire:
    :func:`tagswarm.protocol.codec.decode_any`); one that does not decode is counted in
    ``rejected``, never delivered.  ``get`` blocks, iterating yields what has arrived so far, ``drain`` takes it all."""

    def __init__(self, bus: Bus, keyexpr: str, *, newest_only: bool = False) -> None:
        self.keyexpr = keyexpr
        self.rejected = 0
        self._bus = bus
        self._inbox = bus.subscribe(keyexpr, newest_only=newest_only)
        self._ready: deque[Sample] = deque()

    def _pull(self) -> None:
        for item in self._inbox.drain():
            try:
                msg = codec.decode_any(item.value)
            except codec.DecodeError:
                self.rejected += 1
                continue
            self._ready.append(Sample(item.key, msg, bytes(item.value)))

    def drain(self) -> list[Sample]:
        """Every message received and not yet taken, oldest first."""
        self._pull()
        out = list(self._ready)
        self._ready.clear()
        return out

    def __iter__(self) -> Iterator[Sample]:
        """What has arrived so far (does not wait)."""
        return iter(self.drain())

    def get(self, timeout_s: float = 30.0, where: Callable[[Sample], bool] | None = None) -> Sample:
        """The next message (the next one ``where`` accepts: the others are dropped), waiting up
        to ``timeout_s`` wall seconds; :class:`SwarmTimeout` if none comes."""

        def have() -> bool:
            self._pull()
            while self._ready and where is not None and not where(self._ready[0]):
                self._ready.popleft()
            return bool(self._ready)

        if not self._bus.wait_for(have, timeout_s):
            raise SwarmTimeout(f"no message on {self.keyexpr} within {timeout_s:g} s")
        return self._ready.popleft()
