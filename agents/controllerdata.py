"""The data of the controller API (pure code, no I/O; :mod:`tagswarm.agents.controller`
re-exports every name: import them from there): the commands a controller returns
(:class:`Twist`, :class:`WheelSpeeds`, :class:`Command` their union), what it is made with
(:class:`ControllerConfig`), what it gets each control cycle (:class:`ControlInput`, with
:class:`GoalRequest` and the camera frames, see :func:`gray`) and how the agent builds that
from its state (:func:`control_input`).

Frames and units: map frame when localised, else the robot's odometry frame; metres, radians,
seconds; relative observations in this robot's base_link frame (x forward, y left); covariances
3x3 row-major of (x_m, y_m, yaw_rad).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from tagswarm.agents.avoidgeom import Box, Neighbour, static_boxes
from tagswarm.protocol import messages as m
from tagswarm.protocol.geometry import Pose2, se2_compose
from tagswarm.protocol.layout import arena_to_map
from tagswarm.protocol.scenario import Agent, Mission, Robot, Scenario


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
