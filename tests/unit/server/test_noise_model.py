"""The fusion's noise model as the scenario's [server] table sets it."""

from __future__ import annotations

import math

import numpy as np

from tagswarm.protocol.bus import BusConfig
from tagswarm.protocol.scenario import load_scenario
from tagswarm.server.config import ServerConfig
from tagswarm.server.node import make_fusion
from tagswarm.server.noise import FusionParams, floored_obs_cov, tangent_cov


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
