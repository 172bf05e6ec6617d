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

Algorithm per target:

1. Start: ``cv2.solvePnPGeneric(SOLVEPNP_IPPE_SQUARE)`` on the largest tag gives the
   two poses a planar square cannot tell apart.
2. Each start is refined by Levenberg-Marquardt over every corner of the target
   (``cv2.solvePnPRefineLM`` for one camera; a small LM over all cameras' corners
   for a rig) and scored as a negative log-likelihood: reprojection residuals /
   ``pixel_sigma_px``, the ground-robot prior (both robots stand on the floor, so the
   target's base has z near 0 -- a landmark near its known height -- and little
   roll/pitch), the caller's prior pose if any, and negative evidence: a face the
   solution says squarely faces the camera, big enough to decode, yet not
   detected.  The best plausible candidate wins.
3. Covariance: ``s^2 (J^T J)^-1`` from the Jacobian of the residuals at the solution
   w.r.t. a right perturbation of ``T_base_target``, with
   ``s = max(pixel_sigma_px, residual-based estimate)``, propagated to (x, y, yaw).
   When the losing candidate is still plausible and not negligible, its spread is
   added (moment-matched two-component mixture), so a possibly flipped solution
   says so in its covariance instead of being confidently wrong.
4. Rejected (and counted in :attr:`CubePoseEstimator.rejects`): reprojection RMS
   above ``max_rms_px`` ("reprojection"), |z - expected| > ``z_tol_m`` or roll/pitch
   above ``tilt_tol_rad`` ("implausible"), too few/degenerate corners or a singular
   Jacobian ("degenerate").
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Final

import cv2
import numpy as np
from numpy.typing import NDArray

from agents.detect import TagDetection, TagMap, TargetKind
from protocol import tags
from protocol.geometry import Mat, matrix_to_pose3, pose3_to_matrix
from protocol.messages import CameraImage, RelativeObservation
from protocol.scenario import Scenario

#: Thickness of a landmark plate; the tag is painted on its +x face, at x = +thickness/2.
#: Mirrors the default of ``world.assets.landmark_mesh`` (tests/unit/test_cubepose.py pins it).
LANDMARK_PLATE_THICKNESS_M: Final = 0.01

# IPPE_SQUARE wants the corners TL, TR, BR, BL; the contract order is TR, TL, BL, BR.
_TO_IPPE: Final = np.array([1, 0, 3, 2])
# negative evidence: a face whose normal is within ~55 deg of the line of sight and whose tag spans
# this many pixels decodes reliably on our renders, so a candidate predicting one that was not seen is penalised
_MISSING_COS: Final = 0.57
_MISSING_MIN_PX: Final = 24.0
_MISSING_PENALTY: Final = 9.0


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
    face: tags.Face | None
    obj: NDArray[np.float64]  # (4, 3) corners in the target frame, contract order
    ippe_obj: NDArray[np.float64]  # (4, 3) corners in the tag's own frame, IPPE order
    T_tag_target: Mat  # (4, 4)


@dataclass
class _View:
    """The corners of one target in one camera."""

    cam: CameraModel
    obj: NDArray[np.float64]  # (M, 3) target frame
    img: NDArray[np.float64]  # (M, 2) pixels
    faces: set[tags.Face]


@dataclass
class _Candidate:
    T_base_target: Mat
    sse: float
    cost: float
    se2: NDArray[np.float64]


def _rt_to_matrix(rvec: NDArray[np.float64], tvec: NDArray[np.float64]) -> Mat:
    t = np.eye(4)
    t[:3, :3] = cv2.Rodrigues(rvec)[0]
    t[:3, 3] = tvec.ravel()
    return t


