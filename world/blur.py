"""Motion blur of a rendered frame (pure numpy/OpenCV; docs/camera.md): the camera's twist
between two ticks, the image motion it causes during the exposure, and the sub-exposures (or
one filter) that blur the lens image; the cheap bound of its streak that spares most frames the
exact one is in :mod:`tagswarm.world.streakbound`.

Frames: the camera's optical frame (z forward, x right, y down); metres, seconds, radians;
image maps are float (H, W) pixel coordinates into the pinhole render.
"""

from __future__ import annotations

import functools
import math
from typing import Any, Final

import cv2
import numpy as np
from numpy.typing import NDArray

from tagswarm.protocol.geometry import Mat
from tagswarm.world.streakbound import FLOW_GRID_PX as FLOW_GRID_PX
from tagswarm.world.streakbound import _inverse_map_jacobian as _inverse_map_jacobian
from tagswarm.world.streakbound import streak_bound as streak_bound

#: sub-exposures of a motion blur are at most this far apart along the streak
SAMPLE_SPACING_PX: Final = 1.5
#: at most this many sub-exposures are averaged for a motion blur (longer streaks are sampled sparser)
MAX_BLUR_SAMPLES: Final = 16
#: camera motion between two frames beyond these rates is a jump (teleport, restart), not motion
MAX_SPEED_M_S: Final = 3.0
MAX_TURN_RAD_S: Final = 10.0
F32 = NDArray[np.float32]


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
    # in plain floats: a frame's twist is ~40 small numpy calls' overhead otherwise, 0.04 ms a frame
    # right after a render
    (a00, a01, a02, a03), (a10, a11, a12, a13), (a20, a21, a22, a23) = t_wc_now[:3].tolist()
    (b00, b01, b02, b03), (b10, b11, b12, b13), (b20, b21, b22, b23) = t_wc_prev[:3].tolist()
    # R = R_now^T R_prev: the previous camera's orientation in the current one
    r00 = a00 * b00 + a10 * b10 + a20 * b20
    r01, r02 = a00 * b01 + a10 * b11 + a20 * b21, a00 * b02 + a10 * b12 + a20 * b22
    r10, r11 = a01 * b00 + a11 * b10 + a21 * b20, a01 * b01 + a11 * b11 + a21 * b21
    r12 = a01 * b02 + a11 * b12 + a21 * b22
    r20, r21 = a02 * b00 + a12 * b10 + a22 * b20, a02 * b01 + a12 * b11 + a22 * b21
    r22 = a02 * b02 + a12 * b12 + a22 * b22
    cos_t = max(-1.0, min(1.0, 0.5 * (r00 + r11 + r22 - 1.0)))
    theta = math.acos(cos_t)
    sx, sy, sz = r21 - r12, r02 - r20, r10 - r01  # 2 sin(theta) times the axis
    if theta >= 3.0:  # near a half turn the skew part loses the axis: far beyond a frame's motion anyway
        wx, wy, wz = cv2.Rodrigues(t_wc_now[:3, :3].T @ t_wc_prev[:3, :3])[0].ravel().tolist()
    else:  # theta / (2 sin theta), to second order where the division loses precision
        k = 0.5 * (1.0 + theta * theta / 6.0) if theta < 1e-4 else 0.5 * theta / math.sin(theta)
        wx, wy, wz = k * sx, k * sy, k * sz
    # v = -R_now^T (p_prev - p_now) / dt: the camera's velocity in its current frame
    dx, dy, dz = b03 - a03, b13 - a13, b23 - a23
    inv = -1.0 / dt_s
    vx = (a00 * dx + a10 * dy + a20 * dz) * inv
    vy = (a01 * dx + a11 * dy + a21 * dz) * inv
    vz = (a02 * dx + a12 * dy + a22 * dz) * inv
    wx, wy, wz = wx * inv, wy * inv, wz * inv
    # written so that a NaN (a broken pose) is a jump too
    if not (vx * vx + vy * vy + vz * vz <= MAX_SPEED_M_S ** 2 and wx * wx + wy * wy + wz * wz <= MAX_TURN_RAD_S ** 2):
        return None
    return np.array([vx, vy, vz, wx, wy, wz])


