"""Camera throughput: frames/s delivered over Zenoh by the world process vs raw
``getCameraImage`` calls on the same scene and core count.

For each resolution, robot count and render-worker count K the world runs in
realtime mode with ``clock.speed`` set so that the cameras ask for 1.5x the frames
the render cores can produce (saturated renderers, a world that does not spin);
a subscriber counts the frames that arrive.  The raw reference
runs K processes that each call :meth:`tagswarm.world.render.Renderer.render` in a loop on
the same scene (what K cores can render with no simulation, no encoding and no
transport).  K = 0 means rendering inside the world process (compared with one
raw process).  Writes ``bench/results/render.json``.

Usage: python bench/render.py [--seconds 8] [--quick]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import platform
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import psutil  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from tagswarm.protocol import codec  # noqa: E402
from tagswarm.protocol import messages as m  # noqa: E402
from tagswarm.protocol.keys import Keys  # noqa: E402
from tagswarm.protocol.scenario import load_scenario  # noqa: E402
from tests.harness import client, endpoint, process, world_argv  # noqa: E402


def overrides(width: int, height: int, robots: int) -> list[str]:
    return [f"robots.count={robots}", 'robots.placement="ring"', "missions=[]", "robots.ring_radius_m=2.0",
            "clock.tick_hz=10", "encoders.rate_hz=10",
            f'robot.cameras=[{{name="front", width={width}, height={height}, rate_hz=10}}]', "duration_s=100000"]


def _raw_worker(args: tuple[list[str], float, float]) -> int:
    ov, warmup, seconds = args
    from tagswarm.protocol.geometry import se2_matrix
    from tagswarm.protocol.layout import start_poses
    from tagswarm.world._pybullet import pb
    from tagswarm.world.render import Renderer

    s = load_scenario("paper", ov)
    poses = start_poses(s)
    with Renderer(s) as r:
        for rid, (x, y, yaw) in zip(s.robot_ids, poses, strict=True):
            r.set_pose(rid, (x, y, 0.0), pb.getQuaternionFromEuler((0, 0, yaw)))
        bases = [se2_matrix(*p) for p in poses]
        cam = s.robot.cameras[0]
        n, t0 = 0, time.monotonic()
        while time.monotonic() - t0 < warmup + seconds:
            if time.monotonic() - t0 >= warmup:
                n += 1
            r.render(n % len(bases), cam, bases[n % len(bases)])
        return n


def raw_rate(ov: list[str], procs: int, seconds: float) -> float:
    with mp.get_context("spawn").Pool(procs) as pool:
        counts = pool.map(_raw_worker, [(ov, 1.0, seconds)] * procs)
    return sum(counts) / seconds


def delivered_rate(ov: list[str], workers: int, speed: float, seconds: float, log: Path) -> dict[str, float]:
    ep, run = endpoint(), f"bench{os.getpid()}"
    keys = Keys(run)
    argv = world_argv(ep, run, *ov, f"render.workers={workers}", f"clock.speed={speed}")
    with process(argv, log) as world, client(ep) as bus:
        images = bus.subscribe(keys.images(), capacity=1_000_000)
        ticks = bus.subscribe(keys.tick(), newest_only=True)
        assert bus.wait_for(lambda: len(images) > 0, 60), "no frames arrived"
        time.sleep(2.0)  # warm-up: workers joined, caches hot
        procs = {"world": psutil.Process(world.pid), "bench_subscriber": psutil.Process()}
        for i, child in enumerate(procs["world"].children()):
            procs[f"render_worker_{i}"] = child
        cpu0 = {k: sum(p.cpu_times()[:2]) for k, p in procs.items()}
        images.drain()
        first = ticks.drain()
        t0 = time.monotonic()
        time.sleep(seconds)
        got = images.drain()
        dt = time.monotonic() - t0
        last = ticks.drain()
        cpu = {k: round((sum(p.cpu_times()[:2]) - cpu0[k]) / dt, 3) for k, p in procs.items()}
    step0 = codec.decode(m.Tick, first[-1].value).step if first else 0
    step1 = codec.decode(m.Tick, last[-1].value).step if last else step0
    return {"delivered_fps": len(got) / dt, "sim_ticks_per_s": (step1 - step0) / dt, "cpu_cores": cpu}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, default=8.0)
    p.add_argument("--quick", action="store_true", help="only 320x240 with 4 robots")
    p.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "render.json")
    a = p.parse_args()
    sizes = [(320, 240)] if a.quick else [(320, 240), (640, 480)]
    counts = [4] if a.quick else [4, 16]
    rows = []
    logdir = Path(os.environ.get("TMPDIR", "/tmp")) / "tagswarm-bench"
    logdir.mkdir(exist_ok=True)
    for w, h in sizes:
        for n in counts:
            ov = overrides(w, h, n)
            raw = {k: raw_rate(ov, k, a.seconds) for k in (1, 2)}
            for workers in (0, 1, 2):
                cores = max(workers, 1)
                # realtime, paced so the cameras ask for 1.5x what `cores` can render: the renderers
                # are saturated while the world itself does not spin
                speed = 1.5 * raw[cores] / (n * 10.0)
                d = delivered_rate(ov, workers, speed, a.seconds, logdir / f"world_{w}_{n}_{workers}.log")
                render_cpu = sum(v for k, v in d["cpu_cores"].items()
                                 if k.startswith("render_worker") or (workers == 0 and k == "world"))
                rows.append({"width": w, "height": h, "robots": n, "render_workers": workers,
                             "raw_fps_same_cores": raw[cores], **d,
                             "delivered_over_raw": d["delivered_fps"] / raw[cores],
                             # frames per CPU-second spent in the renderers vs raw frames per core-second
                             "render_cpu_efficiency": d["delivered_fps"] / max(render_cpu, 1e-9) / raw[1]})
                print(rows[-1], flush=True)
    by = {(r["width"], r["robots"], r["render_workers"]): r for r in rows}
    scaling = {f"{w}x{h}/{n}": by[(w, n, 2)]["delivered_fps"] / by[(w, n, 1)]["delivered_fps"]
               for w, h in sizes for n in counts}
    result = {"bench": "render", "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                                             "platform": platform.platform()},
              "seconds_per_point": a.seconds, "rows": rows, "two_over_one_worker": scaling,
              "targets": {"two_over_one_worker": ">= 1.8", "delivered_over_raw": ">= 0.8"}}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(result, indent=2))
    t = Table(title="camera frames/s: delivered over Zenoh vs raw getCameraImage")
    for col in ("res", "robots", "workers", "raw (same cores)", "delivered", "ratio", "sim ticks/s"):
        t.add_column(col)
    for r in rows:
        t.add_row(f"{r['width']}x{r['height']}", str(r["robots"]), str(r["render_workers"]),
                  f"{r['raw_fps_same_cores']:.0f}", f"{r['delivered_fps']:.0f}", f"{r['delivered_over_raw']:.2f}",
                  f"{r['sim_ticks_per_s']:.1f}")
    Console().print(t)
    print("2 workers / 1 worker:", {k: round(v, 2) for k, v in scaling.items()})
    print("wrote", a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
