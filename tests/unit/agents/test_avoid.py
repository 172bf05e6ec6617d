"""Collision avoidance (agents/avoid.py, agents/neighbours.py) in a small kinematic
simulation of several Behaviours: each robot sees the others only through a global
map published at the server's default 2 Hz, as the agents do."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import pytest

from tagswarm.agents import avoid
from tagswarm.agents.avoid import Avoider, Box, Neighbour, box_distance, static_boxes
from tagswarm.agents.behaviour import Behaviour, wheel_speeds
from tagswarm.agents.makeway import aside_spot
from tagswarm.agents.neighbours import NeighbourTracker
from tagswarm.protocol import messages as m
from tagswarm.protocol.geometry import Pose2, se2_compose
from tagswarm.protocol.layout import arena_to_map, footprint_radius, start_poses
from tagswarm.protocol.scenario import Agent, Mission, Robot, load_scenario

ROBOT = Robot()
FOOT = footprint_radius(ROBOT)
CFG = Agent(look_around=False)  # station keepers stand still here (their first turn: test_behaviour.py)
CLEAR = 2 * FOOT + CFG.avoid_clearance_m  # centre distance the avoidance keeps between two robots
DT = 1 / 30
MAP_PERIOD_S = 0.5


def hold(rid: int) -> Mission:
    return Mission(robot=rid, kind="hold")


class World:
    """Unicycle robots driven by their Behaviours; others known from a 2 Hz map (or exactly)."""

    def __init__(self, robots: dict[int, tuple[Pose2, Mission, tuple[float, float] | None]],
                 boxes: tuple[Box, ...] = (), cfg: Agent = CFG, exact: bool = False,
                 arena_to_map: Pose2 = (0.0, 0.0, 0.0), goal_tolerance_m: float = 0.1,
                 unmapped: tuple[int, ...] = (), sight_m: float = 0.0) -> None:
        self.unmapped, self.sight_m = unmapped, sight_m  # robots the map leaves out; camera range (0: none)
        self.beh: dict[int, Behaviour] = {}
        self.pose: dict[int, Pose2] = {}
        self.trackers = {rid: NeighbourTracker(rid, FOOT, 0.5) for rid in robots}
        for rid, (pose, mission, goal) in robots.items():
            b = Behaviour(rid, mission, cfg, ROBOT, arena_to_map, static_obstacles=boxes)
            if goal is not None:
                b.set_goal(goal[0], goal[1], goal_tolerance_m)
            self.beh[rid], self.pose[rid] = b, pose
        self.exact, self.t, self.next_map = exact, 0.0, 0.0
        self.min_dist = math.inf
        self.paths: dict[int, list[Pose2]] = {rid: [] for rid in robots}
        self.velocity = {rid: (0.0, 0.0) for rid in robots}

    def _neighbours(self, rid: int) -> tuple[Neighbour, ...]:
        if self.exact:
            return tuple(Neighbour(o, p[0], p[1], *self.velocity[o], FOOT)
                         for o, p in sorted(self.pose.items()) if o != rid)
        return self.trackers[rid].neighbours(round(self.t * 1e9))

    def run(self, seconds: float) -> World:
        for _ in range(round(seconds / DT)):
            if self.t >= self.next_map - 1e-9:
                cov = (1e-4, 0.0, 0.0, 0.0, 1e-4, 0.0, 0.0, 0.0, 1e-4)
                entries = [m.MapEntry(robot_id=r, x_m=p[0], y_m=p[1], yaw_rad=p[2], cov=cov, last_seen_ns=0, alive=True)
                           for r, p in sorted(self.pose.items()) if r not in self.unmapped]
                for tracker in self.trackers.values():
                    tracker.offer(round(self.t * 1e9), entries)
                self.next_map += MAP_PERIOD_S
            for rid, tracker in self.trackers.items():  # a 60 deg camera ahead sees the others in range
                me = self.pose[rid]
                for o, p in self.pose.items():
                    bearing = math.remainder(math.atan2(p[1] - me[1], p[0] - me[0]) - me[2], math.tau)
                    if o != rid and math.dist(me[:2], p[:2]) < self.sight_m and abs(bearing) < math.radians(30):
                        tracker.saw(o, p[0], p[1], round(self.t * 1e9))
            cmds = {rid: b.cycle(t_s=self.t, map_pose=self.pose[rid], odom_yaw=self.pose[rid][2], moved=True, fix=True,
                                 neighbours=self._neighbours(rid)) for rid, b in self.beh.items()}
            for rid, (v, w) in cmds.items():
                left, right = wheel_speeds(v, w, ROBOT)
                v = ROBOT.wheel_radius_m * (left + right) / 2
                w = ROBOT.wheel_radius_m * (right - left) / ROBOT.wheel_base_m
                before = self.pose[rid]
                self.pose[rid] = se2_compose(before, (v * DT, 0.0, w * DT))
                self.velocity[rid] = ((self.pose[rid][0] - before[0]) / DT, (self.pose[rid][1] - before[1]) / DT)
                self.paths[rid].append(self.pose[rid])
            for a, b in itertools.combinations(sorted(self.pose), 2):
                self.min_dist = min(self.min_dist, math.dist(self.pose[a][:2], self.pose[b][:2]))
            self.t += DT
        return self


@pytest.mark.parametrize("exact", [True, False])
def test_head_on_pair_both_get_through_keeping_the_clearance(exact: bool) -> None:
    w = World({1: ((0.0, 0.0, 0.0), hold(1), (4.0, 0.0)), 2: ((4.0, 0.0, math.pi), hold(2), (0.0, 0.0))},
              exact=exact).run(30.0)
    assert w.beh[1].done and w.beh[2].done, w.pose
    assert math.dist(w.pose[1][:2], (4.0, 0.0)) < 0.11 and math.dist(w.pose[2][:2], (0.0, 0.0)) < 0.11
    # with exact knowledge nobody comes inside the clearance; through a 2 Hz map, never near contact
    assert w.min_dist >= (CLEAR - 1e-3 if exact else 2 * FOOT + 0.05), w.min_dist
    # both passed on their right: robot 1 (eastbound) swerved south, robot 2 (westbound) north
    assert min(p[1] for p in w.paths[1]) < -0.15 and max(p[1] for p in w.paths[2]) > 0.15
    assert w.beh[1].avoider.yields == w.beh[2].avoider.yields == 0


def test_without_avoidance_the_same_pair_collides() -> None:
    off = Agent(avoid=False)
    w = World({1: ((0.0, 0.0, 0.0), hold(1), (4.0, 0.0)), 2: ((4.0, 0.0, math.pi), hold(2), (0.0, 0.0))},
              cfg=off).run(30.0)
    assert w.min_dist < 0.05  # a kinematic world lets them drive through each other


def test_patrol_goes_around_a_robot_holding_station_on_its_line() -> None:
    patrol = Mission(robot=1, kind="patrol", waypoints=((0.0, 0.0), (3.0, 0.0)))
    w = World({0: ((1.5, 0.0, 0.3), hold(0), None), 1: ((0.0, 0.0, 0.0), patrol, None)}).run(40.0)
    assert w.pose[0] == pytest.approx((1.5, 0.0, 0.3))  # the holding robot never moved
    xs = [p[0] for p in w.paths[1]]
    # it reached the far end and came back past the holder at least once each way
    reached_far = next(i for i, x in enumerate(xs) if x > 2.85)
    assert min(xs[reached_far:]) < 0.5
    assert w.min_dist >= CLEAR - 0.02, w.min_dist
    passing = [abs(p[1]) for p in w.paths[1] if abs(p[0] - 1.5) < 0.1]
    assert passing and min(passing) >= CLEAR - 0.02  # it went round, not through


def test_a_robot_the_map_does_not_have_yet_is_avoided_once_seen() -> None:
    """A holding robot nobody has placed is not in the map: a patrol through it drives into it unless
    the patroller's own sightings make it an obstacle (then it goes round with the clearance)."""
    patrol = Mission(robot=1, kind="patrol", waypoints=((0.0, 0.0), (3.0, 0.0)))
    robots = {0: ((1.5, 0.0, 0.3), hold(0), None), 1: ((0.0, 0.0, 0.0), patrol, None)}
    blind = World(robots, unmapped=(0,)).run(20.0)
    assert blind.min_dist < 0.05  # the kinematic world lets it drive through
    seeing = World(robots, unmapped=(0,), sight_m=2.0).run(40.0)
    assert max(p[0] for p in seeing.paths[1]) > 2.85  # it still got past
    assert seeing.min_dist >= CLEAR - 0.02, seeing.min_dist