_GRIDS: dict[tuple[int, int], tuple[F32, F32]] = {}


def _pixel_grid(h: int, w: int) -> tuple[F32, F32]:
    """(u, v) coordinates of every pixel of an (h, w) image (cached per size)."""
    g = _GRIDS.get((h, w))
    if g is None:
        gu, gv = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
        g = _GRIDS[(h, w)] = (gu, gv)
    return g


def blur_flow(xn: F32, yn: F32, depth_m: F32, twist: NDArray[np.float64], tau_s: float) -> tuple[F32, F32]:
    """The motion (dxn, dyn) in normalised image coordinates of the scene points seen at
    (``xn``, ``yn``) at depth ``depth_m`` (broadcastable arrays) ``tau_s`` seconds later, by a
    camera moving with ``twist`` (optical frame)."""
    r = _rodrigues(twist[3:] * tau_s).T.astype(np.float32)  # points move opposite to the camera
    t = (twist[:3] * tau_s).astype(np.float32)
    inv_z = 1.0 / np.maximum(depth_m, np.float32(1e-3))
    # (R (X - t)) / z with X = z (xn, yn, 1): rotation terms need no depth, translation terms 1/z
    tx, ty, tz = r[0] @ t, r[1] @ t, r[2] @ t
    x2 = r[0, 0] * xn + r[0, 1] * yn + r[0, 2] - tx * inv_z
    y2 = r[1, 0] * xn + r[1, 1] * yn + r[1, 2] - ty * inv_z
    z2 = np.maximum(r[2, 0] * xn + r[2, 1] * yn + r[2, 2] - tz * inv_z, np.float32(1e-3))
    return np.asarray(x2 / z2 - xn, np.float32), np.asarray(y2 / z2 - yn, np.float32)


#: a streak (output px) that varies by at most this much over the image is blurred as one kernel over the
#: lens image: each sample lands at most this far from where the per-pixel sub-exposures put it
UNIFORM_STREAK_TOL_PX: Final = 0.25
_FIXED: dict[int, tuple[F32, tuple[Any, Any]]] = {}


#: the streak's uniformity is judged per tile of this many output pixels a side (a multiple of the flow grid)
TILE_PX: Final = 96


class Exposures(list[tuple[F32, F32]]):
    """The sub-exposures of one frame (:func:`exposure_maps`): their sampling maps, or, when the streak
    is the same all over the image, ``kernel``, the blur as one filter over the lens image (the render
    resampled through ``lens_maps``), or, when it is the same within each of some tiles, ``tiles``:
    (rows, columns, filter) per tile, the filter None where the tile needs its sub-exposures' maps."""

    kernel: F32 | None = None
    lens_maps: tuple[F32, F32] | None = None
    tiles: list[tuple[slice, slice, F32 | None]] | None = None


def streak_kernel(du: float, dv: float, n: int) -> F32:
    """The filter (odd square, anchor at its centre) averaging ``n`` bilinear samples of an image at
    offsets ``-a_i (du, dv)`` (px), a_i spread over -1..1 as the sub-exposures are."""
    r = math.ceil(max(abs(du), abs(dv))) + 1
    k = np.zeros((2 * r + 1, 2 * r + 1), np.float32)
    for i in range(n):
        a = 2.0 * ((i + 0.5) / n - 0.5)
        ox, oy = -a * du + r, -a * dv + r
        x0, y0 = math.floor(ox), math.floor(oy)
        wx, wy = ox - x0, oy - y0
        k[y0, x0] += (1 - wx) * (1 - wy) / n
        k[y0, x0 + 1] += wx * (1 - wy) / n
        k[y0 + 1, x0] += (1 - wx) * wy / n
        k[y0 + 1, x0 + 1] += wx * wy / n
    return k


