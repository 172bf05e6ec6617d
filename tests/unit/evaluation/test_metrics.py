"""tagswarm.evaluation.metrics on synthetic run folders whose errors are known by construction.

Trajectories are written as TUM files in the map frame (x_m, y_m, yaw_rad per pose),
so every expected number below is computed by hand from the construction, not by
the code under test.  ``make_run`` is also used by test_report.py.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from tagswarm.evaluation import metrics
from tagswarm.evaluation.metrics import RunFolderError, compute_metrics, fit_se2

Poses = NDArray[np.float64]  # (N, 3): x_m, y_m, yaw_rad
Track = tuple[NDArray[np.float64], Poses]  # (stamps_s, poses)

T20 = np.arange(200) / 10.0  # 20 s at 10 Hz; i/10 is the closest double to the decimal stamp
OMEGA = 0.3  # rad/s on a 1 m circle: 0.3 m/s


# --------------------------------------------------------------------------- builders


def circle(k: int, t: NDArray[np.float64], radius: float = 1.0) -> Poses:
    """Robot k driving anticlockwise on a circle centred at (3k, 0), heading tangent."""
    a = OMEGA * t + k
    return np.column_stack([3.0 * k + radius * np.cos(a), radius * np.sin(a), a + math.pi / 2])


def static(x: float, y: float, t: NDArray[np.float64]) -> Poses:
    return np.column_stack([np.full(len(t), x), np.full(len(t), y), np.zeros(len(t))])


def shifted(p: Poses, dx: float, dy: float) -> Poses:
    return p + np.array([dx, dy, 0.0])


def se2_apply(p: Poses, x: float, y: float, yaw: float) -> Poses:
    """The whole trajectory moved by the SE(2) transform (x, y, yaw) (left-multiplied)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.column_stack([c * p[:, 0] - s * p[:, 1] + x, s * p[:, 0] + c * p[:, 1] + y, p[:, 2] + yaw])