def test_a_sighting_is_an_obstacle_only_while_fresh_and_while_the_map_lacks_the_robot() -> None:
    t = NeighbourTracker(1, FOOT, 0.5)
    t.saw(3, 1.0, 0.5, 0)
    t.saw(1, 9.0, 9.0, 0)  # itself: never
    (n,) = t.neighbours(1_000_000_000)
    assert (n.robot_id, n.x_m, n.y_m, n.vx_m_s, n.radius_m) == (3, 1.0, 0.5, 0.0, FOOT)
    assert t.neighbours(3_500_000_000) == ()  # 3.5 s after: forgotten
    t.saw(3, 1.0, 0.5, 4_000_000_000)
    t.offer(4_000_000_000, [m.MapEntry(robot_id=3, x_m=2.0, y_m=0.0, yaw_rad=0.0, cov=(0.0,) * 9, last_seen_ns=0,
                                       alive=True)])
    (n,) = t.neighbours(4_100_000_000)
    assert (n.x_m, n.y_m) == (2.0, 0.0)  # the map's, once it has the robot


def test_waypoint_on_a_holding_robot_counts_as_reached_at_the_clearance() -> None:
    # the grid case: robot 4 holds exactly on robot 3's patrol waypoint
    patrol = Mission(robot=3, kind="patrol", waypoints=((0.0, 0.0), (1.2, 0.0)))
    w = World({4: ((0.0, 0.0, 1.0), hold(4), None), 3: ((-1.9, 0.0, 0.0), patrol, None)}).run(40.0)
    assert w.pose[4] == pytest.approx((0.0, 0.0, 1.0))
    assert max(p[0] for p in w.paths[3]) > 1.1  # got past the holder to the other waypoint
    assert w.min_dist >= CLEAR - 0.02, w.min_dist


@pytest.mark.parametrize("goal_x", [1.68, 1.72])
def test_goal_beside_a_wall_is_reached(goal_x: float) -> None:
    wall = Box(2.0, 0.0, 0.0, 0.05, 2.0)  # inner face at x = 1.95
    assert FOOT < 1.95 - goal_x < FOOT + CFG.avoid_clearance_m  # closer to the wall than the clearance
    w = World({1: ((0.0, 0.3, 0.5), hold(1), (goal_x, 0.0))}, boxes=(wall,), goal_tolerance_m=0.03).run(20.0)
    assert w.beh[1].done and math.dist(w.pose[1][:2], (goal_x, 0.0)) < 0.03 + 1e-6
    assert min(float(box_distance(wall, p[0], p[1])) for p in w.paths[1]) > FOOT  # never touched it