_GRID_OF_MAP: dict[tuple[int, bytes, tuple[int, ...]], tuple[F32, NDArray[np.intp], F32, F32]] = {}


def _flow_grid(map_x: F32, map_y: F32, K: Mat, depth_shape: tuple[int, ...]) -> tuple[NDArray[np.intp], F32, F32]:
    """On the :data:`FLOW_GRID_PX` grid of the output: the flat index of the render pixel each grid
    point samples (for its depth) and its normalised coordinates (cached per map, intrinsics and size)."""
    key = (id(map_x), np.asarray(K, np.float64).tobytes(), tuple(depth_shape))
    hit = _GRID_OF_MAP.get(key)
    if hit is not None and hit[0] is map_x:
        return hit[1], hit[2], hit[3]
    g = FLOW_GRID_PX
    mx, my = map_x[::g, ::g], map_y[::g, ::g]
    hd, wd = depth_shape
    idx = np.clip(np.rint(my).astype(np.intp), 0, hd - 1) * wd + np.clip(np.rint(mx).astype(np.intp), 0, wd - 1)
    xn = np.asarray((mx - np.float32(K[0, 2])) / np.float32(K[0, 0]), np.float32)
    yn = np.asarray((my - np.float32(K[1, 2])) / np.float32(K[1, 1]), np.float32)
    if len(_GRID_OF_MAP) > 64:
        _GRID_OF_MAP.clear()
    _GRID_OF_MAP[key] = (map_x, idx, xn, yn)  # the map itself is kept: its id cannot be reused meanwhile
    return idx, xn, yn


def _fixed_maps(map_x: F32, map_y: F32) -> tuple[Any, Any]:
    """``cv2.remap``'s fixed-point form of float maps (cached per map)."""
    hit = _FIXED.get(id(map_x))
    if hit is not None and hit[0] is map_x:
        return hit[1]
    fixed = cv2.convertMaps(map_x, map_y, cv2.CV_16SC2)
    if len(_FIXED) > 64:
        _FIXED.clear()
    _FIXED[id(map_x)] = (map_x, (fixed[0], fixed[1]))
    return fixed[0], fixed[1]


@functools.lru_cache(maxsize=4096)
def _tile_kernel(du16: int, dv16: int, n: int) -> F32:
    """:func:`streak_kernel` of a half-streak given in 1/16 px (a tile's centre streak, rounded: 1/32 px
    is nothing next to :data:`UNIFORM_STREAK_TOL_PX`, and neighbouring tiles and frames share filters)."""
    k = streak_kernel(du16 / 16.0, dv16 / 16.0, n)
    k.flags.writeable = False
    return k


def _tiles(su: F32, sv: F32, g: int, n: int, shape: tuple[int, int]) -> list[tuple[slice, slice, F32 | None]]:
    """The :data:`TILE_PX` tiles of an ``shape`` image whose half-streak (``su``, ``sv``: output px on
    the ``g`` grid) varies by at most :data:`UNIFORM_STREAK_TOL_PX` about its centre, with the filter
    of that centre (``n`` sub-exposures), the others with None."""
    t = TILE_PX // g
    starts = [np.arange(0, su.shape[0] - 1, t), np.arange(0, su.shape[1] - 1, t)]

    def per_tile(a: F32, op: np.ufunc) -> F32:
        cell = op(op(a[:-1, :-1], a[1:, :-1]), op(a[:-1, 1:], a[1:, 1:]))  # the 4 grid points around each cell
        return np.asarray(op.reduceat(op.reduceat(cell, starts[0], axis=0), starts[1], axis=1), np.float32)

    umax, umin, vmax, vmin = (per_tile(su, np.maximum), per_tile(su, np.minimum), per_tile(sv, np.maximum),
                              per_tile(sv, np.minimum))
    uniform = np.maximum(umax - umin, vmax - vmin) <= 2.0 * UNIFORM_STREAK_TOL_PX
    cu, cv = (umax + umin) / 2.0, (vmax + vmin) / 2.0
    h, w = shape
    tiles = []
    for i, gy in enumerate(starts[0]):
        rows = slice(int(gy) * g, h if i == len(starts[0]) - 1 else int(gy + t) * g)
        for j, gx in enumerate(starts[1]):
            cols = slice(int(gx) * g, w if j == len(starts[1]) - 1 else int(gx + t) * g)
            tiles.append((rows, cols, _tile_kernel(round(float(cu[i, j]) * 16), round(float(cv[i, j]) * 16), n)
                          if uniform[i, j] else None))
    return tiles


