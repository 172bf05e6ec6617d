"""Every payload that crosses a process boundary.

Conventions (see docs/architecture.md, section 4): SI units with the unit in the field name,
radians, right-handed frames, REP-103 body axes (x forward, y left, z up) and the
OpenCV optical frame for cameras (z out of the lens, x right, y down).  Every
message carries ``seq`` (per-publisher sequence number) and ``stamp_ns``
(simulation time in nanoseconds, the only clock), and ``robot_id`` where a robot
is involved.  Quaternions are (x, y, z, w).  Covariances are row-major flattened
matrices.

The structs are tagged (field ``type``) so that a recording or journal can hold a
mix of them and be decoded with one union decoder.
"""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec

# Bounds chosen so that a hostile payload cannot ask us for absurd allocations or
# ids; robots and tag ids are small, sequence numbers and stamps are non-negative.
RobotId = Annotated[int, msgspec.Meta(ge=0, le=100_000)]
Seq = Annotated[int, msgspec.Meta(ge=0)]
StampNs = Annotated[int, msgspec.Meta(ge=0)]
Count = Annotated[int, msgspec.Meta(ge=0)]
Int64 = Annotated[int, msgspec.Meta(ge=-(2**63), le=2**63 - 1)]
Pixels = Annotated[int, msgspec.Meta(ge=1, le=8192)]
TagId = Annotated[int, msgspec.Meta(ge=0, le=2**31 - 1)]  # tag ids and landmark ids; robot ids are smaller
FocalPx = Annotated[float, msgspec.Meta(gt=0)]


class Msg(msgspec.Struct, frozen=True, kw_only=True, tag_field="type"):
    """Base of every wire message."""

    seq: Seq
    stamp_ns: StampNs


class Pose3(msgspec.Struct, frozen=True, kw_only=True):
    """A rigid transform: translation in metres, unit quaternion (x, y, z, w)
    (a norm off 1 by more than 1 % is rejected as ``inconsistent``)."""

    x_m: float
    y_m: float
    z_m: float
    qx: float = 0.0
    qy: float = 0.0
    qz: float = 0.0
    qw: float = 1.0


class Tick(Msg, frozen=True, kw_only=True, tag="tick"):
    """World clock: the world has finished step ``step`` and published every sensor
    message of that step before this one.  ``cameras_rendered`` lists the
    ``"robot_id/camera"`` pairs that have an image stamped with this tick, so a
    lockstep participant knows what to wait for.  ``run_id`` names the world
    instance (``"<run>-<random>"``, new for a restarted world): receivers follow
    one instance and reject another one's ticks while it is alive."""

    run_id: str
    step: Count
    dt_ns: Annotated[int, msgspec.Meta(gt=0)]
    mode: Literal["realtime", "lockstep"]
    cameras_rendered: tuple[str, ...] = ()

    def cameras_of(self) -> dict[int, set[str]]:
        """``cameras_rendered`` by robot id: robot -> names of its cameras with an image of this
        step (a malformed pair is skipped)."""
        out: dict[int, set[str]] = {}
        for pair in self.cameras_rendered:
            rid, sep, cam = pair.partition("/")
            if sep and rid.isdigit():
                out.setdefault(int(rid), set()).add(cam)
        return out


class TickAck(Msg, frozen=True, kw_only=True, tag="tick_ack"):
    """A lockstep participant (``"agent/3"``, ``"server/0"``, ``"render/1"``) has
    fully processed world step ``step``."""

    participant: str
    step: Count


class CameraImage(Msg, frozen=True, kw_only=True, tag="camera_image"):
    """One camera frame.  ``data`` is (height, width) uint8 row-major for
    ``encoding == "mono8"``.  Intrinsics (fx, fy, cx, cy) are in OpenCV's pixel
    convention (pixel centres at integer coordinates).  ``mount`` is the pose of
    the camera optical frame in the robot base frame (T_base_camera), so a point
    p_cam maps to p_base = R p_cam + t.

    ``lens`` and ``distortion`` (``version`` 2 on) are OpenCV's models: ``pinhole``
    (no coefficients), ``brown_conrady`` (k1, k2, p1, p2, k3 of ``cv2.projectPoints``)
    or ``fisheye`` (equidistant, k1..k4 of ``cv2.fisheye.projectPoints``); the pixels
    of the image are those of that model, and it is the true one (a calibration error
    is applied by the agent, docs/camera.md).  Versions: 1 (before lenses) had neither
    field; an old recording decodes as version 1 with the defaults, a pinhole without
    distortion, which is what its images were.  Senders now write ``version=2``."""

    robot_id: RobotId
    camera: str
    step: Count
    width: Pixels
    height: Pixels
    encoding: Literal["mono8"] = "mono8"
    fx_px: FocalPx
    fy_px: FocalPx
    cx_px: float
    cy_px: float
    mount: Pose3
    data: bytes
    lens: Literal["pinhole", "brown_conrady", "fisheye"] = "pinhole"
    distortion: Annotated[tuple[float, ...], msgspec.Meta(max_length=8)] = ()
    version: Annotated[int, msgspec.Meta(ge=1)] = 1


