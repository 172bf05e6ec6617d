"""Per-trajectory errors for :mod:`tagswarm.evaluation.metrics`: association, ATE and RPE via evo,
and the ONE SE(2) alignment shared by every robot of a swarm.

Pure code.  Every pose is in the MAP frame; positions and errors are metres, angles
radians, timestamps simulation seconds.  ATE and RPE are evo's (``APE`` / ``RPE``,
translation part, on ``PoseTrajectory3D``); ``S`` below is the error-statistics
dict ``{"rmse", "mean", "median", "max", "count"}`` documented in :mod:`tagswarm.evaluation.metrics`.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from evo import EvoException
from evo.core import metrics as evo_metrics
from evo.core import sync as evo_sync
from evo.core.sync_method import SyncMethod
from evo.core.trajectory import PosePath3D, PoseTrajectory3D
from evo.core.units import Unit

from tagswarm.evaluation.runfolder import F64, RunData
from tagswarm.protocol.geometry import se2_matrix

ASSOC_MAX_DIFF_S = 0.05
"""Largest time difference (s) for associating an estimate with the truth."""
RPE_DELTA_M = 1.0
"""RPE segment length (m of true path)."""
KINDS = ("fused", "odom")
"""Estimates evaluated against ``truth``."""

Stats = dict[str, float | int]
"""``S``: ``{"rmse", "mean", "median", "max"}`` metres and ``"count"`` errors pooled."""


# --------------------------------------------------------------------------- evo wrappers


def trajectory_yaw(traj: PoseTrajectory3D | PosePath3D) -> F64:
    """(N,) heading (rad, about z) of every pose of a planar trajectory."""
    q = np.asarray(traj.orientations_quat_wxyz, float)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.asarray(np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)), float)


def associate(truth: PoseTrajectory3D, est: PoseTrajectory3D,
              max_diff: float = ASSOC_MAX_DIFF_S) -> tuple[PoseTrajectory3D, PoseTrajectory3D] | None:
    """(truth, estimate) resampled at common timestamps by evo, or ``None`` if no stamp
    pair is within ``max_diff`` seconds.  The denser trajectory is interpolated at the
    sparser one's stamps, so the truth rate need not match the estimate's."""
    # interpolation needs two poses on the denser side; with one pose each, nearest is exact anyway
    method = SyncMethod.interpolation if max(truth.num_poses, est.num_poses) >= 2 else SyncMethod.nearest_time
    try:
        ref, out = evo_sync.associate_trajectories(truth, est, sync_method=method, max_diff=max_diff)
    except EvoException:
        return None
    return ref, out


def ape(ref: PoseTrajectory3D | PosePath3D, est: PoseTrajectory3D | PosePath3D) -> evo_metrics.APE:
    """evo APE (translation part) of associated poses: ``.error`` is |p_est - p_true| per pose, metres."""
    metric = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    metric.process_data((ref, est))
    return metric


def rpe_per_metre(ref: PoseTrajectory3D, est: PoseTrajectory3D,
                  delta_m: float = RPE_DELTA_M) -> tuple[Stats | None, F64]:
    """evo RPE (translation part) over consecutive segments of ``delta_m`` metres of
    TRUE path (pairs chosen on the reference so that fused and odom are judged on the
    same segments).  Returns (``S`` or ``None`` if no segment fits, per-segment errors)."""
    if ref.num_poses < 2:
        return None, np.zeros(0)
    rpe = evo_metrics.RPE(evo_metrics.PoseRelation.translation_part, delta=delta_m, delta_unit=Unit.meters,
                          all_pairs=False, pairs_from_reference=True)
    try:
        rpe.process_data((ref, est))
    except EvoException:
        return None, np.zeros(0)
    if len(rpe.error) == 0:
        return None, np.zeros(0)
    return _evo_stats(rpe), np.asarray(rpe.error, float)


def _evo_stats(metric: Any) -> Stats:
    s = metric.get_all_statistics()
    return {"rmse": float(s["rmse"]), "mean": float(s["mean"]), "median": float(s["median"]),
            "max": float(s["max"]), "count": len(metric.error)}


def pooled_stats(errors: F64) -> Stats | None:
    """``S`` of errors pooled over robots (same definitions as evo's statistics)."""
    e = np.asarray(errors, float)
    if e.size == 0:
        return None
    return {"rmse": float(np.sqrt(np.mean(e**2))), "mean": float(np.mean(e)), "median": float(np.median(e)),
            "max": float(np.max(e)), "count": int(e.size)}


def _pooled_ape(refs: list[PoseTrajectory3D], ests: list[PoseTrajectory3D]) -> Stats | None:
    """evo APE over all robots at once: their associated poses concatenated into one path."""
    if not refs or len(refs) != len(ests):
        return None
    ref = PosePath3D(poses_se3=[p for r in refs for p in r.poses_se3])
    est = PosePath3D(poses_se3=[p for e in ests for p in e.poses_se3])
    return _evo_stats(ape(ref, est))


# --------------------------------------------------------------------------- shared SE(2) alignment


@dataclass(frozen=True)
class SE2Alignment:
    """p_aligned = R(yaw_rad) p_est + (x_m, y_m), fitted over ``points`` samples."""

    yaw_rad: float
    x_m: float
    y_m: float
    points: int

    def matrix(self) -> F64:
        """(4, 4) SE(3) transform (rotation about +z) to left-multiply estimated poses with."""
        return se2_matrix(self.x_m, self.y_m, self.yaw_rad)

    def as_dict(self) -> dict[str, float | int]:
        return {"yaw_rad": self.yaw_rad, "x_m": self.x_m, "y_m": self.y_m, "points": self.points}


def fit_se2(est_xy: F64, ref_xy: F64) -> SE2Alignment | None:
    """Least-squares rigid 2-D alignment (Kabsch/Umeyama without scale) of ``est_xy``
    onto ``ref_xy``, both (N, 2) metres, row i of one matching row i of the other.

    Closed form: with centred points a_i, b_i, the yaw maximising sum b_i . R a_i is
    atan2(sum a_i x b_i, sum a_i . b_i); the translation moves the rotated centroid of
    the estimate onto that of the reference.  ``None`` for no points; with all points
    coincident the yaw is unobservable and comes out 0."""
    a = np.asarray(est_xy, float).reshape(-1, 2)
    b = np.asarray(ref_xy, float).reshape(-1, 2)
    if a.shape != b.shape:
        raise ValueError(f"fit_se2: {a.shape} points vs {b.shape}")
    if len(a) == 0:
        return None
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    a0, b0 = a - ca, b - cb
    cross = float(np.sum(a0[:, 0] * b0[:, 1] - a0[:, 1] * b0[:, 0]))
    dot = float(np.sum(a0[:, 0] * b0[:, 0] + a0[:, 1] * b0[:, 1]))
    yaw = math.atan2(cross, dot)
    c, s = math.cos(yaw), math.sin(yaw)
    t = cb - np.array([c * ca[0] - s * ca[1], s * ca[0] + c * ca[1]])
    return SE2Alignment(yaw_rad=yaw, x_m=float(t[0]), y_m=float(t[1]), points=len(a))


# --------------------------------------------------------------------------- robots and swarm


@dataclass
class Track:
    """One estimate of one robot associated with its truth (both in the map frame).
    ``aligned`` is the estimate after the swarm's shared alignment (or ``None``)."""

    robot: int
    kind: str
    truth: PoseTrajectory3D
    est: PoseTrajectory3D
    error_m: F64
    aligned: PoseTrajectory3D | None = None
    aligned_error_m: F64 | None = None

    @property
    def stamps_s(self) -> F64:
        return np.asarray(self.truth.timestamps, float)

    @property
    def truth_xy(self) -> F64:
        return np.asarray(self.truth.positions_xyz[:, :2], float)

    @property
    def est_xy(self) -> F64:
        return np.asarray(self.est.positions_xyz[:, :2], float)


def robot_trajectories(run: RunData,
                       warnings: list[str]) -> tuple[dict[tuple[int, str], Track], dict[str, dict[str, Any]]]:
    """Associate every estimate of every robot with its truth.  Returns the tracks by
    (robot, kind) and the per-robot blocks of ``metrics.json`` ``robots`` as far as
    trajectories go (``ate_aligned`` stays ``None``: see :func:`align_swarm`); a
    failed association is appended to ``warnings``."""
    tracks: dict[tuple[int, str], Track] = {}
    robots_out: dict[str, dict[str, Any]] = {}
    for k in run.robots:
        truth = run.truth.get(k)
        robots_out[str(k)] = {
            "truth_samples": truth.num_poses if truth is not None else 0,
            "path_length_m": float(truth.path_length) if truth is not None and truth.num_poses > 1 else 0.0,
        }
        for kind in KINDS:
            est = run.estimate(kind, k)
            block: dict[str, Any] = {"samples": est.num_poses if est is not None else 0, "associated": 0,
                                     "first_s": float(est.timestamps[0]) if est is not None else None,
                                     "ate_unaligned": None, "ate_aligned": None, "rpe_per_m": None}
            robots_out[str(k)][kind] = block
            if truth is None or est is None:
                continue
            pair = associate(truth, est)
            if pair is None:
                warnings.append(f"robot {k}: no {kind} pose within {ASSOC_MAX_DIFF_S} s of a truth pose")
                continue
            ref, out = pair
            metric = ape(ref, out)
            tracks[(k, kind)] = Track(k, kind, ref, out, np.asarray(metric.error, float))
            block["associated"] = ref.num_poses
            block["ate_unaligned"] = _evo_stats(metric)
            block["rpe_per_m"] = rpe_per_metre(ref, out)[0]
    return tracks, robots_out


def align_swarm(tracks: list[Track]) -> tuple[SE2Alignment | None, dict[int, Stats]]:
    """Fit ONE SE(2) alignment over every track of ``tracks`` (one kind, all robots)
    and apply it to each (sets ``aligned`` and ``aligned_error_m``).  Returns the
    alignment (``None`` without tracks) and each robot's aligned ATE ``S``."""
    al = fit_se2(np.vstack([t.est_xy for t in tracks]), np.vstack([t.truth_xy for t in tracks])) if tracks else None
    per_robot: dict[int, Stats] = {}
    if al is None:
        return None, per_robot
    for t in tracks:
        # evo applies the one shared transform to every robot (left-multiplied: a map-frame change)
        t.aligned = copy.deepcopy(t.est)
        t.aligned.transform(al.matrix())
        metric = ape(t.truth, t.aligned)
        t.aligned_error_m = np.asarray(metric.error, float)
        per_robot[t.robot] = _evo_stats(metric)
    return al, per_robot


def swarm_trajectory_stats(tracks: list[Track], al: SE2Alignment | None) -> dict[str, Any]:
    """The pooled trajectory part of ``metrics.json`` ``swarm.<kind>`` for aligned
    ``tracks`` (one kind): ``ate_unaligned``, ``ate_aligned``, ``alignment``, ``rpe_per_m``."""
    rpe_errors = [rpe_per_metre(t.truth, t.est)[1] for t in tracks]
    return {
        "ate_unaligned": _pooled_ape([t.truth for t in tracks], [t.est for t in tracks]),
        "ate_aligned": _pooled_ape([t.truth for t in tracks], [t.aligned for t in tracks if t.aligned is not None]),
        "alignment": al.as_dict() if al is not None else None,
        "rpe_per_m": pooled_stats(np.concatenate(rpe_errors)) if rpe_errors else None,
    }
