"""``tagswarm report RUN_DIR``: evaluate a run folder, write ``metrics.json`` and plots.

Writes into the run folder:

- ``metrics.json``: :func:`tagswarm.evaluation.metrics.compute_metrics` (fields documented in
  :mod:`tagswarm.evaluation.metrics`).
- ``plots/arena.png``: the arena walls (and obstacles, landmarks) with the true,
  fused and odometry-only path of every robot, start and end markers.
- ``plots/error_over_time.png``: fused and odometry-only position error per robot
  against simulation time (unaligned, map frame), with the server's
  re-localisation events (dashed) and kidnaps (solid, ▼ on top) of each robot as
  vertical lines in its colour, and the "localised" threshold.
- ``plots/error_vs_distance.png``: fused error against the true distance to the
  nearest robot that observed it or that it observed (the paper's claim that the
  error shrinks as robots get closer), with the median per distance bin.
- ``plots/true_vs_measured.png``: true and fused positions joined pair by pair
  (like the paper's Fig. 5), subsampled in time.

Everything is drawn in the MAP frame (metres); the arena, given in the arena
frame by the scenario, is moved there with :func:`tagswarm.protocol.layout.arena_to_map`.
Matplotlib is used through the Agg canvas only (no GUI, no global pyplot state).
The printed summary is :mod:`tagswarm.evaluation.reportsummary`.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from tagswarm.evaluation.metrics import F64, Evaluation, RunFolderError, evaluate, load_run
from tagswarm.evaluation.reportsummary import print_summary, summary_tables
from tagswarm.protocol.layout import arena_to_map
from tagswarm.protocol.scenario import Scenario, ScenarioError, convert
from tagswarm.runtime.config import OneLineParser, parse
from tagswarm.runtime.process import run_main

__all__ = ["PLOTS", "main", "plot_error_over_time", "print_summary", "summary_tables", "write_report"]

PLOTS = ("arena.png", "error_over_time.png", "error_vs_distance.png", "true_vs_measured.png")
GAP_S = 1.0
"""A fused trajectory is drawn broken where consecutive poses are further apart (s):
a line across a period without localisation would suggest an estimate that did not exist."""
PAIR_PERIOD_S = 2.0
"""Time between the true/fused pairs drawn in ``true_vs_measured.png`` (s), to keep it legible."""
DPI = 110


def _colour(i: int) -> str:
    return f"C{i % 10}"


def scenario_of(ev: Evaluation) -> Scenario | None:
    """The run's resolved scenario (``run.json`` ``scenario``), or ``None`` if absent.
    Raises :class:`RunFolderError` if present but invalid."""
    table = ev.run.info.get("scenario")
    if table is None:
        return None
    try:
        scenario: Scenario = convert(table, Scenario, "run.json scenario")
    except ScenarioError as exc:
        raise RunFolderError(str(exc)) from None
    return scenario


def arena_points_to_map(scenario: Scenario, xy: F64) -> F64:
    """Points (N, 2) in the arena frame (m) -> map frame (m), via T_map_arena = ``arena_to_map``."""
    tf = arena_to_map(scenario)
    c, s = math.cos(tf[2]), math.sin(tf[2])
    r = np.array([[c, -s], [s, c]])
    return np.asarray(xy, float) @ r.T + np.array(tf[:2])


def _box(cx: float, cy: float, yaw: float, sx: float, sy: float) -> F64:
    """Closed outline (5, 2) of a rectangle of size (sx, sy) centred at (cx, cy), turned by yaw."""
    c, s = math.cos(yaw), math.sin(yaw)
    local = np.array([[-sx, -sy], [sx, -sy], [sx, sy], [-sx, sy], [-sx, -sy]]) / 2
    return local @ np.array([[c, -s], [s, c]]).T + np.array([cx, cy])


def _draw_arena(ax: Axes, scenario: Scenario | None) -> None:
    """Walls (centre lines, drawn as thick as the wall), obstacles and landmarks, map frame."""
    if scenario is None:
        return
    a = scenario.arena
    walls = arena_points_to_map(scenario, _box(0.0, 0.0, 0.0, a.size_x_m, a.size_y_m))
    # linewidth in points ~ wall thickness at the figure's scale is overkill; a firm grey line reads as a wall
    ax.plot(walls[:, 0], walls[:, 1], color="0.35", lw=3, solid_capstyle="butt", zorder=1)
    for ob in a.obstacles:
        outline = arena_points_to_map(scenario, _box(ob.x_m, ob.y_m, ob.yaw_rad, ob.size_x_m, ob.size_y_m))
        ax.fill(outline[:, 0], outline[:, 1], color="0.75", zorder=1)
    if scenario.landmarks:
        lm = arena_points_to_map(scenario, np.array([[m.x_m, m.y_m] for m in scenario.landmarks]))
        ax.plot(lm[:, 0], lm[:, 1], "^", color="0.2", ms=7, ls="none", zorder=2)


def _segments(t: F64, xy: F64, gap_s: float = GAP_S) -> list[F64]:
    """Split a sampled path where the time step exceeds ``gap_s``."""
    if len(t) == 0:
        return []
    cuts = np.flatnonzero(np.diff(t) > gap_s) + 1
    return [seg for seg in np.split(xy, cuts) if len(seg)]


def _save(fig: Figure, path: Path) -> None:
    FigureCanvasAgg(fig)  # attaches the Agg canvas: rendering needs no GUI backend
    fig.savefig(path, dpi=DPI, bbox_inches="tight")


def plot_arena(ev: Evaluation, scenario: Scenario | None, path: Path) -> None:
    """True (solid), fused (dashed) and odometry-only (dotted) paths of every robot over
    the arena, in the map frame; ○ start and □ end of the true path, × end of the fused."""
    fig = Figure(figsize=(7.5, 7))
    ax = fig.add_subplot()
    _draw_arena(ax, scenario)
    run = ev.run
    for i, k in enumerate(run.robots):
        col = _colour(i)
        truth = run.truth.get(k)
        if truth is not None:
            xy = truth.positions_xyz[:, :2]
            ax.plot(xy[:, 0], xy[:, 1], "-", color=col, lw=1.8, zorder=3)
            ax.plot(*xy[0], "o", color=col, ms=8, mfc="white", mew=2, zorder=5)
            ax.plot(*xy[-1], "s", color=col, ms=7, zorder=5)
            ax.annotate(f"{k}", xy[0], xytext=(6, 6), textcoords="offset points", color=col, weight="bold")
        odom = run.odom.get(k)
        if odom is not None:
            xy = odom.positions_xyz[:, :2]
            ax.plot(xy[:, 0], xy[:, 1], ":", color=col, lw=1.2, alpha=0.8, zorder=3)
        fused = run.fused.get(k)
        if fused is not None:
            for seg in _segments(np.asarray(fused.timestamps, float), fused.positions_xyz[:, :2]):
                ax.plot(seg[:, 0], seg[:, 1], "--", color=col, lw=1.2, zorder=4)
            ax.plot(*fused.positions_xyz[-1, :2], "x", color=col, ms=8, mew=2, zorder=5)
    handles = [Line2D([], [], color=_colour(i), lw=2, label=f"robot {k}") for i, k in enumerate(run.robots)]
    handles += [
        Line2D([], [], color="k", ls="-", label="true"),
        Line2D([], [], color="k", ls="--", label="fused"),
        Line2D([], [], color="k", ls=":", label="odometry only"),
        Line2D([], [], color="k", marker="o", mfc="white", ls="none", label="start"),
        Line2D([], [], color="k", marker="s", ls="none", label="end (true)"),
        Line2D([], [], color="k", marker="x", ls="none", label="end (fused)"),
    ]
    if scenario is not None:
        handles.append(Line2D([], [], color="0.35", lw=3, label="arena walls"))
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m] (map frame)")
    ax.set_ylabel("y [m] (map frame)")
    ax.set_title("paths: true, fused, odometry only")
    ax.grid(alpha=0.3)
    _save(fig, path)


def _mark_events(ax_f: Axes, ax_o: Axes, ev: Evaluation) -> list[Line2D]:
    """Vertical lines at every re-localisation event (dashed) and kidnap (solid, ▼ on top
    of the fused axis) in the robot's colour; legend handles for those drawn."""
    colour = {k: _colour(i) for i, k in enumerate(ev.run.robots)}
    handles = []
    relocs = ev.metrics.get("relocalisations") or []
    kidnaps = ev.metrics.get("kidnaps") or []
    for e in relocs:
        for ax in (ax_f, ax_o):
            ax.axvline(e["t_s"], color=colour.get(e["robot"], "k"), ls="--", lw=0.9, alpha=0.8, zorder=1)
    for e in kidnaps:
        for ax in (ax_f, ax_o):
            ax.axvline(e["t_s"], color=colour.get(e["robot"], "k"), ls="-", lw=1.8, alpha=0.6, zorder=1)
        ax_f.plot([e["t_s"]], [1.0], "v", color=colour.get(e["robot"], "k"), ms=8, clip_on=False,
                  transform=ax_f.get_xaxis_transform(), zorder=5)
    if relocs:
        handles.append(Line2D([], [], color="0.3", ls="--", lw=0.9, label="re-localisation"))
    if kidnaps:
        handles.append(Line2D([], [], color="0.3", ls="-", lw=1.8, marker="v", label="kidnap"))
    return handles


