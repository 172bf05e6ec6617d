"""A whole swarm as real OS processes, for the fault, restart, overload and
determinism tests.

The test process is the hub: it listens on a private loopback endpoint, every
process connects to it, and its :class:`~tagswarm.recording.runrecorder.RunRecorder` is
subscribed before anything starts, so no message of a run is missed (``tagswarm
up`` connects its recorder after the world is up and may miss the first ticks).
Processes can be killed and started again one by one.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import time
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path
from typing import IO, Any

import msgspec
import numpy as np

from tagswarm.protocol.bus import Bus, BusConfig, open_bus
from tagswarm.protocol.keys import Keys
from tagswarm.protocol.scenario import Scenario, load_scenario
from tagswarm.recording.runrecorder import RunRecorder
from tests.harness import endpoint, script


def scenario(name: str = "paper", *overrides: str, lockstep: bool = True) -> Scenario:
    """A scenario with every agent and the server as lockstep participants (as ``tagswarm up`` does)."""
    s = load_scenario(name, [*overrides, f'clock.mode="{"lockstep" if lockstep else "realtime"}"'])
    if lockstep:
        parts = [f"agent/{r}" for r in s.robot_ids] + ["server/0"]
        table = msgspec.to_builtins(s)
        table["clock"]["participants"] = parts
        s = msgspec.convert(table, Scenario)
    return s


class Swarm:
    """World, server and agents on a private network, recorded by the test; use as a context manager."""

    def __init__(self, folder: Path, scen: Scenario, run: str) -> None:
        self.folder, self.scenario, self.run = folder, scen, run
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "logs").mkdir(exist_ok=True)
        self.scen_file = folder / "scenario.json"
        self.scen_file.write_bytes(msgspec.json.encode(scen))
        self.ep = endpoint()
        self.keys = Keys(run)
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self._logs: list[IO[bytes]] = []
        self._stack = ExitStack()
        self.bus: Bus = self._stack.enter_context(open_bus(BusConfig(listen=(self.ep,))))
        self.rec = RunRecorder(self.bus, self.keys, scen)

    def __enter__(self) -> Swarm:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ processes
    def common(self) -> list[str]:
        return ["--scenario", str(self.scen_file), "--run", self.run, "--connect", self.ep]

    def start(self, name: str, argv: list[str]) -> subprocess.Popen[bytes]:
        """Start ``argv`` as process ``name`` (a restart gets a fresh log file)."""
        n = sum(1 for p in self.folder.glob(f"logs/{name}*.log"))
        log = open(self.folder / "logs" / f"{name}{'' if n == 0 else f'.{n}'}.log", "wb")
        self._logs.append(log)
        proc = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, env=dict(os.environ, PYTHONUNBUFFERED="1"))
        self.procs[name] = proc
        return proc

    def server(self, *extra: str) -> subprocess.Popen[bytes]:
        return self.start("server", [script("tagswarm-server"), *self.common(), *extra])

    def agent(self, rid: int, *extra: str) -> subprocess.Popen[bytes]:
        return self.start(f"agent{rid}", [script("tagswarm-agent"), *self.common(), "--robot-id", str(rid), *extra])

    def agents(self, *extra: str) -> None:
        for rid in self.scenario.robot_ids:
            self.agent(rid, *extra)

    def world(self, *extra: str) -> subprocess.Popen[bytes]:
        return self.start("world", [script("tagswarm-world"), *self.common(), *extra])

    def kill(self, name: str, sig: int = signal.SIGKILL) -> None:
        proc = self.procs[name]
        proc.send_signal(sig)
        proc.wait(timeout=30)

    def close(self) -> None:
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        for proc in self.procs.values():
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        for log in self._logs:
            log.close()
        self._stack.close()

    # ------------------------------------------------------------------ waiting
    def wait(self, pred: Callable[[], bool], timeout_s: float, what: str) -> None:
        """Poll the recorder until ``pred()`` holds; fail with ``what`` and the log tails if it never does."""

        def check() -> bool:
            self.rec.poll()
            return pred()

        assert self.bus.wait_for(check, timeout_s), f"{what} (after {timeout_s} s)\n{self.tails()}"

    def wait_sim(self, t_s: float, timeout_s: float = 120.0) -> None:
        self.wait(lambda: self.rec.sim_ns >= t_s * 1e9, timeout_s, f"simulated time never reached {t_s} s")

    def finish(self, timeout_s: float = 180.0) -> None:
        """Wait for every process to end by itself (the scenario's duration), then record the rest."""
        deadline = time.monotonic() + timeout_s
        for name, proc in self.procs.items():
            left = max(1.0, deadline - time.monotonic())
            try:
                code = proc.wait(timeout=left)
            except subprocess.TimeoutExpired:
                raise AssertionError(f"{name} did not finish\n{self.tails()}") from None
            assert code in (0, -signal.SIGKILL), f"{name} exited with {code}\n{self.tails()}"
        self.bus.wait(0.2)
        self.rec.poll()

    def tails(self, n: int = 8) -> str:
        out = []
        for log in sorted((self.folder / "logs").glob("*.log")):
            lines = log.read_text(errors="replace").splitlines()[-n:]
            out.append(f"--- {log.name}\n" + "\n".join(lines))
        return "\n".join(out)

    def write(self) -> Path:
        """The run folder's trajectories (TUM, map frame) as ``tagswarm up`` writes them."""
        self.rec.write(self.folder, {"exit_code": 0})
        return self.folder


# ---------------------------------------------------------------------- trajectories
def tum(folder: Path, kind: str, rid: int) -> np.ndarray[Any, Any]:
    """(N, 8) rows of a TUM file: t x y z qx qy qz qw."""
    return np.loadtxt(folder / "trajectories" / f"{kind}_{rid}.tum", ndmin=2)


def errors(truth: list[tuple[int, tuple[float, float, float]]],
           est: list[tuple[int, tuple[float, float, float]]]) -> list[tuple[float, float]]:
    """(t_s, position error in m) of every estimate with a truth sample at the same stamp."""
    at = dict(truth)
    return [(t / 1e9, math.hypot(p[0] - at[t][0], p[1] - at[t][1])) for t, p in est if t in at]


def rms(values: list[float]) -> float:
    return float(np.sqrt(np.mean(np.square(values)))) if values else float("nan")


# ---------------------------------------------------------------------- shared clean runs
_CLEAN: dict[tuple[Any, ...], Path] = {}
PAPER_SEED = 3
PAPER_DURATION_S = 24.0


def clean_run(base: Path, seed: int = PAPER_SEED, duration_s: float = PAPER_DURATION_S, *,
              again: bool = False) -> Path:
    """Folder of a fault-free lockstep run of the paper scenario (trajectories written).
    Cached per (seed, duration) for the whole test session, so the determinism test
    and the fault tests share their reference run; ``again`` forces a new one."""
    key = (seed, duration_s)
    if key in _CLEAN and not again:
        return _CLEAN[key]
    folder = base / f"clean-s{seed}-d{duration_s:g}-{len(_CLEAN)}{'-again' if again else ''}"
    with Swarm(folder, scenario("paper", f"seed={seed}", f"duration_s={duration_s}"), f"clean{seed}") as sw:
        sw.server()
        sw.agents()
        sw.world()
        sw.finish()
        sw.write()
    if not again:
        _CLEAN[key] = folder
    return folder
