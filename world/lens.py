"""Lens models of the simulated cameras and the remap that renders them (pure numpy/OpenCV).

A distorted camera is rendered as a wider pinhole view (pybullet can only render
pinholes) and resampled once per frame with ``cv2.remap`` through maps computed
once per camera: every output pixel is undistorted (OpenCV's own inverse of the
model, iterated to 1e-10) onto the pinhole render.  Models, in OpenCV's
conventions and pixel convention (pixel centres at integer coordinates):

* ``pinhole``: no distortion (the render itself, untouched);
* ``brown_conrady``: (k1, k2, p1, p2, k3) of ``cv2.projectPoints``; the focal length
  is the pinhole one of ``hfov_deg``, so barrel distortion widens the view;
* ``fisheye``: the equidistant model of ``cv2.fisheye`` (k1..k4); the focal length
  puts ``hfov_deg`` across the image width (r = f * theta).

The pinhole render keeps the output's focal length at the image centre (no loss of
detail where the lens magnifies most) unless that would cost more than
:data:`MAX_RENDER_PIXELS_RATIO` times the output's pixels, then its focal length
shrinks to fit.  Frames: the camera's optical frame (z forward, x right, y down).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Final, Literal

import cv2
import msgspec
import numpy as np
from numpy.typing import NDArray

from tagswarm.protocol.scenario import Camera
from tagswarm.protocol.scenario_schema import lens_of
from tagswarm.world.camera import intrinsics

#: the pinhole render may have at most this many times the output image's pixels
MAX_RENDER_PIXELS_RATIO: Final = 4.0
#: margin (px) of the render beyond the outermost sampled position (bilinear needs a neighbour)
RENDER_MARGIN_PX: Final = 2
LensModel = Literal["pinhole", "brown_conrady", "fisheye"]
_UNDISTORT_CRITERIA: Final = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)


@dataclass(frozen=True)
class Lens:
    """A camera's true lens: ``model``, ``coeffs`` (OpenCV's order), ``K`` (3, 3) of the
    output image (pixels), image size."""

    model: LensModel
    coeffs: tuple[float, ...]
    K: NDArray[np.float64]
    width: int
    height: int

    @property
    def D(self) -> NDArray[np.float64]:
        """The coefficients as OpenCV wants them (a column; zeros for a pinhole)."""
        return np.array(self.coeffs if self.coeffs else (0.0,) * 5, np.float64).reshape(-1, 1)

    @property
    def is_pinhole(self) -> bool:
        return self.model == "pinhole" or not any(self.coeffs)


def lens_for(cam: Camera, preset: str) -> Lens:
    """The lens of ``cam`` under the ``[camera]`` preset ``preset`` (output intrinsics included)."""
    name, coeffs = lens_of(cam, preset)
    model: LensModel = "fisheye" if name == "fisheye" else "brown_conrady" if name == "brown_conrady" else "pinhole"
    fx, fy, cx, cy = intrinsics(cam)
    if model == "fisheye":
        fx = fy = (cam.width / 2.0) / math.radians(cam.hfov_deg / 2.0)
    k = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return Lens(model, tuple(float(c) for c in coeffs), k, cam.width, cam.height)


def project(points_cam: NDArray[np.float64], lens: Lens) -> NDArray[np.float64]:
    """Pixels (N, 2) of points (N, 3) in the optical frame (all in front of the camera)."""
    pts = np.ascontiguousarray(points_cam, np.float64).reshape(-1, 1, 3)
    zero = np.zeros(3)
    if lens.model == "fisheye":
        out, _ = cv2.fisheye.projectPoints(pts, zero, zero, lens.K, lens.D)
    else:
        out, _ = cv2.projectPoints(pts, zero, zero, lens.K, lens.D)
    return np.asarray(out, np.float64).reshape(-1, 2)


def undistort(pixels: NDArray[np.float64], model: str, K: NDArray[np.float64], D: NDArray[np.float64],
              P: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
    """Pixels (N, 2) of a ``model`` lens (K, D) moved to the ideal pinhole ``P`` (3, 3), or to
    normalised coordinates (x/z, y/z) when ``P`` is None."""
    pts = np.ascontiguousarray(pixels, np.float64).reshape(-1, 1, 2)
    if model == "fisheye":
        out = cv2.fisheye.undistortPoints(pts, K, D, R=np.eye(3), P=P if P is not None else np.eye(3),
                                          criteria=_UNDISTORT_CRITERIA)
    elif model == "brown_conrady":
        out = cv2.undistortPointsIter(pts, K, D, np.eye(3), P if P is not None else np.eye(3), _UNDISTORT_CRITERIA)
    else:
        p = np.eye(3) if P is None else P
        h = np.linalg.inv(K)
        xy = pts.reshape(-1, 2) @ h[:2, :2].T + h[:2, 2]
        return np.asarray(xy @ p[:2, :2].T + p[:2, 2], np.float64)
    return np.asarray(out, np.float64).reshape(-1, 2)


@dataclass
class RenderPlan:
    """How to render one camera: the pinhole ``render_cam`` (a Camera of the render's size and
    field of view, same mount) and the ``cv2.remap`` maps from it to the lens's image
    (None for a pinhole lens: the render is the image; fixed point, and ``float_maps`` the
    same in float for motion blur)."""

    lens: Lens
    render_cam: Camera
    K_render: NDArray[np.float64]
    maps: tuple[Any, Any] | None = field(default=None, repr=False)
    float_maps: tuple[NDArray[np.float32], NDArray[np.float32]] | None = field(default=None, repr=False)

    def sample_maps(self) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Where each output pixel samples the render (float (H, W) maps; the pixel grid for a pinhole)."""
        if self.float_maps is None:
            gu, gv = np.meshgrid(np.arange(self.render_cam.width, dtype=np.float32),
                                 np.arange(self.render_cam.height, dtype=np.float32))
            self.float_maps = (gu, gv)
        return self.float_maps

    def apply(self, render: NDArray[Any], interpolation: int = cv2.INTER_LINEAR) -> NDArray[Any]:
        """The lens's image of a pinhole ``render`` (H_r, W_r) of :attr:`render_cam`."""
        if self.maps is None:
            return render
        return cv2.remap(render, self.maps[0], self.maps[1], interpolation, borderMode=cv2.BORDER_REPLICATE)


