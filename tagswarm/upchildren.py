"""The child processes of ``tagswarm up``: how each is started (its console script, or its module
when the script is not installed beside this interpreter), the flags they all get, how much of a
recording a replay plays, and the order they are stopped in.

:mod:`tagswarm.up` chooses the children of a run, starts them and watches them.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from tagswarm.protocol.busconfig import BusConfig
from tagswarm.protocol.scenario import Scenario
from tagswarm.runtime import procgroup
from tagswarm.runtime.process import child_env

BIN = Path(sys.executable).parent


def script(name: str) -> list[str]:
    path = BIN / name
    if path.exists():
        return [str(path)]
    module = {"tagswarm-world": "tagswarm.world.node", "tagswarm-agent": "tagswarm.agents.node",
              "tagswarm-server": "tagswarm.server.node"}[name]
    return [sys.executable, "-m", module]


class Child(procgroup.Child):
    """One child process (leading its own process group) and its log file; if ``tagswarm up``
    dies without stopping it (SIGKILL, a test's timeout), the reaper takes it down."""

    def __init__(self, name: str, argv: list[str], log: Path) -> None:
        super().__init__(name, argv, log, child_env(os.environ, keep=("TAGSWARM_VIEW_HOST",)))
        self.log = log

    def stop(self, grace_s: float = 10.0) -> None:
        super().stop(grace_s)

    def tail(self, n: int = 15) -> str:
        lines = self.log.read_text(errors="replace").splitlines()
        return "\n".join(lines[-n:])


def replay_end_s(scenario: Scenario) -> float:
    """How much of a recording ``up --replay`` plays: as far as a world would run for the scenario's
    duration (its last step is the first one past the duration)."""
    return scenario.duration_s + 1.5 / scenario.clock.tick_hz


class Stopping:
    """Stops ``children`` (a list filled later) on exit, inside the bus's ``with``, so they end while
    their router (this process) still forwards their last messages: the live view first (browsers
    see its WebSocket close as soon as the run is over), then the others in start order."""

    def __init__(self, children: list[Child]) -> None:
        self.children = children

    def __enter__(self) -> Stopping:
        return self

    def __exit__(self, *exc: object) -> None:
        for c in sorted(self.children, key=lambda c: c.name != "view"):
            c.stop()


def net_flags(net: BusConfig, log_level: str | None = None) -> list[str]:
    """The fault-injection, Zenoh lease and log-level settings ``up`` resolved (flags over
    ``TAGSWARM_*``), as flags for its children, whose environment holds no ``TAGSWARM_*`` (see
    :func:`child_env`); ``up``'s own recorder is never impaired."""
    default = BusConfig()
    out: list[str] = []
    for flag, value, base in (("--net-loss", net.loss, default.loss),
                              ("--net-delay-ms", net.delay_ms, default.delay_ms),
                              ("--net-jitter-ms", net.jitter_ms, default.jitter_ms),
                              ("--net-seed", net.fault_seed, default.fault_seed),
                              ("--zenoh-lease-ms", net.lease_ms, default.lease_ms)):
        if value != base:
            out += [flag, str(value)]
    for key in net.fault_keys:
        out += ["--net-fault-keys", key]
    if log_level is not None:
        out += ["--log-level", log_level]
    return out
