"""Odometry calibration in the graph (server/odomcal.py): the arc model against wheels simulated
step by step, and a robot with miscalibrated wheels that drives out of view."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest

from tagswarm.protocol.geometry import Pose2, se2_between, se2_compose
from tagswarm.server import odomcal
from tagswarm.server.fusion import Fusion, FusionParams

BASE = 0.22


def _drive(left: float, right: float, base: float, steps: int = 200) -> Pose2:
    """The pose after each wheel rolls ``left``/``right`` metres evenly on wheel base ``base``."""
    pose: Pose2 = (0.0, 0.0, 0.0)
    for _ in range(steps):
        dl, dr = left / steps, right / steps
        ds, dth = (dl + dr) / 2, (dr - dl) / base
        pose = se2_compose(pose, (ds * math.cos(dth / 2), ds * math.sin(dth / 2), dth))
    return pose


@pytest.mark.parametrize(("left", "right"), [(0.2, 0.2), (0.15, 0.21), (-0.05, 0.05), (-0.18, -0.12), (0.0, 0.1)])
def test_a_corrected_increment_is_what_the_real_wheels_made(left: float, right: float) -> None:
    c = (0.012, -0.008, 0.025)  # left radius +1.2 %, right -0.8 %, base +2.5 %
    measured = _drive(left, right, BASE)  # what the nominal wheels integrate
    real = _drive(left * (1 + c[0]), right * (1 + c[1]), BASE * (1 + c[2]))
    got = odomcal.corrected(measured, c, BASE)
    assert abs(got.x() - real[0]) < 1e-6 and abs(got.y() - real[1]) < 1e-6
    assert abs(math.remainder(got.theta() - real[2], math.tau)) < 1e-6
    same = odomcal.corrected(measured, (0.0, 0.0, 0.0), BASE)  # no calibration: the increment as measured
    assert (same.x(), same.y(), same.theta()) == pytest.approx(measured, abs=1e-12)


def test_the_factor_s_jacobians_match_its_error() -> None:
    delta = _drive(0.16, 0.2, BASE)
    f = odomcal.factor(1, 2, 3, delta, np.diag([1e-4, 1e-4, 1e-4]), BASE)
    v = gtsam.Values()
    v.insert(1, gtsam.Pose2(0.3, -0.2, 0.4))
    v.insert(2, gtsam.Pose2(0.45, -0.1, 0.62))
    v.insert(3, np.array([0.01, -0.02, 0.03]))
    jac = f.linearize(v).jacobian()[0]  # whitened: 100 x the unwhitened Jacobian
    e0 = f.unwhitenedError(v)
    h = 1e-7
    for col, (key, i) in enumerate((k, i) for k in (1, 2, 3) for i in range(3)):
        w = gtsam.Values(v)
        step = np.zeros(3)
        step[i] = h
        if key == 3:
            w.update(3, v.atVector(3) + step)
        else:
            w.update(key, v.atPose2(key).retract(step))
        num = (f.unwhitenedError(w) - e0) / h
        assert np.allclose(jac[:, col] / 100.0, num, atol=2e-5), (key, i, jac[:, col] / 100.0, num)


def _loop_pose(t: float) -> Pose2:
    """A robot driving a 1.2 m circle around the origin robot at 0.2 m/s."""
    a = 0.2 * t / 1.2
    return (1.2 * math.cos(a), 1.2 * math.sin(a), a + math.pi / 2)


def _blackout_error(calibrate: bool) -> tuple[float, np.ndarray]:
    """Robot 1's wheels are off (left +1.5 %, right -1 %, base +2 %); robot 0 sees it every 0.5 s
    for 60 s, then not for 10 s.  Its fused position error at the end, and its calibration."""
    c = (0.015, -0.01, 0.02)
    p = FusionParams(odom_wheel_sigma=0.01, odom_scale_sigma=0.005 if calibrate else 0.02,
                     odom_calibration=calibrate)
    fusion = Fusion(p, 0, (0, 1))
    odom: Pose2 = (0.0, 0.0, 0.0)
    prev = _loop_pose(0.0)
    rng = np.random.default_rng(3)
    cov = np.diag([0.005**2, 0.005**2, 0.01**2])
    for k in range(701):
        t = k / 10
        stamp = round(t * 1e9)
        now = _loop_pose(t)
        real = se2_between(prev, now)  # what the wheels really did: the nominal odometry reads it back
        ds, dth = odomcal.arc_of(real)
        dl, dr = (ds - dth * BASE * (1 + c[2]) / 2) / (1 + c[0]), (ds + dth * BASE * (1 + c[2]) / 2) / (1 + c[1])
        m = odomcal.arc_pose((dl + dr) / 2, (dr - dl) / BASE)
        odom = se2_compose(odom, (m.x(), m.y(), m.theta()))
        prev = now
        fusion.add_odometry(0, stamp, (0.0, 0.0, 0.0), distance_m=0.0)
        fusion.add_odometry(1, stamp, odom, distance_m=0.2 * t)
        if k % 5 == 0 and t <= 60.0:
            z = se2_between((0.0, 0.0, 0.0), now)
            fusion.add_observation(0, 1, stamp, (z[0] + rng.normal(0, 0.005), z[1] + rng.normal(0, 0.005),
                                                 z[2] + rng.normal(0, 0.01)), cov)
        fusion.advance(stamp)
    est = fusion.pose(1)
    assert est is not None
    truth = _loop_pose(70.0)
    return math.hypot(est[0][0] - truth[0], est[0][1] - truth[1]), fusion.robots[1].cal


def test_a_calibrated_robot_drifts_less_out_of_view_and_its_calibration_is_found() -> None:
    plain, _ = _blackout_error(False)
    calibrated, cal = _blackout_error(True)
    # 10 s out of view on a tight circle: the plain odometry turns 2 % too little (the base) and
    # veers (the radii), 23 cm in all; the calibrated one stays within 1 cm
    assert plain > 0.1, plain
    assert calibrated < plain / 3, (calibrated, plain)
    # on a circle the radii's common share and the base trade off; their differences show
    assert cal[1] - cal[0] == pytest.approx(-0.025, abs=0.006), cal
