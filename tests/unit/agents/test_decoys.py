"""Decoy posters (``[[decoys]]``): a poster carrying a robot's tag ID on a post is never taken
for that robot (the ground-robot gate rejects it and counts it), a tag of another family is
never decoded, and an ID nothing carries is detected and left to the caller to count."""

from __future__ import annotations

import math

import numpy as np
import pybullet as pb
import pytest

from tagswarm.agents.cubegeom import CameraModel
from tagswarm.agents.cubepose import CubePoseEstimator
from tagswarm.agents.detect import TagMap, make_detector
from tagswarm.protocol.geometry import se2_matrix
from tagswarm.protocol.layout import start_poses
from tagswarm.protocol.scenario import ScenarioError, load_scenario
from tagswarm.world.render import Renderer, image_message

BASE = ["robots.count=2", 'robots.placement="explicit"', "robots.start=[{x_m=0.0, y_m=0.0}, {x_m=-2.0, y_m=1.5}]"]
DECOYS = ('decoys=[{tag_id=11, x_m=2.0, y_m=-0.5, z_m=0.6, yaw_rad=3.1416}, '
          '{tag_id=3, family="tag16h5", x_m=2.0, y_m=0.5, z_m=0.45, yaw_rad=3.1416, size_m=0.15}, '
          '{tag_id=500, x_m=2.3, y_m=0.0, z_m=0.35, yaw_rad=3.1416}]')


@pytest.mark.parametrize("preset", ["ideal", "realistic"])
def test_posters_are_never_taken_for_robots(preset: str) -> None:
    s = load_scenario("paper", [*BASE, DECOYS, f"camera.preset={preset}"])
    cam = s.robot.cameras[0]
    with Renderer(s) as r:
        r.set_pose(0, (0, 0, 0), (0, 0, 0, 1))
        r.set_pose(1, (-2.0, 1.5, 0), (0, 0, 0, 1))  # behind the observer: only the decoys are in view
        msg = image_message(s, 0, cam, r.render(0, cam, se2_matrix(0, 0, 0)), seq=0, step=0, stamp_ns=0)
    img = np.frombuffer(msg.data, np.uint8).reshape(msg.height, msg.width)
    dets = make_detector(s.tags.family).detect(img)
    ids = {d.tag_id for d in dets}
    assert ids == {11, 500}, ids  # the tag16h5 poster is not decoded as anything
    tagmap = TagMap.from_scenario(s)
    assert tagmap.lookup(500) is None  # an ID nothing carries: the agent counts it as unknown_tags
    est = CubePoseEstimator(s)
    out = est.estimate([(CameraModel.from_message(msg), [d for d in dets if tagmap.lookup(d.tag_id)])])
    assert out == [], out  # robot 1's ID on a post 0.6 m up is not robot 1
    assert est.rejects["implausible"] == 1


def test_decoy_validation() -> None:
    with pytest.raises(ScenarioError, match=r"decoys\[0\].tag_id=40: tag16h5 has IDs 0..29"):
        load_scenario("paper", ['decoys=[{tag_id=40, family="tag16h5", x_m=1.0, y_m=0.0}]'])
    with pytest.raises(ScenarioError, match=r"decoys\[0\]: \(9.0, 0.0\) is outside the arena"):
        load_scenario("paper", ["decoys=[{tag_id=11, x_m=9.0, y_m=0.0}]"])
    with pytest.raises(ScenarioError, match=r"decoys\[0\]"):
        load_scenario("paper", ['decoys=[{tag_id=11, x_m=1.0, y_m=0.0, kind="box"}]'])
    assert math.isclose(load_scenario("paper", [DECOYS]).decoys[1].size_m, 0.15)


def test_a_poster_beside_its_robot_is_dropped_not_the_robot() -> None:
    """Robot 2's front tag on the wall behind robot 2: the ID shows twice in one image; the copy
    that fits as a robot on the floor is robot 2, the other is counted as a decoy."""
    s = load_scenario("paper", ["decoys=[{tag_id=21, x_m=3.4, y_m=0.5, z_m=0.6, yaw_rad=3.1416, size_m=0.3}]"])
    cam = s.robot.cameras[0]
    with Renderer(s) as r:
        for rid, (x, y, yaw) in zip(s.robot_ids, start_poses(s), strict=True):
            r.set_pose(rid, (x, y, 0), pb.getQuaternionFromEuler((0, 0, yaw)))
        x0, y0, yaw0 = start_poses(s)[0]
        observer = se2_matrix(x0, y0, yaw0)
        msg = image_message(s, 0, cam, r.render(0, cam, observer), seq=0, step=0, stamp_ns=0)
    img = np.frombuffer(msg.data, np.uint8).reshape(msg.height, msg.width)
    dets = make_detector(s.tags.family).detect(img)
    assert [d.tag_id for d in dets].count(21) == 2
    est = CubePoseEstimator(s)
    found = {e.target_id: e for e in est.estimate([(CameraModel.from_message(msg), dets)])}
    assert 2 in found and est.rejects == {"decoy": 1}
    x2, y2, _ = start_poses(s)[2]
    truth = np.linalg.inv(observer) @ se2_matrix(x2, y2, 0.0)
    assert math.hypot(found[2].x_m - truth[0, 3], found[2].y_m - truth[1, 3]) < 0.05
