"""Run the issue-6 benchmarks in order -- accuracy (paper Fig. 5 static, section 2.2
dynamic, frame-keeping variants, ablations), then realtime speed -- and record how
long each took, so the "under 30 minutes (quick: 5)" budget is itself measured.
Writes ``bench/results/all.json`` (``all_quick.json`` with ``--quick``) beside the
benchmarks' own JSON and plots.

Usage: python bench/all.py [--quick] [--jobs 2]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="the smaller versions (target: under 5 minutes in all)")
    p.add_argument("--jobs", type=int, default=2, help="accuracy runs at a time (each is a whole lockstep system)")
    a = p.parse_args()
    quick = ["--quick"] if a.quick else []
    steps = [("accuracy", [sys.executable, str(ROOT / "bench" / "accuracy.py"), "--jobs", str(a.jobs), *quick]),
             ("speed", [sys.executable, str(ROOT / "bench" / "speed.py"), *quick])]
    out: dict[str, object] = {"bench": "all", "quick": a.quick, "cpus": os.cpu_count(),
                              "platform": platform.platform(), "load_avg_at_start": os.getloadavg(), "steps": {}}
    t_all = time.monotonic()
    failed = 0
    for name, cmd in steps:
        t0 = time.monotonic()
        rc = subprocess.call(cmd, cwd=ROOT)
        out["steps"][name] = {"wall_s": round(time.monotonic() - t0, 1), "exit_code": rc}  # type: ignore[index]
        failed |= rc != 0
        print(f"bench/all: {name} took {(time.monotonic() - t0) / 60:.1f} min (exit {rc})", flush=True)
    out["wall_s"] = round(time.monotonic() - t_all, 1)
    out["load_avg_at_end"] = os.getloadavg()
    path = ROOT / "bench" / "results" / ("all_quick.json" if a.quick else "all.json")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=2))
    print(f"bench/all: everything took {out['wall_s'] / 60:.1f} min; wrote {path}")  # type: ignore[operator]
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
