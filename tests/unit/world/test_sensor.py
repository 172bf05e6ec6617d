"""Sensor effects: noise statistics match the configuration, motion blur grows with speed,
a seed gives the same images, and the ideal preset renders exactly what it did before."""

from __future__ import annotations

import hashlib
import math

import numpy as np
import pytest

from tagswarm.protocol.geometry import se2_matrix
from tagswarm.protocol.scenario import CameraSensor, load_scenario
from tagswarm.world.render import Renderer, image_message
from tagswarm.world.sensor import NoiseBank, develop, frame_key, vignetting_gain

#: sha256 of the frame below, rendered by the code before lenses existed (commit 0c8436c)
IDEAL_SHA256 = "50cd5db4606262aa6eb5e1ead9cf1ed970e299cee13617f5fdbf6111a42eab20"


def _frame(overrides: list[str], *, steps: int = 1, turn_rad_s: float = 0.0, seed_step: int = 0) -> list[bytes]:
    """Frames of robot 0's camera in the paper scene, its base turning at ``turn_rad_s``."""
    s = load_scenario("paper", overrides)
    out = []
    with Renderer(s) as r:
        for rid in s.robot_ids:
            r.set_pose(rid, (0.6 * rid, 0.3 * rid, 0.0), (0, 0, 0, 1))
        cam = s.robot.cameras[0]
        for k in range(steps):
            stamp = k * 33_333_333
            img = r.render(0, cam, se2_matrix(-1.0, 0.1, 0.2 + turn_rad_s * stamp * 1e-9))
            out.append(image_message(s, 0, cam, img, seq=k, step=seed_step + k, stamp_ns=stamp).data)
    return out


def test_ideal_preset_is_byte_identical_to_before() -> None:
    (data,) = _frame([])
    assert hashlib.sha256(data).hexdigest() == IDEAL_SHA256
    (explicit,) = _frame(["camera.preset=ideal"])
    assert explicit == data


@pytest.mark.parametrize(("level", "read", "e_per_dn"), [(100.0, 1.5, 20.0), (200.0, 0.0, 10.0), (60.0, 3.0, 0.0)])
def test_flat_patch_noise_matches_config(level: float, read: float, e_per_dn: float) -> None:
    cfg = CameraSensor(read_noise_dn=read, electrons_per_dn=e_per_dn).resolved()
    patch = np.full((200, 200), level, np.float32)
    bank = NoiseBank(3, "front", patch.size)
    out = develop(patch, cfg, bank=bank, key=frame_key(3, 1, "front", 7)).astype(np.float64)
    want = math.sqrt((level / e_per_dn if e_per_dn else 0.0) + read**2)
    assert abs(out.mean() - level) < 0.1
    assert abs(out.std() - want) / want < 0.05, (out.std(), want)


def test_contrast_brightness_and_vignetting() -> None:
    cfg = CameraSensor(contrast=0.5, brightness_dn=10.0, vignetting=0.4).resolved()
    k = np.array([[100.0, 0, 49.5], [0, 100.0, 39.5], [0, 0, 1]])
    gain = vignetting_gain(100, 80, k, 0.4)
    out = develop(np.full((80, 100), 200.0, np.float32), cfg, gain).astype(float)
    assert out[40, 50] == pytest.approx((200 * gain[40, 50] - 128) * 0.5 + 138, abs=0.51)
    assert out[0, 0] == pytest.approx((200 * 0.6 - 128) * 0.5 + 138, abs=0.51)


def test_rendered_blur_grows_with_turn_rate() -> None:
    """Through the renderer: the robot's own turn between frames blurs the next frame."""
    sharp = []
    for rate in (0.0, 1.0, 3.0):
        _, second = _frame(["camera.preset=realistic", "camera.read_noise_dn=0", "camera.electrons_per_dn=0",
                            "camera.exposure_ms=20"], steps=2, turn_rad_s=rate)
        img = np.frombuffer(second, np.uint8).reshape(240, 320).astype(float)
        sharp.append(float(np.abs(np.diff(img, axis=1)).mean()))
    assert sharp[0] > sharp[1] > sharp[2], sharp


def test_seed_gives_identical_images() -> None:
    ov = ["camera.preset=realistic", "seed=5"]
    a = _frame(ov, steps=3, turn_rad_s=0.5)
    b = _frame(ov, steps=3, turn_rad_s=0.5)
    assert a == b
    assert _frame(["camera.preset=realistic", "seed=6"], steps=3, turn_rad_s=0.5) != a
    assert a[1] != a[2]  # a new tick draws new noise
    # the noise depends on the tick, not on what else was drawn before
    c = _frame(ov, steps=1, seed_step=2)
    d = _frame(ov, steps=1, seed_step=2)
    assert c == d


def test_noise_bank_statistics() -> None:
    """The bank's frames: N(0, 1) per pixel, uncorrelated neighbours, new noise every tick."""
    bank = NoiseBank(1, "front", 320 * 240)
    a = bank.draw(frame_key(1, 0, "front", 10), (240, 320))
    b = bank.draw(frame_key(1, 0, "front", 11), (240, 320))
    assert abs(float(a.mean())) < 0.02 and abs(float(a.std()) - 1.0) < 0.02
    assert abs(float(np.corrcoef(a[:, 1:].ravel(), a[:, :-1].ravel())[0, 1])) < 0.02
    assert abs(float(np.corrcoef(a.ravel(), b.ravel())[0, 1])) < 0.02
    cfg = CameraSensor(read_noise_dn=1.5, electrons_per_dn=20.0).resolved()
    out = develop(np.full((240, 320), 100.0, np.float32), cfg, bank=bank, key=frame_key(1, 0, "front", 3))
    assert abs(float(out.std()) - math.sqrt(100 / 20 + 1.5**2)) < 0.1


def test_frame_key_spreads_the_noise_offsets() -> None:
    """Frame keys place frames uniformly over the bank and differ by seed, robot, camera and tick, so
    two frames never share their noise but by chance."""
    bank_len, n = 320 * 240 * 8, 320 * 240
    offsets = np.array([frame_key(0, 3, "front", k) * (bank_len - n + 1) >> 64 for k in range(4000)])
    counts = np.bincount(offsets * 10 // (bank_len - n + 1), minlength=10)
    assert counts.min() > 340 and counts.max() < 460  # uniform: 400 per tenth (chi-square p > 1e-4)
    keys = {frame_key(s, r, c, k) for s in (0, 1) for r in (0, 1, 2) for c in ("front", "left") for k in range(50)}
    assert len(keys) == 2 * 3 * 2 * 50
    assert frame_key(5, 1, "front", 7) == frame_key(5, 1, "front", 7)
    assert all(0 <= frame_key(s, 0, "f", 0) < 2**64 for s in (0, 2**63, 2**64 - 1))
