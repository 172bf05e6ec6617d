"""A cheap upper bound of a motion blur's streak (pure numpy; docs/camera.md), so that most
frames skip the exact streak of :func:`tagswarm.world.blur.exposure_maps`: the lens's first-order
motion field on the flow grid, and the lens maps' inverse Jacobian it goes through.

Frames: the camera's optical frame (z forward, x right, y down); metres, seconds, radians;
lens maps are float (H, W) pixel coordinates into the pinhole render.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Final

import numpy as np
from numpy.typing import NDArray

from tagswarm.protocol.geometry import Mat

F32 = NDArray[np.float32]

#: the image motion is computed on a grid this many pixels apart and interpolated (it is smooth but
#: at depth edges, where a streak's length changes by a fraction of a pixel)
FLOW_GRID_PX: Final = 4


_JACOBIANS: dict[int, tuple[F32, tuple[F32, F32, F32, F32]]] = {}


def _inverse_map_jacobian(map_x: F32, map_y: F32, g: int) -> tuple[F32, F32, F32, F32]:
    """(a, b, c, e) on the ``g`` grid of the maps: [[a, b], [c, e]] turns a displacement in the
    render (px) into one in the output image (px), the inverse of the maps' derivative (cached per map)."""
    hit = _JACOBIANS.get(id(map_x))
    if hit is not None and hit[0] is map_x:
        return hit[1]
    mx, my = map_x.astype(np.float64), map_y.astype(np.float64)
    xu, xv = np.gradient(mx, axis=1)[::g, ::g], np.gradient(mx, axis=0)[::g, ::g]
    yu, yv = np.gradient(my, axis=1)[::g, ::g], np.gradient(my, axis=0)[::g, ::g]
    det = xu * yv - xv * yu
    det = np.where(np.abs(det) > 1e-9, det, 1e-9)
    inv = (np.asarray(yv / det, np.float32), np.asarray(-xv / det, np.float32), np.asarray(-yu / det, np.float32),
           np.asarray(xu / det, np.float32))
    if len(_JACOBIANS) > 64:
        _JACOBIANS.clear()
    _JACOBIANS[id(map_x)] = (map_x, inv)  # the map itself is kept: its id cannot be reused meanwhile
    return inv


