"""The printed summary of ``tagswarm report``: tables of accuracy, localisation and
recovery, and behaviour per robot plus the swarm, then the formation error,
shared alignment, re-localisation events, kidnaps, contacts, cost and warnings.

Reads only the ``metrics.json`` dict (fields documented in :mod:`tagswarm.evaluation.metrics`);
metres, seconds of simulation time.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from rich import box
from rich.console import Console
from rich.markup import escape
from rich.table import Table

LIST_MAX = 12
"""Re-localisation events and kidnaps listed one per line at most (then a count)."""


def _m(value: Any, digits: int = 3) -> str:
    return "—" if value is None else f"{value:.{digits}f}"


def _rmse(block: dict[str, Any] | None, key: str) -> str:
    stats = (block or {}).get(key)
    return _m(stats["rmse"]) if stats else "—"


def _ate_map(block: dict[str, Any] | None) -> str:
    """Fused ATE in the map frame; where kidnaps left samples out, "all (outside the kidnaps)"."""
    full, nominal = (block or {}).get("ate_unaligned"), (block or {}).get("ate_unaligned_nominal")
    if full and nominal and nominal["count"] != full["count"]:
        return f"{_m(full['rmse'])} ({_m(nominal['rmse'])})"
    return _rmse(block, "ate_unaligned")


def _int(value: Any) -> str:
    return "—" if value is None else str(value)


def _pct(value: Any) -> str:
    return "—" if value is None else f"{100 * value:.1f} %"


def _nees(block: dict[str, Any] | None) -> str:
    n = (block or {}).get("nees_nominal") or (block or {}).get("nees")
    return f"{n['mean']:.2f} / {n['median']:.2f}" if n else "—"


def summary_tables(metrics: dict[str, Any]) -> tuple[Table, Table, Table]:
    """(accuracy, localisation, behaviour) tables: one row per robot plus a pooled swarm
    row.  ATE and RPE are RMSEs in metres ("map" = unaligned in the map frame,
    "aligned" = after the swarm's shared SE(2) alignment; RPE in m per m travelled; a kidnapped
    robot's fused map ATE is followed by the same outside its kidnaps, in brackets; "fused max"
    the largest unaligned error, so a robot that went astray for a while is seen; the odometry's
    aligned ATE is in metrics.json);
    "time localised" is the share of time with fused error under
    ``settings.localised_m``, NEES the fused position's mean / median outside kidnaps, σ median
    the map's own uncertainty of each robot (``fused.sigma_median_m``)."""
    acc = Table(title="accuracy: RMSE in m, max in m (RPE: m per m travelled)", box=box.SIMPLE_HEAD)
    loc = Table(title="localisation and recovery", box=box.SIMPLE_HEAD)
    beh = Table(title="behaviour and cost", box=box.SIMPLE_HEAD)
    for table, names in ((acc, ("fused ATE\nmap", "fused\nmax", "fused ATE\naligned", "odom ATE\nmap",
                                "fused\nRPE/m", "odom\nRPE/m")),
                         (loc, ("time\nlocalised", "once\nplaced", "NEES\nmean / median", "σ\n(m)",
                                "re-\nlocalisations", "kidnaps", "contacts")),
                         (beh, ("fixes", "searches", "lost\nevents", "time\nlost (s)", "frames\nprocessed",
                                "frames\nskipped"))):
        table.add_column("robot", justify="left")
        for name in names:
            table.add_column(name, justify="right")

    def add(name: str, r: dict[str, Any], recovery: tuple[Any, Any, Any], frames: tuple[Any, Any],
            style: str | None = None) -> None:
        f, o = r["fused"], r["odom"]
        fmax = _m((f.get("ate_unaligned") or {}).get("max"))
        acc.add_row(name, _ate_map(f), fmax, _rmse(f, "ate_aligned"), _rmse(o, "ate_unaligned"),
                    _rmse(f, "rpe_per_m"), _rmse(o, "rpe_per_m"), style=style)
        loc.add_row(name, _pct(f.get("time_localised")), _pct(f.get("time_localised_placed")), _nees(f),
                    _m(f.get("sigma_median_m")), *(_int(v) for v in recovery), style=style)
        beh.add_row(name, _int(r["fixes"]), _int(r["searches"]), _int(r["lost_events"]), _m(r["time_lost_s"], 1),
                    _int(frames[0]), _int(frames[1]), style=style)

    for k, r in metrics["robots"].items():
        add(k, r, (r.get("relocalisations"), r.get("kidnaps"), r.get("contacts")),
            (r["frames_processed"], r["frames_skipped"]))
    for table in (acc, loc, beh):
        table.add_section()
    c, s = metrics["cost"], metrics["swarm"]
    contacts = s.get("contacts") or {}
    known = [v for v in contacts.values() if v is not None]
    add("swarm", s, (s.get("relocalisations"), (s.get("kidnaps") or {}).get("count"), sum(known) if known else None),
        (c["frames_processed"], c["frames_skipped"]), style="bold")
    return acc, loc, beh


