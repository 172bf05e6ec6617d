"""Which robots start where no robot that can be placed sees them (pure geometry): a scene's
first check, before anything runs.

At the start only the origin robot is in the map.  Every other robot turns on the spot until
it is placed (a search, or a station keeper's look around), so a robot is placed as soon as
it and a placed robot are within reading range of each other with nothing tall between them;
the robots reached that way from the origin robot, link by link, can be placed without
anyone driving.  The others stay unplaced until a mission brings someone within sight, and
time localised counts those seconds as lost (measured: a store room whose aisle patrols
started behind shelf rows were first placed at 10-26 s).

Reading range is an estimate: a cube is read while its tags span at least ``MIN_TAG_PX``
pixels (about where half the frames still decode, for the ideal camera and the realistic one
with its noise and lens: bench/lens_range.py), capped by ``agent.max_range_m``; the widest camera of a
rig counts.  Obstacles at least as tall as the cubes' centre block a line of sight.  A
scenario with landmark tags is not checked: its robots place themselves from the field's tags.

Arena frame, metres.
"""

from __future__ import annotations

import math
from typing import Final

from tagswarm.protocol.freespace import sight_blocked
from tagswarm.protocol.layout import start_poses
from tagswarm.protocol.scenario_schema import Camera, Scenario, lens_of

__all__ = ["MIN_TAG_PX", "reading_range_m", "unseen_at_start"]

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


def reading_range_m(s: Scenario) -> float:
    """How far (m) a robot's best camera reads another robot's cube, about (see the module docstring)."""
    px = MIN_TAG_PX[s.camera.preset]
    best = max(_focal_px(c, s.camera.preset) for c in s.robot.cameras) * s.tags.size_m / px
    return min(best, s.agent.max_range_m)


def unseen_at_start(s: Scenario) -> list[int]:
    """Robots not linked to the origin robot at their start poses by a chain of robots within
    :func:`reading_range_m` and in sight of each other; empty with landmarks or no such robot."""
    if s.landmarks or not s.robot.cameras or not 0 <= s.map.origin_id < s.robots.count:
        return []  # (no camera: validation, which comes after, says so)
    pts = [(p[0], p[1]) for p in start_poses(s)]
    reach, tall = reading_range_m(s), s.robot.cube_center_z_m
    placed, frontier = {s.map.origin_id}, [s.map.origin_id]
    while frontier:
        a = frontier.pop()
        for b in range(len(pts)):
            if b not in placed and math.dist(pts[a], pts[b]) <= reach and not sight_blocked(
                    pts[a], pts[b], s.arena, tall):
                placed.add(b)
                frontier.append(b)
    return [k for k in range(len(pts)) if k not in placed]

