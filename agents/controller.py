"""Bring your own controller: the API a user's code implements to drive a robot (pure code, no I/O).

An agent started with ``--agent-module MODULE`` (or ``TAGSWARM_AGENT_MODULE``)
still does everything the built-in agent does (tag detection, cube poses,
odometry, publishing observations and odometry, taking the server's
corrections), so the server localises the robot like any other; only the
motion decision is the user's.  Each control cycle (every encoder tick: 30 Hz
in the paper scenario; every world tick in lockstep) the agent calls
:meth:`Controller.step` with a :class:`ControlInput` and sends the returned
command to the wheels.

The contract of ``MODULE`` (a dotted module name importable in the agent
process, or a path to a ``.py`` file): it defines a function
``make_controller(config: ControllerConfig) -> Controller``.  It is called once
when the agent starts and again when the world restarts (a new run: odometry
and map pose start over, so does the controller).

Commands: :class:`Twist` (forward speed m/s, turn rate rad/s, counter-clockwise
positive: what the built-in behaviour computes) or :class:`WheelSpeeds` (left
and right wheel angular speeds in rad/s, positive drives forward: what the
world takes).  Either is scaled down, keeping the path's curvature, so that
neither wheel exceeds ``robot.max_wheel_speed_rad_s``.

Collision avoidance: unless the controller sets ``avoid = False`` (or the
scenario's ``agent.avoid`` is off), every command goes through
:class:`tagswarm.agents.guard.CommandGuard`: a command whose path over the
next ``agent.avoid_horizon_s`` would come closer than
``agent.avoid_clearance_m`` to another robot (from the server's map) or to a
wall/obstacle is replaced by the nearest one that does not.  The guard needs a
map pose: before the robot is first localised, commands pass unfiltered.

Errors: an exception in ``step`` (or a result that is not a finite command)
is logged once with its traceback and counted (status counter
``controller_errors``); that cycle the robot gets a zero command and the
agent carries on, calling the controller again next cycle.

Change only part of the built-in behaviour: subclass
:class:`~tagswarm.agents.behaviour.Behaviour` (e.g. override ``target``, where
to go, or ``steer``, how to get there) and return a :class:`BehaviourController`
subclass whose ``behaviour_class`` is yours.

Frames and units: map frame (the origin robot's first pose, unless landmarks
pin it) when localised, else the robot's odometry frame (its pose when the
agent started); metres, radians, seconds.  Relative observations are in this
robot's base_link frame (x forward, y left).  Covariances are 3x3 row-major of
(x_m, y_m, yaw_rad).

The data crossing the API (:class:`Twist`, :class:`WheelSpeeds`, :class:`Command`, :class:`GoalRequest`,
:class:`ControllerConfig`, :class:`ControlInput`, :func:`gray`, :func:`control_input`) is
defined in :mod:`tagswarm.agents.controllerdata`; this module re-exports it: import it from here.
"""

from __future__ import annotations

import importlib
import importlib.util
import logging
import math
import sys
import threading
import time
import traceback
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar, TypeVar

from tagswarm.agents.avoid import Box, Neighbour
from tagswarm.agents.behaviour import Behaviour, wheel_speeds
from tagswarm.agents.controllerdata import (
    Command,
    ControlInput,
    ControllerConfig,
    GoalRequest,
    Twist,
    WheelSpeeds,
    control_input,
    gray,
)
from tagswarm.agents.guard import CommandGuard
from tagswarm.protocol.errors import UsageError
from tagswarm.protocol.geometry import Pose2, position_sigma_m
from tagswarm.protocol.layout import anchors_map, footprint_radius
from tagswarm.protocol.scenario import Robot, Scenario

B = TypeVar("B", bound=Behaviour)

FACTORY = "make_controller"

__all__ = ["FACTORY", "Behaviour", "BehaviourController", "Box", "ControlInput", "Controller", "ControllerConfig",
           "ControllerRunner", "GoalRequest", "Neighbour", "Twist", "WheelSpeeds", "control_input",
           "gray", "load_factory", "make"]


class Controller:
    """Base class of a user's controller: override :meth:`step`.

    Class attributes a subclass may set: ``wants_images`` (receive the newest
    camera frames in :attr:`ControlInput.images`; off by default, they are
    large), ``avoid`` (filter commands through collision avoidance; on by
    default) and ``mode`` (the string the agent reports as its mode in status
    messages, the live view and ``modes.csv``)."""

    wants_images: ClassVar[bool] = False
    avoid: ClassVar[bool] = True
    mode: str = "custom"

    def step(self, inputs: ControlInput) -> Command:
        """The command for this cycle (see the module docstring for units)."""
        raise NotImplementedError(f"{type(self).__name__} must override step()")


def mission_behaviour(cls: type[B], s: Scenario, rid: int, to_map: Pose2, static_obstacles: tuple[Box, ...]) -> B:
    """Robot ``rid``'s behaviour (class ``cls``) for its mission in scenario ``s``; ``to_map`` (arena to
    map frame) and ``static_obstacles`` (map frame) as in :class:`ControllerConfig`."""
    team = tuple(sorted(mi.robot for mi in s.missions if mi.kind == "leapfrog"))
    return cls(rid, s.mission(rid), s.agent, s.robot, to_map, team, static_obstacles=static_obstacles,
               anchor=anchors_map(s, rid))


