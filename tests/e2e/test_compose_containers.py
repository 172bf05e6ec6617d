"""compose.yaml for real: containers built from the repository's Dockerfile, run by
``docker compose`` (Docker Engine, Compose v2; scripts/compose-setup.sh installs and
builds what is missing, once per module).  Two compose projects run at the same time
on this host, each with its own project name, run id and router port:

- ``paper``: the 4-robot paper scenario, 4 agent replicas;
- ``six``: ``TAGSWARM_ROBOTS=6`` with ``--scale agent=6``; a seventh agent started
  meanwhile finds every robot id taken and exits 2 with one line.

Both in lockstep for DURATION_S simulated seconds; ``six`` starts once ``paper``'s
services are up (the runs may overlap).  Asserted on what the runs leave on
the host: each run folder (written by the recorder service, ``tagswarm record-run``)
localises every robot within 10 cm at the end, every container exited 0, and the
runs did not mix (each folder has its own robots and claims).  While ``paper`` runs:
every process in every container runs as the unprivileged user, and an agent
container that logs in with its own claimed credentials and publishes on another
robot's observation key is denied by the router's ACL: a viewer on the host receives
none of those messages (counted: 0 of FORGED) while the same session's messages on its
own robot's key arrive (FORGED of FORGED), and the map is not moved by them (every
robot still within 10 cm).

Skipped when docker cannot be set up here, unless CI is set (then it fails)."""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from tagswarm.protocol.bus import BusConfig, open_bus
from tagswarm.protocol.keys import Keys
from tests.harness import free_port, script

ROOT = Path(__file__).resolve().parents[2]
SETUP = ROOT / "scripts" / "compose-setup.sh"
COMPOSE = ROOT / "compose.yaml"
DURATION_S = 20.0
MAX_ERROR_M = 0.10
FORGED = 20
IMAGE_UID = 10001
RUN_TIMEOUT_S = 600.0
# timings go to the bench results only when asked (a test run leaves the repository as it found it)
TIMINGS_ENV = "TAGSWARM_WRITE_TIMINGS"
TIMINGS = ROOT / "bench" / "results" / "compose_containers.json"
# a cold setup (engine, Compose, base image, image build) takes minutes: more than the suite's 300 s
pytestmark = pytest.mark.timeout(2400)


def _ci() -> bool:
    return os.environ.get("CI", "").lower() not in ("", "0", "false", "no")


@pytest.fixture(scope="module")
def docker_setup() -> dict[str, float]:
    """Run scripts/compose-setup.sh once for the module (engine, Compose, base image, image)."""
    if os.geteuid() != 0 or shutil.which("apt-get") is None:
        reason = "compose-setup.sh needs root and apt-get"
        if _ci():
            pytest.fail(f"CI is set: {reason}")
        pytest.skip(reason)
    t0 = time.monotonic()
    done = subprocess.run(["bash", str(SETUP)], capture_output=True, text=True, timeout=1200)
    took = time.monotonic() - t0
    if done.returncode != 0:
        message = f"scripts/compose-setup.sh failed ({done.returncode}):\n{done.stdout[-2000:]}{done.stderr[-3000:]}"
        if _ci():
            pytest.fail(message)
        pytest.skip(message)
    print(done.stdout)
    return {"setup_s": took}


