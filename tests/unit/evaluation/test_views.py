"""The robot views against the truth, by range (tagswarm.evaluation.views) and in metrics.json."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from evo.core.trajectory import PoseTrajectory3D

from tagswarm.evaluation.metrics import compute_metrics
from tagswarm.evaluation.reportsummary import view_line
from tagswarm.evaluation.runfolder import Observations
from tagswarm.evaluation.views import view_error_by_range, view_errors
from tests.unit.evaluation.test_metrics import make_run, static

T = np.arange(0.0, 10.0, 0.1)


def traj(x: float, y: float, yaw: float, t: np.ndarray = T) -> PoseTrajectory3D:
    """A robot standing at (x, y, yaw) over ``t``."""
    q = np.tile([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)], (t.size, 1))
    return PoseTrajectory3D(np.tile([x, y, 0.0], (t.size, 1)), q, t)


def seen(obs_pose: tuple[float, float, float], tgt_pose: tuple[float, float, float],
         d_range: float = 0.0, d_across: float = 0.0, d_yaw: float = 0.0) -> tuple[float, float, float]:
    """The target in the observer's base frame, moved by the given errors along and across
    the line of sight and in yaw."""
    ox, oy, oyaw = obs_pose
    c, s = math.cos(oyaw), math.sin(oyaw)
    dx, dy = tgt_pose[0] - ox, tgt_pose[1] - oy
    x, y = c * dx + s * dy, -s * dx + c * dy
    r = math.hypot(x, y)
    ux, uy = x / r, y / r
    return (x + d_range * ux - d_across * uy, y + d_range * uy + d_across * ux, tgt_pose[2] - oyaw + d_yaw)


def observations(rows: list[tuple[float, int, bool, int, tuple[float, float, float]]]) -> Observations:
    return Observations(np.array([r[0] for r in rows]), np.array([r[1] for r in rows], np.int64),
                        np.array([r[2] for r in rows], bool), np.array([r[3] for r in rows], np.int64),
                        np.array([r[4] for r in rows], float).reshape(-1, 3))


P0, P1, P2 = (0.5, -0.2, 0.3), (4.2, 1.4, 2.0), (1.6, 0.7, -1.0)  # robot 1 is 4.0 m from robot 0, robot 2 1.4 m


def test_a_far_view_s_range_across_and_yaw_errors_land_in_its_bin_in_the_observer_s_frame() -> None:
    truth = {0: traj(*P0), 1: traj(*P1), 2: traj(*P2)}
    rows = [(0.1 * k, 0, True, 1, seen(P0, P1, 0.015, -0.004, 0.02)) for k in range(20)]
    rows += [(0.1 * k, 0, True, 2, seen(P0, P2)) for k in range(10)]
    rows += [(0.1 * k, 1, True, 0, seen(P1, P0, 0.025 if k % 2 else 0.005)) for k in range(10)]  # mean 1.5 cm
    rows += [(1.0, 0, False, 7, (1.0, 0.0, 0.0))]  # a landmark view: not a robot view
    out = view_error_by_range(observations(rows), truth)
    assert out["views"] == 40 and out["unmatched"] == 0
    bins = {(b["lo_m"], b["hi_m"]): b for b in out["bins"]}
    assert [b["count"] for b in out["bins"]] == [0, 10, 0, 0, 30, 0]
    far, near = bins[(4.0, 5.0)], bins[(1.0, 2.0)]
    assert far["range_bias_m"] == pytest.approx(0.015, abs=1e-5)  # the across error lengthens the range by 2 um
    assert far["range_rmse_m"] == pytest.approx(math.sqrt((20 * 0.015**2 + 5 * 0.025**2 + 5 * 0.005**2) / 30), abs=1e-5)
    assert far["across_bias_m"] == pytest.approx(-0.004 * 20 / 30, abs=1e-6)
    assert far["yaw_bias_rad"] == pytest.approx(0.02 * 20 / 30, abs=1e-9)
    assert near["range_bias_m"] == pytest.approx(0.0, abs=1e-12)
    assert near["yaw_rmse_rad"] == pytest.approx(0.0, abs=1e-12)
    assert bins[(0.0, 1.0)]["range_bias_m"] is None
    assert out["bins"][-1]["hi_m"] is None


def test_a_target_seen_nearer_has_a_negative_range_bias_and_left_is_positive_across() -> None:
    truth = {0: traj(0.0, 0.0, 0.0), 1: traj(2.5, 0.0, 0.0)}
    out = view_error_by_range(observations([(1.0, 0, True, 1, (2.49, 0.003, 0.0))]), truth)
    b = out["bins"][2]
    assert b["count"] == 1
    assert b["range_bias_m"] == pytest.approx(-0.01 + 0.003**2 / (2 * 2.49), abs=1e-6)
    assert b["across_bias_m"] == pytest.approx(0.003)


def test_views_without_a_true_pose_of_both_robots_or_with_a_non_finite_measurement_are_unmatched() -> None:
    truth: dict[int, PoseTrajectory3D | None] = {0: traj(*P0), 1: traj(*P1, t=np.arange(0.0, 1.0, 0.1)), 3: None}
    rows = [(0.5, 0, True, 1, seen(P0, P1)),  # matched
            (5.0, 0, True, 1, seen(P0, P1)),  # robot 1's truth ends at 0.9 s
            (0.5, 0, True, 3, (1.0, 0.0, 0.0)),  # robot 3 has no truth
            (0.5, 0, True, 9, (1.0, 0.0, 0.0)),  # robot 9 is not in the run
            (0.5, 0, True, 1, (math.nan, 0.0, 0.0))]
    r, err, unmatched = view_errors(observations(rows), truth)
    assert r.shape == (1,) and err.shape == (1, 3) and unmatched == 4
    assert r[0] == pytest.approx(math.hypot(P1[0] - P0[0], P1[1] - P0[1]))
    assert np.allclose(err, 0.0, atol=1e-12)


def test_metrics_json_has_the_views_by_range_and_the_summary_names_the_bias(tmp_path: Path) -> None:
    truth = {0: (T, static(0.0, 0.0, T)), 1: (T, static(3.5, 0.0, T))}
    run = make_run(tmp_path, truth, fused={0: truth[0], 1: truth[1]},
                   observations=[(int(k * 1e8), 0, "robot", 1) for k in range(10)])
    # the agents saw robot 1 at 3.52 m (make_run writes (1, 0, 0): rewrite the measurements)
    lines = (run / "observations.csv").read_text().splitlines()
    (run / "observations.csv").write_text("\n".join([lines[0]] + [ln.replace(",1.0,0.0,0.0", ",3.52,0.0,0.0")
                                                                  for ln in lines[1:]]) + "\n")
    m = compute_metrics(run)
    v = m["view_error_vs_range"]
    assert v["views"] == 10 and v["unmatched"] == 0
    b = v["bins"][3]
    assert (b["lo_m"], b["hi_m"], b["count"]) == (3.0, 4.0, 10)
    assert b["range_bias_m"] == pytest.approx(0.02)
    line = view_line(m)
    assert line is not None and "+20.0 mm at 3-4 m (10)" in line
    assert view_line({"view_error_vs_range": {"views": 0, "unmatched": 0, "bins": []}}) is None


def test_a_moving_target_s_true_pose_is_interpolated_between_the_truth_samples_around_the_view() -> None:
    t = np.arange(0.0, 2.0, 0.1)  # robot 1 drives along x at 1 m/s, turning at 0.5 rad/s, truth every 0.1 s
    q = np.column_stack([np.cos(0.25 * t), np.zeros((t.size, 2)), np.sin(0.25 * t)])
    mover = PoseTrajectory3D(np.column_stack([3.0 + t, np.zeros((t.size, 2))]), q, t)
    truth = {0: traj(0.0, 0.0, 0.0), 1: mover}
    # seen at 0.54 s, where it is (3.54, 0, 0.27): the truth samples are 4 cm either side
    r, err, unmatched = view_errors(observations([(0.54, 0, True, 1, (3.54, 0.0, 0.27))]), truth)
    assert unmatched == 0 and r[0] == pytest.approx(3.54)
    assert np.allclose(err, 0.0, atol=1e-9)


def test_a_view_s_claimed_sigma_and_nees_are_taken_along_and_across_the_line_of_sight() -> None:
    # robot 1 is 4 m off the observer's left (+y): the line of sight is its y axis. Each view claims
    # sigma 2 cm along y (the range) and 5 mm along x (across) and is off by 2 cm in range, 5 mm across
    truth = {0: traj(0.0, 0.0, 0.0), 1: traj(0.0, 4.0, 0.0)}
    cov = np.diag([0.005**2, 0.02**2, 0.01**2])
    rows = [(0.1 * k, 0, True, 1, (-0.005 if k % 2 else 0.005, 4.02, 0.0)) for k in range(10)]
    obs = observations(rows)
    obs = Observations(obs.stamp_s, obs.observer, obs.is_robot, obs.target_id, obs.rel, np.tile(cov, (10, 1, 1)))
    b = view_error_by_range(obs, truth)["bins"][4]
    assert b["count"] == 10
    assert b["range_sigma_m"] == pytest.approx(0.02) and b["across_sigma_m"] == pytest.approx(0.005)
    assert b["nees"] == pytest.approx((1.0 + 1.0) / 2)  # one sigma along and one across
    assert b["yaw_sigma_rad"] == pytest.approx(0.01)
    # the same views claiming twice the range sigma are conservative: NEES (1/4 + 1) / 2
    wide = Observations(obs.stamp_s, obs.observer, obs.is_robot, obs.target_id, obs.rel,
                        np.tile(np.diag([0.005**2, 0.04**2, 0.01**2]), (10, 1, 1)))
    assert view_error_by_range(wide, truth)["bins"][4]["nees"] == pytest.approx(0.625)
    # without covariances (an older run folder) the claim is unknown, the errors are not
    plain = view_error_by_range(observations(rows), truth)["bins"][4]
    assert plain["nees"] is None and plain["range_sigma_m"] is None
    assert plain["range_bias_m"] == pytest.approx(0.02, abs=1e-5)


def test_the_observation_covariance_round_trips_through_observations_csv(tmp_path: Path) -> None:
    truth = {0: (T, static(0.0, 0.0, T)), 1: (T, static(3.5, 0.0, T))}
    run = make_run(tmp_path, truth, fused={0: truth[0], 1: truth[1]},
                   observations=[(int(k * 1e8), 0, "robot", 1) for k in range(10)])
    lines = (run / "observations.csv").read_text().splitlines()
    cols = ",cov_xx,cov_xy,cov_xyaw,cov_yy,cov_yyaw,cov_yawyaw"
    # seen at 3.52 m (2 cm too far) with a claimed range sigma of 1 cm: NEES 2 (4 / 2)
    body = [ln.replace(",1.0,0.0,0.0", ",3.52,0.0,0.0") + ",0.0001,0.0,0.0,0.0001,0.0,0.0004" for ln in lines[1:]]
    (run / "observations.csv").write_text("\n".join([lines[0] + cols, *body]) + "\n")
    m = compute_metrics(run)
    b = m["view_error_vs_range"]["bins"][3]
    assert b["count"] == 10 and b["nees"] == pytest.approx(2.0) and b["range_sigma_m"] == pytest.approx(0.01)
    line = view_line(m)
    assert line is not None and "+20.0 mm at 3-4 m (10, NEES 2.00)" in line
