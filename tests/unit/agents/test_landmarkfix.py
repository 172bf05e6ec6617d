"""Self-localisation from all landmark tags jointly (agents/landmarkfix.py): synthetic corners
projected from a known pose through two cameras' extrinsics give that pose back (1 mm, 0.1 deg);
the covariance shrinks as more tags come into view; the joint fix replaces the per-tag ones."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from tagswarm.agents.cubegeom import CameraModel, PoseEstimate
from tagswarm.agents.landmarkfix import Sighting, _project, as_estimate, joint_fix, landmark_corners, solve
from tagswarm.protocol.geometry import Pose2, se2_between

H = 0.08
OBJ = np.array([[0.0025, -H, H], [0.0025, H, H], [0.0025, H, -H], [0.0025, -H, -H]])  # plate's +x face
K = np.array([[400.0, 0.0, 320.0], [0.0, 400.0, 240.0], [0.0, 0.0, 1.0]])


def camera(name: str, yaw: float) -> CameraModel:
    # optical frame: z along the base's heading + yaw, x to its right, y down
    c, s = math.cos(yaw), math.sin(yaw)
    fwd, left, up = np.array([c, s, 0.0]), np.array([-s, c, 0.0]), np.array([0.0, 0.0, 1.0])
    t = np.eye(4)
    t[:3, :3] = np.stack([-left, -up, fwd], axis=1)
    t[:3, 3] = [0.05 * c, 0.05 * s, 0.15]
    return CameraModel(name=name, K=K, T_base_cam=t, width=640, height=480)


FRONT, BACK = camera("front", 0.0), camera("back", math.pi)
# tag id -> (x, y, yaw), all at 0.25 m, facing the robot near the origin
LANDMARKS: dict[int, Pose2] = {100: (3.0, 0.6, math.pi), 101: (3.0, -0.8, math.pi), 102: (-2.5, 0.3, 0.0),
                               103: (3.2, 0.0, math.pi)}
TRUTH: Pose2 = (0.3, -0.2, 0.1)


def sightings(ids: list[int], pose: Pose2 = TRUTH, noise_px: float = 0.0, seed: int = 0) -> list[Sighting]:
    rng = np.random.default_rng(seed)
    out = []
    for tid in ids:
        x, y, yaw = LANDMARKS[tid]
        world = landmark_corners(x, y, 0.25, yaw, OBJ)
        cam = FRONT if abs(math.remainder(yaw - math.pi, math.tau)) < 1 else BACK
        sg = Sighting(cam, tid, np.zeros((4, 2)), world)
        px = _project(pose, [sg]) + rng.normal(0.0, noise_px, (4, 2))
        assert np.all(np.isfinite(px)) and np.all((px > 0) & (px < [640, 480]))  # really in view
        out.append(Sighting(cam, tid, px, world))
    return out


@pytest.mark.parametrize("ids", [[100], [100, 101], [100, 101, 102], [100, 101, 102, 103]])
def test_exact_corners_give_the_pose_back(ids: list[int]) -> None:
    fix = solve(sightings(ids), (TRUTH[0] + 0.15, TRUTH[1] - 0.1, TRUTH[2] + 0.08))
    assert fix is not None
    assert math.dist(fix.pose[:2], TRUTH[:2]) < 1e-3
    assert abs(math.degrees(fix.pose[2] - TRUTH[2])) < 0.1
    assert fix.tag_ids == tuple(ids) and fix.n_corners == 4 * len(ids) and fix.rms_px < 1e-3
    assert set(fix.cameras) == ({"front", "back"} if 102 in ids else {"front"})


def test_covariance_shrinks_with_more_tags() -> None:
    traces = []
    for ids in ([100], [100, 101], [100, 101, 102], [100, 101, 102, 103]):
        fix = solve(sightings(ids), TRUTH)
        assert fix is not None
        traces.append(float(fix.cov[0, 0] + fix.cov[1, 1]))
    assert all(a > b for a, b in itertools.pairwise(traces)), traces
    assert traces[0] > 4 * traces[-1]


def test_covariance_matches_the_scatter_under_pixel_noise() -> None:
    ids = [100, 101, 102]
    errs = []
    for seed in range(200):
        fix = solve(sightings(ids, noise_px=0.5, seed=seed), TRUTH, pixel_sigma_px=0.5)
        assert fix is not None
        errs.append(np.subtract(fix.pose, TRUTH))
    ref = solve(sightings(ids), TRUTH, pixel_sigma_px=0.5)
    assert ref is not None
    sample = np.cov(np.array(errs).T)
    assert np.allclose(np.diag(sample), np.diag(ref.cov), rtol=0.3)


def test_joint_fix_replaces_per_tag_estimates_and_is_an_observation_of_the_reference() -> None:
    sg = sightings([101, 100, 102])

    class Det:
        def __init__(self, tag_id: int, corners: np.ndarray) -> None:
            self.tag_id, self.corners = tag_id, corners

    views = [(FRONT, [Det(s.tag_id, s.corners) for s in sg if s.cam is FRONT]),
             (BACK, [Det(s.tag_id, s.corners) for s in sg if s.cam is BACK])]
    rough = se2_between((TRUTH[0] + 0.05, TRUTH[1], TRUTH[2]), LANDMARKS[100])
    per_tag = PoseEstimate(target_kind="landmark", target_id=100, T_base_target=np.eye(4), x_m=rough[0],
                           y_m=rough[1], yaw_rad=rough[2], cov=np.eye(3) * 1e-2, reprojection_rms_px=1.0,
                           tag_ids=(100,), cameras=("front",), n_corners=4)
    robot = PoseEstimate(target_kind="robot", target_id=1, T_base_target=np.eye(4), x_m=1.0, y_m=0.0, yaw_rad=0.0,
                         cov=np.eye(3) * 1e-3, reprojection_rms_px=1.0, tag_ids=(3,), cameras=("front",), n_corners=4)
    lms = {tid: (p, 0.25, OBJ) for tid, p in LANDMARKS.items()}
    out = joint_fix([per_tag, robot], views, lms, pixel_sigma_px=1.0)
    assert [e.target_kind for e in out] == ["robot", "landmark"]
    joint = out[1]
    assert joint.target_id == 100 and joint.tag_ids == (100, 101, 102) and joint.n_corners == 12
    want = se2_between(TRUTH, LANDMARKS[100])
    assert math.dist((joint.x_m, joint.y_m), want[:2]) < 1e-3 and abs(joint.yaw_rad - want[2]) < 1e-3
    assert np.all(np.linalg.eigvalsh(joint.cov) > 0)
    # one landmark in view: the per-tag estimate stays as it is
    one = joint_fix([per_tag], [(FRONT, [Det(sg[1].tag_id, sg[1].corners)])], lms, pixel_sigma_px=1.0)
    assert one == [per_tag]


def test_as_estimate_moves_the_covariance_onto_the_landmark() -> None:
    fix = solve(sightings([100, 101]), TRUTH)
    assert fix is not None
    est = as_estimate(fix, 100, LANDMARKS[100], 0.25)
    assert est.T_base_target[2, 3] == 0.25
    # against sampling the robot's pose from the fix's covariance
    rng = np.random.default_rng(1)
    samples = [se2_between(tuple(p), LANDMARKS[100]) for p in rng.multivariate_normal(fix.pose, fix.cov, 4000)]
    rel = np.array(samples)
    rel[:, 2] = np.remainder(rel[:, 2] - est.yaw_rad + math.pi, math.tau) - math.pi
    assert np.allclose(np.diag(np.cov(rel.T)), np.diag(est.cov), rtol=0.15)


def test_no_sightings_no_fix() -> None:
    assert solve([], TRUTH) is None
