"""How good the agents' views of each other are, against the truth, by range (pure code).

Every robot-to-robot observation of a run (``observations.csv``: the target's base in the
observer's base frame, as the observer measured it) is compared with the same relative pose
from the two robots' true poses at the observation's stamp.  Its error is split in the
observer's frame along the true line of sight: *range* (measured distance minus true
distance, m; positive = the target seen farther than it is), *across* (the measured
position's offset perpendicular to the line of sight, m, positive to the observer's left of
it) and *yaw* (measured minus true relative heading, rad, wrapped).  The views are binned by
the true distance; a bin's mean is the views' systematic error at that range (it does not
average out over frames or observers), its RMS what a single view carries.

Measured on the built-in scenes with the default camera (320 x 240, 60 deg): nothing under
2 m, +7 to +11 mm at 3-4 m and +13 to +28 mm at 4-5 m on average, positive in every scene
(docs/benchmarks.md, "Where the conservative NEES comes from").
"""

from __future__ import annotations

import itertools
import math
from typing import Any

import numpy as np
from evo.core.trajectory import PoseTrajectory3D
from numpy.typing import NDArray

from tagswarm.evaluation.covframe import position_nees
from tagswarm.evaluation.runfolder import F64, Observations
from tagswarm.evaluation.trajerror import ASSOC_MAX_DIFF_S, trajectory_yaw

VIEW_RANGE_BINS_M: tuple[float, ...] = (0.0, 1.0, 2.0, 3.0, 4.0, 5.0, math.inf)
"""Bin edges (m) of the true observer-target distance; the last bin is open."""


def _xy_yaw(traj: PoseTrajectory3D) -> F64:
    """(N, 3) x, y, yaw of a planar trajectory."""
    return np.column_stack([np.asarray(traj.positions_xyz, float)[:, :2], trajectory_yaw(traj)])


def _at(stamps: F64, poses: F64, t_s: F64, max_diff_s: float) -> F64:
    """(N, 3) pose at each of ``t_s``, linearly interpolated between the two samples around it
    (yaw unwrapped); NaN where no sample lies within ``max_diff_s``."""
    out = np.full((t_s.size, 3), np.nan)
    if stamps.size == 0:
        return out
    j = np.clip(np.searchsorted(stamps, t_s), 0, stamps.size - 1)
    near = np.minimum(np.abs(stamps[j] - t_s), np.abs(stamps[np.maximum(j - 1, 0)] - t_s))
    ok = near <= max_diff_s
    yaw = np.unwrap(poses[:, 2])
    for i, col in enumerate((poses[:, 0], poses[:, 1], yaw)):
        out[ok, i] = np.interp(t_s[ok], stamps, col)
    return out


def view_errors(obs: Observations, truth: dict[int, PoseTrajectory3D | None],
                max_diff_s: float = ASSOC_MAX_DIFF_S) -> tuple[F64, F64, int]:
    """Robot views of ``obs`` against ``truth`` (map frame, per robot id): ``(true_range_m (N,),
    errors (N, 3) range / across / yaw, unmatched)`` for the N views whose observer and target
    both have a true pose within ``max_diff_s`` of the stamp and a finite measurement;
    ``unmatched`` counts the robot views without."""
    r, err, _, unmatched = _views(obs, truth, max_diff_s)
    return r, err, unmatched


def view_sigmas(true_rel: F64, meas: F64, cov: F64) -> F64:
    """(N, 4): per view, the standard deviation its own covariance ``cov`` (N, 3, 3; observer's
    axes, m², rad²) claims along and across the true line of sight (``true_rel`` (N, 3), m), the
    view's position NEES, e^T P^-1 e / 2 with e = ``meas`` - ``true_rel`` (x, y) and P the
    covariance's position block, and the claimed yaw standard deviation (rad).  NaN where the
    covariance is missing or not positive definite."""
    out = np.full((true_rel.shape[0], 4), np.nan)
    if true_rel.shape[0] == 0:
        return out
    p = np.asarray(cov, float)[:, :2, :2]
    r = np.hypot(true_rel[:, 0], true_rel[:, 1])
    u = true_rel[:, :2] / r[:, None]
    v = np.column_stack([-u[:, 1], u[:, 0]])
    det = p[:, 0, 0] * p[:, 1, 1] - p[:, 0, 1] * p[:, 1, 0]
    ok = np.isfinite(det) & (det > 0) & (p[:, 0, 0] > 0)
    for i, w in enumerate((u, v)):
        out[ok, i] = np.sqrt(np.einsum("ni,nij,nj->n", w[ok], p[ok], w[ok]))
    e = meas[ok, :2] - true_rel[ok, :2]
    out[ok, 2] = position_nees(p[ok, 0, 0], p[ok, 0, 1], p[ok, 1, 1], e[:, 0], e[:, 1])
    out[ok, 3] = np.sqrt(np.maximum(np.asarray(cov, float)[ok, 2, 2], 0.0))
    return out


