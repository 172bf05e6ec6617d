"""Robots avoid each other in a real lockstep run of ``tagswarm up``: the grid case
where robot 3's patrol runs through the spot where robot 4 holds station (without
avoidance robot 3 pushed robot 4 1.4 m in 30 s)."""

from __future__ import annotations

import itertools
import json
import math
import subprocess
from pathlib import Path

import numpy as np

from tagswarm.protocol.layout import footprint_radius
from tagswarm.protocol.scenario import load_scenario
from tests.harness import script

ARGS = ["--robots", "8", "--set", 'robots.placement="grid"', "--duration", "20", "--clock", "lockstep", "--seed", "2"]


def _truth(run: Path, rid: int) -> dict[float, tuple[float, float]]:
    rows = np.loadtxt(run / "trajectories" / f"truth_{rid}.tum", ndmin=2)
    return {round(float(r[0]), 4): (float(r[1]), float(r[2])) for r in rows}


def test_grid_of_eight_has_no_robot_robot_contact(tmp_path: Path) -> None:
    out = tmp_path / "run"
    res = subprocess.run([script("tagswarm"), "up", *ARGS, "--out", str(out), "--no-live", "--no-report"],
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    run = json.loads((out / "run.json").read_text())
    assert run["sim_time_s"] >= 19.9
    world = run["counters"]["world"]
    if "contacts_robot_robot" in world:  # counted by the world's physics
        assert world["contacts_robot_robot"] == 0, world
    # the stronger check: the true footprints never overlapped
    s = load_scenario("paper", ["robots.count=8", 'robots.placement="grid"'])
    truth = {rid: _truth(out, rid) for rid in range(8)}
    closest = math.inf
    for a, b in itertools.combinations(range(8), 2):
        common = truth[a].keys() & truth[b].keys()
        assert len(common) > 500
        closest = min(closest, min(math.dist(truth[a][t], truth[b][t]) for t in common))
    assert closest > 2 * footprint_radius(s.robot), f"closest approach {closest:.3f} m"
    # robot 4 held its station and robot 3 still patrolled: it went round, it did not just stop
    still = truth[4]
    assert max(math.dist(still[t], still[0.0]) for t in still) < 0.01
    path3 = [truth[3][t] for t in sorted(truth[3])]
    assert sum(math.dist(p, q) for p, q in itertools.pairwise(path3)) > 2.0
    agent3 = run["counters"]["agent/3"]
    assert agent3["avoiding_cycles"] > 0 and agent3["maps_used"] > 10
