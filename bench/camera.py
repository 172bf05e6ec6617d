"""Cost per frame of the camera model (docs/camera.md) against the render, stage by stage.

For each camera: robot 0 of the paper scene turning at 1.2 rad/s (so motion blur is on),
the other robots in view.  Stages, each timed on the same inputs and interleaved so that
all see the same machine load (median over ``--frames``; wall and process CPU time):

- ``render``: pybullet's ``getCameraImage`` of the ideal pinhole (what an ideal frame costs);
- ``wide_render``: that of the wider pinhole a lens needs, with its depth buffer (blur needs it), and a
  wide lens's fovea (world/lens.py);
- ``lens``: the fixed-point ``cv2.remap`` of the render into the 8-bit lens image (every frame);
- ``blur``: the camera's twist, the sub-exposures' maps and the blur (a filter per uniform tile
  of the lens image, the render resampled per sub-exposure elsewhere; nothing under 1 px);
- ``develop``: the frame's noise draw, vignetting, contrast, shot and read noise, rounding.

``model_share`` = (lens + blur + develop) / render, the issue's target <= 0.2;
``model_share_no_blur`` the same for a frame without motion (lens + develop);
``total_share`` = (wide_render + lens + blur + develop) / render - 1, what a realistic frame adds
in all; each also from process CPU time (``_cpu``), which a loaded machine distorts less
than wall time.  OpenCV runs single-threaded here, so CPU time is the work itself (its
thread pool would add CPU for little wall time on two cores).  Writes
``bench/results/camera.json``.

Usage: python bench/camera.py [--frames 40] [--out bench/results/camera.json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from tagswarm.protocol.geometry import se2_matrix  # noqa: E402
from tagswarm.protocol.scenario import load_scenario  # noqa: E402
from tagswarm.world.blur import Exposures, camera_twist, expose, exposure_maps  # noqa: E402
from tagswarm.world.render import Renderer  # noqa: E402
from tagswarm.world.sensor import NoiseBank, develop, frame_key, tone, vignetting_gain  # noqa: E402

CAMERAS = {
    "320x240 60deg brown_conrady": "robot.cameras=[{name='front', width=320, height=240, hfov_deg=60.0}]",
    "640x480 60deg brown_conrady": "robot.cameras=[{name='front', width=640, height=480, hfov_deg=60.0}]",
    "320x240 120deg fisheye": "robot.cameras=[{name='front', width=320, height=240, hfov_deg=120.0}]",
    "640x480 120deg fisheye (rig)": "robot.cameras=[{name='front', width=640, height=480, hfov_deg=120.0}]",
}
TURN_RAD_S = 1.2
DT_S = 0.1


def _time(fn: Callable[[], Any]) -> tuple[float, float, Any]:
    """(wall ms, process CPU ms, result) of one call."""
    w0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return (time.perf_counter() - w0) * 1e3, (time.process_time() - c0) * 1e3, out


def _blur_path(maps: Exposures | None) -> str:
    """How a frame was blurred, in words."""
    if maps is None:
        return "none (streak < 1 px)"
    if maps.kernel is not None:
        return "one filter"
    if maps.tiles is None:
        return f"{len(maps)} sub-exposures per pixel"
    filters = sum(1 for *_, k in maps.tiles if k is not None)
    return f"a filter in {filters} of {len(maps.tiles)} tiles, {len(maps)} sub-exposures in the others"


def camera_row(name: str, override: str, frames: int) -> dict[str, Any]:
    """The stage costs of one camera (see the module docstring)."""
    ideal_s = load_scenario("paper", [override])
    s = load_scenario("paper", [override, "camera.preset=realistic"])
    cam = s.robot.cameras[0]
    cfg = s.camera.resolved()
    stages: dict[str, list[tuple[float, float]]] = {k: [] for k in ("render", "wide_render", "lens", "blur", "develop")}
    paths: list[str] = []
    with Renderer(ideal_s) as ri, Renderer(s) as rr:
        for r in (ri, rr):
            for rid in s.robot_ids:
                r.set_pose(rid, (0.5 * rid, 0.4 * (rid - 1.5), 0.0), (0, 0, 0, 1))
        p = rr.plan(cam)
        mount = rr._mount[cam.name]
        gain = vignetting_gain(cam.width, cam.height, p.lens.K, cfg.vignetting or 0.0) if cfg.vignetting else None
        toned = tone(cfg, gain, (cam.height, cam.width))
        bank = NoiseBank(s.seed, cam.name, cam.width * cam.height)
        for k in range(frames + 2):
            yaw = TURN_RAD_S * k * DT_S - 0.6
            pose, prev = se2_matrix(-1.5, 0.0, yaw), se2_matrix(-1.5, 0.0, yaw - TURN_RAD_S * DT_S)
            t_wc = pose @ mount
            w, c, _ = _time(lambda t_wc=t_wc: ri._shoot(cam, t_wc, False))
            stages["render"].append((w, c))
            def shoot(t_wc: Any = t_wc) -> Any:  # a wide lens renders its fovea too, into one atlas
                if p.fovea is None:
                    return rr._shoot(p.render_cam, t_wc, True), None
                atlas = p.fovea.atlas()
                shot = rr._shoot(p.render_cam, t_wc, True, out=p.fovea.wide_part(atlas))
                rr._shoot(p.fovea.render_cam, t_wc, False, count=False, out=p.fovea.part(atlas))
                return shot, atlas

            w, c, ((gray, zbuf), atlas) = _time(shoot)
            stages["wide_render"].append((w, c))
            w, c, lensed = _time(lambda gray=gray, atlas=atlas: p.apply(gray if atlas is None else atlas))
            stages["lens"].append((w, c))

            def blur(gray: Any = gray, zbuf: Any = zbuf, t_wc: Any = t_wc, prev: Any = prev,
                     lensed: Any = lensed) -> Any:
                twist = camera_twist(prev @ mount, t_wc, DT_S)
                maps = exposure_maps(*p.sample_maps(), zbuf, p.K_render, twist, (cfg.exposure_ms or 0.0) * 1e-3,
                                     near_far=(cam.near_m, cam.far_m))
                paths.append(_blur_path(maps))
                return lensed if maps is None else expose(gray, maps, lensed)

            w, c, blurred = _time(blur)
            stages["blur"].append((w, c))

            def dev(img: Any = blurred, k: int = k) -> Any:
                return develop(img, cfg, toned=toned, bank=bank, key=frame_key(s.seed, 0, cam.name, k))

            w, c, _ = _time(dev)
            stages["develop"].append((w, c))
    med = {k: (float(np.median([x[0] for x in v[2:]])), float(np.median([x[1] for x in v[2:]])))
           for k, v in stages.items()}
    render_w, render_c = med["render"]
    model_w = med["lens"][0] + med["blur"][0] + med["develop"][0]
    model_c = med["lens"][1] + med["blur"][1] + med["develop"][1]
    return {"camera": name, "render_size": [p.render_cam.width, p.render_cam.height],
            "fovea_size": None if p.fovea is None else [p.fovea.render_cam.width, p.fovea.render_cam.height],
            "blur_path": Counter(paths[2:]).most_common(1)[0][0] if paths[2:] else None,
            "wall_ms": {k: round(v[0], 3) for k, v in med.items()},
            "cpu_ms": {k: round(v[1], 3) for k, v in med.items()},
            "model_share": round(model_w / render_w, 3), "model_share_cpu": round(model_c / max(render_c, 1e-6), 3),
            "model_share_no_blur": round((med["lens"][0] + med["develop"][0]) / render_w, 3),
            "total_share": round((med["wide_render"][0] + model_w) / render_w - 1.0, 3),
            "total_share_cpu": round((med["wide_render"][1] + model_c) / max(render_c, 1e-6) - 1.0, 3)}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=40, help="timed frames per camera (2 more warm up)")
    p.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "camera.json")
    a = p.parse_args()
    cv2.setNumThreads(1)
    rows = []
    for name, override in CAMERAS.items():
        rows.append(camera_row(name, override, a.frames))
        print(json.dumps(rows[-1]), flush=True)
    result = {"bench": "camera", "load_avg": list(os.getloadavg()), "cpus": os.cpu_count(), "frames": a.frames,
              "turn_rad_s": TURN_RAD_S, "rows": rows, "targets": {"model_share": "<= 0.2"}}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(result, indent=2))
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
