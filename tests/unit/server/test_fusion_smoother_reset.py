"""A smoother update that iSAM2 refuses does not stop the fusion (no network)."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest

from tagswarm.server import checkpoint
from tagswarm.server.fusion import Fusion, FusionParams
from tagswarm.server.keyframes import robot_key
from tests.synthetic import SyntheticSwarm


def _feed(fusion: Fusion, sw: SyntheticSwarm, t0: float, t1: float) -> None:
    dt = 1.0 / sw.rate_hz
    for k in range(round(t0 * sw.rate_hz), round(t1 * sw.rate_hz)):
        t = k * dt
        stamp = round(t * 1e9)
        odom, obs = sw.step(t)
        for rid, pose in enumerate(odom):
            fusion.add_odometry(rid, stamp, pose, distance_m=0.2 * t * rid)
        if k % 5 == 0:
            for i, j, z, cov, _ in obs:
                fusion.add_observation(i, j, stamp, z, cov)
        fusion.advance(stamp)


def _errors(fusion: Fusion, sw: SyntheticSwarm, t: float) -> list[float]:
    out = []
    for rid in range(sw.n):
        est = fusion.pose(rid)
        assert est is not None, rid
        truth = sw.truth(rid, t)
        out.append(math.hypot(est[0][0] - truth[0], est[0][1] - truth[1]))
    return out


def _poison(fusion: Fusion) -> None:
    """Stage what makes iSAM2 throw an indeterminate linear system: a new variable tied to
    robot 1's keyframe by a factor certain along x and blind in y and yaw."""
    kf = fusion.robots[1].kf_key
    assert kf is not None
    bad = robot_key(1, 99, 0)
    fusion.graph.values.insert(bad, gtsam.Pose2(0.0, 0.0, 0.0))
    fusion.graph.stamps[bad] = fusion.watermark_ns / 1e9
    fusion.graph.add(gtsam.BetweenFactorPose2(kf, bad, gtsam.Pose2(1.0, 0.0, 0.0),
                                              gtsam.noiseModel.Diagonal.Sigmas(np.array([1e-9, 1e9, 1e9]))))


@pytest.mark.parametrize(("calibrated", "bias_sigma"), [(False, 0.0), (True, 0.0), (False, 1.5e-4)],
                         ids=["plain", "calibrated", "range_bias"])
def test_a_refused_update_restarts_the_smoother_from_the_estimates(calibrated: bool, bias_sigma: float) -> None:
    sw = SyntheticSwarm(n=3, seed=3, outlier_rate=0.0)
    params = FusionParams(odom_scale_sigma=0.05, odom_calibration=calibrated, range_bias_sigma=bias_sigma)
    fusion = Fusion(params, 0, tuple(range(sw.n)))
    _feed(fusion, sw, 0.0, 20.0)
    before = {rid: fusion.pose(rid) for rid in range(sw.n)}
    bias_before = (fusion.graph.bias_gen, fusion.graph.bias, fusion.graph.bias_var)
    _poison(fusion)
    fusion.advance(fusion.watermark_ns)  # would raise RuntimeError out of iSAM2 without the reset
    assert fusion.counters["smoother_resets"] == 1
    assert fusion.graph.bias_key is None  # the old variable went with the old smoother
    assert fusion.counters["smoother_rebuild_failures"] == 0
    for rid, (pose, cov) in ((r, p) for r, p in before.items() if p is not None):
        after = fusion.pose(rid)
        assert after is not None
        assert math.hypot(after[0][0] - pose[0], after[0][1] - pose[1]) < 1e-3, rid
        # the restart carries each robot's uncertainty, it does not make it certain
        assert np.trace(after[1][:2, :2]) >= 0.5 * np.trace(cov[:2, :2]), rid
    # fusion goes on: odometry chains continue and new observations still correct the robots
    _feed(fusion, sw, 20.0, 60.0)
    assert fusion.counters["smoother_resets"] == 1
    assert max(_errors(fusion, sw, 59.9)) < 0.05
    if bias_sigma > 0:
        # a new bias variable of the next generation, started from what the old one had learnt (its prior
        # the old marginal), in the smoother and estimated; without far views it would not exist at all
        assert bias_before[0] >= 1 and bias_before[2] is not None
        assert fusion.graph.bias_gen == bias_before[0] + 1
        assert fusion.graph.bias_key is not None and fusion.graph.bias_key in fusion.graph.smoother
        assert abs(fusion.graph.bias) < 1e-3  # the swarm's views are unbiased: it stays near 0 (m^-2)
        assert fusion.graph.bias_var is not None and fusion.graph.bias_var <= bias_before[2] * 1.01
    # and the state after a reset checkpoints and restores like any other
    blob = checkpoint.snapshot(fusion)
    other = Fusion(params, 0, tuple(range(sw.n)))
    checkpoint.restore(other, blob)
    for rid in range(sw.n):
        a, b = fusion.pose(rid), other.pose(rid)
        assert a is not None and b is not None
        assert np.allclose(a[0], b[0], atol=1e-3)
