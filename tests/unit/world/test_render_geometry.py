"""Rendered tags decode to the right IDs, faces and pixel positions.

The reprojection check is what pins the published intrinsics: true 3D corners
projected with them must land on the detected corners (after AprilTag's +0.5 px
offset), median within 1 px.
"""

from __future__ import annotations

import math

import numpy as np
import pybullet as pb
import pytest

from tagswarm.protocol import tags
from tagswarm.protocol.geometry import se2_matrix
from tagswarm.protocol.layout import start_poses
from tagswarm.protocol.scenario import load_scenario
from tagswarm.world import camera
from tagswarm.world.assets import face_image
from tagswarm.world.render import Renderer
from tests.geometry_check import detector, facing, project, tag_owner, world_corners


def test_painted_tag_corner_order_matches_contract() -> None:
    img = np.pad(face_image("tag36h11", 5, 0.2, 0.16), 20, constant_values=255)
    (det,) = detector().detect(img)
    assert det.tag_id == 5
    c = det.corners - 0.5
    # top-right, top-left, bottom-left, bottom-right in image coordinates (y down)
    assert c[0, 0] > c[1, 0] and c[0, 1] < c[3, 1]
    assert c[2, 0] < c[3, 0] and c[2, 1] > c[1, 1]


@pytest.fixture(scope="module")
def scene():
    s = load_scenario("paper", ['robot.cameras=[{name="front", width=640, height=480, hfov_deg=60, z_m=0.22, '
                                'pitch_deg=0.0}]',
                                "robots.count=2", 'robots.placement="explicit"',
                                "robots.start=[{x_m=0.0, y_m=0.0}, {x_m=2.0, y_m=0.0}]"])
    with Renderer(s) as r:
        yield s, r


def test_the_temporary_assets_are_gone_once_the_scene_is_built(scene) -> None:
    # a render worker SIGKILLed at a run's end left its folder in /tmp; the tags below still decode without it
    _, r = scene
    assert r.asset_dir.name.startswith("tagswarm-assets-") and not r.asset_dir.exists()


CASES = [  # target (x, y, yaw) relative to the observer at the origin
    (0.8, 0.0, math.pi),
    (1.0, 0.15, math.pi + 0.6),
    (1.5, -0.3, math.pi - 0.9),
    (2.0, 0.4, math.pi / 2 + 0.4),
    (2.5, -0.2, 0.3),
    (3.0, 0.0, math.pi + 0.3),
]


@pytest.mark.parametrize(("x", "y", "yaw"), CASES)
def test_detected_ids_faces_and_reprojection(scene, x: float, y: float, yaw: float) -> None:
    s, r = scene
    cam = s.robot.cameras[0]
    observer, target = se2_matrix(0, 0, 0), se2_matrix(x, y, yaw)
    r.set_pose(0, (0, 0, 0), (0, 0, 0, 1))
    r.set_pose(1, (x, y, 0), pb.getQuaternionFromEuler((0, 0, yaw)))
    img = r.render(0, cam, observer)
    assert img.shape == (480, 640) and img.dtype == np.uint8
    dets = detector().detect(img)
    owner = tag_owner(s)
    seen = {owner[d.tag_id] for d in dets}
    assert {rid for rid, _ in seen} == {1}, f"saw {seen}"
    t_wc = observer @ camera.mount_transform(cam)
    must, may = facing(t_wc, target)
    assert must, "every case should squarely show at least one face"
    faces = {f for _, f in seen}
    assert must <= faces <= may, (faces, must, may)
    errs = []
    for d in dets:
        uv = project(camera.intrinsics(cam), t_wc, world_corners(s, target, owner[d.tag_id][1]))
        errs.extend(np.linalg.norm(d.corners - 0.5 - uv, axis=1))
    assert float(np.median(errs)) < 1.0, errs
    assert max(errs) < 2.5, errs


