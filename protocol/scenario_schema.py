"""The scenario's schema: one frozen msgspec Struct per TOML section.

Types, defaults and single-field ranges live here (msgspec checks them when a table
is converted); loading, ``--set`` overrides and the cross-field rules are in
:mod:`tagswarm.protocol.scenario`, which re-exports every name of this module, so
``from tagswarm.protocol.scenario import Scenario, Camera`` is the usual import.
Frames and units: poses in the arena frame (metres, radians, z from the floor),
mounts in the robot's base frame (x forward, y left, z up).
"""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from tagswarm.protocol import tags
from tagswarm.protocol.errors import UsageError


class ScenarioError(UsageError, ValueError):
    """The scenario (or an override of it) is invalid; the message names the field."""


Pos = Annotated[float, msgspec.Meta(gt=0)]
NonNeg = Annotated[float, msgspec.Meta(ge=0)]


class Spec(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Base of scenario sections: frozen, keyword-only, typos are errors."""


class Obstacle(Spec, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A fixed box; pose of its centre in the arena frame (z from the floor)."""

    x_m: float
    y_m: float
    yaw_rad: float = 0.0
    size_x_m: Pos
    size_y_m: Pos
    size_z_m: Pos = 0.5


class Arena(Spec, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Square-cornered arena centred on the origin, surrounded by walls."""

    size_x_m: Pos = 7.0
    size_y_m: Pos = 7.0
    wall_height_m: Pos = 0.5
    wall_thickness_m: Pos = 0.1
    obstacles: tuple[Obstacle, ...] = ()


class TagScheme(Spec, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Tag family and ID scheme: robot k carries ``id_base + id_stride*k + face``
    for the faces front, back, left, right, top, bottom (paper: 10k+1..10k+6).
    ``size_m`` is the edge of the tag's black square."""

    family: Literal["tag36h11", "tag16h5"] = "tag36h11"
    size_m: Pos = 0.16
    id_base: Annotated[int, msgspec.Meta(ge=0)] = 1
    id_stride: Annotated[int, msgspec.Meta(ge=1)] = 10


class Landmark(Spec, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A fixed tag on a wall or post.  (x, y, z) is the tag centre in the arena
    frame; the tag faces the direction ``yaw_rad`` (its outward normal), upright."""

    id: Annotated[int, msgspec.Meta(ge=0)]
    x_m: float
    y_m: float
    z_m: Pos = 0.25
    yaw_rad: float = 0.0
    size_m: Pos = 0.16


class Camera(Spec, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """An onboard pinhole camera.  Mount: optical centre at (x, y, z) in the base
    frame, looking along body yaw ``yaw_deg`` (left positive) tilted up by
    ``pitch_deg``; the image is upright."""

    name: str = "front"
    width: Annotated[int, msgspec.Meta(ge=16, le=4096)] = 320
    height: Annotated[int, msgspec.Meta(ge=16, le=4096)] = 240
    hfov_deg: Annotated[float, msgspec.Meta(gt=1, lt=170)] = 60.0
    rate_hz: Pos = 10.0
    x_m: float = 0.15
    y_m: float = 0.0
    # on a mast above the tag cubes, looking down: from the tags' own height a single
    # tag's two pose solutions differ by a pure yaw flip that no ground prior can
    # resolve; from above, the planar (upright, on the floor) model tells them apart
    z_m: float = 0.6
    yaw_deg: float = 0.0
    pitch_deg: float = -15.0
    near_m: Pos = 0.05
    far_m: Pos = 15.0


class Robot(Spec, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Geometry and limits shared by every robot of the scenario."""

    chassis_length_m: Pos = 0.30
    chassis_width_m: Pos = 0.24
    chassis_height_m: Pos = 0.10
    ground_clearance_m: NonNeg = 0.02
    cube_edge_m: Pos = 0.20
    wheel_radius_m: Pos = 0.05
    wheel_base_m: Pos = 0.22
    max_wheel_speed_rad_s: Pos = 10.0
    cameras: tuple[Camera, ...] = (Camera(),)

    @property
    def cube_center_z_m(self) -> float:
        """Height of the tag cube's centre above the floor (the cube sits on the chassis)."""
        return self.ground_clearance_m + self.chassis_height_m + self.cube_edge_m / 2.0


class StartPose(Spec, frozen=True, kw_only=True, forbid_unknown_fields=True):
    x_m: float
    y_m: float
    yaw_rad: float = 0.0


class Robots(Spec, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """How many robots and where they start.  ``placement``: ``ring`` (evenly on a
    circle of ``ring_radius_m`` facing its centre), ``grid`` (evenly spread with
    seeded random headings), ``random`` (seeded, non-overlapping) or
    ``explicit`` (``start`` lists one pose per robot; a longer list is cut to
    ``count``, and robots beyond a shorter one are placed at free poses with a
    default mission: :mod:`tagswarm.protocol.robotfill`)."""

    count: Annotated[int, msgspec.Meta(ge=1, le=200)] = 4
    placement: Literal["ring", "grid", "random", "explicit"] = "ring"
    ring_radius_m: Pos = 1.5
    start: tuple[StartPose, ...] = ()
    may_die: tuple[int, ...] = ()  # robots whose agent may exit early (fault scenarios)


class Encoders(Spec, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Wheel encoders and their error model.  ``radius_bias_sigma`` and
    ``wheel_base_bias_sigma`` are the standard deviations (fractions) of the
    per-robot systematic miscalibration drawn once from the seed;
    ``slip_sigma`` (sqrt of metres) scales random slip: each wheel's travel d
    gets noise N(0, slip_sigma^2 |d|)."""

    rate_hz: Pos = 30.0
    ticks_per_rev: Annotated[int, msgspec.Meta(ge=1)] = 4096
    error_model: bool = True
    radius_bias_sigma: NonNeg = 0.01
    wheel_base_bias_sigma: NonNeg = 0.02
    slip_sigma: NonNeg = 0.01


class Clock(Spec, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """``realtime``: the world paces itself to ``speed`` x wall time.
    ``lockstep``: after each tick it waits for an ack from every live participant
    in ``participants`` (``"agent/0"``, ``"server/0"``...); one that has not acked
    after ``ack_timeout_s`` is skipped for that tick and logged; one whose
    liveliness token vanishes is dropped until it comes back.  The world waits up
    to ``join_timeout_s`` for participants to appear before the first tick.
    ``observers`` (``"up/0"``, ``"record/0"``) are waited for in the same way
    before the first tick, in either mode, but never for acks: a recorder that
    must not miss the start of a run without slowing it down."""

    mode: Literal["realtime", "lockstep"] = "realtime"
    tick_hz: Annotated[float, msgspec.Meta(gt=0, le=10_000)] = 30.0
    physics_substeps: Annotated[int, msgspec.Meta(ge=1, le=100)] = 4
    speed: Pos = 1.0
    participants: tuple[str, ...] = ()
    observers: tuple[str, ...] = ()
    ack_timeout_s: Pos = 5.0
    join_timeout_s: Pos = 30.0
    command_timeout_s: Pos = 0.5


class Render(Spec, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Rendering: ``workers`` = 0 renders in the world process; K > 0 spawns K
    render worker processes (each a visual-only replica of the scene).
    ``stagger_cameras``: the cameras fire at evenly spread phases of their period
    (camera i of n at i/n of it) rather than all on the same tick, so rendering is
    spread over the ticks instead of a burst that the last camera waits behind."""

    workers: Annotated[int, msgspec.Meta(ge=0, le=32)] = 0
    floor: bool = False
    shadows: bool = False
    stagger_cameras: bool = True


class Agent(Spec, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Agent behaviour and estimation settings shared by every robot.

    Odometry noise (per wheel): the travel d of each wheel gets variance
    ``odom_wheel_sigma^2 * |d|`` (sqrt-metre model), so the covariance grows with
    distance.  ``fix_threshold`` is the number of consecutive odometry-only
    control cycles (encoder updates) after which the robot stops and searches
    by rotating in place (the paper's active re-localisation).

    Collision avoidance (``avoid``, :mod:`tagswarm.agents.avoid`): missions and run-time
    goals steer around the other robots (their poses in the server's map) and
    the arena's walls and obstacles, keeping ``avoid_clearance_m`` between
    footprints (the circle of ``tagswarm.protocol.layout.footprint_radius``); it only
    steps in when the next ``avoid_horizon_s`` of the path would come closer
    than that, and after ``avoid_stall_s`` without progress it tries the other
    side (or backs off for a robot with a lower id).  Holding station and the
    searching rotation are never changed by it."""

    detector: Literal["apriltag", "aruco"] = "apriltag"
    # "cube": every visible face of a cube (and every camera) in one estimate;
    # "single_tag": the largest face alone, as a per-tag PnP would (ablation)
    pose_method: Literal["cube", "single_tag"] = "cube"
    max_hamming: Annotated[int, msgspec.Meta(ge=0, le=3)] = 0
    min_margin: NonNeg = 20.0
    pixel_sigma_px: Pos = 0.3  # measured corner noise 0.25-0.33 px (agents/cubepose.py)
    max_reprojection_px: Pos = 2.0
    max_range_m: Pos = 6.0
    odom_wheel_sigma: NonNeg = 0.02
    fix_threshold: Annotated[int, msgspec.Meta(ge=1)] = 150
    search_speed_rad_s: Pos = 0.6
    search_max_sweep_rad: Pos = 6.3
    lost_speed_factor: Annotated[float, msgspec.Meta(gt=0, le=1)] = 0.3
    max_speed_m_s: Pos = 0.3
    max_turn_rad_s: Pos = 1.2
    goal_tolerance_m: Pos = 0.1
    status_period_s: Pos = 1.0
    frame_wait_s: Pos = 2.0
    # fault injection: extra wall seconds spent on every camera frame (a deliberately slow detector)
    inject_frame_delay_s: NonNeg = 0.0
    avoid: bool = True
    avoid_clearance_m: NonNeg = 0.1  # kept between footprints (robot-robot, robot-wall/obstacle)
    avoid_horizon_s: Annotated[float, msgspec.Meta(ge=0.5, le=10)] = 2.0
    avoid_stall_s: Pos = 6.0


class Mission(Spec, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """What one robot does.  ``hold``: stay put (the origin robot holding station as
    the reference).  ``waypoints``: visit ``waypoints`` ([x, y] in the arena frame)
    once, or forever with ``loop``.  ``patrol``: back and forth along them.
    ``leapfrog``: move to the next waypoint only during this robot's turn (turns
    of ``leapfrog_period_s`` rotate over the robots with a leapfrog mission, so
    the others stand still as references)."""

    robot: Annotated[int, msgspec.Meta(ge=0)]
    kind: Literal["hold", "waypoints", "patrol", "leapfrog"] = "hold"
    waypoints: tuple[tuple[float, float], ...] = ()
    loop: bool = False
    leapfrog_period_s: Pos = 10.0


class MapFrame(Spec, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """The map frame is the origin robot's first pose (or the arena frame when
    landmarks are used, see issue notes)."""

    origin_id: Annotated[int, msgspec.Meta(ge=0)] = 0


class Event(Spec, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A scheduled intervention in the physical world (a ``[[events]]`` table), applied
    by the world at the first step k with ``k / clock.tick_hz >= at_s`` (simulation
    seconds) exactly like a :class:`tagswarm.protocol.messages.WorldCommand`: ``teleport`` puts
    ``robot``'s base at (x_m, y_m, yaw_rad) in the arena frame, ``push`` moves it by
    (x_m, y_m) in the arena frame and turns it by yaw_rad.  The wheels do not turn, so
    the robot's odometry does not see it (a kidnapped robot)."""

    at_s: float
    robot: int
    action: Literal["teleport", "push"]
    x_m: float
    y_m: float
    yaw_rad: float = 0.0


class Scenario(Spec, frozen=True, kw_only=True, forbid_unknown_fields=True):
    name: str = "custom"
    seed: Annotated[int, msgspec.Meta(ge=0)] = 0
    duration_s: Pos = 60.0
    arena: Arena = Arena()
    tags: TagScheme = TagScheme()
    robot: Robot = Robot()
    robots: Robots = Robots()
    landmarks: tuple[Landmark, ...] = ()
    encoders: Encoders = Encoders()
    clock: Clock = Clock()
    render: Render = Render()
    agent: Agent = Agent()
    missions: tuple[Mission, ...] = ()
    map: MapFrame = MapFrame()
    events: tuple[Event, ...] = ()

    @property
    def robot_ids(self) -> tuple[int, ...]:
        return tuple(range(self.robots.count))

    def mission(self, robot_id: int) -> Mission:
        """The mission of ``robot_id`` (``hold`` if the scenario gives none)."""
        for mission in self.missions:
            if mission.robot == robot_id:
                return mission
        return Mission(robot=robot_id)

    def tag_ids(self, robot_id: int) -> tuple[int, ...]:
        """The six tag IDs of ``robot_id`` in :class:`tagswarm.protocol.tags.Face` order."""
        return tags.robot_tag_ids(robot_id, self.tags.id_base, self.tags.id_stride)