class EncoderTicks(Msg, frozen=True, kw_only=True, tag="encoder_ticks"):
    """Cumulative wheel encoder counts since the world started (they wrap never;
    int64 on the wire).  Positive counts drive the robot forward."""

    robot_id: RobotId
    left_ticks: Int64
    right_ticks: Int64
    ticks_per_rev: Annotated[int, msgspec.Meta(ge=1)]


class WheelCommand(Msg, frozen=True, kw_only=True, tag="wheel_command"):
    """Commanded wheel angular speeds in rad/s (positive drives forward)."""

    robot_id: RobotId
    left_rad_s: float
    right_rad_s: float


class GroundTruthPose(Msg, frozen=True, kw_only=True, tag="ground_truth"):
    """True pose of a robot's base in the arena (world) frame.  Evaluation only:
    agents and the server never subscribe to it."""

    robot_id: RobotId
    step: Count
    x_m: float
    y_m: float
    yaw_rad: float
    pose: Pose3
    v_m_s: float = 0.0
    omega_rad_s: float = 0.0


class RelativeObservation(Msg, frozen=True, kw_only=True, tag="observation"):
    """Pose of the observed robot's base (or of a landmark tag) in the observer's
    base frame, measured from one camera frame (or one synchronised rig).
    ``cov`` is the 3x3 covariance of (x_m, y_m, yaw_rad) (every ``cov`` must be
    symmetric positive semi-definite, else the message is ``inconsistent``)."""

    robot_id: RobotId  # observer
    target_kind: Literal["robot", "landmark"]
    target_id: TagId
    x_m: float
    y_m: float
    yaw_rad: float
    cov: tuple[float, ...]
    pose: Pose3
    reprojection_rms_px: float
    tag_ids: tuple[TagId, ...]
    camera: str


class OdometryEstimate(Msg, frozen=True, kw_only=True, tag="odometry"):
    """Dead-reckoned pose of ``base_link`` in the robot's ``odom`` frame, with the
    3x3 covariance of (x_m, y_m, yaw_rad) and the distance travelled so far.
    ``slip_m`` is the cumulative evidence of wheel slip or stall in metres of wheel
    travel (commanded against measured wheel rotation, summed over both wheels;
    0 when there is none): the server widens the odometry's covariance where it
    grows.  Older senders omit it (0)."""

    robot_id: RobotId
    x_m: float
    y_m: float
    yaw_rad: float
    cov: tuple[float, ...]
    distance_m: float
    slip_m: Annotated[float, msgspec.Meta(ge=0)] = 0.0


class Correction(Msg, frozen=True, kw_only=True, tag="correction"):
    """The server's ``map -> odom_k`` transform for one robot plus its fused pose in
    the map frame and that pose's 3x3 covariance.  ``stamp_ns`` is the simulation
    time of the newest data the estimate includes (the server's clock), ``pose_stamp_ns``
    the time of the fused pose: this robot's newest odometry the estimate includes, which
    lags ``stamp_ns`` while that odometry is late (0: the same as ``stamp_ns``); ``last_fix_ns`` the time of the
    newest accepted observation involving this robot (as observer or observed).
    In lockstep the server sends one every tick; in realtime one when it matters: a new
    fix, a change of localisation, ``map -> odom`` moved by 1 mm or 1 mrad, or 100 ms of
    simulation time after the last.  ``localised=False`` means the server cannot place
    this robot yet (every pose field and ``cov`` zero), or does not vouch for its place:
    the map has it, but less sure than ``[server] claim_sigma_m`` or with its latest
    observations putting it elsewhere; the fields then hold the map's loose estimate, which
    a robot never vouched for drives on slowly (the global map lists it too).  ``cov`` is GTSAM's
    marginal of the Pose2 in its tangent space: the position block is in the
    robot's own axes (x forward, y left), so rotate it by the yaw for the map
    frame."""

    robot_id: RobotId
    map_odom_x_m: float
    map_odom_y_m: float
    map_odom_yaw_rad: float
    x_m: float
    y_m: float
    yaw_rad: float
    cov: tuple[float, ...]
    last_fix_ns: StampNs = 0
    localised: bool = True
    pose_stamp_ns: StampNs = 0

    @property
    def pose_time_ns(self) -> int:
        """Simulation time of ``x_m``, ``y_m``, ``yaw_rad`` (``pose_stamp_ns``, else ``stamp_ns``)."""
        return self.pose_stamp_ns or self.stamp_ns


class Goal(Msg, frozen=True, kw_only=True, tag="goal"):
    """Send a robot to (x_m, y_m) in the map frame; it stops within ``tolerance_m``."""

    robot_id: RobotId
    x_m: float
    y_m: float
    tolerance_m: Annotated[float, msgspec.Meta(gt=0)] = 0.1


