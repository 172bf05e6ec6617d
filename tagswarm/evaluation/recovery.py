"""Evaluation of localisation recovery for :mod:`tagswarm.evaluation.metrics`: how much of the
time each robot is localised, kidnaps and how long the swarm takes to recover
from them, the server's re-localisation events, collisions and the consistency
of the fused covariance (NEES).  The ``metrics.json`` fields are documented in
:mod:`tagswarm.evaluation.metrics`.

Pure code.  Positions and errors are metres in the MAP frame, timestamps
simulation seconds.  "Localised" is defined in :mod:`tagswarm.evaluation.localised`; it is
sampled on the robot's truth stamps, each sample holding until the next one
(time-weighted), so time before the first fused estimate and gaps in the
corrections count as not localised.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from evo.core.trajectory import PoseTrajectory3D
from numpy.typing import NDArray

from tagswarm.evaluation.covframe import covariance_ellipse, position_cov_in_map, position_nees
from tagswarm.evaluation.localised import LOCALISED_HOLD_S, LOCALISED_M
from tagswarm.evaluation.runfolder import F64, CovTrack, RelocEvent, RunData
from tagswarm.evaluation.trajerror import ASSOC_MAX_DIFF_S, Track, pooled_stats, trajectory_yaw

RECOVERED_STAY_S = 1.0
"""After a kidnap a robot has recovered once it stays localised this long (s)."""
KIDNAP_BEFORE_S = 0.1
KIDNAP_AFTER_S = 1.0
"""The kidnap's displacement is the largest step of the true path within
[t - :data:`KIDNAP_BEFORE_S`, t + :data:`KIDNAP_AFTER_S`] (the world applies a command at its next step)."""
KIDNAP_MERGE_S = 0.5
"""A recorded world command this close (s) to a scheduled event of the same robot is that event."""
KIDNAP_ACTIONS = ("teleport", "push")
CONTACT_KINDS = ("robot_robot", "robot_obstacle", "robot_wall")
"""World counters ``contacts_<kind>`` copied into ``swarm.contacts``."""


# --------------------------------------------------------------------------- localised share


@dataclass(frozen=True)
class LocalisedSignal:
    """Whether a robot is localised at each of its truth stamps (``stamp_s``, sorted);
    ``ok[i]`` holds from ``stamp_s[i]`` until ``stamp_s[i + 1]``."""

    stamp_s: F64
    ok: NDArray[np.bool_]

    @property
    def durations_s(self) -> F64:
        return np.append(np.diff(self.stamp_s), 0.0)

    def seconds(self) -> tuple[float, float]:
        """(localised seconds, evaluated seconds)."""
        d = self.durations_s
        return float(np.sum(d[self.ok])), float(np.sum(d))

    def since(self, t0_s: float) -> LocalisedSignal:
        """The signal from the first truth stamp at or after ``t0_s`` on."""
        keep = self.stamp_s >= t0_s - 1e-9
        return LocalisedSignal(self.stamp_s[keep], self.ok[keep])

    def recovered_at(self, t0_s: float, stay_s: float = RECOVERED_STAY_S) -> float | None:
        """The first truth stamp t >= ``t0_s`` from which the robot stays localised for
        ``stay_s`` (every sample in [t, t + stay_s) localised, the record reaching
        t + stay_s), or ``None``."""
        t, ok = self.stamp_s, self.ok
        end = float(t[-1]) if t.size else -math.inf
        eps = 1e-9
        bad = np.flatnonzero(~ok)
        for i in np.flatnonzero((t >= t0_s - eps) & ok):
            start = float(t[i])
            if start + stay_s > end + eps:
                return None
            # the first not-localised sample after this one decides
            j = np.searchsorted(bad, i)
            if j == bad.size or float(t[bad[j]]) >= start + stay_s - eps:
                return start
        return None


def _hold_errors(sample_s: F64, est_s: F64, err_m: F64, hold_s: float) -> F64:
    """Error of the newest estimate at or before each ``sample_s`` (inf where there is
    none within ``hold_s``)."""
    idx = np.searchsorted(est_s, sample_s + 1e-9, side="right") - 1
    out = np.full(sample_s.shape, np.inf)
    has = idx >= 0
    fresh = has.copy()
    fresh[has] = sample_s[has] - est_s[idx[has]] <= hold_s + 1e-9
    out[fresh] = err_m[idx[fresh]]
    return out


def localised_signal(truth: PoseTrajectory3D | None, track: Track | None,
                     threshold_m: float = LOCALISED_M, hold_s: float = LOCALISED_HOLD_S) -> LocalisedSignal | None:
    """The localised step function of one robot on its truth stamps (``None`` without
    at least two truth poses); without a ``track`` (never localised) it is all false."""
    if truth is None or truth.num_poses < 2:
        return None
    t = np.asarray(truth.timestamps, float)
    if track is None:
        return LocalisedSignal(t, np.zeros(t.size, bool))
    err = _hold_errors(t, track.stamps_s, track.error_m, hold_s)
    return LocalisedSignal(t, err < threshold_m)


def time_localised(signals: Sequence[LocalisedSignal | None]) -> float | None:
    """Share of robot-time localised, pooled (time-weighted) over ``signals``; ``None``
    if none covers any time."""
    loc = total = 0.0
    for s in signals:
        if s is not None:
            a, b = s.seconds()
            loc, total = loc + a, total + b
    return loc / total if total > 0 else None


# --------------------------------------------------------------------------- NEES


def outside(stamps_s: F64, windows: Sequence[tuple[float, float]]) -> NDArray[np.bool_]:
    """(N,) mask of the ``stamps_s`` (s, shape (N,)) outside every closed interval of ``windows``."""
    keep = np.ones(stamps_s.shape, bool)
    for t0, t1 in windows:
        keep &= ~((stamps_s >= t0) & (stamps_s <= t1))
    return keep


def nees_samples(track: Track, cov: CovTrack | None, max_diff_s: float = ASSOC_MAX_DIFF_S,
                 exclude: Sequence[tuple[float, float]] = ()) -> F64 | None:
    """e^T P^-1 e / 2 for every sample of a fused ``track`` with a covariance within
    ``max_diff_s`` of its stamp: e the map-frame position error, P the 2x2 position
    block of that covariance rotated into the map frame by the estimate's yaw.  A
    covariance that is not positive definite is skipped, and so is a sample inside one
    of the ``exclude`` intervals ``(t0_s, t1_s)``.  ``None`` without covariances."""
    if cov is None or cov.stamp_s.size == 0:
        return None
    s = track.stamps_s
    idx = np.searchsorted(cov.stamp_s, s)
    left = np.clip(idx - 1, 0, cov.stamp_s.size - 1)
    right = np.clip(idx, 0, cov.stamp_s.size - 1)
    pick = np.where(np.abs(cov.stamp_s[left] - s) <= np.abs(cov.stamp_s[right] - s), left, right)
    e = track.est_xy - track.truth_xy
    yaw = trajectory_yaw(track.est)
    keep = outside(s, exclude)
    out = []
    for i, c in enumerate(pick):
        if abs(cov.stamp_s[c] - s[i]) > max_diff_s or not keep[i]:
            continue
        sxx, sxy, syy = position_cov_in_map(cov.cov[c].ravel(), float(yaw[i]))
        det = sxx * syy - sxy * sxy
        if not (math.isfinite(det) and det > 0.0 and sxx > 0.0):
            continue
        out.append(position_nees(sxx, sxy, syy, *e[i]))
    return np.asarray(out, float)


def sigma_median(cov: CovTrack | None) -> float | None:
    """Median over the recorded covariances of the fused position's largest standard
    deviation (m): the square root of the 2x2 position block's larger eigenvalue (the
    same in any frame).  ``None`` without covariances."""
    if cov is None or cov.stamp_s.size == 0:
        return None
    sigmas = [covariance_ellipse(tuple(c), scale=1.0)[0] for c in np.asarray(cov.cov, float).reshape(-1, 9)]
    finite = [x for x in sigmas if math.isfinite(x)]
    return float(np.median(finite)) if finite else None


def nees_stats(values: F64 | None) -> dict[str, float | int] | None:
    """``{"mean", "median", "count"}`` of NEES values, or ``None`` for none."""
    if values is None or values.size == 0:
        return None
    return {"mean": float(np.mean(values)), "median": float(np.median(values)), "count": int(values.size)}


# --------------------------------------------------------------------------- events


def _error_near(track: Track | None, t_s: float) -> tuple[float | None, float | None]:
    """Fused error of the newest sample strictly before and the oldest strictly after ``t_s``."""
    if track is None:
        return None, None
    s = track.stamps_s
    i = int(np.searchsorted(s, t_s - 1e-9, side="left")) - 1
    j = int(np.searchsorted(s, t_s + 1e-9, side="right"))
    return (float(track.error_m[i]) if i >= 0 else None, float(track.error_m[j]) if j < s.size else None)


def relocalisation_events(events: list[RelocEvent], tracks: dict[tuple[int, str], Track]) -> list[dict[str, Any]]:
    """``metrics.json`` ``relocalisations``: one dict per event, in time order."""
    out = []
    for e in events:
        before, after = _error_near(tracks.get((e.robot, "fused")), e.stamp_s)
        out.append({"t_s": e.stamp_s, "robot": e.robot, "jump_m": e.jump_m, "evidence": e.evidence,
                    "observers": list(e.observers), "error_before_m": before, "error_after_m": after})
    return out


@dataclass(frozen=True)
class Kidnap:
    t_s: float
    robot: int
    action: str
    source: str  # "scenario" (scheduled [[events]]) or "command" (a recorded WorldCommand)


def _num(v: Any) -> float | None:
    return float(v) if isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) else None


def kidnaps_of(run: RunData, warnings: list[str]) -> list[Kidnap]:
    """The interventions the world applied (``interventions.csv``), at the step it applied them, an
    application within :data:`KIDNAP_MERGE_S` after a scheduled event of the same robot being that
    event; in time order.  A run folder older than that file: the scheduled kidnaps (``run.json``
    ``scenario.events``) and the recorded world commands, a command within :data:`KIDNAP_MERGE_S` of a
    scheduled event of the same robot counting as that event."""
    scenario = run.info.get("scenario")
    raw = scenario.get("events") if isinstance(scenario, dict) else None
    found: list[Kidnap] = []
    for n, ev in enumerate(raw if isinstance(raw, list) else []):
        robot = ev.get("robot", ev.get("robot_id")) if isinstance(ev, dict) else None
        at = _num(ev.get("at_s")) if isinstance(ev, dict) else None
        action = ev.get("action") if isinstance(ev, dict) else None
        if at is None or not isinstance(robot, int) or isinstance(robot, bool) or action not in KIDNAP_ACTIONS:
            warnings.append(f"scenario event {n} is not a kidnap this evaluation understands: {ev!r}")
            continue
        found.append(Kidnap(at, robot, str(action), "scenario"))
    scheduled = list(found)
    if run.applied is not None:  # what the world did, at the step it did it: refused ones never count
        applied = [Kidnap(a.stamp_s, a.robot, a.action, "scenario" if any(
            k.robot == a.robot and -1e-3 <= a.stamp_s - k.t_s <= KIDNAP_MERGE_S for k in scheduled) else "command")
                   for a in run.applied]
        refused = len(scheduled) + len(run.world_commands) - len(applied)
        if refused > 0:
            warnings.append(f"{refused} kidnap(s) asked for were not applied by the world (refused, or due after "
                            "the end of the run): see the world's log")
        found = applied
    for c in ([] if run.applied is not None else run.world_commands):
        t = c.stamp_s if c.stamp_s > 0 else c.received_s  # a tool that does not know the sim time stamps 0
        if any(k.robot == c.robot and abs(k.t_s - t) <= KIDNAP_MERGE_S for k in scheduled):
            continue
        found.append(Kidnap(t, c.robot, c.action, "command"))
    known = [k for k in found if k.robot in run.robots]
    for k in found:
        if k.robot not in run.robots:
            warnings.append(f"kidnap of robot {k.robot} at {k.t_s:.2f} s: not a robot of this run")
    return sorted(known, key=lambda k: (k.t_s, k.robot))


def displacement(truth: PoseTrajectory3D | None, t_s: float) -> float | None:
    """The largest step of the true path within [t_s - KIDNAP_BEFORE_S, t_s + KIDNAP_AFTER_S] (m)."""
    if truth is None:
        return None
    t = np.asarray(truth.timestamps, float)
    sel = np.flatnonzero((t >= t_s - KIDNAP_BEFORE_S - 1e-9) & (t <= t_s + KIDNAP_AFTER_S + 1e-9))
    if sel.size < 2:
        return None
    xy = np.asarray(truth.positions_xyz[sel, :2], float)
    return float(np.max(np.linalg.norm(np.diff(xy, axis=0), axis=1)))


def kidnap_records(run: RunData, kidnaps: list[Kidnap], signals: dict[int, LocalisedSignal | None],
                   events: list[RelocEvent]) -> list[dict[str, Any]]:
    """``metrics.json`` ``kidnaps``: one dict per kidnap, in time order."""
    out = []
    for k in kidnaps:
        sig = signals.get(k.robot)
        back = sig.recovered_at(k.t_s) if sig is not None else None
        first = next((e.stamp_s for e in events if e.robot == k.robot and e.stamp_s >= k.t_s - 1e-9), None)
        out.append({"t_s": k.t_s, "robot": k.robot, "action": k.action, "source": k.source,
                    "displacement_m": displacement(run.truth.get(k.robot), k.t_s),
                    "time_to_relocalise_s": None if back is None else back - k.t_s,
                    "first_relocalisation_s": None if first is None else first - k.t_s})
    return out


# --------------------------------------------------------------------------- contacts


def _count(counters: dict[str, Any], name: str, reported: bool) -> int | None:
    v = counters.get(name)
    if isinstance(v, int | float) and not isinstance(v, bool):
        return int(v)
    # the world counts with a Counter: once it reports contacts at all, a name it never incremented is zero
    return 0 if reported else None


def contacts(run: RunData) -> tuple[dict[str, int | None], dict[int, int | None]]:
    """(``swarm.contacts``, per-robot contacts) from the world's counters in ``run.json``;
    ``None`` where the world reported no contact counters at all."""
    all_counters = run.info.get("counters")
    world = all_counters.get("world") if isinstance(all_counters, dict) else None
    world = world if isinstance(world, dict) else {}
    reported = any(str(name).startswith("contacts_") for name in world)
    swarm = {kind: _count(world, f"contacts_{kind}", reported) for kind in CONTACT_KINDS}
    return swarm, {k: _count(world, f"contacts_robot_{k}", reported) for k in run.robots}


# --------------------------------------------------------------------------- assembly


def recovery_metrics(run: RunData, tracks: dict[tuple[int, str], Track], robots_out: dict[str, dict[str, Any]],
                     swarm: dict[str, Any], kinds: Sequence[str], warnings: list[str]) -> dict[str, Any]:
    """Add ``time_localised`` (both kinds), ``nees`` (fused), ``relocalisations``,
    ``kidnaps`` and ``contacts`` to the per-robot blocks ``robots_out`` and to
    ``swarm`` in place; return the top-level ``relocalisations`` and ``kidnaps`` lists."""
    fused_signals: dict[int, LocalisedSignal | None] = {}
    for kind in kinds:
        signals = []
        for k in run.robots:
            sig = localised_signal(run.truth.get(k), tracks.get((k, kind)))
            robots_out[str(k)][kind]["time_localised"] = time_localised([sig])
            signals.append(sig)
            if kind == "fused":
                fused_signals[k] = sig
        swarm[kind]["time_localised"] = time_localised(signals)
    # once placed: the same share from each robot's first fused estimate on (acquisition left out, so
    # tracking and start-up can be told apart; a robot never placed adds no time)
    placed = []
    for k in run.robots:
        sig, track = fused_signals.get(k), tracks.get((k, "fused"))
        after = None if sig is None or track is None else sig.since(float(track.stamps_s[0]))
        robots_out[str(k)]["fused"]["time_localised_placed"] = time_localised([after])
        placed.append(after)
    swarm["fused"]["time_localised_placed"] = time_localised(placed)

    relocs = relocalisation_events([e for e in run.relocalisations if e.robot in run.robots], tracks)
    kidnaps = kidnap_records(run, kidnaps_of(run, warnings), fused_signals, run.relocalisations)

    # NEES judges the covariance against the errors the fusion models; a kidnap is outside that model
    # (the robot is carried off, its wheels never turn), so "nees_nominal" leaves out each kidnapped
    # robot from the kidnap until it is localised again (or the end of the run).  The window opens one
    # association tolerance early: a sample stamped 1 ns before the kidnap's tick is paired with the moved
    # truth (measured: that one sample, NEES 57,800, lifted a 40 s run's mean from 3 to 51)
    # The same windows give the position error outside kidnaps: a kidnapped robot is ~1 m off until it is
    # re-localised, and in a short run those seconds are most of its RMSE (kidnap scene: 10.6 cm swarm RMSE,
    # most of it the 1.2-1.4 s after the two kidnaps), while the recovery time is what measures them
    pooled: dict[str, list[F64]] = {"nees": [], "nees_nominal": []}
    nominal_errors: list[F64] = []
    for k in run.robots:
        tr = tracks.get((k, "fused"))
        windows = [(e["t_s"] - ASSOC_MAX_DIFF_S,
                    math.inf if e["time_to_relocalise_s"] is None else e["t_s"] + e["time_to_relocalise_s"])
                   for e in kidnaps if e["robot"] == k]
        for key, exclude in (("nees", []), ("nees_nominal", windows)):
            values = nees_samples(tr, run.fused_cov.get(k), exclude=exclude) if tr is not None else None
            robots_out[str(k)]["fused"][key] = nees_stats(values)
            if values is not None:
                pooled[key].append(values)
        robots_out[str(k)]["fused"]["sigma_median_m"] = sigma_median(run.fused_cov.get(k))
        errors = None if tr is None else tr.error_m[outside(tr.stamps_s, windows)]
        robots_out[str(k)]["fused"]["ate_unaligned_nominal"] = None if errors is None else pooled_stats(errors)
        if errors is not None:
            nominal_errors.append(errors)
    for key, chunks in pooled.items():
        swarm["fused"][key] = nees_stats(np.concatenate(chunks)) if chunks else None
    swarm["fused"]["ate_unaligned_nominal"] = pooled_stats(np.concatenate(nominal_errors)) if nominal_errors else None
    swarm_contacts, robot_contacts = contacts(run)
    for k in run.robots:
        r = robots_out[str(k)]
        r["relocalisations"] = sum(1 for e in relocs if e["robot"] == k)
        r["kidnaps"] = sum(1 for e in kidnaps if e["robot"] == k)
        r["contacts"] = robot_contacts[k]
    recovered = [e["time_to_relocalise_s"] for e in kidnaps if e["time_to_relocalise_s"] is not None]
    swarm["relocalisations"] = len(relocs)
    swarm["kidnaps"] = {"count": len(kidnaps), "recovered": len(recovered),
                        "mean_time_to_relocalise_s": float(np.mean(recovered)) if recovered else None,
                        "max_time_to_relocalise_s": float(np.max(recovered)) if recovered else None}
    swarm["contacts"] = swarm_contacts
    return {"relocalisations": relocs, "kidnaps": kidnaps}