def plan(cam: Camera, preset: str) -> RenderPlan:
    """The render plan of ``cam`` (computed once per camera: ~10-50 ms for the maps)."""
    lens = lens_for(cam, preset)
    if lens.is_pinhole:
        fx, fy, cx, cy = intrinsics(cam)
        return RenderPlan(lens, cam, np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]))
    u, v = np.meshgrid(np.arange(cam.width, dtype=np.float64), np.arange(cam.height, dtype=np.float64))
    xy = undistort(np.stack([u.ravel(), v.ravel()], axis=1), lens.model, lens.K, lens.D)
    if not np.isfinite(xy).all():
        raise ValueError(f"camera {cam.name!r}: the {lens.model} lens does not invert over the image")
    f = float(lens.K[0, 0])
    ax, ay = float(np.abs(xy[:, 0]).max()), float(np.abs(xy[:, 1]).max())
    # the pybullet frustum is symmetric: an even size about the centre, room for bilinear neighbours
    ratio = (2 * ax * f) * (2 * ay * f) / (cam.width * cam.height)
    if ratio > MAX_RENDER_PIXELS_RATIO:
        f /= math.sqrt(ratio / MAX_RENDER_PIXELS_RATIO)
    w = 2 * math.ceil(ax * f + RENDER_MARGIN_PX)
    h = 2 * math.ceil(ay * f + RENDER_MARGIN_PX)
    render_cam = msgspec.structs.replace(cam, width=w, height=h,
                                         hfov_deg=math.degrees(2.0 * math.atan(w / (2.0 * f))))
    fx, fy, cx, cy = intrinsics(render_cam)
    k_r = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    map_x = (fx * xy[:, 0] + cx).reshape(cam.height, cam.width).astype(np.float32)
    map_y = (fy * xy[:, 1] + cy).reshape(cam.height, cam.width).astype(np.float32)
    fixed = cv2.convertMaps(map_x, map_y, cv2.CV_16SC2)  # fixed point: ~2x faster remap, 1/32 px steps
    return RenderPlan(lens, render_cam, k_r, (fixed[0], fixed[1]), (map_x, map_y))
