"""What a test asks for, turned into a scenario and command lines (pure: no processes, no network).

- :class:`NetFault`: the receive-side fault layer of a process (``--net-loss``,
  ``--net-delay-ms``, ``--net-fault-keys``, ``--net-seed``; :mod:`tagswarm.protocol.netfaults`).
- :func:`overrides`: ``set={"agent.avoid": False}`` and ``agent__avoid=False`` become the
  scenario overrides ``agent.avoid=false`` (what ``--set`` takes), values written as TOML.
- :class:`SwarmSpec`: everything a run is made of; :meth:`SwarmSpec.build_scenario` resolves it
  as ``tagswarm up`` does (in lockstep every agent and the server are participants).
- :func:`process_names`, :func:`command`: which processes a run has (start order: server,
  agents, world) and the console-script command line of each.
"""

from __future__ import annotations

import json
import math
import re
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import msgspec

from tagswarm.protocol.bus import MAX_DELAY_MS, check_key_expr
from tagswarm.protocol.errors import TagswarmError
from tagswarm.protocol.scenario import Scenario, load_scenario
from tagswarm.protocol.scenario_schema import ScenarioError
from tagswarm.testing.errors import SwarmError, SwarmScenarioError

_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")
_AGENT = re.compile(r"agent/(0|[1-9][0-9]*)")
#: console script -> module, for an environment without the scripts on disk (``python -m``)
SCRIPTS: Mapping[str, str] = {"tagswarm-world": "tagswarm.world.node", "tagswarm-agent": "tagswarm.agents.node",
                              "tagswarm-server": "tagswarm.server.node"}


@dataclass(frozen=True)
class NetFault:
    """Faults on what one process receives: ``loss`` (share 0..1 of matching messages lost),
    ``delay_ms`` (milliseconds added), ``keys`` (key expressions they apply to; empty: the
    default set -- encoders, wheel commands, goals, observations, odometry, the map), ``seed``
    (of the loss pattern: lockstep runs with loss repeat)."""

    loss: float = 0.0
    delay_ms: float = 0.0
    keys: tuple[str, ...] = ()
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0.0 <= self.loss <= 1.0:  # also rejects nan
            raise SwarmError(f"NetFault.loss must be a share between 0 and 1, got {self.loss!r}")
        if not 0.0 <= self.delay_ms <= MAX_DELAY_MS:
            raise SwarmError(f"NetFault.delay_ms must be 0..{MAX_DELAY_MS:g} ms, got {self.delay_ms!r}")
        if isinstance(self.keys, str):
            raise SwarmError("NetFault.keys is a tuple of key expressions, not one string")
        for k in self.keys:
            try:
                check_key_expr(k)
            except TagswarmError as exc:
                raise SwarmError(f"NetFault.keys: {exc}") from None

    def flags(self) -> list[str]:
        """The command-line flags of this fault (every process understands them)."""
        out = ["--net-loss", repr(float(self.loss)), "--net-delay-ms", repr(float(self.delay_ms)),
               "--net-seed", str(int(self.seed))]
        for k in self.keys:
            out += ["--net-fault-keys", k]
        return out


