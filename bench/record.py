"""Recording cost and size: ``tagswarm up`` (lockstep, paper scenario at 320x240) with
and without ``--record`` (wall time and CPU of the whole process tree), then the same
recording written again offline with every option (MB per simulated second, CPU per
message), and how fast ``tagswarm up --replay`` runs it.  Writes
``bench/results/record.json``.

Usage: python bench/record.py [--seconds 20] [--robots 3] [--repeat 2] [--floor]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from tagswarm.recording.mcapio import iter_raw, verify  # noqa: E402
from tagswarm.recording.record import McapRecording, RecordOptions  # noqa: E402

TAGSWARM = str(Path(sys.executable).parent / "tagswarm")


def _children_cpu() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)  # every reaped descendant (up waits for its children)
    return ru.ru_utime + ru.ru_stime


def up(args: list[str]) -> tuple[float, float]:
    """(wall s, CPU s of the whole process tree) of one ``tagswarm up`` run."""
    cpu0, t0 = _children_cpu(), time.perf_counter()
    res = subprocess.run([TAGSWARM, "up", "--no-live", "--no-report", *args], capture_output=True, text=True)
    if res.returncode != 0:
        raise SystemExit(res.stdout[-2000:] + res.stderr[-2000:])
    return time.perf_counter() - t0, _children_cpu() - cpu0


VARIANTS: dict[str, RecordOptions] = {
    "default (zstd, raw + Foxglove)": RecordOptions(),
    "raw only (--no-foxglove)": RecordOptions(foxglove=False),
    "no images (--no-images)": RecordOptions(images=False),
    "no images, raw only": RecordOptions(images=False, foxglove=False),
    "--image-scale 0.5": RecordOptions(image_scale=0.5),
    "lz4": RecordOptions(compression="lz4"),
    "uncompressed": RecordOptions(compression="none"),
}


def sizes(src: Path, sim_s: float, folder: Path) -> list[dict[str, object]]:
    msgs = [(r.key, r.data) for r in iter_raw(src, lambda _: True)]
    out = []
    for name, opt in VARIANTS.items():
        path = folder / "variant.mcap"
        cpu0 = time.process_time()
        rec = McapRecording(path, opt, run="bench", keyexpr="bench")
        for key, data in msgs:
            rec.add(key, data, 0)
        rec.close()
        cpu = time.process_time() - cpu0
        verify(path)
        out.append({"variant": name, "mb": path.stat().st_size / 1e6, "mb_per_sim_s": path.stat().st_size / 1e6 / sim_s,
                    "cpu_us_per_raw_msg": 1e6 * cpu / len(msgs), "cpu_share_of_core_at_rtf1": cpu / sim_s})
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--robots", type=int, default=3)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--floor", action="store_true", help="also measure sizes with the textured floor in view")
    a = ap.parse_args()
    console = Console()
    base = ["--clock", "lockstep", "--seed", "3", "--duration", str(a.seconds), "--robots", str(a.robots)]
    result: dict[str, object] = {"machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
                                 "seconds": a.seconds, "robots": a.robots, "resolution": "320x240"}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        runs: dict[str, list[tuple[float, float]]] = {"plain": [], "record": []}
        for i in range(a.repeat):  # alternate, so load drifts hit both alike
            runs["plain"].append(up([*base, "--out", str(folder / f"p{i}")]))
            runs["record"].append(up([*base, "--out", str(folder / f"r{i}"), "--record", str(folder / "rec.mcap")]))
        rec = folder / "rec.mcap"
        v = verify(rec)
        sim_s = (v.end_ns - v.start_ns) / 1e9
        replay = [up(["--replay", str(rec), "--out", str(folder / f"replay{i}")]) for i in range(a.repeat)]
        result["up"] = {k: {"wall_s": [w for w, _ in r], "cpu_s": [c for _, c in r]} for k, r in runs.items()}
        result["up_replay"] = {"wall_s": [w for w, _ in replay], "cpu_s": [c for _, c in replay]}
        best = {k: min(w for w, _ in r) for k, r in runs.items()}
        cpu = {k: min(c for _, c in r) for k, r in runs.items()}
        result["overhead"] = {"wall_pct_best_of": 100 * (best["record"] / best["plain"] - 1),
                              "cpu_s_per_sim_s": (cpu["record"] - cpu["plain"]) / sim_s}
        result["recording"] = {"file_mb": rec.stat().st_size / 1e6, "messages": v.messages, "sim_s": sim_s,
                               "per_type": v.metadata.get("tagswarm.stats", {})}
        result["variants"] = sizes(rec, sim_s, folder)
        if a.floor:
            frec = folder / "floor.mcap"
            up([*base, "--out", str(folder / "floor"), "--record", str(frec), "--set", "render.floor=true"])
            fv = verify(frec)
            result["variants_floor"] = sizes(frec, (fv.end_ns - fv.start_ns) / 1e9, folder)
    out = ROOT / "bench" / "results" / "record.json"
    out.write_text(json.dumps(result, indent=2))
    t = Table(title=f"recording {a.robots} robots x {a.seconds:g} s lockstep at 320x240")
    for col in ("variant", "MB", "MB / sim s", "µs CPU / msg"):
        t.add_column(col)
    for key in ("variants", "variants_floor"):
        for row in result.get(key, []):  # type: ignore[union-attr]
            t.add_row(("floor: " if key == "variants_floor" else "") + str(row["variant"]), f"{row['mb']:.2f}",
                      f"{row['mb_per_sim_s']:.3f}", f"{row['cpu_us_per_raw_msg']:.0f}")
    console.print(t)
    console.print(f"up wall s plain {result['up']['plain']['wall_s']} vs --record {result['up']['record']['wall_s']}; "  # type: ignore[index]
                  f"overhead {result['overhead']}; replay wall s {result['up_replay']['wall_s']}")  # type: ignore[index]
    console.print(f"written {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
