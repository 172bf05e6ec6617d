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
detail where the lens magnifies most) while that costs at most
:data:`SINGLE_RENDER_RATIO` times the output's pixels.  A wider lens (a 120 deg
fisheye needs ~12x in one pinhole, most of it spent oversampling the corners) gets
two renders along the same axis: a *fovea*, a narrow pinhole at the lens's own
focal length for the centre, and a wide one at a smaller focal length for the rest,
chosen together for the fewest pixels (each render also costs
:data:`RENDER_FIXED_PX` pixels' worth) such that outside the fovea the wide render
still samples :data:`MIN_SAMPLING` render px per output px in its sparsest direction.
Frames: the camera's optical frame (z forward, x right, y down).
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

#: one pinhole render at the lens's focal length while it has at most this many times the output's pixels
SINGLE_RENDER_RATIO: Final = 4.0
#: a lens's renders have at most this many times the output's pixels in all (beyond, they sample sparser)
MAX_RENDER_PIXELS_RATIO: Final = 16.0
#: outside the fovea the wide render samples at least this many render px per output px in every direction
#: (one capped render of a 120 deg fisheye sampled its centre at 0.58 and decoded a 16 cm tag ahead to 1 m only)
MIN_SAMPLING: Final = 0.7
#: what a render costs beyond its pixels, in pixels' worth (TinyRenderer here: ~0.04 us/px, ~1 ms per call)
RENDER_FIXED_PX: Final = 25_000
#: margin (px) of the render beyond the outermost sampled position (bilinear needs a neighbour)
RENDER_MARGIN_PX: Final = 2
#: margin (px) of the fovea beyond its part of the image: the motion blur's sub-exposures sample around it
#: (half a streak: a 120 deg fisheye's 320x240 image turning at 4 rad/s for 30 ms; beyond, the edge repeats)
FOVEA_MARGIN_PX: Final = 16
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
class Fovea:
    """The narrow pinhole ``render_cam`` (intrinsics ``K_render``) that renders the centre of a wide
    lens at its own focal length: the output pixels ``mask`` (bool, of the box ``rows`` x ``cols``)
    sample it (``float_maps``, float, of the box's shape, for motion blur).  The lens's two renders
    are resampled at once from an *atlas*: the wide render at its top left, the fovea's right of it
    from column ``col0``."""

    render_cam: Camera
    K_render: NDArray[np.float64]
    rows: slice
    cols: slice
    mask: NDArray[np.bool_] = field(repr=False)
    float_maps: tuple[NDArray[np.float32], NDArray[np.float32]] = field(repr=False)
    col0: int = 0
    wide_rows: int = 0
    atlas_shape: tuple[int, int] = (0, 0)

    def atlas(self, dtype: Any = np.uint8) -> NDArray[Any]:
        """An uninitialised atlas (what neither render covers is never sampled)."""
        return np.empty(self.atlas_shape, dtype)

    def wide_part(self, atlas: NDArray[Any]) -> NDArray[Any]:
        """The wide render's place in ``atlas`` (a view)."""
        return atlas[: self.wide_rows, : self.col0]

    def part(self, atlas: NDArray[Any]) -> NDArray[Any]:
        """The fovea's place in ``atlas`` (a view)."""
        return atlas[: self.render_cam.height, self.col0: self.col0 + self.render_cam.width]


@dataclass
class RenderPlan:
    """How to render one camera: the pinhole ``render_cam`` (a Camera of the render's size and
    field of view, same mount) and the ``cv2.remap`` maps from it to the lens's image
    (None for a pinhole lens: the render is the image; fixed point, and ``float_maps`` the
    same in float for motion blur); a wide lens's centre also comes from its ``fovea``."""

    lens: Lens
    render_cam: Camera
    K_render: NDArray[np.float64]
    maps: tuple[Any, Any] | None = field(default=None, repr=False)
    float_maps: tuple[NDArray[np.float32], NDArray[np.float32]] | None = field(default=None, repr=False)
    fovea: Fovea | None = None

    def sample_maps(self) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Where each output pixel samples the render (float (H, W) maps; the pixel grid for a pinhole)."""
        if self.float_maps is None:
            gu, gv = np.meshgrid(np.arange(self.render_cam.width, dtype=np.float32),
                                 np.arange(self.render_cam.height, dtype=np.float32))
            self.float_maps = (gu, gv)
        return self.float_maps

    def apply(self, render: NDArray[Any], fovea: NDArray[Any] | None = None,
              interpolation: int = cv2.INTER_LINEAR) -> NDArray[Any]:
        """The lens's image of a pinhole ``render`` (H_r, W_r) of :attr:`render_cam` and, when the
        plan has a fovea, of ``fovea``, the render of its :attr:`Fovea.render_cam` (or ``render``
        is the atlas holding both, :meth:`Fovea.atlas`: no copy)."""
        if self.maps is None:
            return render
        fv = self.fovea
        if fv is not None and render.shape[:2] != fv.atlas_shape:
            if fovea is None:
                raise ValueError(f"camera {self.render_cam.name!r}: the plan has a fovea, its render is needed")
            atlas = fv.atlas(render.dtype)
            fv.wide_part(atlas)[...] = render
            fv.part(atlas)[...] = fovea
            render = atlas
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
    xy_img = xy.reshape(cam.height, cam.width, 2)
    ax, ay = float(np.abs(xy[:, 0]).max()), float(np.abs(xy[:, 1]).max())
    # the pybullet frustum is symmetric: an even size about the centre, room for bilinear neighbours
    npx = cam.width * cam.height
    if (2 * ax * f) * (2 * ay * f) <= SINGLE_RENDER_RATIO * npx:
        fw, t = f, 0.0
    else:
        fw, t = _choose_renders(xy_img, f, (ax, ay), npx)
    render_cam, k_r = _pinhole(cam, fw, ax, ay, RENDER_MARGIN_PX)
    map_x = (k_r[0, 0] * xy[:, 0] + k_r[0, 2]).reshape(cam.height, cam.width).astype(np.float32)
    map_y = (k_r[1, 1] * xy[:, 1] + k_r[1, 2]).reshape(cam.height, cam.width).astype(np.float32)
    fovea = None
    atlas_x, atlas_y = map_x, map_y
    if t > 0:
        fovea = _fovea(cam, xy_img, f, min(t, ax), min(t, ay), render_cam)
        atlas_x, atlas_y = map_x.copy(), map_y.copy()
        fmx, fmy = fovea.float_maps
        np.copyto(atlas_x[fovea.rows, fovea.cols], fmx + np.float32(fovea.col0), where=fovea.mask)
        np.copyto(atlas_y[fovea.rows, fovea.cols], fmy, where=fovea.mask)
    fixed = cv2.convertMaps(atlas_x, atlas_y, cv2.CV_16SC2)  # fixed point: ~2x faster remap, 1/32 px steps
    return RenderPlan(lens, render_cam, k_r, (fixed[0], fixed[1]), (map_x, map_y), fovea)


def _pinhole(cam: Camera, f: float, ax: float, ay: float, margin: int) -> tuple[Camera, NDArray[np.float64]]:
    """A pinhole render of ``cam``'s mount at focal length ``f`` (px) covering normalised |x| <= ax,
    |y| <= ay with ``margin`` px to spare, and its intrinsics (3, 3)."""
    w = 2 * math.ceil(ax * f + margin)
    h = 2 * math.ceil(ay * f + margin)
    render_cam = msgspec.structs.replace(cam, width=w, height=h,
                                         hfov_deg=math.degrees(2.0 * math.atan(w / (2.0 * f))))
    fx, fy, cx, cy = intrinsics(render_cam)
    return render_cam, np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def sparsest_sampling(xy: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per output pixel of the undistorted normalised coordinates ``xy`` (H, W, 2): the smaller
    singular value of d(xy)/d(u, v), i.e. how far (normalised units) one output pixel reaches in
    the direction the image is sparsest; a pinhole of focal f samples it at f times that."""
    (a, c), (b, d) = np.moveaxis(np.gradient(xy, axis=1), -1, 0), np.moveaxis(np.gradient(xy, axis=0), -1, 0)
    s = a * a + b * b + c * c + d * d  # a 2x2 matrix's singular values in closed form (an SVD per pixel is 10x slower)
    det = a * d - b * c
    return np.asarray(np.sqrt(np.maximum(s - np.sqrt(np.maximum(s * s - 4.0 * det * det, 0.0)), 0.0) / 2.0),
                      np.float64)


def _choose_renders(xy: NDArray[np.float64], f: float, extent: tuple[float, float],
                    npx: int) -> tuple[float, float]:
    """The wide render's focal length (px) and the fovea's half-width t (normalised, max(|x|, |y|) <= t;
    0 for none) with the fewest pixels in all such that the wide render samples every output pixel
    outside the fovea at >= :data:`MIN_SAMPLING` within :data:`MAX_RENDER_PIXELS_RATIO` (when nothing
    does, one render shrunk to :data:`SINGLE_RENDER_RATIO`)."""
    ax, ay = extent
    sparse = sparsest_sampling(xy).ravel()
    cheb = np.maximum(np.abs(xy[..., 0]), np.abs(xy[..., 1])).ravel()
    order = np.argsort(sparse)
    reach = np.maximum.accumulate(cheb[order])  # the fovea needed when the k sparsest pixels are too sparse
    sorted_sparse = sparse[order]
    best: tuple[float, float, float] | None = None
    for s in np.linspace(0.1, 1.0, 91):
        fw = f * float(s)
        k = int(np.searchsorted(sorted_sparse, MIN_SAMPLING / fw))
        t = float(reach[k - 1]) if k else 0.0
        tx, ty = min(t, ax), min(t, ay)
        cost = (2 * ax * fw) * (2 * ay * fw) + RENDER_FIXED_PX
        if k:
            cost += (2 * tx * f + 2 * FOVEA_MARGIN_PX) * (2 * ty * f + 2 * FOVEA_MARGIN_PX) + RENDER_FIXED_PX
        if cost <= MAX_RENDER_PIXELS_RATIO * npx and (best is None or cost < best[0]):
            best = (cost, fw, t)
    if best is None:  # as before fovea renders: one render at the single-render cap
        return f * math.sqrt(SINGLE_RENDER_RATIO * npx / ((2 * ax * f) * (2 * ay * f))), 0.0
    return best[1], best[2]


def _fovea(cam: Camera, xy: NDArray[np.float64], f: float, tx: float, ty: float, wide: Camera) -> Fovea:
    """The fovea of a lens (undistorted normalised ``xy`` (H, W, 2)) covering |x| <= tx, |y| <= ty,
    right of the ``wide`` render in their atlas."""
    render_cam, k_f = _pinhole(msgspec.structs.replace(cam, name=f"{cam.name}/fovea"), f, tx, ty, FOVEA_MARGIN_PX)
    inside = (np.abs(xy[..., 0]) <= tx) & (np.abs(xy[..., 1]) <= ty)
    rows_any, cols_any = np.flatnonzero(inside.any(axis=1)), np.flatnonzero(inside.any(axis=0))
    rows = slice(int(rows_any[0]), int(rows_any[-1]) + 1)
    cols = slice(int(cols_any[0]), int(cols_any[-1]) + 1)
    box = xy[rows, cols]
    # the box's corners outside the fovea fall outside its render (the atlas takes the mask only); not
    # clipped, or the maps would fold there and the blur would measure an endless streak across the fold
    map_x = (k_f[0, 0] * box[..., 0] + k_f[0, 2]).astype(np.float32)
    map_y = (k_f[1, 1] * box[..., 1] + k_f[1, 2]).astype(np.float32)
    shape = (max(wide.height, render_cam.height), wide.width + render_cam.width)
    return Fovea(render_cam, k_f, rows, cols, np.ascontiguousarray(inside[rows, cols]), (map_x, map_y),
                 col0=wide.width, atlas_shape=shape, wide_rows=wide.height)
