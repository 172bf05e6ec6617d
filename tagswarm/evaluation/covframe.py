"""The frame of the server's pose covariances, in one place for the tools that read them.

The server publishes (``Correction.cov``, ``MapEntry.cov``) GTSAM's marginal
covariance of a ``Pose2``: a row-major 3x3 covariance of (x, y, yaw) in the pose's
own tangent space, i.e. x and y along the ROBOT's axes (GTSAM retracts on the
right: ``p.retract([dx, 0, 0])`` of a robot heading +y moves it along map +y).
A map-frame position error must therefore be compared with that block rotated
by the robot's yaw: ``P_map = R(yaw) P_body R(yaw)^T``; so must a drawn
covariance ellipse.  Pure math, no numpy, so that the live view can use it too.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, Final

#: Scale of a drawn 95 % covariance ellipse: sqrt of the chi-square 95 % quantile for 2 degrees of freedom.
ELLIPSE_SCALE_95: Final = math.sqrt(5.991)


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


def position_nees(sxx: Any, sxy: Any, syy: Any, ex: Any, ey: Any) -> Any:
    """e^T P^-1 e / 2 of a position error ``(ex, ey)`` (m) against the 2x2 covariance ``[[sxx,
    sxy], [sxy, syy]]`` (m², same axes): 1 on average for an honest covariance.  Scalars or
    arrays of one shape; the caller checks that P is positive definite."""
    det = sxx * syy - sxy * sxy
    return (syy * ex * ex - 2 * sxy * ex * ey + sxx * ey * ey) / det / 2.0


def covariance_ellipse(cov: tuple[float, ...], scale: float = ELLIPSE_SCALE_95,
                       yaw_rad: float = 0.0) -> tuple[float, float, float]:
    """Semi-axes (a_m >= b_m) and orientation (rad, of the a axis from +x) of the ellipse of
    the (x, y) block of a row-major 3x3 covariance of (x_m, y_m, yaw_rad), times ``scale``.
    The block is in the axes of a pose heading ``yaw_rad`` (the server's convention, see
    the module docstring; 0 for a covariance already in the frame drawn in).
    Negative eigenvalues (a covariance that is not quite PSD) are clamped to zero."""
    sxx, sxy, syy = position_cov_in_map(cov, yaw_rad)
    mean, diff = 0.5 * (sxx + syy), 0.5 * (sxx - syy)
    r = math.hypot(diff, sxy)
    l1, l2 = max(mean + r, 0.0), max(mean - r, 0.0)
    angle = 0.5 * math.atan2(2.0 * sxy, sxx - syy)
    return scale * math.sqrt(l1), scale * math.sqrt(l2), angle
