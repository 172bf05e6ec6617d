"""Evaluation of one run folder: trajectory errors, formation error, behaviour and cost.

Pure code (files in, numbers out; no plotting, no network).  ATE and RPE are evo's
(``evo.core.metrics.APE`` / ``RPE`` on ``PoseTrajectory3D``); what evo lacks and
this module adds is the *multi-robot* part: ONE SE(2) alignment shared by every
robot, the pairwise (formation) error, and error against the distance to the
nearest robot involved in an observation.

Frames and units
----------------
Every pose is in the MAP frame (the origin robot's first pose, or the arena frame
when the scenario has landmarks; see :func:`protocol.layout.arena_to_map`).
Positions and errors are metres, angles radians, timestamps simulation-time
seconds (``stamp_ns`` columns are converted).  Estimates are associated with the
truth by timestamp (evo ``associate_trajectories``, linear/slerp interpolation of
the denser trajectory, at most :data:`ASSOC_MAX_DIFF_S` apart).

Inputs (the run folder contract)
--------------------------------
``run.json``, ``trajectories/{truth,odom,fused}_<k>.tum``, ``observations.csv``,
``modes.csv``; see :func:`load_run`.  A missing or empty ``fused_<k>.tum`` means
robot k was never localised: its fused metrics are ``null``.

``metrics.json`` fields (the dict returned by :func:`compute_metrics`)
---------------------------------------------------------------------
``S`` below is an error-statistics object ``{"rmse", "mean", "median", "max",
"count"}`` (metres; ``count`` = number of errors pooled) or ``null`` when there is
nothing to evaluate.  ``E`` is a per-estimate block, given for ``"fused"`` (the
server's fused estimate) and for ``"odom"`` (dead reckoning only, started from
the true initial pose, so its error is pure drift).

- ``schema``: ``"tagswarm.metrics/1"``.
- ``run``: ``clock`` ("lockstep"/"realtime"), ``sim_time_s``, ``wall_time_s``,
  ``exit_code``, ``failure`` (the orchestrator's failure message or ``null``),
  ``origin_id``, ``robots`` (ids), copied from ``run.json``.
- ``settings``: ``assoc_max_diff_s`` (timestamp association tolerance, s),
  ``rpe_delta_m`` (RPE segment length, m), ``neighbour_window_s`` (± window for
  error-vs-distance, s), ``distance_bins_m`` (bin edges, m; ``null`` = infinity).
- ``cost``: ``wall_time_s``; ``sim_time_s``; ``real_time_factor`` = sim/wall
  (``null`` if wall time is 0 or unknown); ``frames_rendered`` (world total);
  ``frames_rendered_per_robot`` (that total / number of robots);
  ``frames_processed`` and ``frames_skipped`` (sums over agents; per robot in
  ``robots``).
- ``swarm``: pooled over all robots.
  - ``fused`` / ``odom`` (each):
    - ``ate_unaligned`` S: position error |p_est - p_true| in the map frame, every
      associated sample of every robot.
    - ``ate_aligned`` S: the same after ONE SE(2) alignment shared by all robots.
    - ``alignment``: that alignment, ``{"yaw_rad", "x_m", "y_m", "points"}``:
      p_aligned = R(yaw) p_est + (x, y), the least-squares fit (2-D Kabsch /
      Umeyama without scale) over ``points`` associated samples of all robots at
      once; ``null`` if there are none.  Removes the drift of the swarm as a
      whole (unobservable from relative measurements alone).
    - ``rpe_per_m`` S: evo RPE, translation part, over consecutive segments of
      ``rpe_delta_m`` of TRUE path length: metres of error per metre travelled;
      ``null`` if no robot travelled that far.
    - ``pairwise`` ``{"rmse", "max", "count", "pairs"}``: formation error
      | |p_i - p_j|_est - |p_i - p_j|_true | over every robot pair i < j at their
      common associated timestamps (m; ``count`` samples over ``pairs`` robot
      pairs); alignment-invariant.  ``null`` with fewer than two evaluable robots.
    - ``robots_evaluated``: robots with at least one associated sample.
  - ``fixes``, ``searches``, ``lost_events``: sums of the agents' counters
    (visual fixes; re-localisation rotations started; full sweeps that found
    nobody); ``null`` if no agent reported counters.
  - ``time_lost_s``: total seconds spent in mode ``lost`` (see ``mode_time_s``).
  - ``mode_time_s``: ``{mode: seconds}`` summed over robots.
- ``robots``: ``{"<k>": {...}}`` per robot:
  - ``truth_samples``; ``path_length_m`` (true distance travelled, m).
  - ``fused`` / ``odom`` (each): ``samples`` (poses in the file), ``associated``
    (poses matched with the truth), ``first_s`` (first estimate's time, s),
    ``ate_unaligned`` S, ``ate_aligned`` S (under the swarm's shared alignment),
    ``rpe_per_m`` S.
  - ``fixes``, ``searches``, ``lost_events``, ``frames_processed``,
    ``frames_skipped``: that agent's counters from ``run.json`` (a name missing
    from a reported counter set counts 0; all ``null`` if the agent reported none).
  - ``time_lost_s``, ``mode_time_s``: from ``modes.csv``.  Each sample's mode
    holds until that robot's next sample; the last one until the end of the
    recorded truth (the latest truth timestamp of any robot).
- ``error_vs_distance``: for every associated fused sample of robot k at time t,
  the true distance at t to the nearest robot j such that j observed k or k
  observed j within ± ``neighbour_window_s``; its error is the unaligned fused
  position error.  ``samples`` (with such a neighbour), ``unobserved_samples``
  (without), ``bins``: ``[{"lo_m", "hi_m" (null = open), "count",
  "median_error_m", "mean_error_m"}]`` (errors ``null`` in an empty bin).
- ``warnings``: human-readable notes about missing or unusable inputs.
"""

