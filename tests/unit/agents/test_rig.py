"""The ``rig`` scenario (four 120 deg fisheye cameras per robot): a rig's cameras fire on the
same ticks (stamps), and a target straddling two of them is estimated from both at once,
through their lenses."""

from __future__ import annotations

import math

import numpy as np
import pybullet as pb

from tagswarm.agents.cubegeom import CameraModel
from tagswarm.agents.cubepose import CubePoseEstimator
from tagswarm.agents.detect import make_detector
from tagswarm.protocol.geometry import se2_matrix
from tagswarm.protocol.scenario import load_scenario
from tagswarm.world.node import due
from tagswarm.world.render import Renderer, image_message

S = load_scenario("rig", ["robots.count=2", 'robots.placement="explicit"',
                          "robots.start=[{x_m=0.0, y_m=0.0}, {x_m=0.8, y_m=0.8, yaw_rad=-2.36}]"])


def test_a_rigs_cameras_fire_together() -> None:
    """The world's phases (world/node.py: robot i of n at i/n of the period, a robot's cameras
    together): a rig fires all four cameras on one tick, the robots on different ticks."""
    assert [c.hfov_deg for c in S.robot.cameras] == [120.0] * 4 and S.render.stagger_cameras
    pairs = [(rid, cam, i / len(S.robot_ids)) for i, rid in enumerate(S.robot_ids) for cam in S.robot.cameras]
    ticks: dict[int, set[int]] = {rid: set() for rid in S.robot_ids}
    for step in range(1, 60):  # step 0: every sensor fires
        for robot in S.robot_ids:
            fired = {cam.name for rid, cam, ph in pairs if rid == robot and due(step, cam.rate_hz, S.clock.tick_hz, ph)}
            assert fired in (set(), {"front", "left", "rear", "right"}), (step, fired)
            if fired:
                ticks[robot].add(step)
    assert ticks[0] and ticks[1] and not ticks[0] & ticks[1], ticks


def test_target_straddling_two_fisheyes_uses_both() -> None:
    target = (0.8, 0.8, -2.36)  # 45 deg to the left, facing us: in the overlap of the front and left cameras
    with Renderer(S) as r:
        r.set_pose(0, (0, 0, 0), (0, 0, 0, 1))
        r.set_pose(1, (target[0], target[1], 0), pb.getQuaternionFromEuler((0, 0, target[2])))
        msgs = [image_message(S, 0, cam, r.render(0, cam, se2_matrix(0, 0, 0)), seq=0, step=3, stamp_ns=100)
                for cam in S.robot.cameras]
    assert {m.stamp_ns for m in msgs} == {100} and {m.lens for m in msgs} == {"fisheye"}
    det = make_detector(S.tags.family)
    views = []
    for m in msgs:
        dets = [d for d in det.detect(np.frombuffer(m.data, np.uint8).reshape(m.height, m.width)) if d.tag_id > 10]
        views.append((CameraModel.from_message(m), dets))
    seen = {v[0].name for v in views if v[1]}
    assert {"front", "left"} <= seen, seen
    (est,) = CubePoseEstimator(S).estimate(views)
    assert len(est.cameras) >= 2, est.cameras
    assert math.hypot(est.x_m - target[0], est.y_m - target[1]) < 0.05
    assert abs(math.remainder(est.yaw_rad - target[2], math.tau)) < math.radians(3)