def test_goal_behind_a_shelf_is_reached_around_it() -> None:
    shelf = Box(1.5, 0.0, 0.0, 0.3, 0.8)
    w = World({1: ((0.0, 0.0, 0.0), hold(1), (3.0, 0.0))}, boxes=(shelf,)).run(40.0)
    assert w.beh[1].done
    assert min(float(box_distance(shelf, p[0], p[1])) for p in w.paths[1]) >= FOOT + 0.05


def test_nothing_changes_when_nobody_is_near() -> None:
    # the paper's layout: patrols 0.9 m apart in parallel lines, the origin holding 1.5 m away
    def layout(cfg: Agent) -> World:
        def patrol(rid: int, a: tuple[float, float], b: tuple[float, float]) -> Mission:
            return Mission(robot=rid, kind="patrol", waypoints=(a, b))

        return World({0: ((-1.5, 0.0, 0.0), hold(0), None),
                      1: ((0.0, 0.9, 0.0), patrol(1, (0.0, 0.9), (2.0, 0.9)), None),
                      2: ((2.0, 0.0, math.pi), patrol(2, (2.0, 0.0), (0.0, 0.0)), None),
                      3: ((0.0, -0.9, 0.0), patrol(3, (0.0, -0.9), (2.0, -0.9)), None)}, cfg=cfg).run(30.0)

    on, off = layout(CFG), layout(Agent(avoid=False, look_around=False))
    assert on.paths == off.paths
    assert all(b.avoider.cycles_avoiding == 0 for b in on.beh.values())


def test_searching_rotation_is_never_stopped() -> None:
    b = Behaviour(1, Mission(robot=1, kind="waypoints", waypoints=((3.0, 0.0),)), Agent(fix_threshold=5), ROBOT)
    crowd = tuple(Neighbour(i, 0.45 * math.cos(a), 0.45 * math.sin(a), 0.0, 0.0, FOOT)
                  for i, a in enumerate((0.0, 1.6, 3.2, 4.8), start=2))
    b.cycle(t_s=0.0, map_pose=(0.0, 0.0, 0.0), odom_yaw=0.0, moved=True, fix=True, neighbours=crowd)
    for k in range(1, 30):
        v, w = b.cycle(t_s=k * 0.1, map_pose=(0.0, 0.0, 0.0), odom_yaw=0.0, moved=True, fix=False, neighbours=crowd)
    assert b.mode == "searching" and (v, w) == (0.0, CFG.search_speed_rad_s)


def test_hemmed_in_robot_turns_in_place_but_never_drives_closer() -> None:
    a = Avoider(FOOT, CFG.avoid_clearance_m)
    pose = (0.0, 0.0, 0.0)
    ahead = (Neighbour(2, CLEAR - 0.05, 0.0, 0.0, 0.0, FOOT),)  # already inside the clearance, dead ahead

    def steer(p: Pose2) -> tuple[float, float]:
        return 0.3, 0.0

    v, _ = a.command(pose=pose, target=(3.0, 0.0), steer=steer, v_max=0.3, w_max=1.2, neighbours=ahead, boxes=(),
                     t_s=0.0)
    assert a.avoiding and v <= 1e-9  # no forward motion into it; turning on the spot is allowed


def test_a_robot_unsure_where_it_is_keeps_its_sigma_s_multiple_farther_from_a_shelf() -> None:
    # driving at 0.3 m/s, 0.1 rad towards a shelf on its left: over the 2 s horizon it comes 6 cm nearer, and its
    # face is 12 cm beyond what the clearance needs (6 cm to spare)
    need = FOOT + CFG.avoid_clearance_m

    def shelf(beyond_m: float) -> tuple[Box, ...]:
        return (Box(1.0, need + beyond_m + 0.3, 0.0, 1.5, 0.3),)

    def steer(p: Pose2) -> tuple[float, float]:
        return 0.3, 0.0

    def drive(sigma: float | None, k: float = CFG.avoid_sigma_k, beyond_m: float = 0.12) -> tuple[Avoider, float]:
        a = Avoider(FOOT, CFG.avoid_clearance_m, sigma_k=k)
        _, w = a.command(pose=(0.0, 0.0, 0.1), target=(3.0, 0.3), steer=steer, v_max=0.3, w_max=1.2, neighbours=(),
                         boxes=shelf(beyond_m), t_s=0.0, pos_sigma_m=sigma)
        return a, w

    for sigma in (None, 0.0, 0.02, math.nan):  # sure of itself (2 sigma under the 6 cm to spare), or no sigma
        a, w = drive(sigma)
        assert not a.avoiding and w == 0.0, sigma
    a, w = drive(0.05)  # 2 sigma = 10 cm: the shelf would come 4 cm too near, it turns away (right)
    assert a.avoiding and w < 0.0
    assert not drive(0.05, k=0.0)[0].avoiding  # the margin switched off
    # a robot lost by metres keeps at most 20 cm more: a shelf 29 cm beyond (23 after the 6 cm) leaves it be
    assert not drive(5.0, beyond_m=0.29)[0].avoiding
    assert drive(0.5 * avoid.MAX_SIGMA_MARGIN_M + 0.05, beyond_m=0.23)[0].avoiding


