"""The views' shared range bias as a graph variable (server/rangebias.py): the factor against
GTSAM's own between-factor and numerical derivatives, a chain of observers whose views all
overestimate the range, and a bias learnt where two observers disagree."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest

from tagswarm.protocol.geometry import Pose2, se2_compose, se2_inverse
from tagswarm.server import rangebias

B_TRUE = 1.5e-4  # m^-2: the default camera's fit (+9.6 mm at 4 m)
KB = rangebias.key(1)


def _noise(sigma_m: float = 0.004, sigma_rad: float = 0.01) -> gtsam.noiseModel.Base:
    return gtsam.noiseModel.Diagonal.Sigmas(np.array([sigma_m, sigma_m, sigma_rad]))


def _biased(rel: Pose2, b: float) -> Pose2:
    """What a camera with bias coefficient ``b`` reports for the true view ``rel``: the range
    stretched by b r^3 along the line of sight."""
    x, y, th = rel
    r = math.hypot(x, y)
    k = 1.0 + b * r * r
    return (x * k, y * k, th)


def test_at_zero_bias_it_is_the_between_factor() -> None:
    rng = np.random.default_rng(3)
    for _ in range(20):
        xa, xb = gtsam.Pose2(*rng.normal(0, 2, 3)), gtsam.Pose2(*rng.normal(0, 2, 3))
        da, rel, db = (tuple(rng.normal(0, s, 3)) for s in (0.1, 2.0, 0.1))
        z = se2_compose(se2_compose(da, rel), se2_inverse(db))  # type: ignore[arg-type]
        plain = gtsam.BetweenFactorPose2(1, 2, gtsam.Pose2(*z), _noise())
        ours = rangebias.factor(1, 2, KB, da, rel, db, _noise())  # type: ignore[arg-type]
        v = gtsam.Values()
        v.insert(1, xa)
        v.insert(2, xb)
        v.insert(KB, rangebias.value(0.0))
        assert ours.error(v) == pytest.approx(plain.error(v), rel=1e-9, abs=1e-12)


def test_the_jacobians_match_numerical_derivatives() -> None:
    xa, xb = gtsam.Pose2(0.3, -0.2, 0.4), gtsam.Pose2(3.1, 1.2, -0.7)
    f = rangebias.factor(1, 2, KB, (0.05, 0.01, 0.02), (3.0, 1.1, -1.05), (0.02, -0.01, 0.03), _noise())
    v = gtsam.Values()
    v.insert(1, xa)
    v.insert(2, xb)
    v.insert(KB, rangebias.value(2e-4))
    lin = f.linearize(v)
    a, _ = lin.jacobian()
    for col, (k, dim) in enumerate([(1, 3), (2, 3), (KB, 1)]):
        for j in range(dim):
            step = np.zeros(dim)
            step[j] = 1e-6 if k != KB else 1e-8
            vp, vm = gtsam.Values(v), gtsam.Values(v)
            if k == KB:
                vp.update(k, rangebias.value(2e-4 + step[j]))
                vm.update(k, rangebias.value(2e-4 - step[j]))
            else:
                vp.update(k, v.atPose2(k).retract(step))
                vm.update(k, v.atPose2(k).retract(-step))
            num = (f.unwhitenedError(vp) - f.unwhitenedError(vm)) / (2 * step[j])
            # whitened columns of the linearised factor, back to unwhitened through the sigmas
            got = a[:, [0, 3, 6][col] + j] * np.array([0.004, 0.004, 0.01])
            assert got == pytest.approx(num, rel=1e-4, abs=1e-6), (k, j)


def _chain(with_bias: bool, views_per_link: int = 30) -> tuple[float, float]:
    """Four robots standing 4 m apart in a line, the first pinned; each sees the next ``views_per_link``
    times with independent 4 mm noise and the camera's shared range bias.  Returns the last robot's
    position error and its standard deviation along the line (m)."""
    rng = np.random.default_rng(7)
    truth = [(4.0 * i, 0.0, 0.0) for i in range(4)]
    g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
    g.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*truth[0]), _noise(1e-5, 1e-6)))
    if with_bias:
        g.add(rangebias.prior(KB, 0.0, B_TRUE))
        v.insert(KB, rangebias.value(0.0))
    for i in range(4):
        v.insert(i, gtsam.Pose2(*truth[i]))
    for i in range(3):
        rel = _biased((4.0, 0.0, 0.0), B_TRUE)
        for _ in range(views_per_link):
            z = (rel[0] + rng.normal(0, 0.004), rel[1] + rng.normal(0, 0.004), rng.normal(0, 0.01))
            if with_bias:
                g.add(rangebias.factor(i, i + 1, KB, (0.0, 0.0, 0.0), z, (0.0, 0.0, 0.0), _noise()))
            else:
                g.add(gtsam.BetweenFactorPose2(i, i + 1, gtsam.Pose2(*z), _noise()))
    est = gtsam.GaussNewtonOptimizer(g, v).optimize()
    sigma = math.sqrt(gtsam.Marginals(g, est).marginalCovariance(3)[0, 0])
    return est.atPose2(3).x() - truth[3][0], sigma


def test_a_chain_of_biased_views_is_overconfident_without_the_bias_and_honest_with_it() -> None:
    err, sigma = _chain(with_bias=False)
    assert err == pytest.approx(3 * B_TRUE * 4.0**3, abs=0.004)  # each link adds the same 9.6 mm
    assert (err / sigma) ** 2 > 30  # 30 views per link average the noise, not the bias: far outside its sigma
    err_b, sigma_b = _chain(with_bias=True)
    assert (err_b / sigma_b) ** 2 < 4  # the shared bias is part of the covariance
    assert abs(err_b) <= abs(err) + 1e-3


def test_two_observers_that_disagree_about_ranges_teach_the_graph_the_bias() -> None:
    # observers 0 and 1 known 5 m apart; robot 2 between them, 1.5 m from 0 and 3.5 m from 1: with the same
    # b, the near view says 2 is at 1.5 + 0.5 mm, the far one at 5 - 3.5 - 6.4 mm, so b explains both
    rng = np.random.default_rng(11)
    g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for k, x in ((0, 0.0), (1, 5.0)):
        g.add(gtsam.PriorFactorPose2(k, gtsam.Pose2(x, 0.0, 0.0 if k == 0 else math.pi), _noise(1e-5, 1e-6)))
        v.insert(k, gtsam.Pose2(x, 0.0, 0.0 if k == 0 else math.pi))
    v.insert(2, gtsam.Pose2(1.5, 0.0, 0.0))
    g.add(rangebias.prior(KB, 0.0, 5e-4))
    v.insert(KB, rangebias.value(0.0))
    for obs, rel in ((0, (1.5, 0.0, 0.0)), (1, (3.5, 0.0, math.pi))):
        for _ in range(200):
            b = _biased(rel, B_TRUE)
            z = (b[0] + rng.normal(0, 0.002), b[1] + rng.normal(0, 0.002), b[2] + rng.normal(0, 0.005))
            g.add(rangebias.factor(obs, 2, KB, (0.0, 0.0, 0.0), z, (0.0, 0.0, 0.0), _noise(0.002, 0.005)))
    est = gtsam.GaussNewtonOptimizer(g, v).optimize()
    assert float(est.atVector(KB)[0]) == pytest.approx(B_TRUE, rel=0.1)
    assert est.atPose2(2).x() == pytest.approx(1.5, abs=5e-4)
