"""The corner noise the agent builds its covariances on (agents/lens.py ``corner_sigma_px``):
the render's own for the ideal camera, wider with the configured image noise and motion blur."""

from __future__ import annotations

import math

from tagswarm.agents.cubepose import CubePoseEstimator
from tagswarm.agents.lens import CORNER_PX_PER_STREAK_PX, corner_sigma_px
from tagswarm.protocol.scenario import load_scenario


def _sigma(*overrides: str) -> float:
    return corner_sigma_px(load_scenario("paper", list(overrides)), 0.3)


def test_the_ideal_camera_keeps_the_render_noise() -> None:
    assert _sigma() == 0.3
    assert CubePoseEstimator(load_scenario("paper")).pixel_sigma_px == 0.3


def test_noise_and_blur_widen_the_corner_noise() -> None:
    realistic = _sigma("camera.preset=realistic")
    assert 0.3 < realistic < 0.35  # 4 ms at 1.2 rad/s: a ~1.5 px streak; ~3 DN of noise
    assert _sigma("camera.preset=realistic", "camera.read_noise_dn=20.0") > realistic
    assert _sigma("camera.preset=realistic", "camera.contrast=0.3") > realistic  # the same noise on fainter edges
    blurred = _sigma("camera.preset=realistic", "camera.exposure_ms=20.0", "camera.read_noise_dn=0.0",
                     "camera.electrons_per_dn=0.0")
    streak = 0.020 * 1.2 * 160.0 / math.radians(30.0)  # the 320 px, 60 deg camera at its fastest turn
    assert math.isclose(blurred, math.hypot(0.3, CORNER_PX_PER_STREAK_PX * streak))
    s = load_scenario("paper", ["camera.preset=realistic", "camera.exposure_ms=20.0"])
    assert math.isclose(CubePoseEstimator(s).pixel_sigma_px, corner_sigma_px(s, 0.3))
