"""The whole system as compose runs it: world + server + one agent per robot,
started by ``tagswarm up`` (real OS processes, private loopback network)."""

from __future__ import annotations

import json
import math
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import psutil
import pytest

from tests.harness import script


def _final_errors(run: Path, rid: int) -> tuple[float, float]:
    truth = np.loadtxt(run / "trajectories" / f"truth_{rid}.tum", ndmin=2)
    fused = np.loadtxt(run / "trajectories" / f"fused_{rid}.tum", ndmin=2)
    odom = np.loadtxt(run / "trajectories" / f"odom_{rid}.tum", ndmin=2)
    t_end = truth[-1]

    def err(est: np.ndarray) -> float:
        i = int(np.argmin(np.abs(est[:, 0] - t_end[0])))
        assert abs(est[i, 0] - t_end[0]) < 0.1
        return math.hypot(est[i, 1] - t_end[1], est[i, 2] - t_end[2])

    return err(fused), err(odom)


@pytest.fixture(scope="module")
def paper_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("paper") / "run"
    res = subprocess.run([script("tagswarm"), "up", "--duration", "60", "--clock", "lockstep", "--seed", "3",
                          "--out", str(out), "--no-live"], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    return out


def test_paper_scenario_localises_every_robot_within_10cm(paper_run: Path) -> None:
    drifts = []
    robots = json.loads((paper_run / "metrics.json").read_text())["robots"]
    for rid in range(4):
        fused_err, odom_err = _final_errors(paper_run, rid)
        assert fused_err < 0.10, f"robot {rid}: fused error {fused_err:.3f} m at the end"
        drifts.append(odom_err)
        if rid != 0:  # the origin holds station: no drift to beat
            # over the whole run, not at the last instant: a drifting odometry can pass near the truth
            # at the end (robot 1's ended 5 mm off with a 14.5 cm RMSE)
            fused, odom = (robots[str(rid)][kind]["ate_unaligned"]["rmse"] for kind in ("fused", "odom"))
            assert odom > 5 * fused, f"robot {rid}: odometry RMSE {odom:.3f} m vs fused {fused:.3f} m"
    assert max(drifts) > 0.10  # the error model really drifts over 60 s


def test_run_folder_is_complete_and_loads_with_evo(paper_run: Path) -> None:
    from evo.tools import file_interface

    for name in ("scenario.json", "run.json", "observations.csv", "modes.csv", "metrics.json",
                 "logs/world.log", "logs/server.log", "logs/agent0.log"):
        assert (paper_run / name).is_file(), name
    for kind in ("truth", "odom", "fused"):
        for rid in range(4):
            traj = file_interface.read_tum_trajectory_file(str(paper_run / "trajectories" / f"{kind}_{rid}.tum"))
            assert traj.num_poses > 1000
            if kind == "truth":  # the world waits for up's recorder (clock.observers): nothing is missed
                assert traj.timestamps[0] == 0.0, traj.timestamps[:3]
    metrics = json.loads((paper_run / "metrics.json").read_text())
    swarm = metrics["swarm"]
    assert swarm["fused"]["ate_unaligned"]["rmse"] < swarm["odom"]["ate_unaligned"]["rmse"]
    assert len(list((paper_run / "plots").glob("*.png"))) >= 4
    run = json.loads((paper_run / "run.json").read_text())
    assert run["exit_code"] == 0 and run["sim_time_s"] >= 59.9
    assert all(run["counters"][f"agent/{r}"]["frames_processed"] > 100 for r in range(4))


def _text(path: Path) -> str:
    """A log's text so far: empty until its process has created it (the children counted above include
    the reaper, so the world may not have opened its log yet; seen once in CI)."""
    return path.read_text() if path.exists() else ""


def test_sigint_stops_every_child_and_still_writes_a_report(tmp_path: Path) -> None:
    out = tmp_path / "run"
    proc = subprocess.Popen([script("tagswarm"), "up", "--duration", "600", "--out", str(out), "--no-live",
                             "--set", "robots.count=2", "--set", "missions=[]",
                             "--set", 'robots.placement="ring"'],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    me = psutil.Process(proc.pid)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and len(me.children(recursive=True)) < 4:
        time.sleep(0.2)
    kids = me.children(recursive=True)
    assert len(kids) >= 4  # server, 2 agents, world
    while time.monotonic() < deadline and "INFO" not in _text(out / "logs" / "world.log"):
        time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=60) == 130
    _gone, alive = psutil.wait_procs(kids, timeout=10)
    assert not alive, f"children still running: {alive}"
    assert (out / "run.json").is_file() and (out / "metrics.json").is_file()
    assert (out / "trajectories" / "truth_0.tum").stat().st_size > 0


def test_a_dying_agent_fails_the_run_with_its_last_log_lines(tmp_path: Path) -> None:
    out = tmp_path / "run"
    proc = subprocess.Popen([script("tagswarm"), "up", "--duration", "600", "--out", str(out), "--no-live",
                             "--no-report", "--set", "robots.count=2", "--set", 'robots.placement="ring"',
                             "--set", "missions=[]"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    me = psutil.Process(proc.pid)
    victim = None
    deadline = time.monotonic() + 60
    while victim is None and time.monotonic() < deadline:
        for child in me.children(recursive=True):
            cmd = " ".join(child.cmdline())
            if "--robot-id 1" in cmd:
                victim = child
        time.sleep(0.2)
    assert victim is not None
    while time.monotonic() < deadline and "agent 1 up" not in _text(out / "logs" / "agent1.log"):
        time.sleep(0.2)
    victim.send_signal(signal.SIGKILL)
    text, _ = proc.communicate(timeout=60)
    assert proc.returncode == 1, text
    assert "agent/1 exited with code -9" in text
    assert "last lines of" in text and "agent 1 up" in text  # the agent's own log tail is shown
    assert json.loads((out / "run.json").read_text())["exit_code"] == 1


@pytest.mark.parametrize("args", [["--scenario", "nope"], ["--robots", "0"], ["--duration", "0"],
                                  ["--duration", "-5"], ["--clock", "warp"], ["--set", "robot.cameras=[{width=-1}]"],
                                  # flags the children would refuse are checked before any child starts
                                  ["--zenoh-lease-ms", "5"], ["--net-loss", "2"], ["--zenoh-config", "/nonexistent"],
                                  ["--listen", "foo:bar"], ["--connect", "tcp/127.0.0.1:7447"],
                                  ["--robot", "3"]])  # no abbreviations: --robot is not --robots
def test_up_rejects_bad_flags_with_one_line(args: list[str], tmp_path: Path) -> None:
    res = subprocess.run([script("tagswarm"), "up", "--out", str(tmp_path / "r"), *args], capture_output=True,
                         text=True, timeout=60)
    assert res.returncode == 2
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "error" in lines[0], res.stderr
    assert not (tmp_path / "r").exists()  # nothing started, nothing written


@pytest.mark.parametrize("kind", ["run folder", "file"])
def test_up_never_writes_into_a_folder_that_holds_files(kind: str, tmp_path: Path) -> None:
    """A second run into the same --out would leave a folder mixing both runs' files."""
    out = tmp_path / "r"
    if kind == "file":
        out.write_text("mine")
    else:
        out.mkdir()
        (out / "metrics.json").write_text("{}")
    res = subprocess.run([script("tagswarm"), "up", "--out", str(out), "--duration", "1", "--no-live"],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2, res.stdout + res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and f"--out {str(out)!r}" in lines[0], res.stderr
    if kind == "file":
        assert out.read_text() == "mine"
    else:
        assert [p.name for p in out.iterdir()] == ["metrics.json"]
