"""The paper's experiment side by side (part of the accuracy benchmark): the server's
two methods, ``[server] method = "stitch"`` (the paper's chain of homogeneous
transforms, live) and ``"graph"`` (the GTSAM fixed-lag pose graph), on the same
scenes and seeds, each a real lockstep ``tagswarm up``.  Per scene and method: fused
error of the swarm (unaligned ATE RMSE, the map frame) against odometry only, the
worst robot's RMSE and final error, time localised and NEES of the fused position;
and per method one plot of the fused position error over time of every robot
(``bench/results/methods_<method>.png``, one panel per scene).  Runs are shorter than
the scenes' own ``duration_s`` (see SCENES) to keep the bench under an hour on two
cores.  ``python bench/methods.py`` runs it alone; results in
``bench/results/methods.json``."""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

METHODS = ("stitch", "graph")
# scene -> simulated seconds here
SCENES: dict[str, float] = {"paper": 20.0, "allmoving": 20.0, "leapfrog": 20.0, "landmarks": 20.0, "hall": 20.0,
                            "corridor": 20.0, "crowd": 10.0, "kidnap": 20.0}


def error_over_time(run: Path, rid: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(t_s, fused position error m) of robot ``rid`` at each fused estimate (truth interpolated)."""
    tf, ff = run / "trajectories" / f"truth_{rid}.tum", run / "trajectories" / f"fused_{rid}.tum"
    if not ff.exists() or ff.stat().st_size == 0:
        return None
    truth, fused = np.loadtxt(tf, ndmin=2), np.loadtxt(ff, ndmin=2)
    x = np.interp(fused[:, 0], truth[:, 0], truth[:, 1])
    y = np.interp(fused[:, 0], truth[:, 0], truth[:, 2])
    return fused[:, 0], np.hypot(fused[:, 1] - x, fused[:, 2] - y)


def method_run(up: Callable[..., Path], work: Path, scene: str, method: str, duration: float,
               seed: int = 0) -> dict[str, Any]:
    """One scene with one server method end to end (``up`` runs ``tagswarm up``, see bench/accuracy.py);
    the table's numbers, and each robot's error curve under ``_curves`` (for :func:`plot`, not JSON)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from scenes import final_error  # type: ignore[import-not-found]

    run = up(work / f"{scene}_{method}_{seed}", "--scenario", scene, "--seed", str(seed), "--duration", str(duration),
             "--set", f'server.method="{method}"')
    m = json.loads((run / "metrics.json").read_text())
    assert m["run"]["method"] == method, m["run"]
    sw, robots = m["swarm"], m["robots"]
    fused = sw.get("fused") or {}

    def rmse(block: dict[str, Any] | None) -> float | None:
        return ((block or {}).get("ate_unaligned") or {}).get("rmse")

    per_robot = {rid: {"fused_rmse_m": rmse(r.get("fused")), "odom_rmse_m": rmse(r.get("odom")),
                       "final_m": final_error(run, int(rid))} for rid, r in robots.items()}
    curves = {rid: c for rid in robots if (c := error_over_time(run, int(rid))) is not None}
    finals = [v["final_m"] for v in per_robot.values()]
    nees = fused.get("nees_nominal") or fused.get("nees") or {}
    return {
        "scene": scene, "method": method, "seed": seed, "duration_s": duration, "robots": len(robots),
        "fused_ate_rmse_m": rmse(fused), "odom_ate_rmse_m": rmse(sw.get("odom")),
        "worst_robot_rmse_m": max((v["fused_rmse_m"] for v in per_robot.values() if v["fused_rmse_m"] is not None),
                                  default=None),
        "worst_final_m": None if None in finals else max(finals, default=None),
        "time_localised": fused.get("time_localised"), "nees_mean": nees.get("mean"),
        "relocalisations": sw.get("relocalisations"), "per_robot": per_robot,
        "_curves": {rid: (t.tolist(), e.tolist()) for rid, (t, e) in curves.items()},
    }


def plot(results: list[dict[str, Any]], method: str, path: Path) -> None:
    """One figure per method: a panel per scene, the fused error over time of every robot."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rs = [r for r in results if r["method"] == method]
    cols = 4
    rows = (len(rs) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 2.8 * rows), squeeze=False, sharey=True)
    for ax, r in zip(axes.ravel(), rs, strict=False):
        for rid, (t, e) in sorted(r["_curves"].items(), key=lambda kv: int(kv[0])):
            ax.plot(t, np.asarray(e) * 100, lw=0.8, label=f"robot {rid}")
        ax.set_title(f"{r['scene']} ({method})", fontsize=9)
        ax.set_yscale("log")
        ax.set_ylim(0.05, 300)
        ax.grid(True, which="both", lw=0.3)
        ax.set_xlabel("simulated s", fontsize=8)
    for ax in axes.ravel()[len(rs):]:
        ax.axis("off")
    axes[0, 0].set_ylabel("fused position error (cm)")
    fig.suptitle(f"server method = {method}: fused position error per robot over time")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def without_curves(results: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The results as written to JSON."""
    return [{k: v for k, v in r.items() if k != "_curves"} for r in results]


def table_rows(results: list[dict[str, Any]]) -> list[list[str]]:
    def cm(v: float | None) -> str:
        return "-" if v is None else f"{100 * v:.1f}"

    rows = []
    for r in results:
        tl, nees = r.get("time_localised"), r.get("nees_mean")
        rows.append([r["scene"], r["method"], str(r["robots"]), f"{r['duration_s']:.0f}", cm(r["fused_ate_rmse_m"]),
                     cm(r["odom_ate_rmse_m"]), cm(r["worst_robot_rmse_m"]), cm(r["worst_final_m"]),
                     "-" if tl is None else f"{100 * tl:.1f} %", "-" if nees is None else f"{nees:.2f}"])
    return rows


HEADER = ["scene", "method", "robots", "s", "swarm RMSE cm", "odom RMSE cm", "worst robot RMSE cm", "worst final cm",
          "time localised", "NEES mean"]


def main() -> int:
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import tempfile

    from accuracy import machine, print_table, up  # type: ignore[import-not-found]

    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--scenes", nargs="*", default=list(SCENES))
    p.add_argument("--methods", nargs="*", default=list(METHODS), choices=METHODS)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=None, help="JSON (default bench/results/methods.json)")
    a = p.parse_args()
    root = Path(__file__).resolve().parents[1]
    out = a.out or root / "bench" / "results" / "methods.json"
    t0 = time.monotonic()
    results: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="tagswarm-methods-") as tmp:
        for scene in a.scenes:
            for method in a.methods:
                try:
                    results.append(method_run(up, Path(tmp), scene, method, SCENES[scene], a.seed))
                except RuntimeError as exc:  # one failed run is a result too, not the end of the bench
                    results.append({"scene": scene, "method": method, "seed": a.seed, "duration_s": SCENES[scene],
                                    "robots": 0, "fused_ate_rmse_m": None, "odom_ate_rmse_m": None,
                                    "worst_robot_rmse_m": None, "worst_final_m": None, "time_localised": None,
                                    "nees_mean": None, "error": str(exc)[-500:], "_curves": {}})
                print(f"{scene} {method}: {table_rows(results[-1:])[0]}", flush=True)
    for method in a.methods:
        plot(results, method, out.parent / f"methods_{method}.png")
    out.write_text(json.dumps({"bench": "methods", "machine": machine(), "scenes": SCENES,
                               "results": without_curves(results),
                               "wall_time_s": time.monotonic() - t0}, indent=2))
    print_table(f"server methods (lockstep, seed {a.seed})", HEADER, table_rows(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
