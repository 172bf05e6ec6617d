"""First placement of a robot in the map (pure logic): candidates from the
paper's stitching are collected until ``init_min`` recent ones agree; the most
certain agreeing one places the robot and becomes its first factor."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tagswarm.protocol.geometry import Pose2
from tagswarm.server.noise import FusionParams


@dataclass
class Candidate:
    """One stitched placement of a not-yet-placed robot: when, where its odometry
    origin would sit in the map, how uncertain (trace), and the measurement itself
    (``(observer, target, rel, cov)`` for a robot pair, ``(pose, cov_map)`` for a
    landmark) so the chosen one can become the robot's first factor."""

    stamp_ns: int
    origin: Pose2
    trace: float
    meas: tuple  # type: ignore[type-arg]


@dataclass
class Placement:
    """The outcome of :meth:`Fusion._initial_pose`: the start pose now, the most
    certain agreeing candidate, and whether the triggering measurement agreed."""

    pose: Pose2
    best: Candidate
    trigger: Candidate
    trigger_agrees: bool


def choose(cands: list[Candidate], p: FusionParams) -> tuple[Candidate, list[Candidate]] | None:
    """The most certain of the candidates that agree (within ``init_agree_m`` of the
    median odometry-origin position), and the agreeing ones; None until ``init_min``
    agree.  Comparing odometry origins lets candidates of different times agree."""
    if len(cands) < p.init_min:
        return None
    med = np.median(np.array([c.origin[:2] for c in cands]), axis=0)
    agree = [c for c in cands if math.dist(c.origin[:2], med) < p.init_agree_m]
    if len(agree) < p.init_min:
        return None
    return min(agree, key=lambda c: c.trace), agree
