"""Single cube faces seen almost square-on, 2-3.5 m away, by the paper scenario's camera.

The paper scenario's camera (320x240, 60 deg HFOV, 0.6 m up, pitched -15 deg) sees a
face of a cube 2-3.5 m away as a ~10-20 px square: the worst case for the yaw (the
two-fold ambiguity of a small square; the foreshortening that gives the yaw barely
visible).  Rendered views of robot 0's cube from robot 1 in the paper arena (walls,
floor) check that the covariance does not claim a yaw the pixels cannot give.

Measured on the 144 views of the test below (off square-on by up to 25 deg): planar
yaw error p90 5.3 deg, claimed yaw sigma median 10 deg; yaw NEES mean 0.14, none
beyond 3 sigma; (x, y, yaw) NEES mean 0.87 (on 381 views in an open arena: 0.16 and
0.82).  The covariance errs on the safe side here: the ambiguity term weighs the
mirrored pose (~20 deg of yaw away) at ~0.25 in the median, and even without it the
yaw NEES is 0.4.  The 6-DOF fit (``planar=False``) of the same views would fail the
test: yaw NEES 1.5 with 5.6% of the errors beyond 3 sigma.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.typing import NDArray

from tagswarm.agents.cubepose import CameraModel, CubePoseEstimator
from tagswarm.agents.detect import AprilTagDetector
from tagswarm.protocol import tags
from tagswarm.protocol.geometry import se2_matrix, wrap_angle, yaw_quat
from tagswarm.protocol.scenario import load_scenario
from tagswarm.world.render import Renderer, image_message

S = load_scenario("paper")
CAM = S.robot.cameras[0]
TARGET = (-1.5, 0.0)  # robot 0's start: the origin robot the others look at
SIDES = [tags.Face.FRONT, tags.Face.BACK, tags.Face.LEFT, tags.Face.RIGHT]


def test_the_scenario_is_the_hard_case() -> None:
    assert (CAM.width, CAM.height, CAM.hfov_deg) == (320, 240, 60.0)
    assert CAM.z_m - S.robot.cube_center_z_m > 0.3 and CAM.pitch_deg < 0


def _model() -> CameraModel:
    img = np.zeros((CAM.height, CAM.width), np.uint8)
    return CameraModel.from_message(image_message(S, 1, CAM, img, seq=0, step=0, stamp_ns=0))


def _errors(est: CubePoseEstimator, r: Renderer, det: AprilTagDetector, observer: tuple[float, float, float],
            target_yaw: float) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """(x, y, yaw) error of the estimate of robot 0 (at TARGET, ``target_yaw``) from robot 1 at
    ``observer`` (map frame), and its claimed covariance; None unless exactly one face decodes
    and the estimator answers."""
    r.set_pose(0, (*TARGET, 0.0), yaw_quat(target_yaw))
    t_obs = se2_matrix(*observer)
    dets = det.detect(r.render(1, CAM, t_obs))
    if len(dets) != 1:
        return None
    ests = est.estimate([(_model(), dets)])
    if not ests:
        return None
    (e,) = ests
    truth = np.linalg.inv(t_obs) @ se2_matrix(*TARGET, target_yaw)
    err = np.array([e.x_m - truth[0, 3], e.y_m - truth[1, 3], wrap_angle(e.yaw_rad - math.atan2(truth[1, 0],
                                                                                                 truth[0, 0]))])
    return err, e.cov


@pytest.fixture(scope="module")
def scene():
    with Renderer(S) as r:
        for rid in S.robot_ids:
            r.set_pose(rid, (0.0, 0.0, -10.0), (0, 0, 0, 1))  # out of the way until placed
        yield r, AprilTagDetector(S.tags.family)


def test_the_paper_run_start_view(scene) -> None:
    """Robot 1's first view of robot 0 in the paper scenario (2.85 m, 18 deg off square-on):
    the lockstep seed-3 run saw a 3.3 deg yaw error here; the claimed yaw sigma covers it."""
    r, det = scene
    out = _errors(CubePoseEstimator(S), r, det, (1.2, 0.9, math.pi), 0.0)
    assert out is not None
    err, cov = out
    assert math.hypot(err[0], err[1]) < 0.05
    assert 0.5 < math.degrees(abs(err[2])) < 8.0
    assert abs(err[2]) < 2.0 * math.sqrt(cov[2, 2])
    assert math.degrees(math.sqrt(cov[2, 2])) > 3.0


def test_frontal_single_faces_yaw_covariance_is_not_overconfident(scene) -> None:
    r, det = scene
    est = CubePoseEstimator(S)
    rng = np.random.default_rng(31)
    rows = []
    for _ in range(160):
        d, bearing, look = rng.uniform(2.0, 3.5), rng.uniform(-0.4, 0.4), rng.uniform(-0.35, 0.35)
        ox, oy = TARGET[0] + d * math.cos(bearing), TARGET[1] + d * math.sin(bearing)
        # one side face turned towards the observer, up to 25 deg off square-on
        n = tags.face_axes(SIDES[rng.integers(4)])[0]
        yaw = bearing - math.atan2(n[1], n[0]) + math.radians(rng.uniform(-25.0, 25.0))
        out = _errors(est, r, det, (ox, oy, bearing + math.pi + look), yaw)
        if out is not None:
            err, cov = out
            rows.append((err[2] ** 2 / cov[2, 2], float(err @ np.linalg.solve(cov, err)), abs(err[2])))
    a = np.array(rows)
    assert len(a) >= 120, f"only {len(a)} single-face estimates"
    yaw_nees, nees3 = a[:, 0], a[:, 1]
    # a yaw error of a few degrees is expected here: the views must not all be trivially easy
    assert math.degrees(float(np.percentile(a[:, 2], 90))) > 3.0
    # not over-confident: mean near 1 or below, and hardly any error beyond 3 sigma
    assert float(np.mean(yaw_nees)) <= 1.5, f"yaw NEES {np.mean(yaw_nees):.2f}"
    assert float(np.mean(yaw_nees > 9.0)) <= 0.02
    assert float(np.mean(nees3)) <= 1.5 * 3, f"NEES {np.mean(nees3):.2f}"
    assert float(np.mean(nees3 > 16.27)) <= 0.02  # chi^2(3) 99.9%
    # conservative but still informative (measured: yaw NEES ~0.16, sigma ~2.5x the RMS error)
    assert float(np.mean(yaw_nees)) >= 0.05
