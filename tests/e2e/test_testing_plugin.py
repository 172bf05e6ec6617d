"""The shipped pytest plugin (tagswarm.testing) as a user meets it: a test file in a temporary
directory outside the repository, no conftest, run by ``python -m pytest`` in a subprocess
with only the installed package.

- a finished run (every robot localised within 10 cm at the end), a run with the user's own
  controller module on one robot (``agent_modules``), and a live handle (map, subscription,
  goal, teleport, kill, restart with network faults, freeze) pass;
- two such pytest processes at once do not mix: different run ids, each run's metrics and
  counters name only its own robots;
- no process of a swarm survives a test that fails, one that pytest-timeout stops (its
  ``signal`` method: teardown runs; its ``thread`` method: ``os._exit``, only the reaper is
  left), or a pytest interrupted with SIGINT (psutil: every descendant seen during the run is
  gone, and no process on the machine carries the run id).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import psutil
import pytest

REPO = Path(__file__).resolve().parents[2]

USER_TESTS = '''
import json, math, os, signal, sys
from pathlib import Path

import pytest

from tagswarm.testing import NetFault, SwarmError, SwarmTimeout

OUT = Path(os.environ["TSW_OUT"])
ROBOTS = int(os.environ["TSW_ROBOTS"])


def test_only_the_installed_package():
    import tagswarm
    assert not any(Path(p or ".").resolve() == Path({repo!r}) for p in sys.path), sys.path
    assert "tests" not in sys.modules


def test_a_finished_run_localises_every_robot(swarm):
    run = swarm(scenario="paper", robots=ROBOTS, seed=0, duration_s=8)
    errors = {{r: run.final_error(r) for r in run.robots}}
    assert run.robots == tuple(range(ROBOTS))
    assert all(e < 0.10 for e in errors.values()), errors
    truth = run.truth(1)
    assert truth.shape[1] == 4 and truth[-1, 0] >= 7.9
    info = json.loads((run.run_dir / "run.json").read_text())
    OUT.write_text(json.dumps({{"run_id": run.run_id, "robots": run.metrics["run"]["robots"],
                               "metric_robots": sorted(run.metrics["robots"]), "counters": sorted(info["counters"]),
                               "errors": errors}}))


def test_my_own_controller_drives_robot_1(swarm):
    run = swarm(robots=2, duration_s=6, agent_modules={{1: "my_controller"}})  # next to this file
    start = run.truth(1)[0]
    assert max(math.dist(row[1:3], start[1:3]) for row in run.truth(1)) < 0.02  # held, did not patrol
    assert "held" in (run.run_dir / "modes.csv").read_text()
    assert run.final_error(1) < 0.10  # localised by the server like the built-in agent
    assert run.counters("agent/1")["controller_errors"] == 0 and run.counters("agent/1")["controller_cycles"] > 150
    assert not [w for w in run.metrics["warnings"] if "controller" in w]


def test_a_live_swarm(swarm):
    with swarm.start(robots=3, duration_s=16) as s:
        odo = s.subscribe("robot/1/odometry")
        s.wait_sim(2.0)
        first = odo.get(timeout_s=60)
        assert first.msg.robot_id == 1 and first.key == f"tagswarm/{{s.run_id}}/robot/1/odometry"
        assert {{e.robot_id for e in s.latest_map(after_s=1.0).robots}} == {{0, 1, 2}}
        _, (x, y, _) = s.recorder.truth[1][-1]  # map frame
        for bad, why in (((7, x, y), "no robot 7 in this run"), ((1, 40.0, 0.0), "would refuse it: a robot there")):
            with pytest.raises(SwarmError, match=why):  # said at once, not a timeout later
                s.goto(*bad)
        with pytest.raises(SwarmError, match="would not be inside the arena walls"):
            s.teleport(2, 40.0, 0.0)
        with pytest.raises(SwarmError, match="goto: X and Y must be finite"):
            s.goto(1, float("nan"), 0.0)
        with pytest.raises(SwarmError, match="has passed"):
            s.teleport(2, 0.3, 0.0, push=True, at_s=0.5)
        s.goto(1, x, y + 0.4, tolerance_m=0.05)
        s.wait(lambda: math.dist(s.recorder.truth[1][-1][1][:2], (x, y + 0.4)) < 0.1, 120, "robot 1 never arrived")
        cmd = s.teleport(2, 0.3, 0.0, push=True, at_s=round(s.sim_time_s) + 1.0)

        def jumped():
            tr = s.recorder.truth[2]
            return any(math.dist(a[1][:2], b[1][:2]) > 0.25 for a, b in zip(tr, tr[1:]) if b[0] >= cmd.stamp_ns)

        s.wait(jumped, 120, "robot 2 was never moved")
        odo2 = s.subscribe("robot/2/odometry")
        s.kill("agent/2")
        killed_ns = s.recorder.sim_ns
        assert s.process("agent/2").returncode == -signal.SIGKILL
        with pytest.raises(SwarmError, match="agent/2 is not running"):  # at once, not after timeout_s
            s.goto(2, 0.0, 0.0, timeout_s=600)
        s.spawn("agent/2", net=NetFault(loss=0.05, seed=2))
        assert odo2.get(timeout_s=120, where=lambda smp: smp.msg.stamp_ns > killed_ns).msg.robot_id == 2
        s.freeze("agent/0")
        assert s.running("agent/0")
        s.thaw("agent/0")
        run = s.finish()
        with pytest.raises(SwarmTimeout, match="the world ended"):  # at once, not after timeout_s
            s.wait_sim(1000.0, timeout_s=600)
        with pytest.raises(SwarmTimeout, match="and the run has ended"):
            odo.get(timeout_s=600, where=lambda smp: False)
    with pytest.raises(SwarmError, match="no log of 'agnet/1'"):
        run.log("agnet/1")
    assert run.log("server/0") == run.log("server") and "server" in run.log("server")
    assert run.counters("world")["world_commands"] == 1 and run.counters("agent/1")["fixes"] > 0
    assert "injecting network faults" in run.log("agent/2.1") and "injecting" not in run.log("agent/2")
    assert run.exit_codes == {{"server": 0, "agent/0": 0, "agent/1": 0, "agent/2": 0, "world": 0}}
    assert run.metrics["run"]["robots"] == [0, 1, 2]
    assert run.final_error(0) < 0.10 and run.final_error(1) < 0.10
'''

#: a controller in the user's project (tagswarm.agents.controller's contract): robot 1 stands still
USER_CONTROLLER = '''
from tagswarm.agents.controller import Controller, Twist


class Hold(Controller):
    mode = "held"

    def step(self, inputs):
        return Twist(v_m_s=0.0, w_rad_s=0.0)


def make_controller(config):
    return Hold()
'''

#: a swarm is up (its run id written to $TSW_READY), then the test fails, hangs or is interrupted
STRAY_TESTS = '''
import os
import signal
from pathlib import Path

import pytest

READY = Path(os.environ["TSW_READY"])


def _up(swarm):
    s = swarm.start(robots=2, duration_s=600)
    s.wait_sim(0.5)
    # what a Ctrl-C meets in this process, for the outer test's report if the interrupt is lost
    Path(str(READY) + ".signals").write_text(f"SIGINT handler {signal.getsignal(signal.SIGINT)!r}, main thread "
                                             f"mask {sorted(signal.pthread_sigmask(signal.SIG_BLOCK, []))}")
    tmp = Path(str(READY) + ".tmp")
    tmp.write_text(s.run_id)
    tmp.rename(READY)  # the outer test interrupts as soon as READY exists: it must hold the whole run id
    return s


def test_fails(swarm):
    with _up(swarm) as s:
        assert s.sim_time_s < 0, "fails on purpose"


@pytest.mark.timeout(25, method="signal")
def test_times_out(swarm):
    s = _up(swarm)
    s.wait_sim(1e9, timeout_s=1e9)


@pytest.mark.timeout(25, method="thread")
def test_times_out_hard(swarm):
    s = _up(swarm)
    s.wait_sim(1e9, timeout_s=1e9)


def test_interrupted(swarm):
    s = _up(swarm)
    s.wait_sim(1e9, timeout_s=1e9)
'''


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTEST_ADDOPTS", "PYTEST_PLUGINS")}
    return {**env, **extra}


#: ``python -m pytest`` as a terminal starts it: Ctrl-C raises KeyboardInterrupt.  A process started in
#: the background by a shell without job control (``cmd &`` in a script, as a CI runner may) inherits
#: SIGINT ignored, and Python then leaves it ignored: the interrupted pytest below would never see its
#: SIGINT (three local full runs hung that way, the first SIGINT lost and the test process still waiting)
_AS_IN_A_TERMINAL = ("import signal, sys, pytest; signal.signal(signal.SIGINT, signal.default_int_handler); "
                     "sys.exit(pytest.console_main())")


def _pytest(folder: Path, test_file: str, *args: str, **env: str) -> subprocess.Popen[str]:
    """``python -m pytest`` on ``test_file`` with ``folder`` as its working directory (outside the repo),
    Ctrl-C handled as in a terminal whatever this process inherited."""
    return subprocess.Popen([sys.executable, "-c", _AS_IN_A_TERMINAL, "-p", "no:cacheprovider", "-q", "-rA",
                             f"--basetemp={folder / 'tmp'}", test_file, *args], cwd=folder, env=_env(**env),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _outside(tmp_path_factory: pytest.TempPathFactory, name: str) -> Path:
    folder = tmp_path_factory.mktemp(name)
    assert not folder.resolve().is_relative_to(REPO)
    assert not (folder / "conftest.py").exists()
    return folder


def test_a_user_test_file_passes_outside_the_repo_and_two_run_in_parallel_without_mixing(
        tmp_path_factory: pytest.TempPathFactory) -> None:
    procs: dict[int, tuple[subprocess.Popen[str], Path]] = {}
    started: dict[int, float] = {}
    for robots in (2, 3):
        folder = _outside(tmp_path_factory, f"user{robots}")
        (folder / "test_my_swarm.py").write_text(USER_TESTS.format(repo=str(REPO)))
        (folder / "my_controller.py").write_text(USER_CONTROLLER)
        started[robots] = time.monotonic()
        procs[robots] = (_pytest(folder, "test_my_swarm.py", TSW_OUT=str(folder / "out.json"),
                                 TSW_ROBOTS=str(robots)), folder)
    results: dict[int, dict[str, Any]] = {}
    ended: dict[int, float] = {}
    for robots, (proc, folder) in procs.items():
        out, _ = proc.communicate(timeout=900)
        ended[robots] = time.monotonic()
        assert proc.returncode == 0 and "4 passed" in out, out[-6000:]
        results[robots] = json.loads((folder / "out.json").read_text())
    print(json.dumps({"results": results, "wall_s": {r: ended[r] - started[r] for r in procs}}, indent=1))
    # both pytest processes ran at the same time (each took minutes, they started together)
    assert started[3] < ended[2] and started[2] < ended[3]
    a, b = results[2], results[3]
    assert a["run_id"] != b["run_id"]
    for robots, res in results.items():
        assert res["robots"] == list(range(robots)), res
        assert res["metric_robots"] == [str(r) for r in range(robots)], res
        assert res["counters"] == sorted([*(f"agent/{r}" for r in range(robots)), "server", "world"]), res


def _descendants(pid: int, cmdlines: dict[psutil.Process, str]) -> None:
    """Add every live descendant of ``pid`` with its command line (read now: a dead process has none)."""
    try:
        children = psutil.Process(pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return
    for p in children:
        # read again each time: a child caught between fork and exec still shows its parent's command line
        try:
            cmd = " ".join(p.cmdline())
        except psutil.Error:
            cmd = ""
        if cmd or p not in cmdlines:
            cmdlines[p] = cmd


def _signal_state(pid: int, ready: Path) -> str:
    """Signal masks and dispositions of ``pid`` and each of its threads (/proc), with what the
    test wrote when its swarm was up (``<ready>.signals``): what a lost SIGINT met."""
    note = Path(f"{ready}.signals")
    lines = [note.read_text() if note.exists() else "no signal note"]
    for status in [Path(f"/proc/{pid}/status"), *sorted(Path(f"/proc/{pid}/task").glob("*/status"))]:
        try:
            fields = dict(line.split(":", 1) for line in status.read_text().splitlines() if ":" in line)
        except OSError:
            continue
        lines.append(f"{status.parent.name} {fields.get('Name', '').strip()}: " + " ".join(
            f"{k}={fields.get(k, '').strip()}" for k in ("SigPnd", "ShdPnd", "SigBlk", "SigIgn", "SigCgt")))
    return "\n".join(lines)


def _with_run_id(run_id: str) -> list[psutil.Process]:
    found = []
    for p in psutil.process_iter(["cmdline"]):
        try:
            if run_id in " ".join(p.info["cmdline"] or ()) and p.status() != psutil.STATUS_ZOMBIE:
                found.append(p)
        except psutil.Error:
            pass
    return found


def _alive(procs: list[psutil.Process]) -> list[psutil.Process]:
    out = []
    for p in procs:
        try:
            if p.is_running() and p.status() != psutil.STATUS_ZOMBIE:
                out.append(p)
        except psutil.NoSuchProcess:
            pass
    return out


@pytest.mark.parametrize(("case", "code"), [("test_fails", 1), ("test_times_out", 1), ("test_times_out_hard", 1),
                                            ("test_interrupted", 2)])
def test_no_process_survives_a_failed_timed_out_or_interrupted_test(
        tmp_path_factory: pytest.TempPathFactory, case: str, code: int) -> None:
    folder = _outside(tmp_path_factory, case)
    (folder / "test_strays.py").write_text(STRAY_TESTS)
    ready = folder / "ready"
    proc = _pytest(folder, f"test_strays.py::{case}", TSW_READY=str(ready))
    seen: dict[psutil.Process, str] = {}
    interrupted = False
    deadline = time.monotonic() + 200  # within pytest-timeout's 300 s, so that a hang shows where it hangs
    while proc.poll() is None:
        if time.monotonic() > deadline:
            report = _signal_state(proc.pid, ready)
            # faulthandler (on in every pytest) prints every thread's stack on SIGABRT
            proc.send_signal(signal.SIGABRT)
            out, _ = proc.communicate(timeout=30)
            pytest.fail(f"the pytest run never ended (interrupted: {interrupted}):\n{report}\n{out[-12000:]}")
        _descendants(proc.pid, seen)
        if case == "test_interrupted" and ready.exists() and not interrupted:
            note = Path(f"{ready}.signals").read_text()
            assert note.startswith("SIGINT handler <built-in function default_int_handler>, main thread mask []"), note
            proc.send_signal(signal.SIGINT)  # what Ctrl-C in a terminal sends to the foreground pytest
            interrupted = True
            deadline = min(deadline, time.monotonic() + 90)
        time.sleep(0.2)  # sampling the process tree, not waiting for a result
    out = proc.stdout.read() if proc.stdout else ""
    assert proc.returncode == code, out[-6000:]
    run_id = ready.read_text()
    with_id = [cmd for cmd in seen.values() if run_id in cmd]
    # the swarm was up while the test ran: server, two agents and the world carry its run id
    assert len(with_id) >= 4, list(seen.values())
    # the reaper acts once the pytest process is gone (os._exit): give the kernel a moment to deliver its SIGKILL
    left = _alive(list(seen))
    until = time.monotonic() + 15
    while left and time.monotonic() < until:
        time.sleep(0.1)
        left = _alive(list(seen))
    assert left == [], [(p.pid, seen[p]) for p in left]
    assert _with_run_id(run_id) == []
    print(json.dumps({"case": case, "exit_code": proc.returncode, "processes_seen": len(seen),
                      "with_run_id": len(with_id)}))


# ---------------------------------------------------------------------- errors, in this process
def test_a_process_that_dies_early_is_reported_at_once_with_its_log(swarm: Any) -> None:
    from tagswarm.testing import SwarmProcessDied

    with swarm.start(robots=2, duration_s=5, extra_args={"server": ["--lag", "-1"]}) as s:
        # reported when it dies, not when the wait runs out: that would be a SwarmTimeout, and after pytest's timeout
        with pytest.raises(SwarmProcessDied) as failed:
            s.wait_sim(4.0, timeout_s=3600)
    assert failed.value.name == "server" and failed.value.code == 2
    assert "tagswarm-server: error: --lag must be > 0" in str(failed.value)  # the log's tail


def test_a_wait_that_runs_out_says_what_and_shows_the_logs(swarm: Any) -> None:
    from tagswarm.protocol.errors import TagswarmError
    from tagswarm.testing import SwarmTimeout

    with swarm.start(robots=2, duration_s=5) as s:
        s.freeze("world")  # nothing moves any more
        with pytest.raises(SwarmTimeout) as late:
            s.wait_sim(4.0, timeout_s=3)
        pids = [s.pid(n) for n in s.names]
    assert isinstance(late.value, TagswarmError)
    assert "simulated time never reached 4 s" in str(late.value) and "--- world.log" in str(late.value)
    assert not any(psutil.pid_exists(p) and psutil.Process(p).status() != psutil.STATUS_ZOMBIE for p in pids)


def test_a_process_that_outlives_the_world_is_stopped_and_named(swarm: Any) -> None:
    with swarm.start(robots=2, duration_s=3) as s:
        s.wait(lambda: not s.running("world"), 120, "the world never finished")
        s.restart("agent/1")  # too late: it waits for a world that is gone
        s.wait_exit(linger_s=2.0)
        run = s.write()
    assert s.stopped_at_end == ["agent/1"]
    assert run.exit_codes["agent/1"] in (0, -signal.SIGTERM) and run.exit_codes["world"] == 0
    assert json.loads((run.run_dir / "run.json").read_text())["stopped_at_end"] == ["agent/1"]
