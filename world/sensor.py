"""Sensor effects on a rendered frame: motion blur, vignetting, contrast/brightness, shot and
read noise (pure numpy/OpenCV; docs/camera.md).

Intensities are 8-bit digital numbers (DN) in float32 until :func:`develop` rounds and
clips them.  Randomness comes only from :func:`frame_rng`, seeded by (scenario seed,
robot, camera, tick), so a lockstep run repeats its images byte for byte whatever
else draws random numbers.  Frames: the camera's optical frame (z forward, x right,
y down); metres, seconds, radians.
"""

from __future__ import annotations

import math
import zlib
from typing import Any, Final

import cv2
import numpy as np
from numpy.typing import NDArray

from tagswarm.protocol.geometry import Mat
from tagswarm.protocol.scenario import CameraSensor

#: at most this many sub-exposures are averaged for a motion blur (longer streaks are sampled sparser)
MAX_BLUR_SAMPLES: Final = 16
#: camera motion between two frames beyond these rates is a jump (teleport, restart), not motion
MAX_SPEED_M_S: Final = 3.0
MAX_TURN_RAD_S: Final = 10.0
F32 = NDArray[np.float32]


def frame_rng(seed: int, robot_id: int, camera: str, step: int) -> np.random.Generator:
    """The random generator of one frame: a function of (seed, robot, camera, tick) only."""
    return np.random.default_rng([seed, robot_id, zlib.crc32(camera.encode()), step])


def linear_depth(zbuffer: NDArray[Any], near_m: float, far_m: float) -> F32:
    """Metric depth along the optical axis (H, W) from an OpenGL depth buffer in [0, 1]."""
    d = np.asarray(zbuffer, np.float32)
    return np.asarray(far_m * near_m / (far_m - (far_m - near_m) * d), np.float32)


def _rodrigues(rotvec: NDArray[np.float64]) -> Mat:
    return np.asarray(cv2.Rodrigues(np.asarray(rotvec, np.float64).reshape(3, 1))[0], np.float64)


def camera_twist(t_wc_prev: Mat, t_wc_now: Mat, dt_s: float) -> NDArray[np.float64] | None:
    """(v (3), w (3)) of the camera in its own frame now (m/s, rad/s) from two poses T_world_cam
    ``dt_s`` apart, or None when the step is a jump rather than motion."""
    if dt_s <= 0:
        return None
    delta = np.linalg.inv(t_wc_now) @ t_wc_prev  # the previous camera in the current one
    w = -np.asarray(cv2.Rodrigues(delta[:3, :3])[0], np.float64).ravel() / dt_s
    v = -delta[:3, 3] / dt_s
    if np.linalg.norm(v) > MAX_SPEED_M_S or np.linalg.norm(w) > MAX_TURN_RAD_S:
        return None
    return np.concatenate([v, w])


def blur_flow(depth_m: F32, K: Mat, twist: NDArray[np.float64], tau_s: float) -> tuple[F32, F32]:
    """The image motion (du, dv) (H, W) of each pixel's scene point ``tau_s`` seconds later, seen
    by a pinhole ``K`` moving with ``twist`` (optical frame)."""
    h, w = depth_m.shape
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    xn = ((np.arange(w, dtype=np.float32) - np.float32(cx)) / np.float32(fx))[None, :]
    yn = ((np.arange(h, dtype=np.float32) - np.float32(cy)) / np.float32(fy))[:, None]
    r = _rodrigues(twist[3:] * tau_s).T.astype(np.float32)  # points move opposite to the camera
    t = (twist[:3] * tau_s).astype(np.float32)
    inv_z = 1.0 / np.maximum(depth_m, np.float32(1e-3))
    # (R (X - t)) / z with X = z (xn, yn, 1): rotation terms need no depth, translation terms 1/z
    tx = r[0] @ t
    ty = r[1] @ t
    tz = r[2] @ t
    x2 = r[0, 0] * xn + r[0, 1] * yn + r[0, 2] - tx * inv_z
    y2 = r[1, 0] * xn + r[1, 1] * yn + r[1, 2] - ty * inv_z
    z2 = np.maximum(r[2, 0] * xn + r[2, 1] * yn + r[2, 2] - tz * inv_z, np.float32(1e-3))
    return (np.float32(fx) * (x2 / z2 - xn)).astype(np.float32), (np.float32(fy) * (y2 / z2 - yn)).astype(np.float32)