class BehaviourController(Controller):
    """The built-in behaviour (mission, go-to-goal, active re-localisation, its own collision
    avoidance) as a :class:`Controller`.  Subclass it with ``behaviour_class`` set to a
    :class:`~tagswarm.agents.behaviour.Behaviour` subclass to change only part of it."""

    behaviour_class: ClassVar[type[Behaviour]] = Behaviour
    avoid: ClassVar[bool] = False  # the behaviour plans around others itself

    def __init__(self, config: ControllerConfig) -> None:
        self.behaviour = mission_behaviour(self.behaviour_class, config.scenario, config.robot_id,
                                           config.arena_to_map, config.static_obstacles)
        self._goal_number = 0
        self.mode = str(self.behaviour.mode)

    def step(self, inputs: ControlInput) -> Command:
        g = inputs.goal
        if g is not None and g.number != self._goal_number:
            self._goal_number = g.number
            self.behaviour.set_goal(g.x_m, g.y_m, g.tolerance_m)
        sigma = position_sigma_m(inputs.pose_cov) if inputs.localised else None
        v, w = self.behaviour.cycle(t_s=inputs.t_s, map_pose=inputs.pose if inputs.localised else None,
                                    odom_yaw=inputs.odom[2], moved=inputs.moved, fix=inputs.fix,
                                    server_up=inputs.server_up, neighbours=inputs.neighbours, pos_sigma_m=sigma,
                                    loose_pose=None if inputs.localised else inputs.loose_pose, vouched=inputs.vouched)
        self.mode = str(self.behaviour.mode)
        return Twist(v, w)


Factory = Callable[[ControllerConfig], Controller]


def load_factory(spec: str) -> Factory:
    """``make_controller`` of the module ``spec`` (a dotted name, or a path ending in ``.py``).
    Raises :class:`~tagswarm.protocol.errors.UsageError` (one line, naming the module; exit
    code 2) if it cannot be imported or has no callable ``make_controller``."""
    where = f"--agent-module {spec}"
    try:
        if spec.endswith(".py"):
            path = Path(spec)
            if not path.is_file():
                raise UsageError(f"{where}: no such file")
            name = f"tagswarm_user_controller_{path.stem}"
            module = sys.modules.get(name)
            if module is None or getattr(module, "__file__", None) != str(path.resolve()):
                loader_spec = importlib.util.spec_from_file_location(name, path.resolve())
                if loader_spec is None or loader_spec.loader is None:
                    raise UsageError(f"{where}: cannot load this file as a Python module")
                module = importlib.util.module_from_spec(loader_spec)
                sys.modules[name] = module
                try:
                    loader_spec.loader.exec_module(module)
                except BaseException:
                    sys.modules.pop(name, None)
                    raise
        else:
            module = importlib.import_module(spec)
    except UsageError:
        raise
    except Exception as exc:  # whatever the user's module raises while importing
        detail = " ".join(str(exc).split())
        raise UsageError(f"{where}: cannot import it: {type(exc).__name__}: {detail} "
                              "(the module must be importable in the agent process: check PYTHONPATH)") from None
    factory = getattr(module, FACTORY, None)
    if factory is None:
        raise UsageError(f"{where}: the module defines no {FACTORY}(config) -> Controller")
    if not callable(factory):
        raise UsageError(f"{where}: {FACTORY} is not callable")
    return factory  # type: ignore[no-any-return]


def make(factory: Factory, config: ControllerConfig, spec: str) -> Controller:
    """Call the factory; anything but a :class:`Controller` is a :class:`UsageError`."""
    try:
        ctrl = factory(config)
    except Exception as exc:
        detail = " ".join(str(exc).split())
        raise UsageError(f"--agent-module {spec}: {FACTORY} raised {type(exc).__name__}: {detail}") from None
    if not isinstance(ctrl, Controller):
        raise UsageError(f"--agent-module {spec}: {FACTORY} returned {type(ctrl).__name__}, "
                              "not a tagswarm.agents.controller.Controller")
    return ctrl


def _twist(cmd: object, robot: Robot) -> tuple[float, float]:
    """(v_m_s, w_rad_s) of a command; TypeError/ValueError for anything else or non-finite numbers."""
    if isinstance(cmd, Twist):
        v, w = float(cmd.v_m_s), float(cmd.w_rad_s)
    elif isinstance(cmd, WheelSpeeds):
        r, b = robot.wheel_radius_m, robot.wheel_base_m
        left, right = float(cmd.left_rad_s), float(cmd.right_rad_s)
        v, w = r * (left + right) / 2, r * (right - left) / b
    else:
        raise TypeError(f"step() returned {type(cmd).__name__}, not a Twist or WheelSpeeds")
    if not (math.isfinite(v) and math.isfinite(w)):
        raise ValueError(f"step() returned a non-finite command {cmd!r}")
    return v, w