class MapEntry(msgspec.Struct, frozen=True, kw_only=True):
    """One robot in the global map (map frame); ``cov`` and ``pose_stamp_ns`` as in
    :class:`Correction` (position block in the robot's own axes; 0: the map's
    ``stamp_ns``).  ``localised`` is whether the server vouches for the pose, as in the
    robot's :class:`Correction` (False: the map's loose estimate)."""

    robot_id: RobotId
    x_m: float
    y_m: float
    yaw_rad: float
    cov: tuple[float, ...]
    last_seen_ns: StampNs
    alive: bool
    localised: bool = True
    pose_stamp_ns: StampNs = 0

    def pose_time_at(self, map_stamp_ns: int) -> int:
        """Simulation time of ``x_m``, ``y_m``, ``yaw_rad`` (``pose_stamp_ns``, else the
        ``stamp_ns`` of the :class:`GlobalMap` holding this entry)."""
        return self.pose_stamp_ns or map_stamp_ns


class GlobalMap(Msg, frozen=True, kw_only=True, tag="global_map"):
    """Every robot's fused pose; ``edges`` lists (observer, observed) pairs seen
    recently."""

    origin_id: RobotId
    robots: tuple[MapEntry, ...]
    edges: tuple[tuple[RobotId, RobotId], ...] = ()


class AgentStatus(Msg, frozen=True, kw_only=True, tag="status"):
    """Periodic health of one process: its mode and its counters (frames
    processed/skipped, rejected payloads per kind, ...)."""

    robot_id: RobotId | None = None
    role: str
    mode: str
    counters: dict[str, int] = {}


class WorldCommand(Msg, frozen=True, kw_only=True, tag="world_command"):
    """An operator's (or a test's) intervention in the physical world, applied by
    the world at its next step: ``teleport`` puts robot ``robot_id``'s base at
    (x_m, y_m, yaw_rad) in the arena frame; ``push`` moves it by (x_m, y_m) in the
    arena frame and turns it by yaw_rad.  The wheels do not turn (a kidnapped
    robot's odometry knows nothing of it).  Ground truth for evaluation follows."""

    robot_id: RobotId
    action: Literal["teleport", "push"]
    x_m: float
    y_m: float
    yaw_rad: float = 0.0


class Relocalisation(Msg, frozen=True, kw_only=True, tag="relocalisation"):
    """The server re-initialised robot ``robot_id`` because a mutually consistent
    set of observations contradicted its estimate (a pushed, slipping or kidnapped
    robot).  Poses are map-frame (x_m, y_m, yaw_rad) at ``stamp_ns`` before and
    after; ``observers`` are the robots whose observations formed the consistent
    set (``-1`` stands for a landmark), ``evidence`` how many observations it
    held."""

    robot_id: RobotId
    from_x_m: float
    from_y_m: float
    from_yaw_rad: float
    to_x_m: float
    to_y_m: float
    to_yaw_rad: float
    jump_m: Annotated[float, msgspec.Meta(ge=0)]
    evidence: Count
    observers: tuple[Annotated[int, msgspec.Meta(ge=-1, le=100_000)], ...] = ()


class ClaimReply(Msg, frozen=True, kw_only=True, tag="claim_reply"):
    """The claim authority's answer to an agent container's query on the claim key:
    robot ``robot_id`` (0..) with the Zenoh login of that robot's agent (``user``,
    ``password``), or ``robot_id`` -1 and the ``reason``.  ``robots`` is the run's
    number of robots; ``seq`` counts the authority's replies, ``stamp_ns`` is 0 (claims
    happen before the simulation clock starts).  Only the claim authority may answer
    and only the claimant login may ask (router ACL), so the password travels to
    nobody else."""

    robot_id: Annotated[int, msgspec.Meta(ge=-1, le=100_000)]
    robots: Count
    user: str = ""  # the codec's 2 KB limit bounds these
    password: str = ""
    reason: str = ""

    @property
    def granted(self) -> bool:
        return self.robot_id >= 0


class RenderPoses(Msg, frozen=True, kw_only=True, tag="render_poses"):
    """World -> render workers: the robot poses to render for step ``step`` and the
    cameras each worker must render (``"robot_id/camera"``); ``poses[i]`` is robot
    ``robot_ids[i]``'s base in the arena frame."""

    step: Count
    robot_ids: tuple[RobotId, ...]
    poses: tuple[Pose3, ...]
    cameras: tuple[str, ...]


AnyMessage = (
    Tick
    | TickAck
    | CameraImage
    | EncoderTicks
    | WheelCommand
    | GroundTruthPose
    | RelativeObservation
    | OdometryEstimate
    | Correction
    | GlobalMap
    | AgentStatus
    | RenderPoses
    | Goal
    | WorldCommand
    | Relocalisation
    | ClaimReply
)
