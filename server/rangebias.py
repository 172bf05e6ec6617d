"""The range bias the robots' views share, as one variable of the pose graph (pure code, GTSAM).

A view of a far cube overestimates its range, by more the farther it is (about ``1.5e-4 r^3`` m
for the default camera: +2 mm at 2.5 m, +14 mm at 4.5 m, docs/benchmarks.md), and with the same
sign in every view.  Per-view covariances cannot say that: along a chain of observers each link
adds the same centimetre, while the graph averages the views as if their errors were
independent.  Here the bias coefficient ``b`` (m^-2) is one ``Vector1`` variable that every
robot view from ``MIN_RANGE_M`` on predicts through: the measured translation ``t`` (m, observer's base frame)
is read as ``t (1 - b |t|^2)``, so the factor is the plain between-factor at ``b = 0``.  Its prior
(mean 0, ``range_bias_sigma``) makes the shared error part of every fused covariance, and where
the views and the odometry disagree about ranges the graph learns ``b``.
"""

from __future__ import annotations

import math
from typing import Any

import gtsam
import numpy as np
from numpy.typing import NDArray

from tagswarm.protocol.geometry import Pose2
from tagswarm.server.through import between_through

STEP = 1e-7  # numerical derivative step in b (m^-2); b itself is of order 1e-4
# nearer views keep GTSAM's own between-factor: their bias is at most b 8 m^3 (1.2 mm at the fit), a third of
# their claimed sigma, and a Python factor costs about ten times a C++ one at every linearisation
MIN_RANGE_M = 2.0


def key(generation: int) -> int:
    """The GTSAM key of the bias variable of a generation (a new one after a smoother reset)."""
    return int(gtsam.symbol("b", generation))


def is_bias_key(k: int) -> bool:
    """Whether ``k`` is a bias variable's key."""
    return gtsam.Symbol(k).chr() == ord("b")


def scaled(rel: Pose2, b: float) -> gtsam.Pose2:
    """The view ``rel`` (x_m, y_m, yaw_rad of the target in the observer's frame) with its range
    corrected for the bias coefficient ``b`` (m^-2)."""
    x, y, th = rel
    k = 1.0 - b * (x * x + y * y)
    return gtsam.Pose2(x * k, y * k, th)


def factor(ka: int, kb: int, kbias: int, da: Pose2, rel: Pose2, db: Pose2,
           noise: gtsam.noiseModel.Base) -> gtsam.CustomFactor:
    """Observation factor between keyframes ``ka`` and ``kb`` through the bias ``kbias``: the
    measurement is ``da * scaled(rel, b) * db^-1`` (the observer's odometry since its keyframe, the
    view, back along the target's), with ``noise`` in its tangent space."""
    pa, pb_inv = gtsam.Pose2(*da), gtsam.Pose2(*db).inverse()

    def meas(b: NDArray[np.float64]) -> gtsam.Pose2:
        return pa.compose(scaled(rel, float(b[0]))).compose(pb_inv)

    return between_through(ka, kb, kbias, meas, noise, STEP)


def prior(kbias: int, mean: float, sigma: float) -> gtsam.PriorFactorVector:
    """The bias variable's prior: ``mean`` and ``sigma`` (m^-2)."""
    return gtsam.PriorFactorVector(kbias, np.array([mean]), gtsam.noiseModel.Isotropic.Sigma(1, max(sigma, 1e-9)))


def value(b: float) -> Any:
    """The variable's value for ``gtsam.Values.insert``."""
    return np.array([float(b)])


def summary(b: float, var: float | None) -> str:
    """One log line: the bias coefficient the graph learnt (m^-2, with 1-sigma) and what it means at 3 and 4.5 m."""
    sig = f"{math.sqrt(var):.2g}" if var is not None and var >= 0 else "?"
    return (f"the views' range bias: b = {b:.2g} m^-2 (sigma {sig}): {1000 * b * 27:+.1f} mm at 3 m, "
            f"{1000 * b * 4.5**3:+.1f} mm at 4.5 m")
