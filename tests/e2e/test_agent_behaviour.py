"""Active re-localisation with the real world, server and agents in lockstep."""

from __future__ import annotations

import csv
import json
import subprocess
from pathlib import Path

from tests.harness import script

REACQUIRE = """
name = "reacquire"
seed = 1
duration_s = 40.0
[robots]
count = 2
placement = "explicit"
start = [{ x_m = -2.0, y_m = 0.0, yaw_rad = 3.14159 }, { x_m = 0.3, y_m = 0.0, yaw_rad = 0.0 }]
[[robot.cameras]]
name = "front"
width = 640
height = 480
rate_hz = 10.0
[agent]
fix_threshold = 60
[[missions]]
robot = 0
kind = "hold"
[[missions]]
robot = 1
kind = "patrol"
waypoints = [[0.3, 0.0], [1.8, 0.0]]
"""

LOST = """
name = "alone"
seed = 2
duration_s = 25.0
[robots]
count = 2
placement = "explicit"
start = [{ x_m = -2.6, y_m = -2.6, yaw_rad = -2.3 }, { x_m = 2.6, y_m = 2.6, yaw_rad = 0.0 }]
[[missions]]
robot = 1
kind = "waypoints"
waypoints = [[0.0, 0.0]]
"""


def _up(tmp: Path, toml: str) -> tuple[dict, list[tuple[float, str]]]:
    scen = tmp / "scenario.toml"
    scen.write_text(toml)
    out = tmp / "run"
    res = subprocess.run([script("tagswarm"), "up", "--scenario", str(scen), "--clock", "lockstep", "--out", str(out),
                          "--no-live", "--no-report"], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    run = json.loads((out / "run.json").read_text())
    with open(out / "modes.csv") as f:
        modes = [(int(r["stamp_ns"]) / 1e9, r["mode"]) for r in csv.DictReader(f) if r["robot"] == "1"]
    return run["counters"]["agent/1"], modes


def test_robot_out_of_sight_rotates_reacquires_and_resets(tmp_path: Path) -> None:
    counters, modes = _up(tmp_path, REACQUIRE)
    # one search at start-up (not localised yet) and at least one after driving away blind
    assert counters["searches"] >= 2, counters
    assert counters["fixes"] >= 2 and counters["lost_events"] == 0, counters
    names = [mo for _, mo in modes]
    # searching -> (tag found) visual -> back on the mission on odometry -> searching again ...
    cycle = ["searching", "visual", "odometry", "searching"]
    it = iter(names)
    assert all(any(n == want for n in it) for want in cycle), names
    assert counters["observations"] >= 2


def test_robot_with_nobody_in_view_ends_lost_not_spinning(tmp_path: Path) -> None:
    counters, modes = _up(tmp_path, LOST)
    assert counters["fixes"] == 0, counters
    assert counters["searches"] == 1 and counters["lost_events"] == 1, counters
    assert modes[-1][1] == "lost" and modes[-2][1] == "lost", modes
