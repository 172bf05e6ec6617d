"""Fusion cost: update time per tick and memory vs robot count and run length
(synthetic swarm: robot 0 static, the others on circles, drifting odometry,
noisy observations with 5 % outliers, 10 Hz ticks).  Writes
``bench/results/fusion.json``.

Usage: python bench/fusion.py [--seconds 600] [--robots 4 16 64]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
import tracemalloc
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
import psutil  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from tagswarm.server.fusion import Fusion, FusionParams  # noqa: E402
from tests.synthetic import SyntheticSwarm  # noqa: E402


def run(n: int, seconds: float, rate_hz: float = 10.0) -> dict[str, object]:
    sw = SyntheticSwarm(n=n, seed=n, rate_hz=rate_hz)
    fusion = Fusion(FusionParams(lag_s=30.0, odom_scale_sigma=0.05), 0, tuple(range(n)))
    proc = psutil.Process()
    windows: list[dict[str, float]] = []
    window_s = seconds / 10
    times: list[float] = []
    cpu0 = sum(proc.cpu_times()[:2])
    wall0 = time.perf_counter()
    steps = int(seconds * rate_hz)
    for k in range(steps + 1):
        t = k / rate_hz
        stamp = round(t * 1e9)
        odom, obs = sw.step(t)
        t0 = time.perf_counter()
        for rid, pose in enumerate(odom):
            fusion.add_odometry(rid, stamp, pose, 0.0)
        for i, j, z, cov, _ in obs:
            fusion.add_observation(i, j, stamp, z, cov)
        fusion.advance(stamp)
        times.append(time.perf_counter() - t0)
        if k and k % int(window_s * rate_hz) == 0:
            windows.append({"sim_time_s": t, "update_ms_mean": 1e3 * float(np.mean(times)),
                            "update_ms_p95": 1e3 * float(np.percentile(times, 95)),
                            "rss_mb": proc.memory_info().rss / 2**20,
                            "variables": fusion.smoother.calculateEstimate().size()})
            times = []
    wall = time.perf_counter() - wall0
    cpu = sum(proc.cpu_times()[:2]) - cpu0
    return {"robots": n, "seconds": seconds, "rate_hz": rate_hz, "windows": windows,
            "core_share_at_rate": cpu / seconds,  # CPU-seconds per simulated second incl. data generation
            "wall_s": wall, "counters": dict(fusion.counters)}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, default=600.0)
    p.add_argument("--robots", type=int, nargs="+", default=[4, 16, 64])
    p.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "fusion.json")
    a = p.parse_args()
    tracemalloc.stop()
    rows = [run(n, a.seconds) for n in a.robots]
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps({"bench": "fusion", "machine": {"cpus": os.cpu_count(),
                                                                "python": platform.python_version()},
                                 "rows": rows, "targets": {"16 robots at 10 Hz core share": "<= 0.10",
                                                           "update time": "flat over run length"}}, indent=2))
    t = Table(title="fusion update cost (synthetic, 10 Hz)")
    for c in ("robots", "sim t [s]", "update mean [ms]", "p95 [ms]", "RSS [MB]", "variables"):
        t.add_column(c)
    for r in rows:
        for w in r["windows"]:  # type: ignore[attr-defined]
            t.add_row(str(r["robots"]), f"{w['sim_time_s']:.0f}", f"{w['update_ms_mean']:.2f}",
                      f"{w['update_ms_p95']:.2f}", f"{w['rss_mb']:.0f}", str(w["variables"]))
    Console().print(t)
    for r in rows:
        print(f"{r['robots']} robots: {r['core_share_at_rate']:.3f} core-seconds per simulated second")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
