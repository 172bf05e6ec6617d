"""Behaviour and cost of a run for :mod:`tagswarm.evaluation.metrics`: the agents' counters and
the world's rendered frames from ``run.json``, time per behaviour mode from
``modes.csv``, and the real-time factor.

Pure code; times are simulation seconds except ``wall_time_s``.  Values that are
missing or of the wrong type in ``run.json`` become ``None`` (never raised): a run
that crashed early still gets its metrics.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from tagswarm.evaluation.runfolder import ModeSample, RunData

AGENT_COUNTERS = ("fixes", "searches", "lost_events", "frames_processed", "frames_skipped", "avoid_yields",
                  "avoid_reroutes", "avoid_side_flips", "avoid_steps_aside", "avoid_gate_waits")
"""Per-robot counters copied from the agent's status (``run.json`` ``counters["agent/<k>"]``)."""
SWARM_COUNTERS = ("fixes", "searches", "lost_events", "avoid_side_flips", "avoid_steps_aside", "avoid_gate_waits")
"""Counters summed over robots into ``swarm``."""


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


def robot_behaviour(run: RunData, warnings: list[str]) -> dict[int, dict[str, Any]]:
    """Per robot: :data:`AGENT_COUNTERS` (``None`` each if the agent reported none),
    ``mode_time_s`` ``{mode: seconds}`` and ``time_lost_s``.  The last mode sample of
    a robot holds until the end of the recorded truth (latest truth stamp of any
    robot).  Without any mode sample a note goes to ``warnings``."""
    counters = _dict(run.info.get("counters"))
    truth_ends = [float(t.timestamps[-1]) for t in run.truth.values() if t is not None]
    durations = mode_durations(run.modes, max(truth_ends) if truth_ends else None)
    out: dict[int, dict[str, Any]] = {}
    for k in run.robots:
        agent = _dict(counters.get(f"agent/{k}"))
        # agents report a Counter: a name it never incremented is absent, i.e. zero
        r: dict[str, Any] = {name: _counter(agent, name) if name in agent or not agent else 0
                             for name in AGENT_COUNTERS}
        modes = durations.get(k, {})
        r["mode_time_s"] = dict(sorted(modes.items()))
        r["time_lost_s"] = float(modes.get("lost", 0.0))
        out[k] = r
    if not run.modes:
        warnings.append("no mode samples: time_lost_s is 0")
    return out


#: a source last heard this long (sim s) before the run's end fell silent: its data is incomplete
SILENT_AFTER_S = 2.0


def controller_trouble(counters: Any) -> list[str]:
    """One note per robot whose own controller (``--agent-module``) failed or was slow, from the
    agents' counters (``run.json`` ``counters``): ``controller_errors`` (steps that raised or
    returned no finite command; the robot got a zero command) and ``controller_slow`` (steps longer
    than a control period).  The agent carries on in both cases, so only these counters tell."""
    notes = []
    for name, c in sorted(_dict(counters).items()):
        if not (str(name).startswith("agent/") and isinstance(c, dict)):
            continue
        rid = str(name)[len("agent/"):]
        cycles, errors, slow = (_int_or_zero(c.get(k)) for k in ("controller_cycles", "controller_errors",
                                                                  "controller_slow"))
        if errors:
            notes.append(f"robot {rid}'s controller: {errors} of {cycles} steps failed and stopped the robot "
                         f"(traceback in logs/agent{rid}.log)")
        if slow:
            notes.append(f"robot {rid}'s controller: {slow} of {cycles} steps took longer than a control period")
    # a step that never returns leaves no counter of its agent (it reports no more): the world's tells
    stalls = _int_or_zero(_dict(_dict(counters).get("world")).get("ack_stalls"))
    if stalls:
        notes.append(f"the lockstep world stopped waiting for a participant alive but silent ({stalls} time(s)): "
                     "a controller step that never returns? logs/world.log names it, its agent's log shows where")
    return notes


#: a robot whose avoidance stalled this often with no way round found is named in the warnings
STALL_NOTE_FLIPS = 3


