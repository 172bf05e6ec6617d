"""Planar (SE(2)) pose of an upright target from its tag corners (pure code).

Both robots stand upright on the same flat floor, so of the target's pose in the
observer's base frame only (x, y, yaw) is unknown: its height is known (0 for a
robot's base, the scenario's ``z_m`` for a landmark's tag frame) and its roll and
pitch are zero.  A full 6-DOF PnP of one small square trades yaw against pitch at
distance (the width/height ratio of the tag only fixes ``cos(yaw)/cos(pitch)``);
solving for the three planar parameters removes that valley, and a camera above
or below the tag centres gets the range from the elevation angle.  It does not
remove the two-fold ambiguity of a single tag seen from the tag's own height: there
the mirrored pose is a pure yaw flip, planar too (:func:`mirror`).

:func:`solve` is Gauss-Newton (with step halving) on p = (x, y, yaw) of
``T_base_target = [Rz(yaw) | (x, y, z0)]`` over every corner of every camera,
each camera at its own ``T_base_cam``; :func:`covariance` is ``s^2 (J^T J)^-1``
of (x, y, yaw) from the planar Jacobian.  Pinholes in OpenCV's convention (pixel
centres at integer coordinates), no distortion.  Metres, radians, pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from tagswarm.protocol.geometry import Mat

_Arr = NDArray[Any]


@dataclass(slots=True)
class PlanarProblem:
    """The corners of one target in every camera that sees it, prepared for the planar model.

    With ``A = K R_cam_base`` of the corner's camera, its homogeneous pixel is
    ``q = A (Rz(yaw) P + (x, y, z0)) + K t_cam_base = cos(yaw) P_c + sin(yaw) P_s + x A_0 + y A_1 + q_z``
    for a corner ``P`` in the target frame, where ``A_0, A_1`` are A's first two columns,
    ``P_c = P_x A_0 + P_y A_1``, ``P_s = P_x A_1 - P_y A_0`` and ``q_z = (P_z + z0) A_2 + K t_cam_base``.
    ``basis`` (M, 3, 4) stacks (P_c, P_s, A_0, A_1) per corner (all cameras), ``q_z`` is (M, 3),
    ``img`` (M, 2) the detected pixels; ``dq`` (M, 3, 3) is scratch for d q / d (x, y, yaw)."""

    basis: _Arr
    q_z: _Arr
    img: _Arr
    dq: _Arr

    @classmethod
    def make(cls, views: list[tuple[Mat, Mat, _Arr, _Arr]], z0: float) -> PlanarProblem:
        """From ``(K, T_cam_base, obj (M, 3) target frame, img (M, 2) px)`` per camera and the
        target's known height ``z0`` in the observer's base frame."""
        m = sum(len(obj) for _, _, obj, _ in views)
        basis, q_z, img = np.empty((m, 3, 4)), np.empty((m, 3)), np.empty((m, 2))
        i = 0
        for k, t_cam_base, obj, pix in views:
            a = k @ t_cam_base[:3, :3]
            j = i + len(obj)
            ox, oy = obj[:, 0:1], obj[:, 1:2]
            basis[i:j, :, 0] = ox * a[:, 0] + oy * a[:, 1]
            basis[i:j, :, 1] = ox * a[:, 1] - oy * a[:, 0]
            basis[i:j, :, 2] = a[:, 0]
            basis[i:j, :, 3] = a[:, 1]
            q_z[i:j] = (obj[:, 2:3] + z0) * a[:, 2] + k @ t_cam_base[:3, 3]
            img[i:j] = pix
            i = j
        dq = np.empty((m, 3, 3))
        dq[:, :, :2] = basis[:, :, 2:]
        return cls(basis, q_z, img, dq)


@dataclass(slots=True)
class PlanarFit:
    """A converged planar pose: p = (x, y, yaw), residuals r (2M,) projected - detected (px),
    their Jacobian (2M, 3) w.r.t. p, and the sum of squared residuals (px^2)."""

    p: _Arr
    r: _Arr
    jac: _Arr
    sse: float


def matrix(x: float, y: float, yaw: float, z0: float) -> Mat:
    """``T_base_target`` (4, 4) of a planar pose at height ``z0``."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0, x], [s, c, 0.0, y], [0.0, 0.0, 1.0, z0], [0.0, 0.0, 0.0, 1.0]])


