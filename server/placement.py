"""First placement of a robot in the map (pure logic): candidates from the
paper's stitching are collected until ``init_min`` recent ones agree; the most
certain agreeing one places the robot and becomes its first factor.  Poses are in
the map frame unless named odometry poses (the robot's own odom frame); metres,
radians, simulation ns."""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass

import numpy as np

from tagswarm.protocol.geometry import Pose2, se2_between, se2_compose, se2_inverse
from tagswarm.server.keyframes import KeyframeGraph
from tagswarm.server.noise import Cov, FusionParams, odom_increment_cov, tangent_cov


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
    """The outcome of :func:`initial_pose`: the start pose now, the most
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


def first_factors(graph: KeyframeGraph, p: FusionParams, counters: Counter[str], new: int, pl: Placement,
                  stamp_ns: int, now: dict[int, tuple[Pose2, Pose2]],
                  meas: list[tuple[int, int, Pose2, Cov]]) -> list[tuple[int, int, Pose2, Cov]]:
    """The measurements that tie a just-placed robot into the graph (``now``: map pose
    and odometry pose at ``stamp_ns`` of the robots of the triggering observation).
    The start pose comes from the most certain agreeing candidate, so that candidate,
    carried forward to now by odometry, becomes a factor; the triggering observation
    joins it only if it agreed.  (Adding the trigger alone let one disagreeing
    observation, e.g. a frontal face's yaw levered by the range, set the pose.)"""
    out = list(meas) if pl.trigger_agrees else []
    if not pl.trigger_agrees:
        counters["init_trigger_dropped"] += 1
    if pl.best is pl.trigger:
        return out
    b_obs, b_tgt, b_rel, b_cov = pl.best.meas
    poses = {rid: pose for rid, (pose, _) in now.items()}
    growth = np.zeros((3, 3))
    for rid in (b_obs, b_tgt):
        then, odom_now = graph.odom_at(rid, pl.best.stamp_ns), graph.odom_at(rid, stamp_ns)
        if then is not None and odom_now is not None:
            growth += odom_increment_cov(se2_between(then, odom_now), p)
        if rid not in poses:
            r = graph.robots[rid]
            if r.estimate is None or odom_now is None:
                return list(meas)  # cannot carry the candidate forward: fall back to the trigger
            poses[rid] = se2_compose(r.estimate, se2_between(r.kf_odom, odom_now))
    out.append((b_obs, b_tgt, se2_between(poses[b_obs], poses[b_tgt]), tangent_cov(b_rel, b_cov) + growth))
    return out


def initial_pose(init: dict[int, list[Candidate]], p: FusionParams, counters: Counter[str], rid: int, stamp_ns: int,
                 placed: Pose2, odom_pose: Pose2, trace: float,
                 meas: tuple) -> Placement | None:  # type: ignore[type-arg]
    """Collect stitched placements of an unplaced robot (in ``init``, the fusion's
    candidates); once ``init_min`` recent ones agree, return the most certain one
    carried forward by odometry to now."""
    cands = [c for c in init.setdefault(rid, []) if stamp_ns - c.stamp_ns < p.init_window_s * 1e9]
    # express every candidate as the pose of the odometry origin, so they compare across time
    trigger = Candidate(stamp_ns, se2_compose(placed, se2_inverse(odom_pose)), trace, meas)
    cands.append(trigger)
    init[rid] = cands
    chosen = choose(cands, p)
    if chosen is None:
        counters["deferred_init"] += 1
        return None
    best, agree = chosen
    counters["init_discarded"] += len(cands) - len(agree)
    del init[rid]
    return Placement(se2_compose(best.origin, odom_pose), best, trigger, any(c is trigger for c in agree))