def test_the_margin_gives_way_where_it_leaves_no_way_forward_and_the_clearance_still_holds() -> None:
    """The depot's robot 6 reaches its patrol waypoint 0.4 m from the north wall with a 6 cm sigma and
    must turn back along the wall: every way to the next waypoint bulges nearer the wall than the 12 cm
    margin allows.  It drops the margin for those cycles and goes on (it stood 22 s there when the
    margin was a hard bound) without ever coming within the clearance."""
    s = load_scenario("depot")
    mission = next(mi for mi in s.missions if mi.robot == 6)
    t = arena_to_map(s)
    boxes = static_boxes(s)
    for sigma in (0.06, 0.15):
        b = Behaviour(6, mission, s.agent, s.robot, t, static_obstacles=boxes)
        pose = se2_compose(t, (2.07, 1.21, 1.2))
        nearest = math.inf
        for k in range(30 * 20):
            v, w = b.cycle(t_s=k / 30, map_pose=pose, odom_yaw=pose[2], moved=True, fix=True, pos_sigma_m=sigma)
            pose = (pose[0] + v * math.cos(pose[2]) / 30, pose[1] + v * math.sin(pose[2]) / 30, pose[2] + w / 30)
            nearest = min(nearest, min(float(box_distance(bx, pose[0], pose[1])) for bx in boxes))
        assert b.waypoint_index == 1
        start = se2_compose(t, (2.2, 1.6, 0.0))
        travelled = math.hypot(pose[0] - start[0], pose[1] - start[1])
        assert travelled > 2.0, (sigma, travelled)  # well on its way west along the wall
        assert nearest >= FOOT + s.agent.avoid_clearance_m - 0.01, nearest


def test_swap_on_a_circle_resolves_without_contact() -> None:
    robots: dict[int, tuple[Pose2, Mission, tuple[float, float] | None]] = {}
    for k in range(6):
        a = 2 * math.pi * k / 6
        c, s = math.cos(a), math.sin(a)
        robots[k] = ((1.5 * c, 1.5 * s, a + math.pi), hold(k), (-1.5 * c, -1.5 * s))
    w = World(robots).run(60.0)
    assert all(b.done for b in w.beh.values()), w.pose
    assert w.min_dist > 2 * FOOT + 0.05, w.min_dist


def test_tracker_extrapolates_and_uses_only_maps_it_may() -> None:
    t = NeighbourTracker(1, FOOT, 0.5)

    def entry(rid: int, x: float, alive: bool = True) -> m.MapEntry:
        return m.MapEntry(robot_id=rid, x_m=x, y_m=0.0, yaw_rad=0.0, cov=(0.0,) * 9, last_seen_ns=0, alive=alive)

    t.offer(0, [entry(1, 5.0), entry(2, 0.0), entry(3, 1.0)])
    t.offer(500_000_000, [entry(1, 5.0), entry(2, 0.1), entry(3, 1.0, alive=False)])
    assert [n.robot_id for n in t.neighbours(400_000_000, usable_until_ns=400_000_000)] == [2, 3]
    assert t.adopted_ns == 0  # the newer map is not usable yet
    nbs = t.neighbours(1_000_000_000)
    assert t.adopted_ns == 500_000_000
    two = nbs[0]
    assert two.vx_m_s == pytest.approx(0.2) and two.x_m == pytest.approx(0.2)  # 0.1 + 0.2 m/s * 0.5 s
    assert two.radius_m > FOOT  # widened by the extrapolation
    three = nbs[1]
    assert (three.vx_m_s, three.x_m, three.radius_m) == (0.0, 1.0, FOOT)  # gone agent: an obstacle at rest
    t.offer(200_000_000, [entry(2, 9.0)])  # older than the one in use
    assert t.neighbours(1_000_000_000)[0].x_m == pytest.approx(0.2)


def test_a_map_entry_older_than_its_map_is_extrapolated_from_its_own_time() -> None:
    """Robot 2 drives at 0.2 m/s; in the second map its pose is 0.4 s older than the map (its odometry
    reached the server late): its speed and where it is now come from the pose's time, not the map's."""
    t = NeighbourTracker(1, FOOT, 0.5)

    def entry(x: float, pose_ns: int) -> m.MapEntry:
        return m.MapEntry(robot_id=2, x_m=x, y_m=0.0, yaw_rad=0.0, cov=(0.0,) * 9, last_seen_ns=0, alive=True,
                          pose_stamp_ns=pose_ns)

    t.offer(1_000_000_000, [entry(0.2, 0)])  # 0: at the map's stamp
    t.offer(2_000_000_000, [entry(0.32, 1_600_000_000)])
    two = t.neighbours(2_000_000_000)[0]
    assert two.vx_m_s == pytest.approx(0.2)  # 0.12 m in 0.6 s (read at the map's 1 s: 0.12 m/s)
    assert two.x_m == pytest.approx(0.4)  # 0.32 + 0.2 m/s * 0.4 s


