"""The fused covariance against what the graph really knows: a robot standing still keeps
its keyframe instead of growing a chain of zero-motion odometry factors, and the
factors one pair adds within ``obs_pair_window_s`` are weighed as the correlated
measurements they are."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tagswarm.server.fusion import Fusion, FusionParams
from tagswarm.server.noise import pair_inflation

COV = np.diag([1e-4, 1e-4, 1e-4])
STEP_NS = 10**8


def _sigma(fusion: Fusion, rid: int) -> float:
    est = fusion.pose(rid)
    assert est is not None
    return math.sqrt(float(est[1][0, 0] + est[1][1, 1]) / 2)


def test_pair_inflation_is_the_power_of_the_factor_count() -> None:
    p = FusionParams(obs_pair_window_s=10.0, obs_pair_power=0.5)
    assert pair_inflation(0, p) == 1.0
    assert pair_inflation(3, p) == pytest.approx(2.0)
    assert pair_inflation(8, p) == pytest.approx(3.0)
    assert pair_inflation(8, FusionParams(obs_pair_window_s=0.0)) == 1.0


def test_a_standing_robot_keeps_one_keyframe_alive_past_the_lag_and_its_sigma_stays() -> None:
    fusion = Fusion(FusionParams(lag_s=10.0), 0, (0, 1))
    sigmas = {}
    for k in range(600):  # 60 s, six times the lag
        t = k * STEP_NS
        fusion.add_odometry(0, t, (0.0, 0.0, 0.0), 0.0)
        fusion.add_odometry(1, t, (0.0, 0.0, 0.0), 0.0)
        if 5 <= k <= 8:  # the origin sees robot 1 at 1.5 m, then never again
            fusion.add_observation(0, 1, t, (1.5, 0.0, math.pi), COV)
        fusion.advance(t)
        if k in (50, 599):
            sigmas[k] = _sigma(fusion, 1)
    # still estimated after six lags with nothing new: its keyframe was kept, not marginalised away
    assert fusion.pose(1) is not None
    assert math.dist(fusion.pose(1)[0][:2], (1.5, 0.0)) < 1e-6  # type: ignore[index]
    # one keyframe per robot (and per placement), not one every kf_max_interval_s
    assert fusion.counters["keyframes"] <= 3, fusion.counters
    # a zero-motion keyframe every 2 s added 1 mm of sigma each: 1.01 -> 1.14 cm over these 55 s
    assert sigmas[599] == pytest.approx(sigmas[50], rel=0.01), sigmas


def _watch_a_driving_robot(params: FusionParams, seconds: float = 9.0) -> float:
    """The standing origin watches robot 1 drive away along x at 0.1 m/s and sees it every
    0.3 s; robot 1's sigma (m) at the end."""
    fusion = Fusion(params, 0, (0, 1))
    for k in range(int(seconds * 10)):
        t = k * STEP_NS
        x = 0.01 * k
        fusion.add_odometry(0, t, (0.0, 0.0, 0.0), 0.0)
        fusion.add_odometry(1, t, (x, 0.0, 0.0), x)
        if k % 3 == 0:
            fusion.add_observation(0, 1, t, (1.0 + x, 0.0, 0.0), COV)
        fusion.advance(t)
    return _sigma(fusion, 1)


def test_a_pairs_factors_within_the_window_count_as_correlated() -> None:
    independent = _watch_a_driving_robot(FusionParams(obs_pair_window_s=0.0))
    correlated = _watch_a_driving_robot(FusionParams(obs_pair_window_s=10.0, obs_pair_power=0.5))
    one_view = math.sqrt(1e-4)
    # thirty views of one pair are worth less than thirty independent ones, more than one
    assert correlated > 1.2 * independent, (independent, correlated)  # measured 0.74 against 0.56 cm
    assert correlated < one_view, correlated
