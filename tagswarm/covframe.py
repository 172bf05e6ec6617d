"""The frame of the server's pose covariances, in one place for the tools that read them.

The server publishes (``Correction.cov``, ``MapEntry.cov``) GTSAM's marginal
covariance of a ``Pose2``: a row-major 3x3 covariance of (x, y, yaw) in the pose's
own tangent space, i.e. x and y along the ROBOT's axes (GTSAM retracts on the
right: ``p.retract([dx, 0, 0])`` of a robot heading +y moves it along map +y).
A map-frame position error must therefore be compared with that block rotated
by the robot's yaw: ``P_map = R(yaw) P_body R(yaw)^T``.  Pure math, no numpy, so
that the live view can use it too.
"""

from __future__ import annotations

import math
from collections.abc import Sequence


def position_cov_in_map(cov: Sequence[float], yaw_rad: float) -> tuple[float, float, float]:
    """(sxx, sxy, syy) m² of the MAP-frame position covariance of a pose with heading
    ``yaw_rad`` (map frame) whose row-major 3x3 covariance ``cov`` of (x, y, yaw) is
    in the robot's own axes (see the module docstring)."""
    bxx, bxy, byy = cov[0], 0.5 * (cov[1] + cov[3]), cov[4]
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    sxx = c * c * bxx - 2 * c * s * bxy + s * s * byy
    syy = s * s * bxx + 2 * c * s * bxy + c * c * byy
    sxy = c * s * (bxx - byy) + (c * c - s * s) * bxy
    return sxx, sxy, syy
