"""The scenario's schema: one frozen msgspec Struct per TOML section.

Types, defaults and single-field ranges live here (msgspec checks them when a table
is converted); loading, ``--set`` overrides and the cross-field rules are in
:mod:`tagswarm.protocol.scenario`, which re-exports every name of this module, so
``from tagswarm.protocol.scenario import Scenario, Camera`` is the usual import.
The camera sections are in :mod:`tagswarm.protocol.scenario_camera` and the sections'
base in :mod:`tagswarm.protocol.scenario_spec`; this module re-exports their names.
Frames and units: poses in the arena frame (metres, radians, z from the floor),
mounts in the robot's base frame (x forward, y left, z up).
"""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from tagswarm.protocol import tags
from tagswarm.protocol.errors import UsageError
from tagswarm.protocol.scenario_camera import (
    FISHEYE_MIN_HFOV_DEG,
    IDEAL,
    LENS_COEFFICIENTS,
    REALISTIC,
    REALISTIC_BROWN_CONRADY,
    REALISTIC_FISHEYE,
    CalibrationError,
    Camera,
    CameraSensor,
    LensName,
    lens_of,
)
from tagswarm.protocol.scenario_spec import NonNeg, Pos, Spec

__all__ = [
    "FISHEYE_MIN_HFOV_DEG", "IDEAL", "LENS_COEFFICIENTS", "REALISTIC", "REALISTIC_BROWN_CONRADY", "REALISTIC_FISHEYE",
    "Agent", "Arena", "CalibrationError", "Camera", "CameraSensor", "Clock", "Decoy", "Encoders", "Event",
    "Landmark", "LensName", "MapFrame", "Mission", "NonNeg", "Obstacle", "Pos", "Render", "Robot", "Robots",
    "Scenario", "ScenarioError", "Server", "Spec", "StartPose", "TagScheme", "decoy_cube_ids", "lens_of",
]


class ScenarioError(UsageError, ValueError):
    """The scenario (or an override of it) is invalid; the message names the field."""


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


