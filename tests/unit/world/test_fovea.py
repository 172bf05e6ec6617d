"""A wide lens's centre keeps its own resolution: a 120 deg fisheye is rendered as a wide pinhole
at a smaller focal length plus a *fovea*, a narrow pinhole at the lens's focal length for the
centre (world/lens.py).  One capped pinhole render sampled a 320x240 fisheye's centre at 0.58 px
per output px, and a 16 cm tag straight ahead decoded to 1.0 m only (0 of 12 frames at 1.5 m)."""

from __future__ import annotations

import math

import numpy as np
import pybullet as pb
import pytest

from tagswarm.agents.detect import make_detector
from tagswarm.protocol.geometry import se2_matrix
from tagswarm.protocol.scenario import load_scenario
from tagswarm.world import blur
from tagswarm.world import lens as lens_mod
from tagswarm.world.render import Renderer, image_message

FISHEYE = 'robot.cameras=[{name="front", width=320, height=240, hfov_deg=120, z_m=0.6, pitch_deg=-15.0}]'
BASE = ["robots.count=2", 'robots.placement="explicit"', "robots.start=[{x_m=0.0, y_m=0.0}, {x_m=2.0, y_m=0.0}]",
        "camera.preset=realistic"]


def _scenario(*extra: str):
    return load_scenario("paper", [*BASE, FISHEYE, *extra])


