"""The fusion's noise model as the scenario's [server] table sets it."""

from __future__ import annotations

import math

import numpy as np

from tagswarm.protocol.bus import BusConfig
from tagswarm.protocol.scenario import load_scenario
from tagswarm.server.config import ServerConfig
from tagswarm.server.node import make_fusion
from tagswarm.server.noise import FusionParams, floored_obs_cov, relative_cov, reported_cov, tangent_cov


def _config(*overrides: str) -> ServerConfig:
    return ServerConfig(scenario=load_scenario("paper", list(overrides)), bus=BusConfig(), run="t")


def test_unset_server_noise_follows_the_agents_odometry_model_without_calibration() -> None:
    p = make_fusion(_config("agent.odom_wheel_sigma=0.03", "server.odom_calibration=false")).p
    assert (p.odom_wheel_sigma, p.odom_scale_sigma, p.obs_sigma_floor_m) == (0.03, 0.02, 0.0)
    assert not p.odom_calibration


def test_with_the_calibration_unset_server_noise_is_the_wheels_own() -> None:
    p = make_fusion(_config("agent.odom_wheel_sigma=0.03")).p  # calibration on by default
    assert (p.odom_wheel_sigma, p.odom_scale_sigma, p.obs_sigma_floor_m, p.odom_calibration) == \
        (0.01, 0.01, 0.0, True)


def test_server_table_sets_the_fusions_noise_model() -> None:
    p = make_fusion(_config("agent.odom_wheel_sigma=0.03", "server.odom_wheel_sigma=0.01",
                            "server.odom_scale_sigma=0.005", "server.obs_sigma_floor_m=0.02")).p
    assert (p.odom_wheel_sigma, p.odom_scale_sigma, p.obs_sigma_floor_m) == (0.01, 0.005, 0.02)


def test_the_floor_adds_isotropic_position_variance_and_leaves_yaw() -> None:
    cov = np.diag([1e-4, 4e-4, 1e-3])
    cov[0, 1] = cov[1, 0] = 5e-5
    out = floored_obs_cov(cov, FusionParams(obs_sigma_floor_m=0.02))
    assert np.allclose(out - cov, np.diag([4e-4, 4e-4, 0.0]))
    assert np.array_equal(floored_obs_cov(cov, FusionParams()), cov)  # default: no floor
    # isotropic: the same added variance in the target's axes, whatever the relative yaw
    rel = (2.0, 0.5, math.radians(70))
    added = tangent_cov(rel, out) - tangent_cov(rel, cov)
    assert np.allclose(added, np.diag([4e-4, 4e-4, 0.0]))


def test_relative_cov_matches_sampled_relative_poses_and_levers_the_heading_by_the_range() -> None:
    import gtsam

    rng = np.random.default_rng(0)
    a, b = gtsam.Pose2(1.0, 2.0, 0.7), gtsam.Pose2(-3.0, 5.5, -2.4)
    cov_a, cov_b = np.diag([0.02**2, 0.03**2, 0.05**2]), np.diag([0.01**2, 0.04**2, 0.02**2])
    cov_a[0, 2] = cov_a[2, 0] = 0.5 * 0.02 * 0.05
    rel = a.between(b)
    eps = []
    for _ in range(20000):  # both poses perturbed in their own tangent spaces, as GTSAM's marginals are
        a2 = a.compose(gtsam.Pose2.Expmap(rng.multivariate_normal(np.zeros(3), cov_a)))
        b2 = b.compose(gtsam.Pose2.Expmap(rng.multivariate_normal(np.zeros(3), cov_b)))
        eps.append(gtsam.Pose2.Logmap(rel.between(a2.between(b2))))
    sampled = np.cov(np.array(eps).T)
    model = relative_cov((rel.x(), rel.y(), rel.theta()), cov_a, cov_b)
    assert np.allclose(model, sampled, rtol=0.08, atol=2e-5), (model, sampled)
    # the sideways spread of a far target is mostly the observer's heading: about range * sigma_yaw
    rng_m = math.hypot(rel.x(), rel.y())
    assert np.trace(model[:2, :2]) > 0.8 * (0.05 * rng_m) ** 2 > 10 * np.trace((cov_a + cov_b)[:2, :2])


def _pivoted(sigma_phi: float, r_m: float, n: int = 20000) -> tuple[np.ndarray, np.ndarray]:
    """Errors (n, 2) of a robot r_m ahead of a pivot whose heading error is N(0, sigma_phi^2), in the
    robot's axes (x towards the pivot's far side, y tangential), and the graph's linearised (3, 3)
    covariance of it (tangential sigma r * sigma_phi, 2 cm otherwise, the heading's sigma_phi)."""
    rng = np.random.default_rng(4)
    phi = rng.normal(0.0, sigma_phi, n)
    err = np.column_stack([r_m * (np.cos(phi) - 1.0) + rng.normal(0, 0.02, n),
                           r_m * np.sin(phi) + rng.normal(0, 0.02, n)])
    cov = np.diag([0.02**2, (r_m * sigma_phi) ** 2 + 0.02**2, sigma_phi**2])
    return err, cov


def _nees(err: np.ndarray, cov: np.ndarray) -> float:
    p = np.linalg.inv(cov[:2, :2])
    return float(np.mean(np.einsum("ni,ij,nj->n", err, p, err)) / 2.0)


def test_the_reported_covariance_holds_a_loose_headings_arc_and_leaves_a_firm_one_alone() -> None:
    """A robot 5 m from a pivot whose heading is 17 deg unsure lies on an arc: the linearised
    covariance calls its errors ~20x too unlikely (the arc's bow towards the pivot, across a 2 cm
    axis); the reported one is consistent (NEES ~1).  At 1 deg the two are the same to 1 %."""
    err, cov = _pivoted(math.radians(17.0), 5.0)
    assert _nees(err, cov) > 10.0
    rep = reported_cov(cov)
    assert 0.6 < _nees(err, rep) < 1.4
    assert rep[1, 1] == cov[1, 1] and rep[2, 2] == cov[2, 2]  # the arc's tangent and the heading as they were
    firm_err, firm = _pivoted(math.radians(1.0), 5.0)
    assert np.allclose(reported_cov(firm), firm, rtol=1e-2, atol=0.0)
    assert 0.8 < _nees(firm_err, reported_cov(firm)) < 1.2
    # a rotated frame gets the same term along its own minor axis
    c, s = math.cos(0.7), math.sin(0.7)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    assert np.allclose(reported_cov(rot @ cov @ rot.T), rot @ rep @ rot.T, atol=1e-12)
    assert np.array_equal(reported_cov(np.zeros((3, 3))), np.zeros((3, 3)))


def test_the_reported_covariance_of_a_round_or_broken_ellipse() -> None:
    """A round position ellipse gets the term on both axes (no direction to prefer, and a rounding's
    difference must not swing it); a non-finite covariance is passed on as it is."""
    round_cov = np.diag([0.04, 0.04, 0.09])
    nudged = np.diag([0.04, 0.04 + 1e-12, 0.09])
    assert np.allclose(reported_cov(round_cov), reported_cov(nudged), atol=1e-9)
    assert np.allclose(reported_cov(round_cov)[:2, :2], np.diag([0.04 + 0.0027, 0.04 + 0.0027]))
    bad = np.diag([0.04, 0.01, math.nan])
    assert np.array_equal(reported_cov(bad), bad, equal_nan=True)
