"""tagswarm.view.thumbnails: the camera thumbnail's overlay lands on the tags the renderer drew
(the scenario's own mast camera, pupil-apriltags as the judge; no network)."""

from __future__ import annotations

import base64
import math

import cv2
import numpy as np
import pybullet as pb
import pytest

from tagswarm.protocol import messages as m
from tagswarm.protocol.geometry import matrix_to_pose3, se2_matrix
from tagswarm.protocol.scenario import load_scenario
from tagswarm.view.thumbnails import camera_message, downscale, overlays
from tagswarm.world.render import Renderer, image_message
from tests.geometry_check import detector


@pytest.fixture(scope="module")
def scene():
    s = load_scenario("paper", ["robots.count=2", 'robots.placement="explicit"',
                                "robots.start=[{x_m=0.0, y_m=0.0}, {x_m=2.0, y_m=0.0}]",
                                'robot.cameras=[{name="front", width=640, height=480, hfov_deg=60, x_m=0.15, '
                                'z_m=0.6, pitch_deg=-15.0}]'])
    with Renderer(s) as r:
        yield s, r


def _observation(target: np.ndarray, tag_ids: tuple[int, ...], stamp_ns: int) -> m.RelativeObservation:
    return m.RelativeObservation(seq=0, stamp_ns=stamp_ns, robot_id=0, target_kind="robot", target_id=1,
                                 x_m=float(target[0, 3]), y_m=float(target[1, 3]), yaw_rad=0.0, cov=(0.0,) * 9,
                                 pose=matrix_to_pose3(target), reprojection_rms_px=0.2, tag_ids=tag_ids,
                                 camera="front")


@pytest.mark.parametrize(("x", "y", "yaw"), [(1.2, 0.1, math.pi + 0.5), (2.0, -0.3, math.pi - 0.8)])
def test_overlay_matches_the_detected_tag_corners(scene, x: float, y: float, yaw: float) -> None:
    s, r = scene
    cam = s.robot.cameras[0]
    r.set_pose(0, (0, 0, 0), (0, 0, 0, 1))
    r.set_pose(1, (x, y, 0), pb.getQuaternionFromEuler((0, 0, yaw)))
    frame = r.render(0, cam, se2_matrix(0, 0, 0))
    img = image_message(s, 0, cam, frame, seq=0, step=0, stamp_ns=7)
    dets = {d.tag_id: d.corners - 0.5 for d in detector().detect(frame)}  # AprilTag's +0.5 px convention
    assert dets, "the target should be in view"
    ob = _observation(se2_matrix(x, y, yaw), tuple(sorted(dets)), 7)

    (full,) = overlays(img, [ob], s, scale=1.0)
    assert {p["tag"] for p in full["polys"]} == set(dets)
    for p in full["polys"]:
        err = np.linalg.norm(np.array(p["uv"]) - dets[p["tag"]], axis=1)
        assert err.max() < 2.0, (p["tag"], err)
    assert full["range_m"] == pytest.approx(math.hypot(x, y), abs=0.01)

    # the thumbnail (half size) carries the same overlay in its own pixels
    msg = camera_message(img, [ob], s, max_width=320)
    assert (msg["width"], msg["height"], msg["source_size"]) == (320, 240, [640, 480])
    thumb = cv2.imdecode(np.frombuffer(base64.b64decode(msg["jpeg"]), np.uint8), cv2.IMREAD_GRAYSCALE)
    assert thumb.shape == (240, 320)
    for p in msg["detections"][0]["polys"]:
        expect = (dets[p["tag"]] + 0.5) * 0.5 - 0.5
        assert np.abs(np.array(p["uv"]) - expect).max() < 1.5


def test_tags_behind_the_camera_and_unknown_targets_are_not_drawn(scene) -> None:
    s, _renderer = scene
    cam = s.robot.cameras[0]
    frame = np.zeros((cam.height, cam.width), np.uint8)
    img = image_message(s, 0, cam, frame, seq=0, step=0, stamp_ns=1)
    behind = _observation(se2_matrix(-1.5, 0.0, 0.0), s.tag_ids(1), 1)
    ghost = behind.__class__(**{**{f: getattr(behind, f) for f in behind.__struct_fields__}, "target_id": 99})
    assert overlays(img, [behind, ghost], s) == []


def test_small_frames_are_not_upscaled() -> None:
    img = m.CameraImage(seq=0, stamp_ns=0, robot_id=0, camera="front", step=0, width=64, height=48, fx_px=50.0,
                        fy_px=50.0, cx_px=32.0, cy_px=23.0, mount=m.Pose3(x_m=0.0, y_m=0.0, z_m=0.0),
                        data=bytes(64 * 48))
    gray, scale = downscale(img, 320)
    assert gray.shape == (48, 64) and scale == 1.0