class _StreakGains:
    """A lens's first-order motion field on the :data:`FLOW_GRID_PX` grid (output px per unit of
    twist times time) and the largest squared normalised radius ``r2_max``: the rotation's columns
    (w_x, w_y, w_z), the translation's worst-point gains (v_x, v_y, v_z per unit of 1/depth), and
    the worst-point gain of each rotation axis seen so far (a level robot's camera always turns
    about one axis, so this holds one or two entries)."""

    def __init__(self, map_x: F32, map_y: F32, K: Mat) -> None:
        g = FLOW_GRID_PX
        x = (map_x[::g, ::g].astype(np.float64) - K[0, 2]) / K[0, 0]
        y = (map_y[::g, ::g].astype(np.float64) - K[1, 2]) / K[1, 1]
        a, b, c, e = (np.asarray(m, np.float64) for m in _inverse_map_jacobian(map_x, map_y, g))
        fx, fy = float(K[0, 0]), float(K[1, 1])

        def out(du: NDArray[np.float64], dv: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
            return a * du + b * dv, c * du + e * dv

        # the motion field's columns in render px (points move opposite to the camera; signs do not matter)
        self.rotation = (out(fx * x * y, fy * (1 + y * y)), out(-fx * (1 + x * x), -fy * x * y), out(fx * y, -fy * x))
        translation = (out(np.full_like(x, -fx), np.zeros_like(x)), out(np.zeros_like(x), np.full_like(x, -fy)),
                       out(fx * x, fy * y))
        self.translation = tuple(float(np.sqrt((su * su + sv * sv).max())) for su, sv in translation)
        self.r2_max = float((x * x + y * y).max())
        # the inverse Jacobian's worst condition number: a map that nearly folds (a strong barrel lens's
        # corners) stretches a small change of the flow's direction into a large one of the streak
        sq, det = a * a + b * b + c * c + e * e, np.abs(a * e - b * c)
        root = np.sqrt(np.maximum(sq * sq - 4.0 * det * det, 0.0))
        big, small = np.sqrt((sq + root) / 2.0), np.sqrt(np.maximum(sq - root, 0.0) / 2.0)
        self.condition = float((big / np.maximum(small, 1e-12)).max())
        self.axes: dict[tuple[float, float, float], float] = {}

    def rotation_gain(self, wx: float, wy: float, wz: float) -> float:
        """The worst grid point's output-pixel motion per radian about the axis (wx, wy, wz) (not 0)."""
        n = math.sqrt(wx * wx + wy * wy + wz * wz)
        unit = (wx / n, wy / n, wz / n)
        if max(unit, key=abs) < 0:
            unit = (-unit[0], -unit[1], -unit[2])  # the field is odd in w: one entry per axis
        key = (round(unit[0], 3), round(unit[1], 3), round(unit[2], 3))
        gain = self.axes.get(key)
        if gain is None:
            # the axis rounded to 1e-3 moves a gain by < 0.2 % (|A| ~ f (1 + r^2)): covered by the margin
            (ax, ay), (bx, by), (cx, cy) = self.rotation
            su = unit[0] * ax + unit[1] * bx + unit[2] * cx
            sv = unit[0] * ay + unit[1] * by + unit[2] * cy
            gain = float(np.sqrt((su * su + sv * sv).max()))
            if len(self.axes) < 64:
                self.axes[key] = gain
        return gain


_GAINS: dict[tuple[int, bytes], tuple[F32, _StreakGains]] = {}
#: a lens map whose inverse Jacobian is worse conditioned than this gets no streak bound (the exact
#: streak every frame): its second-order terms are no longer a small share of the first-order one
MAX_BOUND_CONDITION: Final = 10.0


def streak_bound(map_x: F32, map_y: F32, K: Mat, twist: Sequence[float], tau_s: float,
                 depth_min_m: float | None) -> float:
    """An upper bound of the streak :func:`tagswarm.world.blur.exposure_maps` measures (output px, over the whole
    exposure, ``tau_s`` its half) for a camera moving with ``twist`` (optical frame; v, w) whose
    nearest grid sample is ``depth_min_m`` away (None: no translation).  The first-order motion
    field is linear in the twist: the rotation's worst grid point about the twist's own axis,
    plus each translation component's worst grid point at the nearest depth; the finite motion's
    second-order terms are covered by a margin (checked against the exact streak for lenses of 60 to
    120 deg, tests/unit/world/test_blur.py), and a motion too large for it, or a lens map that nearly
    folds (a strong barrel lens's corners, where the margin does not hold), gives inf."""
    key = (id(map_x), np.asarray(K, np.float64).tobytes())
    hit = _GAINS.get(key)
    if hit is None or hit[0] is not map_x:
        if len(_GAINS) > 64:
            _GAINS.clear()
        hit = _GAINS[key] = (map_x, _StreakGains(map_x, map_y, K))  # the map is kept: its id cannot be reused
    gains = hit[1]
    if gains.condition > MAX_BOUND_CONDITION:
        return math.inf
    vx, vy, vz, wx, wy, wz = (float(c) * tau_s for c in twist)
    if depth_min_m is None:
        if vx or vy or vz:
            return math.inf
        inv_z = 0.0
    else:
        inv_z = 1.0 / max(depth_min_m, 1e-3)
    theta = math.sqrt(wx * wx + wy * wy + wz * wz)
    tx, ty, tz = gains.translation
    first = (theta * gains.rotation_gain(wx, wy, wz) if theta > 0 else 0.0) + (
        tx * abs(vx) + ty * abs(vy) + tz * abs(vz)) * inv_z
    # the first-order motion in normalised coordinates is at most f1; the exact one differs from it by
    # less than 0.35 f1^2 for f1 <= 0.2 (checked over random motions; 1 f1^2 is used) plus float32
    # rounding (~1e-7), a difference the inverse Jacobian may stretch (a distorting lens's corners)
    nonlinear = (theta * (1.0 + gains.r2_max)
                 + math.sqrt(vx * vx + vy * vy + vz * vz) * inv_z * math.sqrt(1.0 + gains.r2_max))
    if nonlinear > 0.2:
        return math.inf
    return 2.0 * first * (1.0 + 2.0 * nonlinear) + 0.02
