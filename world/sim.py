"""Physics of the arena and the differential-drive robots (pybullet, no I/O).

Each robot is one rigid body (a collision box around chassis and cube) driven
by wheel-speed kinematics: every physics substep its base velocity is set from
the commanded wheel speeds and the robot's *true* wheel radii and wheel base,
and pybullet resolves collisions with walls, obstacles and other robots.
Contacts are frictionless so the imposed velocity is what the robot does
unless something blocks it.

Encoders integrate each wheel's rotation from the body's actual motion.  The
error model (per robot, drawn once from the seed) makes the true wheel radii
and wheel base differ from the nominal ones the agents assume, adds random
slip proportional to the square root of the wheel travel, and lets wheels spin
freely when the robot is blocked, so dead reckoning drifts like a real robot's.

:meth:`Sim.place_robot` moves a robot by hand (teleport / push: a kidnapped
robot) without turning its wheels.  Contact events (robot–robot, –obstacle,
–wall) are counted after every physics step by :mod:`tagswarm.world.contacts`.

Frames: arena (world) frame, z up, origin at the arena centre.  A robot's base
frame sits on the floor at the chassis centre, x forward, y left.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from tagswarm.protocol.errors import TagswarmError
from tagswarm.protocol.geometry import wrap_angle
from tagswarm.protocol.layout import start_poses, wall_boxes
from tagswarm.protocol.scenario import Scenario
from tagswarm.world._pybullet import pb
from tagswarm.world.contacts import ContactCounter, StaticBox

CONTACT_SLACK_M = 0.05
"""Added to the distance robots can cover in a tick when the contact broad phase
picks the pairs to watch (m): solver pushes out of penetration are millimetres."""
OVERLAP_TOL_M = 1e-4
"""A placement may overlap a wall, obstacle or robot by at most this much (m): a
robot set flush against a wall measures about -3e-7 m."""


class PlacementError(TagswarmError, ValueError):
    """A robot cannot be placed where asked; the message says why."""


@dataclass
class RobotState:
    """Mutable per-robot state of the simulation."""

    robot_id: int
    body: int
    radius_l_m: float  # true wheel radii and wheel base (nominal x (1 + bias))
    radius_r_m: float
    base_m: float
    rng: np.random.Generator
    cmd_l_rad_s: float = 0.0
    cmd_r_rad_s: float = 0.0
    cmd_stamp_ns: int | None = None
    timed_out: bool = True
    wheel_l_rad: float = 0.0
    wheel_r_rad: float = 0.0
    x_m: float = 0.0
    y_m: float = 0.0
    yaw_rad: float = 0.0
    v_m_s: float = 0.0
    omega_rad_s: float = 0.0
    counters: dict[str, int] = field(default_factory=lambda: {"cmd_clamped": 0, "cmd_timeouts": 0})


class Sim:
    """The physical world: arena, obstacles, robots, encoders.  Deterministic for
    a given scenario (seed) and command sequence."""

    def __init__(self, scenario: Scenario) -> None:
        self.s = scenario
        self.cid = pb.connect(pb.DIRECT)
        self.dt_ns = round(1e9 / scenario.clock.tick_hz)
        self.substeps = scenario.clock.physics_substeps
        self.sub_dt_s = self.dt_ns / 1e9 / self.substeps
        self.step_index = 0
        pb.setPhysicsEngineParameter(fixedTimeStep=self.sub_dt_s, numSubSteps=1, deterministicOverlappingPairs=1,
                                     physicsClientId=self.cid)
        pb.setGravity(0, 0, -9.81, physicsClientId=self.cid)
        self._walls: list[int] = []
        self._obstacles: list[int] = []
        self._statics: list[StaticBox] = []
        self._build_static()
        self.robots: dict[int, RobotState] = {}
        r = scenario.robot
        self._half = (max(r.chassis_length_m, r.cube_edge_m) / 2, max(r.chassis_width_m, r.cube_edge_m) / 2,
                      (r.ground_clearance_m + r.chassis_height_m + r.cube_edge_m) / 2)
        self._half_h = self._half[2]
        enc = scenario.encoders
        for rid, (x, y, yaw) in zip(scenario.robot_ids, start_poses(scenario), strict=True):
            rng = np.random.default_rng([scenario.seed, rid])
            if enc.error_model:
                bias_l, bias_r = rng.normal(0.0, enc.radius_bias_sigma, 2)
                bias_b = rng.normal(0.0, enc.wheel_base_bias_sigma)
            else:
                bias_l = bias_r = bias_b = 0.0
            self.robots[rid] = RobotState(
                robot_id=rid, body=self._make_robot(x, y, yaw), rng=rng,
                radius_l_m=r.wheel_radius_m * (1 + float(bias_l)), radius_r_m=r.wheel_radius_m * (1 + float(bias_r)),
                base_m=r.wheel_base_m * (1 + float(bias_b)), x_m=x, y_m=y, yaw_rad=yaw)
        # created after the bodies, so their ids do not depend on it: the footprint that placements are checked with
        self._probe = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=self._half, physicsClientId=self.cid)
        v_max = r.max_wheel_speed_rad_s * max(max(st.radius_l_m, st.radius_r_m) for st in self.robots.values())
        self.contacts = ContactCounter(self.cid, {st.body: rid for rid, st in self.robots.items()}, self._statics,
                                       radius_m=math.hypot(self._half[0], self._half[1]),
                                       reach_m=2 * v_max * self.dt_ns / 1e9 + CONTACT_SLACK_M)

    # ------------------------------------------------------------------ build
    def _static_box(self, half: tuple[float, float, float], pos: tuple[float, float, float], yaw: float = 0.0) -> int:
        col = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=half, physicsClientId=self.cid)
        body = pb.createMultiBody(0, col, -1, pos, pb.getQuaternionFromEuler((0, 0, yaw)), physicsClientId=self.cid)
        pb.changeDynamics(body, -1, lateralFriction=0.0, restitution=0.0, physicsClientId=self.cid)
        return body

    def _build_static(self) -> None:
        a = self.s.arena
        self._static_box((a.size_x_m, a.size_y_m, 0.05), (0, 0, -0.05))
        for pos, half in wall_boxes(a):
            body = self._static_box(half, pos)
            self._walls.append(body)
            self._statics.append(StaticBox(body, "wall", pos[0], pos[1], 0.0, half[0], half[1]))
        for ob in a.obstacles:
            body = self._static_box((ob.size_x_m / 2, ob.size_y_m / 2, ob.size_z_m / 2),
                                    (ob.x_m, ob.y_m, ob.size_z_m / 2), ob.yaw_rad)
            self._obstacles.append(body)
            self._statics.append(StaticBox(body, "obstacle", ob.x_m, ob.y_m, ob.yaw_rad, ob.size_x_m / 2,
                                           ob.size_y_m / 2))

    def _make_robot(self, x: float, y: float, yaw: float) -> int:
        col = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=self._half, physicsClientId=self.cid)
        body = pb.createMultiBody(5.0, col, -1, (x, y, self._half_h), pb.getQuaternionFromEuler((0, 0, yaw)),
                                  physicsClientId=self.cid)
        pb.changeDynamics(body, -1, lateralFriction=0.0, spinningFriction=0.0, rollingFriction=0.0,
                          linearDamping=0.0, angularDamping=0.0, restitution=0.0, physicsClientId=self.cid)
        return body

    # ------------------------------------------------------------------ commands
    @property
    def time_ns(self) -> int:
        """Simulation time of the current state."""
        return self.step_index * self.dt_ns

    def set_command(self, robot_id: int, left_rad_s: float, right_rad_s: float) -> bool:
        """Set a robot's wheel speeds (rad/s), clamped to the limit; returns True
        if clamping was needed.  The command expires after clock.command_timeout_s."""
        st = self.robots[robot_id]
        lim = self.s.robot.max_wheel_speed_rad_s
        cl, cr = min(max(left_rad_s, -lim), lim), min(max(right_rad_s, -lim), lim)
        clamped = (cl, cr) != (left_rad_s, right_rad_s)
        if clamped:
            st.counters["cmd_clamped"] += 1
        st.cmd_l_rad_s, st.cmd_r_rad_s, st.cmd_stamp_ns, st.timed_out = cl, cr, self.time_ns, False
        return clamped

    def _expire_commands(self) -> None:
        timeout_ns = int(self.s.clock.command_timeout_s * 1e9)
        for st in self.robots.values():
            if not st.timed_out and (st.cmd_stamp_ns is None or self.time_ns - st.cmd_stamp_ns > timeout_ns):
                st.cmd_l_rad_s = st.cmd_r_rad_s = 0.0
                st.timed_out = True
                st.counters["cmd_timeouts"] += 1

    # ------------------------------------------------------------------ stepping
    def step(self) -> None:
        """Advance one tick (``physics_substeps`` physics steps)."""
        self._expire_commands()
        self.contacts.begin_tick({st.body: (st.x_m, st.y_m) for st in self.robots.values()})
        for _ in range(self.substeps):
            for st in self.robots.values():
                v = (st.radius_l_m * st.cmd_l_rad_s + st.radius_r_m * st.cmd_r_rad_s) / 2.0
                w = (st.radius_r_m * st.cmd_r_rad_s - st.radius_l_m * st.cmd_l_rad_s) / st.base_m
                vz = pb.getBaseVelocity(st.body, physicsClientId=self.cid)[0][2]
                pb.resetBaseVelocity(st.body, (v * math.cos(st.yaw_rad), v * math.sin(st.yaw_rad), vz), (0, 0, w),
                                     physicsClientId=self.cid)
            pb.stepSimulation(physicsClientId=self.cid)
            for st in self.robots.values():
                self._update_robot(st)
            self.contacts.update()
        self.step_index += 1

    def _update_robot(self, st: RobotState) -> None:
        pos, quat = pb.getBasePositionAndOrientation(st.body, physicsClientId=self.cid)
        yaw = pb.getEulerFromQuaternion(quat)[2]
        dx, dy = pos[0] - st.x_m, pos[1] - st.y_m
        dyaw = wrap_angle(yaw - st.yaw_rad)
        mid = st.yaw_rad + dyaw / 2.0
        ds = dx * math.cos(mid) + dy * math.sin(mid)
        # true travel of each wheel's contact point for the body's actual motion
        arc_l = ds - dyaw * st.base_m / 2.0
        arc_r = ds + dyaw * st.base_m / 2.0
        if self.s.encoders.error_model:
            cmd_l = st.cmd_l_rad_s * st.radius_l_m * self.sub_dt_s
            cmd_r = st.cmd_r_rad_s * st.radius_r_m * self.sub_dt_s
            # a blocked robot's wheels keep turning: the encoders count the commanded rotation
            if abs(cmd_l) > abs(arc_l) + 1e-6 or abs(cmd_r) > abs(arc_r) + 1e-6:
                arc_l, arc_r = cmd_l, cmd_r
            sig = self.s.encoders.slip_sigma
            if sig > 0:
                arc_l += float(st.rng.normal(0.0, sig * math.sqrt(abs(arc_l))))
                arc_r += float(st.rng.normal(0.0, sig * math.sqrt(abs(arc_r))))
        st.wheel_l_rad += arc_l / st.radius_l_m
        st.wheel_r_rad += arc_r / st.radius_r_m
        st.v_m_s = ds / self.sub_dt_s
        st.omega_rad_s = dyaw / self.sub_dt_s
        st.x_m, st.y_m, st.yaw_rad = pos[0], pos[1], yaw

    # ------------------------------------------------------------------ placing
    def place_robot(self, robot_id: int, x_m: float, y_m: float, yaw_rad: float) -> None:
        """Put robot ``robot_id``'s base at (x_m, y_m, yaw_rad) in the arena frame, at
        rest, without turning its wheels (its encoders never see the move; its wheel
        command stays).  Raises :class:`PlacementError` (robot unchanged) for an
        unknown robot, a non-finite pose, a footprint not inside the walls, or one
        that would overlap a wall, obstacle or other robot."""
        st = self.robots.get(robot_id)
        if st is None:
            raise PlacementError(f"robot {robot_id} is not in the roster ({len(self.robots)} robots)")
        if not all(math.isfinite(v) for v in (x_m, y_m, yaw_rad)):
            raise PlacementError(f"robot {robot_id}: pose ({x_m}, {y_m}, {yaw_rad}) is not finite")
        yaw_rad = wrap_angle(yaw_rad)
        hl, hw = self._half[0], self._half[1]
        c, s = abs(math.cos(yaw_rad)), abs(math.sin(yaw_rad))
        a = self.s.arena
        if (abs(x_m) + c * hl + s * hw > a.size_x_m / 2 - a.wall_thickness_m / 2
                or abs(y_m) + s * hl + c * hw > a.size_y_m / 2 - a.wall_thickness_m / 2):
            raise PlacementError(f"robot {robot_id} at ({x_m:.3f}, {y_m:.3f}, {yaw_rad:.3f} rad) would not be "
                                 f"inside the arena walls")
        pos, quat = (x_m, y_m, self._half_h), pb.getQuaternionFromEuler((0, 0, yaw_rad))
        for what, body in self._others(robot_id):
            hits = pb.getClosestPoints(bodyA=-1, bodyB=body, distance=0.0, collisionShapeA=self._probe,
                                       collisionShapePositionA=pos, collisionShapeOrientationA=quat,
                                       physicsClientId=self.cid)
            depth = min((p[8] for p in hits), default=0.0)
            if depth < -OVERLAP_TOL_M:
                raise PlacementError(f"robot {robot_id} at ({x_m:.3f}, {y_m:.3f}, {yaw_rad:.3f} rad) would overlap "
                                     f"{what} by {-depth * 1000:.0f} mm")
        pb.resetBasePositionAndOrientation(st.body, pos, quat, physicsClientId=self.cid)
        pb.resetBaseVelocity(st.body, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), physicsClientId=self.cid)
        # the pose as pybullet holds it, so the next step's wheel travel is the physical motion alone
        got, got_quat = pb.getBasePositionAndOrientation(st.body, physicsClientId=self.cid)
        st.x_m, st.y_m, st.yaw_rad = got[0], got[1], pb.getEulerFromQuaternion(got_quat)[2]
        st.v_m_s = st.omega_rad_s = 0.0

    def _others(self, robot_id: int) -> list[tuple[str, int]]:
        out = [(f"wall {i}", b) for i, b in enumerate(self._walls)]
        out += [(f"obstacle {i}", b) for i, b in enumerate(self._obstacles)]
        out += [(f"robot {rid}", st.body) for rid, st in self.robots.items() if rid != robot_id]
        return out

    # ------------------------------------------------------------------ sensing
    def encoder_ticks(self, robot_id: int) -> tuple[int, int]:
        """Cumulative (left, right) encoder counts."""
        st = self.robots[robot_id]
        tpr = self.s.encoders.ticks_per_rev
        return (math.floor(st.wheel_l_rad / (2 * math.pi) * tpr), math.floor(st.wheel_r_rad / (2 * math.pi) * tpr))

    def base_pose(self, robot_id: int) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
        """Position (floor level) and (x, y, z, w) orientation of the robot's base frame."""
        pos, quat = pb.getBasePositionAndOrientation(self.robots[robot_id].body, physicsClientId=self.cid)
        return (pos[0], pos[1], pos[2] - self._half_h), tuple(quat)  # type: ignore[return-value]

    def close(self) -> None:
        if self.cid >= 0:
            pb.disconnect(physicsClientId=self.cid)
            self.cid = -1

    def __enter__(self) -> Sim:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
