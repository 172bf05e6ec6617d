"""compose.yaml, run without Docker: every service's command with its environment as a
LOCAL process, in the file's start order (``depends_on`` with ``service_healthy`` waits
for the dependency's own healthcheck command to pass).  The router endpoint
``tcp/router:7447`` is rewritten to a free loopback port that the router service
listens on; every other process is a Zenoh client of it, so all traffic goes through
the router.  The secrets are made by ``tagswarm router --make-secrets`` (what the
compose header tells people to run) and each service's ``/run/secrets/<target>`` is
rewritten to its own host file, so every process logs in with its role's password
and the router enforces the ACL.  The scaled ``agent`` service runs once per robot
(each replica claims its robot id from the recorder, with its own ``--state-dir``).
A 20 s lockstep run of the paper scenario must localise every robot, and the
recorder must leave the run folder (metrics.json) in the ``/runs`` mount."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import time
from collections.abc import Iterator, Mapping
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import pytest

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import BusConfig, open_bus
from tagswarm.protocol.geometry import se2_compose
from tagswarm.protocol.keys import Keys
from tagswarm.protocol.layout import arena_to_map
from tagswarm.world.config import build_config as world_config
from tests.harness import BIN, free_port, script
from tests.unit.deploy.test_compose_file import PASSWORD_FILE, ROUTER_ENDPOINT, load_compose, service_env

DURATION_S = 20.0
MAX_ERROR_M = 0.15
HEALTH_TIMEOUT_S = 60.0


class Service:
    """One compose service as a local process."""

    def __init__(self, name: str, spec: Mapping[str, Any], env: dict[str, str], rewrite: Mapping[str, str],
                 logs: Path, service: str | None = None) -> None:
        self.name = name
        self.service = service or name
        self.spec = spec

        def fix(text: str) -> str:
            for old, new in rewrite.items():
                text = text.replace(old, new)
            return text

        self.env = {k: fix(v) for k, v in env.items()}
        self.argv = [script("tagswarm"), *(fix(a) for a in spec["command"])]
        test = [fix(a) for a in spec["healthcheck"]["test"]]
        self.health = test[1:] if test[0] == "CMD" else ["sh", "-c", test[1]]
        assert test[0] in ("CMD", "CMD-SHELL"), test
        self.log = logs / f"{name}.log"
        self.proc: subprocess.Popen[bytes] | None = None

    def process_env(self) -> dict[str, str]:
        """The container's environment: ours without any TAGSWARM_*/ZENOH_* (isolation) plus
        the service's; the venv's console scripts first on PATH (the image's /usr/local/bin)."""
        base = {k: v for k, v in os.environ.items() if not k.startswith(("TAGSWARM_", "ZENOH_"))}
        base["PATH"] = f"{BIN}{os.pathsep}{base.get('PATH', '')}"
        return {**base, **self.env, "PYTHONUNBUFFERED": "1"}

    def start(self) -> None:
        with open(self.log, "wb") as out:
            self.proc = subprocess.Popen(self.argv, stdout=out, stderr=subprocess.STDOUT, env=self.process_env())

    def check(self) -> subprocess.Popen[bytes]:
        """Start the healthcheck command (as compose would run it inside the container)."""
        return subprocess.Popen(self.health, env=self.process_env(), stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT)

    def stop(self) -> int | None:
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return self.proc.returncode

    def tail(self) -> str:
        return "\n".join(self.log.read_text(errors="replace").splitlines()[-20:]) if self.log.exists() else ""


def wait_healthy(services: list[Service], timeout_s: float = HEALTH_TIMEOUT_S) -> None:
    """Run the healthchecks of ``services`` (in parallel) until each has passed once."""
    pending = {s.name: s for s in services}
    last: dict[str, str] = {}
    deadline = time.monotonic() + timeout_s
    while pending:
        checks = {name: s.check() for name, s in pending.items()}
        for name, check in checks.items():
            out, _ = check.communicate(timeout=30)
            last[name] = out.decode(errors="replace").strip()
            svc = pending[name]
            if check.returncode == 0:
                del pending[name]
            else:
                assert svc.proc is None or svc.proc.poll() is None, f"{name} died:\n{svc.tail()}"
        assert time.monotonic() < deadline, f"never healthy: {[(n, last[n]) for n in sorted(pending)]}"
        if pending:
            time.sleep(0.5)


@contextmanager
def compose_up(services: dict[str, Service]) -> Iterator[dict[str, Service]]:
    """Start every container once its service's ``service_healthy`` dependencies (every
    replica of them) passed their checks."""
    try:
        healthy: set[str] = set()
        todo = dict(services)
        while todo:
            ready = [s for s in todo.values() if set(s.spec.get("depends_on", {})) <= healthy]
            for s in ready:
                for dep, cond in s.spec.get("depends_on", {}).items():
                    assert cond == {"condition": "service_healthy"}, (s.name, dep)
                if s.proc is None:
                    s.start()
                del todo[s.name]
            # wait for what the remaining services depend on and is already running
            needed = {d for s in todo.values() for d in s.spec.get("depends_on", {}) if d not in healthy}
            replicas = [s for s in services.values() if s.service in needed]
            assert ready or all(r.proc is not None for r in replicas), f"dependency cycle among {sorted(todo)}"
            wait_healthy([r for r in replicas if r.proc is not None])
            healthy |= {d for d in needed if all(r.proc is not None for r in services.values() if r.service == d)}
        yield services
    finally:
        for s in services.values():
            s.stop()


def secret_mounts(compose: Mapping[str, Any], service: Mapping[str, Any], folder: Path) -> dict[str, str]:
    """``/run/secrets/<target>`` -> the host file in ``folder`` that compose would mount there."""
    out = {}
    for entry in service.get("secrets", []):
        source, target = (entry, entry) if isinstance(entry, str) else (entry["source"], entry["target"])
        host_file = folder / compose["secrets"][source]["file"].rsplit("/", 1)[1]
        assert host_file.is_file(), f"{source}: {host_file} was not made by tagswarm router --make-secrets"
        out[f"/run/secrets/{target}"] = str(host_file)
    return out


def test_compose_services_as_local_processes_localise_through_the_router(tmp_path: Path) -> None:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    run = f"compose{os.getpid()}"
    host = {"TAGSWARM_RUN": run, "TAGSWARM_CLOCK": "lockstep", "TAGSWARM_DURATION": f"{DURATION_S:g}",
            "TAGSWARM_SEED": "3"}
    secrets = tmp_path / "secrets"
    made = subprocess.run([script("tagswarm"), "router", "--make-secrets", str(secrets)], capture_output=True,
                          text=True, timeout=60)
    assert made.returncode == 0, made.stderr
    compose = load_compose(host)
    spec = compose["services"]
    router_cmd = spec["router"]["command"]
    heartbeat = router_cmd[router_cmd.index("--heartbeat") + 1]
    runs = tmp_path / "runs"
    rewrite = {ROUTER_ENDPOINT: endpoint, "tcp/0.0.0.0:7447": endpoint, heartbeat: str(tmp_path / "router.hb"),
               "/runs": str(runs)}
    services: dict[str, Service] = {}
    robots = int(service_env(spec["world"], host)["TAGSWARM_ROBOTS"])
    for name, s in spec.items():
        if name == "agent":  # --scale agent=<robots>: replicas, each with its own claim folder and marker
            assert s["scale"] == str(robots)
            for i in range(1, robots + 1):
                own = {"/tmp/tagswarm-claim": str(tmp_path / f"claim{i}"), "/tmp/healthy": str(tmp_path / f"ok{i}")}
                services[f"agent-{i}"] = Service(f"agent-{i}", s, service_env(s, host),
                                                 {**rewrite, **secret_mounts(compose, s, secrets), **own}, tmp_path,
                                                 service="agent")
        else:
            services[name] = Service(name, s, service_env(s, host), {
                **rewrite, **secret_mounts(compose, s, secrets), "/tmp/healthy": str(tmp_path / f"ok-{name}")},
                tmp_path)
    for name, s in services.items():
        if name != "router":
            assert s.env["TAGSWARM_ZENOH_MODE"] == "client" and s.env["TAGSWARM_CONNECT"] == endpoint
            assert "TAGSWARM_LISTEN" not in s.env and "--listen" not in s.argv
            user = s.env["TAGSWARM_ZENOH_USER"]
            assert s.env["TAGSWARM_ZENOH_PASSWORD_FILE"] == str(secrets / f"{user}.password")
    assert services["router"].argv[-9:] == ["--listen", endpoint, "--heartbeat", str(tmp_path / "router.hb"),
                                            "--users", str(secrets / "users.txt"), "--acl", "--until-gone",
                                            "recorder/0"]
    assert PASSWORD_FILE not in str(services["world"].env)

    world_env = services["world"].env
    scenario = world_config([], world_env).scenario
    assert scenario.clock.mode == "lockstep" and len(scenario.robot_ids) == 4
    a2m = arena_to_map(scenario)
    keys = Keys(run)
    truth: dict[int, dict[int, tuple[float, float, float]]] = {r: {} for r in scenario.robot_ids}
    fused: dict[int, tuple[int, float, float, float]] = {}
    corrections = 0

    t0 = time.monotonic()
    with ExitStack() as stack:
        # the router first, then our observer (a client of the router, like every service:
        # the read-only viewer; without credentials it could not even connect)
        router = services["router"]
        router.start()
        wait_healthy([router], 30)
        viewer = BusConfig(mode="client", connect=(endpoint,), user="viewer",
                           password_file=str(secrets / "viewer.password"))
        bus = stack.enter_context(open_bus(viewer))
        truth_in = bus.subscribe(keys.truth())
        corr_in = bus.subscribe(keys.correction())
        stack.enter_context(compose_up(services))
        started = time.monotonic() - t0

        # `tagswarm alive` against the running system, with the world's own environment
        world = services["world"]
        wait_healthy([world], 30)
        probe = subprocess.run([script("tagswarm"), "alive", "agent/99", "--timeout", "1"], env=world.process_env(),
                               capture_output=True, text=True, timeout=30)
        assert probe.returncode == 1, probe.stderr
        assert probe.stderr.strip().splitlines() == [
            f"tagswarm alive: agent/99 is not alive (no liveliness token {keys.alive('agent/99')})"]
        ok = subprocess.run([script("tagswarm"), "alive", "world/0"], env=world.process_env(), capture_output=True,
                            text=True, timeout=30)
        assert ok.returncode == 0 and keys.alive("world/0") in ok.stdout, ok.stdout + ok.stderr

        def drain() -> None:
            nonlocal corrections
            for item in truth_in.drain():
                t = codec.decode(m.GroundTruthPose, item.value)
                truth[t.robot_id][t.stamp_ns] = se2_compose(a2m, (t.x_m, t.y_m, t.yaw_rad))
            for item in corr_in.drain():
                c = codec.decode(m.Correction, item.value)
                if c.localised:
                    corrections += 1
                    fused[c.robot_id] = (c.stamp_ns, c.x_m, c.y_m, c.yaw_rad)

        assert world.proc is not None
        deadline = time.monotonic() + 90
        heartbeat_ages = []
        while world.proc.poll() is None and time.monotonic() < deadline:
            bus.wait(0.2)
            drain()
            if (tmp_path / "router.hb").exists():
                heartbeat_ages.append(time.time() - (tmp_path / "router.hb").stat().st_mtime)
        assert world.proc.returncode == 0, world.tail()
        # touched every second all along (the run took far longer than the healthcheck's 5 s)
        assert heartbeat_ages and max(heartbeat_ages) < 2.5, heartbeat_ages
        for name, s in services.items():  # server and agents stop by themselves at the end, then the
            if name != "router":          # recorder writes the run folder and leaves
                assert s.proc is not None
                assert s.proc.wait(timeout=120) == 0, f"{name}:\n{s.tail()}"
        bus.wait(0.5)
        drain()
        assert time.monotonic() - t0 > 10
        # --until-gone recorder/0: the router ends by itself once the recorder left
        assert router.proc is not None and router.proc.wait(timeout=30) == 0, router.tail()
        assert not (tmp_path / "router.hb").exists()  # removed on exit: unhealthy from then on
    wall = time.monotonic() - t0

    end_ns = int(DURATION_S * 1e9)
    assert corrections > 100 * len(scenario.robot_ids)
    errors = {}
    for rid in scenario.robot_ids:
        assert rid in fused, f"robot {rid} was never localised"
        stamp, x, y, _ = fused[rid]
        assert stamp >= end_ns - 100_000_000, f"robot {rid}: last correction at {stamp / 1e9:.2f} s"
        tx, ty, _ = truth[rid][stamp]  # lockstep: the truth of that very tick arrived too
        err = errors[rid] = math.hypot(x - tx, y - ty)
        assert err < MAX_ERROR_M, f"robot {rid}: fused pose {err:.3f} m from the truth at {stamp / 1e9:.2f} s"
    moved = max(math.dist(truth[r][min(truth[r])][:2], truth[r][max(truth[r])][:2]) for r in scenario.robot_ids)
    assert moved > 0.3  # the patrols really drove: the check above is not about parked robots
    # the recorder's run folder: every robot claimed once, and the metrics of the same run
    folders = list(runs.glob(f"{run}-*"))
    assert len(folders) == 1, folders
    kept = json.loads((folders[0] / "run.json").read_text())
    assert sorted(kept["claims"]["taken"]) == list(scenario.robot_ids) and kept["claims"]["refused"] == 0
    assert kept["sim_time_s"] >= DURATION_S - 0.1
    metrics = json.loads((folders[0] / "metrics.json").read_text())
    assert metrics["swarm"]["fused"]["ate_unaligned"]["rmse"] < MAX_ERROR_M
    print(f"compose run: started in {started:.1f} s, {wall:.1f} s wall, final errors [m] {errors}")


@pytest.mark.parametrize("argv", [["alive"], ["alive", "world"], ["alive", "world/0", "--timeout", "0"],
                                  ["alive", "--heartbeat", "x", "world/0"], ["router", "--zenoh-mode", "client"],
                                  ["router", "--bogus"]])
def test_alive_and_router_reject_bad_usage_with_one_line(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    from tagswarm import cli

    try:
        code = cli.main(argv)
    except SystemExit as exc:  # argparse errors exit from inside parse_args
        code = int(exc.code or 0)
    err = capsys.readouterr().err
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and err.startswith(f"tagswarm {argv[0]}: error: "), err


def test_alive_heartbeat_file(tmp_path: Path) -> None:
    from tagswarm.deploy import alive

    hb = tmp_path / "hb"
    assert alive.main(["--heartbeat", str(hb)]) == 1
    hb.touch()
    assert alive.main(["--heartbeat", str(hb), "--max-age", "5"]) == 0
    old = time.time() - 10
    os.utime(hb, (old, old))
    assert alive.main(["--heartbeat", str(hb), "--max-age", "5"]) == 1
    assert alive.main(["--heartbeat", str(hb), "--max-age", "20"]) == 0


def test_router_always_runs_in_router_mode() -> None:
    from tagswarm.deploy import router

    env = {"TAGSWARM_ZENOH_MODE": "client", "TAGSWARM_CONNECT": "tcp/10.0.0.1:7447"}  # a compose-wide env
    cfg = router.router_config(router.parser().parse_args([]), env)
    assert (cfg.mode, cfg.listen, cfg.connect) == ("router", ("tcp/0.0.0.0:7447",), ("tcp/10.0.0.1:7447",))
    cfg = router.router_config(router.parser().parse_args(["--listen", "tcp/127.0.0.1:1", "--zenoh-mode", "router"]),
                               {})
    assert (cfg.mode, cfg.listen, cfg.multicast_scouting) == ("router", ("tcp/127.0.0.1:1",), False)