@dataclass
class Project:
    """One compose project in its own folder (secrets, runs/) with its own run id and port."""

    name: str
    robots: int
    folder: Path
    agents: int = 0
    port: int = field(default_factory=free_port)

    def __post_init__(self) -> None:
        self.agents = self.agents or self.robots
        self.run = f"{self.name}{os.getpid()}"
        self.runs = self.folder / "runs"
        self.runs.mkdir(parents=True)
        os.chown(self.runs, IMAGE_UID, IMAGE_UID)  # the recorder writes as the image's user
        made = subprocess.run([script("tagswarm"), "router", "--make-secrets", str(self.folder / "deploy" / "secrets"),
                               "--robots", str(self.robots)], capture_output=True, text=True, timeout=60)
        assert made.returncode == 0, made.stderr

    @property
    def env(self) -> dict[str, str]:
        base = {k: v for k, v in os.environ.items() if not k.startswith(("TAGSWARM_", "ZENOH_"))}
        return {**base, "TAGSWARM_RUN": self.run, "TAGSWARM_CLOCK": "lockstep", "TAGSWARM_DURATION": f"{DURATION_S:g}",
                "TAGSWARM_SEED": "3", "TAGSWARM_ROBOTS": str(self.robots), "TAGSWARM_PORT": str(self.port)}

    def compose(self, *args: str, timeout: float = 300, check: bool = True) -> subprocess.CompletedProcess[str]:
        argv = ["docker", "compose", "-f", str(COMPOSE), "--project-directory", str(self.folder),
                "-p", f"tagswarm-test-{self.run}", *args]
        done = subprocess.run(argv, capture_output=True, text=True, timeout=timeout, env=self.env)
        if check:
            assert done.returncode == 0, f"{' '.join(args)}: {done.stdout[-2000:]}{done.stderr[-3000:]}"
        return done

    def start(self) -> subprocess.Popen[str]:
        """``up -d`` in the background (it returns once every service started, after the healthchecks)."""
        argv = ["docker", "compose", "-f", str(COMPOSE), "--project-directory", str(self.folder),
                "-p", f"tagswarm-test-{self.run}", "up", "-d", "--no-build", "--scale", f"agent={self.agents}"]
        return subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=self.env)

    def containers(self) -> list[dict[str, object]]:
        out = self.compose("ps", "-a", "--format", "json").stdout.strip()
        if not out:
            return []
        if out.startswith("["):
            items: list[dict[str, object]] = json.loads(out)
            return items
        return [json.loads(line) for line in out.splitlines() if line.strip()]

    def wait_all_exited(self, timeout_s: float = RUN_TIMEOUT_S) -> list[dict[str, object]]:
        deadline = time.monotonic() + timeout_s
        while True:
            items = self.containers()
            if items and all(c["State"] == "exited" for c in items):
                return items
            assert time.monotonic() < deadline, f"{self.name}: still running: " + \
                ", ".join(f"{c['Name']} {c['State']}" for c in items if c["State"] != "exited")
            time.sleep(2)

    def logs(self) -> str:
        return self.compose("logs", "--no-color", "--tail", "30", check=False).stdout[-8000:]

    def down(self) -> None:
        self.compose("down", "-v", "--remove-orphans", "-t", "5", check=False, timeout=180)

    def run_folder(self) -> Path:
        folders = sorted(self.runs.glob(f"{self.run}-*"))
        assert len(folders) == 1, f"{self.name}: run folders {folders} in {self.runs}"
        return folders[0]


def read_tum(path: Path) -> dict[int, tuple[float, float]]:
    """stamp_ns -> (x, y) of a TUM trajectory."""
    out = {}
    for line in path.read_text().splitlines():
        f = line.split()
        out[round(float(f[0]) * 1e9)] = (float(f[1]), float(f[2]))
    return out


def final_errors(folder: Path, robots: int) -> dict[int, float]:
    """Each robot's fused position error at its last correction, against the truth of that tick."""
    errors = {}
    for rid in range(robots):
        fused = read_tum(folder / "trajectories" / f"fused_{rid}.tum")
        truth = read_tum(folder / "trajectories" / f"truth_{rid}.tum")
        assert fused, f"robot {rid} was never localised"
        stamp = max(fused)
        assert stamp >= (DURATION_S - 0.5) * 1e9, f"robot {rid}: last correction at {stamp / 1e9:.2f} s"
        errors[rid] = math.dist(fused[stamp], truth[stamp])
    return errors


FORGER = r"""
import sys, time
from tagswarm.protocol.bus import BusConfig, open_bus
from tagswarm.protocol.keys import Keys
me = int(open("/tmp/tagswarm-claim/robot_id").read())
other = (me + 1) % int(sys.argv[2])
keys = Keys(sys.argv[1])
cfg = BusConfig(mode="client", connect=("tcp/router:7447",), user=f"agent{me}",
                password_file="/tmp/tagswarm-claim/agent.password")
with open_bus(cfg) as bus:
    time.sleep(1.0)
    for i in range(int(sys.argv[3])):
        bus.put(keys.observation(other), b"FORGED-OTHER")  # another robot's key: the ACL denies it
        bus.put(keys.observation(me), b"FORGED-OWN")  # its own key: allowed (undecodable, dropped, counted)
        time.sleep(0.05)
    time.sleep(1.0)
print(me, other)
"""


def forge(project: Project, secrets: Path) -> tuple[int, int, dict[str, int]]:
    """From the second agent container, publish on another robot's and on its own key;
    count on the host, as the viewer, what the router let through."""
    viewer = BusConfig(mode="client", connect=(f"tcp/127.0.0.1:{project.port}",), user="viewer",
                       password_file=str(secrets / "viewer.password"))
    keys = Keys(project.run)
    counts = {"own": 0, "other": 0}
    with open_bus(viewer) as bus:
        inbox = bus.subscribe(keys.observation())
        time.sleep(1.0)
        done = project.compose("exec", "-T", "--index", "2", "agent", "python", "-c", FORGER, project.run,
                               str(project.robots), str(FORGED), timeout=120)
        me, other = (int(x) for x in done.stdout.split())
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and counts["own"] < FORGED:
            bus.wait(0.2)
            for item in inbox.drain():
                if item.value == b"FORGED-OWN" and item.key == keys.observation(me):
                    counts["own"] += 1
                elif item.value.startswith(b"FORGED"):
                    counts["other"] += 1
    return me, other, counts