from __future__ import annotations

import copy
import csv
import itertools
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from evo import EvoException
from evo.core import metrics as evo_metrics
from evo.core import sync as evo_sync
from evo.core.sync_method import SyncMethod
from evo.core.trajectory import PosePath3D, PoseTrajectory3D
from evo.core.units import Unit
from evo.tools import file_interface
from numpy.typing import NDArray

from protocol.geometry import se2_matrix

F64 = NDArray[np.float64]

SCHEMA = "tagswarm.metrics/1"
ASSOC_MAX_DIFF_S = 0.05
"""Largest time difference (s) for associating an estimate with the truth."""
RPE_DELTA_M = 1.0
"""RPE segment length (m of true path)."""
NEIGHBOUR_WINDOW_S = 0.5
"""± window (s) around a fused sample in which an observation makes a robot a neighbour."""
DISTANCE_BINS_M: tuple[float, ...] = (0.0, 1.0, 2.0, 3.0, 4.0, math.inf)
"""Bin edges (m) of the error-vs-distance helper; the last bin is open."""
KINDS = ("fused", "odom")
"""Estimates evaluated against ``truth``."""

OBS_HEADER = ("stamp_ns", "observer", "target_kind", "target_id", "x_m", "y_m", "yaw_rad")
MODES_HEADER = ("stamp_ns", "robot", "mode")


class RunFolderError(ValueError):
    """The run folder is missing or malformed; the message is one line naming the file."""


# --------------------------------------------------------------------------- loading


@dataclass(frozen=True)
class Observations:
    """Relative observations published by the agents (one row each of ``observations.csv``).
    ``stamp_s`` simulation seconds; ``target_id`` is a robot id when ``is_robot``,
    else a landmark tag id."""

    stamp_s: F64
    observer: NDArray[np.int64]
    is_robot: NDArray[np.bool_]
    target_id: NDArray[np.int64]

    @staticmethod
    def empty() -> Observations:
        return Observations(np.zeros(0), np.zeros(0, np.int64), np.zeros(0, bool), np.zeros(0, np.int64))


