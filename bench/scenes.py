"""Scenes nobody tuned for (part of the accuracy benchmark): the hall with
occluding shelves, the crowd of 16, the long corridor, the kidnap scene, the
warehouse, the nudge scene (small pushes within the fusion's gate) and the depot
bay (8 robots dropped at random, seen mostly from 3-5 m), each a real lockstep
``tagswarm up`` at its own length.  Per scene: fused error of the swarm and of its
worst robot, time localised (share of robot-time under 10 cm), re-localisations
and kidnap recovery times, contacts, and NEES of the fused position.
``python bench/scenes.py`` runs them alone."""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

# scene -> simulated seconds of its full run (its own duration_s) and of a quick one
SCENES: dict[str, tuple[float, float]] = {"hall": (90.0, 30.0), "crowd": (60.0, 20.0), "corridor": (90.0, 30.0),
                                          "kidnap": (40.0, 30.0), "warehouse": (40.0, 20.0), "nudge": (30.0, 30.0),
                                          "depot": (45.0, 25.0)}
TARGETS = ("every robot: fused RMSE <= 10 cm and final error <= 10 cm; swarm RMSE <= 5 cm; time localised >= 99 %; "
           "kidnap and nudge: back under 10 cm within 3 s; zero robot-robot contacts")


def final_error(run: Path, rid: int) -> float | None:
    """Fused position error (m) at the end of the run, None if never localised."""
    tf, ff = run / "trajectories" / f"truth_{rid}.tum", run / "trajectories" / f"fused_{rid}.tum"
    if not ff.exists() or ff.stat().st_size == 0:
        return None
    truth, fused = np.loadtxt(tf, ndmin=2), np.loadtxt(ff, ndmin=2)
    i = int(np.argmin(np.abs(fused[:, 0] - truth[-1, 0])))
    return math.hypot(fused[i, 1] - truth[-1, 1], fused[i, 2] - truth[-1, 2])


def scene_run(up: Callable[..., Path], work: Path, scene: str, duration: float,
              seed: int | None = None, overrides: tuple[str, ...] = ()) -> dict[str, Any]:
    """One scene end to end with its own seed unless ``seed`` and the scenario ``overrides``
    (``--set`` values); the numbers the README table shows."""
    if seed is None:
        from tagswarm.protocol.scenario import load_scenario

        seed = load_scenario(scene).seed  # a random placement is part of the scene
    sets = [arg for o in overrides for arg in ("--set", o)]
    run = up(work / f"scene_{scene}_{seed}", "--scenario", scene, "--seed", str(seed), "--duration", str(duration),
             *sets)
    m = json.loads((run / "metrics.json").read_text())
    sw, robots = m["swarm"], m["robots"]
    fused = sw.get("fused") or {}

    def rmse(r: dict[str, Any]) -> float | None:
        return ((r.get("fused") or {}).get("ate_unaligned") or {}).get("rmse")

    def nominal(r: dict[str, Any]) -> float | None:
        return ((r.get("fused") or {}).get("ate_unaligned_nominal") or {}).get("rmse")

    per_robot = {rid: {"rmse_m": rmse(r), "rmse_nominal_m": nominal(r), "final_m": final_error(run, int(rid)),
                       "time_localised": (r.get("fused") or {}).get("time_localised"),
                       "time_localised_placed": (r.get("fused") or {}).get("time_localised_placed"),
                       "first_placed_s": (r.get("fused") or {}).get("first_s"),
                       "relocalisations": r.get("relocalisations"), "contacts": r.get("contacts")}
                 for rid, r in robots.items()}
    worst_rmse = max((v["rmse_m"] for v in per_robot.values() if v["rmse_m"] is not None), default=None)
    finals = [v["final_m"] for v in per_robot.values()]
    return {
        "scene": scene, "seed": seed, "duration_s": duration, "robots": len(robots),
        "fused_ate_rmse_m": (fused.get("ate_unaligned") or {}).get("rmse"),
        "fused_ate_max_m": (fused.get("ate_unaligned") or {}).get("max"),
        "odom_ate_rmse_m": ((sw.get("odom") or {}).get("ate_unaligned") or {}).get("rmse"),
        "worst_robot_rmse_m": worst_rmse,
        # outside each kidnap until its robot is localised again (the recovery time measures those seconds)
        "fused_ate_rmse_nominal_m": (fused.get("ate_unaligned_nominal") or {}).get("rmse"),
        "worst_robot_rmse_nominal_m": max((v["rmse_nominal_m"] for v in per_robot.values()
                                           if v["rmse_nominal_m"] is not None), default=None),
        "worst_final_m": None if None in finals else max(finals, default=None),
        "time_localised": fused.get("time_localised"),
        "time_localised_min_robot": min((v["time_localised"] for v in per_robot.values()
                                         if v["time_localised"] is not None), default=None),
        "time_localised_placed": fused.get("time_localised_placed"),
        "last_first_placement_s": max((v["first_placed_s"] for v in per_robot.values()
                                       if v["first_placed_s"] is not None), default=None),
        "relocalisations": sw.get("relocalisations"), "kidnaps": sw.get("kidnaps"), "contacts": sw.get("contacts"),
        "nees": fused.get("nees"), "nees_nominal": fused.get("nees_nominal"),
        "searches": sw.get("searches"), "rtf": m["cost"].get("real_time_factor"),
        # the robot views' systematic range error per range bin (metrics.json view_error_vs_range)
        "view_range_bias_m": {f"{b['lo_m']:g}-{'' if b['hi_m'] is None else format(b['hi_m'], 'g')}": b["range_bias_m"]
                              for b in (m.get("view_error_vs_range") or {}).get("bins", []) if b["count"]},
        "per_robot": per_robot,
    }


