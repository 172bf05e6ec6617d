"""Pose of an observed tag cube (or landmark tag) from one camera or a rig (pure code).

This is the seed-003 bundle adjustment (DESIGN.md section 5): every visible corner
of one target, over every camera that sees it, in one least-squares problem with
the target's geometry known.

Frames: the result is ``T_base_target``, the pose of the observed robot's BASE
frame (on the floor, x forward, y left, z up) -- or of a landmark tag's frame
(origin at the plate centre, +x the tag's outward normal, z up; see
``world.assets.landmark_mesh``) -- in the OBSERVER's base frame.  Cameras are
OpenCV pinholes (pixel centres at integer coordinates, no distortion) mounted at
``T_base_cam``.  Metres, radians, pixels.

Algorithm per target (``c0``: the camera that sees the target's largest tag):

1. Start: ``cv2.solvePnPGeneric(SOLVEPNP_IPPE_SQUARE)`` on the largest tag gives the
   two poses a small square cannot tell apart (normal mirrored about the line of
   sight).  When IPPE's second pose is not that mirror (it degenerates on small,
   nearly frontal tags) the mirror is rebuilt, so the ambiguity is never lost.
2. Refine: Gauss-Newton on theta = (rvec, tvec) of ``T_c0_target`` over every corner
   of the target in every view, with ``cv2.projectPoints`` Jacobians (other cameras
   chained through their fixed ``T_cam_c0``).  One tag: the better start is refined,
   the other kept as IPPE left it.  Several tags: the start that throws the other
   tags' corners off is dropped unrefined.
3. Choose: candidates are scored by a negative log-likelihood -- reprojection
   residuals over ``choice_sigma_px``, the ground-robot prior (both robots stand on
   the floor: the target's base near z = 0 -- a landmark near its known height --
   with little roll/pitch) and the caller's prior pose if any.  The best plausible
   one wins.
4. Covariance: ``s^2 (J^T J)^-1`` with ``s = max(pixel_sigma_px, residual-based
   estimate)``, propagated to (x, y, yaw) of ``T_base_target``; when the other
   candidate of the two-fold ambiguity is still plausible its spread is added with
   its weight (moment-matched two-component mixture), so a possibly flipped yaw
   says so in its covariance instead of being confidently wrong.
5. Reject (counted in :attr:`CubePoseEstimator.rejects`): reprojection RMS above
   ``max_rms_px`` ("reprojection"); height or roll/pitch out of tolerance beyond
   the estimate's own 3-sigma, or a tag seen from behind ("implausible"); too few
   or collapsed corners, a singular Jacobian ("degenerate"); one tag ID twice in
   one image ("duplicate").
6. Planar (the default for robots, ``planar=True``): both robots stand upright on
   one floor, so once the 6-DOF stage has found a plausible pose (step 5 still
   rejects a target its 6-DOF fit puts off the floor or tilted), (x, y, yaw) of
   ``T_base_target`` is re-solved with z = 0 and roll = pitch = 0
   (:mod:`agents.planar`: Gauss-Newton over every corner of every camera, each at
   its ``T_base_cam``) from the plausible 6-DOF pose(s) -- one tag: from the better
   IPPE pose and from the pose with the tag's normal mirrored about the horizontal
   line of sight, the two-fold ambiguity in the plane.  The lowest score wins (a
   distinct runner-up is folded into the covariance as in step 4), its reprojection
   RMS must stay under ``max_rms_px``, and its covariance is the planar
   ``s^2 (J^T J)^-1``.  What it buys depends on the camera's height above the tag centres:
   a camera at their height (the default mount, z = 0.22 m = the cube centre) sees
   the two-fold ambiguity as a pure yaw mirror the planar model cannot remove, and
   the range comes from the tag's size alone, so yaw and position stay as the
   6-DOF ones; a camera above (or below) them gets the range from the elevation
   angle and loses the mirror (0.68 m above: position ~5x, p90 yaw ~2x better at
   2.5-4 m; tests/unit/test_cubepose.py).  Landmarks stay 6-DOF unless
   ``planar_landmarks`` (z fixed at the scenario's height).

Cost: the single-camera path is a handful of OpenCV calls per target (IPPE,
Rodrigues, projectPoints, solve, invert) plus two or three evaluations of the
3-parameter planar model (a dozen numpy operations each); bench/detect.py measures
it against a bare AprilTag detect call.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Any, Final, cast

import cv2
import numpy as np
from numpy.typing import NDArray

from agents import planar
from agents.detect import TagDetection, TagMap, TargetKind
from agents.planar import PlanarProblem
from protocol import tags
from protocol.geometry import Mat, matrix_to_pose3, pose3_to_matrix
from protocol.messages import CameraImage, RelativeObservation
from protocol.scenario import Scenario

#: Thickness of a landmark plate; the tag is painted on its +x face, at x = +thickness/2.
#: Mirrors the default of ``world.assets.landmark_mesh`` (tests/unit/test_cubepose.py pins it).
LANDMARK_PLATE_THICKNESS_M: Final = 0.01

_EYE4: Final = np.eye(4)
_Arr = NDArray[Any]  # float64 arrays that come out of OpenCV (its stubs do not say so)

# IPPE_SQUARE wants the corners TL, TR, BR, BL; the contract order is TR, TL, BL, BR.
_TO_IPPE: Final = np.array([1, 0, 3, 2])
# a losing candidate is kept (for the ambiguity term, weight exp(-gap/2)) only within this score gap
_AMBIGUITY_GAP: Final = 20.0
# a single tag's winning start gets this many Gauss-Newton steps: one takes ~90% of the residual
# decrease IPPE leaves, and the valley along the two-fold ambiguity is too flat for more to pay
_SINGLE_TAG_ITERATIONS: Final = 1
# IPPE's second solution counts as the mirror of its first if their normals agree within 20 deg;
# a rebuilt mirror starts off the residual minimum and gets a few more steps
_MIRROR_COS: Final = math.cos(math.radians(20.0))
_MIRROR_ITERATIONS: Final = 3
# one-camera planar problems kept per (tags, camera): the part that does not depend on the pixels
_PLANAR_CACHE_SIZE: Final = 1024
# the planar covariance's pixel sigma over pixel_sigma_px: see CubePoseEstimator
_PLANAR_NOISE: Final = 1.35


@dataclass(frozen=True)
class CameraModel:
    """A pinhole camera on the observer: ``K`` (3, 3) in OpenCV's pixel convention, no
    distortion; ``T_base_cam`` (4, 4) pose of the optical frame (z forward, x right,
    y down) in the observer's base frame; image size in pixels."""

    name: str
    K: Mat
    T_base_cam: Mat
    width: int
    height: int
    T_cam_base: Mat = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", np.ascontiguousarray(self.K, np.float64))
        object.__setattr__(self, "T_base_cam", np.ascontiguousarray(self.T_base_cam, np.float64))
        object.__setattr__(self, "T_cam_base", np.linalg.inv(self.T_base_cam))

    @classmethod
    def from_message(cls, msg: CameraImage) -> CameraModel:
        """Intrinsics and mount of a :class:`~protocol.messages.CameraImage`."""
        k = np.array([[msg.fx_px, 0.0, msg.cx_px], [0.0, msg.fy_px, msg.cy_px], [0.0, 0.0, 1.0]])
        return cls(msg.camera, k, pose3_to_matrix(msg.mount), msg.width, msg.height)


