"""Differential-drive dead reckoning from wheel-encoder counts (pure code).

Frames (REP-105): the pose is ``base_link`` in the robot's ``odom`` frame, x
forward, y left, yaw counter-clockwise, metres and radians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from protocol.geometry import wrap_angle


@dataclass(frozen=True)
class DiffDriveParams:
    """Nominal geometry the agent believes in (the world's true one may differ)."""

    wheel_radius_m: float
    wheel_base_m: float
    ticks_per_rev: int
    wheel_sigma: float = 0.0  # sqrt(m): each wheel's travel d has variance wheel_sigma^2 |d|


@dataclass
class DiffDriveOdometry:
    """Integrates cumulative encoder counts into a pose with exact arc updates.

    The first :meth:`update` only latches the counts (no motion), so the
    odometry can start from any counter value, e.g. after an agent restart.
    ``cov`` (3, 3) is the covariance of (x_m, y_m, yaw_rad), propagated with the
    wheel-travel noise model of :class:`DiffDriveParams` (first order), so it
    grows with the distance travelled and the angle turned.
    """

    params: DiffDriveParams
    x_m: float = 0.0
    y_m: float = 0.0
    yaw_rad: float = 0.0
    distance_m: float = 0.0
    cov: NDArray[np.float64] = field(default_factory=lambda: np.zeros((3, 3)))
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
        self._propagate(ds, dth, dl, dr)
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

    def _propagate(self, ds: float, dth: float, dl: float, dr: float) -> None:
        """First-order covariance update for the midpoint motion model."""
        b = self.params.wheel_base_m
        a = self.yaw_rad + dth / 2.0
        c, s = math.cos(a), math.sin(a)
        f = np.array([[1.0, 0.0, -ds * s], [0.0, 1.0, ds * c], [0.0, 0.0, 1.0]])
        # d(x, y, yaw) / d(dl, dr)
        g = np.array([
            [0.5 * c + ds * s / (2 * b), 0.5 * c - ds * s / (2 * b)],
            [0.5 * s - ds * c / (2 * b), 0.5 * s + ds * c / (2 * b)],
            [-1.0 / b, 1.0 / b],
        ])
        k2 = self.params.wheel_sigma ** 2
        q = np.diag([k2 * abs(dl) + 1e-12, k2 * abs(dr) + 1e-12])
        self.cov = f @ self.cov @ f.T + g @ q @ g.T

    def pose(self) -> tuple[float, float, float]:
        """(x_m, y_m, yaw_rad) of base_link in odom."""
        return self.x_m, self.y_m, self.yaw_rad
