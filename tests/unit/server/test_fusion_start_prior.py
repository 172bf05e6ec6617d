"""Known start poses (``[server] start_prior_sigma``): each robot is in the map from its first
odometry at its start pose, a wrong start pose is corrected by the views, and with the option off
nothing changes (a robot waits for the views that link it to the origin)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from tagswarm.protocol.busconfig import BusConfig
from tagswarm.protocol.geometry import Pose2, se2_between, se2_compose
from tagswarm.protocol.scenario import load_scenario
from tagswarm.server.config import ServerConfig
from tagswarm.server.estimator import make_fusion, start_poses_in_map
from tagswarm.server.fusion import Fusion, FusionParams

DT_NS = 100_000_000  # 10 Hz
COV = np.diag([0.01**2, 0.01**2, 0.01**2])
TRUTH: dict[int, Pose2] = {0: (0.0, 0.0, 0.0), 1: (2.0, 1.0, math.pi), 2: (3.0, -1.5, 2.0)}


def _run(seconds: float, sigma: float, starts: dict[int, Pose2], sees: dict[int, tuple[int, ...]],
         from_s: float = 0.0) -> tuple[Fusion, dict[float, dict[int, Pose2 | None]]]:
    """Robots standing at TRUTH (the map frame is robot 0's pose); observations from ``from_s`` on.
    Returns the fusion and each instant's fused poses."""
    rng = np.random.default_rng(0)
    fusion = Fusion(replace(FusionParams(), start_prior_sigma=sigma), 0, tuple(TRUTH), start_poses=starts)
    seen: dict[float, dict[int, Pose2 | None]] = {}
    for k in range(int(seconds * 10) + 1):
        t_ns = k * DT_NS
        for rid in TRUTH:
            fusion.add_odometry(rid, t_ns, (0.0, 0.0, 0.0), 0.0)
        if t_ns >= from_s * 1e9:
            for obs, targets in sees.items():
                for tgt in targets:
                    rel = se2_between(TRUTH[obs], TRUTH[tgt])
                    fusion.add_observation(obs, tgt, t_ns, tuple(v + rng.normal(0, 0.01) for v in rel), COV)
        fusion.advance(t_ns)
        seen[t_ns / 1e9] = {rid: (None if (p := fusion.pose(rid)) is None else p[0]) for rid in TRUTH}
    return fusion, seen


def _err(p: Pose2 | None, rid: int) -> float:
    assert p is not None, f"robot {rid} not in the map"
    return math.dist(p[:2], TRUTH[rid][:2])


def test_every_robot_is_in_the_map_at_its_start_pose_from_its_first_odometry() -> None:
    # nobody sees anybody: only the start poses place the robots
    fusion, seen = _run(2.0, 0.02, dict(TRUTH), sees={})
    for t in (0.0, 2.0):
        for rid in TRUTH:
            assert _err(seen[t][rid], rid) < 1e-3, (t, rid)
    assert abs(seen[2.0][2][2] - TRUTH[2][2]) < 1e-3  # nobody's view turned it: the start heading
    _, cov = fusion.pose(1)  # type: ignore[misc]
    assert 0.015 < math.sqrt(cov[0, 0]) < 0.025  # the prior's sigma


def test_without_the_option_a_robot_waits_for_the_views_that_place_it() -> None:
    _, seen = _run(2.0, 0.0, dict(TRUTH), sees={0: (1, 2)}, from_s=1.0)
    assert seen[0.5][1] is None and seen[0.5][2] is None
    assert _err(seen[2.0][1], 1) < 0.03 and _err(seen[2.0][2], 2) < 0.03


def test_a_start_pose_given_a_metre_wrong_is_corrected_by_the_views() -> None:
    # the user wrote robot 1's start a metre off; the origin sees it where it really is
    wrong = dict(TRUTH)
    wrong[1] = se2_compose(TRUTH[1], (0.0, 1.0, 0.0))
    fusion, seen = _run(6.0, 0.02, wrong, sees={0: (1, 2), 2: (1,)}, from_s=1.0)
    assert _err(seen[0.9][1], 1) > 0.9  # on the written start until the first views
    assert _err(seen[6.0][1], 1) < 0.03
    assert _err(seen[6.0][2], 2) < 0.03  # the right one is not dragged along
    assert [e.robot_id for e in fusion.take_relocalisations()] == [1]


@pytest.mark.parametrize("landmarks", [False, True])
def test_start_poses_are_put_in_the_map_frame(landmarks: bool) -> None:
    over = ["server.start_prior_sigma=0.02", 'robots.placement="explicit"', "map.origin_id=1",
            "robots.start=[{x_m=-2.0, y_m=0.0, yaw_rad=0.0}, {x_m=1.0, y_m=1.0, yaw_rad=1.5707963}, "
            "{x_m=0.0, y_m=-2.0, yaw_rad=3.1415927}]", "robots.count=3", "missions=[]"]
    if landmarks:
        over.append("landmarks=[{id=500, x_m=3.4, y_m=0.0, yaw_rad=3.1415927}]")
    s = load_scenario("paper", over)
    poses = start_poses_in_map(s)
    if landmarks:  # the landmarks hold the map in the arena frame
        assert np.allclose(poses[0], (-2.0, 0.0, 0.0))
    else:  # the origin robot 1's start pose is the map frame
        assert np.allclose(poses[1], (0.0, 0.0, 0.0), atol=1e-6)
        assert np.allclose(poses[0], (-1.0, 3.0, -math.pi / 2), atol=1e-6)
        assert np.allclose(poses[2], (-3.0, 1.0, math.pi / 2), atol=1e-6)
    fusion = make_fusion(ServerConfig(scenario=s, bus=BusConfig()))
    assert fusion.p.start_prior_sigma == 0.02 and fusion.start_poses == poses
    assert make_fusion(ServerConfig(scenario=load_scenario("paper"), bus=BusConfig())).start_poses == {}


def test_a_start_pose_a_little_wrong_gives_way_to_the_views() -> None:
    # 15 cm off with a stated 2 cm: within the gate, so not a re-localisation; the prior is robust (Huber),
    # so the views win over the run (a Gaussian prior still held the robot 4.5 cm off after 20 s)
    wrong = dict(TRUTH)
    wrong[1] = se2_compose(TRUTH[1], (0.0, 0.15, 0.0))
    fusion, seen = _run(20.0, 0.02, wrong, sees={0: (1, 2), 2: (1,)}, from_s=1.0)
    assert _err(seen[0.9][1], 1) > 0.14
    assert _err(seen[20.0][1], 1) < 0.02
    assert _err(seen[20.0][2], 2) < 0.02
    assert fusion.counters["relocalisations"] == 0