def test_principal_point_fit(scene) -> None:
    """Least-squares principal point from many corners agrees with intrinsics()."""
    s, r = scene
    cam = s.robot.cameras[0]
    fx, fy, cx, cy = camera.intrinsics(cam)
    res = []
    for x, y, yaw in CASES:
        target = se2_matrix(x, y, yaw)
        r.set_pose(1, (x, y, 0), pb.getQuaternionFromEuler((0, 0, yaw)))
        t_wc = se2_matrix(0, 0, 0) @ camera.mount_transform(cam)
        for d in detector().detect(r.render(0, cam, se2_matrix(0, 0, 0))):
            uv = project((fx, fy, cx, cy), t_wc, world_corners(s, target, tag_owner(s)[d.tag_id][1]))
            res.append(d.corners - 0.5 - uv)
    mean = np.concatenate(res).mean(axis=0)
    assert abs(mean[0]) < 0.35 and abs(mean[1]) < 0.35, f"principal point is off by {mean} px"


def test_landmark_and_tag16h5_cubes_decode() -> None:
    s = load_scenario("paper", ['tags.family="tag16h5"', "tags.id_base=0", "tags.id_stride=6", "tags.size_m=0.15",
                                "robots.count=2",
                                'robots.placement="explicit"', "robots.start=[{x_m=0.0, y_m=0.0}, {x_m=1.2, y_m=0.0}]",
                                "landmarks=[{id=20, x_m=1.5, y_m=0.6, z_m=0.25, yaw_rad=3.1416, size_m=0.16}]",
                                'robot.cameras=[{name="front", width=640, height=480, z_m=0.22, pitch_deg=0.0}]'])
    with Renderer(s) as r:
        r.set_pose(0, (0, 0, 0), (0, 0, 0, 1))
        r.set_pose(1, (1.2, 0, 0), pb.getQuaternionFromEuler((0, 0, math.pi)))
        ids = {d.tag_id for d in detector("tag16h5").detect(r.render(0, s.robot.cameras[0], se2_matrix(0, 0, 0)))}
    assert ids == {s.tag_ids(1)[tags.Face.FRONT], 20}


class _WholeBoxes(Renderer):
    """The scene with every static box drawn whole, as before the walls were cut in pieces."""

    def _box(self, half: tuple[float, float, float], pos: tuple[float, float, float], yaw: float,
             rgba: tuple[float, ...]) -> None:
        vis = pb.createVisualShape(pb.GEOM_BOX, halfExtents=half, rgbaColor=rgba, physicsClientId=self.cid)
        pb.createMultiBody(baseMass=0, baseVisualShapeIndex=vis, basePosition=pos,
                           baseOrientation=pb.getQuaternionFromEuler((0, 0, yaw)), physicsClientId=self.cid)


@pytest.mark.parametrize("extra", [[], ["render.floor=true"]])
def test_walls_in_pieces_render_the_same_pixels(extra: list[str]) -> None:
    """Walls (and floor, obstacles) are drawn in 1 m pieces because that is ~1.8x cheaper
    (bench/render.py); the images must not change by a single grey level."""
    s = load_scenario("paper", ["robots.count=8", 'robots.placement="grid"', *extra,
                                'robot.cameras=[{name="front", width=320, height=240, hfov_deg=60}]'])
    poses = start_poses(s)
    frames = []
    for cls in (_WholeBoxes, Renderer):
        with cls(s) as r:
            for rid, (x, y, yaw) in zip(s.robot_ids, poses, strict=True):
                r.set_pose(rid, (x, y, 0.0), pb.getQuaternionFromEuler((0, 0, yaw)))
            # every robot's view, and one from the corner looking along two walls
            views = [se2_matrix(*p) for p in poses] + [se2_matrix(3.2, 3.2, -2.4)]
            frames.append([r.render(rid % 8, s.robot.cameras[0], b) for rid, b in enumerate(views)])
    for whole, pieces in zip(*frames, strict=True):
        assert (whole < 200).mean() > 0.02  # something in view besides the white background
        assert np.array_equal(whole, pieces)
