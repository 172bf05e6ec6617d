"""The fusion's noise model as the scenario's [server] table sets it."""

from __future__ import annotations

import math

import numpy as np

from tagswarm.protocol.bus import BusConfig
from tagswarm.protocol.scenario import load_scenario
from tagswarm.server.config import ServerConfig
from tagswarm.server.node import make_fusion
from tagswarm.server.noise import FusionParams, floored_obs_cov, relative_cov, tangent_cov


def _config(*overrides: str) -> ServerConfig:
    return ServerConfig(scenario=load_scenario("paper", list(overrides)), bus=BusConfig(), run="t")


def test_unset_server_noise_follows_the_agents_odometry_model() -> None:
    p = make_fusion(_config("agent.odom_wheel_sigma=0.03")).p
    assert (p.odom_wheel_sigma, p.odom_scale_sigma, p.obs_sigma_floor_m) == (0.03, 0.02, 0.0)


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
