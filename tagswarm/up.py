"""``tagswarm up``: run a whole swarm on one host and write a run folder.

Starts the server, one agent per robot and the world as separate OS processes
(the same console scripts compose runs) on a private Zenoh network, shows live
progress, and on the end (or Ctrl-C, or a child dying) stops every child and
writes ``runs/<timestamp>/``: the resolved scenario, per-process logs, TUM
trajectories, ``metrics.json`` and plots.
"""

from __future__ import annotations

import os
import re
import signal
import socket
import sys
import threading
import time
from collections.abc import Sequence
from datetime import datetime
from pathlib import Path
from typing import Any

import msgspec
from rich.console import Console
from rich.live import Live
from rich.table import Table

from tagswarm.agents.controller import ControllerConfig, load_factory, make
from tagswarm.protocol.bus import BusConfig, BusError, open_bus, zenoh_config
from tagswarm.protocol.keys import Keys
from tagswarm.protocol.layout import pinned
from tagswarm.protocol.scenario import Scenario
from tagswarm.recording.runrecorder import RunRecorder
from tagswarm.runtime import procgroup
from tagswarm.runtime.config import (
    ConfigError,
    Invocation,
    OneLineParser,
    add_common_args,
    bus_from,
    scenario_from,
)
from tagswarm.runtime.process import run_main, setup_logging
from tagswarm.upchildren import Child, Stopping, net_flags, replay_end_s, script
from tagswarm.upsummary import print_controller_trouble, print_summary


