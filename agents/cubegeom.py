"""Cameras, targets and results of the cube pose estimator, and its frame helpers (pure code).

Frames: a result is ``T_base_target``, the pose of the observed robot's BASE frame
(on the floor, x forward, y left, z up) -- or of a landmark tag's frame (origin at
the plate centre, +x the tag's outward normal, z up; see
``tagswarm.world.assets.landmark_mesh``) -- in the OBSERVER's base frame.  Cameras are OpenCV
pinholes (pixel centres at integer coordinates) mounted at ``T_base_cam``; a distorted
camera's corners are undistorted onto its pinhole first (:mod:`tagswarm.agents.lens`).  Metres, radians, pixels.

:mod:`tagswarm.agents.cubepose` is the estimator; :mod:`tagswarm.agents.sixdof` its 6-DOF core and
:mod:`tagswarm.agents.planar` its planar model.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Final

import cv2
import numpy as np
from numpy.typing import NDArray

from tagswarm.agents.detect import TargetKind
from tagswarm.protocol import tags
from tagswarm.protocol.errors import TagswarmError
from tagswarm.protocol.geometry import Mat, matrix_to_pose3, pose3_to_matrix
from tagswarm.protocol.messages import CameraImage, RelativeObservation

#: Thickness of a landmark plate; the tag is painted on its +x face, at x = +thickness/2.
#: Mirrors the default of ``tagswarm.world.assets.landmark_mesh`` (tests/unit/agents/test_cubepose.py pins it).
LANDMARK_PLATE_THICKNESS_M: Final = 0.01

#: The identity: a view's ``T_cam_c0`` when it is the start camera itself (compared by identity).
EYE4: Final = np.eye(4)
Arr = NDArray[Any]  # float64 arrays that come out of OpenCV (its stubs do not say so)


class Rejected(TagswarmError):
    """A target the estimator drops; ``str(exc)`` is the reason counted in
    :attr:`tagswarm.agents.cubepose.CubePoseEstimator.rejects`."""


@dataclass(frozen=True)
class CameraModel:
    """A camera on the observer: ``K`` (3, 3) in OpenCV's pixel convention; ``T_base_cam``
    (4, 4) pose of the optical frame (z forward, x right, y down) in the observer's base
    frame; image size in pixels; ``lens`` and ``distortion`` as in
    :class:`~tagswarm.protocol.messages.CameraImage` (the estimator works on pinholes:
    :mod:`tagswarm.agents.lens` undistorts the corners first); ``robot_id`` the observer
    (-1: unknown), which seeds its calibration error."""

    name: str
    K: Mat
    T_base_cam: Mat
    width: int
    height: int
    lens: str = "pinhole"
    distortion: tuple[float, ...] = ()
    robot_id: int = -1
    T_cam_base: Mat = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", np.ascontiguousarray(self.K, np.float64))
        object.__setattr__(self, "T_base_cam", np.ascontiguousarray(self.T_base_cam, np.float64))
        object.__setattr__(self, "T_cam_base", np.linalg.inv(self.T_base_cam))

    @classmethod
    def from_message(cls, msg: CameraImage) -> CameraModel:
        """Intrinsics and mount of a :class:`~tagswarm.protocol.messages.CameraImage`."""
        k = np.array([[msg.fx_px, 0.0, msg.cx_px], [0.0, msg.fy_px, msg.cy_px], [0.0, 0.0, 1.0]])
        return cls(msg.camera, k, pose3_to_matrix(msg.mount), msg.width, msg.height, msg.lens, tuple(msg.distortion),
                   msg.robot_id)


@dataclass(frozen=True)
class PoseEstimate:
    """One target's pose in the observer's base frame.

    ``T_base_target`` (4, 4): observed robot's base frame (or landmark tag frame) in
    the observer's base frame; ``(x_m, y_m, yaw_rad)`` its SE(2) projection
    (yaw = atan2(R10, R00)); ``cov`` (3, 3) covariance of (x_m, y_m, yaw_rad);
    ``reprojection_rms_px`` over the ``n_corners`` corners used; ``ambiguity`` the
    weight of the losing two-fold solution folded into ``cov`` (0 = none).
    """

    target_kind: TargetKind
    target_id: int
    T_base_target: Mat
    x_m: float
    y_m: float
    yaw_rad: float
    cov: Mat
    reprojection_rms_px: float
    tag_ids: tuple[int, ...]
    cameras: tuple[str, ...]
    n_corners: int
    ambiguity: float = 0.0

    def to_message(self, observer_id: int, *, seq: int, stamp_ns: int) -> RelativeObservation:
        """The wire form; a rig's camera names are joined with '+'."""
        return RelativeObservation(
            seq=seq, stamp_ns=stamp_ns, robot_id=observer_id, target_kind=self.target_kind,
            target_id=self.target_id, x_m=self.x_m, y_m=self.y_m, yaw_rad=self.yaw_rad,
            cov=tuple(float(v) for v in self.cov.ravel()), pose=matrix_to_pose3(self.T_base_target),
            reprojection_rms_px=self.reprojection_rms_px, tag_ids=self.tag_ids, camera="+".join(self.cameras))