def with_nominal(r: dict[str, Any], key: str) -> str:
    """``r[key]`` in cm; in a scene with kidnaps followed by the same outside them in brackets (a kidnapped
    robot is ~1 m off until it is found again, and the recovery time measures those seconds)."""
    nominal = r.get(key.replace("_rmse_m", "_rmse_nominal_m"))
    text = "-" if r.get(key) is None else f"{100 * r[key]:.1f}"
    return text if not (r.get("kidnaps") or {}).get("count") or nominal is None else f"{text} ({100 * nominal:.1f})"


def table_rows(results: list[dict[str, Any]], show_seed: bool = False) -> list[list[str]]:
    """README-style rows: scene, robots, s, swarm RMSE, worst robot RMSE (with kidnaps: "all (outside the
    kidnaps)"), worst final, time localised (swarm /
    worst robot), time localised once placed (swarm), re-localisations, kidnap recovery, robot-robot contacts,
    NEES mean (outside kidnaps)."""
    def cm(v: float | None) -> str:
        return "-" if v is None else f"{100 * v:.1f}"

    rows = []
    for r in results:
        kid = r.get("kidnaps") or {}
        rec = "-" if not kid.get("count") else f"{kid.get('recovered')}/{kid.get('count')}, max " \
              f"{kid.get('max_time_to_relocalise_s') or float('nan'):.1f} s"
        tl, tlm, tlp = r.get("time_localised"), r.get("time_localised_min_robot"), r.get("time_localised_placed")
        nees = (r.get("nees_nominal") or r.get("nees") or {}).get("mean")
        name = f"{r['scene']} (seed {r['seed']})" if show_seed else r["scene"]
        rows.append([name, str(r["robots"]), f"{r['duration_s']:.0f}", with_nominal(r, "fused_ate_rmse_m"),
                     with_nominal(r, "worst_robot_rmse_m"), cm(r["worst_final_m"]),
                     "-" if tl is None else f"{100 * tl:.1f} / {100 * (tlm or 0):.1f} %",
                     "-" if tlp is None else f"{100 * tlp:.1f} %",
                     str(r.get("relocalisations") or 0), rec,
                     str((r.get("contacts") or {}).get("robot_robot", "-")),
                     "-" if nees is None else f"{nees:.2f}"])
    return rows


HEADER = ["scene", "robots", "s", "swarm RMSE cm", "worst robot RMSE cm", "worst final cm", "time localised",
          "once placed",
          "re-loc.", "kidnaps", "robot contacts", "NEES mean"]


def main() -> int:
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import tempfile

    from accuracy import machine, print_table, up  # type: ignore[import-not-found]

    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--quick", action="store_true", help="shorter runs (see SCENES)")
    p.add_argument("--scenes", nargs="*", default=list(SCENES))
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="scenario override for every scene (repeatable), e.g. server.obs_sigma_floor_m=0.02")
    p.add_argument("--keep", type=Path, default=None, help="keep the run folders here (default: deleted)")
    p.add_argument("--seeds", type=int, nargs="+", default=None, metavar="N",
                   help="run every scene at these seeds instead of its own (the seed draws the wheels' biases "
                        "and the sensor noise; a scene's random placement too)")
    a = p.parse_args()
    if any(o.split("=", 1)[0].strip() == "seed" for o in a.set):
        # each run's --seed flag beats a --set override: it would silently run the scene's own seed
        p.error("--set seed=N has no effect here (each run gets --seed): use --seeds N")
    root = Path(__file__).resolve().parents[1]
    out = a.out or root / "bench" / "results" / ("scenes_quick.json" if a.quick else "scenes.json")
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="tagswarm-scenes-") as tmp:
        work = Path(tmp) if a.keep is None else a.keep
        work.mkdir(parents=True, exist_ok=True)
        results = [scene_run(up, work, s, SCENES[s][1 if a.quick else 0], seed=seed, overrides=tuple(a.set))
                   for seed in (a.seeds or [None]) for s in a.scenes]
    out.write_text(json.dumps({"bench": "scenes", "machine": machine(), "targets": TARGETS, "overrides": a.set,
                               "seeds": a.seeds,
                               "scenes": results,
                               "wall_time_s": time.monotonic() - t0}, indent=2))
    print_table("scenes", HEADER, table_rows(results, show_seed=bool(a.seeds)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
