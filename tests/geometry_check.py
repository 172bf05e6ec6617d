"""Shared checks of rendered images against the scenario's true geometry."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from pupil_apriltags import Detector

from tagswarm.protocol import tags
from tagswarm.protocol.geometry import Mat, transform
from tagswarm.protocol.scenario import Scenario

_DETECTORS: dict[str, Detector] = {}


def detector(family: str = "tag36h11") -> Detector:
    if family not in _DETECTORS:
        _DETECTORS[family] = Detector(families=family, quad_decimate=1.0, nthreads=1)
    return _DETECTORS[family]


def tag_owner(s: Scenario) -> dict[int, tuple[int, tags.Face]]:
    """tag id -> (robot id, face)."""
    return {tid: (rid, face) for rid in s.robot_ids for face, tid in zip(tags.Face, s.tag_ids(rid), strict=True)}


def world_corners(s: Scenario, robot_pose: Mat, face: tags.Face) -> NDArray[np.float64]:
    """(4, 3) world coordinates of a robot's tag corners, detector order."""
    local = tags.cube_tag_corners(face, s.robot.cube_edge_m, s.tags.size_m) + np.array([0, 0, s.robot.cube_center_z_m])
    return (robot_pose @ np.c_[local, np.ones(4)].T).T[:, :3]


def project(k: tuple[float, float, float, float], t_world_cam: Mat, pts: NDArray[np.float64]) -> NDArray[np.float64]:
    """Pixels (N, 2) of world points through a pinhole camera at T_world_cam."""
    fx, fy, cx, cy = k
    pc = (np.linalg.inv(t_world_cam) @ np.c_[pts, np.ones(len(pts))].T)[:3]
    return np.stack([fx * pc[0] / pc[2] + cx, fy * pc[1] / pc[2] + cy], axis=1)


def facing(observer_cam: Mat, target_pose: Mat) -> tuple[set[tags.Face], set[tags.Face]]:
    """(must, may): faces of the target cube that squarely face the camera (normal
    within ~50 degrees of the line of sight: a detector must find them) and faces
    that face it at all (a detector may find them).  Ignores occlusion and FOV."""
    must, may = set(), set()
    cam_pos = observer_cam[:3, 3]
    for f in tags.Face:
        n = target_pose[:3, :3] @ tags.face_axes(f)[0]
        centre = target_pose[:3, 3] + n * 0.1
        to_cam = cam_pos - centre
        cos = float(n @ to_cam / np.linalg.norm(to_cam))
        if cos > 0.65:
            must.add(f)
        if cos > 0.0:
            may.add(f)
    return must, may


def pose_from(pos: tuple[float, float, float], quat: tuple[float, float, float, float]) -> Mat:
    from tagswarm.protocol.geometry import quat_to_rot

    return transform(quat_to_rot(quat), pos)
