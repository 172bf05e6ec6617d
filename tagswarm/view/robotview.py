"""What the live view keeps of one robot (:class:`RobotView`) and of one observation
(:class:`Sighting`), as :class:`~tagswarm.view.state.ViewState` folds messages into them.

Plain records: how messages fill them (frames, checks) and the JSON the page gets are in
:mod:`tagswarm.view.state`.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Final

from tagswarm.evaluation.localised import LocalisedClock
from tagswarm.protocol.geometry import Pose2

#: Ground-truth history kept per robot to compare a fused pose with the truth at the same stamp.
TRUTH_HISTORY: Final = 240


@dataclass
class RobotView:
    """What the view knows about one robot; poses (x_m, y_m, yaw_rad) in the map frame."""

    robot_id: int
    truth: Pose2 | None = None
    truth_history: deque[tuple[int, Pose2]] = field(default_factory=lambda: deque(maxlen=TRUTH_HISTORY))
    fused: Pose2 | None = None
    fused_cov: tuple[float, ...] = ()
    fused_stamp_ns: int = -1
    fused_source: str = ""  # "map" (GlobalMap entry) or "correction"
    localised: bool | None = None
    last_fix_ns: int = 0
    odom: Pose2 | None = None
    odom_distance_m: float = 0.0
    mode: str | None = None
    alive: bool | None = None
    counters: dict[str, int] = field(default_factory=dict)
    localised_clock: LocalisedClock = field(default_factory=LocalisedClock)
    relocalisations: int = 0

    def truth_at(self, stamp_ns: int) -> Pose2 | None:
        """The newest ground truth at or before ``stamp_ns`` (None if none is kept)."""
        for t, p in reversed(self.truth_history):
            if t <= stamp_ns:
                return p
        return None


@dataclass(frozen=True)
class Sighting:
    """The newest observation of one target by one observer (target pose in the observer's base frame)."""

    observer: int
    kind: str
    target: int
    stamp_ns: int
    x_m: float
    y_m: float