def exposure_maps(map_x: F32, map_y: F32, depth_m: NDArray[Any], K: Mat, twist: NDArray[np.float64] | None,
                  exposure_s: float, near_far: tuple[float, float] | None = None,
                  resample: bool = False) -> Exposures | None:
    """Sampling maps of the sub-exposures of one frame: the output pixel q of sub-exposure i shows
    the pinhole render (intrinsics ``K``, depth ``depth_m``) at ``map(q) - a_i flow(map(q))``,
    with ``map`` the lens's maps into the render (float (H, W); the pixel grid for a pinhole),
    ``flow`` the image motion over half the exposure of a camera moving with ``twist`` and a_i
    spread over -1..1.  The motion is linear in time over the exposure and computed on a
    :data:`FLOW_GRID_PX` grid (it is smooth but at depth edges); the depth is the centre
    frame's, so occlusions changing within the exposure are ignored.  Sub-exposures at most
    :data:`SAMPLE_SPACING_PX` output pixels apart (bilinear sampling fills between them), at least
    2, at most :data:`MAX_BLUR_SAMPLES`; None for a streak under 1 output pixel.  With ``near_far``
    (m), ``depth_m`` is the render's OpenGL depth buffer, linearised only where the grid samples it.
    ``resample``: every pixel by its sub-exposures, never a filter (a lens's fovea, see world/lens.py)."""
    if twist is None or exposure_s <= 0:
        return None
    components = twist.tolist()
    if not any(components):
        return None
    g = FLOW_GRID_PX
    depth_at, xn, yn = _flow_grid(map_x, map_y, K, depth_m.shape)
    fx, fy = np.float32(K[0, 0]), np.float32(K[1, 1])
    raw = depth_m.ravel().take(depth_at) if any(components[:3]) else None
    nearest = None
    if raw is not None:  # an OpenGL depth buffer grows with the depth: linearise its least value only
        nearest = float(raw.min())
        if near_far is not None:
            near, far = near_far
            nearest = far * near / (far - (far - near) * nearest)
    if streak_bound(map_x, map_y, K, components, exposure_s / 2.0, nearest) < 1.0:
        return None  # most frames: the exact streak below costs several times this bound
    if raw is None:
        depth = np.ones_like(xn)  # no translation: the flow does not depend on depth
    else:
        depth = linear_depth(raw, *near_far) if near_far is not None else raw
    dx, dy = blur_flow(xn, yn, depth, twist, exposure_s / 2.0)
    du, dv = dx * fx, dy * fy
    # the streak in OUTPUT pixels decides the sub-exposures (the lens may sample the render sparser or
    # denser than one render pixel per output pixel: a fisheye's wide pinhole render is ~2x its image)
    a, b, c, e = _inverse_map_jacobian(map_x, map_y, g)
    su, sv = a * du + b * dv, c * du + e * dv
    streak = 2.0 * float(np.sqrt((su * su + sv * sv).max()))
    if streak < 1.0:
        return None
    n = min(MAX_BLUR_SAMPLES, max(2, math.ceil(streak / SAMPLE_SPACING_PX)))
    out = Exposures()
    out.lens_maps = (map_x, map_y)
    u0, u1, v0, v1 = float(su.min()), float(su.max()), float(sv.min()), float(sv.max())
    if max(u1 - u0, v1 - v0) <= 2.0 * UNIFORM_STREAK_TOL_PX and not resample:
        # a turn seen through a narrow lens: one small filter instead of n resamplings of the render
        out.kernel = streak_kernel((u0 + u1) / 2.0, (v0 + v1) / 2.0, n)
        return out
    h, w = map_x.shape
    # else per tile (a wide or distorting lens, a large image): a filter where the streak is uniform
    # within it, the sub-exposures' maps only where it is not (a depth edge under translation)
    tiles = _tiles(su, sv, g, n, (h, w)) if min(su.shape) > 1 and not resample else []
    if tiles and all(k is not None for _, _, k in tiles):
        out.tiles = tiles
        return out
    du = np.asarray(cv2.resize(du, (w, h), interpolation=cv2.INTER_LINEAR), np.float32)
    dv = np.asarray(cv2.resize(dv, (w, h), interpolation=cv2.INTER_LINEAR), np.float32)
    for i in range(n):
        weight = -2.0 * ((i + 0.5) / n - 0.5)
        out.append((np.asarray(cv2.scaleAdd(du, weight, map_x), np.float32),  # type: ignore[call-overload]
                    np.asarray(cv2.scaleAdd(dv, weight, map_y), np.float32)))  # type: ignore[call-overload]
    # else every pixel by its sub-exposures
    out.tiles = tiles if any(k is not None for _, _, k in tiles) else None
    return out


