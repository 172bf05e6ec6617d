"""A robot the server places but does not vouch for drives its mission slowly on the map's loose
estimate, end to end (``tagswarm up``, lockstep, fixed seed)."""

from __future__ import annotations

import json
import math
import subprocess
from pathlib import Path

import numpy as np

from tests.harness import script


def test_a_robot_placed_but_never_vouched_for_drives_its_patrol_slowly_on_the_loose_pose(tmp_path: Path) -> None:
    # loose_as_written.toml: robot 1 is placed at 10.5 s through its own 4.2 m views of the origin's cube
    # (sigma 0.85 m); with claim_sigma_m = 0.1 the server never vouches for it.  Before the loose pose it
    # searched on the spot for the whole run (0.4 cm of travel); now, fix_threshold cycles after its
    # placement, it drives its patrol towards the origin at the lost speed (0.45 m by 25 s)
    scene = Path(__file__).with_name("loose_as_written.toml")
    out = tmp_path / "run"
    res = subprocess.run([script("tagswarm"), "up", "--clock", "lockstep", "--out", str(out), "--no-live",
                          "--scenario", str(scene), "--set", "server.claim_sigma_m=0.1"],
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    m = json.loads((out / "metrics.json").read_text())
    robot = m["robots"]["1"]
    assert robot["fused"]["first_s"] is None  # never vouched for: no fused trajectory
    truth = np.loadtxt(out / "trajectories" / "truth_1.tum", ndmin=2)
    start, end = truth[0, 1:3], truth[-1, 1:3]
    assert robot["path_length_m"] > 0.3, robot["path_length_m"]
    origin = np.loadtxt(out / "trajectories" / "truth_0.tum", ndmin=2)[0, 1:3]
    # towards its patrol's far end, by the origin: the loose pose is good enough to steer by
    assert math.dist(end, origin) < math.dist(start, origin) - 0.3, (start, end, origin)
    assert sum(m["swarm"]["contacts"].values()) == 0
    assert "robot 1 is in the map but not reported localised" in (out / "logs" / "server.log").read_text()