def toml_literal(value: Any, where: str = "value") -> str:
    """``value`` as a TOML literal (what a scenario override's right-hand side is parsed as)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise SwarmError(f"{where}: {value!r} is not a finite number")
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)  # a TOML basic string: JSON's escapes are TOML's
    if isinstance(value, Mapping):
        items = []
        for k, v in value.items():
            if not isinstance(k, str) or not _BARE_KEY.fullmatch(k):
                raise SwarmError(f"{where}: table key {k!r} must be letters, digits, '_' or '-'")
            items.append(f"{k} = {toml_literal(v, f'{where}.{k}')}")
        return "{ " + ", ".join(items) + " }" if items else "{}"
    if isinstance(value, list | tuple):
        return "[" + ", ".join(toml_literal(v, f"{where}[]") for v in value) + "]"
    raise SwarmError(f"{where}: cannot write {type(value).__name__} {value!r} as a scenario value")


def overrides(dotted: Mapping[str, Any] | None = None, keywords: Mapping[str, Any] | None = None) -> tuple[str, ...]:
    """Scenario overrides (``section.field=value``) from ``dotted`` (``{"agent.avoid": False}``)
    and ``keywords`` (``agent__avoid=False``: a double underscore is a dot)."""
    out: list[str] = []
    pairs = [*(dotted or {}).items(), *((k.replace("__", "."), v) for k, v in (keywords or {}).items())]
    for key, value in pairs:
        parts = key.split(".") if isinstance(key, str) else [""]
        if not all(_BARE_KEY.fullmatch(p) for p in parts):
            raise SwarmError(f"scenario override {key!r}: fields are dotted names such as 'agent.avoid'")
        out.append(f"{key}={toml_literal(value, key)}")
    return tuple(out)


FaultSpec = NetFault | Mapping[str, NetFault] | None


@dataclass(frozen=True)
class SwarmSpec:
    """One swarm run: the scenario and its overrides, custom agents, faults and extra flags.

    ``robots``/``seed``/``duration_s`` ``None`` keep the scenario's own value.  ``net`` is one
    :class:`NetFault` for every process, or one per process name (``"world"``, ``"server"``,
    ``"agent/<id>"``).  ``agent_modules`` maps a robot id to the Python module its
    ``tagswarm-agent`` runs (``--agent-module``); ``extra_args`` maps a process name to more
    flags for its command line."""

    scenario: str = "paper"
    robots: int | None = None
    seed: int | None = 0
    duration_s: float | None = 20.0
    clock: Literal["lockstep", "realtime"] = "lockstep"
    overrides: tuple[str, ...] = ()
    agent_modules: tuple[tuple[int, str], ...] = ()
    net: tuple[tuple[str, NetFault], ...] = ()
    net_all: NetFault | None = None
    extra_args: tuple[tuple[str, tuple[str, ...]], ...] = ()
    log_level: str = "INFO"

    @classmethod
    def make(cls, *, scenario: str | Path = "paper", robots: int | None = None, seed: int | None = 0,
             duration_s: float | None = 20.0, clock: str = "lockstep", set: Mapping[str, Any] | None = None,
             agent_modules: Mapping[int, str] | None = None, net: FaultSpec = None,
             extra_args: Mapping[str, Sequence[str]] | None = None, log_level: str = "INFO",
             **keyword_overrides: Any) -> SwarmSpec:
        """Validate what a test passed (see :func:`tagswarm.testing.factory.SwarmFactory.__call__`)."""
        if clock not in ("lockstep", "realtime"):
            raise SwarmError(f"clock must be 'lockstep' or 'realtime', got {clock!r}")
        if robots is not None and (isinstance(robots, bool) or not isinstance(robots, int) or robots < 1):
            raise SwarmScenarioError(f"robots must be a positive integer, got {robots!r}")
        if duration_s is not None and not (isinstance(duration_s, int | float) and 0 < duration_s < math.inf):
            raise SwarmScenarioError(f"duration_s must be a positive number of simulated seconds, got {duration_s!r}")
        modules: list[tuple[int, str]] = []
        for rid, mod in sorted((agent_modules or {}).items()):
            if not isinstance(rid, int) or not isinstance(mod, str) or not mod:
                raise SwarmError(f"agent_modules maps a robot id to a module name, got {rid!r}: {mod!r}")
            modules.append((rid, mod))
        per: list[tuple[str, NetFault]] = []
        net_all = None
        if isinstance(net, NetFault):
            net_all = net
        elif net is not None:
            for name, fault in sorted(net.items()):
                check_name(name)
                if not isinstance(fault, NetFault):
                    raise SwarmError(f"net[{name!r}] must be a NetFault, got {fault!r}")
                per.append((name, fault))
        extra = []
        for name, args in sorted((extra_args or {}).items()):
            check_name(name)
            if isinstance(args, str):
                raise SwarmError(f"extra_args[{name!r}] is a list of arguments, not one string")
            extra.append((name, tuple(str(a) for a in args)))
        return cls(scenario=str(scenario), robots=robots, seed=seed,
                   duration_s=None if duration_s is None else float(duration_s), clock=clock,  # type: ignore[arg-type]
                   overrides=overrides(set, keyword_overrides), agent_modules=tuple(modules), net=tuple(per),
                   net_all=net_all, extra_args=tuple(extra), log_level=log_level)

    def scenario_overrides(self) -> list[str]:
        """Every override, in the order ``--set`` would apply them (the explicit ones last)."""
        out = [f'clock.mode="{self.clock}"']
        if self.seed is not None:
            out.append(f"seed={int(self.seed)}")
        if self.duration_s is not None:
            out.append(f"duration_s={self.duration_s!r}")
        if self.robots is not None:
            out.append(f"robots.count={int(self.robots)}")
        return [*out, *self.overrides]

    def same_run_key(self) -> tuple[object, ...]:
        """What makes two specs the same run: the resolved scenario (so ``robots=None`` and the
        scenario's own count are one run) and everything outside it.  SwarmScenarioError if invalid."""
        return (msgspec.json.encode(self._load()), self.agent_modules, self.net, self.net_all, self.extra_args,
                self.log_level)

    def _load(self) -> Scenario:
        """The scenario with this spec's overrides, as ``--set`` would give it; SwarmScenarioError if invalid."""
        try:
            return load_scenario(self.scenario, self.scenario_overrides())
        except ScenarioError as exc:
            raise SwarmScenarioError(str(exc)) from None

    def build_scenario(self) -> Scenario:
        """The resolved scenario; in lockstep every agent and the server ack each tick (as in
        ``tagswarm up``) unless the scenario names its participants.  SwarmScenarioError if invalid."""
        s = self._load()
        if s.clock.mode == "lockstep" and not s.clock.participants:
            table = msgspec.to_builtins(s)
            table["clock"]["participants"] = [f"agent/{r}" for r in s.robot_ids] + ["server/0"]
            s = msgspec.convert(table, Scenario)
        for rid, mod in self.agent_modules:
            if rid not in s.robot_ids:
                raise SwarmError(f"agent_modules: robot {rid} is not in the scenario (robots {list(s.robot_ids)})")
            from tagswarm.agents.controller import ControllerConfig, load_factory, make

            try:  # as the agent will, before anything starts: a broken module is one line, not a dead agent
                make(load_factory(mod), ControllerConfig(rid, s), mod)
            except TagswarmError as exc:
                raise SwarmError(f"agent_modules[{rid}]: {exc}") from None
        names = set(process_names(s))
        for name in [n for n, _ in self.net] + [n for n, _ in self.extra_args]:
            if name not in names:
                raise SwarmError(f"no process {name!r} in this run (processes: {', '.join(sorted(names))})")
        return s

    def fault(self, name: str) -> NetFault | None:
        """The fault layer process ``name`` starts with (a per-process one wins)."""
        return dict(self.net).get(name, self.net_all)

    def agent_module(self, name: str) -> str | None:
        """The controller module process ``name`` runs, if it is an agent given one."""
        m = _AGENT.fullmatch(name)
        return dict(self.agent_modules).get(int(m.group(1))) if m else None

    def extra(self, name: str) -> tuple[str, ...]:
        """Flags the test asked for on ``name``'s command line, ``--agent-module`` included."""
        out = dict(self.extra_args).get(name, ())
        module = self.agent_module(name)
        return (*out, "--agent-module", module) if module else out


def check_name(name: str) -> str:
    """``name`` if it names a process of a swarm (``world``, ``server``, ``agent/<id>``)."""
    if name in ("world", "server") or (isinstance(name, str) and _AGENT.fullmatch(name)):
        return name
    raise SwarmError(f"process names are 'world', 'server' and 'agent/<robot id>', got {name!r}")


def process_names(scenario: Scenario) -> list[str]:
    """Every process of a run, in start order: server, agents, world (the world comes last so
    that in realtime nobody misses its first messages; in lockstep it waits for them anyway)."""
    return ["server", *(f"agent/{r}" for r in scenario.robot_ids), "world"]


def log_name(name: str) -> str:
    """File stem of a process's log (``agent/3`` -> ``agent3``)."""
    return name.replace("/", "")


def script(name: str, bin_dir: Path | None = None) -> list[str]:
    """The console script ``name`` next to this Python, else ``python -m`` its module."""
    path = (bin_dir or Path(sys.executable).parent) / name
    return [str(path)] if path.exists() else [sys.executable, "-m", SCRIPTS[name]]


def command(name: str, common: Sequence[str], extra: Sequence[str] = (), fault: NetFault | None = None,
            bin_dir: Path | None = None) -> list[str]:
    """Command line of process ``name``: its console script, the ``common`` flags (scenario,
    run, network), the fault flags, then ``extra``."""
    check_name(name)
    if name == "world":
        head = script("tagswarm-world", bin_dir)
    elif name == "server":
        head = script("tagswarm-server", bin_dir)
    else:
        head = [*script("tagswarm-agent", bin_dir), "--robot-id", name.split("/")[1]]
    return [*head, *common, *(fault.flags() if fault is not None else ()), *extra]