def plot_error_over_time(ev: Evaluation, path: Path) -> None:
    """Position error |p_est - p_true| (m, map frame, unaligned) against simulation time:
    fused on top, odometry only below (its drift would flatten the fused curves); events
    and kidnaps as vertical lines (see :func:`_mark_events`)."""
    fig = Figure(figsize=(8, 6))
    ax_f, ax_o = fig.subplots(2, 1, sharex=True)
    extra = _mark_events(ax_f, ax_o, ev)
    threshold = ev.metrics["settings"].get("localised_m")
    if threshold is not None and any((k, "fused") in ev.tracks for k in ev.run.robots):
        ax_f.axhline(threshold, color="0.5", lw=0.8, ls=":", zorder=1)
        extra.append(Line2D([], [], color="0.5", ls=":", lw=0.8, label=f"localised < {threshold:g} m"))
    for i, k in enumerate(ev.run.robots):
        for ax, kind in ((ax_f, "fused"), (ax_o, "odom")):
            tr = ev.tracks.get((k, kind))
            if tr is None:
                continue
            segments = _segments(tr.stamps_s, np.column_stack([tr.stamps_s, tr.error_m]))
            for n, seg in enumerate(segments):
                ax.plot(seg[:, 0], seg[:, 1], color=_colour(i), lw=1.2, label=f"robot {k}" if n == 0 else None)
    for ax, what in ((ax_f, "fused"), (ax_o, "odometry only")):
        ax.set_ylabel(f"{what} error [m]")
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            lines = ax.get_legend_handles_labels()[0] + (extra if ax is ax_f else [])
            ax.legend(handles=lines, fontsize=8, ncol=2)
        else:
            ax.text(0.5, 0.5, f"no {what} estimate", transform=ax.transAxes, ha="center", va="center")
    ax_o.set_xlabel("simulation time [s]")
    ax_f.set_title("position error against time (map frame, no alignment)")
    _save(fig, path)


