"""How far a robot's camera reads another robot's cube (pure optics on the scenario's
types): what :mod:`tagswarm.protocol.sightlines` and the start poses of
:mod:`tagswarm.protocol.layout` call "in reach".

Reading range is an estimate: a cube is read while its tags span at least ``MIN_TAG_PX``
pixels (about where half the frames still decode, for the ideal camera and the realistic one
with its noise and lens: bench/lens_range.py), capped by ``agent.max_range_m``; of a rig,
the camera that reads farthest counts.  Metres.
"""

from __future__ import annotations

import math
from typing import Final

from tagswarm.protocol.scenario_schema import Camera, Scenario, lens_of

__all__ = ["MIN_TAG_PX", "camera_range_m", "reading_range_m"]

#: a tag this many pixels wide is read in about half the frames (bench/lens_range.py, 320x240, 60 deg,
#: cube straight ahead: the ideal camera reads 7 of 12 at 4.0 m and none at 4.5 m, ~4.2 m; the realistic
#: one, noisy and behind its lens, 5 of 12 at 3.5 m and none at 4.0 m, ~3.4 m)
MIN_TAG_PX: Final = {"ideal": 10.5, "realistic": 13.0}


def _focal_px(cam: Camera, preset: str) -> float:
    """Pixels per radian at the image centre of ``cam``'s lens (:func:`lens_of`): equidistant for a
    fisheye, pinhole otherwise (distortion is small at the centre)."""
    half = math.radians(cam.hfov_deg) / 2.0
    if lens_of(cam, preset)[0] == "fisheye":
        return cam.width / 2.0 / half
    return cam.width / 2.0 / math.tan(half)


def camera_range_m(s: Scenario, cam: Camera) -> float:
    """How far (m) camera ``cam`` of a robot reads another robot's cube, about (see the module docstring)."""
    return min(_focal_px(cam, s.camera.preset) * s.tags.size_m / MIN_TAG_PX[s.camera.preset], s.agent.max_range_m)


def reading_range_m(s: Scenario) -> float:
    """How far (m) the camera of a robot's rig that reads farthest reads another robot's cube, about."""
    return max(camera_range_m(s, c) for c in s.robot.cameras)