def motion_blur(img: F32, depth_m: F32, K: Mat, twist: NDArray[np.float64] | None, exposure_s: float) -> F32:
    """``img`` (H, W) of a pinhole ``K`` averaged over an exposure of ``exposure_s`` centred on
    its instant, the camera moving with ``twist``: each sub-exposure is the frame warped by the
    image motion of its time (linear in time over the exposure; depth of the centre frame, so
    occlusions changing within the exposure are ignored).  As many sub-exposures as the streak
    is long in pixels (at most :data:`MAX_BLUR_SAMPLES`)."""
    if twist is None or exposure_s <= 0:
        return img
    du, dv = blur_flow(depth_m, K, twist, exposure_s / 2.0)
    streak = 2.0 * float(np.sqrt((du * du + dv * dv).max()))
    n = min(MAX_BLUR_SAMPLES, math.ceil(streak))
    if n < 2:
        return img
    h, w = img.shape
    gu, gv = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    acc = np.zeros_like(img)
    for i in range(n):
        a = np.float32(2.0 * ((i + 0.5) / n - 0.5))  # -1 .. 1 over the exposure
        # backward warp: the sub-exposure at pixel q shows what the centre frame has at q - flow(q)
        acc += np.asarray(cv2.remap(img, gu - a * du, gv - a * dv, cv2.INTER_LINEAR,
                                    borderMode=cv2.BORDER_REPLICATE), np.float32)
    return acc / np.float32(n)


def vignetting_gain(width: int, height: int, K: Mat, strength: float) -> F32:
    """Relative brightness (H, W): 1 at the principal point, ``1 - strength`` in the farthest image
    corner, quadratic in the radius between (the cos^4 fall-off's leading term)."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32))
    cx, cy = float(K[0, 2]), float(K[1, 2])
    r2 = (u - cx) ** 2 + (v - cy) ** 2
    corner2 = max((x - cx) ** 2 + (y - cy) ** 2 for x in (0, width - 1) for y in (0, height - 1))
    return np.asarray(1.0 - strength * r2 / corner2, np.float32)


def develop(img: F32, cfg: CameraSensor, rng: np.random.Generator, gain: F32 | None = None) -> NDArray[np.uint8]:
    """The 8-bit frame of a light image ``img`` (H, W, DN): vignetting ``gain``, contrast about
    mid-grey and brightness, shot noise (signal / ``electrons_per_dn`` DN^2), read noise (Gaussian, DN),
    rounded and clipped.  ``cfg`` is a resolved ``[camera]`` section."""
    out = img if gain is None else img * gain
    contrast = 1.0 if cfg.contrast is None else cfg.contrast
    out = (out - 128.0) * contrast + 128.0 + (cfg.brightness_dn or 0.0)
    out = np.clip(out, 0.0, 255.0)
    read2 = float(cfg.read_noise_dn or 0.0) ** 2
    if cfg.electrons_per_dn or read2:
        # shot noise as its Gaussian limit (>= 20 electrons per DN is far beyond where Poisson differs),
        # one draw with read noise: variance signal / (e/DN) + read^2 (DN^2)
        var = out * np.float32(1.0 / cfg.electrons_per_dn) + np.float32(read2) if cfg.electrons_per_dn \
            else np.float32(read2)
        out = out + np.sqrt(var) * rng.standard_normal(out.shape, dtype=np.float32)
    return np.asarray(np.clip(np.rint(out), 0, 255), np.uint8)
