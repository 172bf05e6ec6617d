"""Motion blur: streaks grow with speed, one filter (per tile) matches the sub-exposures where
the streak is uniform, the cheap streak bound never undercuts the exact streak, and the
camera's twist is exact down to tiny rotations."""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
import pytest

from tagswarm.protocol.geometry import se2_matrix
from tagswarm.protocol.scenario import load_scenario
from tagswarm.world import blur
from tagswarm.world.blur import camera_twist, motion_blur
from tagswarm.world.render import Renderer


def _edge_width(row: np.ndarray) -> int:
    """Pixels of a 0 -> 1 step's transition between 5 % and 95 %."""
    return int(np.count_nonzero((row > 0.05) & (row < 0.95)))


def test_blur_length_grows_with_speed() -> None:
    img = np.zeros((60, 200), np.float32)
    img[:, 100:] = 1.0
    depth = np.full(img.shape, 2.0, np.float32)
    k = np.array([[300.0, 0, 99.5], [0, 300.0, 29.5], [0, 0, 1]])
    widths = []
    for yaw_rate in (0.0, 0.5, 1.0, 2.0):  # about the optical y axis (down): a pan
        twist = np.array([0.0, 0.0, 0.0, 0.0, yaw_rate, 0.0])
        widths.append(_edge_width(motion_blur(img, depth, k, twist, 0.02)[30]))
    assert widths[0] == 0 and widths[1] < widths[2] < widths[3], widths
    assert abs(widths[3] - 300 * 2.0 * 0.02) <= 2, widths  # f * omega * exposure pixels
    # a sideways translation blurs near things more than far ones
    twist = np.array([0.5, 0.0, 0.0, 0.0, 0.0, 0.0])
    near = _edge_width(motion_blur(img, np.full(img.shape, 1.0, np.float32), k, twist, 0.02)[30])
    far = _edge_width(motion_blur(img, np.full(img.shape, 4.0, np.float32), k, twist, 0.02)[30])
    assert near > far


def _camera(hfov_deg: float, width: int = 320) -> str:
    """The override giving robots one front camera of this field of view and width (4:3)."""
    return f"robot.cameras=[{{name='front', width={width}, height={width * 3 // 4}, hfov_deg={hfov_deg}}}]"


def _turned_render(overrides: list[str], turn_rad: float) -> tuple[Any, Any, np.ndarray, np.ndarray, np.ndarray,
                                                                     np.ndarray, np.ndarray | None]:
    """(render plan, camera, pinhole render, metric depth (render size), T_world_cam before and now, the
    lens's fovea render or None) of robot 0 of the paper scene (realistic camera) after turning
    ``turn_rad`` on the spot."""

    s = load_scenario("paper", ["camera.preset=realistic", *overrides])
    cam = s.robot.cameras[0]
    with Renderer(s) as r:
        for rid in s.robot_ids:
            r.set_pose(rid, (0.5 * rid, 0.4 * (rid - 1.5), 0), (0, 0, 0, 1))
        p = r.plan(cam)
        mount = r._mount[cam.name]
        t_wc, prev = se2_matrix(-1.5, 0, 0) @ mount, se2_matrix(-1.5, 0, -turn_rad) @ mount
        gray, zbuf = r._shoot(p.render_cam, t_wc, True)
        fovea = None if p.fovea is None else r._shoot(p.fovea.render_cam, t_wc, False)[0]
    return p, cam, gray, blur.linear_depth(zbuf, cam.near_m, cam.far_m), prev, t_wc, fovea


def _turning_exposure(overrides: list[str], exposure_s: float,
                      tol_px: float | None = None) -> tuple[object, np.ndarray, np.ndarray]:
    """(exposure maps, blurred frame, sharp frame) of robot 0 of the paper scene turning at 1.2 rad/s."""

    p, _, gray, depth, prev, t_wc, fovea = _turned_render(overrides, 0.12)
    twist = blur.camera_twist(prev, t_wc, 0.1)
    kept = blur.UNIFORM_STREAK_TOL_PX
    if tol_px is not None:
        blur.UNIFORM_STREAK_TOL_PX = tol_px
    try:
        maps = blur.exposure_maps(*p.sample_maps(), depth, p.K_render, twist, exposure_s)
    finally:
        blur.UNIFORM_STREAK_TOL_PX = kept
    g = gray.astype(np.float32)
    f = None if fovea is None else fovea.astype(np.float32)
    return maps, (p.apply(g, f) if maps is None else blur.expose(g, maps)), p.apply(g, f)


