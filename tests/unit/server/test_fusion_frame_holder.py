"""The robot holding the map frame (the origin, no landmarks) standing still is held to the
encoders' resolution: its keyframes do not random-walk by the numerical floor, which let
the whole map turn with it over long runs (paper scenario, 300 s: 0.17 deg)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tagswarm.protocol.geometry import Pose2, se2_between
from tagswarm.server.fusion import Fusion, FusionParams
from tagswarm.server.noise import still_increment_cov

COV = np.diag([0.01**2, 0.01**2, 0.05**2])
UNHELD = FusionParams(still_m=0.0)  # no increment is "still": the floor's random walk, as before


def _origin_alone(p: FusionParams, seconds: float, landmarks: dict[int, Pose2] | None = None,
                  turn_rad_s: float = 0.0) -> tuple[Pose2, np.ndarray]:
    """Robot 0 stands (or turns on the spot) for ``seconds``; robot 1 never shows up."""
    f = Fusion(p, 0, (0, 1), landmarks)
    for k in range(int(seconds * 30)):
        ns = round(k * 1e9 / 30)
        f.add_odometry(0, ns, (0.0, 0.0, math.remainder(turn_rad_s * k / 30, math.tau)), 0.0)
        f.advance(ns)
    est = f.pose(0)
    assert est is not None
    return est[0], est[1]


def test_the_standing_origin_keeps_its_anchors_sigma_over_minutes() -> None:
    _, held = _origin_alone(FusionParams(), 120.0)
    _, floor = _origin_alone(UNHELD, 120.0)
    # the anchor's 1e-4 (m, rad) plus 60 keyframes of 1e-5; the floor's walk is 1 mm / 1 mrad per keyframe
    assert np.all(np.sqrt(np.diag(held)) < 2e-4), np.sqrt(np.diag(held))
    assert np.all(np.sqrt(np.diag(floor)) > 5e-3), np.sqrt(np.diag(floor))


def test_a_turning_origin_or_one_pinned_by_landmarks_is_not_held() -> None:
    _, turning = _origin_alone(FusionParams(), 60.0, turn_rad_s=0.3)
    assert math.sqrt(turning[2, 2]) > 1e-3, np.sqrt(np.diag(turning))
    far = {7: (3.0, 0.0, math.pi)}  # a landmark it never sees: the map is pinned by landmarks, not by robot 0
    assert Fusion(FusionParams(), 0, (0, 1), far).graph.frame_holder is None
    assert Fusion(FusionParams(), 0, (0, 1)).graph.frame_holder == 0


def test_still_means_under_a_millimetre_and_no_slip() -> None:
    p = FusionParams()
    assert still_increment_cov((2e-4, -1e-4, 5e-4), p) == pytest.approx(np.eye(3) * 1e-10)
    assert still_increment_cov((2e-3, 0.0, 0.0), p) is None
    assert still_increment_cov((0.0, 0.0, 0.01), p) is None
    assert still_increment_cov((0.0, 0.0, 0.0), p, slip_m=0.01) is None  # pushed: the agent saw its wheels slip


def _biased_run(p: FusionParams, seconds: float = 120.0, bias: float = 0.02) -> Pose2:
    """The origin stands; robot 1 drives a 1 m circle around (2, 0) at 0.2 m/s.  The origin's
    views of it are turned by ``bias`` rad (a systematic error of its camera), robot 1's of the
    origin are not: the inconsistency has to go somewhere, and the floor let it go into the
    origin's heading, keyframe by keyframe."""
    f = Fusion(p, 0, (0, 1))
    rng = np.random.default_rng(1)
    c, s = math.cos(bias), math.sin(bias)
    for k in range(int(seconds * 30)):
        t = k / 30
        ns = round(t * 1e9)
        a = 0.2 * t
        p1 = (2 + math.cos(a), math.sin(a), a + math.pi / 2)
        f.add_odometry(0, ns, (0.0, 0.0, 0.0), 0.0)
        f.add_odometry(1, ns, (math.sin(a), 1 - math.cos(a), a), 0.2 * t)
        if k % 9 == 0:
            r01 = se2_between((0.0, 0.0, 0.0), p1)
            r10 = se2_between(p1, (0.0, 0.0, 0.0))
            f.add_observation(0, 1, ns, (c * r01[0] - s * r01[1], s * r01[0] + c * r01[1], r01[2] + bias), COV)
            f.add_observation(1, 0, ns, tuple(float(v) for v in np.asarray(r10) + rng.normal(0, 0.003, 3)), COV)
        f.advance(ns)
    est = f.pose(0)
    assert est is not None
    return est[0]


def test_biased_views_do_not_turn_the_standing_origin() -> None:
    held, floor = _biased_run(FusionParams()), _biased_run(UNHELD)
    assert abs(held[2]) < 5e-6 and math.hypot(held[0], held[1]) < 1e-5, held
    assert abs(floor[2]) > 3e-5, floor  # what the hold takes away: the origin drifted with its views
