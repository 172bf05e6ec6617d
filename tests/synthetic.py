"""Synthetic multi-robot data for fusion tests and benchmarks: true trajectories,
drifting odometry and noisy relative observations with outliers."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from tagswarm.protocol.geometry import Pose2, se2_between, se2_compose


@dataclass
class SyntheticSwarm:
    """Robot 0 holds station at the origin; the others drive circles around it."""

    n: int = 4
    rate_hz: float = 10.0
    seed: int = 0
    odom_bias: float = 0.03  # per-robot wheel-scale/heading drift strength
    obs_sigma_m: float = 0.02
    obs_sigma_rad: float = 0.01
    outlier_rate: float = 0.05
    max_range_m: float = 4.0
    rng: np.random.Generator = field(init=False)

    def __post_init__(self) -> None:
        self.rng = np.random.default_rng(self.seed)
        self.radius = [0.0] + [1.0 + 0.5 * k for k in range(1, self.n)]
        self.speed = [0.0] + [0.15 + 0.05 * (k % 3) for k in range(1, self.n)]
        self.bias = [(0.0, 0.0)] + [tuple(self.rng.normal(0, self.odom_bias, 2)) for _ in range(1, self.n)]
        self.odom: list[Pose2] = [(0.0, 0.0, 0.0)] * self.n
        self.prev_truth = [self.truth(k, 0.0) for k in range(self.n)]

    def truth(self, k: int, t: float) -> Pose2:
        if k == 0:
            return (0.0, 0.0, 0.0)
        r, v = self.radius[k], self.speed[k]
        a = v * t / r + k
        return (r * math.cos(a), r * math.sin(a), math.atan2(math.cos(a), -math.sin(a)))

    def step(self, t: float) -> tuple[list[Pose2], list[tuple[int, int, Pose2, np.ndarray, bool]]]:
        """Advance to time t: cumulative odometry per robot and observations
        (observer, target, relative pose, covariance, is_outlier)."""
        truths = [self.truth(k, t) for k in range(self.n)]
        for k in range(self.n):
            d = se2_between(self.prev_truth[k], truths[k])
            dist = math.hypot(d[0], d[1])
            scale, turn = self.bias[k]
            noisy = (d[0] * (1 + scale) + self.rng.normal(0, 0.002 * math.sqrt(dist + 1e-9)),
                     d[1] + self.rng.normal(0, 0.001 * math.sqrt(dist + 1e-9)),
                     d[2] + turn * dist + self.rng.normal(0, 0.003 * math.sqrt(dist + 1e-9)))
            self.odom[k] = se2_compose(self.odom[k], noisy)
        self.prev_truth = truths
        obs = []
        cov = np.diag([self.obs_sigma_m**2, self.obs_sigma_m**2, self.obs_sigma_rad**2])
        for i in range(self.n):
            for j in range(self.n):
                if i == j or self.rng.random() > 0.3:
                    continue
                rel = se2_between(truths[i], truths[j])
                if math.hypot(rel[0], rel[1]) > self.max_range_m:
                    continue
                outlier = bool(self.rng.random() < self.outlier_rate)
                if outlier:
                    z = (float(self.rng.uniform(-3, 3)), float(self.rng.uniform(-3, 3)),
                         float(self.rng.uniform(-math.pi, math.pi)))
                else:
                    z = (rel[0] + self.rng.normal(0, self.obs_sigma_m), rel[1] + self.rng.normal(0, self.obs_sigma_m),
                         rel[2] + self.rng.normal(0, self.obs_sigma_rad))
                obs.append((i, j, z, cov, outlier))
        return list(self.odom), obs
