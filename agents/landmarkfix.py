"""Self-localisation from every field tag in view at once (pure code; the marker
document's method).

With landmark tags (fixed, known poses in the arena frame) in view, the robot solves
its own planar pose -- base on the floor at (x, y) facing yaw, arena frame -- from
*all* their corners jointly, across all its cameras: one Gauss-Newton refinement of
the three pose parameters over every corner's reprojection error, each camera
projecting through its own body-camera extrinsics ``T_base_cam`` (OpenCV pinhole;
distorted corners are undistorted first, see :mod:`tagswarm.agents.lens`).  The
covariance is ``σ² (JᵀJ)⁻¹`` with σ the corner noise (px): more tags, more corners,
a longer baseline -- a smaller covariance.  A per-tag estimate, by contrast, sees one
small square and its yaw is levered by the range.

The fix goes to the server as one absolute observation (see :func:`as_estimate`): the
pose of one of the landmarks (the reference, the lowest ID) in the robot's base frame,
with every landmark tag ID used in ``tag_ids``.  Frames: arena (metres, radians),
pixels in OpenCV's convention.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tagswarm.agents.cubegeom import CameraModel, PoseEstimate
from tagswarm.agents.cubepose import CubePoseEstimator
from tagswarm.agents.detect import TagDetection
from tagswarm.protocol.geometry import Pose2, se2_between, se2_compose, se2_inverse
from tagswarm.protocol.scenario import Scenario

Mat = NDArray[np.float64]
#: Gauss-Newton stops when a step moves the pose less than this (m and rad)
STEP_TOL = 1e-9
MAX_ITERATIONS = 30
#: rendered corners scatter this much more than ``agent.pixel_sigma_px`` (as the cube estimator's planar model)
RENDER_NOISE = 1.35


@dataclass(frozen=True)
class Sighting:
    """One landmark tag in one camera: ``corners`` (4, 2) undistorted pixels matching
    ``world`` (4, 3), the tag's corners in the arena frame (metres), same order."""

    cam: CameraModel
    tag_id: int
    corners: Mat
    world: Mat


@dataclass(frozen=True)
class LandmarkFix:
    """The robot's base in the arena frame, ``pose`` (x_m, y_m, yaw_rad) with ``cov`` (3, 3)
    of those (arena axes); ``rms_px`` over ``n_corners`` corners of the tags ``tag_ids``
    seen by ``cameras``."""

    pose: Pose2
    cov: Mat
    rms_px: float
    n_corners: int
    tag_ids: tuple[int, ...]
    cameras: tuple[str, ...]


def landmark_corners(x_m: float, y_m: float, z_m: float, yaw_rad: float, obj: Mat) -> Mat:
    """(4, 3) arena corners of a landmark tag whose frame (origin at the plate centre, +x its
    outward normal, z up) is at (x, y, z) facing ``yaw_rad``; ``obj`` (4, 3) in that frame."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return np.asarray(obj @ rot.T + np.array([x_m, y_m, z_m]))


def _project(pose: Pose2, sightings: Sequence[Sighting]) -> Mat:
    """All corners' pixels (N*4, 2) with the robot at ``pose``; NaN behind a camera."""
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    r_base_arena = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    out = []
    for sg in sightings:
        p_base = (sg.world - np.array([x, y, 0.0])) @ r_base_arena.T
        t = sg.cam.T_cam_base
        p_cam = p_base @ t[:3, :3].T + t[:3, 3]
        z = p_cam[:, 2:3]
        uv = (p_cam @ sg.cam.K.T)[:, :2] / np.where(z > 1e-6, z, np.nan)
        out.append(uv)
    return np.concatenate(out)


def solve(sightings: Sequence[Sighting], initial: Pose2, pixel_sigma_px: float = 1.0) -> LandmarkFix | None:
    """The robot's planar pose from every landmark corner at once, starting at ``initial``
    (e.g. from one tag's own estimate); None without sightings or if it does not converge
    (a corner behind a camera, a singular geometry)."""
    if not sightings:
        return None
    measured = np.concatenate([sg.corners for sg in sightings])
    pose = np.array(initial, float)
    eps = 1e-6
    for _ in range(MAX_ITERATIONS):
        r = (_project(tuple(pose), sightings) - measured).ravel()  # type: ignore[arg-type]
        jac = np.empty((r.size, 3))
        for k in range(3):
            d = np.zeros(3)
            d[k] = eps
            hi = _project(tuple(pose + d), sightings).ravel()  # type: ignore[arg-type]
            lo = _project(tuple(pose - d), sightings).ravel()  # type: ignore[arg-type]
            jac[:, k] = (hi - lo) / (2 * eps)
        if not (np.all(np.isfinite(r)) and np.all(np.isfinite(jac))):
            return None
        try:
            step = np.linalg.lstsq(jac, -r, rcond=None)[0]
        except np.linalg.LinAlgError:
            return None
        pose = pose + step
        if float(np.max(np.abs(step))) < STEP_TOL:
            break
    else:
        return None
    r = (_project(tuple(pose), sightings) - measured).ravel()  # type: ignore[arg-type]
    if not np.all(np.isfinite(r)):
        return None
    info = jac.T @ jac
    if np.linalg.cond(info) > 1e12:
        return None
    cov = pixel_sigma_px**2 * np.linalg.inv(info)
    pose[2] = math.remainder(pose[2], math.tau)
    return LandmarkFix(pose=(float(pose[0]), float(pose[1]), float(pose[2])), cov=np.asarray((cov + cov.T) / 2),
                       rms_px=float(np.sqrt(np.mean(r**2) * 2)), n_corners=measured.shape[0],
                       tag_ids=tuple(sorted({sg.tag_id for sg in sightings})),
                       cameras=tuple(dict.fromkeys(sg.cam.name for sg in sightings)))


