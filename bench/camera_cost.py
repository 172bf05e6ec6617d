"""Cost per frame of the camera model (lens remap, motion blur, vignetting, noise) against
the render itself, in one process (docs/camera.md).  Used by bench/speed.py
(``--camera-model-only`` runs just this).

For each camera: frames of robot 0 turning (1.2 rad/s, so motion blur is on) in the
paper scene; ``render_ms`` is pybullet's ``getCameraImage`` of the ideal pinhole,
``wide_render_ms`` that of the wider pinhole a lens needs (with a wide lens's fovea), ``model_ms`` everything
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
    "320x240 60deg brown_conrady, no blur": "robot.cameras=[{name='front', width=320, height=240, hfov_deg=60.0}]",
    "640x480 60deg brown_conrady": "robot.cameras=[{name='front', width=640, height=480, hfov_deg=60.0}]",
    "320x240 120deg fisheye": "robot.cameras=[{name='front', width=320, height=240, hfov_deg=120.0}]",
}


class _Timed:
    """A renderer of one camera whose ``getCameraImage`` and whole-frame times are recorded."""

    def __init__(self, overrides: list[str]) -> None:
        self.s = load_scenario("paper", overrides)
        self.r = Renderer(self.s)
        self.cam = self.s.robot.cameras[0]
        self.shoot_s: list[float] = []
        self.total_s: list[float] = []
        inner = self.r._shoot

        def timed(*args: Any, **kwargs: Any) -> Any:
            t0 = time.perf_counter()
            out = inner(*args, **kwargs)
            self._in_shoot += time.perf_counter() - t0  # a wide lens's fovea is a second render of the frame
            return out

        self._in_shoot = 0.0

        self.r._shoot = timed  # type: ignore[method-assign]
        for rid in self.s.robot_ids:
            self.r.set_pose(rid, (0.5 * rid, 0.4 * (rid - 1.5), 0.0), (0, 0, 0, 1))

    def frame(self, k: int) -> None:
        stamp = k * 33_333_333
        self._in_shoot = 0.0
        t0 = time.perf_counter()
        img = self.r.render(0, self.cam, se2_matrix(-1.5, 0.0, 1.2 * stamp * 1e-9 - 0.6))
        image_message(self.s, 0, self.cam, img, seq=k, step=k, stamp_ns=stamp)
        self.total_s.append(time.perf_counter() - t0)
        self.shoot_s.append(self._in_shoot)

    def medians(self) -> tuple[float, float]:
        """(ms in getCameraImage, ms in the rest) per frame; the first frames build maps and have no motion."""
        shoot, total = np.array(self.shoot_s[2:]), np.array(self.total_s[2:])
        return float(np.median(shoot) * 1e3), float(np.median(total - shoot) * 1e3)


def camera_model_cost(frames: int = 30) -> list[dict[str, Any]]:
    """One row per camera of :data:`CAMERAS` (see the module docstring); the ideal and the realistic
    frames alternate, so both see the same machine load."""
    rows = []
    for name, cam in CAMERAS.items():
        extra = ["camera.exposure_ms=0"] if "no blur" in name else []
        ideal, real = _Timed([cam]), _Timed([cam, "camera.preset=realistic", *extra])
        try:
            for k in range(frames + 2):
                ideal.frame(k)
                real.frame(k)
        finally:
            ideal.r.close()
            real.r.close()
        render_ms, ideal_rest_ms = ideal.medians()
        wide_ms, model_ms = real.medians()
        rows.append({"camera": name, "render_ms": round(render_ms, 2), "wide_render_ms": round(wide_ms, 2),
                     "model_ms": round(model_ms, 2), "ideal_rest_ms": round(ideal_rest_ms, 3),
                     "model_share": round(model_ms / render_ms, 3),
                     "total_share": round((wide_ms + model_ms) / render_ms - 1.0, 3)})
    return rows