def expose(render: NDArray[Any], maps: Exposures, lensed: NDArray[Any] | None = None) -> F32:
    """The mean of the sub-exposures sampled from ``render`` (H_r, W_r; 8-bit or float) through
    ``maps`` (:func:`exposure_maps`), in float; ``lensed``, the render already resampled through the
    lens's maps (8-bit or float), spares resampling it again where a filter does the blur."""
    if (maps.kernel is not None or maps.tiles is not None) and lensed is None:
        assert maps.lens_maps is not None
        lensed = cv2.remap(render, *_fixed_maps(*maps.lens_maps), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    if maps.kernel is not None:
        assert lensed is not None
        return np.asarray(cv2.filter2D(lensed, cv2.CV_32F, maps.kernel, borderType=cv2.BORDER_REPLICATE), np.float32)
    src = render.astype(np.float32) if len(maps) else render  # float only when it is resampled
    if maps.tiles is None:
        acc = np.zeros(maps[0][0].shape, np.float32)
        for mx, my in maps:
            acc += np.asarray(cv2.remap(src, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE), np.float32)
        return acc / np.float32(len(maps))
    assert lensed is not None
    out = np.empty(lensed.shape, np.float32)  # every tile is written below
    h, w = lensed.shape
    for rows, cols, k in maps.tiles:
        if k is None:
            acc = np.zeros((rows.stop - rows.start, cols.stop - cols.start), np.float32)
            for mx, my in maps:
                acc += np.asarray(cv2.remap(src, mx[rows, cols], my[rows, cols], cv2.INTER_LINEAR,
                                            borderMode=cv2.BORDER_REPLICATE), np.float32)
            out[rows, cols] = acc / np.float32(len(maps))
            continue
        # the tile with the filter's reach around it (the image's own border replicates, as for one filter)
        r = k.shape[0] // 2
        y0, y1, x0, x1 = max(0, rows.start - r), min(h, rows.stop + r), max(0, cols.start - r), min(w, cols.stop + r)
        part = cv2.filter2D(lensed[y0:y1, x0:x1], cv2.CV_32F, k, borderType=cv2.BORDER_REPLICATE)
        out[rows, cols] = part[rows.start - y0:rows.stop - y0, cols.start - x0:cols.stop - x0]
    return out


def motion_blur(img: F32, depth_m: F32, K: Mat, twist: NDArray[np.float64] | None, exposure_s: float) -> F32:
    """A pinhole frame ``img`` (H, W, intrinsics ``K``) exposed for ``exposure_s`` by a camera
    moving with ``twist``: :func:`exposure_maps` through the identity."""
    gu, gv = _pixel_grid(*img.shape)
    maps = exposure_maps(gu, gv, depth_m, K, twist, exposure_s)
    return img if maps is None else expose(img, maps)
