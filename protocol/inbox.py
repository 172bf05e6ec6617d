"""The queues Zenoh callbacks fill and a node's loop drains (:class:`Inbox`), and what
they hold (:class:`Received`).

Pure threading, no Zenoh import: :class:`tagswarm.protocol.bus.Bus` creates them and
re-exports both names.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass
from typing import Generic, TypeVar

T = TypeVar("T")


@dataclass
class Received(Generic[T]):
    """One item delivered to an :class:`Inbox`: the key it came on and its value."""

    key: str
    value: T


class Inbox(Generic[T]):
    """A bounded queue filled by Zenoh callbacks and drained by the node's loop.

    ``newest_only`` keeps just the latest item (a ring of one): use it for
    camera frames so that a slow consumer skips frames instead of queueing them.
    Otherwise it is a FIFO of ``capacity`` items; items beyond that are dropped
    and counted in ``overflow`` (a safety net, not a flow-control mechanism).
    ``fault_dropped`` counts the samples lost to injected network faults.
    ``wakes=False``: an arrival does not wake the loop (:meth:`tagswarm.protocol.bus.Bus.wait`); for inputs the
    loop only reads when something else woke it, so each such sample does not cost a
    pass of the loop.
    """

    def __init__(self, wake: threading.Condition, *, newest_only: bool, capacity: int, wakes: bool = True) -> None:
        self._items: deque[Received[T]] = deque(maxlen=1 if newest_only else capacity)
        self._wake = wake
        self._wakes = wakes
        self.received = 0
        self.overflow = 0
        self.fault_dropped = 0
        self._newest_only = newest_only

    def put(self, key: str, value: T) -> None:
        """Called from Zenoh threads: enqueue and wake the loop, nothing else."""
        with self._wake:
            if len(self._items) == self._items.maxlen and not self._newest_only:
                self.overflow += 1
            self._items.append(Received(key, value))
            self.received += 1
            if self._wakes:
                self._wake.notify_all()

    def count_fault_drop(self) -> None:
        """Called from Zenoh threads for a sample the fault injector discarded."""
        with self._wake:
            self.fault_dropped += 1

    def drain(self) -> list[Received[T]]:
        """Everything queued so far, oldest first."""
        with self._wake:
            items = list(self._items)
            self._items.clear()
        return items

    def __len__(self) -> int:
        return len(self._items)