def test_a_uniform_streak_is_one_filter_close_to_the_sub_exposures() -> None:
    """A turn through the 60 deg lens: the streak is the same all over the image, so the blur is one
    small filter over the lens image, within a fraction of a DN of resampling the render per
    sub-exposure (its own bilinear step smooths a little more)."""
    maps, fast, sharp = _turning_exposure([], 0.004)
    assert maps is not None and maps.kernel is not None  # type: ignore[attr-defined]
    per_pixel, slow, _ = _turning_exposure([], 0.004, tol_px=-1.0)
    assert per_pixel is not None and per_pixel.kernel is None and len(per_pixel) == 2  # type: ignore[attr-defined]
    blur = float(np.abs(slow - sharp).mean())
    assert blur > 0.2
    assert float(np.abs(fast - slow).mean()) < 0.6 * blur


def test_sub_exposures_count_output_pixels() -> None:
    """A 320x240 120 deg fisheye turning at 1.2 rad/s for 4 ms streaks ~0.7 output px (its pinhole
    render, twice the image's size, would call it ~1.5 px): no blur; 20 ms is a blur."""
    fisheye = _camera(120.0)
    assert _turning_exposure([fisheye], 0.004)[0] is None
    assert _turning_exposure([fisheye], 0.020)[0] is not None


def test_a_streak_uniform_per_tile_is_a_filter_per_tile_close_to_the_sub_exposures() -> None:
    """A turn at 640x480: the streak grows towards the image's sides by more than the tolerance, but
    within each tile it does not, so the blur is a filter per tile, as close to resampling the render
    per sub-exposure as the one-filter blur is."""
    cam = _camera(60.0, 640)
    maps, fast, sharp = _turning_exposure([cam], 0.004)
    assert maps is not None and maps.kernel is None  # type: ignore[attr-defined]
    tiles = maps.tiles  # type: ignore[attr-defined]
    assert tiles is not None and all(k is not None for _, _, k in tiles) and len(maps) == 0  # type: ignore[arg-type]
    covered = np.zeros(sharp.shape, int)
    for rows, cols, _ in tiles:
        covered[rows, cols] += 1
    assert (covered == 1).all()  # the tiles partition the image
    per_pixel, slow, _ = _turning_exposure([cam], 0.004, tol_px=-1.0)
    assert per_pixel is not None and per_pixel.tiles is None and len(per_pixel) >= 2  # type: ignore[attr-defined]
    blur = float(np.abs(slow - sharp).mean())
    assert blur > 0.2
    assert float(np.abs(fast - slow).mean()) < 0.6 * blur


