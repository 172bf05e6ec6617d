"""Trajectories of a run folder as numpy arrays, and the errors between them (pure).

Rows are ``(t_s, x_m, y_m, yaw_rad)``: simulation time in seconds, position in metres and
heading in radians (counter-clockwise from +x, in (-pi, pi]), all in the MAP frame (the
origin robot's first pose, or the arena frame when the scenario has landmarks), read from
the run folder's TUM files (``trajectories/<kind>_<k>.tum``, ``t x y z qx qy qz qw``)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

Array = np.ndarray[Any, np.dtype[np.float64]]
KINDS = ("truth", "odom", "fused")
#: columns of a planar trajectory array
COLUMNS = ("t_s", "x_m", "y_m", "yaw_rad")


def read_tum(path: Path) -> Array:
    """The rows of a TUM file as an (N, 8) array ``t x y z qx qy qz qw`` (N = 0 for an empty file)."""
    if not path.read_text().strip():  # a robot never localised has an empty fused file
        return np.zeros((0, 8))
    return np.loadtxt(path, ndmin=2)


def planar(tum: Array) -> Array:
    """(N, 8) TUM rows -> (N, 4) ``t_s, x_m, y_m, yaw_rad`` (yaw about z from the quaternion)."""
    if len(tum) == 0:
        return np.zeros((0, 4))
    yaw = 2.0 * np.arctan2(tum[:, 6], tum[:, 7])
    yaw = np.arctan2(np.sin(yaw), np.cos(yaw))
    return np.column_stack([tum[:, 0], tum[:, 1], tum[:, 2], yaw])


def position_errors(truth: Array, est: Array, max_dt_s: float = 1e-6) -> Array:
    """(M, 2) rows ``t_s, error_m``: for every estimate with a truth row at the same time
    (within ``max_dt_s``), the distance between the two positions."""
    if len(truth) == 0 or len(est) == 0:
        return np.zeros((0, 2))
    i = np.clip(np.searchsorted(truth[:, 0], est[:, 0]), 0, len(truth) - 1)
    j = np.clip(i - 1, 0, len(truth) - 1)
    nearest = np.where(np.abs(truth[j, 0] - est[:, 0]) < np.abs(truth[i, 0] - est[:, 0]), j, i)
    ok = np.abs(truth[nearest, 0] - est[:, 0]) <= max_dt_s
    d = np.hypot(est[ok, 1] - truth[nearest[ok], 1], est[ok, 2] - truth[nearest[ok], 2])
    return np.column_stack([est[ok, 0], d])


def recorded_errors(truth: Sequence[tuple[int, tuple[float, float, float]]],
                    est: Sequence[tuple[int, tuple[float, float, float]]]) -> list[tuple[float, float]]:
    """(t_s, position error in m) of every estimate with a truth sample at the same stamp, for the
    live series of :class:`~tagswarm.recording.runrecorder.RunRecorder` (``(stamp_ns, (x, y, yaw))``)."""
    at = dict(truth)
    return [(t / 1e9, math.hypot(p[0] - at[t][0], p[1] - at[t][1])) for t, p in est if t in at]


def rms(values: Sequence[float]) -> float:
    """Root mean square; nan for no values."""
    return float(np.sqrt(np.mean(np.square(values)))) if len(values) else float("nan")
