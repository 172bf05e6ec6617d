"""Detection + cube pose per camera frame vs a bare AprilTag detect call, and pose error by distance.

Frames are rendered once per resolution (the paper arena with its walls, 4 robots:
robot 0 observes, robots 1-3 stand at random poses 0.5-5 m in front of it, some
occluding others) and then, frame by frame in the same loop, timed with

* ``bare``: ``pupil_apriltags.Detector(quad_decimate=1, nthreads=1).detect`` -- the reference;
* ``full``: :class:`tagswarm.agents.detect.AprilTagDetector` (same settings, filters, corner shift)
  followed by :meth:`tagswarm.agents.cubepose.CubePoseEstimator.estimate` (the default: planar
  fit of (x, y, yaw)) on its detections.

The target is ``full / bare <= 1.3``.  Pose errors compare every estimate with the
true relative pose of the robot it names, binned by true distance, all views and
single-face views apart; NEES is of (x, y, yaw) against the estimate's covariance
(expected 3).  The 6-DOF estimator (``planar=False``) runs on the same detections,
untimed, as the reference (``*_6dof``).  Writes ``bench/results/detect.json``.

Usage: python bench/detect.py [--frames 150] [--repeats 5] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from pupil_apriltags import Detector  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from tagswarm.agents.cubepose import CameraModel, CubePoseEstimator  # noqa: E402
from tagswarm.agents.detect import AprilTagDetector  # noqa: E402
from tagswarm.protocol.geometry import se2_matrix, wrap_angle, yaw_quat  # noqa: E402
from tagswarm.protocol.layout import footprint_radius  # noqa: E402
from tagswarm.protocol.scenario import Scenario, load_scenario  # noqa: E402
from tagswarm.world.render import Renderer, image_message  # noqa: E402

BINS = [(0.5, 1.0), (1.0, 2.0), (2.0, 3.0), (3.0, 4.0), (4.0, 5.0)]


def scenario(width: int, height: int) -> Scenario:
    return load_scenario("paper", [f'robot.cameras=[{{name="front", width={width}, height={height}, hfov_deg=60}}]'])


def layouts(s: Scenario, n: int, rng: np.random.Generator) -> list[list[tuple[float, float, float]]]:
    """``n`` arena layouts (x, y, yaw per robot): robot 0 faces into the arena, the others
    stand in its field of view, inside the walls and not overlapping."""
    half = min(s.arena.size_x_m, s.arena.size_y_m) / 2 - s.arena.wall_thickness_m / 2 - footprint_radius(s.robot)
    gap = 2 * footprint_radius(s.robot) + 0.05
    hfov = math.radians(s.robot.cameras[0].hfov_deg)
    out: list[list[tuple[float, float, float]]] = []
    while len(out) < n:
        x0, y0 = rng.uniform(-half, half, 2)
        yaw0 = math.atan2(-y0, -x0) + rng.uniform(-0.6, 0.6)
        poses = [(float(x0), float(y0), float(yaw0))]
        for _ in range(200):
            if len(poses) == s.robots.count:
                break
            d, az = rng.uniform(0.5, 5.0), rng.uniform(-0.42, 0.42) * hfov
            x, y = x0 + d * math.cos(yaw0 + az), y0 + d * math.sin(yaw0 + az)
            if abs(x) < half and abs(y) < half and all(math.dist((x, y), p[:2]) > gap for p in poses):
                poses.append((x, y, float(rng.uniform(-math.pi, math.pi))))
        if len(poses) == s.robots.count:
            out.append(poses)
    return out


def relative(observer: tuple[float, float, float], target: tuple[float, float, float]) -> tuple[float, float, float]:
    t = np.linalg.inv(se2_matrix(*observer)) @ se2_matrix(*target)
    return float(t[0, 3]), float(t[1, 3]), math.atan2(t[1, 0], t[0, 0])


def run(width: int, height: int, frames: int, repeats: int, seed: int) -> dict[str, Any]:
    s = scenario(width, height)
    cam = s.robot.cameras[0]
    rng = np.random.default_rng(seed)
    imgs, truths = [], []
    with Renderer(s) as r:
        for poses in layouts(s, frames, rng):
            for rid, (x, y, yaw) in enumerate(poses):
                r.set_pose(rid, (x, y, 0.0), yaw_quat(yaw))
            imgs.append(r.render(0, cam, se2_matrix(*poses[0])))
            truths.append({rid: relative(poses[0], p) for rid, p in enumerate(poses) if rid})
        model = CameraModel.from_message(image_message(s, 0, cam, imgs[0], seq=0, step=0, stamp_ns=0))
    bare = Detector(families=s.tags.family, quad_decimate=1.0, nthreads=1)
    det = AprilTagDetector(s.tags.family)
    est = CubePoseEstimator(s)
    est6 = CubePoseEstimator(s, planar=False)
    t_bare = np.zeros(len(imgs))
    t_full = np.zeros(len(imgs))
    t_pose = np.zeros(len(imgs))
    n_targets = 0
    errors: list[tuple[float, float, float, float, float]] = []  # distance, dxy, dyaw, nees, faces
    errors6: list[tuple[float, float, float, float, float]] = []
    for rep in range(repeats + 1):  # the first pass warms caches and is not counted
        for i, img in enumerate(imgs):
            t0 = time.perf_counter_ns()
            bare.detect(img)
            t1 = time.perf_counter_ns()
            dets = det.detect(img)
            t2 = time.perf_counter_ns()
            ests = est.estimate([(model, dets)])
            t3 = time.perf_counter_ns()
            if rep == 0:
                n_targets += len(ests)
                for out, es in ((errors, ests), (errors6, est6.estimate([(model, dets)]))):
                    for e in es:
                        x, y, yaw = truths[i][e.target_id]
                        err = np.array([e.x_m - x, e.y_m - y, wrap_angle(e.yaw_rad - yaw)])
                        out.append((math.hypot(x, y), math.hypot(err[0], err[1]), abs(err[2]),
                                    float(err @ np.linalg.solve(e.cov, err)), len(e.tag_ids)))
                continue
            t_bare[i] += (t1 - t0) / repeats
            t_full[i] += (t3 - t1) / repeats
            t_pose[i] += (t3 - t2) / repeats
    ev = np.array(errors) if errors else np.zeros((0, 5))
    ev6 = np.array(errors6) if errors6 else np.zeros((0, 5))
    ratio = t_full / np.maximum(t_bare, 1.0)
    return {
        "width": width, "height": height, "frames": len(imgs), "targets_estimated": n_targets,
        "rejects": dict(est.rejects),
        "bare_detect_ms": float(t_bare.mean() / 1e6), "full_ms": float(t_full.mean() / 1e6),
        "pose_ms_per_frame": float(t_pose.mean() / 1e6),
        "pose_ms_per_target": float(t_pose.sum() / 1e6 / max(n_targets, 1)),
        "ratio_total": float(t_full.sum() / t_bare.sum()), "ratio_median_frame": float(np.median(ratio)),
        "ratio_p90_frame": float(np.percentile(ratio, 90)),
        "error_bins": error_bins(ev), "mean_nees": float(ev[:, 3].mean()) if len(ev) else None,
        "yaw_over_10deg_multi_face": int(((ev[:, 2] > math.radians(10)) & (ev[:, 4] > 1)).sum()),
        "error_bins_single_face": error_bins(ev[ev[:, 4] == 1]),
        "error_bins_6dof": error_bins(ev6), "mean_nees_6dof": float(ev6[:, 3].mean()) if len(ev6) else None,
        "error_bins_single_face_6dof": error_bins(ev6[ev6[:, 4] == 1]),
    }


def error_bins(ev: np.ndarray) -> list[dict[str, Any]]:
    """Errors (rows: distance, dxy, dyaw, NEES, faces) binned by true distance."""
    bins: list[dict[str, Any]] = []
    for lo, hi in BINS:
        sel = ev[(ev[:, 0] >= lo) & (ev[:, 0] < hi)]
        if len(sel) == 0:
            bins.append({"range_m": [lo, hi], "n": 0})
            continue
        bins.append({"range_m": [lo, hi], "n": len(sel),
                     "median_xy_cm": float(np.median(sel[:, 1]) * 100),
                     "p90_xy_cm": float(np.percentile(sel[:, 1], 90) * 100),
                     "median_yaw_deg": float(np.degrees(np.median(sel[:, 2]))),
                     "p90_yaw_deg": float(np.degrees(np.percentile(sel[:, 2], 90))),
                     "yaw_over_10deg": int((sel[:, 2] > math.radians(10)).sum()),
                     "mean_nees": float(sel[:, 3].mean())})
    return bins


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=150, help="frames per resolution")
    p.add_argument("--repeats", type=int, default=5, help="timed passes over the frames")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "detect.json")
    a = p.parse_args()
    rows = [run(w, h, a.frames, a.repeats, a.seed) for w, h in ((320, 240), (640, 480))]
    result = {"bench": "detect", "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                                             "platform": platform.platform()},
              "repeats": a.repeats, "seed": a.seed, "rows": rows, "targets": {"ratio_total": "<= 1.3"}}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(result, indent=2))
    con = Console()
    t = Table(title="per frame: AprilTag detect + cube pose vs bare pupil_apriltags detect")
    for col in ("res", "frames", "targets", "bare ms", "full ms", "pose ms/target", "ratio", "p90 frame ratio"):
        t.add_column(col)
    for r in rows:
        t.add_row(f"{r['width']}x{r['height']}", str(r["frames"]), str(r["targets_estimated"]),
                  f"{r['bare_detect_ms']:.2f}", f"{r['full_ms']:.2f}", f"{r['pose_ms_per_target']:.3f}",
                  f"{r['ratio_total']:.2f}", f"{r['ratio_p90_frame']:.2f}")
    con.print(t)
    for key, title in (("error_bins", "all views"), ("error_bins_single_face", "single-face views")):
        t = Table(title=f"relative pose error by true distance, {title} (median / p90; planar | 6-DOF)")
        for col in ("res", "distance m", "n", "xy cm", "yaw deg", "yaw>10deg", "NEES"):
            t.add_column(col)
        for r in rows:
            for b, b6 in zip(r[key], r[f"{key}_6dof"], strict=True):
                if b["n"] and b6["n"]:
                    t.add_row(f"{r['width']}x{r['height']}", f"{b['range_m'][0]}-{b['range_m'][1]}",
                              f"{b['n']} | {b6['n']}",
                              f"{b['median_xy_cm']:.2f} / {b['p90_xy_cm']:.2f} | "
                              f"{b6['median_xy_cm']:.2f} / {b6['p90_xy_cm']:.2f}",
                              f"{b['median_yaw_deg']:.2f} / {b['p90_yaw_deg']:.2f} | "
                              f"{b6['median_yaw_deg']:.2f} / {b6['p90_yaw_deg']:.2f}",
                              f"{b['yaw_over_10deg']} | {b6['yaw_over_10deg']}",
                              f"{b['mean_nees']:.2f} | {b6['mean_nees']:.2f}")
        con.print(t)
    print("wrote", a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
