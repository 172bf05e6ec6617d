"""Which robots start where no robot that can be placed sees them (pure geometry): a scene's
first check, before anything runs.

At the start only the origin robot is in the map.  Every other robot turns on the spot until
it is placed (a search, or a station keeper's look around), so a robot is placed as soon as
it and a placed robot are within reading range of each other with nothing tall between them;
the robots reached that way from the origin robot, link by link, can be placed without
anyone driving.  The others stay unplaced until a mission brings someone within sight, and
time localised counts those seconds as lost (measured: a store room whose aisle patrols
started behind shelf rows were first placed at 10-26 s).

Reading range (:func:`~tagswarm.protocol.readrange.reading_range_m`) is an estimate: where
about half the frames still decode a cube.  Obstacles at least as tall as the cubes' centre
block a line of sight.  A
scenario with landmark tags is not checked: its robots place themselves from the field's tags.

Arena frame, metres.
"""

from __future__ import annotations

import math

from tagswarm.protocol.freespace import sight_blocked
from tagswarm.protocol.layout import start_poses
from tagswarm.protocol.readrange import MIN_TAG_PX, reading_range_m
from tagswarm.protocol.scenario_schema import Scenario

__all__ = ["MIN_TAG_PX", "reading_range_m", "unseen_at_start"]


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