def free_endpoint() -> str:
    """A loopback TCP endpoint on a port that is free right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def parser() -> OneLineParser:
    p = OneLineParser(prog="tagswarm up", description=__doc__)
    add_common_args(p)
    p.add_argument("--out", type=Path, help="run folder (default runs/<timestamp>)")
    p.add_argument("--no-live", action="store_true", help="plain log lines instead of the live table")
    p.add_argument("--no-report", action="store_true", help="do not compute metrics and plots at the end")
    p.add_argument("--record", type=Path, metavar="FILE.mcap",
                   help="also record every message of the run to an MCAP file (as tagswarm record does)")
    p.add_argument("--replay", type=Path, metavar="FILE.mcap",
                   help="no world: replay a recording's world streams in lockstep into fresh agents and server "
                        "(scenario: the recorded one unless --scenario)")
    p.add_argument("--view", nargs="?", const=8765, type=int, metavar="PORT",
                   help="also serve the live web view (tagswarm view) on http://127.0.0.1:PORT/ (default 8765)")
    p.add_argument("--agent-module", action="append", metavar="MODULE[:ROBOTS]",
                   help="drive robots ROBOTS (e.g. 1,3; default all) with your own controller: a module importable "
                        "here and in the agents (pkg.mod, see PYTHONPATH) or a .py file, defining "
                        "make_controller(config) (docs/controllers.md); repeatable; env TAGSWARM_AGENT_MODULE "
                        "(';'-separated)")
    return p


AGENT_MODULE_ENV = "TAGSWARM_AGENT_MODULE"


def agent_modules(specs: Sequence[str], robot_ids: Sequence[int], scenario: Scenario | None = None,
                  run: str = "default") -> dict[int, str]:
    """Robot id -> controller module from ``MODULE[:ROBOTS]`` specs; each module is imported
    here first and, given the ``scenario``, its ``make_controller`` called for each of its robots
    (as the agent will), so that a broken one is a one-line error before anything starts."""
    out: dict[int, str] = {}
    for spec in specs:
        module, robots = spec, ""
        head, sep, tail = spec.rpartition(":")
        # a module name holds no colon: after the last one come ROBOTS (unless the whole spec names a file)
        if sep and not Path(spec).is_file():
            module, robots = head, tail
            if not re.fullmatch(r" *[0-9]+ *(, *[0-9]+ *)*", tail):
                raise ConfigError(f"--agent-module {spec}: ROBOTS must be robot ids like 1,3")
        if not module:
            raise ConfigError(f"--agent-module {spec}: no module named")
        if module.endswith(".py"):
            module = str(Path(module).resolve())  # the agents resolve it alike, but say which file in their logs
        factory = load_factory(module)
        chosen = [int(r) for r in robots.split(",")] if robots else list(robot_ids)
        for rid in chosen:
            if rid not in robot_ids:
                raise ConfigError(f"--agent-module {spec}: robot {rid} is not in this run "
                                  f"({', '.join(map(str, robot_ids))})")
            if rid in out:
                raise ConfigError(f"--agent-module {spec}: robot {rid} already has controller {out[rid]}")
            if scenario is not None:
                make(factory, ControllerConfig(rid, scenario, run), module)
            out[rid] = module
    return out


def resolve(args: Any, env: dict[str, str]) -> Scenario:
    """Scenario with lockstep participants filled in (every agent and the server), and
    ``up/0`` as a clock observer: the world starts only once this process records."""
    scenario = scenario_from(args, env)
    table = msgspec.to_builtins(scenario)
    if scenario.clock.mode == "lockstep" and not scenario.clock.participants:
        table["clock"]["participants"] = [f"agent/{r}" for r in scenario.robot_ids] + ["server/0"]
    if "up/0" not in scenario.clock.observers:
        table["clock"]["observers"] = [*scenario.clock.observers, "up/0"]
    scenario = msgspec.convert(table, Scenario)
    return scenario


class Pace:
    """The simulation's real-time factor so far: simulated over wall time since the first
    simulated time was heard (process start-up is not the simulation's pace)."""

    def __init__(self) -> None:
        self._first: tuple[float, float] | None = None  # (monotonic s, sim s) when time first moved

    def rtf(self, sim_s: float, now: float) -> float:
        if self._first is None:
            if sim_s > 0:
                self._first = (now, sim_s)
            return 0.0
        wall, sim0 = now - self._first[0], self._first[1]
        return (sim_s - sim0) / wall if wall > 0.5 else 0.0


def _table(rec: RunRecorder, scenario: Scenario, rtf: float, out: Path, endpoint: str) -> Table:
    sim = rec.sim_ns / 1e9
    t = Table(title=f"tagswarm up — {scenario.name}  t={sim:6.1f}/{scenario.duration_s:g} s  "
                    f"RTF {rtf:4.2f}  {endpoint}", caption=f"run folder: {out}")
    for col in ("robot", "mode", "fused error [m]", "fixes", "searches", "frames"):
        t.add_column(col)
    for rid in scenario.robot_ids:
        c = rec.counters.get(f"agent/{rid}", {})
        err = rec.fused_error(rid)
        t.add_row(str(rid), rec.mode_now.get(rid, "-"), "-" if err is None else f"{err:.3f}",
                  str(c.get("fixes", 0)), str(c.get("searches", 0)), str(c.get("frames_processed", 0)))
    return t


def default_out(base: Path, now: datetime) -> Path:
    """``base/<YYYYmmdd-HHMMSS>``, with ``-2``, ``-3`` ... when runs started the same second."""
    stem = now.strftime("%Y%m%d-%H%M%S")
    out, k = base / stem, 1
    while out.exists():
        k += 1
        out = base / f"{stem}-{k}"
    return out


def check_out(out: Path) -> None:
    """Refuse a run folder that would mix two runs or cannot be made (:class:`ConfigError`):
    ``out`` must be missing or an empty folder, under a folder that exists or can be made."""
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {str(out)!r}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()):
        raise ConfigError(f"--out {str(out)!r}: already holds files (a run would mix its files with theirs): "
                          "choose a new folder or remove it")
    parent = out.absolute().parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise ConfigError(f"--out {str(out)!r}: cannot be made, {str(parent)!r} is not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ConfigError(f"--out {str(out)!r}: cannot be made, {str(parent)!r} is not writable")


def run_up(scenario: Scenario, out: Path, endpoint: str, run: str, *, live: bool, report: bool,
           stop: threading.Event, console: Console, record: Path | None = None, replay: Path | None = None,
           child_args: Sequence[str] = (), view: int | None = None,
           controllers: dict[int, str] | None = None, zenoh_config_file: str | None = None) -> int:
    """Start everything, record until the world ends or ``stop``, write the run folder.
    ``child_args`` go to every child (e.g. the ``--net-*`` fault-injection flags);
    ``controllers``: robot id -> ``--agent-module`` of its agent (the others run the built-in behaviour);
    ``zenoh_config_file``: a Zenoh JSON5 config for the router and every child (their mode and endpoints
    are set on top of it)."""
    scenario = pinned(scenario)  # the run folder and the recording keep the poses drawn today
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"--out {str(out)!r}: cannot be made ({exc.strerror})") from None
    logs = out / "logs"
    logs.mkdir(exist_ok=True)
    scen_file = out / "scenario.json"
    scen_file.write_bytes(msgspec.json.format(msgspec.json.encode(scenario)))
    zenoh_file = ["--zenoh-config", zenoh_config_file] if zenoh_config_file else []
    common = ["--scenario", str(scen_file), "--run", run, *child_args, *zenoh_file]
    procgroup.REGISTRY.catch_term = False  # SIGTERM stops the run in order (see main)
    children: list[Child] = []
    failure: str | None = None
    may_die = {f"agent/{r}" for r in scenario.robots.may_die}
    t0 = time.monotonic()
    recording = None
    view_child: Child | None = None  # never ends on its own: stopped (first) once the run is over (Stopping)
    try:
        # this process is the run's Zenoh router and every child its client: each link is one its client
        # re-opens by itself.  In the peer mesh up ran before, a link made by Zenoh's gossip that dropped
        # (a lease missed on a saturated machine) was never re-made, so its two ends stopped hearing each
        # other for the rest of the run (the recorder lost the server, or an agent its corrections).  The
        # hub outlives every child, so their last messages after the world's end still arrive, and its
        # recorder is subscribed before anything starts
        with open_bus(BusConfig(mode="router", listen=(endpoint,), config_file=zenoh_config_file)) as bus, \
                Stopping(children):
            rec = RunRecorder(bus, Keys(run), scenario)
            if record is not None:
                from tagswarm.recording.record import start_recording

                recording = start_recording(bus, Keys(run), record, scenario)
            client = ["--zenoh-mode", "client", "--connect", endpoint]
            # the server's write-ahead journal (restart it by hand with the same --journal to resume the
            # map); a run folder is rewritten, and a journal of an earlier run would be refused by the server
            journal = out / "server.journal"
            journal.unlink(missing_ok=True)
            children.append(Child("server", [*script("tagswarm-server"), *common, *client, "--journal",
                                             str(journal)], logs / "server.log"))
            for rid in scenario.robot_ids:
                own = ["--agent-module", controllers[rid]] if controllers and rid in controllers else []
                children.append(Child(f"agent/{rid}", [*script("tagswarm-agent"), *common, *client,
                                                       "--robot-id", str(rid), *own], logs / f"agent{rid}.log"))
            # a replay plays the world; it also waits for this process's token (up/0) so the run folder
            # misses nothing
            world_cmd = [sys.executable, "-m", "tagswarm.recording.replay", str(replay), "--lockstep",
                         "--wait-for", "up/0", "--duration", repr(replay_end_s(scenario))] if replay \
                else script("tagswarm-world")
            if view is not None:  # a read-only tool: never impaired by child_args, it sees what the run publishes
                view_child = Child("view", [sys.executable, "-m", "tagswarm.view.view", "--scenario",
                                            str(scen_file), "--run", run, *client, "--port", str(view)],
                                   logs / "view.log")
                children.append(view_child)
                console.print(f"live view: [cyan]http://127.0.0.1:{view}/[/]")
            world = Child("world", [*world_cmd, *common, *client], logs / "world.log")
            children.append(world)
            n = len(scenario.robot_ids)
            console.print(f"[bold]tagswarm up[/]: {n} robot{'' if n == 1 else 's'}, {scenario.clock.mode} clock, "
                          f"Zenoh endpoint [cyan]{endpoint}[/] (join with --connect {endpoint}), run id {run!r}")
            from tagswarm.recording.record import declare_when_meshed

            # once every process is there (the world and a lockstep replay wait for this token: the run
            # folder misses nothing, and a realtime world ticks only once the agents and the server hear it)
            everyone = ("world/0", "server/0", *(f"agent/{r}" for r in scenario.robot_ids),
                        *scenario.clock.participants)
            declare_when_meshed(bus, Keys(run), "up/0", everyone, scenario.clock.join_timeout_s, stop)
            with Live(console=console, refresh_per_second=2, transient=False) if live else _Null() as display:
                last_print = 0.0
                pace = Pace()
                while not stop.is_set():
                    # a fixed pace, not woken by every message: the recorder drains its inboxes in
                    # batches, and polling the children at message rate cost this process 0.1 core
                    stop.wait(0.25)
                    rec.poll()
                    wall = time.monotonic() - t0
                    rtf = pace.rtf(rec.sim_ns / 1e9, time.monotonic())
                    if live:
                        display.update(_table(rec, scenario, rtf, out, endpoint))
                    elif wall - last_print > 5:
                        console.print(f"t={rec.sim_ns / 1e9:.1f} s  RTF {rtf:.2f}")
                        last_print = wall
                    if world.proc.poll() is not None:
                        if world.proc.returncode != 0:
                            failure = f"world exited with code {world.proc.returncode}"
                        break
                    dead = [c for c in children if c is not world and c.proc.poll() is not None
                            and (c.proc.returncode != 0 or rec.sim_ns / 1e9 < scenario.duration_s - 0.5)
                            and c.name not in may_die]
                    if dead:
                        failure = ", ".join(f"{c.name} exited with code {c.proc.returncode}" for c in dead)
                        break
                # let agents and the server finish their last tick, then collect what they sent
                deadline = time.monotonic() + 5.0
                while time.monotonic() < deadline and not failure and \
                        any(c.proc.poll() is None for c in children if c is not view_child):
                    bus.wait(0.2)
                    rec.poll()
                rec.poll()
    finally:
        if recording is not None:
            recording.stop()
    wall = time.monotonic() - t0
    if failure:
        console.print(f"[red]run failed: {failure}[/]")
        for c in children:
            if c.proc.returncode not in (0, -signal.SIGTERM):
                console.print(f"[bold]last lines of {c.log}[/]:\n{c.tail()}")
    code = 1 if failure else (130 if stop.is_set() else 0)
    rec.write(out, {"wall_time_s": wall, "exit_code": code, "failure": failure, "endpoint": endpoint,
                    "exit_codes": {c.name: c.proc.returncode for c in children}})
    if not report:  # else it is among the report's warnings, printed below
        print_controller_trouble(console, out)
    if report:
        from tagswarm.evaluation.report import write_report

        metrics = write_report(out)
        console.print(f"metrics: {out / 'metrics.json'}  plots: {out / 'plots'}")
        print_summary(console, metrics, failed=bool(failure))
    console.print(f"run folder: {out}")
    return code


