"""Speed of the whole system in realtime mode: real-time factor, camera-frame
efficiency against bare ``getCameraImage``, image-to-correction latency and CPU
per process type.  Writes ``bench/results/speed.json``.

Each point is a real ``tagswarm up --clock realtime`` (world with K render
workers, server, one agent per robot, as OS processes).  A bench client joins
the run's Zenoh network and, after a warm-up, measures for ``--seconds``:

- RTF: simulated seconds (from the world's ticks) per wall second.
- frames: camera frames the agents processed (their status counters), per wall
  second, next to what the cameras asked for (robots x rate x RTF).
- latency: for every correction whose ``last_fix_ns`` is new for its robot, the
  wall time from the arrival of the image that produced the fix to the arrival of
  that correction (p50 / p95 / max).  The fix is an observation stamped
  ``last_fix_ns`` by or of that robot; the image is the earliest-arriving frame of
  that stamp from a robot that made such an observation (the bench hears the
  observations too).  ``latency_any_image_ms`` is the older, looser measure: from
  the first image of that stamp from *any* robot, which adds the spread of one
  tick's renders over the robots (up to a render per robot per worker) to the delay.
  The bench client and the agents sit on the same loopback, so this is what an
  agent sees.  The bench subscribes to every image for this; its own CPU is
  reported apart.
- CPU: cores used per process type (world, render workers, agents, server,
  ``up`` with its recorder), from psutil over the measurement window.

Efficiency (on by default, ``--no-saturate`` skips it): for each resolution, 8
robots with 2 render workers, the clock at real time and the cameras at one frame
per tick, at a rate that asks for 1.5x what 2 bare ``getCameraImage`` processes
render on this machine (measured right before, same scene, start poses and
resolution): frames processed by the agents per second over that bare rate.  That
is the share of the machine's rendering limit the full pipeline (render, send,
detect, estimate, fuse) delivers; its ceiling is render time over render + the
rest of the per-frame work, since all of it shares the same cores.

The camera model (lens remap, motion blur, noise) is measured apart, in one process
against the render it follows (bench/camera_cost.py; ``--camera-model-only``).

Headline (``--headline``, issue 18): the plain ``tagswarm up --robots N --clock realtime`` at 8 and 16
robots, ``--repeats`` runs each (medians), with the CPU per role (world, render workers, agents, server,
up + recorder, router), the frames the workers rendered, the agents' own per-frame account (status
counters ``cpu_frames_us`` and ``cpu_detect_pose_us``) and, with ``--budget-lockstep`` /
``--budget-speed``, the core-seconds per simulated second with every frame processed; to
``bench/results/speed_headline.json``.  ``--wait-load`` waits for a shared machine's load to drop.

Usage: python bench/speed.py [--seconds 10] [--quick] [--camera-model-only]
       python bench/speed.py --headline [--repeats 3] [--budget-lockstep] [--wait-load 4 120]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import numpy as np  # noqa: E402
import psutil  # noqa: E402
from camera_cost import camera_model_cost  # noqa: E402
from render import raw_rate  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from tagswarm.protocol import messages as m  # noqa: E402
from tagswarm.protocol.keys import Keys  # noqa: E402
from tagswarm.protocol.scenario import load_scenario  # noqa: E402
from tagswarm.runtime import streams  # noqa: E402
from tests.harness import client, endpoint  # noqa: E402

TAGSWARM = str(Path(sys.executable).parent / "tagswarm")
# the built-in paper.toml still says `[render] workers = 0` (from before the automatic default, -1)
PAPER_PINS_WORKERS = load_scenario("paper").render.workers != -1
RESOLUTIONS = {"320x240@10Hz": (320, 240, 10.0), "640x480@5Hz": (640, 480, 5.0)}


def camera_override(w: int, h: int, hz: float) -> str:
    return f'robot.cameras=[{{name="front", width={w}, height={h}, hfov_deg=60, rate_hz={hz}}}]'


def _kind(proc: psutil.Process) -> str:
    try:
        cmd = " ".join(proc.cmdline())
    except psutil.Error:
        return "gone"
    for name in ("render", "world", "agent", "server"):
        if f"tagswarm-{name}" in cmd or f"world.{name}" in cmd:
            return "render_worker" if name == "render" else name
    return "render_worker" if "render_worker" in cmd else "other"


def _cpu(procs: dict[int, psutil.Process]) -> dict[int, float]:
    out = {}
    for pid, p in procs.items():
        try:
            out[pid] = sum(p.cpu_times()[:2])
        except psutil.Error:
            out[pid] = float("nan")
    return out


def measure(robots: int, res: str, workers: int | None, seconds: float, warmup: float,
            camera_hz: float | None = None, log_dir: Path | None = None, headline: bool = False,
            latency: bool = True, extra: tuple[str, ...] = ()) -> dict[str, Any]:
    """One realtime run; returns RTF, frame rates, latency and CPU per process type.
    ``camera_hz``: cameras (and the world's clock) at this rate instead of the
    resolution's own, to ask for more frames than the machine can render.  ``headline``:
    exactly ``tagswarm up --robots N --clock realtime`` (the paper scenario's camera, the
    automatic ``render.workers``; ``res`` and ``workers`` are ignored).  ``latency=False``
    leaves the images alone (the bench client then costs the machine almost nothing)."""
    w, h, hz = RESOLUTIONS[res]
    tick: list[str] = []  # the scenario's clock (30 Hz)
    if camera_hz is not None:
        hz = camera_hz
        tick = ["--set", f"clock.tick_hz={max(30.0, hz)}"]
    ep, run = endpoint(), f"speed{os.getpid()}"
    keys = Keys(run)
    out = Path(tempfile.mkdtemp(prefix="tagswarm-speed-"))
    argv = [TAGSWARM, "up", "--clock", "realtime", "--listen", ep, "--run", run, "--out", str(out), "--no-live",
            "--no-report", "--robots", str(robots), "--duration", "100000"]
    argv += list(extra)
    if not headline:
        # the paper scenario (robot 0 holds, the others patrol) on an even grid for any robot count
        argv += ["--seed", "0", "--set", 'robots.placement="grid"', "--set", camera_override(w, h, hz), *tick]
        if workers is not None:
            argv += ["--set", f"render.workers={workers}"]
    if WAIT_LOAD[0] > 0:  # a shared machine: start when the others' load has dropped, or after WAIT_LOAD[1] s
        until = time.monotonic() + WAIT_LOAD[1]
        while os.getloadavg()[0] > WAIT_LOAD[0] and time.monotonic() < until:
            time.sleep(2.0)
    load_before = [round(x, 2) for x in os.getloadavg()]
    log = open((log_dir or out) / f"up_{robots}_{res}_{workers}{'_headline' if headline else ''}.log", "w")
    up = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        with client(ep) as bus:
            ticks = bus.subscribe(keys.tick(), capacity=1_000_000)
            images = bus.subscribe(keys.images() if latency else keys.tick(), capacity=1_000_000)
            corr = bus.subscribe(keys.correction(), capacity=1_000_000)
            obs = bus.subscribe(keys.observation() if latency else keys.tick(), capacity=1_000_000)
            status = bus.subscribe(keys.robot_status(), capacity=1_000_000)
            wstatus = bus.subscribe(keys.world_status(), capacity=1_000_000)
            if not bus.wait_for(lambda: len(ticks) > 0 or up.poll() is not None, 120) or up.poll() is not None:
                raise RuntimeError(f"no ticks from {argv}; see {log.name}")
            deadline = time.monotonic() + 120
            # warm-up: every agent has reported and the world has run `warmup` wall seconds
            seen: set[int] = set()
            t_first = time.monotonic()
            while time.monotonic() < deadline and (len(seen) < robots or time.monotonic() - t_first < warmup):
                bus.wait(0.2)
                for _, st in streams.RejectCounter().decoded(status.drain(), m.AgentStatus):
                    seen.add(st.robot_id)
            for box in (ticks, images, corr, obs, status, wstatus):
                box.drain()
            procs = {p.pid: p for p in [psutil.Process(up.pid), *psutil.Process(up.pid).children(recursive=True)]}
            kinds = {pid: "up_and_recorder" if pid == up.pid else _kind(p) for pid, p in procs.items()}
            me = psutil.Process()
            cpu0, my0 = _cpu(procs), sum(me.cpu_times()[:2])
            t0 = time.monotonic()
            first_image: dict[int, float] = {}
            robot_image: dict[tuple[int, int], float] = {}  # (stamp_ns, robot) -> first arrival
            fixers: dict[int, list[tuple[int, int]]] = defaultdict(list)  # stamp_ns -> (observer, target robot)
            any_latencies: list[float] = []
            last_fix: dict[int, int] = {}
            latencies: list[float] = []
            frames: dict[int, list[tuple[float, int]]] = defaultdict(list)
            rendered: dict[str, list[tuple[int, int]]] = defaultdict(list)
            agent_cpu: dict[int, list[dict[str, int]]] = {}  # first and last status counters in the window
            sim: list[int] = []
            n_images = 0
            rc = streams.RejectCounter()
            while (now := time.monotonic()) - t0 < seconds:
                bus.wait(0.05)
                now = time.monotonic()
                for _, tk in rc.decoded(ticks.drain(), m.Tick):
                    sim.append(tk.stamp_ns)
                if latency:
                    for _, im in rc.decoded(images.drain(), m.CameraImage):
                        first_image.setdefault(im.stamp_ns, now)
                        robot_image.setdefault((im.stamp_ns, im.robot_id), now)
                        n_images += 1
                    for _, ob in rc.decoded(obs.drain(), m.RelativeObservation):
                        fixers[ob.stamp_ns].append((ob.robot_id, ob.target_id if ob.target_kind == "robot" else -1))
                else:
                    images.drain()
                    obs.drain()
                for _, c in rc.decoded(corr.drain(), m.Correction):
                    if c.localised and c.last_fix_ns > last_fix.get(c.robot_id, -1):
                        if c.robot_id in last_fix and c.last_fix_ns in first_image:
                            any_latencies.append(now - first_image[c.last_fix_ns])
                            made = [robot_image[(c.last_fix_ns, o)] for o, t in fixers.get(c.last_fix_ns, ())
                                    if c.robot_id in (o, t) and (c.last_fix_ns, o) in robot_image]
                            if made:
                                latencies.append(now - min(made))
                        last_fix[c.robot_id] = c.last_fix_ns
                for _, st in rc.decoded(status.drain(), m.AgentStatus):
                    frames[st.robot_id].append((now, st.counters.get("frames_processed", 0)))
                    agent_cpu.setdefault(st.robot_id, [st.counters, st.counters])[1] = st.counters
                for _, st in rc.decoded(wstatus.drain(), m.AgentStatus):
                    # the world's own renders (in-process) or each render worker's, by simulation time
                    if "frames_rendered" in st.counters:
                        rendered[st.role].append((st.stamp_ns, st.counters["frames_rendered"]))
            wall = time.monotonic() - t0
            cpu1, my1 = _cpu(procs), sum(me.cpu_times()[:2])
    finally:
        up.send_signal(signal.SIGINT)
        try:
            up.wait(60)
        except subprocess.TimeoutExpired:
            os.killpg(up.pid, signal.SIGKILL)
            up.wait()
        log.close()
    cpu: dict[str, float] = defaultdict(float)
    count: dict[str, int] = defaultdict(int)
    for pid in procs:
        kind = kinds[pid]
        if np.isfinite(cpu1[pid] - cpu0[pid]):
            cpu[kind] += (cpu1[pid] - cpu0[pid]) / wall
            count[kind] += 1
    processed = 0.0
    for series in frames.values():
        if len(series) >= 2 and series[-1][0] > series[0][0]:
            processed += (series[-1][1] - series[0][1]) / (series[-1][0] - series[0][0])
    rtf = (sim[-1] - sim[0]) / 1e9 / wall if len(sim) >= 2 else 0.0
    rendered_per_sim_s = 0.0
    for series in rendered.values():
        if len(series) >= 2 and series[-1][0] > series[0][0]:
            rendered_per_sim_s += (series[-1][1] - series[0][1]) / ((series[-1][0] - series[0][0]) / 1e9)
    asked = robots * hz * rtf
    lat = np.array(latencies) * 1e3
    lat_any = np.array(any_latencies) * 1e3
    sim_s = rtf * wall

    def delta(name: str) -> int:
        return sum(last.get(name, 0) - first.get(name, 0) for first, last in agent_cpu.values())

    n_frames, frames_us, dp_us = delta("frames_processed"), delta("cpu_frames_us"), delta("cpu_detect_pose_us")
    agent_s = cpu.get("agent", 0.0) * wall
    return {
        "robots": robots, "resolution": res, "render_workers": count.get("render_worker", 0), "camera_hz": hz,
        "command": " ".join(["tagswarm", *argv[1:]]), "load_avg_before": load_before,
        "wall_s": round(wall, 2), "rtf": round(rtf, 3),
        "frames_asked_per_s": round(asked, 1), "images_delivered_per_s": round(n_images / wall, 1),
        "frames_rendered_per_s": round(rendered_per_sim_s * rtf, 1),
        "frames_processed_per_s": round(processed, 1),
        "processed_share": round(processed / asked, 3) if asked else None,
        "cpu_core_s_per_sim_s": {k: round(v * wall / sim_s, 3) for k, v in sorted(cpu.items())} if sim_s else {},
        # the agents' own account (status counters cpu_frames_us, cpu_detect_pose_us) over the window: per
        # frame, detect + pose, all the frame handling, and the whole agent process (psutil) per frame
        "agent_ms_per_frame": {
            "frames": n_frames,
            "detect_pose": round(dp_us / n_frames / 1e3, 3) if n_frames and dp_us else None,
            "frame_handling": round(frames_us / n_frames / 1e3, 3) if n_frames and frames_us else None,
            "whole_process": round(agent_s / n_frames * 1e3, 3) if n_frames else None,
            "handling_over_detect_pose": round(frames_us / dp_us, 3) if dp_us else None,
            "process_over_detect_pose": round(agent_s * 1e6 / dp_us, 3) if dp_us else None},
        "latency_ms": {"n": int(lat.size), "p50": float(np.percentile(lat, 50)) if lat.size else None,
                       "p95": float(np.percentile(lat, 95)) if lat.size else None,
                       "max": float(lat.max()) if lat.size else None},
        "latency_any_image_ms": {"n": int(lat_any.size),
                                 "p50": float(np.percentile(lat_any, 50)) if lat_any.size else None,
                                 "p95": float(np.percentile(lat_any, 95)) if lat_any.size else None},
        "cpu_cores": {k: round(v, 3) for k, v in sorted(cpu.items())},
        "processes": dict(count), "bench_client_cpu_cores": round((my1 - my0) / wall, 3),
    }


WAIT_LOAD = [0.0, 0.0]  # --wait-load: 1-minute load average to wait for before each run, and for how long at most
ROLES = ("world", "render_worker", "agent", "server", "up_and_recorder", "router")


def headline(robots: list[int], repeats: int, seconds: float, warmup: float, log_dir: Path,
             extra: tuple[str, ...] = (), speed: float = 1.0, lockstep: bool = False) -> list[dict[str, Any]]:
    """The goal's command, ``tagswarm up --robots N --clock realtime`` and nothing else, ``repeats``
    times per robot count: the median of each figure and the CPU budget per role (cores over the
    window, median over the repeats).  ``tagswarm up`` runs no Zenoh router (its processes are peers
    linked directly), so the router's share is 0; the Zenoh I/O is in each process's own figure.
    Latency only at 8 robots or fewer: there the bench client's own work on every image is small.
    ``speed`` < 1 (``--set clock.speed``) measures the budget where the machine has room for every
    frame: core-seconds per simulated second is then what real time needs."""
    out = []
    if speed != 1.0:
        extra = (*extra, "--set", f"clock.speed={speed}")
    for n in robots:
        runs = [measure(n, "320x240@10Hz", None, seconds, warmup, log_dir=log_dir, headline=True,
                        latency=n <= 8 and speed == 1.0 and not lockstep, extra=extra) for _ in range(repeats)]

        def med(get: Any, runs: list[dict[str, Any]] = runs) -> Any:
            vals = [v for v in (get(r) for r in runs) if v is not None]
            return round(float(np.median(vals)), 3) if vals else None

        row: dict[str, Any] = {
            "robots": n, "resolution": "320x240@10Hz", "headline": True, "repeats": repeats,
            "command": " ".join(["tagswarm up --robots", str(n), "--clock realtime", *extra]),
            "clock_speed": speed, "lockstep": lockstep,
            "render_workers": runs[0]["render_workers"],
            "rtf": med(lambda r: r["rtf"]), "rtf_all": [r["rtf"] for r in runs],
            "frames_asked_per_s": med(lambda r: r["frames_asked_per_s"]),
            "frames_rendered_per_s": med(lambda r: r["frames_rendered_per_s"]),
            "frames_processed_per_s": med(lambda r: r["frames_processed_per_s"]),
            "processed_share": med(lambda r: r["processed_share"]),
            "latency_ms": {k: med(lambda r, k=k: r["latency_ms"][k]) for k in ("p50", "p95", "max")},
            "latency_any_image_ms": {k: med(lambda r, k=k: r["latency_any_image_ms"][k]) for k in ("p50", "p95")},
            "agent_ms_per_frame": {k: med(lambda r, k=k: r["agent_ms_per_frame"][k])
                                   for k in runs[0]["agent_ms_per_frame"]},
            "cpu_cores": {k: med(lambda r, k=k: r["cpu_cores"].get(k, 0.0)) for k in ROLES},
            "cpu_core_s_per_sim_s": {k: med(lambda r, k=k: r["cpu_core_s_per_sim_s"].get(k, 0.0)) for k in ROLES},
            "bench_client_cpu_cores": med(lambda r: r["bench_client_cpu_cores"]),
            "load_avg_before": [r["load_avg_before"] for r in runs], "runs": runs,
        }
        row["cpu_cores"]["total"] = round(sum(v or 0.0 for v in row["cpu_cores"].values()), 3)
        row["cpu_core_s_per_sim_s"]["total"] = round(sum(v or 0.0 for v in row["cpu_core_s_per_sim_s"].values()), 3)
        row["per_agent_cores"] = round((row["cpu_cores"]["agent"] or 0.0) / n, 4)
        out.append(row)
        Console().print({k: v for k, v in row.items() if k != "runs"})
    return out


def print_budget(rows: list[dict[str, Any]]) -> None:
    """The CPU budget per role of the headline rows (cores, median over the repeats)."""
    t = Table(title="tagswarm up --robots N --clock realtime: CPU per role (cores; at clock.speed < 1 "
                    "core-seconds per simulated second)")
    for col in ("robots", "speed", "RTF", "frames processed / asked", "latency p50/p95 ms", *ROLES, "total"):
        t.add_column(col)
    for r in rows:
        budget = r["clock_speed"] != 1.0 or r["lockstep"]
        c, lat = r["cpu_core_s_per_sim_s"] if budget else r["cpu_cores"], r["latency_ms"]
        t.add_row(str(r["robots"]), "lockstep" if r["lockstep"] else f"{r['clock_speed']:g}", f"{r['rtf']:.2f}",
                  f"{r['frames_processed_per_s']:.0f} / {r['frames_asked_per_s']:.0f}",
                  "-" if lat["p50"] is None else f"{lat['p50']:.0f} / {lat['p95']:.0f}",
                  *(f"{c[k] or 0:.2f}" for k in ROLES), f"{c['total']:.2f}")
    Console().print(t)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, default=10.0, help="measurement window per point (wall)")
    p.add_argument("--warmup", type=float, default=3.0)
    p.add_argument("--robots", type=int, nargs="+", default=[2, 4, 8, 16])
    p.add_argument("--quick", action="store_true",
                   help="4 and 8 robots at 320x240 only, one render worker, 6 s windows")
    p.add_argument("--no-saturate", action="store_true", help="skip the efficiency (saturated) points")
    p.add_argument("--camera-model-only", action="store_true",
                   help="only the camera model's cost per frame against the render (bench/camera_cost.py), to "
                        "bench/results/camera_model.json")
    p.add_argument("--headline", action="store_true",
                   help="only the headline: the plain `tagswarm up --robots N --clock realtime` (N from --robots, "
                        "default 8 16) --repeats times each, with the CPU budget per role, to "
                        "bench/results/speed_headline.json")
    p.add_argument("--repeats", type=int, default=3, help="runs per headline point (medians are reported)")
    p.add_argument("--budget-speed", type=float, default=0.5,
                   help="headline: also run each point at this clock.speed, where every frame fits, for the CPU "
                        "budget in core-seconds per simulated second (0: skip)")
    p.add_argument("--budget-lockstep", action="store_true",
                   help="headline: also run each point in lockstep (every frame processed however loaded the "
                        "machine is) for the CPU budget in core-seconds per simulated second")
    p.add_argument("--wait-load", type=float, nargs=2, default=[0.0, 0.0], metavar=("LOAD", "SECONDS"),
                   help="before each run wait until the 1-minute load average is below LOAD, at most SECONDS")
    p.add_argument("--as-configured", action="store_true",
                   help="headline: the command exactly, even while paper.toml pins render.workers = 0")
    p.add_argument("--out", type=Path, default=None,
                   help="JSON to write (default bench/results/speed.json, speed_quick.json with --quick)")
    a = p.parse_args()
    if a.camera_model_only:
        return camera_model_main(a.out or ROOT / "bench" / "results" / "camera_model.json")
    WAIT_LOAD[:] = a.wait_load
    if a.headline:
        return headline_main(a)
    if a.out is None:
        a.out = ROOT / "bench" / "results" / ("speed_quick.json" if a.quick else "speed.json")
    resolutions = list(RESOLUTIONS)
    if a.quick:
        a.robots, a.seconds, resolutions = [4, 8], 6.0, ["320x240@10Hz"]
    workers_list = (1,) if a.quick else (1, 2)
    console = Console()
    log_dir = Path(tempfile.mkdtemp(prefix="tagswarm-speed-logs-"))
    rows = []
    for res in resolutions:
        for n in a.robots:
            for workers in workers_list:
                rows.append(measure(n, res, workers, a.seconds, a.warmup, log_dir=log_dir))
                console.print(rows[-1])
    efficiency = []
    if not a.no_saturate:
        for res in resolutions:
            w, h, hz = RESOLUTIONS[res]
            # the scene of the measured run (paper scenario, 8 robots on the grid) at its start poses
            ov = ["robots.count=8", 'robots.placement="grid"', camera_override(w, h, hz)]
            raw = raw_rate(ov, os.cpu_count() or 2, min(a.seconds, 8.0))
            # cameras (one frame a tick) asking for 1.5x the bare rate, the clock at real time: speeding the
            # clock up instead would multiply the per-tick work (physics, encoders, odometry, fusion) too
            row = measure(8, res, 2, a.seconds, a.warmup, camera_hz=round(max(hz, 1.5 * raw / 8), 1),
                          log_dir=log_dir)
            row["bare_getCameraImage_fps"] = round(raw, 1)
            row["efficiency"] = round(row["frames_processed_per_s"] / raw, 3)
            efficiency.append(row)
            console.print(row)
    import cv2
    import pybullet  # noqa: F401
    import zenoh

    result = {
        "bench": "speed",
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform(),
                    "processor": platform.processor() or platform.machine(),
                    "memory_gb": round(psutil.virtual_memory().total / 2**30, 1),
                    "load_avg_at_end": os.getloadavg()},
        "versions": {"zenoh": getattr(zenoh, "__version__", "?"), "opencv": cv2.__version__,
                     "numpy": np.__version__},
        "seeds": [0], "seconds_per_point": a.seconds, "warmup_s": a.warmup, "rows": rows,
        "efficiency": efficiency, "camera_model": camera_model_cost(),
        "targets": {"rtf_8_robots_320x240_10Hz": ">= 1.0", "efficiency": ">= 0.8",
                    "latency_p95_ms_8_robots": "<= 50"},
    }
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(result, indent=2))
    t = Table(title="realtime speed (full system)")
    for col in ("camera", "robots", "workers", "RTF", "frames asked/s", "processed/s", "latency p50/p95 ms",
                "CPU cores: world+render / agents / server"):
        t.add_column(col)
    for r in rows + efficiency:
        c = r["cpu_cores"]
        lat = r["latency_ms"]
        t.add_row(r["resolution"] + (f" at {r['camera_hz']:.0f} Hz" if r in efficiency else ""),
                  str(r["robots"]), str(r["render_workers"]), f"{r['rtf']:.2f}", f"{r['frames_asked_per_s']:.0f}",
                  f"{r['frames_processed_per_s']:.0f}",
                  f"{lat['p50'] or 0:.0f} / {lat['p95'] or 0:.0f}",
                  f"{c.get('world', 0) + c.get('render_worker', 0):.2f} / {c.get('agent', 0):.2f} / "
                  f"{c.get('server', 0):.2f}")
    console.print(t)
    for r in efficiency:
        console.print(f"efficiency {r['resolution']}: {r['frames_processed_per_s']:.0f} processed/s over "
                      f"{r['bare_getCameraImage_fps']:.0f} bare getCameraImage/s = {r['efficiency']:.2f}")
    console.print(f"wrote {a.out}")
    return 0


def machine() -> dict[str, Any]:
    return {"cpus": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "memory_gb": round(psutil.virtual_memory().total / 2**30, 1), "load_avg_at_end": os.getloadavg()}


def headline_main(a: argparse.Namespace) -> int:
    """``--headline``: the goal's command at each robot count, to speed_headline.json."""
    robots = a.robots if a.robots != [2, 4, 8, 16] else [8, 16]
    log_dir = Path(tempfile.mkdtemp(prefix="tagswarm-speed-logs-"))
    # what the command gives once paper.toml leaves render.workers at its default (automatic)
    extra = ("--set", "render.workers=-1") if PAPER_PINS_WORKERS and not a.as_configured else ()
    rows = headline(robots, a.repeats, a.seconds, a.warmup, log_dir, extra)
    if a.budget_speed:
        rows += headline(robots, a.repeats, a.seconds, a.warmup, log_dir, extra, speed=a.budget_speed)
    if a.budget_lockstep:
        for n in robots:
            # every frame processed whatever else loads the machine: the work of a simulated second, with
            # the render workers the realtime run chose (lockstep alone would render in-process)
            k = next(r["render_workers"] for r in rows if r["robots"] == n)
            rows += headline([n], a.repeats, a.seconds, a.warmup, log_dir,
                             (*extra, "--clock", "lockstep", "--set", f"render.workers={k}"), lockstep=True)
    out = a.out or ROOT / "bench" / "results" / "speed_headline.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({
        "bench": "speed_headline", "machine": machine(), "seconds_per_run": a.seconds, "warmup_s": a.warmup,
        "rows": rows,
        "note": "the machine is shared with other sessions' test runs: load_avg_before per run; medians over "
                "the repeats",
        "targets": {"rtf_16_robots": ">= 0.95", "processed_share_16_robots": ">= 0.95",
                    "latency_p95_ms_8_robots": "<= 50"}}, indent=2))
    print_budget(rows)
    Console().print(f"wrote {out}")
    return 0


def camera_model_main(out: Path) -> int:
    """The camera model's cost per frame alone (bench/camera_cost.py)."""
    rows = camera_model_cost()
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"bench": "camera_model", "load_avg": os.getloadavg(), "rows": rows,
                               "targets": {"model_share": "<= 0.2"}}, indent=2))
    t = Table(title="camera model cost per frame (ms, median)")
    for col in ("camera", "ideal render", "wider pinhole render", "lens + blur + noise", "model / render",
                "all extra / render"):
        t.add_column(col)
    for r in rows:
        t.add_row(r["camera"], f"{r['render_ms']:.1f}", f"{r['wide_render_ms']:.1f}", f"{r['model_ms']:.1f}",
                  f"{r['model_share']:.2f}", f"{r['total_share']:.2f}")
    Console().print(t)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