def plot_error_vs_distance(ev: Evaluation, path: Path) -> None:
    """Fused error (m) against the true distance (m) to the nearest robot that observed
    it or that it observed within the neighbour window; median per distance bin."""
    d = ev.distance
    bins = ev.metrics["error_vs_distance"]["bins"]
    fig = Figure(figsize=(7, 4.5))
    ax = fig.add_subplot()
    for i, k in enumerate(ev.run.robots):
        sel = d.robot == k
        if np.any(sel):
            ax.plot(d.distance_m[sel], d.error_m[sel], ".", color=_colour(i), ms=3, alpha=0.35, label=f"robot {k}")
    top = float(np.max(d.distance_m)) if d.distance_m.size else 5.0
    xs, ys, labels = [], [], []
    for b in bins:
        if b["median_error_m"] is None:
            continue
        hi = b["hi_m"] if b["hi_m"] is not None else max(top, b["lo_m"] + 1.0)
        xs.append((b["lo_m"] + hi) / 2)
        ys.append(b["median_error_m"])
        labels.append(b["count"])
        ax.hlines(b["median_error_m"], b["lo_m"], hi, color="k", lw=2.5)
    if xs:
        ax.plot(xs, ys, "k-", lw=1, alpha=0.6, label="median per bin")
        for x, y, n in zip(xs, ys, labels, strict=True):
            ax.annotate(f"n={n}", (x, y), xytext=(0, 6), textcoords="offset points", ha="center", fontsize=8)
        ax.legend(fontsize=8)
    else:
        ax.text(0.5, 0.5, "no fused sample with an observing robot nearby", transform=ax.transAxes,
                ha="center", va="center")
    for b in bins[1:]:
        ax.axvline(b["lo_m"], color="0.6", lw=0.8, ls=":")
    ax.set_xlim(left=0.0)
    ax.set_ylim(bottom=0.0)
    ax.set_xlabel("true distance to nearest observing / observed robot [m]")
    ax.set_ylabel("fused position error [m]")
    ax.set_title("error against distance to the nearest observing robot")
    ax.grid(alpha=0.3)
    _save(fig, path)