def _views(obs: Observations, truth: dict[int, PoseTrajectory3D | None],
           max_diff_s: float) -> tuple[F64, F64, F64, int]:
    """:func:`view_errors` plus, per matched view, :func:`view_sigmas` (N, 4)."""
    robot = np.flatnonzero(obs.is_robot)
    stamps = obs.stamp_s[robot]
    poses = {k: (np.asarray(tr.timestamps, float), _xy_yaw(tr)) for k, tr in truth.items()
             if tr is not None and len(tr.timestamps) > 0}

    def true_poses(ids: NDArray[np.int64]) -> F64:
        out = np.full((ids.size, 3), np.nan)
        for k in np.unique(ids):
            if int(k) in poses:
                sel = ids == k
                out[sel] = _at(*poses[int(k)], stamps[sel], max_diff_s)
        return out

    a, b = true_poses(obs.observer[robot]), true_poses(obs.target_id[robot])
    d = b[:, :2] - a[:, :2]
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    true_rel = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], b[:, 2] - a[:, 2]])
    meas = obs.rel[robot]
    true_range = np.hypot(true_rel[:, 0], true_rel[:, 1])
    ok = np.all(np.isfinite(true_rel), axis=1) & np.all(np.isfinite(meas), axis=1) & (true_range > 0)
    tr, m, r = true_rel[ok], meas[ok], true_range[ok]
    along = np.hypot(m[:, 0], m[:, 1]) - r
    across = (tr[:, 0] * m[:, 1] - tr[:, 1] * m[:, 0]) / r
    yaw = (m[:, 2] - tr[:, 2] + math.pi) % (2 * math.pi) - math.pi
    sig = view_sigmas(tr, m, obs.covariances()[robot][ok])
    return r, np.column_stack([along, across, yaw]), sig, int(robot.size - np.count_nonzero(ok))


def view_error_by_range(obs: Observations, truth: dict[int, PoseTrajectory3D | None]) -> dict[str, Any]:
    """``{"views", "unmatched", "bins"}``: the robot views' errors (see :func:`view_errors`) per
    bin of :data:`VIEW_RANGE_BINS_M`: ``{"lo_m", "hi_m" (null = open), "count", "range_bias_m",
    "range_rmse_m", "across_bias_m", "across_rmse_m", "yaw_bias_rad", "yaw_rmse_rad"}`` (the
    errors ``null`` in an empty bin), and what the views' own covariances claim
    (:func:`view_sigmas`): ``"range_sigma_m"``, ``"across_sigma_m"`` and ``"yaw_sigma_rad"`` (RMS
    of the claimed standard deviations) and ``"nees"`` (mean position NEES, 1 when the claim is honest; below,
    the observers claim worse than they see), ``null`` when no view of the bin has a covariance."""
    r, err, sig, unmatched = _views(obs, truth, ASSOC_MAX_DIFF_S)
    bins = []
    for lo, hi in itertools.pairwise(VIEW_RANGE_BINS_M):
        sel = (r >= lo) & (r < hi)
        row: dict[str, Any] = {"lo_m": lo, "hi_m": hi if math.isfinite(hi) else None, "count": int(sel.sum())}
        for i, name in enumerate(("range", "across", "yaw")):
            unit = "rad" if name == "yaw" else "m"
            e = err[sel, i]
            row[f"{name}_bias_{unit}"] = float(np.mean(e)) if e.size else None
            row[f"{name}_rmse_{unit}"] = float(np.sqrt(np.mean(e**2))) if e.size else None
        claimed = sig[sel & np.isfinite(sig[:, 2])]
        row["range_sigma_m"] = float(np.sqrt(np.mean(claimed[:, 0] ** 2))) if claimed.size else None
        row["across_sigma_m"] = float(np.sqrt(np.mean(claimed[:, 1] ** 2))) if claimed.size else None
        row["nees"] = float(np.mean(claimed[:, 2])) if claimed.size else None
        row["yaw_sigma_rad"] = float(np.sqrt(np.mean(claimed[:, 3] ** 2))) if claimed.size else None
        bins.append(row)
    return {"views": int(r.size), "unmatched": unmatched, "bins": bins}
