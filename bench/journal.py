"""Server journal cost: what journalling adds to the live server, what fsync
batches cost, and how long a restarted server takes to rebuild its graph from a
journal of N records (synthetic swarm as bench/fusion.py, at the live system's
rates: odometry and one fusion update per 30 Hz tick, observations from 10 Hz
cameras), without checkpoints (the whole journal is replayed) and with one every
``--checkpoint`` simulated seconds (only what follows the last one is replayed).
For checkpoints it also reports their size, what writing one (snapshot) and
restoring the live fusion from it cost the live loop, and how far the fusion that
went through them drifts from one that never did.  Writes ``bench/results/journal.json``.

Usage: python bench/journal.py [--seconds 60 300 600] [--robots 4 16] [--checkpoint 10] [--dir DIR]
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

from tagswarm.server import journal as jr  # noqa: E402
from tagswarm.server.fusion import Fusion, FusionParams  # noqa: E402
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


def _gap(a: Fusion, b: Fusion, n: int) -> float:
    """Largest distance (m) between the two fusions' current poses of any robot localised in both."""
    return max((math.dist(pa[0][:2], pb[0][:2]) for r in range(n)
                if (pa := a.pose(r)) is not None and (pb := b.pose(r)) is not None), default=0.0)


def rebuild(n: int, seconds: float, folder: Path, checkpoint_s: float,
            ticks: list[list[jr.Odometry | jr.Observation | jr.Advance]], plain: Fusion,
            plain_s: float) -> dict[str, object]:
    """A journalled live run (checkpoints every ``checkpoint_s``, 0 = none, written and
    applied as the server does), then a rebuild from its journal.  ``plain`` is the
    never-journalled fusion of the same ``ticks`` (``plain_s`` its run time)."""
    path = folder / f"bench{n}_{seconds:g}_{checkpoint_s:g}.journal"
    path.unlink(missing_ok=True)
    live = _fusion(n)
    j = jr.Journal(path, jr.header_for("bench", live))
    t0 = time.perf_counter()
    journal_s = 0.0  # time inside the journal calls only (the fusion's own cost is noisy on a shared machine)
    snapshot_s, restore_s, sizes, drift = [], [], [], 0.0
    # one tick after each multiple of checkpoint_s, so that the journal ends (at a multiple) just before
    # the next one is due: the rebuild replays a whole interval, its worst case
    next_ns = int(checkpoint_s * 1e9) + round(1e9 / TICK_HZ)
    replay_plain = _fusion(n)  # plain, replayed alongside to compare at every update
    for recs in ticks:
        for rec in recs:
            t1 = time.perf_counter()
            j.append(rec)
            journal_s += time.perf_counter() - t1
            jr.apply(live, rec)
        t1 = time.perf_counter()
        j.flush()
        journal_s += time.perf_counter() - t1
        if checkpoint_s and live.watermark_ns >= next_ns:
            t1 = time.perf_counter()
            cp = jr.make_checkpoint(j, live, {}, {})
            j.append(cp)
            j.flush()
            t2 = time.perf_counter()
            jr.apply(live, cp)
            t3 = time.perf_counter()
            snapshot_s.append(t2 - t1)
            restore_s.append(t3 - t2)
            sizes.append(len(cp.fusion))
            next_ns += int(checkpoint_s * 1e9)
        if checkpoint_s:
            t1 = time.perf_counter()
            for rec in recs:
                jr.apply(replay_plain, rec)
            drift = max(drift, _gap(live, replay_plain, n))
            t0 += time.perf_counter() - t1  # not part of the live run
    j.close()
    journalled_s = time.perf_counter() - t0

    rebuilt = _fusion(n)
    again = jr.Journal(path, jr.header_for("bench", rebuilt), replay=lambda r: jr.apply(rebuilt, r))
    again.close()
    records = sum(len(t) for t in ticks)
    size = path.stat().st_size
    path.unlink()
    Path(f"{path}.index").unlink(missing_ok=True)
    return {"robots": n, "sim_seconds": seconds, "checkpoint_s": checkpoint_s, "records": records,
            "measurements": j.counters["records"], "file_mb": size / 2**20, "live_plain_s": plain_s,
            "live_journalled_s": journalled_s, "journal_s": journal_s,
            "journal_share_of_live": journal_s / journalled_s, "journal_core_share": journal_s / seconds,
            "fsyncs": j.counters["fsyncs"], "fsync_ms_mean": 1e3 * j.sync_s_total / max(j.counters["fsyncs"], 1),
            "checkpoints": len(sizes), "checkpoint_kb_mean": sum(sizes) / max(len(sizes), 1) / 1024,
            "checkpoint_kb_max": max(sizes, default=0) / 1024,
            "snapshot_ms_mean": 1e3 * sum(snapshot_s) / max(len(sizes), 1),
            "snapshot_ms_max": 1e3 * max(snapshot_s, default=0.0),
            "restore_ms_mean": 1e3 * sum(restore_s) / max(len(sizes), 1),
            "restore_ms_max": 1e3 * max(restore_s, default=0.0),
            "replayed": again.counters["replayed"], "replay_skipped": again.counters["replay_skipped"],
            "rebuild_s": again.replay_s, "rebuild_us_per_replayed_record": 1e6 * again.replay_s / max(
                again.counters["replayed"], 1),
            "rebuilt_max_gap_m": _gap(rebuilt, live, n), "rebuilt_same_decisions": rebuilt.counters == live.counters,
            "checkpointed_vs_never_max_gap_m": drift if checkpoint_s else 0.0,
            "checkpointed_vs_never_same_decisions": live.counters == plain.counters}