@dataclass(frozen=True)
class ModeSample:
    """One row of ``modes.csv``: robot ``robot`` was in ``mode`` at ``stamp_s`` (sim seconds)."""

    stamp_s: float
    robot: int
    mode: str


@dataclass
class RunData:
    """A loaded run folder.  Trajectories are in the map frame; ``None`` means the file
    is missing or holds no pose."""

    path: Path
    info: dict[str, Any]
    robots: tuple[int, ...]
    truth: dict[int, PoseTrajectory3D | None]
    odom: dict[int, PoseTrajectory3D | None]
    fused: dict[int, PoseTrajectory3D | None]
    observations: Observations
    modes: list[ModeSample]
    warnings: list[str] = field(default_factory=list)

    def estimate(self, kind: str, robot: int) -> PoseTrajectory3D | None:
        """The ``kind`` ("fused"/"odom") trajectory of ``robot``."""
        table = self.fused if kind == "fused" else self.odom
        return table.get(robot)


def read_tum(path: Path) -> PoseTrajectory3D | None:
    """A TUM trajectory (``t x y z qx qy qz qw``, seconds/metres) read by evo, or
    ``None`` if the file is missing or has no pose line.  Raises
    :class:`RunFolderError` on a malformed file."""
    if not path.is_file():
        return None
    try:
        text = path.read_text()
    except OSError as exc:
        raise RunFolderError(f"cannot read {path}: {exc.strerror}") from None
    # evo refuses empty files; an empty fused file is a legal "never localised"
    if not any(line.strip() and not line.lstrip().startswith("#") for line in text.splitlines()):
        return None
    try:
        traj = file_interface.read_tum_trajectory_file(str(path))
    except (EvoException, ValueError) as exc:
        raise RunFolderError(f"{path}: not a TUM trajectory ({exc})") from None
    if not np.all(np.isfinite(traj.positions_xyz)) or not np.all(np.isfinite(traj.timestamps)):
        raise RunFolderError(f"{path}: non-finite value in a pose")
    if np.any(np.diff(traj.timestamps) < 0):
        # evo's association assumes sorted stamps; sorting keeps a hand-made file usable
        order = np.argsort(traj.timestamps, kind="stable")
        traj.reduce_to_ids(order)
    return traj


def _read_csv(path: Path, header: tuple[str, ...], warnings: list[str]) -> list[dict[str, str]]:
    if not path.is_file():
        warnings.append(f"{path.name} is missing")
        return []
    try:
        with path.open(newline="") as f:
            reader = csv.DictReader(f)
            fields = tuple(reader.fieldnames or ())
            if fields[: len(header)] != header:
                raise RunFolderError(f"{path}: header must start with {','.join(header)}, got {','.join(fields)}")
            return list(reader)
    except OSError as exc:
        raise RunFolderError(f"cannot read {path}: {exc.strerror}") from None


def _int(value: str, path: Path, line: int, name: str) -> int:
    try:
        return int(value)
    except (TypeError, ValueError):
        raise RunFolderError(f"{path}:{line}: {name} must be an integer, got {value!r}") from None


def read_observations(path: Path, warnings: list[str]) -> Observations:
    """``observations.csv`` (header :data:`OBS_HEADER`); only who saw whom and when is kept."""
    rows = _read_csv(path, OBS_HEADER, warnings)
    if not rows:
        return Observations.empty()
    stamps, observers, robot, target = [], [], [], []
    for i, r in enumerate(rows, start=2):
        stamps.append(_int(r["stamp_ns"], path, i, "stamp_ns") / 1e9)
        observers.append(_int(r["observer"], path, i, "observer"))
        kind = (r["target_kind"] or "").strip()
        if kind not in ("robot", "landmark"):
            raise RunFolderError(f"{path}:{i}: target_kind must be robot or landmark, got {kind!r}")
        robot.append(kind == "robot")
        target.append(_int(r["target_id"], path, i, "target_id"))
    return Observations(np.array(stamps, float), np.array(observers, np.int64), np.array(robot, bool),
                        np.array(target, np.int64))


