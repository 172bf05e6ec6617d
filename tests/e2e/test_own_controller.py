"""Bring your own controller, end to end: ``tagswarm up --agent-module`` drives robot 3 of
the paper scenario (lockstep, seed 0, 20 s) with the example controller
(examples/controllers/circle.py), and the run folder shows that robot driving the
example's circle (not the built-in patrol) while the server localises it like the
built-in agents.  In the same run robot 1's controller raises on every cycle: its agent
logs that once, stands the robot still and keeps serving.  A controller that drives
robot 3 straight at robot 0 (and asks for camera frames) is stopped short of it by the
collision filter.  A broken module stops
``tagswarm up`` and ``tagswarm-agent`` at start with exit code 2 and one line."""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import uuid
from pathlib import Path

import numpy as np
import pytest

from tests.harness import endpoint, script

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "controllers" / "circle.py"
ROBOT = 3
DURATION_S = 20.0
RADIUS_M = 0.15  # examples/controllers/circle.py
START = (2.7, 0.0)  # robot 3's start in the map frame (robot 0's first pose is the map origin)
FAILING = 1
FAILING_SOURCE = """
from tagswarm.agents.controller import Controller


class Broken(Controller):
    mode = "broken"

    def step(self, inputs):
        raise RuntimeError("a controller bug on purpose")


def make_controller(config):
    return Broken()
"""


STRAIGHT_SOURCE = """
from tagswarm.agents.controller import Controller, Twist, gray


class Straight(Controller):
    wants_images = True
    mode = "blind"

    def step(self, inputs):
        # the mode (modes.csv) tells the test what the controller was given: camera frames, then
        # robot 0 seen ahead (x forward, y left in this robot's frame)
        if self.mode == "blind" and any(gray(img).shape == (240, 320) for img in inputs.images.values()):
            self.mode = "seeing"
        if self.mode == "seeing" and any(o.target_kind == "robot" and o.target_id == 0 and o.x_m > 0.3
                                         and abs(o.y_m) < 0.5 * o.x_m for o in inputs.observations):
            self.mode = "sees-robot-0"
        return Twist(0.25, 0.0)  # robot 3 starts facing robot 0, 2.7 m away: contact after about 9 s


def make_controller(config):
    return Straight()
"""


HANGING = 1
HANGING_SOURCE = """
import time

from tagswarm.agents.controller import Controller, Twist


class Hang(Controller):
    def step(self, inputs):
        if inputs.t_s >= 2.0:
            time.sleep(3600)  # a bug: the step never returns
        return Twist(0.0, 0.0)


def make_controller(config):
    return Hang()
"""