def as_estimate(fix: LandmarkFix, ref_id: int, ref_pose: Pose2, ref_z_m: float) -> PoseEstimate:
    """The fix as the observation of landmark ``ref_id`` (frame at ``ref_pose`` in the arena,
    its centre ``ref_z_m`` up): that frame in the robot's base frame, ``L ⊖ pose``, with the
    covariance moved onto it (first order, numerically)."""
    rel = se2_between(fix.pose, ref_pose)
    jac = np.empty((3, 3))
    eps = 1e-6
    for k in range(3):
        d = np.zeros(3)
        d[k] = eps
        hi = se2_between(tuple(np.add(fix.pose, d)), ref_pose)  # type: ignore[arg-type]
        lo = se2_between(tuple(np.subtract(fix.pose, d)), ref_pose)  # type: ignore[arg-type]
        diff = np.subtract(hi, lo)
        diff[2] = math.remainder(diff[2], math.tau)
        jac[:, k] = diff / (2 * eps)
    cov = jac @ fix.cov @ jac.T
    c, s = math.cos(rel[2]), math.sin(rel[2])
    t = np.array([[c, -s, 0.0, rel[0]], [s, c, 0.0, rel[1]], [0.0, 0.0, 1.0, ref_z_m], [0.0, 0.0, 0.0, 1.0]])
    return PoseEstimate(target_kind="landmark", target_id=ref_id, T_base_target=t, x_m=rel[0], y_m=rel[1],
                        yaw_rad=rel[2], cov=np.asarray((cov + cov.T) / 2), reprojection_rms_px=fix.rms_px,
                        tag_ids=fix.tag_ids, cameras=fix.cameras, n_corners=fix.n_corners)


def joint_fix(estimates: Iterable[PoseEstimate], views: Sequence[tuple[CameraModel, Sequence[object]]],
              landmarks: Mapping[int, tuple[Pose2, float, Mat]], pixel_sigma_px: float,
              min_tags: int = 2) -> list[PoseEstimate]:
    """``estimates`` with every per-tag landmark estimate replaced by one joint fix, when at
    least ``min_tags`` landmark tags are in view.  ``views``: (pinhole camera, undistorted
    detections with ``tag_id`` and ``corners``) per camera; ``landmarks``: tag ID ->
    (planar pose in the arena, centre height, (4, 3) corners in the landmark frame)."""
    ests = list(estimates)
    lm_ests = [e for e in ests if e.target_kind == "landmark" and e.target_id in landmarks]
    sightings = []
    for cam, dets in views:
        for d in dets:
            tid = int(d.tag_id)  # type: ignore[attr-defined]
            if tid in landmarks:
                (lx, ly, lyaw), lz, obj = landmarks[tid]
                corners = np.asarray(d.corners, np.float64)  # type: ignore[attr-defined]
                sightings.append(Sighting(cam, tid, corners, landmark_corners(lx, ly, lz, lyaw, obj)))
    if not lm_ests or len({sg.tag_id for sg in sightings}) < min_tags:
        return ests
    # start from the most certain single-tag estimate, turned into the robot's pose
    best = min(lm_ests, key=lambda e: float(e.cov[0, 0] + e.cov[1, 1]))
    start = se2_compose(landmarks[best.target_id][0], se2_inverse((best.x_m, best.y_m, best.yaw_rad)))
    fix = solve(sightings, start, pixel_sigma_px)
    if fix is None or math.dist(fix.pose[:2], start[:2]) > 1.0:
        return ests
    ref = min(fix.tag_ids)
    joint = as_estimate(fix, ref, landmarks[ref][0], landmarks[ref][1])
    return [e for e in ests if not (e.target_kind == "landmark" and e.target_id in landmarks)] + [joint]


def fix_estimates(estimator: CubePoseEstimator, scenario: Scenario, estimates: Iterable[PoseEstimate],
                  views: Sequence[tuple[CameraModel, list[TagDetection]]]) -> list[PoseEstimate]:
    """The agent's hook: :func:`joint_fix` over one synchronised set of frames ``views``
    (raw cameras and detections, as given to ``estimator``), with the scenario's landmarks."""
    if not scenario.landmarks:
        return list(estimates)
    table: dict[int, tuple[Pose2, float, Mat]] = {}
    for lm in scenario.landmarks:
        obj = estimator.object_points(lm.id)
        if obj is not None:
            table[lm.id] = ((lm.x_m, lm.y_m, lm.yaw_rad), lm.z_m, obj)
    prepared = [estimator.lens.prepare(cam, dets) for cam, dets in views]
    return joint_fix(estimates, prepared, table, estimator.pixel_sigma_px * RENDER_NOISE)