def read_modes(path: Path, warnings: list[str]) -> list[ModeSample]:
    """``modes.csv`` (header :data:`MODES_HEADER`), sorted by time."""
    out = []
    for i, r in enumerate(_read_csv(path, MODES_HEADER, warnings), start=2):
        out.append(ModeSample(_int(r["stamp_ns"], path, i, "stamp_ns") / 1e9, _int(r["robot"], path, i, "robot"),
                              (r["mode"] or "").strip()))
    return sorted(out, key=lambda s: (s.robot, s.stamp_s))


def load_run(run_dir: Path) -> RunData:
    """Read a run folder.  Raises :class:`RunFolderError` if it is not a directory, has
    no readable ``run.json`` with a ``robots`` list, or holds a malformed file.  Missing
    optional inputs (a robot's trajectories, the CSV files) become warnings."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise RunFolderError(f"{run_dir} is not a run folder (no such directory)")
    info_path = run_dir / "run.json"
    if not info_path.is_file():
        raise RunFolderError(f"{run_dir} is not a run folder (no run.json)")
    try:
        info = json.loads(info_path.read_text())
    except (OSError, ValueError) as exc:
        raise RunFolderError(f"{info_path}: cannot be parsed ({exc})") from None
    if not isinstance(info, dict):
        raise RunFolderError(f"{info_path}: must hold a JSON object")
    robots = info.get("robots")
    if not isinstance(robots, list) or not all(isinstance(r, int) and not isinstance(r, bool) for r in robots):
        raise RunFolderError(f"{info_path}: 'robots' must be a list of robot ids")
    warnings: list[str] = []
    traj_dir = run_dir / "trajectories"
    tables: dict[str, dict[int, PoseTrajectory3D | None]] = {"truth": {}, "odom": {}, "fused": {}}
    for k in robots:
        for kind, table in tables.items():
            table[k] = read_tum(traj_dir / f"{kind}_{k}.tum")
            if table[k] is None and kind != "fused":
                warnings.append(f"robot {k}: no {kind} trajectory")
    return RunData(
        path=run_dir, info=info, robots=tuple(robots), truth=tables["truth"], odom=tables["odom"],
        fused=tables["fused"], observations=read_observations(run_dir / "observations.csv", warnings),
        modes=read_modes(run_dir / "modes.csv", warnings), warnings=warnings,
    )


# --------------------------------------------------------------------------- trajectory metrics (evo)


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
                  delta_m: float = RPE_DELTA_M) -> tuple[dict[str, float | int] | None, F64]:
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


def _evo_stats(metric: Any) -> dict[str, float | int]:
    s = metric.get_all_statistics()
    return {"rmse": float(s["rmse"]), "mean": float(s["mean"]), "median": float(s["median"]),
            "max": float(s["max"]), "count": len(metric.error)}


def pooled_stats(errors: F64) -> dict[str, float | int] | None:
    """``S`` of errors pooled over robots (same definitions as evo's statistics)."""
    e = np.asarray(errors, float)
    if e.size == 0:
        return None
    return {"rmse": float(np.sqrt(np.mean(e**2))), "mean": float(np.mean(e)), "median": float(np.median(e)),
            "max": float(np.max(e)), "count": int(e.size)}


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


# --------------------------------------------------------------------------- evaluation


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


@dataclass
class DistanceSamples:
    """Error against distance to the nearest observing/observed robot: one entry per
    fused sample that had such a neighbour (robot id, time s, distance m, error m)."""

    robot: NDArray[np.int64]
    stamp_s: F64
    distance_m: F64
    error_m: F64
    unobserved: int


@dataclass
class Evaluation:
    """Everything :func:`evaluate` derived from a run: the JSON-able ``metrics`` plus the
    arrays the plots need."""

    run: RunData
    tracks: dict[tuple[int, str], Track]
    alignment: dict[str, SE2Alignment | None]
    distance: DistanceSamples
    metrics: dict[str, Any]


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


def mode_durations(samples: list[ModeSample], end_s: float | None) -> dict[int, dict[str, float]]:
    """Seconds per mode per robot: each sample's mode holds until that robot's next
    sample; the last one until ``end_s`` (nothing if ``end_s`` is ``None`` or earlier)."""
    by_robot: dict[int, list[ModeSample]] = {}
    for s in samples:
        by_robot.setdefault(s.robot, []).append(s)
    out: dict[int, dict[str, float]] = {}
    for rid, rows in by_robot.items():
        rows = sorted(rows, key=lambda s: s.stamp_s)
        acc: dict[str, float] = {}
        for cur, nxt in zip(rows, [*rows[1:], None], strict=True):
            stop = nxt.stamp_s if nxt is not None else (end_s if end_s is not None else cur.stamp_s)
            acc[cur.mode] = acc.get(cur.mode, 0.0) + max(0.0, stop - cur.stamp_s)
        out[rid] = acc
    return out


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


def _num(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        return None
    return float(value)


def _dict(value: Any) -> dict[str, Any]:
    return value if isinstance(value, dict) else {}


def _counter(counters: dict[str, Any], name: str) -> int | None:
    v = counters.get(name)
    return int(v) if isinstance(v, int | float) and not isinstance(v, bool) else None


def _sum(values: list[int | None]) -> int | None:
    known = [v for v in values if v is not None]
    return sum(known) if known else None


def evaluate(run: RunData) -> Evaluation:
    """Compute every metric of a loaded run (see the module docstring for the fields)."""
    warnings = list(run.warnings)
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

    swarm: dict[str, Any] = {}
    alignment: dict[str, SE2Alignment | None] = {}
    for kind in KINDS:
        ts = [tracks[(k, kind)] for k in run.robots if (k, kind) in tracks]
        al = fit_se2(np.vstack([t.est_xy for t in ts]), np.vstack([t.truth_xy for t in ts])) if ts else None
        alignment[kind] = al
        rpe_errors: list[F64] = []
        for t in ts:
            if al is not None:
                # evo applies the one shared transform to every robot (left-multiplied: a map-frame change)
                t.aligned = copy.deepcopy(t.est)
                t.aligned.transform(al.matrix())
                metric = ape(t.truth, t.aligned)
                t.aligned_error_m = np.asarray(metric.error, float)
                robots_out[str(t.robot)][kind]["ate_aligned"] = _evo_stats(metric)
            rpe_errors.append(rpe_per_metre(t.truth, t.est)[1])
        swarm[kind] = {
            "ate_unaligned": _pooled_ape([t.truth for t in ts], [t.est for t in ts]),
            "ate_aligned": _pooled_ape([t.truth for t in ts], [t.aligned for t in ts if t.aligned is not None]),
            "alignment": al.as_dict() if al is not None else None,
            "rpe_per_m": pooled_stats(np.concatenate(rpe_errors)) if rpe_errors else None,
            "pairwise": pairwise_error(ts),
            "robots_evaluated": len(ts),
        }

    # behaviour: counters from run.json, time per mode from modes.csv
    counters = _dict(run.info.get("counters"))
    truth_ends = [float(t.timestamps[-1]) for t in run.truth.values() if t is not None]
    durations = mode_durations(run.modes, max(truth_ends) if truth_ends else None)
    for k in run.robots:
        agent = _dict(counters.get(f"agent/{k}"))
        r = robots_out[str(k)]
        for name in ("fixes", "searches", "lost_events", "frames_processed", "frames_skipped"):
            # agents report a Counter: a name it never incremented is absent, i.e. zero
            r[name] = _counter(agent, name) if name in agent or not agent else 0
        modes = durations.get(k, {})
        r["mode_time_s"] = dict(sorted(modes.items()))
        r["time_lost_s"] = float(modes.get("lost", 0.0))
    for name in ("fixes", "searches", "lost_events"):
        swarm[name] = _sum([robots_out[str(k)][name] for k in run.robots])
    total_modes: dict[str, float] = {}
    for k in run.robots:
        for mode, secs in robots_out[str(k)]["mode_time_s"].items():
            total_modes[mode] = total_modes.get(mode, 0.0) + secs
    swarm["mode_time_s"] = dict(sorted(total_modes.items()))
    swarm["time_lost_s"] = float(total_modes.get("lost", 0.0))
    if not run.modes:
        warnings.append("no mode samples: time_lost_s is 0")

    # cost
    sim_s, wall_s = _num(run.info.get("sim_time_s")), _num(run.info.get("wall_time_s"))
    rendered = _counter(_dict(counters.get("world")), "frames_rendered")
    cost = {
        "wall_time_s": wall_s,
        "sim_time_s": sim_s,
        "real_time_factor": sim_s / wall_s if sim_s is not None and wall_s else None,
        "frames_rendered": rendered,
        "frames_rendered_per_robot": rendered / len(run.robots) if rendered is not None and run.robots else None,
        "frames_processed": _sum([robots_out[str(k)]["frames_processed"] for k in run.robots]),
        "frames_skipped": _sum([robots_out[str(k)]["frames_skipped"] for k in run.robots]),
    }

    dist = error_vs_distance(run, tracks)
    metrics: dict[str, Any] = {
        "schema": SCHEMA,
        "run": {"clock": run.info.get("clock"), "sim_time_s": sim_s, "wall_time_s": wall_s,
                "exit_code": run.info.get("exit_code"), "failure": run.info.get("failure"),
                "origin_id": run.info.get("origin_id"),
                "robots": list(run.robots)},
        "settings": {"assoc_max_diff_s": ASSOC_MAX_DIFF_S, "rpe_delta_m": RPE_DELTA_M,
                     "neighbour_window_s": NEIGHBOUR_WINDOW_S,
                     "distance_bins_m": [e if math.isfinite(e) else None for e in DISTANCE_BINS_M]},
        "cost": cost,
        "swarm": swarm,
        "robots": robots_out,
        "error_vs_distance": {"samples": int(dist.error_m.size), "unobserved_samples": dist.unobserved,
                              "bins": bin_by_distance(dist.distance_m, dist.error_m)},
        "warnings": warnings,
    }
    return Evaluation(run=run, tracks=tracks, alignment=alignment, distance=dist, metrics=_finite(metrics))


def _finite(value: Any) -> Any:
    """``value`` with NaN/inf floats replaced by ``None`` and numpy scalars by Python ones,
    so that ``json.dumps(..., allow_nan=False)`` accepts it (strict JSON has no NaN)."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _pooled_ape(refs: list[PoseTrajectory3D], ests: list[PoseTrajectory3D]) -> dict[str, float | int] | None:
    """evo APE over all robots at once: their associated poses concatenated into one path."""
    if not refs or len(refs) != len(ests):
        return None
    ref = PosePath3D(poses_se3=[p for r in refs for p in r.poses_se3])
    est = PosePath3D(poses_se3=[p for e in ests for p in e.poses_se3])
    return _evo_stats(ape(ref, est))


def compute_metrics(run_dir: Path) -> dict[str, Any]:
    """The metrics of a run folder as a JSON-able dict (fields: see the module docstring).
    Raises :class:`RunFolderError` for a missing or malformed folder."""
    return evaluate(load_run(Path(run_dir))).metrics
