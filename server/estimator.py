"""What the server node needs from a map estimator (pure code, no I/O).

Both :class:`~tagswarm.server.fusion.Fusion` (``[server] method = "graph"``, the GTSAM
pose graph) and :class:`~tagswarm.server.stitchmap.StitchMap` (``"stitch"``, the paper's
chain of homogeneous transforms) satisfy :class:`Estimator`; :func:`make_estimator` builds
the one a server's config chooses (:mod:`tagswarm.server.node` runs it).  Poses are in the map frame (metres, radians),
covariances (3, 3) in the robot's own axes (GTSAM's tangent convention), times
simulation nanoseconds.
"""

from __future__ import annotations

from collections import Counter
from typing import Protocol

import numpy as np

from tagswarm.protocol.geometry import Pose2, se2_compose
from tagswarm.protocol.layout import arena_to_map, start_poses
from tagswarm.protocol.scenario import Scenario
from tagswarm.server import journal_format as jf
from tagswarm.server import odomcal, rangebias
from tagswarm.server.config import ServerConfig
from tagswarm.server.fusion import Fusion, FusionParams, RelocEvent
from tagswarm.server.noise import Cov
from tagswarm.server.stitchmap import StitchMap


class Estimator(Protocol):
    """The map estimator interface of the server node (see the module docstring)."""

    counters: Counter[str]
    edges: dict[tuple[int, int], int]  # (observer, target) -> stamp of the newest accepted observation
    watermark_ns: int

    def reset(self) -> None: ...
    def add_odometry(self, rid: int, stamp_ns: int, pose: Pose2, distance_m: float, slip_m: float = 0.0) -> None: ...
    def add_observation(self, observer: int, target: int, stamp_ns: int, rel: Pose2, cov: Cov) -> None: ...
    def add_landmark_observation(self, observer: int, landmark: int, stamp_ns: int, rel: Pose2,
                                 cov: Cov) -> None: ...
    def advance(self, watermark_ns: int) -> int: ...
    def latest_odom_ns(self, rid: int) -> int: ...
    def pose(self, rid: int) -> tuple[Pose2, Cov] | None: ...
    def map_to_odom(self, rid: int) -> Pose2 | None: ...
    def in_dispute(self, rid: int) -> bool: ...
    def last_fix_ns(self, rid: int) -> int: ...
    def localised(self) -> list[int]: ...
    def take_relocalisations(self) -> list[RelocEvent]: ...


def apply_input(est: Estimator, record: jf.Record) -> None:
    """Make the estimator call an input ``record`` stands for (the journal's replay,
    :func:`tagswarm.server.journal_records.apply`, adds checkpoints; they are the graph's own
    state and ignored here)."""
    if isinstance(record, jf.Odometry):
        est.add_odometry(record.robot_id, record.stamp_ns, (record.x_m, record.y_m, record.yaw_rad),
                         record.distance_m, record.slip_m)
    elif isinstance(record, jf.Observation):
        rel = (record.x_m, record.y_m, record.yaw_rad)
        cov = np.asarray(record.cov, float).reshape(3, 3)
        if record.target_kind == "robot":
            est.add_observation(record.observer, record.target_id, record.stamp_ns, rel, cov)
        else:
            est.add_landmark_observation(record.observer, record.target_id, record.stamp_ns, rel, cov)
    elif isinstance(record, jf.Advance):
        est.advance(record.watermark_ns)
    elif isinstance(record, jf.NewRun):
        est.reset()


def make_fusion(config: ServerConfig) -> Fusion:
    """The (empty) fusion a server with ``config`` runs; a journal replayed into it
    rebuilds that server's graph (tools and tests use this too)."""
    s = config.scenario
    cal = s.server.odom_calibration
    wheel, scale = odomcal.odometry_sigmas(cal, s.agent.odom_wheel_sigma, s.server.odom_wheel_sigma,
                                           s.server.odom_scale_sigma)
    params = FusionParams(wheel_base_m=s.robot.wheel_base_m, odom_wheel_sigma=wheel, odom_scale_sigma=scale,
                          obs_sigma_floor_m=s.server.obs_sigma_floor_m, odom_calibration=cal, lag_s=config.lag_s,
                          range_bias_sigma=s.server.range_bias_sigma, start_prior_sigma=s.server.start_prior_sigma)
    landmarks = {lm.id: (lm.x_m, lm.y_m, lm.yaw_rad) for lm in s.landmarks}
    return Fusion(params, s.map.origin_id, s.robot_ids, landmarks, start_poses_in_map(s) if s.server.start_prior_sigma
                  else None)


def start_poses_in_map(s: Scenario) -> dict[int, Pose2]:
    """Each robot's start pose (:func:`tagswarm.protocol.layout.start_poses`) in the map frame
    (:func:`tagswarm.protocol.layout.arena_to_map`)."""
    t_map_arena = arena_to_map(s)
    return {rid: se2_compose(t_map_arena, pose) for rid, pose in enumerate(start_poses(s))}


def make_estimator(config: ServerConfig) -> Estimator:
    """The (empty) map estimator of ``[server] method``: the pose graph (``graph``, see
    :func:`make_fusion`) or the paper's stitched map (``stitch``) with the same parameters."""
    if config.scenario.server.method == "graph":
        return make_fusion(config)
    f = make_fusion(config)  # (cheap: an empty graph) the same parameters, origin and landmarks
    return StitchMap(f.p, f.origin_id, tuple(f.robots), f.landmarks)


def learnt(est: Estimator) -> list[str]:
    """Log lines of what the graph learnt about the sensors by the end of a run: each robot's odometry
    calibration and the views' range bias (nothing for the stitching or where they are off)."""
    if not isinstance(est, Fusion):
        return []
    out = [odomcal.summary(rid, r.cal, r.cal_cov) for rid, r in est.robots.items()
           if est.p.odom_calibration and r.cal_key is not None]
    if est.graph.bias_key is not None:
        out.append(rangebias.summary(est.graph.bias, est.graph.bias_var))
    return out