def write_tum(path: Path, track: Track | None) -> None:
    """TUM lines ``t x y z qx qy qz qw``; ``None`` writes an empty file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if track is None:
        path.write_text("")
        return
    t, p = track
    lines = [" ".join(repr(float(v)) for v in (ti, x, y, 0.0, 0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)))
             for ti, (x, y, yaw) in zip(t, p, strict=True)]
    path.write_text("\n".join(lines) + "\n")


def make_run(root: Path, truth: dict[int, Track], odom: dict[int, Track] | None = None,
             fused: dict[int, Track | None] | None = None, observations: Sequence[tuple[int, int, str, int]] = (),
             modes: Sequence[tuple[int, int, str]] = (), **info: Any) -> Path:
    """A run folder.  ``odom`` defaults to the truth; a robot absent from ``fused`` gets no
    fused file, one mapped to ``None`` an empty one.  ``observations`` rows are
    (stamp_ns, observer, target_kind, target_id); ``modes`` rows (stamp_ns, robot, mode)."""
    root.mkdir(parents=True, exist_ok=True)
    odom = truth if odom is None else odom
    fused = {} if fused is None else fused
    for k in truth:
        write_tum(root / "trajectories" / f"truth_{k}.tum", truth[k])
        write_tum(root / "trajectories" / f"odom_{k}.tum", odom[k])
        if k in fused:
            write_tum(root / "trajectories" / f"fused_{k}.tum", fused[k])
    obs_lines = ["stamp_ns,observer,target_kind,target_id,x_m,y_m,yaw_rad"]
    obs_lines += [f"{s},{a},{kind},{b},1.0,0.0,0.0" for s, a, kind, b in observations]
    (root / "observations.csv").write_text("\n".join(obs_lines) + "\n")
    mode_lines = ["stamp_ns,robot,mode", *(f"{s},{r},{m}" for s, r, m in modes)]
    (root / "modes.csv").write_text("\n".join(mode_lines) + "\n")
    run: dict[str, Any] = {"robots": sorted(truth), "origin_id": 0, "clock": "lockstep", "sim_time_s": 20.0,
                           "wall_time_s": 10.0, "exit_code": 0, "counters": {}}
    run.update(info)
    (root / "run.json").write_text(json.dumps(run))
    return root


def three_circles(root: Path, rng_seed: int = 1, **kw: Any) -> Path:
    """Three robots on circles; fused = truth + 1 cm white noise per axis; odom drifts
    along +x by 1 cm per second (error exactly 0.01 t)."""
    rng = np.random.default_rng(rng_seed)
    truth = {k: (T20, circle(k, T20)) for k in range(3)}
    fused: dict[int, Track | None] = {
        k: (T20, truth[k][1] + np.column_stack([rng.normal(0, 0.01, (len(T20), 2)), np.zeros(len(T20))]))
        for k in range(3)}
    odom = {k: (T20, np.column_stack([truth[k][1][:, 0] + 0.01 * T20, truth[k][1][:, 1:]])) for k in range(3)}
    return make_run(root, truth, odom, fused, **kw)


# --------------------------------------------------------------------------- ATE


def test_constant_offset_ate_is_the_offset_and_alignment_removes_it(tmp_path: Path) -> None:
    truth = {k: (T20, circle(k, T20)) for k in range(2)}
    fused: dict[int, Track | None] = {k: (T20, shifted(truth[k][1], 0.03, 0.04)) for k in range(2)}
    m = compute_metrics(make_run(tmp_path, truth, fused=fused))
    for k in ("0", "1"):
        ate = m["robots"][k]["fused"]["ate_unaligned"]
        assert ate["count"] == 200
        assert ate["rmse"] == pytest.approx(0.05, abs=1e-9)  # |(0.03, 0.04)|
        assert ate["median"] == pytest.approx(0.05, abs=1e-9)
        assert ate["max"] == pytest.approx(0.05, abs=1e-9)
        assert m["robots"][k]["fused"]["ate_aligned"]["rmse"] == pytest.approx(0.0, abs=1e-9)
    al = m["swarm"]["fused"]["alignment"]
    assert al["points"] == 400
    assert al["yaw_rad"] == pytest.approx(0.0, abs=1e-9)
    assert (al["x_m"], al["y_m"]) == pytest.approx((-0.03, -0.04), abs=1e-9)
    assert m["swarm"]["fused"]["ate_unaligned"]["rmse"] == pytest.approx(0.05, abs=1e-9)
    assert m["swarm"]["fused"]["ate_unaligned"]["count"] == 400
    # a common shift keeps every inter-robot distance and every relative motion
    assert m["swarm"]["fused"]["pairwise"]["rmse"] == pytest.approx(0.0, abs=1e-9)
    assert m["swarm"]["fused"]["rpe_per_m"]["max"] == pytest.approx(0.0, abs=1e-9)
    # odom defaults to the truth here
    assert m["swarm"]["odom"]["ate_unaligned"]["max"] == pytest.approx(0.0, abs=1e-12)


def test_odom_drift_ate_matches_hand_computation(tmp_path: Path) -> None:
    m = compute_metrics(three_circles(tmp_path))
    err = 0.01 * T20  # odom error is exactly 1 cm per second along +x
    for k in ("0", "1", "2"):
        ate = m["robots"][k]["odom"]["ate_unaligned"]
        assert ate["rmse"] == pytest.approx(math.sqrt(np.mean(err**2)), rel=1e-9)
        assert ate["median"] == pytest.approx(float(np.median(err)), rel=1e-9)
        assert ate["max"] == pytest.approx(0.199, rel=1e-9)
    assert m["swarm"]["odom"]["ate_unaligned"]["rmse"] == pytest.approx(math.sqrt(np.mean(err**2)), rel=1e-9)
    # fused: 1 cm per axis -> RMS of the 2-D error is sqrt(2) cm
    fused = m["swarm"]["fused"]["ate_unaligned"]
    assert fused["rmse"] == pytest.approx(math.sqrt(2) * 0.01, rel=0.1)
    assert fused["count"] == 600


def test_odom_drift_rpe_per_metre(tmp_path: Path) -> None:
    m = compute_metrics(three_circles(tmp_path))
    # segments: the first true pose at >= 1 m of true (chord-summed) path after the last one
    chord = 2 * math.sin(OMEGA * 0.1 / 2)
    steps = math.ceil(1.0 / chord)
    expected = 0.01 * steps * 0.1  # drift accumulated over one segment's duration, metres
    rpe = m["robots"]["0"]["odom"]["rpe_per_m"]
    assert rpe["count"] == (len(T20) - 1) // steps
    assert rpe["rmse"] == pytest.approx(expected, rel=1e-6)
    assert rpe["max"] == pytest.approx(expected, rel=1e-6)
    # white noise of 1 cm per pose: relative error of two poses ~ 2 cm, far below the 3.4 cm drift
    assert m["swarm"]["fused"]["rpe_per_m"]["rmse"] < 0.025
    assert m["swarm"]["odom"]["rpe_per_m"]["count"] == 3 * rpe["count"]


def test_rpe_is_null_for_robots_that_never_travel_a_metre(tmp_path: Path) -> None:
    t = np.arange(50) / 10.0
    truth = {0: (t, static(0, 0, t)), 1: (T20[:2], circle(1, T20[:2]))}
    m = compute_metrics(make_run(tmp_path, truth, fused={0: truth[0], 1: (T20[:1], circle(1, T20[:1]))}))
    assert m["robots"]["0"]["fused"]["rpe_per_m"] is None
    assert m["robots"]["1"]["fused"]["rpe_per_m"] is None  # a single fused pose
    assert m["robots"]["1"]["fused"]["ate_unaligned"]["count"] == 1
    assert m["swarm"]["fused"]["rpe_per_m"] is None


def test_shared_se2_alignment_recovers_a_swarm_wide_rotation_and_shift(tmp_path: Path) -> None:
    # the whole fused swarm is moved by G = (1.0, -2.0, 0.3 rad) plus 1 cm noise
    gx, gy, gyaw = 1.0, -2.0, 0.3
    rng = np.random.default_rng(7)
    truth = {k: (T20, circle(k, T20)) for k in range(3)}
    fused: dict[int, Track | None] = {}
    for k in range(3):
        noisy = truth[k][1] + np.column_stack([rng.normal(0, 0.01, (len(T20), 2)), np.zeros(len(T20))])
        fused[k] = (T20, se2_apply(noisy, gx, gy, gyaw))
    m = compute_metrics(make_run(tmp_path, truth, fused=fused))
    sw = m["swarm"]["fused"]
    assert sw["ate_unaligned"]["rmse"] > 1.0
    assert sw["ate_aligned"]["rmse"] == pytest.approx(math.sqrt(2) * 0.01, rel=0.1)
    for rid in ("0", "1", "2"):
        assert m["robots"][rid]["fused"]["ate_aligned"]["rmse"] < 0.02
        assert m["robots"][rid]["fused"]["ate_unaligned"]["rmse"] > 0.5
    # the fit is G^-1: yaw -0.3 and translation -R(-0.3) (1, -2)
    al = sw["alignment"]
    c, s = math.cos(-gyaw), math.sin(-gyaw)
    assert al["yaw_rad"] == pytest.approx(-gyaw, abs=2e-3)
    assert al["x_m"] == pytest.approx(-(c * gx - s * gy), abs=5e-3)
    assert al["y_m"] == pytest.approx(-(s * gx + c * gy), abs=5e-3)
    assert al["points"] == 600
    # a rigid motion of the whole swarm leaves the formation intact (noise only)
    assert sw["pairwise"]["rmse"] < 0.03
    assert sw["pairwise"]["pairs"] == 3


def test_shared_alignment_is_one_transform_not_one_per_robot(tmp_path: Path) -> None:
    # robot 0 is shifted +0.2 m in x, robot 1 -0.2 m: one shared transform cannot undo both
    truth = {k: (T20, circle(k, T20)) for k in range(2)}
    fused: dict[int, Track | None] = {0: (T20, shifted(truth[0][1], 0.2, 0)), 1: (T20, shifted(truth[1][1], -0.2, 0))}
    m = compute_metrics(make_run(tmp_path, truth, fused=fused))
    assert m["swarm"]["fused"]["ate_aligned"]["rmse"] > 0.15
    assert m["swarm"]["fused"]["pairwise"]["max"] > 0.3


def test_fit_se2_exact_and_degenerate() -> None:
    rng = np.random.default_rng(3)
    est = rng.uniform(-3, 3, (40, 2))
    yaw, tx, ty = -2.5, 0.7, 4.0
    c, s = math.cos(yaw), math.sin(yaw)
    ref = est @ np.array([[c, -s], [s, c]]).T + [tx, ty]
    al = fit_se2(est, ref)
    assert al is not None
    assert (al.yaw_rad, al.x_m, al.y_m) == pytest.approx((yaw, tx, ty), abs=1e-9)
    assert fit_se2(np.zeros((0, 2)), np.zeros((0, 2))) is None
    one = fit_se2(np.array([[1.0, 2.0]]), np.array([[4.0, 6.0]]))
    assert one is not None and (one.yaw_rad, one.x_m, one.y_m) == pytest.approx((0.0, 3.0, 4.0))


# --------------------------------------------------------------------------- association


def test_sparse_fused_is_associated_with_dense_truth(tmp_path: Path) -> None:
    # truth at 30 Hz on a straight line, fused at 5 Hz exactly on it, 10 ms late stamps
    t30 = np.arange(300) / 30.0
    line = np.column_stack([0.2 * t30, 0.1 * t30, np.full(300, math.atan2(0.1, 0.2))])
    t5 = np.arange(50) / 5.0 + 0.01
    on_line = np.column_stack([0.2 * t5, 0.1 * t5, np.full(50, math.atan2(0.1, 0.2))])
    m = compute_metrics(make_run(tmp_path, {0: (t30, line)}, fused={0: (t5, on_line)}))
    f = m["robots"]["0"]["fused"]
    assert f["samples"] == 50
    assert f["associated"] == 50
    assert f["first_s"] == pytest.approx(0.01)
    assert f["ate_unaligned"]["max"] == pytest.approx(0.0, abs=1e-9)  # truth interpolated at the fused stamps


def test_missing_and_empty_fused_files_give_null_metrics(tmp_path: Path) -> None:
    truth = {k: (T20, circle(k, T20)) for k in range(3)}
    # robot 1: empty fused file; robot 2: no fused file at all
    m = compute_metrics(make_run(tmp_path, truth, fused={0: truth[0], 1: None}))
    for k in ("1", "2"):
        f = m["robots"][k]["fused"]
        assert f == {"samples": 0, "associated": 0, "first_s": None, "ate_unaligned": None, "ate_aligned": None,
                     # never localised: 0, not null
                     "rpe_per_m": None, "time_localised": 0.0, "time_localised_placed": None, "nees": None,
                     "nees_nominal": None, "ate_unaligned_nominal": None, "sigma_median_m": None}
    assert m["robots"]["0"]["fused"]["ate_unaligned"]["rmse"] == pytest.approx(0.0, abs=1e-12)
    assert m["swarm"]["fused"]["robots_evaluated"] == 1
    assert m["swarm"]["fused"]["pairwise"] is None  # needs two localised robots
    assert m["swarm"]["odom"]["robots_evaluated"] == 3
    json.dumps(m, allow_nan=False)


def test_pairwise_error_by_hand(tmp_path: Path) -> None:
    t = np.arange(20) / 10.0
    truth = {0: (t, static(0, 0, t)), 1: (t, static(3, 0, t)), 2: (t, static(0, 4, t))}
    # robot 1 estimated 0.2 m too far along x: d01 +0.2; d12 = |(-3.2, 4)| - 5; d02 unchanged
    fused: dict[int, Track | None] = {0: truth[0], 1: (t, static(3.2, 0, t)), 2: truth[2]}
    m = compute_metrics(make_run(tmp_path, truth, fused=fused))
    e12 = math.hypot(3.2, 4) - 5
    pw = m["swarm"]["fused"]["pairwise"]
    assert pw["pairs"] == 3
    assert pw["count"] == 60
    assert pw["max"] == pytest.approx(0.2, abs=1e-9)
    assert pw["rmse"] == pytest.approx(math.sqrt((0.2**2 + e12**2) / 3), abs=1e-9)


# --------------------------------------------------------------------------- behaviour and cost


def test_time_lost_and_mode_times_from_modes_csv(tmp_path: Path) -> None:
    # one sample per second; robot 0 lost at 5, 6, 7 s; robot 1 lost at its last sample (19 s)
    modes = [(s * 10**9, 0, "lost" if s in (5, 6, 7) else "visual") for s in range(20)]
    modes += [(s * 10**9, 1, "lost" if s == 19 else ("searching" if s < 2 else "odometry")) for s in range(20)]
    truth = {k: (T20, circle(k, T20)) for k in range(2)}
    m = compute_metrics(make_run(tmp_path, truth, modes=modes))
    r0, r1 = m["robots"]["0"], m["robots"]["1"]
    assert r0["time_lost_s"] == pytest.approx(3.0)
    # the last sample holds until the end of the recorded truth, 19.9 s
    assert r0["mode_time_s"] == pytest.approx({"lost": 3.0, "visual": 16.9})
    assert r1["time_lost_s"] == pytest.approx(0.9)
    assert r1["mode_time_s"] == pytest.approx({"lost": 0.9, "odometry": 17.0, "searching": 2.0})
    assert m["swarm"]["time_lost_s"] == pytest.approx(3.9)


def test_counters_cost_and_real_time_factor(tmp_path: Path) -> None:
    counters = {
        "world": {"frames_rendered": 600, "step": 1200},
        "server": {"keyframes": 10},
        "agent/0": {"fixes": 12, "searches": 2, "lost_events": 1, "frames_processed": 190, "frames_skipped": 10},
        "agent/1": {"fixes": 3, "searches": 0, "lost_events": 0, "frames_processed": 150, "frames_skipped": 50},
        "agent/2": {"fixes": 1, "frames_processed": 20},  # counters never incremented are absent: zero
    }
    truth = {k: (T20, circle(k, T20)) for k in range(4)}
    m = compute_metrics(make_run(tmp_path, truth, counters=counters, sim_time_s=30.0, wall_time_s=12.0))
    c = m["cost"]
    assert c["real_time_factor"] == pytest.approx(2.5)
    assert (c["sim_time_s"], c["wall_time_s"]) == (30.0, 12.0)
    assert c["frames_rendered"] == 600
    assert c["frames_rendered_per_robot"] == pytest.approx(150.0)
    assert (c["frames_processed"], c["frames_skipped"]) == (360, 60)
    assert (m["robots"]["0"]["frames_processed"], m["robots"]["0"]["frames_skipped"]) == (190, 10)
    assert (m["robots"]["1"]["frames_processed"], m["robots"]["1"]["frames_skipped"]) == (150, 50)
    assert (m["robots"]["2"]["frames_skipped"], m["robots"]["2"]["searches"]) == (0, 0)
    assert m["robots"]["3"]["fixes"] is None  # agent 3 reported no counters at all
    assert (m["swarm"]["fixes"], m["swarm"]["searches"], m["swarm"]["lost_events"]) == (16, 2, 1)
    assert m["run"]["clock"] == "lockstep"


def test_a_robot_whose_way_was_closed_is_named_with_its_stalls(tmp_path: Path) -> None:
    counters = {
        "agent/0": {"fixes": 5},
        "agent/1": {"avoid_side_flips": 6, "avoid_yields": 2, "avoid_reroutes": 1},
        "agent/2": {"avoid_side_flips": 2, "avoid_yields": 4},  # under STALL_NOTE_FLIPS: not named
        "agent/3": {"avoid_steps_aside": 1},
    }
    truth = {k: (T20, circle(k, T20)) for k in range(4)}
    m = compute_metrics(make_run(tmp_path, truth, counters=counters, sim_time_s=20.0, wall_time_s=10.0))
    r1 = m["robots"]["1"]
    assert (r1["avoid_side_flips"], r1["avoid_yields"], r1["avoid_reroutes"]) == (6, 2, 1)
    assert (m["robots"]["0"]["avoid_side_flips"], m["swarm"]["avoid_side_flips"]) == (0, 8)
    assert (m["robots"]["3"]["avoid_steps_aside"], m["swarm"]["avoid_steps_aside"]) == (1, 1)
    notes = [w for w in m["warnings"] if "way was closed" in w]
    assert len(notes) == 1 and notes[0].startswith("robot 1's way was closed 6 times")
    assert "gave way 2 times, followed 1 way(s) round" in notes[0]
    assert f"drove {r1['path_length_m']:.1f} m" in notes[0]


def test_frames_rendered_by_render_workers_are_summed(tmp_path: Path) -> None:
    # a world with render workers counts requests; the frames are in each worker's render/<i> status
    counters = {"world": {"frames_requested": 700, "step": 1200}, "render/0": {"frames_rendered": 350},
                "render/1": {"frames_rendered": 340}, "agent/0": {"frames_processed": 170}}
    truth = {k: (T20, circle(k, T20)) for k in range(2)}
    c = compute_metrics(make_run(tmp_path, truth, counters=counters, sim_time_s=30.0, wall_time_s=31.0))["cost"]
    assert c["frames_rendered"] == 690
    assert c["frames_rendered_per_robot"] == pytest.approx(345.0)


def test_real_time_factor_is_the_worlds_stepping_pace_not_the_whole_runs(tmp_path: Path) -> None:
    # 25 s simulated in 25.5 s of stepping; the processes' start-up and shutdown made the run 30 s
    counters = {"world": {"step": 750, "stepping_ms": 25_500}, "agent/0": {"frames_processed": 10}}
    truth = {0: (T20, circle(0, T20))}
    c = compute_metrics(make_run(tmp_path, truth, counters=counters, sim_time_s=25.0, wall_time_s=30.0))["cost"]
    assert c["real_time_factor"] == pytest.approx(25.0 / 25.5)
    assert c["run_real_time_factor"] == pytest.approx(25.0 / 30.0)
    assert c["stepping_wall_s"] == pytest.approx(25.5)


def test_real_time_factor_is_null_without_wall_time(tmp_path: Path) -> None:
    truth = {0: (T20, circle(0, T20))}
    m = compute_metrics(make_run(tmp_path, truth, wall_time_s=0.0))
    assert m["cost"]["real_time_factor"] is None
    assert m["cost"]["frames_rendered"] is None
    assert m["swarm"]["fixes"] is None


# --------------------------------------------------------------------------- error against distance


def test_error_vs_distance_bins(tmp_path: Path) -> None:
    t = np.arange(100) / 10.0
    truth = {0: (t, static(0, 0, t)), 1: (t, static(0.5, 0, t)), 2: (t, static(2.5, 0, t))}
    # fused errors: robot 0 5 cm, robot 1 10 cm, robot 2 30 cm (constant offsets)
    fused: dict[int, Track | None] = {0: (t, static(0, 0.05, t)), 1: (t, static(0.6, 0, t)),
                                      2: (t, static(2.5, 0.3, t))}
    # 0 sees 1 every 0.2 s; 1 sees 2 once at 2 s; 0 sees a landmark (ignored)
    obs = [(i * 200_000_000, 0, "robot", 1) for i in range(50)]
    obs += [(2_000_000_000, 1, "robot", 2), (3_000_000_000, 0, "landmark", 0)]
    m = compute_metrics(make_run(tmp_path, truth, fused=fused, observations=obs))
    evd = m["error_vs_distance"]
    # robots 0 and 1: always a neighbour at 0.5 m; robot 2: 1.5..2.5 s (11 samples) at 2.0 m from robot 1
    assert evd["samples"] == 211
    assert evd["unobserved_samples"] == 89
    bins = evd["bins"]
    assert [(b["lo_m"], b["hi_m"]) for b in bins] == [(0, 1), (1, 2), (2, 3), (3, 4), (4, None)]
    assert [b["count"] for b in bins] == [200, 0, 11, 0, 0]
    assert bins[0]["median_error_m"] == pytest.approx(0.075)
    assert bins[0]["mean_error_m"] == pytest.approx(0.075)
    assert bins[2]["median_error_m"] == pytest.approx(0.3)
    assert bins[1]["median_error_m"] is None


def test_bin_by_distance_edges() -> None:
    bins = metrics.bin_by_distance(np.array([0.0, 0.99, 1.0, 7.0]), np.array([1.0, 3.0, 5.0, 9.0]))
    assert [b["count"] for b in bins] == [2, 1, 0, 0, 1]
    assert bins[0]["median_error_m"] == 2.0
    assert bins[4]["median_error_m"] == 9.0


# --------------------------------------------------------------------------- bad folders


def test_missing_folder_and_run_json(tmp_path: Path) -> None:
    with pytest.raises(RunFolderError, match="no such directory"):
        compute_metrics(tmp_path / "nope")
    with pytest.raises(RunFolderError, match=r"no run\.json"):
        compute_metrics(tmp_path)
    (tmp_path / "run.json").write_text("{not json")
    with pytest.raises(RunFolderError, match="cannot be parsed"):
        compute_metrics(tmp_path)
    (tmp_path / "run.json").write_text('{"robots": "all"}')
    with pytest.raises(RunFolderError, match="robots"):
        compute_metrics(tmp_path)


def test_malformed_inputs_are_named(tmp_path: Path) -> None:
    run = make_run(tmp_path, {0: (T20, circle(0, T20))})
    (run / "trajectories" / "fused_0.tum").write_text("0.0 1 2 3\n")
    with pytest.raises(RunFolderError, match=r"fused_0\.tum"):
        compute_metrics(run)
    (run / "trajectories" / "fused_0.tum").unlink()
    (run / "modes.csv").write_text("time,robot,mode\n")
    with pytest.raises(RunFolderError, match=r"modes\.csv"):
        compute_metrics(run)


def test_missing_csvs_and_truth_are_warnings(tmp_path: Path) -> None:
    run = make_run(tmp_path, {k: (T20, circle(k, T20)) for k in range(2)})
    (run / "modes.csv").unlink()
    (run / "observations.csv").unlink()
    (run / "trajectories" / "truth_1.tum").unlink()
    m = compute_metrics(run)
    text = " | ".join(m["warnings"])
    assert "modes.csv is missing" in text and "observations.csv is missing" in text
    assert "robot 1: no truth trajectory" in text
    assert m["robots"]["1"]["odom"]["ate_unaligned"] is None
    assert m["robots"]["0"]["odom"]["ate_unaligned"]["count"] == 200


def test_a_blind_origin_seen_only_from_afar_is_a_warning_with_the_true_range(tmp_path: Path) -> None:
    t = np.arange(200) / 10.0
    truth = {0: (t, static(0, 0, t)), 1: (t, static(3.0, 0, t)), 2: (t, static(3.0, 1.0, t))}
    obs = [(i * 100_000_000, 1, "robot", 0) for i in range(50)] + [(1_000_000_000, 1, "robot", 2)]
    m = compute_metrics(make_run(tmp_path / "far", truth, observations=obs))
    (note,) = [w for w in m["warnings"] if "origin robot 0" in w]
    assert "robot 1 (50 views at 3.0 m)" in note
    # the same run but the origin saw robot 1 once at the start: no warning
    m = compute_metrics(make_run(tmp_path / "sees", truth, observations=[*obs, (500_000_000, 0, "robot", 1)]))
    assert not [w for w in m["warnings"] if "origin robot" in w]
