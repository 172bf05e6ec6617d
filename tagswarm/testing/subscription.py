"""A test's own subscription to a live run: decoded messages in arrival order."""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

from tagswarm.protocol import codec
from tagswarm.protocol.bus import Bus
from tagswarm.testing.errors import SwarmTimeout

ENDED_GRACE_S = 1.0  # wall seconds a run's messages get to arrive after its last process exited


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

    def __init__(self, bus: Bus, keyexpr: str, *, newest_only: bool = False,
                 ended: Callable[[], bool] | None = None) -> None:
        self.keyexpr = keyexpr
        self.rejected = 0
        self._bus = bus
        self._ended = ended  # True once every process of the run has exited: nothing more can come
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
        to ``timeout_s`` wall seconds; :class:`SwarmTimeout` if none comes (at once if the run's
        processes have all exited and nothing is left)."""
        over = False
        ended_at: float | None = None

        def have() -> bool:
            nonlocal over, ended_at
            if ended_at is None and self._ended is not None and self._ended():
                ended_at = time.monotonic()
            self._pull()
            while self._ready and where is not None and not where(self._ready[0]):
                self._ready.popleft()
            # what the processes sent last may still be on its way for a moment after they exited
            over = ended_at is not None and time.monotonic() - ended_at > ENDED_GRACE_S and not self._ready
            return bool(self._ready) or over

        if not self._bus.wait_for(have, timeout_s) or over:
            raise SwarmTimeout(f"no message on {self.keyexpr} "
                               + ("and the run has ended" if over else f"within {timeout_s:g} s"))
        return self._ready.popleft()
