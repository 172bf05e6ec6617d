"""How far a cube is decoded, and how well its pose is estimated, through the realistic wide lenses
(docs/camera.md, "What the world does") and, for comparison, the default (ideal) camera: robot 0 still
at the origin of a 14 m arena, robot 1's cube at distance d and bearing b, facing the camera within
+-30 deg (12 yaws), the preset's noise, no motion.  For each
(lens, bearing, distance): frames in which robot 1's cube is decoded, and the median position and
heading error of the agent's own estimate of it (its Vision pipeline: detection, undistortion,
cube pose).  Writes ``bench/results/lens_range.json``.

Usage: python bench/lens_range.py [--out bench/results/lens_range.json]
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
import pybullet as pb  # noqa: E402

from tagswarm.agents.vision import Vision  # noqa: E402
from tagswarm.protocol.geometry import se2_matrix  # noqa: E402
from tagswarm.protocol.scenario import load_scenario  # noqa: E402
from tagswarm.world.render import Renderer, image_message  # noqa: E402

LENSES = {"320x240 120deg fisheye": (320, 240, 120.0, "realistic"),
          "640x480 120deg fisheye": (640, 480, 120.0, "realistic"),
          "320x240 60deg brown_conrady": (320, 240, 60.0, "realistic"),
          # the default camera, for comparison (protocol/sightlines.py takes its reading range from here)
          "320x240 60deg ideal": (320, 240, 60.0, "ideal")}
BEARINGS_DEG = (0, 25, 45)
DISTANCES_M = (1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 4.5, 5.0)
YAWS = 12


def lens_row(name: str, width: int, height: int, hfov_deg: float, preset: str) -> dict[str, Any]:
    s = load_scenario("paper", [
        "robots.count=2", 'robots.placement="explicit"', "robots.start=[{x_m=0.0, y_m=0.0}, {x_m=2.0, y_m=0.0}]",
        f"camera.preset={preset}", "camera.exposure_ms=0.0", "arena.size_x_m=14.0", "arena.size_y_m=14.0",
        f'robot.cameras=[{{name="front", width={width}, height={height}, hfov_deg={hfov_deg}, z_m=0.6, '
        'pitch_deg=-15.0}]'])
    cam = s.robot.cameras[0]
    cells = []
    with Renderer(s) as r:
        p = r.plan(cam)
        for bearing in BEARINGS_DEG:
            if bearing > hfov_deg / 2 - 10:
                continue
            for d in DISTANCES_M:
                x, y = d * math.cos(math.radians(bearing)), d * math.sin(math.radians(bearing))
                pos, yaw_err, decoded = [], [], 0
                for k in range(YAWS):
                    vision = Vision(s, 0, collections.Counter())  # no prior from the frame before
                    yaw = math.atan2(-y, -x) + math.radians(-30 + 60 * k / (YAWS - 1))
                    r.set_pose(0, (0, 0, 0), (0, 0, 0, 1))
                    r.set_pose(1, (x, y, 0), pb.getQuaternionFromEuler((0, 0, yaw)))
                    msg = image_message(s, 0, cam, r.render(0, cam, se2_matrix(0, 0, 0)), seq=k, step=k, stamp_ns=k)
                    found = [e for e in vision.process([msg], k) if e.target_kind == "robot" and e.target_id == 1]
                    decoded += bool(found)
                    for e in found:
                        pos.append(math.hypot(e.x_m - x, e.y_m - y))
                        yaw_err.append(abs((e.yaw_rad - yaw + math.pi) % (2 * math.pi) - math.pi))
                cells.append({"bearing_deg": bearing, "distance_m": d, "frames": YAWS, "decoded": decoded,
                              "pos_err_median_m": float(np.median(pos)) if pos else None,
                              "yaw_err_median_deg": math.degrees(float(np.median(yaw_err))) if yaw_err else None})
                print(f"{name}: {bearing:2d} deg {d:.1f} m: {decoded}/{YAWS}", flush=True)
    fv = p.fovea
    return {"lens": name, "model": p.lens.model, "render_size": [p.render_cam.width, p.render_cam.height],
            "fovea_size": None if fv is None else [fv.render_cam.width, fv.render_cam.height], "cells": cells}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "lens_range.json")
    args = ap.parse_args()
    t0 = time.monotonic()
    rows = [lens_row(name, *spec) for name, spec in LENSES.items()]
    result = {"bench": "lens_range", "yaws_within_deg": 30, "rows": rows, "wall_time_s": time.monotonic() - t0}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
