"""What "localised" means for evaluation, shared by the offline metrics
(:mod:`tagswarm.evaluation.recovery`) and the live view (:mod:`tagswarm.view.state`), and the live
view's running share of time localised.  Pure code, no numpy (the view imports it).

A robot is localised at time t while the newest fused estimate at or before t is
at most :data:`LOCALISED_HOLD_S` old and its position error (map frame, against
the truth at the estimate's stamp) is below :data:`LOCALISED_M`.  Each truth
sample's verdict holds until the robot's next truth sample (time-weighted).
"""

from __future__ import annotations

from typing import Final

LOCALISED_M: Final = 0.10
"""A robot is localised while its fused position error is below this (m)."""
LOCALISED_HOLD_S: Final = 0.5
"""A fused estimate stands for at most this long (s); a longer gap counts as not localised."""
MAX_STEP_NS: Final = 1_000_000_000
"""Truth samples further apart than this (ns: a viewer that joined late or stalled) add no time."""


class LocalisedClock:
    """Running localised / evaluated simulation time of one robot, fed one verdict per
    truth sample (ns of simulation time)."""

    def __init__(self) -> None:
        self.total_ns = 0
        self.localised_ns = 0
        self._last: tuple[int, bool] | None = None

    def add(self, stamp_ns: int, localised: bool) -> None:
        """The verdict at truth stamp ``stamp_ns``; the previous one holds until it."""
        last = self._last
        if last is not None and stamp_ns <= last[0]:
            return  # a late or repeated sample: time only moves forward
        if last is not None and stamp_ns - last[0] <= MAX_STEP_NS:
            dt = stamp_ns - last[0]
            self.total_ns += dt
            if last[1]:
                self.localised_ns += dt
        self._last = (stamp_ns, localised)

    @property
    def share(self) -> float | None:
        """Share of the evaluated time localised (None before any time was evaluated)."""
        return self.localised_ns / self.total_ns if self.total_ns > 0 else None
