"""``swarm(...)`` and ``swarm.start(...)``: what the pytest fixture hands a test (usable without
pytest too: ``SwarmFactory(Path("runs/tests"))``)."""

from __future__ import annotations

import itertools
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from tagswarm.testing.live import LiveSwarm
from tagswarm.testing.options import FaultSpec, SwarmSpec
from tagswarm.testing.result import Run
from tagswarm.testing.runfolder import new_run_id


class SwarmFactory:
    """Starts swarms and stops every one of them on :meth:`close` (the fixture's teardown).

    ``folders`` makes a new empty folder for a run from a base name (pytest's
    ``tmp_path_factory.mktemp``) or is a directory under which numbered run folders are made.
    ``cache`` holds finished runs asked for with ``reuse=True`` (the plugin keeps one per
    test session)."""

    def __init__(self, folders: Callable[[str], Path] | Path, cache: dict[Any, Run] | None = None) -> None:
        if isinstance(folders, Path):
            root, counter = folders, itertools.count()

            def numbered(name: str) -> Path:
                while True:
                    path = root / f"{name}{next(counter)}"
                    if not path.exists():
                        path.mkdir(parents=True)
                        return path

            self._folder: Callable[[str], Path] = numbered
        else:
            self._folder = folders
        self._cache = {} if cache is None else cache
        self._live: list[LiveSwarm] = []

    def start(self, scenario: str | Path = "paper", robots: int | None = None, seed: int | None = 0,
              duration_s: float | None = 20.0, clock: str = "lockstep", *, set: Mapping[str, Any] | None = None,
              agent_modules: Mapping[int, str] | None = None, net: FaultSpec = None,
              extra_args: Mapping[str, Sequence[str]] | None = None, launch: bool = True, grace_s: float = 5.0,
              log_level: str = "INFO", **overrides: Any) -> LiveSwarm:
        """Start a swarm and return its live handle (:class:`~tagswarm.testing.live.LiveSwarm`).

        ``scenario``: a built-in name or a TOML path; ``robots``, ``seed``, ``duration_s`` (simulated
        seconds; ``None`` keeps the scenario's value), ``clock`` (``lockstep``: repeatable;
        ``realtime``).  ``set={"agent.avoid": False}`` and keywords such as ``agent__avoid=False``
        override any scenario field.  ``agent_modules={1: "my_pkg.controller"}`` runs robot 1's agent
        with ``--agent-module my_pkg.controller``.  ``net``: a
        :class:`~tagswarm.testing.options.NetFault` for every process or ``{"agent/1": NetFault(...)}``.
        ``extra_args={"server": ["--journal", path]}``: more flags for a process.  ``launch=False``
        starts nothing yet (subscribe first, then :meth:`LiveSwarm.launch`).  ``grace_s``: how long
        processes get between SIGTERM and SIGKILL at the end."""
        spec = SwarmSpec.make(scenario=scenario, robots=robots, seed=seed, duration_s=duration_s, clock=clock,
                              set=set, agent_modules=agent_modules, net=net, extra_args=extra_args,
                              log_level=log_level, **overrides)
        return self._start(spec, launch=launch, grace_s=grace_s)

    def _start(self, spec: SwarmSpec, *, launch: bool, grace_s: float) -> LiveSwarm:
        live = LiveSwarm(spec, self._folder("swarm"), new_run_id(), launch=launch, grace_s=grace_s)
        self._live.append(live)
        return live

    def __call__(self, scenario: str | Path = "paper", robots: int | None = None, seed: int | None = 0,
                 duration_s: float | None = 20.0, clock: str = "lockstep", *, set: Mapping[str, Any] | None = None,
                 agent_modules: Mapping[int, str] | None = None, net: FaultSpec = None,
                 extra_args: Mapping[str, Sequence[str]] | None = None, timeout_s: float = 300.0,
                 plots: bool = False, reuse: bool = False, log_level: str = "INFO", **overrides: Any) -> Run:
        """Run a whole swarm to the end of its ``duration_s`` and return the finished
        :class:`~tagswarm.testing.result.Run` (arguments as :meth:`start`).  ``timeout_s``: wall
        seconds for the whole run.  ``plots``: also draw the report's PNGs.  ``reuse``: a run with
        the same arguments already made in this test session is returned instead of a new one
        (several tests comparing against one reference run)."""
        spec = SwarmSpec.make(scenario=scenario, robots=robots, seed=seed, duration_s=duration_s, clock=clock,
                              set=set, agent_modules=agent_modules, net=net, extra_args=extra_args,
                              log_level=log_level, **overrides)
        key = (spec.same_run_key(), plots)
        if reuse and key in self._cache:
            return self._cache[key]
        with self._start(spec, launch=True, grace_s=5.0) as live:
            run = live.finish(timeout_s, plots=plots)
        if reuse:
            self._cache[key] = run
        return run

    def close(self) -> None:
        """Stop every swarm this factory started (whatever state the test left them in)."""
        errors: list[BaseException] = []
        for live in self._live:
            try:
                live.close()
            except BaseException as exc:  # close the others first, then say what went wrong
                errors.append(exc)
        self._live.clear()
        if errors:
            raise errors[0]
