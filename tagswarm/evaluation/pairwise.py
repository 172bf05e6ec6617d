"""Multi-robot errors for :mod:`tagswarm.evaluation.metrics` that evo lacks: the pairwise
(formation) error, and the error against the distance to the nearest robot involved
in an observation (the paper's claim that the error shrinks as robots get closer).

Pure code.  Positions and errors are metres in the MAP frame, timestamps simulation
seconds; the inputs are :class:`~tagswarm.evaluation.trajerror.Track` objects (estimates
already associated with their truth).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
from evo.core import sync as evo_sync
from numpy.typing import NDArray

from tagswarm.evaluation.runfolder import F64, Observations, RunData
from tagswarm.evaluation.trajerror import ASSOC_MAX_DIFF_S, Track

NEIGHBOUR_WINDOW_S = 0.5
"""± window (s) around a fused sample in which an observation makes a robot a neighbour."""
DISTANCE_BINS_M: tuple[float, ...] = (0.0, 1.0, 2.0, 3.0, 4.0, math.inf)
"""Bin edges (m) of the error-vs-distance helper; the last bin is open."""


def pairwise_error(tracks: list[Track], max_diff: float = ASSOC_MAX_DIFF_S) -> dict[str, float | int] | None:
    """Formation error over every robot pair of ``tracks`` (one kind): at the pair's
    common timestamps (evo's ``matching_time_indices``), | |p_i - p_j|_est - |p_i - p_j|_true |,
    metres.  ``{"rmse", "max", "count", "pairs"}`` or ``None`` with fewer than two tracks
    or no common timestamp."""
    errors: list[F64] = []
    pairs = 0
    for n, ti in enumerate(tracks):
        for tj in tracks[n + 1:]:
            ii, jj = evo_sync.matching_time_indices(ti.stamps_s, tj.stamps_s, max_diff)
            if not ii:
                continue
            pairs += 1
            d_est = np.linalg.norm(ti.est_xy[ii] - tj.est_xy[jj], axis=1)
            d_true = np.linalg.norm(ti.truth_xy[ii] - tj.truth_xy[jj], axis=1)
            errors.append(np.abs(d_est - d_true))
    if not errors:
        return None
    e = np.concatenate(errors)
    return {"rmse": float(np.sqrt(np.mean(e**2))), "max": float(np.max(e)), "count": int(e.size), "pairs": pairs}


@dataclass
class DistanceSamples:
    """Error against distance to the nearest observing/observed robot: one entry per
    fused sample that had such a neighbour (robot id, time s, distance m, error m)."""

    robot: NDArray[np.int64]
    stamp_s: F64
    distance_m: F64
    error_m: F64
    unobserved: int


def _observation_times(obs: Observations) -> dict[tuple[int, int], F64]:
    """Sorted stamps (s) of robot-robot observations per unordered pair (min id, max id)."""
    table: dict[tuple[int, int], list[float]] = {}
    for t, a, is_robot, b in zip(obs.stamp_s, obs.observer, obs.is_robot, obs.target_id, strict=True):
        if is_robot and a != b:
            table.setdefault((int(min(a, b)), int(max(a, b))), []).append(float(t))
    return {k: np.sort(np.array(v)) for k, v in table.items()}


def _any_within(times: F64, t: F64, window: float) -> NDArray[np.bool_]:
    """For each t, whether some value of sorted ``times`` lies in [t - window, t + window]."""
    idx = np.searchsorted(times, t - window, side="left")
    ok = idx < len(times)
    hit = np.zeros(len(t), bool)
    hit[ok] = times[idx[ok]] <= t[ok] + window
    return hit


def error_vs_distance(run: RunData, tracks: dict[tuple[int, str], Track],
                      window_s: float = NEIGHBOUR_WINDOW_S) -> DistanceSamples:
    """For each associated fused sample of robot k at time t: the true distance (m) at t
    to the nearest robot j with an observation k->j or j->k stamped within ± ``window_s``,
    and the sample's unaligned position error (m).  Samples without such a neighbour
    are only counted (``unobserved``)."""
    pair_times = _observation_times(run.observations)
    rob, st, dist, err = [], [], [], []
    unobserved = 0
    for k in run.robots:
        tr = tracks.get((k, "fused"))
        if tr is None:
            continue
        t = tr.stamps_s
        nearest: F64 = np.full(len(t), np.inf)
        for j in run.robots:
            times = pair_times.get((min(j, k), max(j, k)))
            truth_j = run.truth.get(j)
            if j == k or times is None or truth_j is None:
                continue
            tj = np.asarray(truth_j.timestamps, float)
            # only where j's truth covers t: np.interp would otherwise clamp silently
            ok = _any_within(times, t, window_s) & (t >= tj[0] - ASSOC_MAX_DIFF_S) & (t <= tj[-1] + ASSOC_MAX_DIFF_S)
            pj = np.column_stack([np.interp(t, tj, truth_j.positions_xyz[:, 0]),
                                  np.interp(t, tj, truth_j.positions_xyz[:, 1])])
            d = np.linalg.norm(pj - tr.truth_xy, axis=1)
            nearest = np.where(ok, np.minimum(nearest, d), nearest)
        seen = np.isfinite(nearest)
        unobserved += int(np.count_nonzero(~seen))
        rob.append(np.full(int(seen.sum()), k, np.int64))
        st.append(t[seen])
        dist.append(nearest[seen])
        err.append(tr.error_m[seen])
    if not rob:
        return DistanceSamples(np.zeros(0, np.int64), np.zeros(0), np.zeros(0), np.zeros(0), unobserved)
    return DistanceSamples(np.concatenate(rob), np.concatenate(st), np.concatenate(dist), np.concatenate(err),
                           unobserved)


def bin_by_distance(distance_m: F64, error_m: F64,
                    edges: tuple[float, ...] = DISTANCE_BINS_M) -> list[dict[str, float | int | None]]:
    """Errors binned by distance: ``[{"lo_m", "hi_m", "count", "median_error_m",
    "mean_error_m"}]``, lo <= d < hi; ``hi_m`` ``None`` for an open last bin."""
    d, e = np.asarray(distance_m, float), np.asarray(error_m, float)
    out: list[dict[str, float | int | None]] = []
    for lo, hi in itertools.pairwise(edges):
        sel = e[(d >= lo) & (d < hi)]
        out.append({"lo_m": float(lo), "hi_m": float(hi) if math.isfinite(hi) else None, "count": int(sel.size),
                    "median_error_m": float(np.median(sel)) if sel.size else None,
                    "mean_error_m": float(np.mean(sel)) if sel.size else None})
    return out
