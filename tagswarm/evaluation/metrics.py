"""Evaluation of one run folder: trajectory errors, formation error, behaviour and cost.

Pure code (files in, numbers out; no plotting, no network).  ATE and RPE are evo's
(``evo.core.metrics.APE`` / ``RPE`` on ``PoseTrajectory3D``); what evo lacks and
tagswarm adds is the *multi-robot* part: ONE SE(2) alignment shared by every
robot, the pairwise (formation) error, and error against the distance to the
nearest robot involved in an observation.

This module assembles ``metrics.json`` and re-exports the public names of the
modules that compute it (import them from here):

- :mod:`tagswarm.evaluation.runfolder`: reading the run folder (:func:`load_run`).
- :mod:`tagswarm.evaluation.trajerror`: association, ATE/RPE via evo, the shared SE(2) alignment.
- :mod:`tagswarm.evaluation.pairwise`: pairwise (formation) error, error against distance.
- :mod:`tagswarm.evaluation.runsummary`: behaviour (counters, time per mode) and cost.
- :mod:`tagswarm.evaluation.recovery`: time localised, kidnaps and recovery, re-localisation
  events, contacts, NEES.

Frames and units
----------------
Every pose is in the MAP frame (the origin robot's first pose, or the arena frame
when the scenario has landmarks; see :func:`tagswarm.protocol.layout.arena_to_map`).
Positions and errors are metres, angles radians, timestamps simulation-time
seconds (``stamp_ns`` columns are converted).  Estimates are associated with the
truth by timestamp (evo ``associate_trajectories``, linear/slerp interpolation of
the denser trajectory, at most :data:`ASSOC_MAX_DIFF_S` apart).

Inputs (the run folder contract)
--------------------------------
``run.json``, ``trajectories/{truth,odom,fused}_<k>.tum``, ``observations.csv``,
``modes.csv``; see :func:`load_run`.  A missing or empty ``fused_<k>.tum`` means
robot k was never localised: its fused metrics are ``null``.  Optional (older run
folders lack them; formats in :mod:`tagswarm.evaluation.runformat`):
``trajectories/fused_cov_<k>.csv`` (the published fused covariance),
``relocalisations.csv`` (the server's re-localisation events),
``world_commands.csv`` (kidnaps sent on the network) and ``interventions.csv`` (the
teleports and pushes the world applied).

"Localised" at time t (used by ``time_localised`` and ``time_to_relocalise_s``):
the newest fused estimate at or before t is at most ``localised_hold_s`` old and
its position error is below ``localised_m``; sampled on the robot's truth stamps,
each sample holding until the next (time-weighted), so the time before a robot's
first fused estimate and gaps in its corrections count as not localised.

``metrics.json`` fields (the dict returned by :func:`compute_metrics`)
---------------------------------------------------------------------
``S`` below is an error-statistics object ``{"rmse", "mean", "median", "max",
"count"}`` (metres; ``count`` = number of errors pooled) or ``null`` when there is
nothing to evaluate.  ``E`` is a per-estimate block, given for ``"fused"`` (the
server's fused estimate) and for ``"odom"`` (dead reckoning only, started from
the true initial pose, so its error is pure drift).

- ``schema``: ``"tagswarm.evaluation.metrics/1"``.
- ``run``: ``clock`` ("lockstep"/"realtime"), ``sim_time_s``, ``wall_time_s``,
  ``exit_code``, ``failure`` (the orchestrator's failure message or ``null``),
  ``origin_id``, ``robots`` (ids), copied from ``run.json``; ``method``, the server's
  ``[server] method`` (``"graph"`` or ``"stitch"``, from the scenario in ``run.json``);
  ``silent_sources`` ``{source: last heard s}``: the world, server or agents the
  recorder stopped hearing over 2 s before the end (their data is incomplete; also
  a warning), from ``run.json`` ``last_heard_s``; ``landmarks``, how many fixed tags
  the scenario has (they, not the origin robot, fix the map frame then).
- ``settings``: ``assoc_max_diff_s`` (timestamp association tolerance, s),
  ``rpe_delta_m`` (RPE segment length, m), ``neighbour_window_s`` (± window for
  error-vs-distance, s), ``distance_bins_m`` (bin edges, m; ``null`` = infinity),
  ``localised_m`` (0.10 m), ``localised_hold_s`` (0.5 s), ``recovered_stay_s``
  (1.0 s): see "Localised" above and ``kidnaps``.
- ``cost``: ``wall_time_s`` (the whole run, processes' start-up and shutdown included);
  ``sim_time_s``; ``stepping_wall_s`` (the wall time the world spent stepping, ``null`` in
  older run folders); ``real_time_factor`` = sim / stepping wall (whether the simulation kept
  real time; sim / whole wall where the stepping time is unknown); ``run_real_time_factor`` =
  sim / whole wall (``null`` if wall time is 0 or unknown); ``frames_rendered`` (world total: the
  world's own renders, or the sum over its render workers' ``render/<i>`` statuses);
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
    - ``time_localised``: share (0..1) of robot-time localised, pooled over every
      robot with at least two truth poses (time-weighted: each robot's evaluated
      time is its truth span); for ``odom``, how long dead reckoning alone stays
      within ``localised_m``.  ``null`` if no robot has a truth span.
    - ``fused.time_localised_placed``: the same share counted only from each
      robot's first fused estimate on (start-up acquisition left out; robots never
      placed add no time): tracking quality once placed.
  - ``fused.nees``: ``{"mean", "median", "count"}`` of the normalised estimation
    error squared of the fused 2-D position, pooled over robots: e^T P^-1 e / 2
    per fused sample, e the map-frame position error and P the 2x2 position block
    of the published covariance at that stamp (within ``assoc_max_diff_s``)
    rotated into the map frame by the estimate's yaw (it is in the robot's own
    axes, see :mod:`tagswarm.evaluation.covframe`); 1 for a consistent estimator, above 1 an
    over-confident one.  Samples whose block is not positive definite are
    skipped.  ``null`` when no covariance was recorded.
  - ``fused.nees_nominal``: the same without each kidnapped robot's samples from the
    kidnap until it is localised again (a kidnap is outside the fusion's model).
  - ``fused.ate_unaligned_nominal`` S: ``ate_unaligned`` without those samples either
    (tracking quality outside the kidnaps, whose cost ``kidnaps`` measures in seconds).
  - ``relocalisations``: number of re-localisation events (see the top-level list).
  - ``kidnaps``: ``{"count", "recovered"`` (kidnaps with a
    ``time_to_relocalise_s``), ``"mean_time_to_relocalise_s"``,
    ``"max_time_to_relocalise_s"}`` (``null`` when none recovered).
  - ``contacts``: ``{"robot_robot", "robot_obstacle", "robot_wall"}``: the
    world's contact counters (``contacts_<kind>`` in ``run.json``
    ``counters.world``; counted by the world, see its docs); each ``null`` if the
    world reported no ``contacts_*`` counter at all (a name missing from a world
    that reported some counts 0).
  - ``fixes``, ``searches``, ``lost_events``, ``avoid_side_flips``, ``avoid_steps_aside``,
    ``avoid_gate_waits``: sums of the agents' counters (visual fixes; re-localisation rotations
    started; full sweeps that found nobody; avoidance stalls with no way round found; station
    keepers stepping aside for a robot they blocked; waits outside a passage too narrow for two while
    another robot came through it); ``null`` if no agent reported counters.
  - ``time_lost_s``: total seconds spent in mode ``lost`` (see ``mode_time_s``).
  - ``mode_time_s``: ``{mode: seconds}`` summed over robots.
- ``robots``: ``{"<k>": {...}}`` per robot:
  - ``truth_samples``; ``path_length_m`` (true distance travelled, m).
  - ``fused`` / ``odom`` (each): ``samples`` (poses in the file), ``associated``
    (poses matched with the truth), ``first_s`` (first estimate's time, s),
    ``ate_unaligned`` S, ``ate_aligned`` S (under the swarm's shared alignment),
    ``rpe_per_m`` S.
  - ``fixes``, ``searches``, ``lost_events``, ``frames_processed``,
    ``frames_skipped``, ``avoid_yields``, ``avoid_reroutes``, ``avoid_side_flips``
    (stalls of the collision avoidance: gave way, followed a way round the room,
    found none and tried the other side), ``avoid_steps_aside`` (a station keeper stepped
    aside for a robot it blocked), ``avoid_gate_waits`` (waited outside a narrow passage for a robot
    coming through, :mod:`tagswarm.agents.gates`): that agent's counters from ``run.json``
    (a name missing from a reported counter set counts 0; all ``null`` if the agent
    reported none).
  - ``fused.time_localised`` / ``odom.time_localised``: that robot's share of its
    truth span spent localised (``null`` with fewer than two truth poses); a
    robot never localised scores 0; ``fused.time_localised_placed`` from its first
    fused estimate on (``null`` if never placed).
  - ``fused.nees``, ``fused.nees_nominal``, ``fused.ate_unaligned_nominal``: as in
    ``swarm``, for this robot.
  - ``fused.sigma_median_m``: the median over its published covariances of the fused
    position's largest standard deviation (m; ``null`` without covariances): how
    sure the map is of this robot, whatever its error.
  - ``relocalisations``, ``kidnaps``: how many of the top-level events are this robot's.
  - ``contacts``: the world's ``contacts_robot_<k>`` counter (``null`` as in ``swarm``).
  - ``time_lost_s``, ``mode_time_s``: from ``modes.csv``.  Each sample's mode
    holds until that robot's next sample; the last one until the end of the
    recorded truth (the latest truth timestamp of any robot).
- ``error_vs_distance``: for every associated fused sample of robot k at time t,
  the true distance at t to the nearest robot j such that j observed k or k
  observed j within ± ``neighbour_window_s``; its error is the unaligned fused
  position error.  ``samples`` (with such a neighbour), ``unobserved_samples``
  (without), ``bins``: ``[{"lo_m", "hi_m" (null = open), "count",
  "median_error_m", "mean_error_m"}]`` (errors ``null`` in an empty bin).
- ``view_error_vs_range``: every robot's views of the others (``observations.csv``) against
  the truth at their stamps, binned by the true range (:mod:`tagswarm.evaluation.views`):
  ``{"views", "unmatched"`` (robot views without a true pose of both robots within
  ``assoc_max_diff_s``, or non-finite), ``"bins": [{"lo_m", "hi_m" (null = open), "count",
  "range_bias_m", "range_rmse_m", "across_bias_m", "across_rmse_m", "yaw_bias_rad",
  "yaw_rmse_rad", "range_sigma_m", "across_sigma_m", "yaw_sigma_rad", "nees"}]}`` (errors
  ``null`` in an empty bin).  A bin's bias is the views' systematic error at that range:
  positive ``range_bias_m`` = targets seen farther than they are.  The ``*_sigma_*`` are what
  the views' own covariances claim (RMS of the claimed standard deviations), ``nees`` their mean
  position NEES (1 = honest, below = the agents claim worse than they see); ``null`` for run folders older
  than the covariance columns of ``observations.csv``.
- ``relocalisations``: the server's re-localisation events (``relocalisations.csv``)
  of this run's robots, in time order: ``{"t_s", "robot", "jump_m"`` (how far the
  estimate moved), ``"evidence"`` (observations in the consistent set),
  ``"observers"`` (robot ids, -1 = a landmark), ``"error_before_m"``,
  ``"error_after_m"}`` (fused position error of the newest sample strictly before
  and the oldest strictly after the event; ``null`` if none).
- ``kidnaps``: every kidnap the world applied (``interventions.csv``), in time
  order, at the step it applied it (a refused command, or an event due after the
  end, is none: a warning counts them); an application within 0.5 s after a
  scheduled event of the same robot is that event.  Run folders older than
  ``interventions.csv``: scheduled ones (``run.json`` ``scenario.events`` with
  ``action`` teleport or push) and recorded world commands
  (``world_commands.csv``, at their ``stamp_ns``, or their arrival time if
  stamped 0; a command within 0.5 s of a scheduled event of the same robot is
  that event).  ``{"t_s", "robot", "action", "source"`` ("scenario" or
  "command"), ``"displacement_m"`` (the largest step of the true path within
  [t - 0.1 s, t + 1 s]: the world applies a command at its next step; ``null``
  without truth there), ``"time_to_relocalise_s"`` (from the kidnap until the
  robot is localised again and stays so for ``recovered_stay_s``, the record
  reaching that far; ``null`` if never), ``"first_relocalisation_s"`` (from the
  kidnap to the robot's first re-localisation event at or after it; ``null`` if
  none)}``.
- ``warnings``: human-readable notes about missing or unusable inputs, sources
  the recorder lost, kidnaps not applied, robots whose own controller failed
  or was slow (``controller_errors`` / ``controller_slow`` in ``run.json``), and
  an origin robot that saw nobody and was seen only from afar at the start
  (:mod:`tagswarm.evaluation.anchoring`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from tagswarm.evaluation.anchoring import anchoring_note
from tagswarm.evaluation.localised import LOCALISED_HOLD_S, LOCALISED_M
from tagswarm.evaluation.pairwise import (
    DISTANCE_BINS_M,
    NEIGHBOUR_WINDOW_S,
    DistanceSamples,
    bin_by_distance,
    error_vs_distance,
    pairwise_error,
)
from tagswarm.evaluation.recovery import RECOVERED_STAY_S, recovery_metrics
from tagswarm.evaluation.runfolder import (
    F64,
    MODES_HEADER,
    OBS_HEADER,
    ModeSample,
    Observations,
    RunData,
    RunFolderError,
    load_run,
    read_modes,
    read_observations,
    read_tum,
)
from tagswarm.evaluation.runsummary import (
    controller_trouble,
    cost,
    mode_durations,
    robot_behaviour,
    silent_sources,
    stall_trouble,
    swarm_behaviour,
)
from tagswarm.evaluation.trajerror import (
    ASSOC_MAX_DIFF_S,
    KINDS,
    RPE_DELTA_M,
    SE2Alignment,
    Track,
    align_swarm,
    ape,
    associate,
    fit_se2,
    pooled_stats,
    robot_trajectories,
    rpe_per_metre,
    swarm_trajectory_stats,
)
from tagswarm.evaluation.views import view_error_by_range

__all__ = [
    "ASSOC_MAX_DIFF_S", "DISTANCE_BINS_M", "F64", "KINDS", "MODES_HEADER", "NEIGHBOUR_WINDOW_S", "OBS_HEADER",
    "RPE_DELTA_M", "SCHEMA", "DistanceSamples", "Evaluation", "ModeSample", "Observations", "RunData",
    "RunFolderError", "SE2Alignment", "Track", "ape", "associate", "bin_by_distance", "compute_metrics",
    "error_vs_distance", "evaluate", "fit_se2", "load_run", "mode_durations", "pairwise_error", "pooled_stats",
    "read_modes", "read_observations", "read_tum", "rpe_per_metre",
]

SCHEMA = "tagswarm.evaluation.metrics/1"


@dataclass
class Evaluation:
    """Everything :func:`evaluate` derived from a run: the JSON-able ``metrics`` plus the
    arrays the plots need."""

    run: RunData
    tracks: dict[tuple[int, str], Track]
    alignment: dict[str, SE2Alignment | None]
    distance: DistanceSamples
    metrics: dict[str, Any]


def evaluate(run: RunData) -> Evaluation:
    """Compute every metric of a loaded run (see the module docstring for the fields)."""
    warnings = list(run.warnings)
    tracks, robots_out = robot_trajectories(run, warnings)

    swarm: dict[str, Any] = {}
    alignment: dict[str, SE2Alignment | None] = {}
    for kind in KINDS:
        ts = [tracks[(k, kind)] for k in run.robots if (k, kind) in tracks]
        alignment[kind], aligned = align_swarm(ts)
        for k, stats in aligned.items():
            robots_out[str(k)][kind]["ate_aligned"] = stats
        swarm[kind] = {**swarm_trajectory_stats(ts, alignment[kind]), "pairwise": pairwise_error(ts),
                       "robots_evaluated": len(ts)}

    # behaviour: counters from run.json, time per mode from modes.csv
    behaviour = robot_behaviour(run, warnings)
    for k in run.robots:
        robots_out[str(k)].update(behaviour[k])
    swarm.update(swarm_behaviour(run.robots, behaviour))
    costs = cost(run, behaviour)
    if costs["frames_rendered"] is None:
        costs.update(_rendered_by_workers(run))
    events = recovery_metrics(run, tracks, robots_out, swarm, KINDS, warnings)
    silent = silent_sources(run.info, warnings)
    warnings.extend(controller_trouble(run.info.get("counters")))
    warnings.extend(stall_trouble(robots_out))
    origin = run.info.get("origin_id")
    if isinstance(origin, int):
        note = anchoring_note(run.observations, origin, _truth_range(run), landmarks=_landmarks(run.info))
        if note is not None:
            warnings.append(note)

    dist = error_vs_distance(run, tracks)
    metrics: dict[str, Any] = {
        "schema": SCHEMA,
        "run": {"clock": run.info.get("clock"), "sim_time_s": costs["sim_time_s"],
                "wall_time_s": costs["wall_time_s"], "exit_code": run.info.get("exit_code"),
                "failure": run.info.get("failure"), "origin_id": run.info.get("origin_id"),
                "robots": list(run.robots), "method": _method(run.info), "silent_sources": silent,
                "landmarks": _landmarks(run.info)},
        "settings": {"assoc_max_diff_s": ASSOC_MAX_DIFF_S, "rpe_delta_m": RPE_DELTA_M,
                     "neighbour_window_s": NEIGHBOUR_WINDOW_S,
                     "distance_bins_m": [e if math.isfinite(e) else None for e in DISTANCE_BINS_M],
                     "localised_m": LOCALISED_M, "localised_hold_s": LOCALISED_HOLD_S,
                     "recovered_stay_s": RECOVERED_STAY_S},
        "cost": costs,
        "swarm": swarm,
        "robots": robots_out,
        "error_vs_distance": {"samples": int(dist.error_m.size), "unobserved_samples": dist.unobserved,
                              "bins": bin_by_distance(dist.distance_m, dist.error_m)},
        "view_error_vs_range": view_error_by_range(run.observations, run.truth),
        **events,
        "warnings": warnings,
    }
    return Evaluation(run=run, tracks=tracks, alignment=alignment, distance=dist, metrics=_finite(metrics))


def _truth_range(run: RunData) -> Callable[[int, int, float], float | None]:
    """The true distance (m) between two robots at a time (s), None where a truth is missing."""

    def at(robot: int, t_s: float) -> NDArray[np.float64] | None:
        tr = run.truth.get(robot)
        if tr is None or len(tr.timestamps) == 0:
            return None
        i = int(np.clip(np.searchsorted(tr.timestamps, t_s), 0, len(tr.timestamps) - 1))
        return np.asarray(tr.positions_xyz[i, :2], float)

    def distance(a: int, b: int, t_s: float) -> float | None:
        pa, pb = at(a, t_s), at(b, t_s)
        return None if pa is None or pb is None else float(np.hypot(*(pa - pb)))

    return distance


def _landmarks(info: dict[str, Any]) -> int:
    """Number of ``[[landmarks]]`` in the run's scenario (``run.json``), 0 if unknown."""
    scenario = info.get("scenario")
    lms = scenario.get("landmarks") if isinstance(scenario, dict) else None
    return len(lms) if isinstance(lms, list) else 0


