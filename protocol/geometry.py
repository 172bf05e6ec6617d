"""Small rigid-body helpers shared by every process (numpy only).

Quaternions are (x, y, z, w), as in pybullet and :class:`tagswarm.protocol.messages.Pose3`.
Homogeneous transforms are (4, 4) float64; ``T_a_b`` maps points in frame b to
frame a.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from tagswarm.protocol.messages import Pose3

Mat = NDArray[np.float64]


def wrap_angle(a: float) -> float:
    """Angle wrapped to [-pi, pi)."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def quat_to_rot(q: tuple[float, float, float, float] | Mat) -> Mat:
    """(3, 3) rotation matrix of the unit quaternion (x, y, z, w)."""
    x, y, z, w = (float(v) for v in q)
    n = math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def rot_to_quat(r: Mat) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w), w >= 0, of a (3, 3) rotation matrix."""
    m = np.asarray(r, float)
    t = m[0, 0] + m[1, 1] + m[2, 2]
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        w, x, y, z = 0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        w, x, y, z = (m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        w, x, y, z = (m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        w, x, y, z = (m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s
    if w < 0:
        x, y, z, w = -x, -y, -z, -w
    return (float(x), float(y), float(z), float(w))


def yaw_quat(yaw: float) -> tuple[float, float, float, float]:
    """Quaternion of a rotation by ``yaw`` about +z."""
    return (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def quat_yaw(q: tuple[float, float, float, float] | Mat) -> float:
    """Heading (rotation about +z) of a quaternion, radians."""
    x, y, z, w = (float(v) for v in q)
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def transform(r: Mat, t: Mat | tuple[float, float, float]) -> Mat:
    """(4, 4) transform from a (3, 3) rotation and a translation (3,)."""
    out = np.eye(4)
    out[:3, :3] = r
    out[:3, 3] = t
    return out


def pose3_to_matrix(p: Pose3) -> Mat:
    """(4, 4) transform of a :class:`Pose3`."""
    return transform(quat_to_rot((p.qx, p.qy, p.qz, p.qw)), (p.x_m, p.y_m, p.z_m))


def matrix_to_pose3(t: Mat) -> Pose3:
    """:class:`Pose3` of a (4, 4) transform."""
    qx, qy, qz, qw = rot_to_quat(t[:3, :3])
    return Pose3(x_m=float(t[0, 3]), y_m=float(t[1, 3]), z_m=float(t[2, 3]), qx=qx, qy=qy, qz=qz, qw=qw)


def se2_matrix(x: float, y: float, yaw: float, z: float = 0.0) -> Mat:
    """(4, 4) transform of a planar pose (rotation about +z), optional height."""
    c, s = math.cos(yaw), math.sin(yaw)
    return transform(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]), (x, y, z))


Pose2 = tuple[float, float, float]


def se2_compose(a: Pose2, b: Pose2) -> Pose2:
    """a ⊕ b for planar poses (x_m, y_m, yaw_rad): b given in frame a, result in a's parent."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return (a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], wrap_angle(a[2] + b[2]))


def se2_inverse(a: Pose2) -> Pose2:
    """⊖a for a planar pose."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return (-c * a[0] - s * a[1], s * a[0] - c * a[1], wrap_angle(-a[2]))


def se2_between(a: Pose2, b: Pose2) -> Pose2:
    """⊖a ⊕ b: pose b relative to pose a."""
    return se2_compose(se2_inverse(a), b)


def worst_axis_sigma_m(cov: NDArray[np.float64] | tuple[float, ...]) -> float:
    """Standard deviation (m) of a (3, 3) (x, y, yaw) covariance's position along its worst axis (inf
    if it is not finite); a row-major tuple of 9 (a message's ``cov``) too.  What the server vouches
    by (``[server] claim_sigma_m``), so an agent judges a correction the same way."""
    c = np.asarray(cov, float).reshape(3, 3)[:2, :2]
    if not np.all(np.isfinite(c)):
        return math.inf
    return math.sqrt(max(float(np.linalg.eigvalsh(c)[1]), 0.0))


def position_sigma_m(cov: tuple[float, ...] | None) -> float | None:
    """The larger axis's position σ (m) of a row-major 3x3 (x, y, yaw) covariance; None without one."""
    return math.sqrt(max(cov[0], cov[4], 0.0)) if cov is not None and len(cov) == 9 else None