@dataclass(frozen=True)
class TagGeom:
    """One tag on its target: ``obj`` (4, 3) corners in the target frame (contract order),
    ``ippe_obj`` (4, 3) corners in the tag's own frame (x right, y up, z out of the face;
    IPPE order TL, TR, BR, BL), ``T_tag_target`` (4, 4), ``centre`` (3,) and outward
    ``normal`` (3,) in the target frame.  Metres."""

    kind: TargetKind
    target_id: int
    obj: NDArray[np.float64]
    ippe_obj: NDArray[np.float64]
    T_tag_target: Mat
    centre: NDArray[np.float64]
    normal: NDArray[np.float64]

    @classmethod
    def make(cls, kind: TargetKind, target_id: int, centre: NDArray[np.float64], n: NDArray[np.float64],
             u: NDArray[np.float64], r: NDArray[np.float64], size: float) -> TagGeom:
        """A ``size`` (m) square at ``centre`` with outward normal ``n``, up ``u`` and right ``r``
        (unit vectors in the target frame, :func:`tagswarm.protocol.tags.face_axes`)."""
        obj = tags.square_corners(centre, u, r, size)
        t_target_tag = np.eye(4)
        t_target_tag[:3, :3] = np.stack([r, u, n], axis=1)  # tag frame: x right, y up, z out of the face
        t_target_tag[:3, 3] = centre
        h = size / 2.0
        ippe = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
        return cls(kind, target_id, obj, ippe, np.asarray(np.linalg.inv(t_target_tag), np.float64),
                   np.asarray(centre, np.float64), np.asarray(n, np.float64))


@dataclass(slots=True)
class View:
    """The corners of one target in one camera: ``obj`` (M, 3) in the target frame, ``img``
    (M, 2) pixels; ``T_cam_c0`` (4, 4) maps the start camera's optical frame into this
    camera's (:data:`EYE4` for the start camera); ``tag_ids`` in the order of the corners."""

    cam: CameraModel
    obj: NDArray[np.float64]
    img: NDArray[np.float64]
    T_cam_c0: Mat
    tag_ids: tuple[int, ...]


def rt_to_matrix(rvec: NDArray[Any], tvec: NDArray[Any]) -> Mat:
    """The (4, 4) transform of a Rodrigues vector (rad) and a translation (m)."""
    t = EYE4.copy()
    t[:3, :3] = cv2.Rodrigues(rvec)[0]
    t[:3, 3] = tvec.reshape(3)
    return t


def quad_area(c: NDArray[np.float64]) -> float:
    """Signed area (px^2) of a quadrilateral (4, 2) from its diagonals: positive for the
    contract order TR, TL, BL, BR of a tag seen from the front (counter-clockwise on
    screen), negative for one seen from behind (mirrored order)."""
    (x0, y0), (x1, y1), (x2, y2), (x3, y3) = c.tolist()
    return 0.5 * ((x1 - x3) * (y0 - y2) - (x0 - x2) * (y1 - y3))


def output_jacobian(T_base_cam: Mat, rvec: NDArray[Any], tvec: NDArray[Any]) -> tuple[Mat, NDArray[np.float64]]:
    """``T_base_target`` of ``T_cam_target = (rvec, tvec)`` seen from a camera at ``T_base_cam``,
    and the (6, 6) Jacobian w.r.t. theta = (rvec, tvec) of its (x, y, yaw, z, s_x, s_y),
    where yaw = atan2(R10, R00) and (s_x, s_y) = (R02, R12), the horizontal part of the
    target's z axis (sin of its tilt times the tilt direction).  Metres, radians."""
    r_ct, jr = cv2.Rodrigues(rvec)  # jr[i] = d vec_rowmajor(R) / d rvec_i
    r_bc = T_base_cam[:3, :3]
    t_bt = np.eye(4)
    m = r_bc @ r_ct
    t_bt[:3, :3] = m
    t_bt[:3, 3] = r_bc @ np.ravel(tvec) + T_base_cam[:3, 3]
    dcol0 = r_bc @ jr[:, 0::3].T  # (3 rows of M, 3 rvec components): d M[:, 0] / d rvec
    dcol2 = r_bc @ jr[:, 2::3].T
    g = np.zeros((6, 6))
    g[0:2, 3:6] = r_bc[0:2]
    den = m[0, 0] ** 2 + m[1, 0] ** 2
    g[2, 0:3] = (m[0, 0] * dcol0[1] - m[1, 0] * dcol0[0]) / den
    g[3, 3:6] = r_bc[2]
    g[4:6, 0:3] = dcol2[0:2]
    return t_bt, g


def se2_jacobian(T_base_cam: Mat, T_base_target: Mat, rvec: NDArray[Any]) -> NDArray[np.float64]:
    """The first three rows of :func:`output_jacobian`: (x, y, yaw) w.r.t. (rvec, tvec)."""
    jr = cv2.Rodrigues(rvec)[1]
    r_bc, m = T_base_cam[:3, :3], T_base_target
    dcol0 = r_bc[0:2] @ jr[:, 0::3].T
    g = np.zeros((3, 6))
    g[0:2, 3:6] = r_bc[0:2]
    g[2, 0:3] = (m[0, 0] * dcol0[1] - m[1, 0] * dcol0[0]) / (m[0, 0] ** 2 + m[1, 0] ** 2)
    return g