def test_tiles_across_a_depth_edge_keep_their_sub_exposures() -> None:
    """A sideways move past a near wall on the left and a far one on the right: the tiles astride the
    depth edge blur by their sub-exposures exactly as the per-pixel blur does, the others by a filter."""

    h, w = 192, 384
    rng = np.random.default_rng(0)
    img = np.asarray(rng.uniform(0, 255, (h, w)), np.float32)
    depth = np.full((h, w), 4.0, np.float32)
    depth[:, : w // 2 + 10] = 0.5
    k = np.array([[300.0, 0, (w - 1) / 2], [0, 300.0, (h - 1) / 2], [0, 0, 1]])
    twist = np.array([0.4, 0.0, 0.0, 0.0, 0.0, 0.0])
    gu, gv = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    maps = blur.exposure_maps(gu, gv, depth, k, twist, 0.02)
    assert maps is not None and maps.tiles is not None
    mixed = [(r, c) for r, c, kern in maps.tiles if kern is None]
    assert mixed and all(c.start <= w // 2 + 10 < c.stop for _, c in mixed)
    out = blur.expose(img, maps)
    kept = blur.UNIFORM_STREAK_TOL_PX
    blur.UNIFORM_STREAK_TOL_PX = -1.0
    try:
        every = blur.exposure_maps(gu, gv, depth, k, twist, 0.02)
    finally:
        blur.UNIFORM_STREAK_TOL_PX = kept
    assert every is not None and every.tiles is None
    slow = blur.expose(img, every)
    for rows, cols in mixed:
        np.testing.assert_allclose(out[rows, cols], slow[rows, cols], atol=1e-3)
    far = (slice(0, h), slice(w - 96, w))  # uniform: a filter, close to the sub-exposures
    assert float(np.abs(out[far] - slow[far]).mean()) < 0.6 * float(np.abs(slow[far] - img[far]).mean())


def _exact_streak(map_x: np.ndarray, map_y: np.ndarray, depth: np.ndarray, k: np.ndarray, twist: np.ndarray,
                  tau_s: float) -> float:
    """The streak (output px) exposure_maps measures, computed the long way."""

    g = blur.FLOW_GRID_PX
    idx, xn, yn = blur._flow_grid(map_x, map_y, k, depth.shape)
    dx, dy = blur.blur_flow(xn, yn, depth.ravel().take(idx), twist, tau_s)
    du, dv = dx * np.float32(k[0, 0]), dy * np.float32(k[1, 1])
    a, b, c, e = blur._inverse_map_jacobian(map_x, map_y, g)
    su, sv = a * du + b * dv, c * du + e * dv
    return 2.0 * float(np.sqrt((su * su + sv * sv).max()))


@pytest.mark.parametrize("lens", ["pinhole", "fisheye"])
def test_the_streak_bound_never_undercuts_the_streak_and_is_tight_for_a_turn(lens: str) -> None:
    """The cheap bound that spares most frames the streak's computation: never below the streak
    (else a frame that should blur would not), for random motions of a 60 deg pinhole and the
    120 deg fisheye's lens maps, and within 30 % of it for a level robot turning on the spot."""

    p, _, _, depth, prev, t_wc, _ = _turned_render([_camera(60.0 if lens == "pinhole" else 120.0)], 0.04)
    mx, my = p.sample_maps()
    k = p.K_render
    idx, _, _ = blur._flow_grid(mx, my, k, depth.shape)
    nearest = float(depth.ravel().take(idx).min())
    rng = np.random.default_rng(3)
    checked = 0
    for _ in range(300):
        twist = rng.normal(0.0, 1.0, 6) * rng.choice([0.0, 0.05, 0.5, 2.0], 6)
        tau = float(rng.choice([0.0005, 0.002, 0.01]))
        bound = blur.streak_bound(mx, my, k, twist.tolist(), tau, nearest if np.any(twist[:3]) else None)
        if math.isfinite(bound):
            exact = _exact_streak(mx, my, depth, k, twist, tau)
            assert bound >= exact, (twist, tau, bound, exact)
            checked += 1
    assert checked > 200
    turn = blur.camera_twist(prev, t_wc, 0.033)  # a level turn on the spot: its camera also translates
    assert turn is not None and abs(turn[4]) > 1.0
    bound = blur.streak_bound(mx, my, k, turn.tolist(), 0.002, nearest)
    exact = _exact_streak(mx, my, depth, k, turn, 0.002)
    assert exact <= bound <= 1.3 * exact, (bound, exact)


@pytest.mark.parametrize("hfov", ["60.0", "80.0", "120.0"])
def test_a_streak_bound_just_under_a_pixel_never_hides_a_blur(hfov: str) -> None:
    """Where it matters, the bound just under 1 px (the exposure chosen so), the exact streak is
    under 1 px too, for random turns and moves at random depths through the realistic lens of each
    width; a lens map that nearly folds (the 90 deg barrel lens's corners) gets no bound at all."""

    def lens(h: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        p = _turned_render([_camera(float(h))], 0.0)[0]
        mx, my = p.sample_maps()
        return mx, my, p.K_render

    assert blur.streak_bound(*lens("90.0"), [0.0, 0.0, 0.0, 0.0, 1.0, 0.0], 0.001, None) == math.inf
    mx, my, k = lens(hfov)
    shape = (int(my.max()) + 2, int(mx.max()) + 2)
    rng = np.random.default_rng(5)
    worst = 0.0
    for _ in range(150):
        z = float(rng.uniform(0.1, 3.0))
        twist = np.zeros(6)
        axis = rng.normal(0.0, 1.0, 3)
        twist[3:] = axis / np.linalg.norm(axis) * rng.choice([0.0, 1.0])
        twist[:3] = rng.normal(0.0, 1.0, 3) * rng.choice([0.0, 0.3])
        if not np.any(twist):
            continue
        nearest = z if np.any(twist[:3]) else None
        lo, hi = 0.0, 1.0
        for _ in range(40):  # the longest exposure whose bound is under 1 px
            mid = (lo + hi) / 2
            lo, hi = (mid, hi) if blur.streak_bound(mx, my, k, twist.tolist(), mid, nearest) < 1.0 else (lo, mid)
        if lo == 0.0:
            continue
        exact = _exact_streak(mx, my, np.full(shape, z, np.float32), k, twist, lo)
        assert exact < 1.0, (twist, lo, z, exact)
        worst = max(worst, exact)
    assert worst > 0.8  # the bound is close enough to spare frames


def _pose(rotvec: list[float], t: list[float]) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = cv2.Rodrigues(np.asarray(rotvec, float))[0]
    m[:3, 3] = t
    return m


@pytest.mark.parametrize("angle", [0.0, 1e-7, 1e-4, 0.02, 0.5, 2.9, 3.05])
def test_camera_twist_is_the_motion_in_the_current_camera_frame(angle: float) -> None:
    """Rotation rate to 1e-9 relative down to 1e-7 rad a step (OpenCV's Rodrigues returned zero below
    ~1e-5 rad), the velocity in the camera's current frame, and None for a jump."""
    rng = np.random.default_rng(3)
    for _ in range(50):
        now = _pose(list(rng.normal(size=3) * 2), list(rng.normal(size=3)))
        axis = rng.normal(size=3)
        axis *= angle / np.linalg.norm(axis)
        step = rng.normal(size=3) * 0.05
        prev = now @ _pose(list(axis), list(step))  # the previous camera, in the current camera's frame
        twist = camera_twist(prev, now, 0.5)
        assert twist is not None
        np.testing.assert_allclose(twist[3:], -axis / 0.5, rtol=1e-8, atol=1e-15)
        np.testing.assert_allclose(twist[:3], -step / 0.5, rtol=1e-9, atol=1e-12)
    assert camera_twist(now, _pose([0.0, 0.0, 0.0], [0.0, 0.0, 5.0]) @ now, 0.1) is None  # 50 m/s: a teleport
    assert camera_twist(now, now, 0.0) is None
    broken = now.copy()
    broken[0, 3] = math.nan
    assert camera_twist(now, broken, 0.1) is None  # a NaN pose is no motion to blur with


def test_camera_twist_of_a_half_turn_is_that_rotation() -> None:
    """At exactly pi the axis' sign is free: the twist must rotate the camera the same way."""
    for axis in ([0.0, 0.0, 1.0], [0.0, 1.0, 1.0], [1.0, -2.0, 0.5]):
        n = np.asarray(axis) / np.linalg.norm(axis)
        now = _pose([0.3, -0.2, 0.1], [0.0, 0.0, 0.0])
        twist = camera_twist(now @ _pose(list(math.pi * n), [0.0, 0.0, 0.0]), now, 1.0)
        assert twist is not None
        np.testing.assert_allclose(cv2.Rodrigues(-twist[3:])[0], cv2.Rodrigues(math.pi * n)[0], atol=1e-7)
