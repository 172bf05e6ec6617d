"""tagswarm.testing.trajectories and the finished Run: TUM rows to (t, x, y, yaw), errors at
equal stamps."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from tagswarm.protocol.scenario import load_scenario
from tagswarm.testing.errors import SwarmError
from tagswarm.testing.result import Run
from tagswarm.testing.trajectories import planar, position_errors, read_tum, recorded_errors, rms


def _tum_line(t: float, x: float, y: float, yaw: float) -> str:
    return f"{t:.9f} {x:.6f} {y:.6f} 0.0 0.0 0.0 {math.sin(yaw / 2):.9f} {math.cos(yaw / 2):.9f}\n"


def test_tum_rows_become_planar_poses(tmp_path: Path) -> None:
    path = tmp_path / "a.tum"
    path.write_text(_tum_line(0.0, 1.0, 2.0, 0.5) + _tum_line(0.1, -1.0, 0.25, -3.0) + _tum_line(0.2, 0, 0, 3.1))
    rows = planar(read_tum(path))
    assert rows.shape == (3, 4)
    np.testing.assert_allclose(rows[:, :3], [[0.0, 1.0, 2.0], [0.1, -1.0, 0.25], [0.2, 0, 0]])
    np.testing.assert_allclose(rows[:, 3], [0.5, -3.0, 3.1], atol=1e-8)
    empty = tmp_path / "e.tum"
    empty.write_text("")
    assert planar(read_tum(empty)).shape == (0, 4)


def test_errors_pair_equal_stamps_only() -> None:
    truth = np.array([[0.0, 0, 0, 0], [0.1, 1, 0, 0], [0.2, 2, 0, 0]])
    est = np.array([[0.1, 1, 0.03, 0], [0.15, 9, 9, 0], [0.2, 2.04, 0.03, 0]])
    np.testing.assert_allclose(position_errors(truth, est), [[0.1, 0.03], [0.2, 0.05]])
    assert position_errors(truth, np.zeros((0, 4))).shape == (0, 2)
    live = recorded_errors([(100, (1.0, 0.0, 0.0))], [(100, (1.0, 0.3, 0.0)), (200, (5.0, 5.0, 0.0))])
    assert live == [(1e-7, pytest.approx(0.3))]
    assert rms([3.0, 4.0]) == pytest.approx(math.sqrt(12.5)) and math.isnan(rms([]))


def test_a_run_reads_its_folder(tmp_path: Path) -> None:
    traj = tmp_path / "trajectories"
    traj.mkdir()
    (tmp_path / "metrics.json").write_text('{"run": {"robots": [0, 1]}}')
    (traj / "truth_1.tum").write_text(_tum_line(0.0, 0, 0, 0) + _tum_line(1.0, 1, 0, 0))
    (traj / "fused_1.tum").write_text(_tum_line(1.0, 1.0, 0.08, 0))
    run = Run.load(tmp_path, load_scenario("paper", ["robots.count=2"]), "r1")
    assert run.metrics["run"]["robots"] == [0, 1] and run.robots == (0, 1)
    assert run.final_error(1) == pytest.approx(0.08)
    assert run.fused(1).shape == (1, 4)
    with pytest.raises(SwarmError, match="robot 7"):
        run.truth(7)
    with pytest.raises(SwarmError, match="kind"):
        run.trajectory("gps", 1)
    with pytest.raises(SwarmError, match="metrics"):
        Run.load(tmp_path / "missing", load_scenario("paper"), "r2")
