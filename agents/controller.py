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
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar, TypeVar

import numpy as np
from numpy.typing import NDArray

from tagswarm.agents.avoid import Box, Neighbour, static_boxes
from tagswarm.agents.behaviour import Behaviour, wheel_speeds
from tagswarm.agents.guard import CommandGuard
from tagswarm.protocol import messages as m
from tagswarm.protocol.errors import UsageError
from tagswarm.protocol.geometry import Pose2, position_sigma_m, se2_compose
from tagswarm.protocol.layout import anchors_map, arena_to_map, footprint_radius
from tagswarm.protocol.scenario import Agent, Mission, Robot, Scenario

B = TypeVar("B", bound=Behaviour)

FACTORY = "make_controller"

__all__ = ["FACTORY", "Behaviour", "BehaviourController", "Box", "ControlInput", "Controller", "ControllerConfig",
           "ControllerRunner", "GoalRequest", "Neighbour", "Twist", "WheelSpeeds", "control_input",
           "gray", "load_factory", "make"]


@dataclass(frozen=True)
class Twist:
    """Body twist: forward speed (m/s, negative reverses) and turn rate (rad/s, counter-clockwise positive)."""

    v_m_s: float
    w_rad_s: float


@dataclass(frozen=True)
class WheelSpeeds:
    """Wheel angular speeds in rad/s (positive drives the robot forward)."""

    left_rad_s: float
    right_rad_s: float


Command = Twist | WheelSpeeds


@dataclass(frozen=True)
class GoalRequest:
    """A run-time goal (``tagswarm goto``): reach (x_m, y_m) in the map frame within ``tolerance_m``.
    ``number`` counts the goals this agent received (1, 2, ...): a new goal has a new number."""

    x_m: float
    y_m: float
    tolerance_m: float
    number: int


@dataclass(frozen=True)
class ControllerConfig:
    """What ``make_controller`` gets: which robot, and the resolved scenario it runs in."""

    robot_id: int
    scenario: Scenario
    run: str = "default"

    @property
    def robot(self) -> Robot:
        """Wheel radius and base, wheel speed limit, cameras."""
        return self.scenario.robot

    @property
    def agent(self) -> Agent:
        """The built-in behaviour's settings (speeds, avoidance clearance, ...)."""
        return self.scenario.agent

    @property
    def mission(self) -> Mission:
        """This robot's mission in the scenario (waypoints in the arena frame)."""
        return self.scenario.mission(self.robot_id)

    @property
    def arena_to_map(self) -> Pose2:
        """T_map_arena: compose with an arena point to get it in the map frame."""
        return arena_to_map(self.scenario)

    @property
    def static_obstacles(self) -> tuple[Box, ...]:
        """The arena's walls and obstacles as map-frame boxes."""
        return static_boxes(self.scenario)


@dataclass(frozen=True)
class ControlInput:
    """Everything a controller sees in one control cycle.

    ``pose`` is base_link in the map frame when ``localised`` (the server's
    fused estimate carried forward by odometry), else in the odometry frame
    (dead reckoning only).  ``pose_cov`` is, when localised, the covariance of
    the server's newest correction (position block in the robot's own axes,
    x forward, y left, as in :class:`~tagswarm.protocol.messages.Correction`),
    else the odometry covariance.  ``odom`` / ``odom_cov`` are the encoder
    dead reckoning in the odometry frame.  ``loose_pose`` is, when not
    localised, the map's estimate (map frame) if the server has placed this
    robot without vouching for it (position σ over ``[server] claim_sigma_m``),
    else None.  ``vouched``: whether the server vouches for ``pose`` now; False
    when not localised, and when ``pose`` is the map's newest estimate of a robot
    the server vouched for before and no longer does because its σ grew past
    ``claim_sigma_m`` (``pose_cov`` is then that estimate's).  ``observations`` are the relative
    poses this agent measured from its camera images since the previous cycle
    (also published to the server; pose of the target in this robot's
    base_link frame).  ``neighbours`` are the other robots from the server's
    map (map frame, extrapolated to now, ``radius_m`` includes their
    uncertainty).  ``images`` holds the newest frame of each camera processed
    since the previous cycle, only if the controller sets ``wants_images``
    (see :func:`gray`)."""

    robot_id: int
    t_s: float
    localised: bool
    pose: Pose2
    pose_cov: tuple[float, ...]
    odom: Pose2
    odom_cov: tuple[float, ...]
    distance_m: float
    moved: bool
    fix: bool
    server_up: bool
    observations: tuple[m.RelativeObservation, ...] = ()
    neighbours: tuple[Neighbour, ...] = ()
    goal: GoalRequest | None = None
    loose_pose: Pose2 | None = None
    vouched: bool = True
    images: Mapping[str, m.CameraImage] = field(default_factory=dict)


def gray(image: m.CameraImage) -> NDArray[np.uint8]:
    """A camera frame's pixels as a (height, width) uint8 array (mono8, read-only view)."""
    return np.frombuffer(image.data, np.uint8).reshape(image.height, image.width)


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


def control_input(*, robot_id: int, time_ns: int, map_odom: Pose2 | None, map_cov: tuple[float, ...] | None,
                  odom_pose: Pose2, odom_cov: NDArray[np.float64], distance_m: float, moved: bool, fix: bool,
                  server_up: bool, observations: tuple[m.RelativeObservation, ...],
                  neighbours: tuple[Neighbour, ...], goal: GoalRequest | None,
                  images: Mapping[str, m.CameraImage], loose_map_odom: Pose2 | None = None,
                  vouched: bool = True) -> ControlInput:
    """The agent's state as a :class:`ControlInput`: the map pose is ``map_odom`` composed with the
    odometry pose (when localised), else the odometry pose itself; the loose pose likewise from
    ``loose_map_odom`` (the server's unvouched placement) when not localised; ``vouched`` whether the
    server still vouches for ``map_odom``."""
    ocov = tuple(float(c) for c in odom_cov.ravel())
    if map_odom is None:
        pose, cov, localised = odom_pose, ocov, False
    else:
        pose, cov, localised = se2_compose(map_odom, odom_pose), map_cov or ocov, True
    loose = None if localised or loose_map_odom is None else se2_compose(loose_map_odom, odom_pose)
    return ControlInput(robot_id=robot_id, t_s=time_ns / 1e9, localised=localised, pose=pose, pose_cov=cov,
                        odom=odom_pose, odom_cov=ocov, distance_m=distance_m, moved=moved, fix=fix,
                        server_up=server_up, observations=observations, neighbours=neighbours, goal=goal,
                        loose_pose=loose, vouched=localised and vouched, images=dict(images))