def residuals(pr: PlanarProblem, p: _Arr) -> tuple[_Arr, _Arr] | None:
    """Residuals (2M,) projected - detected (px) and their Jacobian (2M, 3) at p = (x, y, yaw);
    None if a corner is not in front of its camera."""
    c, s = math.cos(p[2]), math.sin(p[2])
    # (q - q_z, d q / d yaw) in one product
    qh = pr.basis @ np.array([[c, -s], [s, c], [p[0], 0.0], [p[1], 0.0]])
    q = qh[:, :, 0] + pr.q_z
    iw = q[:, 2:3]
    if not iw.min() > 1e-9:
        return None
    iw = 1.0 / iw
    uv = q[:, :2] * iw
    dq = pr.dq
    dq[:, :, 2] = qh[:, :, 1]
    # d (u, v) = (d q[:2] - (u, v) d q[2]) / q[2]
    jac = (dq[:, :2] - uv[:, :, None] * dq[:, 2:]) * iw[:, :, None]
    return (uv - pr.img).reshape(-1), jac.reshape(-1, 3)


def solve(pr: PlanarProblem, p0: tuple[float, float, float], max_iterations: int, tiny_px2: float, *,
          yaw_fixed: bool = False) -> PlanarFit | None:
    """Gauss-Newton with step halving from ``p0`` (only x, y if ``yaw_fixed``).  A step that would
    lower the sum of squares by less than ``tiny_px2`` (px^2) is the last one and is taken without
    evaluating the residuals again: the fit's residuals and Jacobian are then those before it, its
    SSE the linear model's prediction.  None if the start puts a corner behind a camera."""
    p = np.array(p0, np.float64)
    ev = residuals(pr, p)
    if ev is None:
        return None
    r, jac = ev
    sse = float(r @ r)
    n = 2 if yaw_fixed else 3
    for _ in range(max_iterations):
        j = jac[:, :n]
        grad = j.T @ r
        ok, sol = cv2.solve(j.T @ j, -grad, flags=cv2.DECOMP_CHOLESKY)
        if not ok:
            break
        step: _Arr = np.zeros(3)
        step[:n] = sol.ravel()
        gain = -float(step[:n] @ grad)
        if gain < tiny_px2:
            p += step
            sse -= gain
            break
        for _halving in range(4):
            p2 = p + step
            ev = residuals(pr, p2)
            if ev is not None:
                r2, jac2 = ev
                sse2 = float(r2 @ r2)
                if sse2 <= sse:
                    p, r, jac, sse = p2, r2, jac2, sse2
                    break
            step *= 0.5
        else:
            break
    p[2] = (p[2] + math.pi) % (2.0 * math.pi) - math.pi
    return PlanarFit(p, r, jac, sse)


def mirror(p: _Arr, centre: _Arr, normal: _Arr, eye: _Arr) -> tuple[float, float, float] | None:
    """The planar pose a single upright tag cannot be told apart from under weak perspective:
    the target turned about the vertical through the tag centre so that the tag's normal is
    mirrored about the (horizontal) line of sight from the camera at ``eye`` (base frame).  For
    a camera at the tag's height this is the two-fold ambiguity of a small square exactly, and
    the planar constraint does not remove it.  ``centre``, ``normal``: the tag's in the target
    frame.  None for a tag facing up or down, or seen exactly along its normal."""
    if abs(float(normal[2])) > 0.5:
        return None
    x, y, yaw = float(p[0]), float(p[1]), float(p[2])
    c, s = math.cos(yaw), math.sin(yaw)
    cx, cy = x + c * centre[0] - s * centre[1], y + s * centre[0] + c * centre[1]
    view = math.atan2(float(eye[1]) - cy, float(eye[0]) - cx)
    facing = math.atan2(s * normal[0] + c * normal[1], c * normal[0] - s * normal[1])
    d = 2.0 * ((view - facing + math.pi) % (2.0 * math.pi) - math.pi)
    if abs(d) < 1e-4:
        return None
    yaw2 = yaw + d
    c, s = math.cos(yaw2), math.sin(yaw2)
    return cx - (c * centre[0] - s * centre[1]), cy - (s * centre[0] + c * centre[1]), yaw2


def covariance(fit: PlanarFit, pixel_sigma_px: float) -> Mat | None:
    """(3, 3) covariance of (x, y, yaw): ``s^2 (J^T J)^-1`` with ``s = max(pixel_sigma_px,
    residual-based estimate)``; None when the corners do not constrain all three."""
    dof = len(fit.r) - 3
    s2 = max(pixel_sigma_px**2, fit.sse / dof) if dof > 0 else pixel_sigma_px**2
    # the SVD inverse also returns 1/condition number: a near-singular system is degenerate
    rcond, inv = cv2.invert(fit.jac.T @ fit.jac, flags=cv2.DECOMP_SVD)
    if not rcond > 1e-12:
        return None
    return np.asarray(s2 * 0.5 * (inv + inv.T), np.float64)
