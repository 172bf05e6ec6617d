"""Camera thumbnails for the live web view (pure: OpenCV and numpy, no I/O).

A thumbnail is one :class:`~tagswarm.protocol.messages.CameraImage`, downscaled to at most
``max_width`` pixels and JPEG-encoded, plus the detections the robot's agent
reported for that very frame (its :class:`~tagswarm.protocol.messages.RelativeObservation`
messages with the frame's stamp): each observed target's tag squares are
reprojected from the agent's estimated pose into the image, so the overlay shows
both what was detected and how well the estimate fits the pixels.

Frames: an observation's ``pose`` is T_base_target (target base, or landmark tag
frame, in the observer's base frame); the image's ``mount`` is T_base_camera (the
OpenCV optical frame: z out of the lens, x right, y down); pixels follow OpenCV's
convention (centres at integer coordinates) in both the frame and the thumbnail,
so a thumbnail coordinate is ``(u + 0.5) * scale - 0.5``.
"""

from __future__ import annotations

import base64
from collections.abc import Iterable
from typing import Any, Final

import cv2
import numpy as np
from numpy.typing import NDArray

from tagswarm.protocol import messages as m
from tagswarm.protocol import tags
from tagswarm.protocol.geometry import pose3_to_matrix
from tagswarm.protocol.scenario import Scenario

#: Points closer to the lens than this (m, along the optical axis) are not drawn.
MIN_DEPTH_M: Final = 0.02


def downscale(img: m.CameraImage, max_width: int) -> tuple[NDArray[np.uint8], float]:
    """The frame as a (H, W) uint8 array no wider than ``max_width``, and the scale applied."""
    gray = np.frombuffer(img.data, np.uint8).reshape(img.height, img.width)
    if img.width <= max_width:
        return gray, 1.0
    scale = max_width / img.width
    size = (max_width, max(1, round(img.height * scale)))
    return np.asarray(cv2.resize(gray, size, interpolation=cv2.INTER_AREA), np.uint8), scale


def encode_jpeg(gray: NDArray[np.uint8], quality: int = 80) -> bytes:
    """JPEG bytes of a grayscale image."""
    ok, buf = cv2.imencode(".jpg", gray, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:  # pragma: no cover - OpenCV encodes any non-empty uint8 image
        raise ValueError("JPEG encoding failed")
    return bytes(buf.tobytes())


def project(points_cam: NDArray[np.float64], img: m.CameraImage) -> NDArray[np.float64] | None:
    """Pixels (N, 2) of points (N, 3) given in the camera's optical frame; ``None`` if
    any point is behind (or almost at) the lens."""
    z = points_cam[:, 2]
    if np.any(z < MIN_DEPTH_M):
        return None
    u = img.fx_px * points_cam[:, 0] / z + img.cx_px
    v = img.fy_px * points_cam[:, 1] / z + img.cy_px
    return np.stack([u, v], axis=1)


def target_tag_corners(scenario: Scenario, kind: str, target_id: int,
                       tag_ids: Iterable[int]) -> list[tuple[int, NDArray[np.float64]]]:
    """(tag id, corners (4, 3) in the target's frame) of each of ``tag_ids`` on the target:
    a robot's cube faces (cube centre ``cube_center_z_m`` above its base) or a landmark
    tag (its frame at the tag centre, +x out of the tag, z up).  Unknown IDs are skipped."""
    out: list[tuple[int, NDArray[np.float64]]] = []
    wanted = set(tag_ids)
    if kind == "robot":
        if not 0 <= target_id < scenario.robots.count:
            return out
        r = scenario.robot
        lift = np.array([0.0, 0.0, r.cube_center_z_m])
        for face, tid in zip(tags.Face, scenario.tag_ids(target_id), strict=True):
            if tid in wanted:
                out.append((tid, tags.cube_tag_corners(face, r.cube_edge_m, scenario.tags.size_m) + lift))
    else:
        for lm in scenario.landmarks:
            if lm.id == target_id and lm.id in wanted:
                _, up, right = tags.face_axes(tags.Face.FRONT)
                out.append((lm.id, tags.square_corners(np.zeros(3), up, right, lm.size_m)))
    return out


def overlays(img: m.CameraImage, observations: Iterable[m.RelativeObservation], scenario: Scenario,
             scale: float = 1.0) -> list[dict[str, Any]]:
    """One overlay per observation of this frame: the reprojected tag squares
    (``polys``: list of 4 [u, v] thumbnail pixels each), a label anchor and the range."""
    t_cam_base = np.linalg.inv(pose3_to_matrix(img.mount))
    out = []
    for ob in observations:
        t_cam_target = t_cam_base @ pose3_to_matrix(ob.pose)
        polys: list[dict[str, Any]] = []
        corners_uv: list[list[float]] = []
        for tid, corners in target_tag_corners(scenario, ob.target_kind, ob.target_id, ob.tag_ids):
            pts = (t_cam_target[:3, :3] @ corners.T).T + t_cam_target[:3, 3]
            uv = project(pts, img)
            if uv is not None:
                # pixel centres sit at integers in both images: (u + 0.5) * scale - 0.5
                quad = [[round((float(u) + 0.5) * scale - 0.5, 1), round((float(v) + 0.5) * scale - 0.5, 1)]
                        for u, v in uv]
                polys.append({"tag": tid, "uv": quad})
                corners_uv.extend(quad)
        if not polys:
            continue
        # the label goes centred above the highest corner
        label = [round(sum(q[0] for q in corners_uv) / len(corners_uv), 1), min(q[1] for q in corners_uv)]
        out.append({"kind": ob.target_kind, "target": ob.target_id, "tag_ids": list(ob.tag_ids),
                    "range_m": round(float(np.hypot(ob.x_m, ob.y_m)), 2),
                    "rms_px": round(ob.reprojection_rms_px, 2), "polys": polys, "label": label})
    return out


def camera_message(img: m.CameraImage, observations: Iterable[m.RelativeObservation], scenario: Scenario,
                   max_width: int = 320, quality: int = 80) -> dict[str, Any]:
    """The page's ``camera`` message for one frame (JSON-ready; the JPEG is base64)."""
    gray, scale = downscale(img, max_width)
    return {
        "type": "camera",
        "robot": img.robot_id,
        "camera": img.camera,
        "stamp_ns": img.stamp_ns,
        "width": int(gray.shape[1]),
        "height": int(gray.shape[0]),
        "source_size": [img.width, img.height],
        "jpeg": base64.b64encode(encode_jpeg(gray, quality)).decode("ascii"),
        "detections": overlays(img, observations, scenario, scale),
    }