def test_a_wide_fisheye_has_a_fovea_at_its_focal_length_and_samples_enough_elsewhere() -> None:
    s = _scenario()
    p = lens_mod.plan(s.robot.cameras[0], s.camera.preset)
    fv = p.fovea
    assert fv is not None and fv.K_render[0, 0] == pytest.approx(p.lens.K[0, 0])
    w, h = p.lens.width, p.lens.height
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    xy = lens_mod.undistort(np.stack([u.ravel(), v.ravel()], 1), p.lens.model, p.lens.K, p.lens.D).reshape(h, w, 2)
    served = np.zeros((h, w), bool)
    served[fv.rows, fv.cols] = fv.mask
    wide = p.K_render[0, 0] * lens_mod.sparsest_sampling(xy)
    assert wide[~served].min() >= lens_mod.MIN_SAMPLING - 1e-6
    assert wide[h // 2, w // 2] < 0.6  # the wide render alone would undersample the centre
    # the fovea's samples fall inside its render, and the two cost less than one render at full focal
    assert fv.float_maps[0][fv.mask].min() >= 0 and fv.float_maps[0][fv.mask].max() <= fv.render_cam.width - 1
    total = p.render_cam.width * p.render_cam.height + fv.render_cam.width * fv.render_cam.height
    assert total < 0.5 * 11.8 * w * h
    # a lens a single render at full focal covers cheaply has none
    bc = load_scenario("paper", ["camera.preset=realistic"])
    assert lens_mod.plan(bc.robot.cameras[0], bc.camera.preset).fovea is None


def _frames(s, poses: list[tuple[float, float, float]], target: tuple[float, float, float],
            steps: list[int]) -> list[np.ndarray]:
    """Developed frames of robot 0 at ``poses`` (x, y, yaw) with robot 1 at ``target``."""
    out = []
    cam = s.robot.cameras[0]
    with Renderer(s) as r:
        r.set_pose(1, (target[0], target[1], 0), pb.getQuaternionFromEuler((0, 0, target[2])))
        for (x, y, yaw), k in zip(poses, steps, strict=True):
            r.set_pose(0, (x, y, 0), pb.getQuaternionFromEuler((0, 0, yaw)))
            msg = image_message(s, 0, cam, r.render(0, cam, se2_matrix(x, y, yaw)), seq=k, step=k,
                                stamp_ns=k * 33_333_333)
            out.append(np.frombuffer(msg.data, np.uint8).reshape(msg.height, msg.width).astype(np.float32))
    return out


def test_the_fovea_image_is_the_full_resolution_one(monkeypatch: pytest.MonkeyPatch) -> None:
    """With the noise off, the composed image equals a single render at the lens's focal length
    (12x the pixels) within a DN on average; the wide render alone is far from it at the centre."""
    s = _scenario("camera.read_noise_dn=0", "camera.electrons_per_dn=0", "camera.exposure_ms=0")
    target = (1.2, 0.1, math.pi + 0.3)
    new = _frames(s, [(0, 0, 0)], target, [1])[0]
    monkeypatch.setattr(lens_mod, "SINGLE_RENDER_RATIO", 100.0)
    full = _frames(s, [(0, 0, 0)], target, [1])[0]
    monkeypatch.setattr(lens_mod, "SINGLE_RENDER_RATIO", 4.0)
    # one render at the size the old cap (4x the image's pixels) gave: 0.58 of the focal length
    monkeypatch.setattr(lens_mod, "_choose_renders", lambda xy, f, extent, npx: (0.58 * f, 0.0))
    wide = _frames(s, [(0, 0, 0)], target, [1])[0]
    c = (slice(60, 180), slice(100, 220))
    # the fovea samples the very rays (same focal length and pixel grid) a full render does
    assert float(np.abs(new - full)[c].mean()) < 0.1 < 2.0 < float(np.abs(wide - full)[c].mean())
    assert float(np.abs(new - full).mean()) < 0.5


def test_a_blur_across_a_depth_edge_in_the_fovea_resamples_the_fovea(monkeypatch: pytest.MonkeyPatch) -> None:
    """Sliding sideways at 2 m/s past a cube 0.8 m ahead (20 ms exposure): the cube's edges blur by
    sub-exposures, which in the centre sample the fovea, so the frame equals the blur of a single
    full-resolution render there; without that step it would come from the coarse wide render."""
    s = _scenario("camera.read_noise_dn=0", "camera.electrons_per_dn=0", "camera.exposure_ms=20")
    poses, target = [(0.0, 0.0, 0.0), (0.0, 0.066, 0.0)], (0.8, 0.05, math.pi + 0.3)
    new = _frames(s, poses, target, [0, 1])[1]
    monkeypatch.setattr(lens_mod, "SINGLE_RENDER_RATIO", 100.0)
    full = _frames(s, poses, target, [0, 1])[1]
    monkeypatch.setattr(lens_mod, "SINGLE_RENDER_RATIO", 4.0)
    monkeypatch.setattr(Renderer, "_blur_fovea", staticmethod(lambda fv, maps, img, *rest: img))
    coarse = _frames(s, poses, target, [0, 1])[1]
    sharp = _frames(s, poses[1:], target, [1])[0]
    c = (slice(60, 180), slice(100, 220))
    assert float(np.abs(sharp - full)[c].mean()) > 3.0  # a blur
    assert float(np.abs(new - full)[c].mean()) < 0.3 * float(np.abs(coarse - full)[c].mean())


def test_a_cube_ahead_decodes_at_one_and_a_half_metres() -> None:
    """The case that placed nobody in a user's 120 deg yard: a cube 1.5 m straight ahead."""
    s = _scenario("camera.exposure_ms=0")
    det = make_detector(s.tags.family)
    hits = 0
    for k, dyaw in enumerate((-0.4, -0.15, 0.15, 0.4)):
        img = _frames(s, [(0, 0, 0)], (1.5, 0.0, math.pi + dyaw), [k])[0]
        hits += any(11 <= d.tag_id <= 16 for d in det.detect(img.astype(np.uint8)))
    assert hits >= 3


@pytest.mark.parametrize(("slide_m", "turn_rad"), [(0.033, 0.0), (0.0, 0.04), (0.0, 0.0033)])
def test_the_fovea_blurs_with_as_many_sub_exposures_as_the_wide_render(slide_m: float, turn_rad: float) -> None:
    """The fovea's maps (its box's corners lie outside its render) measure the same streak as the wide
    render's: as many sub-exposures, and none for a streak under a pixel (a slow turn)."""
    s = _scenario("camera.exposure_ms=20")
    cam = s.robot.cameras[0]
    with Renderer(s) as r:
        r.set_pose(1, (0.8, 0.05, 0), pb.getQuaternionFromEuler((0, 0, math.pi + 0.3)))
        p = r.plan(cam)
        assert p.fovea is not None
        mount = r._mount[cam.name]
        prev, now = se2_matrix(0, 0, 0) @ mount, se2_matrix(0, slide_m, turn_rad) @ mount
        _, zbuf = r._shoot(p.render_cam, now, True)
        _, zbuf_f = r._shoot(p.fovea.render_cam, now, True, count=False)
    twist = blur.camera_twist(prev, now, 1 / 30)
    wide = blur.exposure_maps(*p.sample_maps(), zbuf, p.K_render, twist, 0.02, near_far=(cam.near_m, cam.far_m),
                              resample=True)
    fovea = blur.exposure_maps(*p.fovea.float_maps, zbuf_f, p.fovea.K_render, twist, 0.02,
                               near_far=(cam.near_m, cam.far_m), resample=True)
    if turn_rad == 0.0033:
        assert wide is None and fovea is None
    else:
        assert wide is not None and fovea is not None
        assert 2 <= len(fovea) <= len(wide) < blur.MAX_BLUR_SAMPLES


@pytest.mark.parametrize("case", range(12))
def test_any_valid_wide_lens_gets_a_plan_that_keeps_its_promise(case: int) -> None:
    """Random fisheyes the scenario accepts (90-128 deg, 4:3, 16:9 or square, small k1..k4): the maps are
    finite and inside their renders, every output pixel is sampled at >= MIN_SAMPLING by the render it
    comes from, and the renders stay within the pixel budget."""
    rng = np.random.default_rng(case)
    w = int(rng.choice([160, 320, 480, 640]))
    h = int(w * rng.choice([0.75, 0.5625, 1.0])) // 2 * 2
    hfov = float(rng.uniform(90.0, 128.0) if h / w < 1 else rng.uniform(90.0, 110.0))
    coeffs = [float(rng.uniform(-0.03, 0.03)), float(rng.uniform(-0.005, 0.005)), 0.0, 0.0]
    s = load_scenario("paper", [f'robot.cameras=[{{name="c", width={w}, height={h}, hfov_deg={hfov}, lens="fisheye", '
                                f'distortion={coeffs}}}]', "camera.preset=realistic"])
    p = lens_mod.plan(s.robot.cameras[0], s.camera.preset)
    mx, my = p.sample_maps()
    assert np.isfinite(mx).all() and np.isfinite(my).all()
    assert mx.min() >= 0 and mx.max() <= p.render_cam.width - 1
    assert my.min() >= 0 and my.max() <= p.render_cam.height - 1
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    xy = lens_mod.undistort(np.stack([u.ravel(), v.ravel()], 1), p.lens.model, p.lens.K, p.lens.D).reshape(h, w, 2)
    sparse = lens_mod.sparsest_sampling(xy)
    sampled = p.K_render[0, 0] * sparse
    pixels = p.render_cam.width * p.render_cam.height
    if p.fovea is not None:
        fv = p.fovea
        box = (fv.rows, fv.cols)
        sampled[box] = np.where(fv.mask, fv.K_render[0, 0] * sparse[box], sampled[box])
        fx = fv.float_maps[0][fv.mask]
        assert fx.min() >= 0 and fx.max() <= fv.render_cam.width - 1
        pixels += fv.render_cam.width * fv.render_cam.height
    if p.fovea is not None or pixels > lens_mod.SINGLE_RENDER_RATIO * w * h * 1.05:
        assert sampled.min() >= lens_mod.MIN_SAMPLING - 1e-6
    else:  # one render at the lens's focal length samples the centre at 1
        assert p.K_render[0, 0] == pytest.approx(p.lens.K[0, 0]) or sampled.min() >= lens_mod.MIN_SAMPLING - 1e-6
    assert pixels <= lens_mod.MAX_RENDER_PIXELS_RATIO * w * h * 1.1


def test_a_fisheye_with_its_fovea_repeats_its_frames_for_a_seed() -> None:
    """Lockstep determinism through the fovea and its blur: two renderers, the same seed and motion (a
    slide past a near cube, 20 ms exposure, so the fovea resamples its own sub-exposures) give the same
    bytes; another seed gives other noise."""
    poses, target = [(0.0, 0.0, 0.0), (0.0, 0.066, 0.02), (0.0, 0.132, 0.04)], (0.8, 0.05, math.pi + 0.3)
    runs = [_frames(_scenario("camera.exposure_ms=20", f"seed={seed}"), poses, target, [0, 1, 2])
            for seed in (4, 4, 5)]
    assert all(np.array_equal(a, b) for a, b in zip(runs[0], runs[1], strict=True))
    assert not np.array_equal(runs[0][1], runs[2][1])
    assert not np.array_equal(runs[0][1], runs[0][2])  # a new tick, a new frame