def test_a_sighting_far_from_where_the_map_has_the_robot_is_contradicted() -> None:
    """The agent's own check before it counts a sighting as a fix: a copy of robot 2's cube 3 m from
    where the map has robot 2 is contradicted; a sighting within its circle and the gate is not, nor
    is one of a robot the map does not have yet (only the server can judge it), nor one made before
    the map was adopted."""
    from tagswarm.agents.neighbours import SIGHTING_GATE_M

    t = NeighbourTracker(1, FOOT, 0.5)
    assert not t.contradicts(2, 9.0, 9.0, 0)  # no map yet
    cov = (0.01**2, 0.0, 0.0, 0.0, 0.01**2, 0.0, 0.0, 0.0, 0.0)
    t.offer(0, [m.MapEntry(robot_id=2, x_m=1.0, y_m=0.0, yaw_rad=0.0, cov=cov, last_seen_ns=0, alive=True)])
    assert not t.contradicts(2, 9.0, 9.0, 0)  # offered, not adopted: the control cycle adopts maps
    t.neighbours(0)
    radius = t.where(2, 0).radius_m  # type: ignore[union-attr]
    assert not t.contradicts(2, 1.0 + radius + SIGHTING_GATE_M - 0.01, 0.0, 0)
    assert t.contradicts(2, 1.0 + radius + SIGHTING_GATE_M + 0.01, 0.0, 0)
    assert t.contradicts(2, 1.0, 3.0, 0)
    assert not t.contradicts(3, 9.0, 9.0, 0)  # not in the map
    # what the estimator is told, from map pose (1, -1, 90 deg): robot 2 is 1 m ahead; the reach grows
    # with both positions' sigma, uncapped
    x, y, reach = t.expected((1.0, -1.0, math.pi / 2), 0)[("robot", 2)]
    assert (x, y) == pytest.approx((1.0, 0.0)) and reach == pytest.approx(radius + SIGHTING_GATE_M + 0.03)
    assert t.expected((1.0, -1.0, math.pi / 2), 0, me_sigma_m=0.4)[("robot", 2)][2] > reach + 1.0


def test_static_boxes_are_the_walls_and_obstacles_in_the_map_frame() -> None:
    s = load_scenario("hall")
    boxes = static_boxes(s)
    assert len(boxes) == 4 + len(s.arena.obstacles)
    t = arena_to_map(s)
    # the origin robot's start is the map origin, and a shelf's centre is where the arena puts it
    shelf = s.arena.obstacles[0]
    cx, cy, _ = se2_compose(t, (shelf.x_m, shelf.y_m, 0.0))
    assert float(box_distance(boxes[4], cx, cy)) == pytest.approx(-min(shelf.size_x_m, shelf.size_y_m) / 2)
    origin = se2_compose(t, start_poses(s)[0])
    assert math.hypot(origin[0], origin[1]) < 1e-9


# the store floor (12 x 10 m, racks 3.0 x 0.7 m) at 18 s of its run, map frame: robot 12's diagonal patrol meets a
# rack's end with station keepers beside it and behind it
STORE_BOXES = tuple(Box(*b) for b in (
    (-8.76, 6.681, 2.479, 0.05, 5.05), (0.702, -0.7, 2.479, 0.05, 5.05), (-7.105, -0.952, 2.479, 6.05, 0.05),
    (-0.953, 6.933, 2.479, 6.05, 0.05), (-2.894, -0.432, 2.479, 1.5, 0.35), (-7.625, 3.259, 2.479, 1.5, 0.35),
    (-0.433, 2.722, 2.479, 1.5, 0.35), (-5.164, 6.413, 2.479, 1.5, 0.35)))
STORE_HOLDERS = {0: (0.0, 0.0), 2: (1.54, 3.81), 4: (-3.02, 1.04), 5: (-1.24, 4.24), 8: (-1.21, 5.62),
                 11: (-1.01, -0.92), 13: (-2.15, 5.74)}


