"""The agent's view of its cameras' lenses: the calibration it believes, and corners moved
onto the ideal pinhole of that calibration before any pose is solved (pure code).

A frame arrives with its camera's true lens (``CameraImage.lens``/``distortion``,
intrinsics and mount).  The agent may be handed a wrong calibration on purpose
(``[camera.calibration_error]``, docs/camera.md): each camera's error is drawn once,
seeded by (scenario seed, robot, camera), so a run repeats and two robots' errors
differ.  Detected corners (OpenCV pixel convention) are then undistorted with the
believed model (``cv2.undistortPoints`` / ``cv2.fisheye.undistortPoints``) onto the
pinhole with the believed ``K``, which is what :mod:`tagswarm.agents.cubepose` solves on.
A pinhole with no calibration error passes through untouched.  :func:`corner_sigma_px` is the
corner noise the agent expects of its cameras (what its covariances are built on).
"""

from __future__ import annotations

import math
import zlib
from dataclasses import replace
from typing import Final

import cv2
import numpy as np
from numpy.typing import NDArray

from tagswarm.agents.cubegeom import CameraModel
from tagswarm.agents.detect import TagDetection
from tagswarm.protocol.scenario import CalibrationError, Scenario

#: corner noise (px, 1 sigma) per DN of image noise at mid-grey over the contrast: read noise 8-20 DN
#: widened the corners' scatter about the projected truth from 0.23 to 0.24-0.26 px (320x240 60 deg,
#: tags 1-3.5 m; docs/camera.md, Covariance)
CORNER_PX_PER_NOISE_DN: Final = 0.006
#: corner noise (px, 1 sigma) per pixel of motion-blur streak: a 7 px streak (20 ms at 1.2 rad/s)
#: widened the scatter from 0.25 to 0.59 px; a blur is symmetric about the mid-exposure edge, so
#: the detector's line fit moves far less than the streak's length
CORNER_PX_PER_STREAK_PX: Final = 0.08


def corner_sigma_px(scenario: Scenario, render_sigma_px: float) -> float:
    """Corner noise (px, 1 sigma per axis) of the scenario's cameras: the render's own
    ``render_sigma_px`` (aliasing) and, from the ``[camera]`` section, image noise (read and
    shot noise at mid-grey, over the contrast) and motion blur (the streak of the agent's
    fastest turn, ``agent.max_turn_rad_s``, during the exposure at the largest focal length),
    added in quadrature.  The ideal camera gives ``render_sigma_px`` itself."""
    c = scenario.camera.resolved()
    e = c.electrons_per_dn or 0.0
    noise_dn = math.sqrt((c.read_noise_dn or 0.0) ** 2 + (128.0 / e if e else 0.0)) / (c.contrast or 1.0)
    # the equidistant focal length bounds the pinhole one (theta >= tan theta): the larger streak
    f_px = max((cam.width / 2.0) / math.radians(cam.hfov_deg / 2.0) for cam in scenario.robot.cameras)
    streak_px = (c.exposure_ms or 0.0) * 1e-3 * scenario.agent.max_turn_rad_s * f_px
    return math.sqrt(render_sigma_px**2 + (CORNER_PX_PER_NOISE_DN * noise_dn) ** 2
                     + (CORNER_PX_PER_STREAK_PX * streak_px) ** 2)


_CRITERIA: Final = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
# mixed into the calibration error's seed so it never repeats a world-side random stream
_CALIBRATION_STREAM: Final = 0xCA1B


def perturbed(cam: CameraModel, err: CalibrationError, seed: int) -> CameraModel:
    """``cam`` as a calibration with error ``err`` would give it: fx, fy scaled by 1 + N(0,
    focal_rel), cx, cy moved by N(0, center_px), each distortion coefficient scaled by
    1 + N(0, distortion_rel), the mount rotated by N(0, extrinsic_deg) about a random axis and
    moved by N(0, extrinsic_m) per axis.  Drawn from (seed, robot, camera) only."""
    if not (err.focal_rel or err.center_px or err.distortion_rel or err.extrinsic_deg or err.extrinsic_m):
        return cam
    rng = np.random.default_rng([seed, max(cam.robot_id, 0), zlib.crc32(cam.name.encode()), _CALIBRATION_STREAM])
    k = cam.K.copy()
    k[0, 0] *= 1.0 + rng.normal(0.0, err.focal_rel)
    k[1, 1] *= 1.0 + rng.normal(0.0, err.focal_rel)
    k[0, 2] += rng.normal(0.0, err.center_px)
    k[1, 2] += rng.normal(0.0, err.center_px)
    dist = tuple(float(c * (1.0 + rng.normal(0.0, err.distortion_rel))) for c in cam.distortion)
    axis = rng.normal(size=3)
    axis /= max(float(np.linalg.norm(axis)), 1e-12)
    angle = math.radians(rng.normal(0.0, err.extrinsic_deg))
    t = cam.T_base_cam.copy()
    t[:3, :3] = cv2.Rodrigues((axis * angle).reshape(3, 1))[0] @ t[:3, :3]
    t[:3, 3] += rng.normal(0.0, err.extrinsic_m, 3)
    return replace(cam, K=k, T_base_cam=t, distortion=dist)


def undistort_pixels(pixels: NDArray[np.float64], cam: CameraModel) -> NDArray[np.float64]:
    """Pixels (N, 2) of ``cam``'s lens moved onto its ideal pinhole (same ``K``)."""
    if cam.lens == "pinhole" or not any(cam.distortion):
        return pixels
    pts = np.ascontiguousarray(pixels, np.float64).reshape(-1, 1, 2)
    d = np.array(cam.distortion, np.float64).reshape(-1, 1)
    if cam.lens == "fisheye":
        out = cv2.fisheye.undistortPoints(pts, cam.K, d, R=np.eye(3), P=cam.K, criteria=_CRITERIA)
    else:
        out = cv2.undistortPointsIter(pts, cam.K, d, np.eye(3), cam.K, _CRITERIA)
    return np.asarray(out, np.float64).reshape(-1, 2)


class LensCorrector:
    """Turns each (camera, detections) of a frame into its pinhole equivalent, with the
    calibration the agent believes (cached per robot and camera)."""

    def __init__(self, calibration_error: CalibrationError, seed: int) -> None:
        self.err = calibration_error
        self.seed = seed
        self._believed: dict[tuple[int, str, str, tuple[float, ...], bytes, bytes], CameraModel] = {}

    def believed(self, cam: CameraModel) -> CameraModel:
        """The calibration of ``cam`` the agent works with (its true one perturbed)."""
        key = (cam.robot_id, cam.name, cam.lens, cam.distortion, cam.K.tobytes(), cam.T_base_cam.tobytes())
        out = self._believed.get(key)
        if out is None:
            out = self._believed[key] = perturbed(cam, self.err, self.seed)
        return out

    def prepare(self, cam: CameraModel, dets: list[TagDetection]) -> tuple[CameraModel, list[TagDetection]]:
        """The pinhole camera and undistorted detections of one frame."""
        cal = self.believed(cam)
        if cal.lens == "pinhole" or not any(cal.distortion):
            return cal, dets
        if not dets:
            return replace(cal, lens="pinhole", distortion=()), dets
        flat = undistort_pixels(np.concatenate([d.corners for d in dets]), cal)
        out = [TagDetection(d.tag_id, flat[4 * i:4 * i + 4], d.hamming, d.margin) for i, d in enumerate(dets)]
        return replace(cal, lens="pinhole", distortion=()), out