def rebuilds(n: int, seconds: float, folder: Path, checkpoint_s: float) -> list[dict[str, object]]:
    """Without and with checkpoints, on the same synthetic stream."""
    ticks = _stream(n, seconds)
    plain = _fusion(n)
    t0 = time.perf_counter()
    for recs in ticks:
        for rec in recs:
            jr.apply(plain, rec)
    plain_s = time.perf_counter() - t0
    return [rebuild(n, seconds, folder, every, ticks, plain, plain_s) for every in (0.0, checkpoint_s)]


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
    p.add_argument("--checkpoint", type=float, default=10.0, metavar="S",
                   help="simulated seconds between checkpoints (the server's default: 10)")
    p.add_argument("--dir", type=Path, default=None, help="where to write the journals (default: a temp folder "
                   "under runs/, the disk run folders live on)")
    p.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "journal.json")
    a = p.parse_args()
    base = a.dir or ROOT / "runs"
    base.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=base, prefix="bench-journal-") as tmp:
        folder = Path(tmp)
        batches = fsync_batches(folder)
        rows = [row for n in a.robots for s in a.seconds if n <= 4 or s <= min(a.seconds)
                for row in rebuilds(n, s, folder, a.checkpoint)]
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps({"bench": "journal", "machine": {"cpus": os.cpu_count(),
                                                                 "python": platform.python_version(),
                                                                 "load_average_1_5_15": os.getloadavg()},
                                 "fsync_batches": batches, "rebuild": rows,
                                 "targets": {"restart resumes corrections": "<= 3 s",
                                             "pose jump at a restart": "<= 0.10 m"}}, indent=2))
    t = Table(title="journal write cost per record vs fsync batch (one flush per record)")
    for c in ("fsync every", "thread", "loop us/record", "fsyncs", "ms/fsync"):
        t.add_column(c)
    for b in batches:
        t.add_row(str(b["sync_every"] or "never"), "background" if b["background"] else "loop",
                  f"{b['us_per_record']:.1f}", str(b["fsyncs"]), f"{b['fsync_ms_mean']:.2f}")
    Console(width=220).print(t)
    t = Table(title="rebuild from the journal (synthetic, 30 Hz ticks)")
    for c in ("robots", "sim s", "checkpoint s", "records", "MB", "journal core share", "replayed", "rebuild s",
              "ckpt KB", "ckpt write+restore ms", "gap to live m", "gap to never-checkpointed m"):
        t.add_column(c)
    for r in rows:
        t.add_row(str(r["robots"]), f"{r['sim_seconds']:g}", f"{r['checkpoint_s']:g}" if r["checkpoint_s"] else "off",
                  str(r["records"]), f"{r['file_mb']:.1f}",
                  f"{100 * r['journal_core_share']:.2f} %", str(r["replayed"]),  # type: ignore[operator]
                  f"{r['rebuild_s']:.2f}", f"{r['checkpoint_kb_mean']:.0f}",
                  f"{r['snapshot_ms_mean']:.0f}+{r['restore_ms_mean']:.0f}", f"{r['rebuilt_max_gap_m']:.1e}",
                  f"{r['checkpointed_vs_never_max_gap_m']:.1e}")
    Console(width=220).print(t)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
