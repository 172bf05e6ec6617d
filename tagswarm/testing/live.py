"""A live swarm: world, server and agents as real OS processes on a private Zenoh network,
driven by the test (:meth:`tagswarm.testing.factory.SwarmFactory.start`).

The test process is the hub: the Zenoh router of the run, listening on a free loopback
port; every process is its client (multicast scouting off), so a link that drops is re-opened
by the client (in a peer mesh, a link Zenoh's gossip had made was never re-made).  Its
:class:`~tagswarm.recording.runrecorder.RunRecorder` is subscribed before anything starts, so
no message of the run is missed.  Every key is under a run id of its own, so swarms of
parallel tests never see each other.

Process names: ``world``, ``server``, ``agent/<robot id>``.  Signals go to a process's whole
group (the world's render workers with the world).  Times: ``*_s`` arguments named
``timeout_s`` are wall seconds; ``t_s`` and ``at_s`` are simulated seconds.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import msgspec

from tagswarm.operator.goto import make_goal
from tagswarm.operator.kidnap import make_command, stamp_for
from tagswarm.operator.reach import wait_alive
from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import Bus, BusConfig, BusError, open_bus
from tagswarm.protocol.errors import TagswarmError
from tagswarm.protocol.keys import ROOT, Keys
from tagswarm.protocol.layout import map_to_arena_xy, pinned, stand_problem
from tagswarm.recording.runrecorder import RunRecorder
from tagswarm.runtime.process import child_env
from tagswarm.runtime.procgroup import Child
from tagswarm.testing.errors import SwarmError, SwarmProcessDied, SwarmTimeout
from tagswarm.testing.options import NetFault, SwarmSpec, check_name, command, log_name, process_names
from tagswarm.testing.result import Run
from tagswarm.testing.runfolder import free_endpoint, write_run
from tagswarm.testing.subscription import ENDED_GRACE_S, Subscription

_KEEP: Any = object()  # restart with the fault layer the process had


class LiveSwarm:
    """Handle of a running swarm; a context manager (leaving it stops every process).

    Attributes for tests that go beyond the methods: ``bus`` (the test's Zenoh session,
    :class:`~tagswarm.protocol.bus.Bus`), ``keys`` (:class:`~tagswarm.protocol.keys.Keys` of
    this run), ``recorder`` (the :class:`~tagswarm.recording.runrecorder.RunRecorder`: ``sim_ns``,
    ``truth``/``odom``/``fused`` series, ``counters``), ``scenario``, ``run_dir``, ``run_id``,
    ``endpoint``."""

    def __init__(self, spec: SwarmSpec, run_dir: Path, run_id: str, *, launch: bool = True,
                 grace_s: float = 5.0) -> None:
        self.spec, self.run_dir, self.run_id, self.grace_s = spec, Path(run_dir), run_id, grace_s
        self.scenario = pinned(spec.build_scenario())  # scenario.json keeps the poses drawn today
        self.keys = Keys(run_id)
        (self.run_dir / "logs").mkdir(parents=True, exist_ok=True)
        self.scenario_file = self.run_dir / "scenario.json"
        self.scenario_file.write_bytes(msgspec.json.format(msgspec.json.encode(self.scenario)))
        self.names = process_names(self.scenario)
        self._children: dict[str, Child] = {}
        self._history: list[Child] = []
        self._faults: dict[str, NetFault | None] = {n: spec.fault(n) for n in self.names}
        self._stack = ExitStack()
        self._t0 = time.monotonic()
        self.closed = False
        #: processes :meth:`wait_exit` had to stop because they outlived the world
        self.stopped_at_end: list[str] = []
        self.bus, self.endpoint = self._open_hub()
        try:
            self.recorder = RunRecorder(self.bus, self.keys, self.scenario)
            self._maps = self.bus.subscribe(self.keys.map(), newest_only=True)
            self._map: m.GlobalMap | None = None
            if launch:
                self.launch()
        except BaseException:
            self.close()
            raise

    def _open_hub(self) -> tuple[Bus, str]:
        last: Exception | None = None
        for _ in range(5):  # the free port may be taken by another test between the probe and the bind
            ep = free_endpoint()
            try:
                return self._stack.enter_context(open_bus(BusConfig(mode="router", listen=(ep,)))), ep
            except BusError as exc:
                last = exc
        raise SwarmError(f"cannot open the test's Zenoh session: {last}")

    def __enter__(self) -> LiveSwarm:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ processes
    def launch(self, *names: str) -> None:
        """Start ``names`` (default: every process not running, in start order)."""
        for name in names or [n for n in self.names if n not in self._children]:
            self.spawn(name)

    def spawn(self, name: str, *extra: str, net: NetFault | None = _KEEP) -> subprocess.Popen[bytes]:
        """Start process ``name`` (not running) with ``extra`` flags; ``net`` replaces its fault
        layer (``None``: none).  A restart gets a fresh log (``logs/agent1.1.log``).  Returns its
        :class:`subprocess.Popen`."""
        self._check(name)
        if name in self._children and self._children[name].poll() is None:
            raise SwarmError(f"{name} is already running (pid {self._children[name].pid}); kill it first")
        if net is not _KEEP:
            self._faults[name] = net
        common = ["--scenario", str(self.scenario_file), "--run", self.run_id, "--zenoh-mode", "client",
                  "--connect", self.endpoint, "--log-level", self.spec.log_level]
        argv = command(name, common, (*self.spec.extra(name), *extra), self._faults[name])
        n = sum(1 for c in self._history if c.name == name)
        log = self.run_dir / "logs" / f"{log_name(name)}{'' if n == 0 else f'.{n}'}.log"
        own_module = self.spec.agent_module(name) is not None
        child = Child(name, argv, log, child_env(os.environ, import_path=sys.path if own_module else None))
        self._children[name] = child
        self._history.append(child)
        return child.proc

    def restart(self, name: str, *extra: str, net: NetFault | None = _KEEP) -> subprocess.Popen[bytes]:
        """SIGKILL ``name`` if it runs, then start it again (``extra``, ``net`` as :meth:`spawn`)."""
        if self.running(name):
            self.kill(name)
        return self.spawn(name, *extra, net=net)

    def kill(self, name: str, sig: int = signal.SIGKILL, timeout_s: float = 30.0) -> None:
        """Send ``sig`` to ``name``'s process group and wait (up to ``timeout_s``) for it to exit.
        Whatever it exits with is expected: :meth:`wait` and :meth:`finish` do not complain."""
        child = self._child(name)
        child.send(sig)
        if sig != signal.SIGKILL:
            child.send(signal.SIGCONT)  # a frozen process acts on SIGTERM only once it runs again
        try:
            child.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            raise SwarmTimeout(f"{name} did not exit within {timeout_s:g} s of signal {sig}\n{self.tails()}") from None

    def freeze(self, name: str) -> None:
        """SIGSTOP ``name``'s group: its sockets stay open but it goes silent (a hung process)."""
        self._child(name).send(signal.SIGSTOP)

    def thaw(self, name: str) -> None:
        """SIGCONT ``name``'s group."""
        self._child(name).send(signal.SIGCONT)

    def process(self, name: str) -> subprocess.Popen[bytes]:
        """The :class:`subprocess.Popen` of ``name``'s current (or last) process."""
        return self._child(name).proc

    def pid(self, name: str) -> int:
        return self._child(name).pid

    def running(self, name: str) -> bool:
        return name in self._children and self._children[name].poll() is None

    def _check(self, name: str) -> None:
        check_name(name)
        if name not in self.names:
            raise SwarmError(f"no process {name!r} in this run (processes: {', '.join(self.names)})")

    def _child(self, name: str) -> Child:
        self._check(name)
        if name not in self._children:
            raise SwarmError(f"{name} was never started")
        return self._children[name]

    def tails(self, n: int = 12) -> str:
        """The last ``n`` lines of every process's log (restarts included)."""
        return "\n".join(c.tail(n) for c in self._history)

    def _dead(self) -> SwarmProcessDied | None:
        for c in self._children.values():
            code = c.poll()
            if code is not None and code != 0 and not c.signalled:
                return SwarmProcessDied(c.name, code, self.tails())
        return None

    # ------------------------------------------------------------------ waiting
    @property
    def sim_time_s(self) -> float:
        """Simulated time (s) of the newest tick or ground truth received."""
        self.recorder.poll()
        return self.recorder.sim_ns / 1e9

    def wait(self, pred: Callable[[], bool], timeout_s: float = 60.0, what: str = "condition", *,
             _stops_without_world: bool = False) -> None:
        """Poll the recorder until ``pred()`` holds (checked on every arrival, under the bus lock:
        keep it short and make no Zenoh query in it).  :class:`SwarmProcessDied` as soon as a
        process fails, :class:`SwarmTimeout` (naming ``what``) after ``timeout_s`` wall seconds, or
        as soon as the run has ended (the world finished its duration and what it sent had
        :data:`~tagswarm.testing.subscription.ENDED_GRACE_S` to arrive) with ``pred()`` still false."""
        dead: list[SwarmProcessDied] = []
        over: list[float] = []  # wall time the world was first seen gone

        def check() -> bool:
            self.recorder.poll()
            died = self._dead()
            if died is not None:
                dead.append(died)
                return True
            if pred():
                return True
            world = self._children.get("world")
            gone = world is not None and world.poll() is not None and (
                _stops_without_world or (world.proc.returncode == 0 and not world.signalled))
            if gone and not over:
                over.append(time.monotonic())
            return bool(over) and time.monotonic() - over[0] > ENDED_GRACE_S

        ok = self.bus.wait_for(check, timeout_s)
        if dead:
            raise dead[0]
        if over and not pred():
            raise SwarmTimeout(f"{what} (the world {'ended' if not self.running('world') else 'left'} at simulated "
                               f"time {self.recorder.sim_ns / 1e9:.2f} s)\n{self.tails()}")
        if not ok:
            raise SwarmTimeout(f"{what} (after {timeout_s:g} s; simulated time {self.recorder.sim_ns / 1e9:.2f} s)"
                               f"\n{self.tails()}")

    def wait_sim(self, t_s: float, timeout_s: float = 120.0) -> None:
        """Wait until the simulation reached ``t_s`` simulated seconds (at once a :class:`SwarmTimeout` if
        the world is gone: ended, or killed by the test, time does not move)."""
        self.wait(lambda: self.recorder.sim_ns >= t_s * 1e9, timeout_s, f"simulated time never reached {t_s:g} s",
                  _stops_without_world=True)

    # ------------------------------------------------------------------ talking to the run
    def subscribe(self, keyexpr: str, *, newest_only: bool = False) -> Subscription:
        """Decoded messages on ``keyexpr``: a full key expression (``tagswarm/<run>/...``) or one
        relative to this run (``robot/1/odometry``, ``robot/*/correction``, ``server/map``)."""
        full = keyexpr if keyexpr.startswith(f"{ROOT}/") else f"{self.keys.prefix}/{keyexpr.lstrip('/')}"
        try:
            return Subscription(self.bus, full, newest_only=newest_only,
                                ended=lambda: all(c.poll() is not None for c in self._children.values()))
        except TagswarmError as exc:
            raise SwarmError(f"cannot subscribe to {full!r}: {exc}") from None
        except Exception as exc:  # zenoh rejects a malformed key expression
            raise SwarmError(f"cannot subscribe to {full!r}: {exc}") from None

    def latest_map(self, timeout_s: float = 30.0, after_s: float | None = None) -> m.GlobalMap:
        """The newest map the server published (2 simulated Hz), waiting up to ``timeout_s``
        for one (stamped after ``after_s`` simulated seconds if given).  Poses: map frame."""

        def got() -> bool:
            for it in self._maps.drain():
                try:
                    gm = codec.decode(m.GlobalMap, it.value)
                except codec.DecodeError:
                    continue
                if self._map is None or gm.stamp_ns >= self._map.stamp_ns:
                    self._map = gm
            return self._map is not None and (after_s is None or self._map.stamp_ns > after_s * 1e9)

        self.wait(got, timeout_s, "no map from the server" + ("" if after_s is None else f" after {after_s:g} s"))
        assert self._map is not None
        return self._map

    def query_map(self, timeout_s: float = 1.0) -> m.GlobalMap | None:
        """The map the server's queryable answers with now (its alive flags are current), or None."""
        for reply in self.bus.get(self.keys.map(), timeout_s=timeout_s):
            try:
                return codec.decode(m.GlobalMap, reply.value)
            except codec.DecodeError:
                continue
        return None

    def goto(self, robot: int, x_m: float, y_m: float, tolerance_m: float = 0.1, timeout_s: float = 30.0) -> m.Goal:
        """Send robot ``robot`` to (``x_m``, ``y_m``) in the MAP frame (as ``tagswarm goto``), once its
        agent is alive; stamped with the current simulated time.  Returns the goal sent.  A robot not in
        the run, or a goal where no robot can stand (the agent would refuse it), is a :class:`SwarmError`."""
        self._robot(robot)
        with _as_swarm_error("goto"):
            make_goal(robot, x_m, y_m, tolerance_m)
        why = stand_problem(self.scenario, *map_to_arena_xy(self.scenario, x_m, y_m))
        if why is not None:
            raise SwarmError(f"goto robot {robot} ({x_m:g}, {y_m:g}) (map frame): the agent would refuse it: {why}")
        self._alive(f"agent/{robot}", timeout_s)
        goal = make_goal(robot, x_m, y_m, tolerance_m, self.recorder.sim_ns)
        self.bus.put(self.keys.goal(robot), codec.encode(goal))
        return goal

    def teleport(self, robot: int, x_m: float, y_m: float, yaw_rad: float = 0.0, *, push: bool = False,
                 at_s: float | None = None, timeout_s: float = 30.0) -> m.WorldCommand:
        """Move robot ``robot`` to (``x_m``, ``y_m``, ``yaw_rad``) in the ARENA frame without turning its
        wheels (as ``tagswarm kidnap``; ``push``: by that offset), at the world's next step or at the
        first tick at or after ``at_s`` simulated seconds.  Returns the command sent.  A robot not in the
        run, or a place where no robot can stand (the world would refuse it), is a :class:`SwarmError`; the
        world also refuses a place another robot holds then (its counter ``world_command_rejected``)."""
        if at_s is not None and (not math.isfinite(at_s) or at_s < 0):
            raise SwarmError(f"at_s must be a simulated time >= 0, got {at_s!r}")
        if at_s is not None and at_s * 1e9 < self.recorder.sim_ns:
            raise SwarmError(f"at_s {at_s:g} s has passed (simulated time {self.recorder.sim_ns / 1e9:.2f} s): leave "
                             "it out to move the robot at the world's next step")
        self._robot(robot)
        with _as_swarm_error("teleport"):
            make_command(robot, x_m, y_m, yaw_rad, push)
        why = None if push else stand_problem(self.scenario, x_m, y_m)
        if why is not None:
            raise SwarmError(f"teleport robot {robot} to ({x_m:g}, {y_m:g}) (arena frame): the world would refuse "
                             f"it: {why}")
        self._alive("world/0", timeout_s)
        stamp = 0 if at_s is None else stamp_for(at_s, round(1e9 / self.scenario.clock.tick_hz))
        cmd = make_command(robot, x_m, y_m, yaw_rad, push, stamp)
        self.bus.put(self.keys.world_command(), codec.encode(cmd))
        return cmd

    def _robot(self, robot: int) -> None:
        if robot not in self.scenario.robot_ids:
            raise SwarmError(f"no robot {robot} in this run (robots {', '.join(map(str, self.scenario.robot_ids))})")

    def _alive(self, participant: str, timeout_s: float) -> None:
        child = self._children.get(participant.removesuffix("/0"))
        code = None if child is None else child.poll()
        if code is not None:  # no token will come: say so now, not in timeout_s
            raise SwarmError(f"{participant} is not running (it exited with code {code}); spawn or restart it first")
        if not wait_alive(self.bus, self.keys.alive(participant), timeout_s):
            raise SwarmTimeout(f"{participant} not alive after {timeout_s:g} s\n{self.tails()}")

    # ------------------------------------------------------------------ the end
    def wait_exit(self, timeout_s: float = 180.0, linger_s: float = 10.0) -> None:
        """Wait for the world to end by itself (the scenario's duration, within ``timeout_s`` wall
        seconds) and the others after it; one still running ``linger_s`` after the world (a process
        restarted too late to see the last tick waits for a world forever) is stopped (SIGTERM) and
        listed in ``stopped_at_end``.  Then take in the last messages.  :class:`SwarmProcessDied`
        for a failure exit the test did not cause, :class:`SwarmTimeout` if the world never ends."""
        deadline = time.monotonic() + timeout_s
        world = self._children.get("world")
        if world is not None:  # a process failing meanwhile is reported at once, not after the world's end
            self.wait(lambda: world.poll() is not None, timeout_s, f"the world did not finish within {timeout_s:g} s")
        if world is not None:
            deadline = time.monotonic() + linger_s
        for name, child in list(self._children.items()):
            try:
                child.proc.wait(timeout=max(0.01, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                self.stopped_at_end.append(name)
                child.stop(self.grace_s)
                continue
            if child.proc.returncode != 0 and not child.signalled:
                raise SwarmProcessDied(name, child.proc.returncode, self.tails())
        self.bus.wait(0.2)
        self.recorder.poll()

    def write(self, *, plots: bool = False) -> Run:
        """Write the run folder from what the recorder holds (trajectories, CSVs, ``run.json``,
        ``metrics.json``; with ``plots`` the report's PNGs too) and return the :class:`Run`."""
        self.recorder.poll()
        codes = {c.name: c.poll() for c in self._children.values()}
        info = {"exit_code": 0, "run_id": self.run_id, "endpoint": self.endpoint, "exit_codes": codes,
                "wall_time_s": time.monotonic() - self._t0, "stopped_at_end": self.stopped_at_end}
        write_run(self.recorder, self.run_dir, info, plots=plots)
        return Run.load(self.run_dir, self.scenario, self.run_id, codes)

    def finish(self, timeout_s: float = 180.0, *, plots: bool = False) -> Run:
        """:meth:`wait_exit` then :meth:`write`."""
        self.wait_exit(timeout_s)
        return self.write(plots=plots)

    def close(self) -> None:
        """Stop every process (SIGCONT, SIGTERM, then SIGKILL after the grace period: all groups at
        once), wait until every group is empty, close the Zenoh session.  Idempotent."""
        if self.closed:
            return
        self.closed = True
        try:
            live = [c for c in self._history if c.poll() is None]
            for c in live:
                c.send(signal.SIGCONT)
                c.send(signal.SIGTERM)
            deadline = time.monotonic() + self.grace_s
            for c in live:
                try:
                    c.proc.wait(timeout=max(0.01, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    pass  # reap() below SIGKILLs it
        finally:
            for c in self._history:
                c.reap()
            self._stack.close()


@contextmanager
def _as_swarm_error(what: str) -> Iterator[None]:
    """The operator helpers' checks (finite numbers, ranges) raise ConfigError, worded for the CLI: in a
    test they are a SwarmError, like everything the fixture raises on purpose."""
    try:
        yield
    except TagswarmError as exc:
        if isinstance(exc, SwarmError):
            raise
        raise SwarmError(f"{what}: {exc}") from None
