"""Collision avoidance as a filter on any wheel command (pure code, no I/O).

The built-in behaviour plans around the other robots itself
(:class:`tagswarm.agents.avoid.Avoider`, which needs a goal).  A user's
controller (:mod:`tagswarm.agents.controller`) has no goal the agent knows
of, so its command is checked instead: the constant twist is rolled out over
``horizon_s`` against the other robots (moving at their estimated velocity for
``NEIGHBOUR_PREDICT_S``, then standing) and the arena's walls and obstacles,
with the same clearance and admissibility rule as the avoider (never closer
than the clearance, or never deeper inside it than now).  An admissible
command passes unchanged.  Otherwise the admissible twist nearest to it is
used: same or lower forward speed, any turn rate; turning in place is always
admissible (the footprint is a circle about ``base_link``).

Frames and units: map frame, metres, radians, seconds; poses are
(x_m, y_m, yaw_rad) of base_link.  Deterministic: ties go to the first
candidate.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tagswarm.agents.avoid import NEIGHBOUR_PREDICT_S, STEP_S, Box, Neighbour, box_distance, rollout
from tagswarm.protocol.geometry import Pose2

Arr = NDArray[np.float64]
SPEED_SHARES = (1.0, 0.75, 0.5, 0.25, 0.0)  # of the requested forward speed, for the alternatives
TURN_SAMPLES = 13


@dataclass
class CommandGuard:
    """Checks and, if needed, replaces a twist; :meth:`filter` once per control cycle."""

    footprint_m: float
    clearance_m: float
    horizon_s: float = 2.0
    filtered: int = 0  # cycles in which the command was replaced

    def admissible(self, pose: Pose2, v: Arr, w: Arr, neighbours: Sequence[Neighbour],
                   boxes: Sequence[Box]) -> NDArray[np.bool_]:
        """For each constant twist (v m/s, w rad/s): whether its path over the horizon keeps the
        clearance from everything (or, already inside it, never gets deeper)."""
        times: Arr = np.arange(1, round(self.horizon_s / STEP_S) + 1, dtype=np.float64) * STEP_S
        travel = float(np.max(np.abs(v))) * self.horizon_s + 1.0  # never cut short: no goal to stop at
        x, y, _ = rollout(pose, v, w, times, travel)
        ok = np.ones(len(v), bool)
        for nb in neighbours:
            req = self.footprint_m + nb.radius_m + self.clearance_m
            gap0 = math.hypot(pose[0] - nb.x_m, pose[1] - nb.y_m) - req
            ahead = np.minimum(times, NEIGHBOUR_PREDICT_S)
            qx, qy = nb.x_m + nb.vx_m_s * ahead, nb.y_m + nb.vy_m_s * ahead
            gap = np.hypot(x - qx[None, :], y - qy[None, :]).min(axis=1) - req
            ok &= gap >= min(0.0, gap0) - 1e-6
        for b in boxes:
            req = self.footprint_m + self.clearance_m
            gap0 = float(box_distance(b, pose[0], pose[1])) - req
            ok &= box_distance(b, x, y).min(axis=1) - req >= min(0.0, gap0) - 1e-6
        ok |= v == 0.0
        return ok

    def filter(self, pose: Pose2, v_m_s: float, w_rad_s: float, neighbours: Sequence[Neighbour],
               boxes: Sequence[Box], w_max: float) -> tuple[float, float]:
        """The twist to drive instead of (v_m_s, w_rad_s): itself when admissible, else the
        admissible one nearest to it (forward speed weighs double)."""
        v0 = np.array([v_m_s])
        w0 = np.array([w_rad_s])
        if self.admissible(pose, v0, w0, neighbours, boxes)[0]:
            return v_m_s, w_rad_s
        self.filtered += 1
        turns = np.linspace(-w_max, w_max, TURN_SAMPLES)
        v = np.repeat(np.array([v_m_s * k for k in SPEED_SHARES]), len(turns) + 1)
        w = np.tile(np.concatenate([[w_rad_s], turns]), len(SPEED_SHARES))
        ok = self.admissible(pose, v, w, neighbours, boxes)
        scale_v = max(abs(v_m_s), 1e-6)
        scale_w = max(w_max, 1e-6)
        cost = np.where(ok, 2.0 * np.abs(v - v_m_s) / scale_v + np.abs(w - w_rad_s) / scale_w, np.inf)
        best = int(np.argmin(cost))  # v = 0 is always admissible: never inf
        return float(v[best]), float(w[best])