HUNG_STEP_S = 5.0  # wall seconds after which a step that has not returned is reported (with where it is)
HANG_FRAMES = 8  # frames of the stuck step's stack that report shows


class _HangWatch:
    """Reports, once per step, a controller step that has not returned after ``HUNG_STEP_S``
    wall seconds, with the stack it is stuck in: an exception is logged by the runner, but a
    step that never returns says nothing by itself (in lockstep the world and the server stop
    waiting for the robot after ``clock.ack_stall_after`` timeouts; in real time it stands)."""

    def __init__(self, log: logging.Logger, name: str, robot_id: int) -> None:
        self.log, self.name, self.robot_id = log, name, robot_id
        self.started: float | None = None  # perf_counter of the step under way
        self.thread_id = 0
        self.reported: float | None = None  # the step already reported
        self.hung = 0
        self._stop = threading.Event()
        threading.Thread(target=self._watch, name=f"controller-watch-{robot_id}", daemon=True).start()

    def _watch(self) -> None:
        while not self._stop.wait(0.5):
            t0 = self.started
            if t0 is None or t0 == self.reported or time.perf_counter() - t0 < HUNG_STEP_S:
                continue
            self.reported = t0
            self.hung += 1
            frame = sys._current_frames().get(self.thread_id)
            stack = traceback.extract_stack(frame) if frame is not None else traceback.StackSummary()
            # the user's frames: those below this runner's call of step (the last HANG_FRAMES of them)
            calls = [i for i, f in enumerate(stack) if f.name == "command" and f.filename == __file__]
            mine = stack[calls[-1] + 1:] if calls else stack
            where = "".join(traceback.format_list(mine[-HANG_FRAMES:])) or "(stack unknown)\n"
            self.log.warning("robot %d: the controller %s's step has not returned for %.0f s (counted as "
                             "controller_hung); it is here:\n%s", self.robot_id, self.name, HUNG_STEP_S,
                             where.rstrip())

    def close(self) -> None:
        self._stop.set()


@dataclass
class ControllerRunner:
    """Runs one controller for the agent: error containment, collision filter, wheel speeds."""

    controller: Controller
    config: ControllerConfig
    log: logging.Logger = field(default_factory=lambda: logging.getLogger("tagswarm.agent.controller"))
    cycles: int = 0
    errors: int = 0
    fixes: int = 0  # cycles with a new visual fix, as the built-in behaviour counts them
    slow: int = 0  # steps that took longer than a control period (wall clock)
    guard: CommandGuard = field(init=False)

    def __post_init__(self) -> None:
        a = self.config.agent
        self.guard = CommandGuard(footprint_radius(self.config.robot), a.avoid_clearance_m, a.avoid_horizon_s)
        self._boxes = self.config.static_obstacles
        self._period_s = 1.0 / self.config.scenario.encoders.rate_hz
        self._watch: _HangWatch | None = None  # started with the first step

    @property
    def wants_images(self) -> bool:
        return bool(self.controller.wants_images)

    @property
    def mode(self) -> str:
        return str(self.controller.mode)

    def command(self, inputs: ControlInput) -> tuple[float, float]:
        """(left, right) wheel speeds in rad/s for this cycle."""
        self.cycles += 1
        self.fixes += inputs.fix
        robot = self.config.robot
        if self._watch is None:
            self._watch = _HangWatch(self.log, type(self.controller).__name__, inputs.robot_id)
            weakref.finalize(self, self._watch.close)  # a runner replaced (a new run) takes its watch with it
        t0 = time.perf_counter()
        self._watch.thread_id, self._watch.started = threading.get_ident(), t0
        try:
            v, w = _twist(self.controller.step(inputs), robot)
        except Exception:
            self.errors += 1
            if self.errors == 1:
                self.log.exception("robot %d: the controller %s failed; the robot stops on every failing cycle "
                                   "(counted as controller_errors, logged once)", inputs.robot_id,
                                   type(self.controller).__name__)
            return 0.0, 0.0
        finally:
            self._watch.started = None
            took = time.perf_counter() - t0
            if took > self._period_s:
                self.slow += 1
                if self.slow == 1:
                    self.log.warning("robot %d: the controller %s took %.0f ms for one step, longer than the "
                                     "%.0f ms control period: in real time its commands come late and frames "
                                     "queue (counted as controller_slow, logged once)", inputs.robot_id,
                                     type(self.controller).__name__, 1e3 * took, 1e3 * self._period_s)
        if self.controller.avoid and self.config.agent.avoid and inputs.localised:
            v, w = self.guard.filter(inputs.pose, v, w, inputs.neighbours, self._boxes,
                                     self.config.agent.max_turn_rad_s)
        return wheel_speeds(v, w, robot)

    def counters(self) -> dict[str, int]:
        return {"controller_cycles": self.cycles, "controller_errors": self.errors,
                "controller_filtered": self.guard.filtered, "controller_slow": self.slow, "fixes": self.fixes,
                "controller_hung": 0 if self._watch is None else self._watch.hung}

    def close(self) -> None:
        """Stop the hang watch now (a runner that is dropped stops it too, through ``weakref.finalize``)."""
        if self._watch is not None:
            self._watch.close()
