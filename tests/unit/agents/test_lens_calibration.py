"""The agent's lens handling: corners of a distorted lens are undistorted before the pose
is solved (exact corners give the exact pose), and the calibration error it may be handed
is seeded per robot and camera with the configured spread."""

from __future__ import annotations

import math

import cv2
import msgspec
import numpy as np
import pytest

from tagswarm.agents.cubegeom import CameraModel
from tagswarm.agents.cubepose import CubePoseEstimator
from tagswarm.agents.detect import TagDetection
from tagswarm.agents.lens import LensCorrector, perturbed
from tagswarm.protocol.geometry import se2_matrix
from tagswarm.protocol.scenario import CalibrationError, load_scenario
from tagswarm.protocol.scenario_schema import REALISTIC_BROWN_CONRADY, REALISTIC_FISHEYE
from tagswarm.world.camera import mount_transform
from tagswarm.world.lens import lens_for

S = load_scenario("paper", ["camera.preset=realistic"])


def _view(lens: str, hfov: float, target: tuple[float, float, float], robot_id: int = 0) -> tuple[
        CameraModel, list[TagDetection]]:
    """A camera of the paper robot and the exact (distorted) corners of robot 1's visible tags."""
    cam = msgspec.structs.replace(S.robot.cameras[0], width=640, height=480, hfov_deg=hfov)
    true = lens_for(cam, "realistic")
    assert true.model == lens
    t_bc = mount_transform(cam)
    est = CubePoseEstimator(S)
    t_cam_target = np.linalg.inv(t_bc) @ se2_matrix(*target)
    dets = []
    for tid in S.tag_ids(1):
        obj = est.object_points(tid)
        assert obj is not None
        pc = (t_cam_target @ np.c_[obj, np.ones(4)].T).T[:, :3]
        normal_ok = np.cross(pc[1] - pc[0], pc[2] - pc[0]) @ pc.mean(axis=0) < 0
        if (pc[:, 2] < 0.1).any() or not normal_ok:
            continue
        pts = pc.reshape(-1, 1, 3)
        if lens == "fisheye":
            uv = cv2.fisheye.projectPoints(pts, np.zeros(3), np.zeros(3), true.K, true.D)[0]
        else:
            uv = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), true.K, true.D)[0]
        uv = uv.reshape(4, 2)
        if (uv < 0).any() or (uv[:, 0] > 639).any() or (uv[:, 1] > 479).any():
            continue
        dets.append(TagDetection(tid, uv, 0, 100.0))
    model = CameraModel("front", true.K, t_bc, 640, 480, true.model, true.coeffs, robot_id)
    return model, dets


@pytest.mark.parametrize(("lens", "hfov", "target"), [
    ("brown_conrady", 60.0, (2.0, 0.0, math.pi - 0.5)),
    ("brown_conrady", 60.0, (1.6, 0.85, math.pi + 0.4)),  # near the image edge, where distortion is largest
    ("fisheye", 120.0, (1.0, 1.1, math.pi + 0.9)),
])
def test_distorted_corners_give_the_true_pose(lens: str, hfov: float, target: tuple[float, float, float]) -> None:
    cam, dets = _view(lens, hfov, target)
    assert dets
    (est,) = CubePoseEstimator(S).estimate([(cam, dets)])
    assert math.hypot(est.x_m - target[0], est.y_m - target[1]) < 1e-3
    assert abs(math.remainder(est.yaw_rad - target[2], math.tau)) < 1e-3
    # towards the edge, the same corners taken for a pinhole's are off by centimetres: the undistortion matters
    if abs(target[1]) > 0.5:
        pin = CameraModel("front", cam.K, cam.T_base_cam, 640, 480)
        ests = CubePoseEstimator(S, max_rms_px=50.0).estimate([(pin, dets)])
        assert not ests or math.hypot(ests[0].x_m - target[0], ests[0].y_m - target[1]) > 0.01


def test_calibration_error_is_seeded_per_robot_and_camera() -> None:
    err = CalibrationError(focal_rel=0.02, center_px=3.0, distortion_rel=0.1, extrinsic_deg=1.0, extrinsic_m=0.01)
    k = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    base = [CameraModel(name, k, np.eye(4), 320, 240, "brown_conrady", REALISTIC_BROWN_CONRADY, rid)
            for rid in range(300) for name in ("front", "back")]
    cals = [perturbed(c, err, seed=4) for c in base]
    again = [perturbed(c, err, seed=4) for c in base[:10]]
    for a, b in zip(again, cals[:10], strict=True):
        assert np.array_equal(a.K, b.K) and np.array_equal(a.T_base_cam, b.T_base_cam)
    assert not np.array_equal(cals[0].K, cals[1].K) and not np.array_equal(cals[0].K, cals[2].K)
    assert not np.array_equal(perturbed(base[0], err, seed=5).K, cals[0].K)
    focal = np.array([c.K[0, 0] / 300.0 - 1 for c in cals])
    centre = np.array([c.K[0, 2] - 160 for c in cals])
    dist = np.array([c.distortion[0] / REALISTIC_BROWN_CONRADY[0] - 1 for c in cals])
    angle = np.array([np.degrees(np.linalg.norm(cv2.Rodrigues(c.T_base_cam[:3, :3])[0])) for c in cals])
    shift = np.array([c.T_base_cam[:3, 3] for c in cals]).ravel()
    assert focal.std() == pytest.approx(0.02, rel=0.15)
    assert centre.std() == pytest.approx(3.0, rel=0.15)
    assert dist.std() == pytest.approx(0.1, rel=0.15)
    assert np.sqrt((angle**2).mean()) == pytest.approx(1.0, rel=0.15)
    assert shift.std() == pytest.approx(0.01, rel=0.15)
    # no error: the published calibration itself
    assert perturbed(base[0], CalibrationError(), seed=4) is base[0]


def test_calibration_error_costs_accuracy() -> None:
    """A bad extrinsic calibration shows up in the estimate (the world still renders the truth)."""
    target = (2.0, 0.3, math.pi - 0.3)
    cam, dets = _view("brown_conrady", 60.0, target, robot_id=1)
    errors = []
    for deg in (0.0, 1.0, 3.0):
        est = CubePoseEstimator(S, max_rms_px=50.0)
        est.lens = LensCorrector(CalibrationError(extrinsic_deg=deg), seed=2)
        (e,) = est.estimate([(cam, dets)])
        errors.append(math.hypot(e.x_m - target[0], e.y_m - target[1]) + abs(math.remainder(e.yaw_rad - target[2],
                                                                                             math.tau)))
    assert errors[0] < 2e-3 < errors[1] < errors[2], errors


def test_fisheye_preset_coefficients_are_published() -> None:
    s = load_scenario("paper", ["camera.preset=realistic", "robot.cameras=[{name='f', hfov_deg=120.0}]"])
    lens = lens_for(s.robot.cameras[0], "realistic")
    assert lens.model == "fisheye" and lens.coeffs == REALISTIC_FISHEYE
    assert lens.K[0, 0] == pytest.approx(160.0 / math.radians(60.0))
