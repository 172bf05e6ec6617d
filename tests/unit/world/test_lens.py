"""The rendered lenses are the published ones: true 3D tag corners projected through the
model a frame carries (``CameraImage.lens``/``distortion``/intrinsics) land on the
detected corners (median within 1 px), for the realistic 60 deg Brown-Conrady lens and a
120 deg equidistant fisheye, in the middle of the image and near its edge."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pybullet as pb
import pytest

from tagswarm.agents.cubegeom import CameraModel
from tagswarm.agents.detect import make_detector
from tagswarm.agents.lens import undistort_pixels
from tagswarm.protocol.geometry import pose3_to_matrix, se2_matrix
from tagswarm.protocol.scenario import ScenarioError, load_scenario
from tagswarm.world.lens import plan, project, undistort
from tagswarm.world.render import Renderer, image_message
from tests.geometry_check import tag_owner, world_corners

BASE = ["robots.count=2", 'robots.placement="explicit"', "robots.start=[{x_m=0.0, y_m=0.0}, {x_m=2.0, y_m=0.0}]",
        "camera.preset=realistic", "camera.exposure_ms=0.0"]
LENSES = {
    "brown_conrady_60": 'robot.cameras=[{name="front", width=640, height=480, hfov_deg=60, z_m=0.6, pitch_deg=-15.0}]',
    "fisheye_120": 'robot.cameras=[{name="front", width=640, height=480, hfov_deg=120, z_m=0.6, pitch_deg=-15.0}]',
}
# (lens, target x, y, yaw): in the middle and towards the edge of each image (bearing ~27 deg for the
# 60 deg lens, whose barrel distortion widens it; ~50 deg for the fisheye)
CASES = [
    ("brown_conrady_60", 1.5, 0.0, math.pi - 0.4),
    ("brown_conrady_60", 1.6, 0.8, math.pi + 0.5),
    ("brown_conrady_60", 1.4, -0.75, math.pi - 0.7),
    ("fisheye_120", 1.2, 0.0, math.pi + 0.3),
    ("fisheye_120", 0.9, 1.05, math.pi + 0.9),
    ("fisheye_120", 0.8, -1.0, math.pi - 1.0),
]


@pytest.fixture(scope="module")
def renderers():
    out = {}
    for name, cam in LENSES.items():
        s = load_scenario("paper", [*BASE, cam])
        out[name] = (s, Renderer(s))
    yield out
    for _, r in out.values():
        r.close()


@pytest.mark.parametrize(("lens", "x", "y", "yaw"), CASES)
def test_round_trip_through_published_model(renderers, lens: str, x: float, y: float, yaw: float) -> None:
    s, r = renderers[lens]
    cam = s.robot.cameras[0]
    observer, target = se2_matrix(0, 0, 0), se2_matrix(x, y, yaw)
    r.set_pose(0, (0, 0, 0), (0, 0, 0, 1))
    r.set_pose(1, (x, y, 0), pb.getQuaternionFromEuler((0, 0, yaw)))
    msg = image_message(s, 0, cam, r.render(0, cam, observer), seq=0, step=1, stamp_ns=0)
    assert msg.version == 2 and msg.lens == lens.rsplit("_", 1)[0]
    img = np.frombuffer(msg.data, np.uint8).reshape(msg.height, msg.width)
    dets = make_detector(s.tags.family).detect(img)
    owner = tag_owner(s)
    assert {owner[d.tag_id][0] for d in dets} == {1}
    k = np.array([[msg.fx_px, 0, msg.cx_px], [0, msg.fy_px, msg.cy_px], [0, 0, 1.0]])
    d_coef = np.array(msg.distortion).reshape(-1, 1)
    t_cw = np.linalg.inv(observer @ pose3_to_matrix(msg.mount))
    errs, edge = [], 0.0
    for d in dets:
        pts = world_corners(s, target, owner[d.tag_id][1])
        pc = (t_cw @ np.c_[pts, np.ones(4)].T).T[:, :3].reshape(-1, 1, 3)
        if msg.lens == "fisheye":
            uv = cv2.fisheye.projectPoints(pc, np.zeros(3), np.zeros(3), k, d_coef)[0].reshape(-1, 2)
        else:
            uv = cv2.projectPoints(pc, np.zeros(3), np.zeros(3), k, d_coef)[0].reshape(-1, 2)
        errs.extend(np.linalg.norm(d.corners - uv, axis=1))
        edge = max(edge, float(np.abs(d.corners[:, 0] - msg.cx_px).max()) / (msg.width / 2))
    print(lens, x, y, f"median {np.median(errs):.2f} max {max(errs):.2f} edge {edge:.2f}")
    assert dets and float(np.median(errs)) < 1.0, errs
    if abs(y) > 0.5:
        assert edge > 0.6, f"the case should reach towards the image edge ({edge:.2f} of the half-width)"


@pytest.mark.parametrize("lens", sorted(LENSES))
def test_lens_project_undistort_inverse(lens: str) -> None:
    """The world's maps and the agent's undistortion invert the model to 1e-6 px over the image."""
    s = load_scenario("paper", [*BASE, LENSES[lens]])
    p = plan(s.robot.cameras[0], s.camera.preset)
    u, v = np.meshgrid(np.linspace(0, 639, 17), np.linspace(0, 479, 13))
    pix = np.stack([u.ravel(), v.ravel()], axis=1)
    xy = undistort(pix, p.lens.model, p.lens.K, p.lens.D)
    back = project(np.c_[xy, np.ones(len(xy))], p.lens)
    assert np.abs(back - pix).max() < 1e-6
    cam = CameraModel("front", p.lens.K, np.eye(4), 640, 480, p.lens.model, p.lens.coeffs)
    ideal = undistort_pixels(pix, cam)
    assert np.allclose(ideal, xy @ p.lens.K[:2, :2].T + p.lens.K[:2, 2], atol=1e-6)
    # the render covers every ray of the image
    assert p.maps is not None and p.render_cam.width > 640 * 0.9


def test_lens_validation_errors() -> None:
    with pytest.raises(ScenarioError, match=r"distortion: lens 'brown_conrady' takes 5"):
        load_scenario("paper", ['robot.cameras=[{name="f", lens="brown_conrady", distortion=[0.1, 0.2]}]'])
    with pytest.raises(ScenarioError, match=r"fisheye of hfov_deg=160"):
        load_scenario("paper", ['robot.cameras=[{name="f", lens="fisheye", hfov_deg=160}]'])
    with pytest.raises(ScenarioError, match=r"camera.vignetting"):
        load_scenario("paper", ["camera.vignetting=1.5"])
    with pytest.raises(ScenarioError, match=r"camera.preset"):
        load_scenario("paper", ["camera.preset=fancy"])