def _method(info: dict[str, Any]) -> str:
    """The server's ``[server] method`` the run used (older run folders: the graph)."""
    scenario = info.get("scenario")
    server = scenario.get("server") if isinstance(scenario, dict) else None
    method = server.get("method") if isinstance(server, dict) else None
    return method if isinstance(method, str) else "graph"


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


def compute_metrics(run_dir: Path) -> dict[str, Any]:
    """The metrics of a run folder as a JSON-able dict (fields: see the module docstring).
    Raises :class:`RunFolderError` for a missing or malformed folder."""
    return evaluate(load_run(Path(run_dir))).metrics


def _rendered_by_workers(run: RunData) -> dict[str, Any]:
    """``frames_rendered`` (and per robot) as the sum of the render workers' last counters, for a
    world that rendered in ``render/<i>`` worker processes (its own status then has none)."""
    counters = run.info.get("counters")
    counts = [c.get("frames_rendered") for who, c in (counters.items() if isinstance(counters, dict) else ())
              if who.startswith("render/") and isinstance(c, dict)]
    known = [int(v) for v in counts if isinstance(v, int | float) and not isinstance(v, bool)]
    if not known:
        return {}
    total = sum(known)
    return {"frames_rendered": total, "frames_rendered_per_robot": total / len(run.robots) if run.robots else None}
