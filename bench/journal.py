"""Server journal cost: what journalling adds to the live server, what fsync
batches cost, and how long a restarted server takes to rebuild its graph from a
journal of N records (synthetic swarm as bench/fusion.py, at the live system's
rates: odometry and one fusion update per 30 Hz tick, observations from 10 Hz
cameras).  Writes ``bench/results/journal.json``.

Usage: python bench/journal.py [--seconds 60 300 600] [--robots 4 16] [--dir DIR]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from server import journal as jr  # noqa: E402
from server.fusion import Fusion, FusionParams  # noqa: E402
from tests.synthetic import SyntheticSwarm  # noqa: E402

TICK_HZ = 30.0
CAMERA_EVERY = 3  # ticks between camera frames (10 Hz)


def _stream(n: int, seconds: float) -> list[list[jr.Odometry | jr.Observation | jr.Advance]]:
    """Per tick, the records a live server would journal (odometry, observations, the update)."""
    sw = SyntheticSwarm(n=n, seed=n, rate_hz=TICK_HZ)
    ticks = []
    for k in range(int(seconds * TICK_HZ) + 1):
        stamp = round(k / TICK_HZ * 1e9)
        odom, obs = sw.step(k / TICK_HZ)
        recs: list[jr.Odometry | jr.Observation | jr.Advance] = [
            jr.Odometry(robot_id=rid, stamp_ns=stamp, x_m=float(p[0]), y_m=float(p[1]), yaw_rad=float(p[2]),
                        distance_m=0.0) for rid, p in enumerate(odom)]
        if k % CAMERA_EVERY == 0:
            recs += [jr.Observation(observer=i, target_kind="robot", target_id=t, stamp_ns=stamp, x_m=float(z[0]),
                                    y_m=float(z[1]), yaw_rad=float(z[2]), cov=tuple(float(v) for v in c.ravel()))
                     for i, t, z, c, _ in obs]
        recs.append(jr.Advance(watermark_ns=stamp))
        ticks.append(recs)
    return ticks


def _fusion(n: int) -> Fusion:
    return Fusion(FusionParams(odom_scale_sigma=0.05), 0, tuple(range(n)))


def rebuild(n: int, seconds: float, folder: Path) -> dict[str, object]:
    """Live run with and without the journal, then a replay of the journal."""
    ticks = _stream(n, seconds)
    plain = _fusion(n)
    t0 = time.perf_counter()
    for recs in ticks:
        for rec in recs:
            jr.apply(plain, rec)
    plain_s = time.perf_counter() - t0

    path = folder / f"bench{n}_{seconds:g}.journal"
    path.unlink(missing_ok=True)
    live = _fusion(n)
    j = jr.Journal(path, jr.header_for("bench", live))
    t0 = time.perf_counter()
    journal_s = 0.0  # time inside the journal calls only (the fusion's own cost is noisy on a shared machine)
    for recs in ticks:
        for rec in recs:
            t1 = time.perf_counter()
            j.append(rec)
            journal_s += time.perf_counter() - t1
            jr.apply(live, rec)
        t1 = time.perf_counter()
        j.flush()
        journal_s += time.perf_counter() - t1
    j.close()
    journalled_s = time.perf_counter() - t0

    rebuilt = _fusion(n)
    again = jr.Journal(path, jr.header_for("bench", rebuilt), replay=lambda r: jr.apply(rebuilt, r))
    again.close()
    gaps = [math.dist(rebuilt.pose(r)[0][:2], live.pose(r)[0][:2])  # type: ignore[index]
            for r in range(n) if live.pose(r) is not None]
    records = sum(len(t) for t in ticks)
    size = path.stat().st_size
    path.unlink()
    return {"robots": n, "sim_seconds": seconds, "records": records, "measurements": j.counters["records"],
            "file_mb": size / 2**20, "live_plain_s": plain_s, "live_journalled_s": journalled_s,
            "journal_s": journal_s, "journal_share_of_live": journal_s / journalled_s,
            "journal_core_share": journal_s / seconds, "fsyncs": j.counters["fsyncs"],
            "fsync_ms_mean": 1e3 * j.sync_s_total / max(j.counters["fsyncs"], 1),
            "rebuild_s": again.replay_s, "rebuild_us_per_record": 1e6 * again.replay_s / records,
            "rebuilt_max_gap_m": max(gaps), "rebuilt_same_decisions": rebuilt.counters == live.counters}


def fsync_batches(folder: Path, records: int = 4096) -> list[dict[str, float]]:
    """Write cost per record (one flush per record, as the server does per drain)
    for several fsync batch sizes."""
    rec = jr.Odometry(robot_id=1, stamp_ns=123, x_m=1.0, y_m=2.0, yaw_rad=0.3, distance_m=4.0)
    out = []
    for every, background in ((1, False), (16, False), (64, False), (256, False), (10**9, False), (64, True)):
        path = folder / "fsync.journal"
        path.unlink(missing_ok=True)
        j = jr.Journal(path, jr.header_for("bench", _fusion(2)), sync_every=every, sync_interval_s=1e9,
                       background_sync=background)
        fsyncs0, sync0 = j.counters["fsyncs"], j.sync_s_total
        t0 = time.perf_counter()
        for _ in range(records):
            j.append(rec)
            j.flush()
        wall = time.perf_counter() - t0  # what the server's loop spends (fsync included unless in the background)
        j.close()
        n_sync = j.counters["fsyncs"] - fsyncs0
        out.append({"sync_every": every if every < 10**9 else 0, "background": background,
                    "us_per_record": 1e6 * wall / records, "fsyncs": n_sync,
                    "fsync_ms_mean": 1e3 * (j.sync_s_total - sync0) / max(n_sync, 1)})
        path.unlink()
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, nargs="+", default=[60.0, 300.0, 600.0])
    p.add_argument("--robots", type=int, nargs="+", default=[4, 16])
    p.add_argument("--dir", type=Path, default=None, help="where to write the journals (default: a temp folder "
                   "under runs/, the disk run folders live on)")
    p.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "journal.json")
    a = p.parse_args()
    base = a.dir or ROOT / "runs"
    base.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=base, prefix="bench-journal-") as tmp:
        folder = Path(tmp)
        batches = fsync_batches(folder)
        rows = [rebuild(n, s, folder) for n in a.robots for s in a.seconds if n <= 4 or s <= min(a.seconds)]
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps({"bench": "journal", "machine": {"cpus": os.cpu_count(),
                                                                 "python": platform.python_version(),
                                                                 "load_average_1_5_15": os.getloadavg()},
                                 "fsync_batches": batches, "rebuild": rows,
                                 "targets": {"restart resumes corrections": "<= 3 s"}}, indent=2))
    t = Table(title="journal write cost per record vs fsync batch (one flush per record)")
    for c in ("fsync every", "thread", "loop us/record", "fsyncs", "ms/fsync"):
        t.add_column(c)
    for b in batches:
        t.add_row(str(b["sync_every"] or "never"), "background" if b["background"] else "loop",
                  f"{b['us_per_record']:.1f}", str(b["fsyncs"]), f"{b['fsync_ms_mean']:.2f}")
    Console().print(t)
    t = Table(title="rebuild from the journal (synthetic, 30 Hz ticks)")
    for c in ("robots", "sim s", "records", "MB", "journal core share", "rebuild s", "us/record", "max gap m"):
        t.add_column(c)
    for r in rows:
        t.add_row(str(r["robots"]), f"{r['sim_seconds']:g}", str(r["records"]), f"{r['file_mb']:.1f}",
                  f"{100 * r['journal_core_share']:.2f} %", f"{r['rebuild_s']:.2f}",  # type: ignore[operator]
                  f"{r['rebuild_us_per_record']:.0f}", f"{r['rebuilt_max_gap_m']:.1e}")
    Console().print(t)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
