"""Differential-drive dead reckoning from wheel-encoder counts (pure code).

Frames (REP-105): the pose is ``base_link`` in the robot's ``odom`` frame, x
forward, y left, yaw counter-clockwise, metres and radians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from protocol.geometry import wrap_angle


@dataclass(frozen=True)
class DiffDriveParams:
    """Nominal geometry the agent believes in (the world's true one may differ)."""

    wheel_radius_m: float
    wheel_base_m: float
    ticks_per_rev: int


@dataclass
class DiffDriveOdometry:
    """Integrates cumulative encoder counts into a pose with exact arc updates.

    The first :meth:`update` only latches the counts (no motion), so the
    odometry can start from any counter value, e.g. after an agent restart.
    """

    params: DiffDriveParams
    x_m: float = 0.0
    y_m: float = 0.0
    yaw_rad: float = 0.0
    distance_m: float = 0.0
    _last: tuple[int, int] | None = field(default=None, repr=False)

    def update(self, left_ticks: int, right_ticks: int) -> tuple[float, float]:
        """Advance to the new cumulative counts; returns (travel_m, dyaw_rad) of the step."""
        if self._last is None:
            self._last = (left_ticks, right_ticks)
            return 0.0, 0.0
        p = self.params
        per_tick = 2.0 * math.pi * p.wheel_radius_m / p.ticks_per_rev
        dl = (left_ticks - self._last[0]) * per_tick
        dr = (right_ticks - self._last[1]) * per_tick
        self._last = (left_ticks, right_ticks)
        ds = (dl + dr) / 2.0
        dth = (dr - dl) / p.wheel_base_m
        # exact integration along a circular arc; the chord formula for small dth
        if abs(dth) > 1e-9:
            r = ds / dth
            self.x_m += r * (math.sin(self.yaw_rad + dth) - math.sin(self.yaw_rad))
            self.y_m += -r * (math.cos(self.yaw_rad + dth) - math.cos(self.yaw_rad))
        else:
            self.x_m += ds * math.cos(self.yaw_rad + dth / 2.0)
            self.y_m += ds * math.sin(self.yaw_rad + dth / 2.0)
        self.yaw_rad = wrap_angle(self.yaw_rad + dth)
        self.distance_m += abs(ds)
        return ds, dth