def stall_trouble(per_robot: Mapping[Any, dict[str, Any]]) -> list[str]:
    """One note per robot whose way was closed (``metrics.json`` ``robots``, or :func:`robot_behaviour`):
    its avoidance stalled at least :data:`STALL_NOTE_FLIPS` times with no way round the room found
    (``avoid_side_flips``: each time it tried the other side).  Nothing collides then, so without this
    a user sees only a mission that drove little (measured: two rooms joined by a door a station keeper
    stood in, three patrols flipping sides 1-6 times each in 60 s)."""
    notes = []
    for k, r in sorted(per_robot.items(), key=lambda kv: int(kv[0])):
        flips = _int_or_zero(r.get("avoid_side_flips"))
        if flips < STALL_NOTE_FLIPS:
            continue
        path = _num(r.get("path_length_m"))
        notes.append(f"robot {k}'s way was closed {flips} times: its avoidance stalled with no way round the room "
                     f"it could find (it gave way {_int_or_zero(r.get('avoid_yields'))} times, followed "
                     f"{_int_or_zero(r.get('avoid_reroutes'))} way(s) round"
                     f"{'' if path is None else f', drove {path:.1f} m'}); robots holding station or on the same "
                     "way stood in it (plots/arena.png shows where)")
    return notes


def _int_or_zero(v: Any) -> int:
    return int(v) if isinstance(v, int | float) and not isinstance(v, bool) else 0


def silent_sources(info: dict[str, Any], warnings: list[str]) -> dict[str, float]:
    """Sources (``world``, ``server``, ``agent/<k>``) the recorder last heard more than
    :data:`SILENT_AFTER_S` simulated seconds before the run's end (``run.json``
    ``sim_time_s``), with that time (s); each also becomes a warning.  A source the
    recorder lost (e.g. its link dropped under load) leaves trajectories that end early,
    so metrics computed from them describe only part of the run.  Older run folders
    (no ``last_heard_s``) give none."""
    heard = _dict(info.get("last_heard_s"))
    end = info.get("sim_time_s")
    if not isinstance(end, (int, float)):
        return {}
    out: dict[str, float] = {}
    for who, t in sorted(heard.items()):
        if isinstance(t, (int, float)) and end - t > SILENT_AFTER_S:
            out[str(who)] = float(t)
            warnings.append(f"the recorder heard nothing from {who} after {t:.1f} s of the run's {end:.1f} s: "
                            "what it sends ends there, so the metrics cover only part of the run")
    return out


def swarm_behaviour(robots: Sequence[int], per_robot: dict[int, dict[str, Any]]) -> dict[str, Any]:
    """:data:`SWARM_COUNTERS` summed over ``robots`` (``None`` if none reported), and
    ``mode_time_s`` / ``time_lost_s`` summed over them, from :func:`robot_behaviour`."""
    out: dict[str, Any] = {name: _sum([per_robot[k][name] for k in robots]) for name in SWARM_COUNTERS}
    total_modes: dict[str, float] = {}
    for k in robots:
        for mode, secs in per_robot[k]["mode_time_s"].items():
            total_modes[mode] = total_modes.get(mode, 0.0) + secs
    out["mode_time_s"] = dict(sorted(total_modes.items()))
    out["time_lost_s"] = float(total_modes.get("lost", 0.0))
    return out


def cost(run: RunData, per_robot: dict[int, dict[str, Any]]) -> dict[str, Any]:
    """``metrics.json`` ``cost``: wall and sim time (s), real-time factors, frames rendered
    (world total and per robot) and frames processed/skipped (sums over the agents, from
    :func:`robot_behaviour`).  ``real_time_factor`` is the simulation's: sim time over the wall
    time the world spent stepping (its ``stepping_ms``; a run folder without it: over the whole
    run's wall time); ``run_real_time_factor`` is sim time over the whole run's wall time, start-up
    and shutdown of every process included (a 25 s run of 16 robots took ~5 s more)."""
    sim_s, wall_s = _num(run.info.get("sim_time_s")), _num(run.info.get("wall_time_s"))
    world = _dict(_dict(run.info.get("counters")).get("world"))
    rendered = _counter(world, "frames_rendered")
    stepping_ms = _counter(world, "stepping_ms")
    whole = sim_s / wall_s if sim_s is not None and wall_s else None
    return {
        "wall_time_s": wall_s,
        "sim_time_s": sim_s,
        "stepping_wall_s": stepping_ms / 1000 if stepping_ms else None,
        "real_time_factor": sim_s / (stepping_ms / 1000) if sim_s is not None and stepping_ms else whole,
        "run_real_time_factor": whole,
        "frames_rendered": rendered,
        "frames_rendered_per_robot": rendered / len(run.robots) if rendered is not None and run.robots else None,
        "frames_processed": _sum([per_robot[k]["frames_processed"] for k in run.robots]),
        "frames_skipped": _sum([per_robot[k]["frames_skipped"] for k in run.robots]),
    }
