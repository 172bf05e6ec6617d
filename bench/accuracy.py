"""Accuracy benchmarks: the paper's static Fig. 5 experiment and its dynamic
section 2.2 run, plus the frame-keeping variants and ablations.  Every run is a
real ``tagswarm up --clock lockstep`` (world, server, agents as processes).
Writes ``bench/results/accuracy.json`` and plots next to it.

- static: robots at evenly spread points of the 7 m x 7 m arena with seeded
  random headings, no motion.  The paper's stitching from ONE round of
  observations (the first camera frame) and the factor-graph map after one
  second are both scored against the truth (map frame = robot 0's pose).
- dynamic: scenarios on missions with the odometry error model on, several
  seeds: ATE of fused vs odometry-only (unaligned and with one shared SE(2)
  alignment), pairwise distance error, re-localisation rotations, time lost.
- ablations (dynamic, paper scenario): 320x240 vs 640x480, one camera vs a
  four-camera rig, active re-localisation on vs off.

Usage: python bench/accuracy.py [--trials 20] [--duration 300] [--seeds 3] [--quick]
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from protocol.geometry import se2_between, wrap_angle  # noqa: E402
from server.stitch import Edge, stitch  # noqa: E402

TAGSWARM = str(Path(sys.executable).parent / "tagswarm")
CAM640 = 'robot.cameras=[{name="front", width=640, height=480, hfov_deg=60, rate_hz=10}]'
RIG4 = ('robot.cameras=[{name="front", yaw_deg=0}, {name="left", yaw_deg=90}, {name="rear", yaw_deg=180}, '
        '{name="right", yaw_deg=-90}]')


def up(out: Path, *args: str) -> Path:
    cmd = [TAGSWARM, "up", "--clock", "lockstep", "--out", str(out), "--no-live", *args]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{res.stdout[-2000:]}{res.stderr[-2000:]}")
    return out


def _tum_first_last(path: Path) -> tuple[np.ndarray | None, np.ndarray | None]:
    if not path.exists() or path.stat().st_size == 0:
        return None, None
    a = np.loadtxt(path, ndmin=2)
    return a[0], a[-1]


def _yaw(row: np.ndarray) -> float:
    return 2 * math.atan2(row[6], row[7])


def static_trial(seed: int, work: Path) -> dict[str, Any]:
    run = up(work / f"static{seed}", "--seed", str(seed), "--duration", "1.0", "--no-report", "--set",
             'robots.placement="grid"', "--set", "missions=[]", "--set", CAM640)
    meta = json.loads((run / "run.json").read_text())
    robots = meta["robots"]
    truth = {r: _tum_first_last(run / "trajectories" / f"truth_{r}.tum")[0] for r in robots}
    tpose = {r: (float(t[1]), float(t[2]), _yaw(t)) for r, t in truth.items() if t is not None}
    edges, first = [], None
    with open(run / "observations.csv") as f:
        for row in csv.DictReader(f):
            if row["target_kind"] != "robot":
                continue
            stamp = int(row["stamp_ns"])
            first = stamp if first is None else first
            if stamp != first:
                continue  # the paper: one round of observations
            cov = np.eye(3) * 1e-3
            edges.append(Edge(int(row["observer"]), int(row["target_id"]),
                              (float(row["x_m"]), float(row["y_m"]), float(row["yaw_rad"])), cov))
    placed = stitch(edges, origin=0)
    out: dict[str, Any] = {"seed": seed, "robots": len(robots), "stitch": [], "fusion": []}
    for r in robots:
        if r == 0:
            continue
        observers = [tpose[e.observer] for e in edges if e.target == r] + \
                    [tpose[e.target] for e in edges if e.observer == r]
        dist = min((math.dist(tpose[r][:2], p[:2]) for p in observers), default=None)
        if r in placed:
            d = se2_between(tpose[r], placed[r])
            out["stitch"].append({"robot": r, "err_m": math.hypot(d[0], d[1]), "yaw_deg": abs(math.degrees(d[2])),
                                  "dist_m": dist})
        _, last = _tum_first_last(run / "trajectories" / f"fused_{r}.tum")
        if last is not None:
            out["fusion"].append({"robot": r, "err_m": math.hypot(last[1] - tpose[r][0], last[2] - tpose[r][1]),
                                  "yaw_deg": abs(math.degrees(wrap_angle(_yaw(last) - tpose[r][2]))),
                                  "dist_m": dist})
    return out


def summarise_static(trials: list[dict[str, Any]]) -> dict[str, Any]:
    total = sum(t["robots"] - 1 for t in trials)
    res: dict[str, Any] = {"trials": len(trials), "robots_to_place": total}
    for kind in ("stitch", "fusion"):
        rows = [r for t in trials for r in t[kind]]
        e = np.array([r["err_m"] for r in rows]) if rows else np.zeros(0)
        y = np.array([r["yaw_deg"] for r in rows]) if rows else np.zeros(0)
        bins = []
        for lo, hi in ((0, 1), (1, 2), (2, 3), (3, 4), (4, 6)):
            sel = [r["err_m"] for r in rows if r["dist_m"] is not None and lo <= r["dist_m"] < hi]
            bins.append({"range_m": [lo, hi], "n": len(sel),
                         "median_err_m": float(np.median(sel)) if sel else None})
        res[kind] = {"share_localised": len(rows) / max(total, 1),
                     "err_median_m": float(np.median(e)) if len(e) else None,
                     "err_p95_m": float(np.percentile(e, 95)) if len(e) else None,
                     "err_max_m": float(e.max()) if len(e) else None,
                     "yaw_median_deg": float(np.median(y)) if len(y) else None,
                     "yaw_p95_deg": float(np.percentile(y, 95)) if len(y) else None,
                     "by_distance": bins}
    return res


def dynamic_run(name: str, work: Path, seed: int, duration: float, *overrides: str,
                scenario: str = "paper") -> dict[str, Any]:
    args = ["--scenario", scenario, "--seed", str(seed), "--duration", str(duration)]
    for o in overrides:
        args += ["--set", o]
    run = up(work / f"{name}_{seed}", *args)
    m = json.loads((run / "metrics.json").read_text())
    sw = m["swarm"]

    def pick(kind: str) -> dict[str, Any]:
        k = sw[kind]
        return {"ate_unaligned_rmse": (k.get("ate_unaligned") or {}).get("rmse"),
                "ate_unaligned_max": (k.get("ate_unaligned") or {}).get("max"),
                "ate_aligned_rmse": (k.get("ate_aligned") or {}).get("rmse"),
                "ate_aligned_max": (k.get("ate_aligned") or {}).get("max"),
                "pairwise_rmse": (k.get("pairwise") or {}).get("rmse")}

    return {"name": name, "scenario": scenario, "seed": seed, "duration_s": duration, "fused": pick("fused"),
            "odom": pick("odom"), "searches": sw.get("searches"), "time_lost_s": sw.get("time_lost_s"),
            "rtf": m["cost"].get("real_time_factor")}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--trials", type=int, default=20)
    p.add_argument("--duration", type=float, default=300.0)
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--quick", action="store_true", help="5 trials, 60 s, 1 seed")
    p.add_argument("--skip-ablations", action="store_true")
    p.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "accuracy.json")
    a = p.parse_args()
    if a.quick:
        a.trials, a.duration, a.seeds = 5, 60.0, 1
    console = Console()
    result: dict[str, Any] = {"bench": "accuracy", "machine": {"cpus": os.cpu_count()},
                              "targets": {"static": "median <= 3 cm, p95 <= 10 cm, yaw <= 1.5 deg (640x480)",
                                          "dynamic": "fused ATE RMSE <= 5 cm, max <= 20 cm, >= 10x odometry"}}
    with tempfile.TemporaryDirectory(prefix="tagswarm-acc-") as tmp:
        work = Path(tmp)
        trials = [static_trial(s, work) for s in range(a.trials)]
        result["static"] = summarise_static(trials)
        console.print("static", json.dumps({k: result["static"][k] for k in ("stitch", "fusion")}, indent=1))
        dyn = []
        for scenario in ("paper", "allmoving", "leapfrog", "landmarks"):
            for seed in range(a.seeds):
                dyn.append(dynamic_run(scenario, work, seed, a.duration, scenario=scenario))
                console.print(dyn[-1])
        result["dynamic"] = dyn
        if not a.skip_ablations:
            abl = []
            for name, ov in (("paper_640x480", [CAM640]), ("paper_rig4", [RIG4]),
                             ("paper_no_relocalisation", ["agent.fix_threshold=100000000"])):
                abl.append(dynamic_run(name, work, 0, a.duration, *ov))
                console.print(abl[-1])
            result["ablations"] = abl
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(result, indent=2))
    t = Table(title="dynamic runs (swarm, metres)")
    for c in ("run", "seed", "fused ATE", "fused max", "fused aligned", "odom ATE", "odom/fused", "searches"):
        t.add_column(c)
    for r in result["dynamic"] + result.get("ablations", []):
        f, o = r["fused"], r["odom"]
        ratio = (o["ate_unaligned_rmse"] or 0) / max(f["ate_unaligned_rmse"] or 1e-9, 1e-9)
        t.add_row(r["name"], str(r["seed"]), f"{f['ate_unaligned_rmse']:.3f}", f"{f['ate_unaligned_max']:.3f}",
                  f"{f['ate_aligned_rmse']:.3f}", f"{o['ate_unaligned_rmse']:.3f}", f"{ratio:.1f}x",
                  str(r["searches"]))
    console.print(t)
    console.print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