@dataclass(frozen=True)
class PoseEstimate:
    """One target's pose in the observer's base frame.

    ``T_base_target`` (4, 4): observed robot's base frame (or landmark tag frame) in
    the observer's base frame; ``(x_m, y_m, yaw_rad)`` its SE(2) projection
    (yaw = atan2(R10, R00)); ``cov`` (3, 3) covariance of (x_m, y_m, yaw_rad);
    ``reprojection_rms_px`` over the ``n_corners`` corners used; ``ambiguity`` the
    weight of the losing two-fold solution folded into ``cov`` (0 = none).
    """

    target_kind: TargetKind
    target_id: int
    T_base_target: Mat
    x_m: float
    y_m: float
    yaw_rad: float
    cov: Mat
    reprojection_rms_px: float
    tag_ids: tuple[int, ...]
    cameras: tuple[str, ...]
    n_corners: int
    ambiguity: float = 0.0

    def to_message(self, observer_id: int, *, seq: int, stamp_ns: int) -> RelativeObservation:
        """The wire form; a rig's camera names are joined with '+'."""
        return RelativeObservation(
            seq=seq, stamp_ns=stamp_ns, robot_id=observer_id, target_kind=self.target_kind,
            target_id=self.target_id, x_m=self.x_m, y_m=self.y_m, yaw_rad=self.yaw_rad,
            cov=tuple(float(v) for v in self.cov.ravel()), pose=matrix_to_pose3(self.T_base_target),
            reprojection_rms_px=self.reprojection_rms_px, tag_ids=self.tag_ids, camera="+".join(self.cameras))


@dataclass(frozen=True)
class _TagGeom:
    kind: TargetKind
    target_id: int
    obj: NDArray[np.float64]  # (4, 3) corners in the target frame, contract order
    ippe_obj: NDArray[np.float64]  # (4, 3) corners in the tag's own frame, IPPE order
    T_tag_target: Mat  # (4, 4)
    centre: NDArray[np.float64]  # (3,) tag centre in the target frame
    normal: NDArray[np.float64]  # (3,) outward normal in the target frame


@dataclass(slots=True)
class _View:
    """The corners of one target in one camera; ``T_cam_c0`` (4, 4) maps the start
    camera's optical frame into this camera's; ``tag_ids`` in the order of the corners."""

    cam: CameraModel
    obj: NDArray[np.float64]  # (M, 3) target frame
    img: NDArray[np.float64]  # (M, 2) pixels
    T_cam_c0: Mat
    tag_ids: tuple[int, ...]


@dataclass(slots=True)
class _Solution:
    """A candidate pose: T_c0_target (4, 4), its theta = (rvec, tvec) and the residuals'
    Jacobian (2M, 6) w.r.t. theta (None until needed: an unrefined single-tag alternative),
    sum of squared residuals (px^2), ``T_base_target`` with its (x, y, yaw), height z and
    R22 (cos of tilt), and its score."""

    T_c0_target: Mat
    rvec: _Arr | None
    tvec: _Arr | None
    jac: _Arr | None
    sse: float
    T_base_target: Mat
    se2: tuple[float, float, float]
    z: float
    r22: float
    cost: float

    def theta(self) -> tuple[_Arr, _Arr]:
        if self.rvec is None or self.tvec is None:
            self.rvec, self.tvec = cv2.Rodrigues(self.T_c0_target[:3, :3])[0].ravel(), self.T_c0_target[:3, 3].copy()
        return self.rvec, self.tvec


def _rt_to_matrix(rvec: NDArray[Any], tvec: NDArray[Any]) -> Mat:
    t = _EYE4.copy()
    t[:3, :3] = cv2.Rodrigues(rvec)[0]
    t[:3, 3] = tvec.reshape(3)
    return t