def _up(out: Path, duration_s: float, *agent_modules: str, extra: tuple[str, ...] = ()) -> None:
    flags = [f for spec in agent_modules for f in ("--agent-module", spec)]
    res = subprocess.run([script("tagswarm"), "up", "--clock", "lockstep", "--seed", "0", "--duration",
                          str(duration_s), "--listen", endpoint(), "--run", f"own{os.getpid()}x{uuid.uuid4().hex[:6]}",
                          "--out", str(out), "--no-live", *flags, *extra], capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("own") / "run"
    failing = out.parent / "failing_ctrl.py"
    failing.write_text(FAILING_SOURCE)
    _up(out, DURATION_S, f"{EXAMPLE}:{ROBOT}", f"{failing}:{FAILING}")
    return out


def _truth(run: Path, rid: int) -> np.ndarray:
    return np.loadtxt(run / "trajectories" / f"truth_{rid}.tum", ndmin=2)


def _final_error(run: Path, rid: int) -> float:
    truth = _truth(run, rid)
    fused = np.loadtxt(run / "trajectories" / f"fused_{rid}.tum", ndmin=2)
    i = int(np.argmin(np.abs(fused[:, 0] - truth[-1, 0])))
    assert abs(fused[i, 0] - truth[-1, 0]) < 0.1
    return float(np.hypot(fused[i, 1] - truth[-1, 1], fused[i, 2] - truth[-1, 2]))


def test_the_robot_drives_the_example_circle(run: Path) -> None:
    truth = _truth(run, ROBOT)
    assert truth[-1, 0] >= DURATION_S - 0.5
    x, y = truth[:, 1], truth[:, 2]
    yaw = np.unwrap(2.0 * np.arctan2(truth[:, 6], truth[:, 7]))  # planar: qz, qw
    turns = np.diff(yaw)
    # it turns left all the time (the built-in patrol drives straight legs and turns round at each end)
    assert np.mean(turns > 0) >= 0.95, np.mean(turns > 0)
    # a circle of the example's radius about a fixed centre, one radius to its left at the start
    a = np.c_[2 * x, 2 * y, np.ones_like(x)]
    cx, cy, c = np.linalg.lstsq(a, x * x + y * y, rcond=None)[0]
    radius = math.sqrt(c + cx * cx + cy * cy)
    assert radius == pytest.approx(RADIUS_M, abs=0.01)
    assert np.max(np.abs(np.hypot(x - cx, y - cy) - radius)) < 0.02
    # started facing -x: left of it is -y
    assert (cx, cy) == pytest.approx((START[0], START[1] - RADIUS_M), abs=0.02)
    # about v / r * t: more than two laps (the first cycles at half speed, before it is localised)
    assert yaw[-1] - yaw[0] >= 0.8 * 0.1 / RADIUS_M * DURATION_S
    # the built-in patrol would have taken it 1.2 m away, to the other end of its leg
    assert np.max(np.hypot(x - START[0], y - START[1])) <= 2 * RADIUS_M + 0.02


def test_the_agent_reports_the_controller(run: Path) -> None:
    counters = json.loads((run / "run.json").read_text())["counters"][f"agent/{ROBOT}"]
    assert counters["controller_errors"] == 0
    assert counters["controller_cycles"] >= 0.95 * DURATION_S * 30  # one per tick at 30 Hz
    with open(run / "modes.csv") as fh:
        modes = {row["mode"] for row in csv.DictReader(fh) if int(row["robot"]) == ROBOT}
    assert modes == {"circle"}


def test_a_controller_that_raises_stops_its_robot_and_not_its_agent(run: Path) -> None:
    summary = json.loads((run / "run.json").read_text())
    assert summary["exit_codes"][f"agent/{FAILING}"] == 0
    counters = summary["counters"][f"agent/{FAILING}"]
    assert counters["controller_errors"] == counters["controller_cycles"] >= 0.95 * DURATION_S * 30
    truth = _truth(run, FAILING)
    assert np.max(np.hypot(truth[:, 1] - truth[0, 1], truth[:, 2] - truth[0, 2])) < 0.01
    log = (run / "logs" / f"agent{FAILING}.log").read_text()
    assert log.count("Traceback") == 1 and "RuntimeError: a controller bug on purpose" in log


def test_the_server_localises_it_like_the_built_in_agents(run: Path) -> None:
    metrics = json.loads((run / "metrics.json").read_text())
    robots = metrics["robots"]
    mine = robots[str(ROBOT)]["fused"]
    assert _final_error(run, ROBOT) < 0.10
    assert mine["ate_unaligned"]["rmse"] < 0.10
    others = [r["fused"]["time_localised"] for rid, r in robots.items() if int(rid) != ROBOT]
    assert mine["time_localised"] >= min(others) - 0.05, (mine["time_localised"], others)
    assert metrics["swarm"]["contacts"]["robot_robot"] == 0


def test_collision_avoidance_filters_a_controller_driving_into_a_robot(tmp_path: Path) -> None:
    straight = tmp_path / "straight_ctrl.py"
    straight.write_text(STRAIGHT_SOURCE)
    out = tmp_path / "run"
    _up(out, 14.0, f"{straight}:{ROBOT}")
    mine, origin = _truth(out, ROBOT), _truth(out, 0)
    n = min(len(mine), len(origin))
    gap = np.hypot(mine[:n, 1] - origin[:n, 1], mine[:n, 2] - origin[:n, 2])
    footprint = 0.192  # protocol.layout.footprint_radius of the paper robot
    assert gap[0] > 2.5 and gap.min() < 2 * footprint + 0.2  # it did drive up to robot 0 ...
    assert gap.min() >= 2 * footprint + 0.05  # ... and kept (about) the 0.1 m clearance
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["swarm"]["contacts"]["robot_robot"] == 0
    counters = json.loads((out / "run.json").read_text())["counters"][f"agent/{ROBOT}"]
    assert counters["controller_filtered"] > 0 and counters["controller_errors"] == 0
    with open(out / "modes.csv") as fh:
        modes = [row["mode"] for row in csv.DictReader(fh) if int(row["robot"]) == ROBOT]
    assert modes[-1] == "sees-robot-0", modes  # it got its camera frames and its observations


def test_a_broken_module_exits_2_with_one_line(tmp_path: Path) -> None:
    broken = tmp_path / "broken_ctrl.py"
    broken.write_text("import not_a_module_anywhere\n")
    out = tmp_path / "run"
    up = subprocess.run([script("tagswarm"), "up", "--duration", "5", "--out", str(out), "--no-live",
                         "--agent-module", f"{broken}:1"], capture_output=True, text=True, timeout=120)
    lines = up.stderr.strip().splitlines()
    assert up.returncode == 2 and len(lines) == 1, up.stderr
    assert lines[0].startswith(f"tagswarm up: error: --agent-module {broken}: cannot import it: ModuleNotFoundError")
    assert not out.exists()  # nothing was started
    agent = subprocess.run([script("tagswarm-agent"), "--robot-id", "1"], capture_output=True, text=True,
                           timeout=120, env={**os.environ, "TAGSWARM_AGENT_MODULE": "no_such_pkg.ctrl"})
    lines = agent.stderr.strip().splitlines()
    assert agent.returncode == 2 and len(lines) == 1, agent.stderr
    assert lines[0].startswith("tagswarm-agent: error: --agent-module no_such_pkg.ctrl: cannot import it")


def test_a_controller_whose_step_hangs_costs_the_run_a_few_timeouts_and_the_log_says_where(tmp_path: Path) -> None:
    """Robot 1's step never returns from t = 2 s on.  Its agent stays alive (liveliness and all), so
    the lockstep world and the server wait for it: ``clock.ack_timeout_s`` (1 s here) on every tick,
    which made this 8 s run take 180 timeouts (3.4 min); now each stops waiting after
    ``clock.ack_stall_after`` (3) in a row, and the agent logs where the step is stuck."""
    module = tmp_path / "hang.py"
    module.write_text(HANGING_SOURCE)
    out = tmp_path / "run"
    _up(out, 8.0, f"{module}:{HANGING}", extra=("--set", "clock.ack_timeout_s=1.0"))
    summary = json.loads((out / "run.json").read_text())
    world, server = summary["counters"]["world"], summary["counters"]["server"]
    # 3 timeouts stall it (another participant slow for a second on a loaded machine may add one)
    assert world["ack_stalls"] == 1 and 3 <= world["ack_timeouts"] <= 6, world
    assert server["odometry_stalls"] == 1 and 3 <= server["odometry_wait_timeouts"] <= 6, server
    # the others ran to the end
    for rid in (0, 2, 3):
        assert _truth(out, rid)[-1, 0] >= 8.0 - 0.1
    log = (out / "logs" / f"agent{HANGING}.log").read_text()
    assert "the controller Hang's step has not returned for 5 s" in log and "time.sleep(3600)" in log
    assert "missed 3 steps in a row" in (out / "logs" / "world.log").read_text()
    warnings = json.loads((out / "metrics.json").read_text())["warnings"]
    assert any("stopped waiting for a participant alive but silent" in w for w in warnings), warnings