@pytest.mark.parametrize("gives_up", [True, False])
def test_a_patrol_at_a_racks_end_stops_waiting_for_station_keepers_and_goes_round(
        gives_up: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    if not gives_up:
        monkeypatch.setattr(avoid, "MAX_YIELDS", 1000)
    robots: dict[int, tuple[Pose2, Mission, tuple[float, float] | None]] = {
        rid: ((x, y, 0.0), hold(rid), None) for rid, (x, y) in STORE_HOLDERS.items()}
    goal = (2.37, 3.07)
    robots[12] = ((-1.98, 3.97, -0.32), hold(12), goal)
    w = World(robots, boxes=STORE_BOXES, exact=True).run(60.0)
    a = w.beh[12].avoider
    if gives_up:
        # it gave way twice to a robot that never moves, then looked for a way round the rack and took it
        assert w.beh[12].done and a.yields == avoid.MAX_YIELDS and a.reroutes >= 1
        assert math.dist(w.pose[12][:2], goal) < 0.15
    else:
        assert not w.beh[12].done and a.yields >= 4 and a.reroutes == 0
    assert min(float(box_distance(b, p[0], p[1])) for b in STORE_BOXES for p in w.paths[12]) > FOOT
    assert all(p[:2] == robots[rid][0][:2] for rid, p in w.pose.items() if rid != 12)  # they held station
    assert w.min_dist > 2 * FOOT


# a pocket open to the west, the goal east of its back wall, in a closed 8 x 8 m room
POCKET = (Box(1.0, 0.0, 0.0, 0.05, 1.0), Box(0.25, 1.0, 0.0, 0.75, 0.05), Box(0.25, -1.0, 0.0, 0.75, 0.05),
          Box(0.0, 4.0, 0.0, 4.0, 0.05), Box(0.0, -4.0, 0.0, 4.0, 0.05), Box(4.0, 0.0, 0.0, 0.05, 4.0),
          Box(-4.0, 0.0, 0.0, 0.05, 4.0))


def _no_room_route(b: Behaviour) -> None:
    b._route_through_room = lambda *_: None  # type: ignore[method-assign]


@pytest.mark.parametrize("variant", ["as_built", "after_a_stall", "avoidance_alone"])
def test_a_robot_in_a_pocket_finds_the_way_round(variant: str) -> None:
    """The back wall of the pocket stands on the straight way to the goal: the robot plans its way
    round the room at once; without that, once its avoidance stalls; the local avoidance alone never
    gets out (both sides of the back wall look the same)."""
    w = World({1: ((0.0, 0.0, 0.0), hold(1), (3.0, 0.0))}, boxes=POCKET, exact=True)
    b = w.beh[1]
    if variant != "as_built":
        _no_room_route(b)
    if variant == "avoidance_alone":
        b.avoider.replan = None
    w.run(60.0)
    assert min(float(box_distance(box, p[0], p[1])) for box in POCKET for p in w.paths[1]) > FOOT
    if variant == "avoidance_alone":
        assert not b.done and math.dist(w.pose[1][:2], (0.0, 0.0)) < 1.0
        return
    assert b.done and math.dist(w.pose[1][:2], (3.0, 0.0)) < 0.15
    assert b.avoider.reroutes == (0 if variant == "as_built" else 1)
    arrived = next(k for k, p in enumerate(w.paths[1]) if math.dist(p[:2], (3.0, 0.0)) < 0.15) * DT
    assert arrived < (25.0 if variant == "as_built" else 60.0), arrived


# an 8 x 8 m room split by a wall at x = 0 with two 1 m doors: a near one at y 0.5..1.5 and a far one at
# y -3.5..-2.5
DOORS = (Box(0.0, 2.75, 0.0, 0.05, 1.25), Box(0.0, -1.0, 0.0, 0.05, 1.5), Box(0.0, -3.75, 0.0, 0.05, 0.25),
         *POCKET[3:])


@pytest.mark.parametrize("variant", ["as_built", "never_gives_up"])
def test_a_robot_stops_giving_way_to_a_station_keeper_in_the_door_and_takes_the_other(
        variant: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Robot 0 holds station in the near door; robot 1 (a higher id, so it gives way) wants through.
    Backing away for robot 0 is waiting for ever: after MAX_YIELDS at one place robot 1 looks for a
    way round and takes the far door.  (Beside the door its go-to-goal turn and an avoiding turn
    back used to alternate every cycle, each clear cycle restarting the stall clock, hence
    ``CLEAR_RESET_S``; that turn back went for the wall's far corner, on the wrong side, and no
    longer happens here.)"""
    if variant == "never_gives_up":
        monkeypatch.setattr(avoid, "MAX_YIELDS", 1000)
    w = World({0: ((0.0, 1.0, 0.0), hold(0), None), 1: ((-2.0, 1.0, 0.0), hold(1), (2.0, 1.0))},
              boxes=DOORS, exact=True).run(90.0)
    b = w.beh[1]
    assert w.pose[0] == pytest.approx((0.0, 1.0, 0.0))
    assert min(float(box_distance(box, p[0], p[1])) for box in DOORS for p in w.paths[1]) > FOOT
    assert w.min_dist >= CLEAR - 0.02, w.min_dist
    if variant == "as_built":
        assert b.avoider.yields == avoid.MAX_YIELDS and b.avoider.reroutes >= 1
        assert b.done and math.dist(w.pose[1][:2], (2.0, 1.0)) < 0.15
        assert min(p[1] for p in w.paths[1]) < -2.5  # through the far door
    else:
        assert not b.done and b.avoider.yields >= 4 and b.avoider.reroutes == 0 and w.pose[1][0] < 0.0


# two rooms (10 x 6 m) joined by a 1 m door in the wall at x = 0, y -0.5 .. 0.5
TWO_ROOMS = (Box(0.0, 3.0, 0.0, 5.0, 0.05), Box(0.0, -3.0, 0.0, 5.0, 0.05), Box(5.0, 0.0, 0.0, 0.05, 3.0),
             Box(-5.0, 0.0, 0.0, 0.05, 3.0), Box(0.0, -1.75, 0.0, 0.1, 1.25), Box(0.0, 1.75, 0.0, 0.1, 1.25))


def _crossings_s(path: list[Pose2]) -> list[float]:
    """When (s) a robot went through the wall at x = 0."""
    return [k * DT for k, (a, b) in enumerate(itertools.pairwise(path)) if (a[0] > 0.0) != (b[0] > 0.0)]


@pytest.mark.parametrize("exact", [True, False])
@pytest.mark.parametrize("gates", [True, False])
def test_two_patrols_cross_a_door_in_turn(gates: bool, exact: bool) -> None:
    """Two patrols swap rooms through the door, in opposite directions.  Robot 3 waits outside while
    robot 2 comes through (agents/gates.py): both are through by 16.3 s.  Without that they met in the
    door and stood face to face until one stalled and backed away (in a lockstep run of this room from
    8 to 20 s); here the first of them got through at 24.5 s, or 46.1 s with the map's 2 Hz poses."""
    p2 = Mission(robot=2, kind="patrol", waypoints=((-2.0, 0.0), (2.5, 0.0)))
    p3 = Mission(robot=3, kind="patrol", waypoints=((2.0, 0.3), (-2.5, 0.3)))
    w = World({2: ((-2.0, 0.0, 0.0), p2, None), 3: ((2.0, 0.3, math.pi), p3, None)}, boxes=TWO_ROOMS,
              exact=exact)
    if not gates:
        for b in w.beh.values():
            b._gates = ()  # type: ignore[misc]
    w.run(60.0)
    crossings = {rid: _crossings_s(w.paths[rid]) for rid in w.beh}
    first = {rid: c[0] if c else math.inf for rid, c in crossings.items()}
    assert min(float(box_distance(box, p[0], p[1])) for box in TWO_ROOMS for path in w.paths.values()
               for p in path) > FOOT
    # face to face in the door on the map's 2 Hz poses the avoidance alone let them 4 cm inside the clearance
    assert w.min_dist >= (CLEAR - 0.02 if gates else 2 * FOOT), w.min_dist
    if gates:
        assert max(first.values()) < 20.0 and sum(map(len, crossings.values())) >= 5, crossings
        assert first[2] < first[3] and w.beh[3].gate_waits >= 1 and w.beh[2].gate_waits == 0  # lower id first
    else:
        assert min(first.values()) > 20.0, crossings


def test_a_robot_beside_a_wall_goes_round_by_the_door_not_along_the_wall_to_the_room_s_end() -> None:
    """Robot 1 stands in the east room beside the wall, north of the door, its goal in the west room: the
    straight way runs into the wall.  It plans its way through the door; the avoidance's corner of the
    wall on its preferred side (the north end, against the room's wall) used to lead it into that corner."""
    w = World({1: ((0.5, 1.2, math.pi), hold(1), (-2.5, 0.3))}, boxes=TWO_ROOMS, exact=True).run(30.0)
    assert w.beh[1].done and math.dist(w.pose[1][:2], (-2.5, 0.3)) < 0.15
    assert max(p[1] for p in w.paths[1]) < 1.5


# the same room with the near door only: no way round
ONE_DOOR = (Box(0.0, 2.75, 0.0, 0.05, 1.25), Box(0.0, -1.75, 0.0, 0.05, 2.25), *POCKET[3:])


@pytest.mark.parametrize(("make_way", "look_around"), [(True, False), (True, True), (False, False)])
def test_a_station_keeper_in_the_only_door_steps_aside_and_returns(make_way: bool, look_around: bool) -> None:
    """Robot 0 holds station in the only door; robot 1 comes from 3 m away to go through.  With
    ``make_way`` the keeper sees it stay near, stalled, steps aside off its line, lets it through
    and takes its station and heading again (also when robot 1 came while the keeper turned to
    look around: it watched all along); without, robot 1 never gets through."""
    cfg = Agent(look_around=look_around, make_way=make_way)
    w = World({0: ((0.0, 1.0, 0.0), hold(0), None), 1: ((-3.0, 1.0, 0.0), hold(1), (3.0, 1.0))},
              boxes=ONE_DOOR, cfg=cfg, exact=True).run(60.0)
    keeper, mover = w.beh[0], w.beh[1]
    assert min(float(box_distance(box, p[0], p[1])) for box in ONE_DOOR for r in (0, 1) for p in w.paths[r]) > FOOT
    assert w.min_dist >= CLEAR - 0.02, w.min_dist
    if make_way:
        assert keeper.make_way.steps_aside == 1 and keeper.make_way.station is None  # back, and holding
        assert max(math.dist(p[:2], (0.0, 1.0)) for p in w.paths[0]) > 0.6  # it did leave the door
        path = w.paths[0]
        j = next(i for i, p in enumerate(path) if math.dist(p[:2], (0.0, 1.0)) > 0.01) - 1
        while j > 0 and path[j - 1] != path[j]:  # back over its turn towards the spot: the heading it held
            j -= 1
        before = path[j]
        assert math.dist(w.pose[0][:2], (0.0, 1.0)) <= 0.05
        assert abs(math.remainder(w.pose[0][2] - before[2], math.tau)) <= 0.05  # the heading it held
        assert mover.done and math.dist(w.pose[1][:2], (3.0, 1.0)) < 0.15
    else:
        assert keeper.make_way.steps_aside == 0 and w.pose[0] == pytest.approx((0.0, 1.0, 0.0))
        assert not mover.done and w.pose[1][0] < 0.0


def test_a_station_keeper_stays_for_a_robot_that_passed_it_or_parked_beside_it() -> None:
    """Robot 1 drives past station keeper 0 and parks 1 m beyond it; robot 2 comes straight at
    keeper 3 and parks 1 m short of it, still.  Neither keeper moves: one was passed, the other's
    visitor does not try to get anywhere."""
    w = World({0: ((0.0, 1.5, 0.0), hold(0), None), 1: ((-3.0, 1.0, 0.0), hold(1), (1.0, 1.0)),
               3: ((0.0, -2.0, 0.0), hold(3), None), 2: ((-3.0, -2.0, 0.0), hold(2), (-1.0, -2.0))},
              cfg=Agent(look_around=False), exact=True).run(40.0)
    assert w.beh[1].done and w.beh[2].done
    assert w.beh[0].make_way.steps_aside == w.beh[3].make_way.steps_aside == 0
    assert w.pose[0] == pytest.approx((0.0, 1.5, 0.0)) and w.pose[3] == pytest.approx((0.0, -2.0, 0.0))


def test_a_keeper_sent_elsewhere_while_aside_holds_where_it_was_sent() -> None:
    """The door keeper above is sent to a run-time goal while it stands aside: it holds there
    afterwards rather than going back to the door."""
    w = World({0: ((0.0, 1.0, 0.0), hold(0), None), 1: ((-3.0, 1.0, 0.0), hold(1), (3.0, 1.0))},
              boxes=ONE_DOOR, cfg=Agent(look_around=False), exact=True)
    while w.beh[0].make_way.station is None and w.t < 40.0:
        w.run(0.5)
    assert w.beh[0].make_way.station is not None  # it did step aside
    w.beh[0].set_goal(2.0, -2.0, 0.1)
    w.run(40.0)
    assert w.beh[0].make_way.station is None and w.beh[0].done
    assert math.dist(w.pose[0][:2], (2.0, -2.0)) < 0.15


def test_a_keeper_steps_aside_to_a_spot_it_can_reach_past_the_others() -> None:
    """Robot 1 came from the west and stalled at keeper 0 (at the origin): the nearest spots off
    its line are 0.7 m north and south; with robot 2 standing on the way north, the keeper goes
    south (the avoidance would stop it short of the north spot)."""
    blocked = Neighbour(1, -0.6, 0.0, 0.0, 0.0, FOOT)
    keep, path = FOOT + CFG.avoid_clearance_m + 0.05, FOOT + CFG.avoid_clearance_m
    args = ((0.0, 0.0, 0.0), (1.0, 0.0))
    assert aside_spot(*args, [blocked], (), keep, path, 2 * FOOT + CFG.avoid_clearance_m + 0.05) == pytest.approx(
        (0.0, 0.7), abs=1e-9)
    spot = aside_spot(*args, [blocked, Neighbour(2, 0.3, 0.3, 0.0, 0.0, FOOT)], (), keep, path,
                      2 * FOOT + CFG.avoid_clearance_m + 0.05)
    assert spot == pytest.approx((0.0, -0.7), abs=1e-9)


@pytest.mark.parametrize("exact", [True, False])
@pytest.mark.parametrize("open_side", [True, False])
def test_a_station_keeper_beside_a_wall_is_passed_on_its_open_side(open_side: bool, exact: bool,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """Robot 7 holds station 0.75 m from the south wall; robot 3 comes along the wall.  Between them there is
    no room (0.77 m needed), so it passes robot 7 on its north side, against its preference (keep the others
    on the left); heading for the preferred side, it stood against the two until it stalled, planned a way
    round and robot 7 stepped aside (the depot: a patrol stood 15 s there)."""
    if not open_side:
        monkeypatch.setattr(Avoider, "_side_free", lambda *_: True)
    room = (Box(0.0, 2.0, 0.0, 5.0, 0.05), Box(0.0, -2.0, 0.0, 5.0, 0.05), Box(5.0, 0.0, 0.0, 0.05, 2.0),
            Box(-5.0, 0.0, 0.0, 0.05, 2.0))
    w = World({7: ((0.0, -1.2, 1.0), hold(7), None), 3: ((-2.5, -1.62, 0.0), hold(3), (2.5, -1.62))},
              boxes=room, exact=exact).run(30.0)
    b = w.beh[3]
    assert w.min_dist >= CLEAR - 0.02, w.min_dist
    assert min(float(box_distance(box, p[0], p[1])) for box in room for p in w.paths[3]) > FOOT
    if open_side:
        assert b.done and b.avoider.reroutes == 0 and w.beh[7].make_way.steps_aside == 0
        assert w.pose[7][:2] == pytest.approx((0.0, -1.2))
    else:
        assert not b.done and b.avoider.reroutes >= 1


def test_a_patrol_on_the_edge_of_a_station_keeper_s_clearance_gets_going_again(tmp_path: Path) -> None:
    """An office of two rooms: robot 1, on its way to the door, comes to a stop on the edge of station keeper
    7's clearance, the keeper between it and the door.  Every way on starts along that edge, where standing
    costs less than passing; its stall found a way round (robots included) that starts there too, and the
    next stall found the same one again: it stood from 21 s to the end (a user's scene, 2026-12-07).  Now the
    second stall at one place goes the other way, assertively, and a way round the robots is followed on the
    side it chose."""
    scene = tmp_path / "office.toml"
    scene.write_text(OFFICE)
    s = load_scenario(str(scene))
    t = arena_to_map(s)
    boxes = static_boxes(s)
    goal = se2_compose(t, (3.5, -3.0, 0.0))[:2]
    w = World({7: ((1.277, 0.316, 0.683), hold(7), None), 1: ((1.713, 0.823, -2.593), hold(1), goal)},
              boxes=boxes, exact=True).run(25.0)
    start = (1.713, 0.823)
    assert math.dist(w.pose[1][:2], start) > 1.5, w.pose[1]  # past the keeper, through the door (it stood at 0.2)
    assert w.min_dist >= CLEAR - 0.02, w.min_dist
    assert w.pose[7][:2] == pytest.approx((1.277, 0.316), abs=0.05)  # the keeper did not have to step aside


OFFICE = """
name = "office"
seed = 31
[arena]
size_x_m = 10.0
size_y_m = 8.0
obstacles = [
  { x_m = 0.0, y_m = -3.0, size_x_m = 0.2, size_y_m = 2.0, size_z_m = 1.2 },
  { x_m = 0.0, y_m = 0.5, size_x_m = 0.2, size_y_m = 3.0, size_z_m = 1.2 },
  { x_m = 0.0, y_m = 3.7, size_x_m = 0.2, size_y_m = 0.6, size_z_m = 1.2 },
  { x_m = -3.0, y_m = 2.0, size_x_m = 1.2, size_y_m = 0.8, size_z_m = 0.8 },
  { x_m = 3.0, y_m = -1.5, size_x_m = 1.0, size_y_m = 1.0, size_z_m = 0.8 },
]
[robots]
count = 8
placement = "explicit"
start = [
  { x_m = -0.509, y_m = -2.882, yaw_rad = 2.4086 }, { x_m = -2.163, y_m = 0.983, yaw_rad = -2.283 },
  { x_m = -4.089, y_m = -1.737, yaw_rad = 1.824 }, { x_m = -0.322, y_m = 3.030, yaw_rad = 0.707 },
  { x_m = 2.353, y_m = 0.332, yaw_rad = -0.185 }, { x_m = 1.571, y_m = 2.859, yaw_rad = -2.941 },
  { x_m = 1.641, y_m = 0.006, yaw_rad = -1.820 }, { x_m = -1.670, y_m = -2.264, yaw_rad = 2.869 },
]
"""