def _quad_area(c: NDArray[np.float64]) -> float:
    """Signed area (px^2) of a quadrilateral (4, 2) from its diagonals: positive for the
    contract order TR, TL, BL, BR of a tag seen from the front (counter-clockwise on
    screen), negative for one seen from behind (mirrored order)."""
    (x0, y0), (x1, y1), (x2, y2), (x3, y3) = c.tolist()
    return 0.5 * ((x1 - x3) * (y0 - y2) - (x0 - x2) * (y1 - y3))


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def output_jacobian(T_base_cam: Mat, rvec: NDArray[Any], tvec: NDArray[Any]) -> tuple[Mat, NDArray[np.float64]]:
    """``T_base_target`` of ``T_cam_target = (rvec, tvec)`` seen from a camera at ``T_base_cam``,
    and the (6, 6) Jacobian w.r.t. theta = (rvec, tvec) of its (x, y, yaw, z, s_x, s_y),
    where yaw = atan2(R10, R00) and (s_x, s_y) = (R02, R12), the horizontal part of the
    target's z axis (sin of its tilt times the tilt direction).  Metres, radians."""
    r_ct, jr = cv2.Rodrigues(rvec)  # jr[i] = d vec_rowmajor(R) / d rvec_i
    r_bc = T_base_cam[:3, :3]
    t_bt = np.eye(4)
    m = r_bc @ r_ct
    t_bt[:3, :3] = m
    t_bt[:3, 3] = r_bc @ np.ravel(tvec) + T_base_cam[:3, 3]
    dcol0 = r_bc @ jr[:, 0::3].T  # (3 rows of M, 3 rvec components): d M[:, 0] / d rvec
    dcol2 = r_bc @ jr[:, 2::3].T
    g = np.zeros((6, 6))
    g[0:2, 3:6] = r_bc[0:2]
    den = m[0, 0] ** 2 + m[1, 0] ** 2
    g[2, 0:3] = (m[0, 0] * dcol0[1] - m[1, 0] * dcol0[0]) / den
    g[3, 3:6] = r_bc[2]
    g[4:6, 0:3] = dcol2[0:2]
    return t_bt, g


def _se2_jacobian(T_base_cam: Mat, T_base_target: Mat, rvec: NDArray[Any]) -> NDArray[np.float64]:
    """The first three rows of :func:`output_jacobian`: (x, y, yaw) w.r.t. (rvec, tvec)."""
    jr = cv2.Rodrigues(rvec)[1]
    r_bc, m = T_base_cam[:3, :3], T_base_target
    dcol0 = r_bc[0:2] @ jr[:, 0::3].T
    g = np.zeros((3, 6))
    g[0:2, 3:6] = r_bc[0:2]
    g[2, 0:3] = (m[0, 0] * dcol0[1] - m[1, 0] * dcol0[0]) / (m[0, 0] ** 2 + m[1, 0] ** 2)
    return g


