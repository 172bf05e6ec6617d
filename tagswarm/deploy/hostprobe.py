"""What the multi-host harness sees of a run, as one more Zenoh client of its router.

Presence (liveliness tokens, with the wall time of every change), the live record of
:class:`~tagswarm.recording.runrecorder.RunRecorder` (simulation time, fused and true
poses, agents' modes), the real-time factor, and optionally the latency image ->
correction measured as ``bench/speed.py`` does: for every correction whose
``last_fix_ns`` is new for its robot, the wall time from the first arrival here of an
image stamped ``last_fix_ns`` (the frame that gave the fix) to the arrival of that
correction.  The probe's session is delayed like an agent's, so that is the latency
an agent sees.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import Bus, Inbox
from tagswarm.protocol.keys import Keys
from tagswarm.protocol.scenario import Scenario
from tagswarm.recording.runrecorder import RunRecorder
from tagswarm.runtime import streams

MAX_IMAGE_STAMPS = 10_000  # first-arrival times kept (a few minutes of frames)


class Probe:
    """Poll it often (:meth:`poll`); read ``alive``, ``events``, ``rec``, :meth:`summary`."""

    def __init__(self, bus: Bus, keys: Keys, scenario: Scenario, *, latency: bool = False) -> None:
        self.keys = keys
        self.scenario = scenario
        self.rec = RunRecorder(bus, keys, scenario)
        self.presence: Inbox[Any] = bus.watch_liveliness(keys.alive_all())
        self.alive: set[str] = set()
        #: (wall time since the probe began, participant, alive?) for every change
        self.events: list[tuple[float, str, bool]] = []
        self.t0 = time.monotonic()
        self.first_tick: tuple[float, int] | None = None
        self.last_tick: tuple[float, int] | None = None
        self.latency = latency
        self.latencies_s: list[float] = []
        self._rc = streams.RejectCounter()
        self._images: Inbox[Any] | None = bus.subscribe(keys.images(), capacity=100_000) if latency else None
        self._corr: Inbox[Any] | None = bus.subscribe(keys.correction(), capacity=100_000) if latency else None
        self._first_image: dict[int, float] = {}
        self._last_fix: dict[int, int] = {}

    def poll(self) -> None:
        now = time.monotonic()
        for change in self.presence.drain():
            who = self.keys.participant_of(change.key)
            if who is None:
                continue
            (self.alive.add if change.value else self.alive.discard)(who)
            self.events.append((now - self.t0, who, bool(change.value)))
        self.rec.poll()
        if self.rec.sim_ns > 0:
            if self.first_tick is None:
                self.first_tick = (now, self.rec.sim_ns)
            if self.last_tick is None or self.rec.sim_ns > self.last_tick[1]:
                self.last_tick = (now, self.rec.sim_ns)
        if self._images is not None and self._corr is not None:
            for _, im in self._rc.decoded(self._images.drain(), m.CameraImage):
                self._first_image.setdefault(im.stamp_ns, now)
            if len(self._first_image) > MAX_IMAGE_STAMPS:
                for stamp in sorted(self._first_image)[: MAX_IMAGE_STAMPS // 2]:
                    del self._first_image[stamp]
            for _, c in self._rc.decoded(self._corr.drain(), m.Correction):
                if c.localised and c.last_fix_ns > self._last_fix.get(c.robot_id, -1):
                    if c.robot_id in self._last_fix and c.last_fix_ns in self._first_image:
                        self.latencies_s.append(now - self._first_image[c.last_fix_ns])
                    self._last_fix[c.robot_id] = c.last_fix_ns

    def went(self, participant: str, alive: bool, after_s: float = 0.0) -> float | None:
        """Wall time (probe clock) of the first change of ``participant`` to ``alive`` after ``after_s``."""
        return next((t for t, who, up in self.events if who == participant and up == alive and t >= after_s), None)

    def now(self) -> float:
        """The probe's clock: wall seconds since it began."""
        return time.monotonic() - self.t0

    def sim_s(self) -> float:
        return self.rec.sim_ns / 1e9

    def rtf(self) -> float | None:
        """Simulated over wall seconds between the first and the newest tick seen."""
        if self.first_tick is None or self.last_tick is None or self.last_tick[0] <= self.first_tick[0]:
            return None
        return (self.last_tick[1] - self.first_tick[1]) / 1e9 / (self.last_tick[0] - self.first_tick[0])

    def summary(self) -> dict[str, Any]:
        lat = np.array(self.latencies_s) * 1e3
        rtf = self.rtf()
        return {
            "sim_s": round(self.sim_s(), 3),
            "rtf": None if rtf is None else round(rtf, 3),
            "latency_image_to_correction_ms": {
                "n": int(lat.size),
                "p50": round(float(np.percentile(lat, 50)), 1) if lat.size else None,
                "p95": round(float(np.percentile(lat, 95)), 1) if lat.size else None,
                "max": round(float(lat.max()), 1) if lat.size else None,
            } if self.latency else None,
            "presence_changes": [(round(t, 3), who, up) for t, who, up in self.events],
        }