class Decoy(Spec, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A tag that is not what it claims to be (a ``[[decoys]]`` table): a ``poster``, a plate
    like a landmark's (tag centre at (x, y, z) in the arena frame, facing ``yaw_rad``,
    upright) carrying ``tag_id`` of ``family`` (the scenario's if unset) -- a robot's ID, an
    ID nothing carries, or a tag of another family.  A ``cube``: a copy of a robot (its
    chassis and tag cube, the scenario's sizes) standing on the floor at (x, y) facing
    ``yaw_rad`` (``z_m`` and ``size_m`` unused), carrying ``tag_id`` on its front face and the
    next IDs on the other faces as a robot does (a robot's front ID copies that robot's
    cube; :func:`decoy_cube_ids`).  Only the renderer knows it (no physics, no agent): the
    agents must not take it for what its IDs name."""

    kind: Literal["poster", "cube"] = "poster"
    tag_id: Annotated[int, msgspec.Meta(ge=0)]
    family: Literal["tag36h11", "tag16h5"] | None = None
    x_m: float
    y_m: float
    z_m: Pos = 0.6
    yaw_rad: float = 0.0
    size_m: Pos = 0.16


def decoy_cube_ids(d: Decoy, family: str) -> tuple[int, ...]:
    """The six tag IDs of a ``cube`` decoy in :class:`tagswarm.protocol.tags.Face` order
    (``tag_id`` and the next five, wrapping at the end of ``family``)."""
    n = tags.family_size(family)
    return tuple((d.tag_id + k) % n for k in range(len(tags.Face)))


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
    seeded random headings), ``random`` (seeded, non-overlapping; in both the
    origin robot is then turned to see the most robots:
    :func:`tagswarm.protocol.layout.start_poses`) or
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
    after ``ack_timeout_s`` is skipped for that tick and logged, and after
    ``ack_stall_after`` such timeouts in a row (alive but silent: a controller
    whose step hangs) it is not waited for until it acknowledges a tick again
    (0: wait ``ack_timeout_s`` on every tick); one whose
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
    ack_stall_after: Annotated[int, msgspec.Meta(ge=0)] = 3
    join_timeout_s: Pos = 30.0
    command_timeout_s: Pos = 0.5


class Render(Spec, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Rendering: ``workers`` = 0 renders in the world process; K > 0 spawns K
    render worker processes (each a visual-only replica of the scene); -1 (the
    default) lets the world choose from the machine's cores and what the cameras
    ask for (``tagswarm.world.config.auto_render_workers``: in-process for a light
    load and in lockstep, else one or two workers).
    ``stagger_cameras``: the robots' cameras fire at evenly spread phases of their
    period (robot i of n at i/n of it) rather than all on the same tick, so rendering
    is spread over the ticks instead of a burst that the last camera waits behind.
    A robot's own cameras (a rig) always fire on the same tick."""

    workers: Annotated[int, msgspec.Meta(ge=-1, le=32)] = -1
    floor: bool = False
    shadows: bool = False
    stagger_cameras: bool = True


class Agent(Spec, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Agent behaviour and estimation settings shared by every robot.

    Odometry noise (per wheel): the travel d of each wheel gets variance
    ``odom_wheel_sigma^2 * |d|`` (sqrt-metre model), so the covariance grows with
    distance.  ``fix_threshold`` is the number of consecutive odometry-only
    control cycles (encoder updates) after which the robot stops and searches
    by rotating in place (the paper's active re-localisation).  ``look_around``:
    a robot holding station, other than the origin robot, first turns once on
    the spot (``search_max_sweep_rad`` at ``search_speed_rad_s``) so that
    standing robots see each other both ways, then turns on to its next fix (at
    most to the heading of its last one) and holds there.
    ``search_sigma_m`` (> 0; off by default): a moving robot also searches as
    soon as its fused position's σ (the server's newest correction, larger
    axis) passes this, at least a second after its last fix.

    Collision avoidance (``avoid``, :mod:`tagswarm.agents.avoid`): missions and run-time
    goals steer around the other robots (their poses in the server's map) and
    the arena's walls and obstacles, keeping ``avoid_clearance_m`` between
    footprints (the circle of ``tagswarm.protocol.layout.footprint_radius``); it only
    steps in when the next ``avoid_horizon_s`` of the path would come closer
    than that, and after ``avoid_stall_s`` without progress it tries the other
    side (or backs off for a robot with a lower id).  Walls and obstacles are kept
    ``avoid_sigma_k`` of the robot's own fused position σ farther still (at most 0.2 m):
    their geometry is exact, the robot's idea of where it is not.  The searching rotation is
    never changed by it.  ``make_way``: a station keeper (not the origin robot)
    that a robot come from afar has stayed near, barely moving, for 10 s steps
    aside off that robot's line, waits until it has gone and returns to its
    station and heading (:mod:`tagswarm.agents.makeway`)."""

    detector: Literal["apriltag", "aruco"] = "apriltag"
    # "cube": every visible face of a cube (and every camera) in one estimate;
    # "single_tag": the largest face alone, as a per-tag PnP would (ablation)
    pose_method: Literal["cube", "single_tag"] = "cube"
    max_hamming: Annotated[int, msgspec.Meta(ge=0, le=3)] = 0
    min_margin: NonNeg = 20.0
    # corner noise behind each view's covariance.  The renders' corners scatter 0.25-0.33 px, honest for a
    # camera at the tags' height; from the default mast (0.6 m, 15 deg down) the elevation fixes the range and
    # 0.3 px claimed about twice the views' error.  0.17 px makes their NEES 0.4-0.9; it was 0.3 until
    # the far views' shared range bias was modelled (docs/benchmarks.md, "The views' range bias in the graph,
    # and honest views").  A camera at the tags' height wants 0.3.
    pixel_sigma_px: Pos = 0.17
    max_reprojection_px: Pos = 2.0
    max_range_m: Pos = 6.0
    odom_wheel_sigma: NonNeg = 0.02
    fix_threshold: Annotated[int, msgspec.Meta(ge=1)] = 150
    search_speed_rad_s: Pos = 0.6
    search_max_sweep_rad: Pos = 6.3
    # a robot holding station (not the origin) first turns once on the spot (agents/behaviour.py)
    look_around: bool = True
    # > 0: also search once the fused position sigma (m) passes this while driving (0: the cycle count only)
    search_sigma_m: NonNeg = 0.0
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
    # walls and obstacles are kept this many of the robot's own fused position sigma farther (at most 0.2 m)
    avoid_sigma_k: NonNeg = 2.0
    # a station keeper steps aside for a robot it blocks, then returns (agents/makeway.py)
    make_way: bool = True


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


class Server(Spec, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """How the map server fuses (``[server]``): ``graph`` is the GTSAM fixed-lag pose graph
    (:mod:`tagswarm.server.fusion`); ``stitch`` is the paper's map, the composition of the
    latest relative observations along the who-sees-whom chain from the origin robot,
    carried between sightings by odometry, no factor graph (:mod:`tagswarm.server.stitchmap`).

    The graph's noise model: each wheel's travel d has variance ``odom_wheel_sigma^2 |d|``
    plus a per-metre share ``odom_scale_sigma``, and no relative observation
    is trusted better than ``obs_sigma_floor_m`` in position (the detector's systematic
    error at one viewpoint, which repeated sightings do not average out; 0 by default).

    ``odom_calibration`` (on by default) makes each robot's wheel radii and wheel base variables of
    the graph (known beforehand to 1 % and 2 %; :mod:`tagswarm.server.odomcal`): views of a robot
    then correct its odometry between them too, and the server logs what it learnt at the end.  The
    two odometry sigmas then describe only what that model leaves out; unset, they are 0.01 and
    0.01 with it, and with ``false`` the agents' ``agent.odom_wheel_sigma`` and 0.02 (wheel radius and
    base miscalibration folded into per-increment noise, as before it existed: too wide over a few
    seconds, so the fused NEES of most scenes was 0.2-0.4, conservative).
    docs/benchmarks.md, "Odometry calibration in the graph", has what it changes.

    ``range_bias_sigma`` (m^-2): far views overestimate the range by about ``b r^3`` with the same ``b``
    in every view (1.5e-4 for the default 320 x 240 camera); ``b`` is one variable of the graph, with
    this prior around 0, that every robot view from 2 m on goes through (:mod:`tagswarm.server.rangebias`).
    0 leaves it out (plain between-factors, as before 2026-12-07).

    The graph vouches for a placed robot (its correction says ``localised``, its agent steers on
    it, its fused trajectory is recorded) only while its fused position is surer than
    ``claim_sigma_m`` (m, standard deviation along the reported covariance's worst axis) and its
    estimate is not in dispute (two or more of its latest observations contradicted the map and
    none agreed since: a robot carried away is seen elsewhere from the first frame, but the
    evidence that moves it takes a second).  Until then it is in the map, fused and shown with its
    covariance, but reported unlocalised.  A robot placed through a chain of far views starts with
    a heading several degrees unsure and a position decimetres to a metre unsure.  0 vouches for
    every robot as soon as it is placed.

    ``start_prior_sigma`` (m and rad, 0 = off, the default): the robots' start poses of the
    scenario (``robots.start``, or the ones ``grid`` / ``random`` draw) are known to the server, as
    when robots start from docks at surveyed places; each robot is in the map from its first
    odometry with a prior of this standard deviation on its start pose (the graph only).  Off, a
    robot is in the map once a camera links it to the origin robot, the paper's way."""

    method: Literal["graph", "stitch"] = "graph"
    odom_wheel_sigma: NonNeg | None = None
    odom_scale_sigma: NonNeg | None = None
    obs_sigma_floor_m: NonNeg = 0.0
    claim_sigma_m: NonNeg = 0.5
    odom_calibration: bool = True
    range_bias_sigma: NonNeg = 1.5e-4
    start_prior_sigma: NonNeg = 0.0


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
    decoys: tuple[Decoy, ...] = ()
    encoders: Encoders = Encoders()
    clock: Clock = Clock()
    render: Render = Render()
    camera: CameraSensor = CameraSensor()
    agent: Agent = Agent()
    missions: tuple[Mission, ...] = ()
    map: MapFrame = MapFrame()
    server: Server = Server()
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
