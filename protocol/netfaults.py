"""Receive-side network fault injection: message loss and added delay (tests, demos).

Pure logic, no Zenoh: :mod:`tagswarm.protocol.bus` asks :meth:`NetFaults.admit` for every
sample that arrives on a subscription whose key matches the fault keys, drops it
if told so, and hands the rest to :meth:`NetFaults.hold`, which delivers them
``delay_s`` later from one timer thread (the Zenoh callback never sleeps).

Why the receive side: faults then belong to one process (one faulty agent can be
simulated without touching the others), the sender's congestion control is
unchanged, and each subscriber sees its own lossy link, as on a real network.

Reproducibility: the drop decision for the n-th sample on key K of subscription S
comes from a random stream seeded with ``(seed, S, K)``, the run id left out of S
and K (``tagswarm up`` picks a new one per run).  Samples of one key come from one
publisher in order, so the drop pattern of every key is the same on every run with
the same seed, whatever the interleaving between keys (lockstep runs stay
repeatable).  Delays are wall-clock time: in lockstep a delayed message lands at
whatever step the run has reached by then, so runs with delay do not repeat exactly.
"""

from __future__ import annotations

import heapq
import itertools
import random
import threading
import time
from collections.abc import Callable

from tagswarm.protocol.keys import ROOT

#: A sample whose delivery has been postponed: called when it is due.
Deliver = Callable[[], None]


class NetFaults:
    """Loss share ``loss`` (0..1) and added delay ``delay_s`` (seconds) for the keys
    that ``matches`` accepts (concrete sample keys), seeded with ``seed``.  ``jitter_s``
    spreads each sample's delay uniformly over ``delay_s ± jitter_s`` (seeded per key)
    while the samples of one key keep their order, as on one link: a sample is never
    due before the one of its key that arrived before it."""

    def __init__(self, *, loss: float, delay_s: float, seed: int, matches: Callable[[str], bool],
                 jitter_s: float = 0.0) -> None:
        if not 0.0 <= loss <= 1.0:
            raise ValueError(f"loss {loss!r} must be a share between 0 and 1")
        if not delay_s >= 0.0:
            raise ValueError(f"delay {delay_s!r} s must be >= 0")
        if not 0.0 <= jitter_s <= delay_s:
            raise ValueError(f"jitter {jitter_s!r} s must be between 0 and the delay ({delay_s!r} s)")
        self.loss = loss
        self.delay_s = delay_s
        self.jitter_s = jitter_s
        self._jitter: dict[str, random.Random] = {}
        self._last_due: dict[str, float] = {}
        self.seed = seed
        self._matches = matches
        self._lock = threading.Lock()
        self._streams: dict[tuple[str, str], random.Random] = {}
        self._match_cache: dict[str, bool] = {}
        self.dropped = 0
        self.delayed = 0
        self._line: _DelayLine | None = None

    @property
    def active(self) -> bool:
        return self.loss > 0.0 or self.delay_s > 0.0

    def matches(self, key: str) -> bool:
        """Whether faults apply to samples on the concrete ``key`` (cached: keys are few)."""
        hit = self._match_cache.get(key)
        if hit is None:
            hit = self._matches(key)
            if len(self._match_cache) < 65536:  # bounded even if a peer invents keys
                self._match_cache[key] = hit
        return hit

    def admit(self, sub_key: str, key: str) -> bool:
        """False if the sample on ``key`` received by subscription ``sub_key`` is lost."""
        if self.loss <= 0.0 or not self.matches(key):
            return True
        with self._lock:  # several Zenoh receive threads may call in (one per link)
            stream = self._streams.get((sub_key, key))
            if stream is None:
                name = f"{self.seed}/{_without_run(sub_key)}/{_without_run(key)}"
                stream = self._streams[(sub_key, key)] = random.Random(name)
            lost = stream.random() < self.loss
            if lost:
                self.dropped += 1
        return not lost

    def hold(self, key: str, deliver: Deliver) -> None:
        """Deliver now, or ``delay_s`` from now if faults apply to ``key``."""
        if self.delay_s <= 0.0 or not self.matches(key):
            deliver()
            return
        now = time.monotonic()
        with self._lock:
            if self._line is None:
                self._line = _DelayLine()
            line = self._line
            self.delayed += 1
            due = now + self.delay_s
            if self.jitter_s > 0.0:
                stream = self._jitter.get(key)
                if stream is None:
                    stream = self._jitter[key] = random.Random(f"{self.seed}/jitter/{_without_run(key)}")
                due = max(self._last_due.get(key, 0.0), due + stream.uniform(-self.jitter_s, self.jitter_s))
                if len(self._last_due) < 65536:
                    self._last_due[key] = due
        line.push(due, deliver)

    def close(self) -> None:
        """Stop the timer thread; samples still held are discarded."""
        with self._lock:
            line, self._line = self._line, None
        if line is not None:
            line.close()


def _without_run(key: str) -> str:
    """``tagswarm/<run>/rest`` -> ``rest`` (any other key unchanged)."""
    parts = key.split("/", 2)
    return parts[2] if len(parts) == 3 and parts[0] == ROOT else key


class _DelayLine:
    """Holds deliveries until due and runs them, in due order, on one thread."""

    def __init__(self) -> None:
        self._heap: list[tuple[float, int, Deliver]] = []
        self._order = itertools.count()  # ties (same due time) keep arrival order
        self._cv = threading.Condition()
        self._stopped = False
        self._thread = threading.Thread(target=self._run, name="tagswarm-net-delay", daemon=True)
        self._thread.start()

    def push(self, due: float, deliver: Deliver) -> None:
        with self._cv:
            if self._stopped:
                return
            heapq.heappush(self._heap, (due, next(self._order), deliver))
            self._cv.notify()

    def _run(self) -> None:
        with self._cv:
            while not self._stopped:
                now = time.monotonic()
                if self._heap and self._heap[0][0] <= now:
                    _, _, deliver = heapq.heappop(self._heap)
                    # inbox.put only takes its own bus lock, never this one: no lock-order cycle
                    deliver()
                    continue
                self._cv.wait(self._heap[0][0] - now if self._heap else None)

    def close(self) -> None:
        with self._cv:
            self._stopped = True
            self._heap.clear()
            self._cv.notify()
        self._thread.join(timeout=2.0)
