"""Cost per frame of the camera model (lens remap, motion blur, vignetting, noise) against
the render itself, in one process (docs/camera.md).  Used by bench/speed.py
(``--camera-model-only`` runs just this).

For each camera: frames of robot 0 turning (1.2 rad/s, so motion blur is on) in the
paper scene; ``render_ms`` is pybullet's ``getCameraImage`` of the ideal pinhole,
``wide_render_ms`` that of the wider pinhole a lens needs, ``model_ms`` everything
else a realistic frame costs (remap, blur, develop), ``model_share`` =
model_ms / render_ms (target <= 0.2) and ``total_share`` = (wide_render_ms +
model_ms) / render_ms - 1, what the realistic camera adds to a frame in all.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from tagswarm.protocol.geometry import se2_matrix
from tagswarm.protocol.scenario import load_scenario
from tagswarm.world.render import Renderer, image_message

CAMERAS = {
    "320x240 60deg brown_conrady": "robot.cameras=[{name='front', width=320, height=240, hfov_deg=60.0}]",
    "640x480 60deg brown_conrady": "robot.cameras=[{name='front', width=640, height=480, hfov_deg=60.0}]",
    "320x240 120deg fisheye": "robot.cameras=[{name='front', width=320, height=240, hfov_deg=120.0}]",
}


def _frames(overrides: list[str], n: int) -> tuple[float, float]:
    """(ms in getCameraImage, ms in the rest) per frame, medians over ``n`` frames."""
    s = load_scenario("paper", overrides)
    shoot_s: list[float] = []
    total_s: list[float] = []
    with Renderer(s) as r:
        inner = r._shoot

        def timed(*args: Any) -> Any:
            t0 = time.perf_counter()
            out = inner(*args)
            shoot_s.append(time.perf_counter() - t0)
            return out

        r._shoot = timed  # type: ignore[method-assign]
        for rid in s.robot_ids:
            r.set_pose(rid, (0.5 * rid, 0.4 * (rid - 1.5), 0.0), (0, 0, 0, 1))
        cam = s.robot.cameras[0]
        for k in range(n + 2):
            stamp = k * 33_333_333
            t0 = time.perf_counter()
            img = r.render(0, cam, se2_matrix(-1.5, 0.0, 1.2 * stamp * 1e-9 - 0.6))
            image_message(s, 0, cam, img, seq=k, step=k, stamp_ns=stamp)
            total_s.append(time.perf_counter() - t0)
    shoot, total = np.array(shoot_s[2:]), np.array(total_s[2:])  # the first frames build maps and have no motion
    return float(np.median(shoot) * 1e3), float(np.median(total - shoot) * 1e3)


def camera_model_cost(frames: int = 30) -> list[dict[str, Any]]:
    """One row per camera of :data:`CAMERAS` (see the module docstring)."""
    rows = []
    for name, cam in CAMERAS.items():
        render_ms, ideal_rest_ms = _frames([cam], frames)
        wide_ms, model_ms = _frames([cam, "camera.preset=realistic"], frames)
        rows.append({"camera": name, "render_ms": round(render_ms, 2), "wide_render_ms": round(wide_ms, 2),
                     "model_ms": round(model_ms, 2), "ideal_rest_ms": round(ideal_rest_ms, 3),
                     "model_share": round(model_ms / render_ms, 3),
                     "total_share": round((wide_ms + model_ms) / render_ms - 1.0, 3)})
    return rows