class CubePoseEstimator:
    """Bundle adjustment of observed tag cubes and landmark tags, one camera or a rig.

    ``pixel_sigma_px`` is the corner noise (1 sigma per axis) behind the covariance.
    Measured on our renders (AprilTag 3, 0.5-5 m, 320x240 and 640x480, 60 deg HFOV):
    corners scatter 0.25-0.33 px RMS per axis about the projected truth, whatever
    the tag's size; with 0.3 px the NEES of (x, y, yaw) averages 2.5-3.4 over
    several hundred random views (expected: 3; tests/unit/test_cubepose.py asserts
    it).  ``choice_sigma_px`` (>= ``pixel_sigma_px``) scales the residuals when the
    two-fold ambiguity is weighed: render errors are correlated within a tag, so a
    wrong flip can fit a small tag slightly better than the truth, and judging
    that with 0.3 px made some flips look certain (NEES ~400); 0.8 px keeps
    them flagged.  ``max_rms_px``, ``z_tol_m`` and ``tilt_tol_rad`` gate the result
    (see :meth:`_plausible`); ``prior_sigma_xy_m``/``prior_sigma_yaw_rad`` weigh a
    caller's prior pose when choosing between the two-fold solutions.

    ``planar`` (default) answers with the planar fit of step 6 of the module
    docstring, ``planar=False`` with the 6-DOF one; ``planar_landmarks`` extends it
    to landmarks.  The planar covariance uses ``1.35 * pixel_sigma_px``: render
    errors are correlated within a tag (a near-vertical edge shifts as a whole,
    corr ~0.9, so its width and horizontal position scatter ~1.4x what independent
    corners imply), which the 6-DOF fit partly absorbs into z/roll/pitch and the
    planar fit cannot.  Measured on the views of tests/unit/test_cubepose.py: NEES
    of (x, y, yaw) 2.1-3.5 for a camera at the tag's height, 0.4-0.8 (conservative)
    for one 0.68 m above it, whose corner errors are smaller along the elevation
    that then fixes the range.
    """

    def __init__(self, scenario: Scenario, pixel_sigma_px: float = 0.3, max_rms_px: float = 2.0,
                 z_tol_m: float = 0.08, tilt_tol_rad: float = 0.15, *, choice_sigma_px: float = 0.8,
                 prior_sigma_xy_m: float = 0.25, prior_sigma_yaw_rad: float = 0.35, max_iterations: int = 10,
                 planar: bool = True, planar_landmarks: bool = False) -> None:
        if pixel_sigma_px <= 0:
            raise ValueError("pixel_sigma_px must be positive")
        self.scenario = scenario
        self.planar = planar
        # the ablation of a per-tag PnP: keep only the largest face of each target
        self.single_tag = scenario.agent.pose_method == "single_tag"
        self.planar_landmarks = planar_landmarks
        self._planar_cache: dict[tuple[tuple[int, ...], bytes, bytes], PlanarProblem] = {}
        self.pixel_sigma_px = pixel_sigma_px
        self.choice_sigma_px = max(choice_sigma_px, pixel_sigma_px)
        self.max_rms_px = max_rms_px
        self.z_tol_m = z_tol_m
        self.tilt_tol_rad = tilt_tol_rad
        self.prior_sigma_xy_m = prior_sigma_xy_m
        self.prior_sigma_yaw_rad = prior_sigma_yaw_rad
        self.max_iterations = max_iterations
        self.rejects: Counter[str] = Counter()
        self.tag_map = TagMap.from_scenario(scenario)
        self._cos_tilt_tol = math.cos(tilt_tol_rad)
        # Gauss-Newton has converged once a step would buy less than this (px^2, 0.01 in chi^2: the pose
        # then moves by ~0.1 sigma at most); saves the evaluations that only confirm convergence
        self._tiny_px2 = 1e-2 * pixel_sigma_px**2
        # the planar fit's last step, below 0.1 in chi^2 (~0.3 sigma), is taken blind (agents.planar.solve)
        self._planar_tiny_px2 = 1e-1 * pixel_sigma_px**2
        self._geom: dict[int, _TagGeom] = {}
        self._expected_z: dict[tuple[str, int], float] = {}
        r = scenario.robot
        for rid in scenario.robot_ids:
            self._expected_z[("robot", rid)] = 0.0
            for face, tid in zip(tags.Face, scenario.tag_ids(rid), strict=True):
                n, u, rr = tags.face_axes(face)
                centre = n * (r.cube_edge_m / 2.0) + np.array([0.0, 0.0, r.cube_center_z_m])
                self._geom[tid] = self._tag_geom("robot", rid, centre, n, u, rr, scenario.tags.size_m)
        for lm in scenario.landmarks:
            self._expected_z[("landmark", lm.id)] = lm.z_m
            n, u, rr = tags.face_axes(tags.Face.FRONT)
            self._geom[lm.id] = self._tag_geom("landmark", lm.id, n * (LANDMARK_PLATE_THICKNESS_M / 2.0), n, u, rr,
                                               lm.size_m)

    @staticmethod
    def _tag_geom(kind: TargetKind, target_id: int, centre: NDArray[np.float64], n: NDArray[np.float64],
                  u: NDArray[np.float64], r: NDArray[np.float64], size: float) -> _TagGeom:
        obj = tags.square_corners(centre, u, r, size)
        t_target_tag = np.eye(4)
        t_target_tag[:3, :3] = np.stack([r, u, n], axis=1)  # tag frame: x right, y up, z out of the face
        t_target_tag[:3, 3] = centre
        h = size / 2.0
        ippe = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
        return _TagGeom(kind, target_id, obj, ippe, np.asarray(np.linalg.inv(t_target_tag), np.float64),
                        np.asarray(centre, np.float64), np.asarray(n, np.float64))

    def object_points(self, tag_id: int) -> NDArray[np.float64] | None:
        """(4, 3) corners of ``tag_id`` in its target's frame (metres, contract order), or None."""
        g = self._geom.get(tag_id)
        return None if g is None else g.obj.copy()

    # ------------------------------------------------------------------ public
    def estimate(self, views: list[tuple[CameraModel, list[TagDetection]]],
                 priors: dict[tuple[str, int], tuple[float, float, float]] | None = None) -> list[PoseEstimate]:
        """Poses of every target seen in ``views`` (one synchronised frame per camera).

        Detections of tags that belong to nothing in the scenario are ignored (the
        caller counts them with :class:`~agents.detect.TagMap`).  ``priors`` maps
        ``(kind, target_id)`` to a predicted (x_m, y_m, yaw_rad) of the target in the
        observer's base frame; it only helps choose between the two-fold solutions.
        Rejected targets are counted in :attr:`rejects` by reason.
        """
        groups: dict[tuple[str, int], list[tuple[int, _TagGeom, TagDetection]]] = {}
        for vi, (_, dets) in enumerate(views):
            for d in dets:
                g = self._geom.get(d.tag_id)
                if g is not None:
                    groups.setdefault((g.kind, g.target_id), []).append((vi, g, d))
        out = []
        for key, members in groups.items():
            if self.single_tag and len(members) > 1:
                members = [max(members, key=lambda m: _quad_area(m[2].corners))]
            est = self._estimate_target(key, members, views, None if priors is None else priors.get(key))
            if est is not None:
                out.append(est)
        return out

    # ------------------------------------------------------------------ internals
    def _reject(self, reason: str) -> None:
        self.rejects[reason] += 1

    def _views(self, members: list[tuple[int, _TagGeom, TagDetection]],
               views: list[tuple[CameraModel, list[TagDetection]]]) -> tuple[list[_View], _TagGeom, TagDetection]:
        """The target's corners per camera, the start camera (largest tag) first, and the
        largest tag's geometry and detection; raises ValueError(reason) on a bad set."""
        if len(members) == 1:
            vi, g, d = members[0]
            c = d.corners
            if c.shape != (4, 2) or not np.isfinite(c).all():
                raise ValueError("degenerate")
            area = _quad_area(c)
            if area < 4.0:
                # a tag is only decodable from its front: clockwise corners mean a fake or garbled set
                raise ValueError("implausible" if area < -4.0 else "degenerate")
            return [_View(views[vi][0], g.obj, c, _EYE4, (d.tag_id,))], g, d
        per_cam: dict[int, list[tuple[_TagGeom, TagDetection]]] = {}
        best_area, start = -1.0, members[0]
        for m in members:
            vi, g, d = m
            items = per_cam.setdefault(vi, [])
            if any(other.tag_id == d.tag_id for _, other in items):  # one tag twice in one image: a false decode
                raise ValueError("duplicate")
            items.append((g, d))
            c = d.corners
            if c.shape != (4, 2) or not np.isfinite(c).all():
                raise ValueError("degenerate")
            area = _quad_area(c)
            if area < -4.0:
                raise ValueError("implausible")
            if area > best_area:
                best_area, start = area, m
        if not best_area >= 4.0:
            raise ValueError("degenerate")
        c0 = views[start[0]][0]
        out: list[_View] = []
        for vi, items in per_cam.items():
            img = np.ascontiguousarray(np.concatenate([d.corners for _, d in items]), np.float64)
            obj = np.concatenate([g.obj for g, _ in items])
            cam = views[vi][0]
            ids = tuple(d.tag_id for _, d in items)
            if vi == start[0]:
                out.insert(0, _View(cam, obj, img, _EYE4, ids))
            else:
                out.append(_View(cam, obj, img, cam.T_cam_base @ c0.T_base_cam, ids))
        return out, start[1], start[2]

    def _estimate_target(self, key: tuple[str, int], members: list[tuple[int, _TagGeom, TagDetection]],
                         views: list[tuple[CameraModel, list[TagDetection]]],
                         prior: tuple[float, float, float] | None) -> PoseEstimate | None:
        try:
            vlist, sg, sd = self._views(members, views)
        except ValueError as exc:
            self._reject(str(exc))
            return None
        c0 = vlist[0].cam
        try:
            n, rvecs, tvecs, errs = cv2.solvePnPGeneric(sg.ippe_obj, np.ascontiguousarray(sd.corners[_TO_IPPE]),
                                                        c0.K, None, flags=cv2.SOLVEPNP_IPPE_SQUARE)
        except cv2.error:
            n = 0
        if n == 0:
            self._reject("degenerate")
            return None
        n_corners = sum(len(v.obj) for v in vlist)
        z_exp = self._expected_z.get(key, 0.0)
        t_bc = c0.T_base_cam
        t_tags = [_rt_to_matrix(rv, tv) for rv, tv in zip(rvecs, tvecs, strict=True)]
        sse_ippe = [e * e * 8.0 for e in errs.ravel().tolist()]  # IPPE's error: RMS of the 8 coordinates
        starts = [self._candidate(t @ sg.T_tag_target, t_bc, sse, z_exp, prior)
                  for t, sse in zip(t_tags, sse_ippe, strict=True)]
        sols: list[_Solution] = []
        planar_fit = self.planar and (sg.kind == "robot" or self.planar_landmarks)
        if n_corners == 4 and planar_fit:
            # one tag, planar answer: IPPE's poses only gate plausibility and seed the planar fit,
            # which weighs the tag's mirror itself (see _planar)
            sols = sorted(starts, key=lambda c: c.cost)
        elif n_corners == 4:
            mirror = self._mirror_start(vlist, t_tags, sg, z_exp, prior)
            if mirror is not None:
                starts = [starts[0], mirror]
            # one tag: the better start is refined; the other only matters through the ambiguity
            # term, so it stays as IPPE left it, and is dropped when the gap is large
            starts.sort(key=lambda c: c.cost)
            first = starts[0]
            sol = self._solve(vlist, *first.theta(), z_exp, prior, _SINGLE_TAG_ITERATIONS)
            if sol is not None:
                sols.append(sol)
            sols += [c for c in starts[1:] if c.cost - first.cost < _AMBIGUITY_GAP]
        else:
            # several tags: the wrong IPPE start throws the other tags' corners far off; refine the
            # starts whose residuals are not clearly worse than the best one's
            evals = [self._residuals(vlist, *c.theta()) for c in starts]
            sse0 = [float(r0 @ r0) for r0, _ in evals]
            lim = 3.0 * min(sse0) + _AMBIGUITY_GAP * self.choice_sigma_px**2
            for c, sse, ev in zip(starts, sse0, evals, strict=True):
                if sse <= lim:
                    sol = self._solve(vlist, *c.theta(), z_exp, prior, self.max_iterations, ev)
                    if sol is not None:
                        sols.append(sol)
        if not sols:
            self._reject("degenerate")
            return None
        sols.sort(key=lambda c: c.cost)
        plausible: list[tuple[_Solution, Mat | None]] = []
        constrained = False
        for sol in sols:
            cov = None
            if abs(sol.z - z_exp) > self.z_tol_m or sol.r22 < self._cos_tilt_tol:
                cov = self._cov_theta(sol, vlist, n_corners)
                if cov is None or not self._plausible(sol, c0, z_exp, cov):
                    constrained = constrained or cov is not None
                    continue
            constrained = True
            plausible.append((sol, cov))
            if len(plausible) == 2:
                break
        if not plausible:
            self._reject("implausible" if constrained else "degenerate")
            return None
        tag_ids = (sd.tag_id,) if len(members) == 1 else tuple(sorted({d.tag_id for _, _, d in members}))
        cameras = (c0.name,) if len(vlist) == 1 else tuple(v.cam.name for v in vlist)
        if planar_fit:
            # one tag: the best plausible pose (the mirror comes later); several: the 6-DOF stage has
            # already dropped or refined the start that throws the other tags off
            seeds = [s.se2 for s, _ in plausible[:1 if n_corners == 4 else 2]]
            return self._planar(vlist, seeds, z_exp, prior, sg, tag_ids, cameras, n_corners)
        best, cov_theta = plausible[0]
        rms = math.sqrt(best.sse / n_corners)
        if rms > self.max_rms_px:
            self._reject("reprojection")
            return None
        if cov_theta is None:
            cov_theta = self._cov_theta(best, vlist, n_corners)
            if cov_theta is None:
                self._reject("degenerate")
                return None
        g3 = _se2_jacobian(t_bc, best.T_base_target, best.theta()[0])
        cov = g3 @ cov_theta @ g3.T
        ambiguity = 0.0
        if len(plausible) > 1:
            alt = plausible[1][0]
            d = (alt.se2[0] - best.se2[0], alt.se2[1] - best.se2[1], _wrap(alt.se2[2] - best.se2[2]))
            # both refined to the same pose (several faces): no ambiguity left
            if abs(d[2]) > 1e-3 or math.hypot(d[0], d[1]) > 1e-3:
                ambiguity = 1.0 / (1.0 + math.exp(min(50.0, 0.5 * (alt.cost - best.cost))))
                cov += ambiguity * np.outer(d, d)
        c00, c11, c22 = cov[0, 0], cov[1, 1], cov[2, 2]
        # G Sigma G^T of finite factors: a finite positive diagonal means a usable covariance
        if not (c00 > 0.0 and c11 > 0.0 and c22 > 0.0 and math.isfinite(c00 + c11 + c22)):
            self._reject("degenerate")
            return None
        return PoseEstimate(
            target_kind=sg.kind, target_id=sg.target_id, T_base_target=best.T_base_target,
            x_m=best.se2[0], y_m=best.se2[1], yaw_rad=best.se2[2], cov=cov, reprojection_rms_px=rms,
            tag_ids=tag_ids, cameras=cameras, n_corners=n_corners, ambiguity=ambiguity)

    def _planar(self, vlist: list[_View], seeds: list[tuple[float, float, float]], z_exp: float,
                prior: tuple[float, float, float] | None, sg: _TagGeom, tag_ids: tuple[int, ...],
                cameras: tuple[str, ...], n_corners: int) -> PoseEstimate | None:
        """The planar answer (step 6 of the module docstring): Gauss-Newton on (x, y, yaw) at the
        known height from each distinct seed (plausible 6-DOF poses projected onto the floor); one
        tag: also from its mirror (:func:`agents.planar.mirror`).  The lowest score wins; a distinct
        runner-up within the ambiguity gap is folded into the covariance as in the 6-DOF path."""
        pr = self._planar_problem(vlist, z_exp)
        tiny = self._planar_tiny_px2
        fits: list[tuple[float, planar.PlanarFit]] = []
        for seed in seeds:
            fit = planar.solve(pr, seed, self.max_iterations, tiny)
            if fit is not None and not any(self._same(fit, f) for _, f in fits):
                fits.append((self._planar_cost(fit, prior), fit))
        if not fits:
            self._reject("degenerate")
            return None
        fits.sort(key=lambda cf: cf[0])
        if n_corners == 4:
            # one tag: the pose with its normal mirrored about the line of sight may explain the corners
            # about as well (at the tag's height exactly so) -- weigh it where the cost stands there (yaw
            # held: from there Gauss-Newton may roll back over the shallow ridge), and where it fits
            # better than the seed's minimum, that basin is the better one
            first = fits[0][1]
            mirrored = planar.mirror(first.p, sg.centre, sg.normal, vlist[0].cam.T_base_cam[:2, 3])
            # one Gauss-Newton step on (x, y), its SSE as predicted
            alt = None if mirrored is None else planar.solve(pr, mirrored, 1, math.inf, yaw_fixed=True)
            if alt is not None:
                alt_cost = self._planar_cost(alt, prior)
                if alt_cost < fits[0][0]:
                    full = planar.solve(pr, (alt.p[0], alt.p[1], alt.p[2]), self.max_iterations, tiny)
                    if full is not None:
                        alt, alt_cost = full, self._planar_cost(full, prior)
                if not self._same(alt, first):
                    fits = sorted([fits[0], (alt_cost, alt)], key=lambda cf: cf[0])
        cost, best = fits[0]
        rms = math.sqrt(best.sse / n_corners)
        if rms > self.max_rms_px:
            self._reject("reprojection")
            return None
        cov = planar.covariance(best, self.pixel_sigma_px * _PLANAR_NOISE)
        if cov is None:
            self._reject("degenerate")
            return None
        x, y, yaw = best.p.tolist()
        ambiguity = 0.0
        if len(fits) > 1 and fits[1][0] - cost < _AMBIGUITY_GAP:
            other = fits[1][1].p
            d = (other[0] - x, other[1] - y, _wrap(other[2] - yaw))
            ambiguity = 1.0 / (1.0 + math.exp(0.5 * (fits[1][0] - cost)))
            cov = cov + ambiguity * np.outer(d, d)
        return PoseEstimate(
            target_kind=sg.kind, target_id=sg.target_id, T_base_target=planar.matrix(x, y, yaw, z_exp), x_m=x,
            y_m=y, yaw_rad=yaw, cov=cov, reprojection_rms_px=rms, tag_ids=tag_ids, cameras=cameras,
            n_corners=n_corners, ambiguity=ambiguity)

    @staticmethod
    def _same(a: planar.PlanarFit, b: planar.PlanarFit) -> bool:
        """Whether two planar fits found the same minimum (1 mm, 1 mrad)."""
        return abs(_wrap(a.p[2] - b.p[2])) < 1e-3 and math.hypot(a.p[0] - b.p[0], a.p[1] - b.p[1]) < 1e-3

    def _planar_problem(self, vlist: list[_View], z_exp: float) -> PlanarProblem:
        """The planar problem of a target's views; in one camera (the common case) the part that
        only depends on the tags and the camera is reused."""
        if len(vlist) > 1:
            return PlanarProblem.make([(v.cam.K, v.cam.T_cam_base, v.obj, v.img) for v in vlist], z_exp)
        v = vlist[0]
        key = (v.tag_ids, v.cam.K.tobytes(), v.cam.T_base_cam.tobytes())
        pr = self._planar_cache.get(key)
        if pr is None:
            if len(self._planar_cache) >= _PLANAR_CACHE_SIZE:
                self._planar_cache.clear()
            pr = self._planar_cache[key] = PlanarProblem.make([(v.cam.K, v.cam.T_cam_base, v.obj, v.img)],
                                                                      z_exp)
        return PlanarProblem(pr.basis, pr.q_z, v.img, pr.dq)

    def _planar_cost(self, fit: planar.PlanarFit, prior: tuple[float, float, float] | None) -> float:
        """Negative log-likelihood (chi^2 units) of a planar fit: residuals over ``choice_sigma_px``
        and the caller's prior pose."""
        cost = fit.sse / self.choice_sigma_px**2
        if prior is not None:
            x, y, yaw = fit.p[:3].tolist()
            cost += ((x - prior[0]) ** 2 + (y - prior[1]) ** 2) / self.prior_sigma_xy_m**2
            cost += (_wrap(yaw - prior[2]) / self.prior_sigma_yaw_rad) ** 2
        return cost

    def _mirror_start(self, vlist: list[_View], t_tags: list[Mat], sg: _TagGeom, z_exp: float,
                      prior: tuple[float, float, float] | None) -> _Solution | None:
        """The other half of a single tag's two-fold ambiguity when IPPE did not return it.

        The two poses of a small square mirror its normal about the line of sight.  On
        small, nearly frontal tags IPPE's second solution sometimes degenerates (e.g.
        upside down) and the real alternative goes missing, leaving a confidently wrong
        yaw; this rebuilds it from the first solution (``t_tags``: IPPE's T_cam_tag) and
        refines it.  None if IPPE's second solution already is that mirror, or the view
        is exactly frontal."""
        t = t_tags[0]
        (_, _, n0, c0), (_, _, n1, c1), (_, _, n2, c2), _ = t.tolist()  # normal n, centre c (camera frame)
        dist = math.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        v0, v1, v2 = -c0 / dist, -c1 / dist, -c2 / dist  # towards the camera
        cos = n0 * v0 + n1 * v1 + n2 * v2
        if len(t_tags) > 1:
            # the mirrored normal is 2 (n.v) v - n
            (_, _, o0, _), (_, _, o1, _), (_, _, o2, _), _ = t_tags[1].tolist()
            if (2 * cos * v0 - n0) * o0 + (2 * cos * v1 - n1) * o1 + (2 * cos * v2 - n2) * o2 > _MIRROR_COS:
                return None
        axis = np.cross(t[:3, 2], (v0, v1, v2))
        sin = float(np.linalg.norm(axis))
        if sin < 1e-4:
            return None
        r = cv2.Rodrigues(axis * (2.0 * math.atan2(sin, cos) / sin))[0] @ t[:3, :3]
        t_ct = t.copy()
        t_ct[:3, :3] = r
        t_ct = t_ct @ sg.T_tag_target
        return self._solve(vlist, cv2.Rodrigues(t_ct[:3, :3])[0].ravel(), t_ct[:3, 3].copy(), z_exp, prior,
                           _MIRROR_ITERATIONS)

    def _prior_terms(self, sol: _Solution, z_exp: float, prior: tuple[float, float, float] | None) -> float:
        """Negative log-likelihood (chi^2 units) of a candidate under the ground-robot prior
        (tolerances taken as 3 sigma) and the caller's prior pose."""
        tilt = math.acos(max(-1.0, min(1.0, sol.r22)))
        cost = (3.0 * (sol.z - z_exp) / self.z_tol_m) ** 2 + (3.0 * tilt / self.tilt_tol_rad) ** 2
        if prior is not None:
            x, y, yaw = sol.se2
            cost += ((x - prior[0]) ** 2 + (y - prior[1]) ** 2) / self.prior_sigma_xy_m**2
            cost += (_wrap(yaw - prior[2]) / self.prior_sigma_yaw_rad) ** 2
        return cost

    def _candidate(self, t_ct: Mat, t_bc: Mat, sse: float, z_exp: float,
                   prior: tuple[float, float, float] | None) -> _Solution:
        """A scored candidate from T_c0_target and its residual sum of squares (px^2)."""
        t_bt = t_bc @ t_ct
        (r00, _, _, x), (r10, _, _, y), (_, _, r22, z), _ = t_bt.tolist()
        sol = _Solution(t_ct, None, None, None, sse, t_bt, (x, y, math.atan2(r10, r00)), z, r22, 0.0)
        sol.cost = sse / self.choice_sigma_px**2 + self._prior_terms(sol, z_exp, prior)
        return sol

    def _residuals(self, vlist: list[_View], rvec: _Arr, tvec: _Arr) -> tuple[_Arr, _Arr]:
        """Stacked residuals (2M,) projected - detected (px) and their Jacobian (2M, 6) w.r.t.
        theta = (rvec, tvec) of T_c0_target."""
        v = vlist[0]
        proj, jac = cv2.projectPoints(v.obj, rvec, tvec, v.cam.K, None)
        if len(vlist) == 1:
            return proj.reshape(-1) - v.img.reshape(-1), jac[:, :6]
        rs, js = [proj.reshape(-1) - v.img.reshape(-1)], [jac[:, :6]]
        r_c0, jr = cv2.Rodrigues(rvec)
        jr = jr.reshape(3, 3, 3)  # [i] = d R / d rvec_i
        for v in vlist[1:]:
            rcc = v.T_cam_c0[:3, :3]
            proj, jac = cv2.projectPoints(v.obj, cv2.Rodrigues(rcc @ r_c0)[0], rcc @ tvec + v.T_cam_c0[:3, 3],
                                          v.cam.K, None)
            rs.append(proj.reshape(-1) - v.img.reshape(-1))
            # d uv / d tvec_c is d uv / d p_cam; chain through p_cam = Rcc (R(rvec) P + tvec) + tcc
            duv = jac[:, 3:6].reshape(-1, 2, 3)
            dp = np.transpose(rcc @ (jr @ v.obj.T), (2, 1, 0))  # (M, 3, 3): [k, a, i] = d p_cam[k, a] / d rvec_i
            j = np.empty((len(v.obj), 2, 6))
            j[:, :, :3] = duv @ dp
            j[:, :, 3:] = duv @ rcc
            js.append(j.reshape(-1, 6))
        return np.concatenate(rs), np.concatenate(js)

    def _in_front(self, vlist: list[_View], t_c0_target: Mat) -> bool:
        """Whether every corner lies in front of every camera."""
        for v in vlist:
            t = t_c0_target if v.T_cam_c0 is _EYE4 else v.T_cam_c0 @ t_c0_target
            if not (v.obj @ t[2, :3] + t[2, 3] > 0.0).all():
                return False
        return True

    def _solve(self, vlist: list[_View], rvec: _Arr, tvec: _Arr, z_exp: float,
               prior: tuple[float, float, float] | None, max_iterations: int,
               start: tuple[_Arr, _Arr] | None = None) -> _Solution | None:
        """Gauss-Newton (with step halving) on theta = (rvec, tvec) of T_c0_target over every
        corner of every view, then scored (``start``: residuals and Jacobian at the start,
        if already known); None if a corner ends up behind a camera."""
        r, jac = start if start is not None else self._residuals(vlist, rvec, tvec)
        sse = float(r @ r)
        for _ in range(max_iterations):
            grad = jac.T @ r
            ok, step = cv2.solve(jac.T @ jac, -grad, flags=cv2.DECOMP_CHOLESKY)
            if not ok:
                break
            step = step.ravel()
            if -float(step @ grad) < self._tiny_px2:
                break
            for _halving in range(4):
                nr, nt = rvec + step[:3], tvec + step[3:]
                r2, jac2 = self._residuals(vlist, nr, nt)
                sse2 = float(r2 @ r2)
                if sse2 <= sse:
                    rvec, tvec, r, jac, sse = nr, nt, r2, jac2, sse2
                    break
                step *= 0.5
            else:
                break
        t_ct = _rt_to_matrix(rvec, tvec)
        # one view: the start faced the camera and Gauss-Newton does not jump through the image plane
        if len(vlist) > 1 and not self._in_front(vlist, t_ct):
            return None
        sol = self._candidate(t_ct, vlist[0].cam.T_base_cam, sse, z_exp, prior)
        sol.rvec, sol.tvec, sol.jac = rvec, tvec, jac
        return sol

    def _cov_theta(self, sol: _Solution, vlist: list[_View], n_corners: int) -> Mat | None:
        """(6, 6) covariance of theta = (rvec, tvec), or None when the corners do not
        constrain all six degrees of freedom."""
        if sol.jac is None:
            sol.jac = self._residuals(vlist, *sol.theta())[1]
        dof = 2 * n_corners - 6
        s2 = max(self.pixel_sigma_px**2, sol.sse / dof) if dof > 0 else self.pixel_sigma_px**2
        # the SVD inverse also returns 1/condition number: a near-singular system is degenerate
        rcond, inv = cv2.invert(sol.jac.T @ sol.jac, flags=cv2.DECOMP_SVD)
        if not rcond > 1e-12:
            return None
        return cast(Mat, s2 * inv)

    def _plausible(self, sol: _Solution, c0: CameraModel, z_exp: float, cov_theta: Mat) -> bool:
        """Whether the target stands on the floor like the observer: height within
        ``z_tol_m`` of the expected one (0 for a robot's base, the scenario's height for
        a landmark) and roll/pitch within ``tilt_tol_rad`` -- each widened by 3 sigma of
        the estimate itself, so a far single face whose tilt is barely observable is
        kept while a confident tilted (or fake) solution is not."""
        t_bt = sol.T_base_target
        g = output_jacobian(c0.T_base_cam, *sol.theta())[1]
        dz = float(t_bt[2, 3]) - z_exp
        if abs(dz) > self.z_tol_m + 3.0 * math.sqrt(max(0.0, float(g[3] @ cov_theta @ g[3]))):
            return False
        if t_bt[2, 2] <= 0.0:
            return False
        s = float(np.hypot(t_bt[0, 2], t_bt[1, 2]))
        tilt = math.asin(min(1.0, s))
        if tilt <= self.tilt_tol_rad:
            return True
        gt = (t_bt[0, 2] * g[4] + t_bt[1, 2] * g[5]) / s  # d sin(tilt) / d theta
        return tilt <= self.tilt_tol_rad + 3.0 * math.sqrt(max(0.0, float(gt @ cov_theta @ gt)))
