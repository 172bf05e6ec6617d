"""What a robot does: its mission, go-to-goal control and the paper's Fig. 3
self-calibrating loop (pure code, no I/O).

Modes:
- ``visual``: a visual fix within the last ``visual_hold`` cycles (an accepted
  observation of another robot, or a server correction built on a new
  observation involving this robot).
- ``odometry``: no fix for fewer than ``fix_threshold`` moving cycles.
- ``searching``: too long on odometry alone (or never localised): stop the
  mission and rotate in place until a fix, at most ``search_max_sweep_rad``.
  A robot holding station searches only if it is still not placed after
  three times ``fix_threshold`` cycles, and then turns the whole sweep even if
  placed on the way (turning on the spot keeps its station).
- Looking around (shown as ``searching``): a robot holding station, unless it
  is the map's anchor (the origin robot), first turns once on the spot, the
  whole sweep at ``search_speed_rad_s`` (``agent.look_around``).
- Either whole turn of a station keeper ends at a fix: if it had one on the
  way, it turns on to its next fix, at most to the heading of its last one
  (see :meth:`Behaviour._turn_on`), and holds there; without one it holds at
  its own heading.  Standing robots see each other both ways only if they
  look: a pair that sees each other gets its relative heading from two
  bearings, which a far cube's face alone leaves several degrees uncertain, and
  those degrees become decimetres along a chain (measured: a yard of 9 still
  robots, fused RMSE 20 cm without it, 5.5 cm with it and < 1 cm once every
  robot has turned).
- ``lost``: a full sweep found nobody: resume the mission slowly (or stand
  still if the robot has never been localised) until the next fix.
- On a loose pose: a robot the server has placed but does not vouch for (its
  position σ over ``[server] claim_sigma_m``) searches like one not placed, and
  after ``fix_threshold`` cycles of that drives its mission slowly
  (``lost_speed_factor``) on the map's estimate: standing and turning on the
  spot gives its observers the same views again, moving gives new ones
  (measured: a lab of 10 robots whose origin saw nobody, two patrols stood
  40 s).

Only cycles in which the robot moves count towards the threshold: dead
reckoning does not drift while the robot stands still.

Without a map server (its liveliness token gone) nothing can correct the pose:
the robot stays in ``odometry`` mode and keeps its mission on dead reckoning
(a search cannot help), and searches again once a server is back if it has
gone too long without a fix meanwhile.

Missions and run-time goals go through :mod:`tagswarm.agents.avoid` (unless
``agent.avoid`` is off): the go-to-goal command is kept while its path is
clear of the other robots (``neighbours``, from the server's map) and of the
arena's walls and obstacles (``static_obstacles``), and replaced by an avoiding
one otherwise; a waypoint or goal occupied by another robot counts as reached
as close as the clearance allows.  After a stall the robot follows a way round
the room (:mod:`tagswarm.agents.route`) towards its target, if there is one.
Holding and searching are not affected.

Frames: poses are (x_m, y_m, yaw_rad) of base_link in the map frame; waypoints
are given in the arena frame and converted with ``arena_to_map``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from functools import cached_property

from tagswarm.agents.avoid import Avoider, Box, Neighbour
from tagswarm.agents.gates import Gate, gates, must_wait
from tagswarm.agents.makeway import MakeWay
from tagswarm.agents.route import Grid, Route, blocked, plan, static_grid
from tagswarm.protocol.geometry import Pose2, wrap_angle
from tagswarm.protocol.geometry import se2_compose as compose
from tagswarm.protocol.layout import footprint_radius
from tagswarm.protocol.scenario import Agent, Mission, Robot

#: a station keeper's turn on to its last fix's heading ends this close to it (or this far past it), and slows
#: to it at this gain (1/s)
TURN_ON_TOL_RAD = 0.01
TURN_ON_PASSED_RAD = 0.3
TURN_ON_GAIN = 3.0
#: a way round the room keeps this much beyond the avoidance's clearance, so the avoidance lets the robot follow it
KEEP_MARGIN_M = 0.05
#: a goal the room offers no way to is planned for again this much later (a search that finds none has gone
#: through every cell of the room: 0.2 s in a 10 m x 10 m one)
ROUTE_RETRY_S = 5.0
#: a robot waits outside a narrow passage at most this long (s) before it goes on anyway (the avoidance's
#: giving way then decides): the robot it waits for may have stopped in it without showing as standing
GATE_MAX_WAIT_S = 15.0


class Mode(StrEnum):
    VISUAL = "visual"
    ODOMETRY = "odometry"
    SEARCHING = "searching"
    LOST = "lost"


def wheel_speeds(v_m_s: float, w_rad_s: float, robot: Robot) -> tuple[float, float]:
    """(left, right) wheel speeds in rad/s for a body twist, scaled down together
    so that neither exceeds the wheel limit (keeps the path's curvature)."""
    r, b = robot.wheel_radius_m, robot.wheel_base_m
    left, right = (v_m_s - w_rad_s * b / 2) / r, (v_m_s + w_rad_s * b / 2) / r
    worst = max(abs(left), abs(right))
    if worst > robot.max_wheel_speed_rad_s:
        k = robot.max_wheel_speed_rad_s / worst
        left, right = left * k, right * k
    return left, right


def go_to(pose: Pose2, goal: tuple[float, float], cfg: Agent, speed_factor: float = 1.0) -> tuple[float, float]:
    """Unicycle go-to-goal twist (v_m_s, w_rad_s): turn on the spot when the goal
    is far off the heading, otherwise drive and steer proportionally."""
    dx, dy = goal[0] - pose[0], goal[1] - pose[1]
    dist = math.hypot(dx, dy)
    err = wrap_angle(math.atan2(dy, dx) - pose[2])
    w = max(-cfg.max_turn_rad_s, min(cfg.max_turn_rad_s, 2.0 * err)) * speed_factor
    if abs(err) > 0.6:
        return 0.0, w
    v = min(cfg.max_speed_m_s, 0.8 * dist) * speed_factor * math.cos(err)
    return v, w


@dataclass
class Behaviour:
    """One robot's decision state; call :meth:`cycle` once per control step."""

    robot_id: int
    mission: Mission
    cfg: Agent
    robot: Robot
    arena_to_map: Pose2 = (0.0, 0.0, 0.0)
    leapfrog_team: tuple[int, ...] = ()
    static_obstacles: tuple[Box, ...] = ()  # map frame (tagswarm.agents.avoidgeom.static_boxes)
    anchor: bool = False  # its first pose is the map frame: turning would only blur the frame, it never looks around
    mode: Mode = Mode.ODOMETRY
    counter: int = 0
    since_fix: int = 1_000_000
    visual_hold: int = 15  # cycles a fix keeps the robot in visual mode (0.5 s at 30 Hz)
    fixes: int = 0
    searches: int = 0
    lost_events: int = 0
    look_arounds: int = 0
    swept_rad: float = 0.0
    looking_around: bool = False  # the sweep under way is the first look around, not a search
    look_pending: bool = True  # no look around yet, nor a run-time goal (after one the robot holds where sent)
    goal: tuple[float, float] | None = None
    goal_tolerance_m: float = 0.1
    waypoint_index: int = 0
    direction: int = 1
    done: bool = False
    _last_yaw: float | None = field(default=None, repr=False)
    _fix_yaw: float | None = field(default=None, repr=False)  # odometry heading at the last fix
    _fixes_at_sweep: int = field(default=0, repr=False)  # fixes before the sweep under way began
    _neighbours: tuple[Neighbour, ...] = field(default=(), repr=False)
    _pos_sigma: float | None = field(default=None, repr=False)  # the fused position's sigma this cycle (m)
    loose_cycles: int = 0  # cycles with only a loose pose (placed by the server, not vouched for)
    on_loose: bool = False  # the last cycle drove on a loose pose
    avoider: Avoider = field(init=False, repr=False)
    route: Route | None = field(default=None, repr=False)  # a way through the room (agents.route)
    _no_way: tuple[tuple[float, float], float] | None = field(default=None, repr=False)  # (goal, until t_s)
    gate_waits: int = 0  # times it stopped outside a narrow passage for a robot coming through (agents.gates)
    _gate_since: float | None = field(default=None, repr=False)  # when the current wait began (t_s)
    _goal: tuple[float, float] | None = field(default=None, repr=False)  # the target the route leads to
    make_way: MakeWay = field(init=False, repr=False)  # a station keeper steps aside (agents.makeway)

    def __post_init__(self) -> None:
        self.avoider = Avoider(footprint_radius(self.robot), self.cfg.avoid_clearance_m, self.cfg.avoid_horizon_s,
                               self.robot_id, self.cfg.avoid_stall_s, sigma_k=self.cfg.avoid_sigma_k,
                               replan=self._replan)
        foot = footprint_radius(self.robot)
        # a spot keeps the route's margin from walls; the blocked robot passes it with two footprints and that margin
        self.make_way = MakeWay(self.robot_id, self._keep_m, foot + self.cfg.avoid_clearance_m, self._keep_m + foot)

    @property
    def _keep_m(self) -> float:
        """How far a planned way keeps the robot's centre from everything (m): the avoidance must pass it."""
        return footprint_radius(self.robot) + self.cfg.avoid_clearance_m + KEEP_MARGIN_M

    @cached_property
    def _room(self) -> Grid | None:
        """The walls and obstacles as a grid for :func:`tagswarm.agents.route.plan`, built at the first
        stall (None: the room has none)."""
        return static_grid(self.static_obstacles, self._keep_m)

    def _replan(self, pose: Pose2, target: tuple[float, float], neighbours: Sequence[Neighbour],
                _boxes: Sequence[Box]) -> bool:
        """The avoidance stalled: look for a way round the room to the target (see :mod:`tagswarm.agents.route`);
        the room is this behaviour's ``static_obstacles``, the boxes the avoidance is given."""
        goal = self._goal or target
        grid = self._room
        points = None if grid is None else plan(grid, (pose[0], pose[1]), goal, neighbours, self._keep_m)
        keep = footprint_radius(self.robot) + self.cfg.avoid_clearance_m
        self.route = None if points is None or len(points) < 2 else Route(
            goal, points, around_robots=True, clear_of=tuple((nb.x_m, nb.y_m, nb.radius_m + keep) for nb in neighbours))
        return self.route is not None

    @cached_property
    def _gates(self) -> tuple[Gate, ...]:
        """The room's passages too narrow for two robots to pass in (:mod:`tagswarm.agents.gates`)."""
        return gates(self.static_obstacles, footprint_radius(self.robot), self.cfg.avoid_clearance_m)

    def _gate_wait(self, pose: Pose2, aim: tuple[float, float], target: tuple[float, float], t_s: float) -> bool:
        """Whether to stand outside a narrow passage this cycle, on the way to ``aim`` (``target``'s carrot),
        while another robot comes through (at most ``GATE_MAX_WAIT_S`` in a row)."""
        reach = math.dist(pose[:2], target)
        if not self._gates or must_wait(self._gates, pose, aim, self.robot_id, self._neighbours,
                                        footprint_radius(self.robot), reach) is None:
            self._gate_since = None
            return False
        if self._gate_since is None:
            self._gate_since = t_s
            self.gate_waits += 1
        return t_s - self._gate_since < GATE_MAX_WAIT_S

    def _route_through_room(self, pose: Pose2, target: tuple[float, float], t_s: float) -> None:
        """A way through the room's walls and obstacles (not the robots: the avoidance passes them) when
        the straight way to ``target`` runs into one; planned once per target, again after ``ROUTE_RETRY_S``
        if the room offered none (the avoidance alone steers meanwhile)."""
        if (self.route is not None and self.route.goal == target) or (
                self._no_way is not None and self._no_way[0] == target and t_s < self._no_way[1]):
            return
        grid = self._room
        start = (pose[0], pose[1])
        need = footprint_radius(self.robot) + self.cfg.avoid_clearance_m
        if grid is None or not blocked(self.static_obstacles, start, target, need):
            return
        points = plan(grid, start, target, (), self._keep_m)
        self.route = None if points is None or len(points) < 2 else Route(target, points)
        self._no_way = (target, t_s + ROUTE_RETRY_S) if self.route is None else None

    def set_goal(self, x_m: float, y_m: float, tolerance_m: float) -> None:
        """A run-time goal (map frame) replaces the mission until reached."""
        self.goal, self.goal_tolerance_m, self.done = (x_m, y_m), tolerance_m, False
        self.look_pending = False
        self.make_way.cancel()

    def _waypoints(self) -> list[tuple[float, float]]:
        return [compose(self.arena_to_map, (x, y, 0.0))[:2] for x, y in self.mission.waypoints]

    def _my_turn(self, t_s: float) -> bool:
        if self.mission.kind != "leapfrog" or not self.leapfrog_team:
            return True
        turn = int(t_s // self.mission.leapfrog_period_s) % len(self.leapfrog_team)
        return self.leapfrog_team[turn] == self.robot_id

    def _slack(self, goal: tuple[float, float]) -> float:
        """Extra tolerance for a goal that cannot be reached with the clearance kept."""
        if not self.cfg.avoid:
            return 0.0
        return self.avoider.goal_slack(goal, self._neighbours, self.static_obstacles)

    def target(self, pose: Pose2, t_s: float) -> tuple[float, float] | None:
        """Where to go now (map frame), None to stand still; a hook for subclasses
        (:class:`tagswarm.agents.controller.BehaviourController`).  The built-in one follows
        the run-time goal, else the mission's waypoints."""
        return self._target(pose, t_s)

    def steer(self, pose: Pose2, target: tuple[float, float], speed_factor: float) -> tuple[float, float]:
        """The twist (v_m_s, w_rad_s) towards ``target`` from ``pose`` (map frame) before collision
        avoidance; a hook for subclasses.  The built-in one is :func:`go_to`."""
        return go_to(pose, target, self.cfg, speed_factor)

    def _target(self, pose: Pose2, t_s: float) -> tuple[float, float] | None:
        """Current goal (map frame) or None to stand still; advances waypoints."""
        if self.goal is not None:
            if math.dist(pose[:2], self.goal) < self.goal_tolerance_m + self._slack(self.goal):
                self.goal = None
                self.done = True
                return None
            return self.goal
        if self.mission.kind == "hold" or self.done or not self._my_turn(t_s):
            return None
        wps = self._waypoints()
        target = wps[self.waypoint_index]
        if math.dist(pose[:2], target) < self.cfg.goal_tolerance_m + self._slack(target):
            nxt = self.waypoint_index + self.direction
            if self.mission.kind == "patrol":
                if not 0 <= nxt < len(wps):
                    self.direction = -self.direction
                    nxt = self.waypoint_index + self.direction
                self.waypoint_index = max(0, min(len(wps) - 1, nxt))
            elif nxt >= len(wps):
                if self.mission.loop or self.mission.kind == "leapfrog":
                    self.waypoint_index = 0
                else:
                    self.done = True
                    return None
            else:
                self.waypoint_index = nxt
            if self.mission.kind == "leapfrog":
                return None  # one leg per turn
            target = wps[self.waypoint_index]
        return target

    def _turn_on(self, odom_yaw: float) -> float | None:
        """After a station keeper's whole turn: the yaw rate (rad/s) that carries it on, the same way, to
        its next fix or at most to the heading of its last fix during the turn; None once there (or
        without a fix during the turn).  Ending the turn at a fix leaves no net rotation since it, so a
        wheel-base error, which scales every turn, adds nothing to the heading it holds: after a whole
        turn it had up to 2 % of the part after its last sighting (static Fig. 5 trials, heading p95
        4.4 deg).  It turns on rather than back: reversing a turn made the wheels slip (3 % of the way
        back in the same trials), and what it last saw is usually seen again on the way."""
        if self._fix_yaw is None or self.fixes == self._fixes_at_sweep:
            return None
        left = (self._fix_yaw - odom_yaw) % math.tau
        if left < TURN_ON_TOL_RAD or left > math.tau - TURN_ON_PASSED_RAD:
            return None  # there, or it passed the heading a moment ago (the sweep overshoots a little)
        return min(self.cfg.search_speed_rad_s, TURN_ON_GAIN * left)

    def cycle(self, *, t_s: float, map_pose: Pose2 | None, odom_yaw: float, moved: bool,
              fix: bool, server_up: bool = True, neighbours: Sequence[Neighbour] = (),
              pos_sigma_m: float | None = None, loose_pose: Pose2 | None = None,
              vouched: bool = True) -> tuple[float, float]:
        """One control step.  ``map_pose`` is the corrected pose (None if never
        localised), ``odom_yaw`` the smooth odometry heading (to measure the sweep),
        ``moved`` whether the encoders moved since the last cycle, ``fix`` whether
        a visual fix arrived, ``server_up`` whether a map server is reachable (see
        the module docstring), ``neighbours`` the other robots now (map frame),
        ``pos_sigma_m`` the fused position's σ in metres (None if unknown; used
        by ``agent.search_sigma_m``), ``loose_pose`` the map's estimate of a robot the server has
        placed but does not vouch for (None otherwise; see the module docstring), ``vouched`` False
        when ``map_pose`` is the map's estimate of a robot the server no longer vouches for (driven on
        slowly, as a loose pose).  Returns (v_m_s, w_rad_s)."""
        self.on_loose = map_pose is not None and not vouched
        if map_pose is None and loose_pose is not None:
            self.loose_cycles += 1
            if self.loose_cycles > self.cfg.fix_threshold:
                map_pose, self.on_loose = loose_pose, True
        self._neighbours = tuple(neighbours)
        self._pos_sigma = pos_sigma_m
        if self.mission.kind == "hold":
            self.make_way.watch(t_s, self._neighbours)
        swept = 0.0 if self._last_yaw is None else abs(wrap_angle(odom_yaw - self._last_yaw))
        self._last_yaw = odom_yaw
        stationary = self.mission.kind == "hold" and self.goal is None
        if fix:
            self.fixes += 1
            self._fix_yaw = odom_yaw
            self.counter = self.since_fix = 0
            if not (stationary and self.mode == Mode.SEARCHING):  # a station keeper finishes its turn
                self.mode = Mode.VISUAL
                self.looking_around = False
        else:
            self.since_fix += 1
            if moved or map_pose is None:
                self.counter += 1
        if self.mode == Mode.VISUAL and self.since_fix > self.visual_hold:
            self.mode = Mode.ODOMETRY
        if not server_up and self.mode in (Mode.SEARCHING, Mode.LOST):
            self.mode = Mode.ODOMETRY  # nobody can turn a sighting into a fix: stop looking
        uncertain = (self.cfg.search_sigma_m > 0 and pos_sigma_m is not None and moved
                     and pos_sigma_m > self.cfg.search_sigma_m and self.since_fix > 2 * self.visual_hold)
        needs_search = server_up and (map_pose is None or self.counter > self.cfg.fix_threshold or uncertain)
        # a robot holding station turns on the spot to look around only if it is still not placed after three
        # times fix_threshold cycles (nobody saw it, it saw nobody): turning keeps the station, and standing
        # still would leave it out of the map for good (measured: robot 5 of the warehouse scene, 40 s).  The
        # wait lets far chains place it first (the corridor's robot 4 at 7.7 s)
        never_placed = map_pose is None and self.counter > 3 * self.cfg.fix_threshold
        look_around = stationary and server_up and self.cfg.look_around and not self.anchor and self.look_pending
        if self.mode in (Mode.ODOMETRY, Mode.VISUAL) and (look_around or (
                needs_search and (never_placed or not stationary))):
            self.mode = Mode.SEARCHING
            self.looking_around = look_around
            self.look_pending = self.look_pending and not look_around
            self.look_arounds += look_around
            self.searches += not look_around
            self.swept_rad = 0.0
            self._fixes_at_sweep = self.fixes
        if self.mode == Mode.SEARCHING:
            self.swept_rad += swept
            if self.swept_rad < self.cfg.search_max_sweep_rad:
                return 0.0, self.cfg.search_speed_rad_s
            if self.looking_around or (stationary and map_pose is not None):
                on = self._turn_on(odom_yaw)
                if on is not None:
                    return 0.0, on
                # the whole turn, ended at a fix (or at its own heading without one): hold station again (one not
                # placed by now may still search)
                self.mode = Mode.ODOMETRY
            else:
                self.mode = Mode.LOST
                self.lost_events += 1
            self.looking_around = False
        if map_pose is None:
            return 0.0, 0.0
        target = self.target(map_pose, t_s)
        keeper = stationary and self.cfg.make_way and self.cfg.avoid and not (self.anchor or self.on_loose)
        if target is None and keeper:
            aside = self.make_way.target(t_s, map_pose, self._neighbours, self.static_obstacles)
            if isinstance(aside, float):  # back on its station: its heading again
                return 0.0, max(-self.cfg.max_turn_rad_s, min(self.cfg.max_turn_rad_s,
                                                              2.0 * wrap_angle(aside - map_pose[2])))
            target = aside
        if target is None:
            return 0.0, 0.0
        factor = self.cfg.lost_speed_factor if self.mode == Mode.LOST or self.on_loose else 1.0
        if not self.cfg.avoid:
            return self.steer(map_pose, target, factor)
        self._goal, aim = target, target
        self._route_through_room(map_pose, target, t_s)
        if self.route is not None:  # a way through the room: its carrot, until the goal itself is near
            carrot = self.route.carrot(map_pose[0], map_pose[1]) if self.route.goal == target else None
            self.route = None if carrot is None else self.route
            aim = carrot or target

        if self._gate_wait(map_pose, aim, target, t_s):
            return 0.0, 0.0

        def steer(p: Pose2) -> tuple[float, float]:
            return self.steer(p, aim, factor)

        return self.avoider.command(pose=map_pose, target=aim, steer=steer, v_max=self.cfg.max_speed_m_s * factor,
                                    w_max=self.cfg.max_turn_rad_s * factor, neighbours=self._neighbours,
                                    boxes=self.static_obstacles, t_s=t_s, pos_sigma_m=self._pos_sigma,
                                    round_boxes=aim == target,
                                    round_robots=aim == target or not (self.route and self.route.around_robots))
