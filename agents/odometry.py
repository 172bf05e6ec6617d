"""Differential-drive dead reckoning from wheel-encoder counts, and evidence of
wheel slip from commanded against measured wheel rotation (pure code).

Frames (REP-105): the pose is ``base_link`` in the robot's ``odom`` frame, x
forward, y left, yaw counter-clockwise, metres and radians.

Slip evidence (:class:`SlipMonitor`): the agent knows the wheel speeds it
commanded, and the world turns the wheels at exactly those speeds (whatever the
true wheel radius) unless something moves the robot otherwise.  Over windows of
encoder intervals, the measured rotation of each wheel is compared with the
range the commands allow given that the world applies a command up to
``delay_ns`` after its stamp; a difference beyond the encoder resolution and
``sigmas`` standard deviations of the assumed wheel noise is evidence, summed
over both wheels in metres of wheel travel (``slip_m``, cumulative).  What it
can see depends on the physics: a robot pushed while it stands (or pushed
along faster than it drives) has its wheels turned by the ground, which shows;
a blocked robot whose wheels keep turning at the commanded speed, or a
sideways push that does not turn the wheels, leaves no trace in the encoders.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from tagswarm.protocol.geometry import wrap_angle


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

    def add_slip(self, slip_m: float) -> None:
        """Widen the covariance by ``slip_m`` metres of unexplained wheel travel: that much error in
        any direction, and the heading error of it on one wheel (as the server's noise model does)."""
        var = slip_m * slip_m
        self.cov = self.cov + np.diag([var, var, var / (self.params.wheel_base_m / 2.0) ** 2])


SLIP_WINDOW = 9  # encoder intervals per comparison (0.3 s at 30 Hz): long enough to beat the noise, short
SLIP_SIGMAS = 3.0
SLIP_TICKS = 2.0  # encoder resolution allowance (counts are floored; a window's sum is off by < 1 count)


@dataclass
class SlipMonitor:
    """Cumulative slip evidence ``slip_m`` (m of wheel travel) from the commands sent
    (:meth:`commanded`) and the encoder counts received (:meth:`measured`); see the module docstring.

    ``delay_ns`` is the longest the world may take to apply a command after its stamp (0 in
    lockstep, where a command stamped at a tick drives the very next step); ``timeout_ns`` the
    world's command timeout, after which a command no longer drives; ``wheel_sigma`` (sqrt(m)) the
    wheel-travel noise the agent assumes (variance ``wheel_sigma^2 |d|`` for a travel d)."""

    wheel_radius_m: float
    ticks_per_rev: int
    wheel_sigma: float
    delay_ns: int
    timeout_ns: int
    window: int = SLIP_WINDOW
    sigmas: float = SLIP_SIGMAS
    slip_m: float = 0.0
    events: int = 0
    replaying: bool = False
    _cmds: list[tuple[int, float, float]] = field(default_factory=list, repr=False)
    _last: tuple[int, int, int] | None = field(default=None, repr=False)
    _acc: list[float] = field(default_factory=lambda: [0.0] * 5, repr=False)  # disc l, r; travel l, r; count

    def commanded(self, stamp_ns: int, left_rad_s: float, right_rad_s: float, *, recorded: bool = False) -> None:
        """A wheel command sent with this stamp (rad/s).  ``recorded``: a replay's copy of the command the
        wheels were driven with when the run was recorded; from the first one on, the agent's own commands
        (which drive nothing in a replay) are ignored, so a replay with other settings or another controller
        sees the recorded wheels against the recorded commands, not against its own."""
        if recorded and not self.replaying:
            self.replaying = True
            self._cmds.clear()
        elif self.replaying and not recorded:
            return
        if self._cmds and stamp_ns < self._cmds[-1][0]:
            return  # a command never takes effect before an earlier one
        self._cmds.append((stamp_ns, left_rad_s, right_rad_s))
        if self._last is not None:
            # keep the newest command from before anything still to be compared
            horizon = self._last[0] - self.delay_ns - self.timeout_ns
            while len(self._cmds) > 2 and self._cmds[1][0] <= horizon:
                self._cmds.pop(0)

    def _pieces(self, t0: int, t1: int) -> Iterator[tuple[int, int, float, float]]:
        """The commanded (left, right) rates in force over [t0, t1), as (start, end, l, r) pieces."""
        cmds = self._cmds
        for i, (s, left, right) in enumerate(cmds):
            end = cmds[i + 1][0] if i + 1 < len(cmds) else t1
            lo, hi = max(s, t0), min(end, s + self.timeout_ns, t1)
            if hi > lo:
                yield lo, hi, left, right

    def _rotation(self, t0: int, t1: int) -> tuple[float, float]:
        """Commanded wheel rotation (rad) over [t0, t1)."""
        left = right = 0.0
        for lo, hi, cl, cr in self._pieces(t0, t1):
            left += cl * (hi - lo) / 1e9
            right += cr * (hi - lo) / 1e9
        return left, right

    def measured(self, stamp_ns: int, left_ticks: int, right_ticks: int) -> float:
        """New cumulative encoder counts; returns the slip evidence (m) this adds (0 mostly)."""
        last, self._last = self._last, (stamp_ns, left_ticks, right_ticks)
        if last is None or stamp_ns <= last[0]:
            return 0.0
        a, b = last[0], stamp_ns
        if not self._cmds or a < self._cmds[0][0] + self.delay_ns:
            return 0.0  # what drove the wheels before our first command is unknown
        per_rad = 2.0 * math.pi / self.ticks_per_rev
        meas = ((left_ticks - last[1]) * per_rad, (right_ticks - last[2]) * per_rad)
        # the command a delay d ago drove the wheels: the extremes over d lie at d = 0, the longest
        # delay, or where a command change crosses an end of the interval
        delays = {0, self.delay_ns}
        for s, _, _ in self._cmds:
            delays.update(d for d in (a - s, b - s) if 0 < d < self.delay_ns)
        options = [self._rotation(a - d, b - d) for d in sorted(delays)]
        r = self.wheel_radius_m
        acc = self._acc
        for w in (0, 1):
            lo, hi = min(o[w] for o in options), max(o[w] for o in options)
            acc[w] += (meas[w] - min(max(meas[w], lo), hi)) * r
            acc[2 + w] += max(abs(meas[w]), abs(hi), abs(lo)) * r
        acc[4] += 1
        if acc[4] < self.window:
            return 0.0
        self._acc = [0.0] * 5
        resolution = SLIP_TICKS * per_rad * r
        evidence = 0.0
        for w in (0, 1):
            if abs(acc[w]) > resolution + self.sigmas * self.wheel_sigma * math.sqrt(acc[2 + w]):
                evidence += abs(acc[w])
        if evidence > 0:
            self.slip_m += evidence
            self.events += 1
        return evidence