def plot_true_vs_measured(ev: Evaluation, scenario: Scenario | None, path: Path) -> None:
    """True (○) and fused (●) positions, map frame, joined pair by pair, one pair per
    :data:`PAIR_PERIOD_S` of simulation time per robot."""
    fig = Figure(figsize=(7.5, 7))
    ax = fig.add_subplot()
    _draw_arena(ax, scenario)
    drawn = False
    for i, k in enumerate(ev.run.robots):
        tr = ev.tracks.get((k, "fused"))
        if tr is None:
            continue
        t = tr.stamps_s
        # one sample per period: the first sample at or after each multiple of PAIR_PERIOD_S
        _, pick = np.unique(np.floor((t - t[0]) / PAIR_PERIOD_S), return_index=True)
        true_xy, est_xy = tr.truth_xy[pick], tr.est_xy[pick]
        col = _colour(i)
        for a, b in zip(true_xy, est_xy, strict=True):
            ax.plot([a[0], b[0]], [a[1], b[1]], "-", color="0.4", lw=0.8, zorder=2)
        ax.plot(true_xy[:, 0], true_xy[:, 1], "o", mfc="none", color=col, ms=6, ls="none", zorder=3,
                label=f"robot {k} true")
        ax.plot(est_xy[:, 0], est_xy[:, 1], "o", color=col, ms=3.5, ls="none", zorder=4, label=f"robot {k} fused")
        drawn = True
    if drawn:
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    else:
        ax.text(0.5, 0.5, "no fused estimate", transform=ax.transAxes, ha="center", va="center")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m] (map frame)")
    ax.set_ylabel("y [m] (map frame)")
    ax.set_title(f"true vs measured positions (one pair per {PAIR_PERIOD_S:g} s)")
    ax.grid(alpha=0.3)
    _save(fig, path)


def write_report(run_dir: Path) -> dict[str, Any]:
    """Evaluate ``run_dir``; write ``metrics.json`` and ``plots/*.png`` (see the module
    docstring) and return the metrics.  Raises :class:`RunFolderError` for a missing
    or malformed folder."""
    run_dir = Path(run_dir)
    ev = evaluate(load_run(run_dir))
    scenario = scenario_of(ev)
    if scenario is None:
        ev.metrics["warnings"].append("run.json has no scenario: arena walls not drawn")
    plots = run_dir / "plots"
    plots.mkdir(exist_ok=True)
    plot_arena(ev, scenario, plots / "arena.png")
    plot_error_over_time(ev, plots / "error_over_time.png")
    plot_error_vs_distance(ev, plots / "error_vs_distance.png")
    plot_true_vs_measured(ev, scenario, plots / "true_vs_measured.png")
    # strict JSON (no NaN): metrics already hold None where a value is undefined
    (run_dir / "metrics.json").write_text(json.dumps(ev.metrics, indent=2, allow_nan=False) + "\n")
    return ev.metrics


# --------------------------------------------------------------------------- CLI


def main(argv: Sequence[str] | None = None) -> int:
    """``tagswarm report RUN_DIR``: 0 on success, 2 with a one-line error for a missing
    or invalid run folder."""
    parser = OneLineParser(prog="tagswarm report",
                           description="Evaluate a run folder written by 'tagswarm up': writes RUN_DIR/metrics.json "
                                       "and RUN_DIR/plots/*.png and prints a summary.")
    parser.add_argument("run_dir", type=Path, metavar="RUN_DIR", help="the run folder")
    args = parse(parser, argv)

    def body() -> int:
        metrics = write_report(args.run_dir)  # a RunFolderError is a usage error: exit 2 (run_main)
        print_summary(metrics, args.run_dir)
        return 0

    return run_main(parser.prog, body)


if __name__ == "__main__":
    raise SystemExit(main())