def _se2(t: Mat) -> NDArray[np.float64]:
    return np.array([t[0, 3], t[1, 3], math.atan2(t[1, 0], t[0, 0])])


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def project_with_jacobian(cam: CameraModel, T_cam_target: Mat, obj: NDArray[np.float64]
                          ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Pixels (M, 2) of target-frame points ``obj`` (M, 3), their Jacobian (2M, 6) w.r.t.
    a right perturbation ``T_cam_target @ [Exp(w), v]`` with xi = (w, v) (rad, m, in the
    target frame), and the points' depths (M,) in metres.

    A right perturbation of ``T_cam_target`` is the same as one of ``T_base_target``
    (``T_cam_base`` multiplies on the left), so Jacobians from several cameras stack.
    """
    r, t = T_cam_target[:3, :3], T_cam_target[:3, 3]
    pc = obj @ r.T + t
    z = pc[:, 2]
    iz = 1.0 / z
    k = cam.K
    fx, fy = k[0, 0], k[1, 1]
    uv = np.empty((len(obj), 2))
    uv[:, 0] = fx * pc[:, 0] * iz + k[0, 2]
    uv[:, 1] = fy * pc[:, 1] * iz + k[1, 2]
    a = np.zeros((len(obj), 2, 3))
    a[:, 0, 0] = fx * iz
    a[:, 0, 2] = -fx * pc[:, 0] * iz * iz
    a[:, 1, 1] = fy * iz
    a[:, 1, 2] = -fy * pc[:, 1] * iz * iz
    b = a @ r  # d uv / d v, (M, 2, 3)
    # d pc / d w = -R [P]x, and b^T [P]x = (b x P)^T, hence P x b
    jw = np.cross(obj[:, None, :], b)
    jac = np.concatenate([jw, b], axis=2).reshape(-1, 6)
    return uv, jac, z


def se2_jacobian(T_base_target: Mat) -> NDArray[np.float64]:
    """(3, 6) Jacobian of (x, y, yaw) of ``T_base_target`` w.r.t. the right perturbation
    xi = (w, v) of :func:`project_with_jacobian`."""
    r = T_base_target[:3, :3]
    den = r[0, 0] ** 2 + r[1, 0] ** 2
    g = np.zeros((3, 6))
    g[0:2, 3:6] = r[0:2, :]
    g[2, 1] = (r[1, 0] * r[0, 2] - r[0, 0] * r[1, 2]) / den
    g[2, 2] = (r[0, 0] * r[1, 1] - r[1, 0] * r[0, 1]) / den
    return g


def _retract(t: Mat, xi: NDArray[np.float64]) -> Mat:
    out = t.copy()
    out[:3, :3] = t[:3, :3] @ cv2.Rodrigues(xi[:3].reshape(3, 1))[0]
    out[:3, 3] = t[:3, 3] + t[:3, :3] @ xi[3:]
    return out


class CubePoseEstimator:
    """Bundle adjustment of observed tag cubes and landmark tags, one camera or a rig.

    ``pixel_sigma_px`` is the corner noise (1 sigma per axis) assumed for the
    covariance and the candidate scores: measured on our renders (640x480 and
    320x240, 0.5-5 m), AprilTag 3 corners scatter ~0.27 px RMS per axis about the
    projected truth, but the errors of one tag's four corners are correlated
    (edge fits share pixels), so the honest per-corner sigma is larger; 0.5 px
    gives NEES ~3 for (x, y, yaw) over many random views (tests/unit/test_cubepose.py
    asserts it).  ``max_rms_px``, ``z_tol_m`` and ``tilt_tol_rad`` gate the result;
    ``prior_sigma_xy_m``/``prior_sigma_yaw_rad`` weigh a caller's prior pose when
    choosing between the two-fold solutions.
    """

    def __init__(self, scenario: Scenario, pixel_sigma_px: float = 0.5, max_rms_px: float = 2.0,
                 z_tol_m: float = 0.08, tilt_tol_rad: float = 0.15, *, prior_sigma_xy_m: float = 0.25,
                 prior_sigma_yaw_rad: float = 0.35, max_iterations: int = 10) -> None:
        if pixel_sigma_px <= 0:
            raise ValueError("pixel_sigma_px must be positive")
        self.scenario = scenario
        self.pixel_sigma_px = pixel_sigma_px
        self.max_rms_px = max_rms_px
        self.z_tol_m = z_tol_m
        self.tilt_tol_rad = tilt_tol_rad
        self.prior_sigma_xy_m = prior_sigma_xy_m
        self.prior_sigma_yaw_rad = prior_sigma_yaw_rad
        self.max_iterations = max_iterations
        self.rejects: Counter[str] = Counter()
        self.tag_map = TagMap.from_scenario(scenario)
        self._geom: dict[int, _TagGeom] = {}
        self._expected_z: dict[tuple[str, int], float] = {}
        self._faces: dict[tags.Face, tuple[NDArray[np.float64], NDArray[np.float64]]] = {}
        self._build()

    # ------------------------------------------------------------------ geometry
    def _build(self) -> None:
        s = self.scenario
        zc = s.robot.cube_center_z_m
        for face in tags.Face:
            n, _, _ = tags.face_axes(face)
            self._faces[face] = (n, n * (s.robot.cube_edge_m / 2.0) + np.array([0.0, 0.0, zc]))
        for rid in s.robot_ids:
            self._expected_z[("robot", rid)] = 0.0
            for face, tid in zip(tags.Face, s.tag_ids(rid), strict=True):
                n, u, r = tags.face_axes(face)
                centre = n * (s.robot.cube_edge_m / 2.0) + np.array([0.0, 0.0, zc])
                self._geom[tid] = self._tag_geom("robot", rid, face, centre, n, u, r, s.tags.size_m)
        for lm in s.landmarks:
            self._expected_z[("landmark", lm.id)] = lm.z_m
            n, u, r = tags.face_axes(tags.Face.FRONT)
            centre = n * (LANDMARK_PLATE_THICKNESS_M / 2.0)
            self._geom[lm.id] = self._tag_geom("landmark", lm.id, None, centre, n, u, r, lm.size_m)

    @staticmethod
    def _tag_geom(kind: TargetKind, target_id: int, face: tags.Face | None, centre: NDArray[np.float64],
                  n: NDArray[np.float64], u: NDArray[np.float64], r: NDArray[np.float64], size: float) -> _TagGeom:
        obj = tags.square_corners(centre, u, r, size)
        t_target_tag = np.eye(4)
        t_target_tag[:3, :3] = np.stack([r, u, n], axis=1)  # tag frame: x right, y up, z out of the face
        t_target_tag[:3, 3] = centre
        h = size / 2.0
        ippe = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
        return _TagGeom(kind, target_id, face, obj, ippe, np.linalg.inv(t_target_tag))

    def object_points(self, tag_id: int) -> NDArray[np.float64] | None:
        """(4, 3) corners of ``tag_id`` in its target's frame (contract order), or None."""
        g = self._geom.get(tag_id)
        return None if g is None else g.obj.copy()

    # ------------------------------------------------------------------ public
    def estimate(self, views: list[tuple[CameraModel, list[TagDetection]]],
                 priors: dict[tuple[str, int], tuple[float, float, float]] | None = None) -> list[PoseEstimate]:
        """Poses of every target seen in ``views`` (one synchronised frame per camera).

        Detections of tags that belong to nothing in the scenario are ignored (the
        caller counts them with :class:`~agents.detect.TagMap`).  ``priors`` maps
        ``(kind, target_id)`` to a predicted (x_m, y_m, yaw_rad) in the observer's base
        frame; it only breaks ties between the two-fold solutions.  Rejected
        targets are counted in :attr:`rejects` by reason.
        """
        groups: dict[tuple[str, int], list[tuple[int, _TagGeom, TagDetection]]] = {}
        for vi, (_, dets) in enumerate(views):
            for d in dets:
                g = self._geom.get(d.tag_id)
                if g is not None:
                    groups.setdefault((g.kind, g.target_id), []).append((vi, g, d))
        out = []
        for key, members in groups.items():
            est = self._estimate_target(key, members, views, None if priors is None else priors.get(key))
            if est is not None:
                out.append(est)
        return out

    # ------------------------------------------------------------------ internals
    def _reject(self, reason: str) -> None:
        self.rejects[reason] += 1

    def _estimate_target(self, key: tuple[str, int], members: list[tuple[int, _TagGeom, TagDetection]],
                         views: list[tuple[CameraModel, list[TagDetection]]],
                         prior: tuple[float, float, float] | None) -> PoseEstimate | None:
        per_cam: dict[int, list[tuple[_TagGeom, TagDetection]]] = {}
        seen: set[tuple[int, int]] = set()
        best_area, start = -1.0, (0, members[0][1], members[0][2])
        for vi, g, d in members:
            if (vi, d.tag_id) in seen:  # one tag twice in one image: a false decode somewhere
                self._reject("duplicate")
                return None
            seen.add((vi, d.tag_id))
            per_cam.setdefault(vi, []).append((g, d))
            c = d.corners
            area = 0.5 * abs(float((c[0, 0] - c[2, 0]) * (c[1, 1] - c[3, 1]) - (c[1, 0] - c[3, 0]) * (c[0, 1] - c[2, 1])))
            if area > best_area:
                best_area, start = area, (vi, g, d)
        if best_area < 4.0 or not np.all(np.isfinite([d.corners for _, _, d in members])):
            self._reject("degenerate")
            return None
        vlist = []
        for vi, items in per_cam.items():
            vlist.append(_View(views[vi][0], np.concatenate([g.obj for g, _ in items]),
                               np.concatenate([d.corners for _, d in items]).astype(np.float64),
                               {g.face for g, _ in items if g.face is not None}))
        svi, sg, sd = start
        scam = views[svi][0]
        sview = next(v for v, vi in zip(vlist, per_cam, strict=True) if vi == svi)
        try:
            n, rvecs, tvecs, _ = cv2.solvePnPGeneric(sg.ippe_obj, np.ascontiguousarray(sd.corners[_TO_IPPE]),
                                                     scam.K, None, flags=cv2.SOLVEPNP_IPPE_SQUARE)
        except cv2.error:
            n = 0
        if n == 0:
            self._reject("degenerate")
            return None
        cands: list[_Candidate] = []
        for rvec, tvec in zip(rvecs, tvecs, strict=True):
            t_cam_target = _rt_to_matrix(rvec, tvec) @ sg.T_tag_target
            rv, tv = cv2.Rodrigues(t_cam_target[:3, :3])[0], t_cam_target[:3, 3:4].copy()
            if len(sview.obj) > 4:
                rv, tv = cv2.solvePnPRefineLM(sview.obj, sview.img, scam.K, None, rv, tv)
            t_bt = scam.T_base_cam @ _rt_to_matrix(rv, tv)
            if len(vlist) > 1:
                t_bt = self._refine(t_bt, vlist)
            cand = self._score(key, t_bt, vlist, prior)
            if cand is not None:
                cands.append(cand)
        if not cands:
            self._reject("degenerate")
            return None
        cands.sort(key=lambda c: c.cost)
        n_corners = sum(len(v.obj) for v in vlist)
        plausible: list[tuple[_Candidate, Mat]] = []
        constrained = False
        for cand in cands:
            cov6 = self._covariance6(cand, vlist, n_corners)
            constrained = constrained or cov6 is not None
            if cov6 is not None and self._plausible(key, cand.T_base_target, cov6):
                plausible.append((cand, cov6))
        if not plausible:
            self._reject("implausible" if constrained else "degenerate")
            return None
        best, cov6 = plausible[0]
        rms = math.sqrt(best.sse / n_corners)
        if rms > self.max_rms_px:
            self._reject("reprojection")
            return None
        g = se2_jacobian(best.T_base_target)
        cov = g @ cov6 @ g.T
        ambiguity = 0.0
        if len(plausible) > 1:
            alt = plausible[1][0]
            d = alt.se2 - best.se2
            d[2] = _wrap(float(d[2]))
            # both refined to the same pose (several faces): no ambiguity left
            if abs(d[2]) > 1e-3 or math.hypot(d[0], d[1]) > 1e-3:
                ambiguity = 1.0 / (1.0 + math.exp(min(50.0, 0.5 * (alt.cost - best.cost))))
                cov = cov + ambiguity * np.outer(d, d)
        if not np.all(np.isfinite(cov)) or np.linalg.det(cov) <= 0.0:
            self._reject("degenerate")
            return None
        tag_ids = tuple(sorted({d.tag_id for _, _, d in members}))
        return PoseEstimate(
            target_kind=sg.kind, target_id=sg.target_id, T_base_target=best.T_base_target,
            x_m=float(best.se2[0]), y_m=float(best.se2[1]), yaw_rad=float(best.se2[2]), cov=cov,
            reprojection_rms_px=rms, tag_ids=tag_ids, cameras=tuple(v.cam.name for v in vlist),
            n_corners=n_corners, ambiguity=ambiguity)

    def _covariance6(self, cand: _Candidate, vlist: list[_View], n_corners: int) -> Mat | None:
        """(6, 6) covariance of the right perturbation xi = (w, v) of ``T_base_target``, or
        None when the corners do not constrain all six degrees of freedom."""
        jac = np.concatenate([project_with_jacobian(v.cam, v.cam.T_cam_base @ cand.T_base_target, v.obj)[1]
                              for v in vlist])
        dof = 2 * n_corners - 6
        s2 = max(self.pixel_sigma_px**2, cand.sse / dof) if dof > 0 else self.pixel_sigma_px**2
        info = jac.T @ jac
        if np.linalg.cond(info) > 1e12:
            return None
        cov6: Mat = s2 * np.linalg.inv(info)
        return cov6

    def _plausible(self, key: tuple[str, int], t_bt: Mat, cov6: Mat) -> bool:
        """Whether the target stands on the floor like the observer: height within
        ``z_tol_m`` of the expected one and roll/pitch within ``tilt_tol_rad`` -- each
        widened by 3 sigma of the estimate itself, so a far single face whose tilt is
        barely observable is not thrown away while a confident tilted solution is."""
        r = t_bt[:3, :3]
        dz = float(t_bt[2, 3]) - self._expected_z.get(key, 0.0)
        tv = r[0:2, 2]  # horizontal part of the target's z axis: (sin tilt) * direction
        tilt = math.asin(min(1.0, float(np.hypot(tv[0], tv[1])))) if r[2, 2] > 0 else math.pi / 2
        hz = r[2, :]
        sz = math.sqrt(max(0.0, float(hz @ cov6[3:, 3:] @ hz)))
        if abs(dz) > self.z_tol_m + 3.0 * sz:
            return False
        if tilt <= self.tilt_tol_rad:
            return True
        if r[2, 2] <= 0:
            return False
        u = tv / np.hypot(tv[0], tv[1])
        # d(R e3)[:2] / dw = R[:2, :] @ [[0, 1, 0], [-1, 0, 0], [0, 0, 0]]
        ht = np.array([-(u @ r[0:2, 1]), u @ r[0:2, 0], 0.0])
        st = math.sqrt(max(0.0, float(ht @ cov6[:3, :3] @ ht)))
        return tilt <= self.tilt_tol_rad + 3.0 * st

    def _score(self, key: tuple[str, int], t_bt: Mat, vlist: list[_View],
               prior: tuple[float, float, float] | None) -> _Candidate | None:
        """Negative log-likelihood of a candidate pose, or None if it is not physical
        (a point behind a camera, a detected face turned away from it)."""
        sse, missing = 0.0, 0
        for v in vlist:
            t_ct = v.cam.T_cam_base @ t_bt
            rv = cv2.Rodrigues(t_ct[:3, :3])[0]
            proj = cv2.projectPoints(v.obj, rv, t_ct[:3, 3], v.cam.K, None)[0].reshape(-1, 2)
            if np.any(v.obj @ t_ct[2, :3] + t_ct[2, 3] <= 0.0):
                return None
            sse += float(np.sum((proj - v.img) ** 2))
            if key[0] == "robot":
                bad, miss = self._face_evidence(v, t_ct)
                if bad:
                    return None
                missing += miss
        dz = float(t_bt[2, 3]) - self._expected_z.get(key, 0.0)
        tilt = math.acos(max(-1.0, min(1.0, float(t_bt[2, 2]))))
        se2 = _se2(t_bt)
        cost = sse / self.pixel_sigma_px**2
        cost += (3.0 * dz / self.z_tol_m) ** 2 + (3.0 * tilt / self.tilt_tol_rad) ** 2
        cost += _MISSING_PENALTY * missing
        if prior is not None:
            cost += ((se2[0] - prior[0]) ** 2 + (se2[1] - prior[1]) ** 2) / self.prior_sigma_xy_m**2
            cost += (_wrap(float(se2[2]) - prior[2]) / self.prior_sigma_yaw_rad) ** 2
        return _Candidate(t_bt, sse, cost, se2)

    def _face_evidence(self, v: _View, t_ct: Mat) -> tuple[bool, int]:
        """(a detected face is turned away from the camera, number of faces that squarely
        face the camera, would be big enough to decode and inside the image, yet were not seen)."""
        r, t = t_ct[:3, :3], t_ct[:3, 3]
        k = v.cam.K
        tag = self.scenario.tags.size_m
        missing = 0
        for face, (n, c) in self._faces.items():
            nc, cc = r @ n, r @ c + t
            dist = float(np.linalg.norm(cc))
            cos = -float(nc @ cc) / dist
            if face in v.faces:
                if cos <= 0.0:
                    return True, 0
                continue
            if cos < _MISSING_COS or cc[2] <= 0.0:
                continue
            u, w = k[0, 0] * cc[0] / cc[2] + k[0, 2], k[1, 1] * cc[1] / cc[2] + k[1, 2]
            size = k[0, 0] * tag / dist * math.sqrt(cos)
            m = size
            if size >= _MISSING_MIN_PX and m <= u <= v.cam.width - m and m <= w <= v.cam.height - m:
                missing += 1
        return False, missing

    def _refine(self, t_bt: Mat, vlist: list[_View]) -> Mat:
        """Levenberg-Marquardt on ``T_base_target`` over every camera's corners."""
        def residuals(t: Mat, with_jac: bool) -> tuple[NDArray[np.float64], NDArray[np.float64] | None, bool]:
            rs, js, ok = [], [], True
            for v in vlist:
                uv, jac, z = project_with_jacobian(v.cam, v.cam.T_cam_base @ t, v.obj)
                ok = ok and bool(np.all(z > 0))
                rs.append((uv - v.img).ravel())
                js.append(jac)
            return np.concatenate(rs), (np.concatenate(js) if with_jac else None), ok

        lam = 1e-3
        r, j, _ = residuals(t_bt, True)
        cost = float(r @ r)
        for _ in range(self.max_iterations):
            assert j is not None
            h = j.T @ j
            g = j.T @ r
            try:
                step = -np.linalg.solve(h + lam * np.diag(np.diag(h)), g)
            except np.linalg.LinAlgError:
                break
            t_new = _retract(t_bt, step)
            r_new, j_new, ok = residuals(t_new, True)
            c_new = float(r_new @ r_new)
            if ok and c_new < cost:
                t_bt, r, j, lam = t_new, r_new, j_new, max(lam / 10.0, 1e-9)
                converged = cost - c_new < 1e-10 * max(cost, 1.0) or float(np.abs(step).max()) < 1e-10
                cost = c_new
                if converged:
                    break
            else:
                lam *= 10.0
                if lam > 1e8:
                    break
        return t_bt