def recovery_lines(metrics: dict[str, Any]) -> list[str]:
    """One line per re-localisation event and kidnap (at most :data:`LIST_MAX` each), and the contacts."""
    lines = []
    relocs = metrics.get("relocalisations") or []
    if relocs:
        lines.append(f"re-localisations: {len(relocs)}")
    for e in relocs[:LIST_MAX]:
        observers = ", ".join("landmark" if o < 0 else str(o) for o in e["observers"]) or "—"
        lines.append(f"  t={e['t_s']:.2f} s robot {e['robot']}: jump {e['jump_m']:.2f} m on {e['evidence']} "
                     f"observations by {observers}; error {_m(e['error_before_m'])} -> {_m(e['error_after_m'])} m")
    if len(relocs) > LIST_MAX:
        lines.append(f"  … and {len(relocs) - LIST_MAX} more (metrics.json)")
    kidnaps = metrics.get("kidnaps") or []
    for k in kidnaps[:LIST_MAX]:
        back = k["time_to_relocalise_s"]
        first = k["first_relocalisation_s"]
        lines.append(f"kidnap t={k['t_s']:.2f} s robot {k['robot']} ({k['action']}, {_m(k['displacement_m'], 2)} m): "
                     + (f"localised again after {back:.2f} s" if back is not None else "never localised again")
                     + (f", first re-localisation after {first:.2f} s" if first is not None else ""))
    if len(kidnaps) > LIST_MAX:
        lines.append(f"… and {len(kidnaps) - LIST_MAX} more kidnaps (metrics.json)")
    contacts = metrics["swarm"].get("contacts") or {}
    if any(v is not None for v in contacts.values()):
        lines.append("contacts: " + ", ".join(f"{k.replace('_', '-')} {_int(v)}" for k, v in contacts.items()))
    return lines


def view_line(metrics: dict[str, Any]) -> str | None:
    """The robot views' range bias per range bin (mm, bins with views) and, where the views
    carried covariances, their NEES; ``None`` without views."""
    v = metrics.get("view_error_vs_range") or {}
    bins = [b for b in v.get("bins", []) if b["count"]]
    if not bins:
        return None
    parts = [f"{1000 * b['range_bias_m']:+.1f} mm "
             + (f"at {b['lo_m']:g}-{b['hi_m']:g} m" if b["hi_m"] is not None else f"beyond {b['lo_m']:g} m")
             + f" ({b['count']}" + (f", NEES {b['nees']:.2f})" if b.get("nees") is not None else ")")
             for b in bins]
    return f"robot views against the truth, range bias (+ = seen farther): {', '.join(parts)}"


def print_summary(metrics: dict[str, Any], run_dir: Path, console: Console | None = None) -> None:
    """The summary tables, formation error, shared alignment, recovery, cost and warnings."""
    con = console or Console()
    con.print(f"server method: {metrics['run'].get('method', 'graph')}", highlight=False)
    for table in summary_tables(metrics):
        con.print(table)
    s, c = metrics["swarm"], metrics["cost"]
    for kind in ("fused", "odom"):
        pw, al = s[kind]["pairwise"], s[kind]["alignment"]
        con.print(f"{kind}: pairwise distance error rmse {_rmse(s[kind], 'pairwise')} m, "
                  f"max {_m(pw and pw['max'])} m", highlight=False)
        if al:
            con.print(f"  shared SE(2) alignment: yaw {math.degrees(al['yaw_rad']):.2f} deg, "
                      f"shift ({al['x_m']:.3f}, {al['y_m']:.3f}) m, {al['points']} points", highlight=False)
    views = view_line(metrics)
    if views is not None:
        con.print(views, highlight=False, soft_wrap=True)
    for line in recovery_lines(metrics):
        con.print(line, highlight=False, soft_wrap=True)
    con.print(f"cost: wall {_m(c['wall_time_s'], 1)} s, sim {_m(c['sim_time_s'], 1)} s, "
              f"real-time factor {_m(c['real_time_factor'], 2)}, frames rendered {_int(c['frames_rendered'])}",
              highlight=False)
    for w in metrics["warnings"]:
        con.print(f"[yellow]warning:[/yellow] {escape(w)}", highlight=False)  # a note may hold [brackets]
    con.print(f"wrote {run_dir / 'metrics.json'} and {run_dir / 'plots'}/", highlight=False)
