"""``tagswarm snapshot``: start a world on a private Zenoh network, grab one frame
per robot camera plus ground truth, decode the tags and write what each robot
sees (annotated PNGs, a top-down arena plot and a JSON summary)."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Sequence
from datetime import datetime
from pathlib import Path

import cv2
import numpy as np
from pupil_apriltags import Detector
from rich.console import Console
from rich.table import Table

from tagswarm.protocol import codec, tags
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import BusConfig, open_bus
from tagswarm.protocol.keys import Keys
from tagswarm.runtime.config import ConfigError, Invocation, OneLineParser, add_common_args
from tagswarm.runtime.process import run_main


def _free_endpoint() -> str:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def _plot_arena(path: Path, scenario_size: tuple[float, float], truth: dict[int, m.GroundTruthPose],
                edges: list[tuple[int, int]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sx, sy = scenario_size
    fig, ax = plt.subplots(figsize=(6, 6))
    ax.add_patch(plt.Rectangle((-sx / 2, -sy / 2), sx, sy, fill=False, lw=2))
    for a, b in edges:
        pa, pb = truth[a], truth[b]
        ax.annotate("", xy=(pb.x_m, pb.y_m), xytext=(pa.x_m, pa.y_m),
                    arrowprops={"arrowstyle": "->", "color": "tab:green", "alpha": 0.6})
    for rid, t in truth.items():
        ax.plot(t.x_m, t.y_m, "o", ms=12, color="tab:blue")
        ax.arrow(t.x_m, t.y_m, 0.35 * np.cos(t.yaw_rad), 0.35 * np.sin(t.yaw_rad), width=0.03, color="tab:red")
        ax.text(t.x_m + 0.15, t.y_m + 0.15, f"robot {rid}")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title("arena: true poses; green arrow = 'sees a tag of'")
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry for ``tagswarm snapshot``."""
    p = OneLineParser(prog="tagswarm snapshot", description=__doc__)
    add_common_args(p)
    p.add_argument("--out", type=Path, help="output folder (default runs/snapshot-<timestamp>)")
    p.add_argument("--timeout", type=float, default=60.0, help="seconds to wait for frames (default 60)")

    def body() -> int:
        inv = Invocation(p, argv)
        args = inv.args
        scenario = inv.scenario()  # validates before anything starts
        run = inv.pick("run", "snapshot")
        keys = Keys(run)
        out = args.out or Path("runs") / f"snapshot-{datetime.now():%Y%m%d-%H%M%S}"
        out.mkdir(parents=True, exist_ok=True)
        ep = _free_endpoint()
        world_argv = [sys.executable, "-m", "tagswarm.world.node", "--listen", ep, "--run", run, "--duration", "3600"]
        if args.scenario:
            world_argv += ["--scenario", args.scenario]
        for o in args.overrides:
            world_argv += ["--set", o]
        if args.seed is not None:
            world_argv += ["--seed", str(args.seed)]
        if args.robots is not None:
            world_argv += ["--robots", str(args.robots)]
        wanted = {(rid, c.name) for rid in scenario.robot_ids for c in scenario.robot.cameras}
        frames: dict[tuple[int, str], m.CameraImage] = {}
        truth: dict[int, m.GroundTruthPose] = {}
        with open(out / "world.log", "wb") as log:
            world = subprocess.Popen(world_argv, stdout=log, stderr=subprocess.STDOUT)
            try:
                with open_bus(BusConfig(connect=(ep,))) as bus:
                    images, truths = bus.subscribe(keys.images()), bus.subscribe(keys.truth())

                    def collect() -> bool:
                        for it in images.drain():
                            img = codec.decode(m.CameraImage, it.value)
                            frames[(img.robot_id, img.camera)] = img
                        for it in truths.drain():
                            t = codec.decode(m.GroundTruthPose, it.value)
                            truth[t.robot_id] = t
                        return set(frames) >= wanted and len(truth) == len(scenario.robot_ids)

                    t0 = time.monotonic()
                    while not collect():
                        if world.poll() is not None:
                            raise ConfigError(f"the world exited with code {world.returncode}; see {out}/world.log")
                        if time.monotonic() - t0 > args.timeout:
                            raise ConfigError(f"no frames after {args.timeout} s; see {out}/world.log")
                        bus.wait(0.2)
            finally:
                world.terminate()
                world.wait(timeout=10)
        owner = {tid: (rid, f) for rid in scenario.robot_ids for f, tid in zip(tags.Face, scenario.tag_ids(rid),
                                                                                 strict=True)}
        det = Detector(families=scenario.tags.family, quad_decimate=1.0, nthreads=1)
        table = Table(title=f"what each robot sees ({scenario.name}, {len(scenario.robot_ids)} robots)")
        for col in ("robot", "camera", "tags decoded", "robots seen (faces)"):
            table.add_column(col)
        summary, edges = [], []
        for (rid, cam), img in sorted(frames.items()):
            gray = np.frombuffer(img.data, np.uint8).reshape(img.height, img.width)
            vis = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
            seen = []
            for d in det.detect(gray):
                who = owner.get(d.tag_id)
                label = f"r{who[0]} {who[1].name.lower()}" if who else f"id {d.tag_id}"
                cv2.polylines(vis, [np.round(d.corners - 0.5).astype(np.int32)], True, (0, 200, 0), 2)
                cv2.putText(vis, label, tuple(int(v) for v in d.center), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                            (0, 0, 255), 1)
                seen.append({"tag_id": int(d.tag_id), "robot": who[0] if who else None,
                             "face": who[1].name.lower() if who else None})
                if who and (rid, who[0]) not in edges:
                    edges.append((rid, who[0]))
            cv2.imwrite(str(out / f"robot{rid}_{cam}.png"), vis)
            summary.append({"robot": rid, "camera": cam, "step": img.step, "detections": seen})
            table.add_row(str(rid), cam, str(len(seen)),
                          ", ".join(f"{s['robot']} ({s['face']})" for s in seen if s["robot"] is not None) or "-")
        _plot_arena(out / "arena.png", (scenario.arena.size_x_m, scenario.arena.size_y_m), truth, edges)
        (out / "snapshot.json").write_text(json.dumps({"scenario": scenario.name, "frames": summary,
                                                       "truth": {r: [t.x_m, t.y_m, t.yaw_rad]
                                                                 for r, t in truth.items()}}, indent=2))
        console = Console()
        console.print(table)
        console.print(f"wrote {out}/arena.png, robot*_*.png and snapshot.json")
        return 0

    return run_main("tagswarm snapshot", body)
