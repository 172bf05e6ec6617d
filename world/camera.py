"""Pinhole model of a simulated camera: intrinsics and mount (pure numpy)."""

from __future__ import annotations

import math

import numpy as np

from tagswarm.protocol.geometry import Mat, transform
from tagswarm.protocol.scenario import Camera

#: Principal-point offsets (px) of pybullet's TinyRenderer relative to (W/2, H/2),
#: in OpenCV's pixel convention (pixel centres at integer coordinates).
#: Measured by tests/unit/world/test_render_geometry.py against rendered tag corners.
CX_OFFSET_PX = 0.0
CY_OFFSET_PX = -1.0


def vfov_deg(cam: Camera) -> float:
    """Vertical field of view (deg) for the configured horizontal one and square pixels."""
    return math.degrees(2.0 * math.atan(math.tan(math.radians(cam.hfov_deg) / 2.0) * cam.height / cam.width))


def intrinsics(cam: Camera) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) in pixels, OpenCV convention, no distortion."""
    f = (cam.height / 2.0) / math.tan(math.radians(vfov_deg(cam)) / 2.0)
    return f, f, cam.width / 2.0 + CX_OFFSET_PX, cam.height / 2.0 + CY_OFFSET_PX


def camera_matrix(cam: Camera) -> Mat:
    """(3, 3) OpenCV camera matrix K."""
    fx, fy, cx, cy = intrinsics(cam)
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])


def mount_transform(cam: Camera) -> Mat:
    """T_base_camera (4, 4): pose of the optical frame (z forward, x right, y down)
    in the robot base frame."""
    yaw, pitch = math.radians(cam.yaw_deg), math.radians(cam.pitch_deg)
    z = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), math.sin(pitch)])
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return transform(np.stack([x, y, z], axis=1), (cam.x_m, cam.y_m, cam.z_m))
