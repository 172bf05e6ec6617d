"""The scenes nobody tuned for, end to end (``tagswarm up``, lockstep, seed 0,
shortened runs): every robot localised to within 10 cm RMSE and at the end,
the swarm within 5 cm, no robot-robot contact.  The full-length numbers (time
localised, NEES) are in bench/results/scenes.json."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

from tests.harness import script

# scene -> simulated seconds here (the bench runs each at its own length)
# the warehouse: nine robots holding station at random, the realistic camera -- every robot but the origin
# first turns once to look around; without that its worst robot was 0.61 m RMSE (bench/results/scenes.json)
SCENES = {"hall": 40.0, "corridor": 40.0, "crowd": 15.0, "warehouse": 30.0}


def _final_error(run: Path, rid: int) -> float:
    truth = np.loadtxt(run / "trajectories" / f"truth_{rid}.tum", ndmin=2)
    fused = np.loadtxt(run / "trajectories" / f"fused_{rid}.tum", ndmin=2)
    i = int(np.argmin(np.abs(fused[:, 0] - truth[-1, 0])))
    assert abs(fused[i, 0] - truth[-1, 0]) < 0.1
    return float(np.hypot(fused[i, 1] - truth[-1, 1], fused[i, 2] - truth[-1, 2]))


@pytest.mark.parametrize("scene", list(SCENES))
def test_scene_localises_every_robot(scene: str, tmp_path: Path) -> None:
    out = tmp_path / "run"
    res = subprocess.run([script("tagswarm"), "up", "--scenario", scene, "--clock", "lockstep", "--seed", "0",
                          "--duration", str(SCENES[scene]), "--out", str(out), "--no-live"],
                         capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    m = json.loads((out / "metrics.json").read_text())
    swarm = m["swarm"]
    assert swarm["fused"]["ate_unaligned"]["rmse"] <= 0.05
    for rid, r in m["robots"].items():
        assert r["fused"]["ate_unaligned"]["rmse"] <= 0.10, (rid, r["fused"]["ate_unaligned"])
        assert _final_error(out, int(rid)) <= 0.10, rid
    assert swarm["contacts"]["robot_robot"] == 0
    # the share of robot-time under 10 cm counts the start, before a robot is first placed (hall: a robot behind
    # a shelf is first seen after 7 s; warehouse: two robots placed during their first turn, at 7 s): a floor
    # here, the full-length number in the bench
    assert swarm["fused"]["time_localised"] >= 0.85
    # from each robot's first placement on, the 99 % nearly holds already in these short runs
    # (98.3-100 %, measured 2026-12-06): a robot that loses its place after being found fails here
    assert swarm["fused"]["time_localised_placed"] >= 0.97


def test_hall_with_known_start_poses_is_localised_from_the_first_instant(tmp_path: Path) -> None:
    """``[server] start_prior_sigma``: robots starting from surveyed places are in the map from t = 0.
    Without it the hall's robots 3 and 4 face nobody placeable and are first placed after 7-10 s (the
    10 s run measures 59.9 % then; with it 100 %)."""
    out = tmp_path / "run"
    res = subprocess.run([script("tagswarm"), "up", "--scenario", "hall", "--clock", "lockstep", "--seed", "0",
                          "--duration", "10", "--out", str(out), "--no-live",
                          "--set", "server.start_prior_sigma=0.02"],
                         capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    assert "start poses known (sigma 0.02)" in (out / "logs" / "server.log").read_text()
    m = json.loads((out / "metrics.json").read_text())
    assert m["swarm"]["fused"]["time_localised"] >= 0.99
    for rid, r in m["robots"].items():
        assert r["fused"]["ate_unaligned"]["rmse"] <= 0.05, (rid, r["fused"]["ate_unaligned"])
        assert _final_error(out, int(rid)) <= 0.10, rid