def uids(project: Project) -> dict[str, set[int]]:
    """Container name -> the uids of every process in it (while it runs)."""
    out: dict[str, set[int]] = {}
    for c in project.containers():
        if c["State"] != "running":
            continue
        # docker top needs the pid column in its ps options
        top = subprocess.run(["docker", "top", str(c["ID"]), "-eo", "pid,uid,args"], capture_output=True, text=True,
                             timeout=30)
        if top.returncode == 0:
            out[str(c["Name"])] = {int(line.split()[1]) for line in top.stdout.splitlines()[1:] if line.strip()}
    return out


@pytest.fixture(scope="module")
def projects(docker_setup: dict[str, float], tmp_path_factory: pytest.TempPathFactory) -> Iterator[list[Project]]:
    base = tmp_path_factory.mktemp("compose")
    made = [Project("paper", 4, base / "paper"), Project("six", 6, base / "six")]
    try:
        yield made
    finally:
        for p in made:
            p.down()
        shutil.rmtree(base, ignore_errors=True)


def test_two_compose_projects_in_containers_localise_and_keep_their_results(
        docker_setup: dict[str, float], projects: list[Project]) -> None:
    paper, six = projects
    t0 = time.monotonic()

    def up(p: Project) -> None:
        proc = p.start()
        out, _ = proc.communicate(timeout=RUN_TIMEOUT_S)
        assert proc.returncode == 0, f"{p.name}: up failed:\n{out[-3000:]}\n{p.logs()}"

    # one after the other: their start-ups (a Python import storm each) would starve each
    # other's healthchecks on two cores
    up(paper)
    started = time.monotonic() - t0
    # while paper runs (its world has started): who runs the processes, and a forged publish
    running = uids(paper)
    me, other, counts = forge(paper, paper.folder / "deploy" / "secrets")

    up(six)
    # a seventh agent for six robots: every id is taken, one line, exit 2
    extra = six.compose("run", "--rm", "--no-deps", "-T", "agent", check=False, timeout=300)
    lines = [ln for ln in (extra.stdout + extra.stderr).splitlines() if ln.startswith("tagswarm")]
    assert extra.returncode == 2, extra.stdout + extra.stderr
    assert lines == ["tagswarm claim: error: no robot for this agent: every robot id is taken (6 robots)"], lines

    results = {p.name: p.wait_all_exited() for p in projects}
    wall = time.monotonic() - t0
    for p in projects:
        codes = {str(c["Name"]): c["ExitCode"] for c in results[p.name]}
        services = sorted(str(c["Service"]) for c in results[p.name])
        assert services == sorted(["router", "recorder", "server", "world", *["agent"] * p.agents]), services
        assert all(code == 0 for code in codes.values()), f"{p.name}: exit codes {codes}\n{p.logs()}"

    # unprivileged: every process of every running container of the paper project
    assert len(running) >= 8 - 1, running  # the router, recorder, server, world and 4 agents (one may be done)
    for name, seen in running.items():
        assert seen == {IMAGE_UID}, f"{name}: processes run as uids {seen}"
    # the ACL: the other robot's key never delivered, its own key delivered (counted on the host)
    assert me != other
    assert counts == {"own": FORGED, "other": 0}, counts

    errors = {}
    for p in projects:
        folder = p.run_folder()
        for name in ("metrics.json", "run.json", "scenario.json"):
            assert (folder / name).is_file(), f"{p.name}: no {name} in {folder}"
        assert list((folder / "plots").glob("*.png")), f"{p.name}: no plots"
        run = json.loads((folder / "run.json").read_text())
        assert run["robots"] == list(range(p.robots))
        assert sorted(run["claims"]["taken"]) == list(range(p.robots))
        assert run["scenario"]["clock"]["participants"] == [*(f"agent/{r}" for r in range(p.robots)), "server/0"]
        assert run["sim_time_s"] >= DURATION_S - 0.5
        metrics = json.loads((folder / "metrics.json").read_text())
        assert set(metrics["robots"]) == {str(r) for r in range(p.robots)} or len(metrics["robots"]) == p.robots
        errors[p.name] = final_errors(folder, p.robots)
        worst = max(errors[p.name].values())
        assert worst < MAX_ERROR_M, f"{p.name}: final errors [m] {errors[p.name]}"
    assert six.run_folder().parent != paper.run_folder().parent
    print(f"compose containers: started in {started:.1f} s, {wall:.1f} s wall; final errors [m] {errors}")
    if not os.environ.get(TIMINGS_ENV):
        return
    TIMINGS.parent.mkdir(parents=True, exist_ok=True)
    TIMINGS.write_text(json.dumps({"setup_s": docker_setup["setup_s"], "up_s": started, "wall_s": wall,
                                   "duration_s": DURATION_S, "python": sys.version.split()[0],
                                   "final_errors_m": errors}, indent=2) + "\n")