class _Null:
    def __enter__(self) -> _Null:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def update(self, *_: object) -> None:
        return None


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry for ``tagswarm up``."""

    def body() -> int:
        inv = Invocation(parser(), argv)
        args = inv.args
        env = inv.env
        if args.duration is not None and args.duration <= 0:
            raise ConfigError("--duration must be > 0")
        if args.robots is not None and args.robots < 1:
            raise ConfigError("--robots must be >= 1")
        if args.view is not None and not 0 < args.view <= 65535:
            raise ConfigError(f"--view: port must be 1..65535, got {args.view}")
        if args.record is not None and not args.record.parent.is_dir():
            raise ConfigError(f"--record: no such directory {str(args.record.parent)!r}")
        if args.record is not None and args.record.exists():
            same = args.replay is not None and args.record.resolve() == args.replay.resolve()
            raise ConfigError(f"--record {str(args.record)!r}: " + (
                "is the recording --replay reads; record the replay to another file" if same else
                "exists already; remove it or name another file (a recording is never overwritten)"))
        for flag in ("connect", "zenoh_mode", "zenoh_user", "zenoh_password_file"):
            if getattr(args, flag, None):
                raise ConfigError(f"--{flag.replace('_', '-')}: not used by tagswarm up, which is its run's Zenoh "
                                  "router (its processes join it as clients; join from elsewhere with "
                                  "--connect to the endpoint it prints, or start the processes yourself: "
                                  "docs/multihost.md)")
        # the network and fault flags go to the children: check them here, before anything starts
        net = bus_from(args, env)
        try:
            zenoh_config(net)
        except BusError as exc:
            raise ConfigError(f"--zenoh-config {net.config_file}: {exc}" if net.config_file else str(exc)) from None
        # the scenario loader says at INFO what it filled in (robots beyond the scenario's list, tag scheme)
        setup_logging(inv.pick("log_level"), "up")
        if args.replay is not None:
            from tagswarm.recording.replay import scenario_for_replay

            scenario = scenario_for_replay(args.replay, args, env, resolve)
        else:
            scenario = resolve(args, env)
        # the pid too: two runs started in the same second (a script, a bench) must not share keys
        run = inv.pick("run", f"up{int(time.time()) % 100000}-{os.getpid()}")
        Keys(run)
        specs = args.agent_module or [x for x in env.get(AGENT_MODULE_ENV, "").split(";") if x.strip()]
        controllers = agent_modules(specs, scenario.robot_ids, scenario, run)
        if args.record is not None:
            from tagswarm.recording.record import with_recorder

            scenario = with_recorder(scenario)  # lockstep: the world waits for the recorder (nothing missed)
        out = args.out or default_out(Path("runs"), datetime.now())
        check_out(out)
        endpoint = (args.listen or [None])[0] or free_endpoint()
        stop = threading.Event()
        previous = signal.signal(signal.SIGINT, lambda *_: stop.set())
        signal.signal(signal.SIGTERM, lambda *_: stop.set())
        try:
            return run_up(scenario, out, endpoint, run, live=not args.no_live and sys.stdout.isatty(),
                          report=not args.no_report, stop=stop, console=Console(), record=args.record,
                          replay=args.replay, child_args=net_flags(net, inv.pick("log_level")), view=args.view,
                          controllers=controllers, zenoh_config_file=net.config_file)
        finally:
            signal.signal(signal.SIGINT, previous)

    return run_main("tagswarm up", body)
