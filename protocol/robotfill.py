"""Robots a scenario does not place itself: free start poses, default missions, and a
tag-ID scheme that has room for them.  This is what makes ``--robots N`` work on a
scenario written for fewer robots.

Placement.  A scenario with ``placement = "explicit"`` lists start poses for its own
robots; robots beyond that list are put on a square lattice over the free floor: at
least ``r + MARGIN_M`` from the walls and obstacles (``r`` the footprint radius), and
at least one lattice spacing (never less than ``2 r + MARGIN_M``) from every landmark
tag (so nobody hides it), from the other robots' starts *and* from the straight paths
their missions drive along (so nobody stands in a patrol lane).  The spacing is the
widest of 1.0, 0.9, ... m down to ``2 r + MARGIN_M`` that has room for every extra
robot; the lattice points nearest to the scenario's own robots' paths are taken
first, so the newcomers gather around the action.  Only if no spacing has room off
the paths are points that merely clear the other robots' starts used (those off the
paths first; the log says how many stand in a path: they will be bumped).  When even
that has no room, :class:`ScenarioError` names ``robots.count`` and how many fit.

Heading.  Each placed robot faces the origin robot (the map's anchor: seeing it ties
a robot to the map directly) if it is within ``REACH_SHARE`` of ``agent.max_range_m``
and no obstacle taller than the tag cube's centre stands between them; otherwise the
nearest of the scenario's robots in reach and in sight (else simply the nearest).

Mission.  A placed robot patrols back and forth between its start and a point 0.8 m
(or 0.5 m) straight ahead, towards a robot it faces, so that on every outward leg it
drives while reading that robot's cube (a fix per camera frame) and on the way back
shows its own cube to the robots behind it.  The lane towards the origin robot is
tried first, then towards the others in sight, nearest first; a lane is kept only if
it stays ``2 r + MARGIN_M + PATROL_CLEARANCE_M`` from every other robot's start and
path (the scenario's and the newcomers' so far), ``r + MARGIN_M`` from walls and
obstacles, and ends at least ``MIN_SIGHT_M`` short of the robot it faces.  With no
such lane the robot holds station facing the origin robot: a standing robot does not
drift and is a reference for the others, which is what a crowded scene needs.  A
placed origin robot holds.  A mission the scenario already gives a placed robot is kept.

Tag IDs.  Robot k carries ``id_base + id_stride k + face``.  If the scenario's scheme
runs past the tag family or onto a landmark's ID with this many robots (tag36h11's
587 IDs hold 59 robots at the paper's stride of 10), the compact scheme stride 6 is
used instead, from the scenario's ``id_base`` if that block is free, else from the
first free block; with no room even then, :class:`ScenarioError` says how many fit.

Everything is deterministic: a pure function of the scenario (no random draws, so
the same scenario and seed always give the same poses).  Arena frame, metres, radians.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator, Sequence

import msgspec

from tagswarm.protocol import tags
from tagswarm.protocol.freespace import XY, obstacle_clearance, segment_distance, sight_blocked, wall_clearance
from tagswarm.protocol.layout import anchors_map, footprint_radius, in_view, origin_heading, start_poses
from tagswarm.protocol.scenario_schema import Mission, Scenario, ScenarioError, StartPose
from tagswarm.protocol.sightlines import reading_range_m, unseen_at_start

MARGIN_M = 0.1
MAX_SPACING_M = 1.0
SPACING_STEP_M = 0.1
PATROL_LENGTHS_M = (0.8, 0.5)
# a patrol lane keeps this much more room than a standing robot: the robot drives to
# within agent.goal_tolerance_m of its waypoints on an estimate that may be off
PATROL_CLEARANCE_M = 0.3
MIN_SIGHT_M = 1.0  # a robot's camera reads a cube from about 0.5 m; stop well before that
REACH_SHARE = 0.8  # of agent.max_range_m: the origin robot is worth facing up to this far

Path = list[tuple[XY, XY]]


def complete(s: Scenario, toml_count: int) -> tuple[Scenario, list[str]]:
    """The scenario with every robot placed and a tag scheme that fits, plus one
    log line per thing that was filled in (empty if nothing was).  ``toml_count`` is
    ``robots.count`` as the scenario file had it, before overrides: with an explicit
    start list the scenario's own robots are the listed ones, otherwise that many."""
    notes: list[str] = []
    own = len(s.robots.start) if s.robots.placement == "explicit" else min(toml_count, s.robots.count)
    s, note = fill_robots(s)
    if note:
        notes.append(note)
    s, note = fit_tag_ids(s, own)
    if note:
        notes.append(note)
    for note in (idle_note(s), unseen_note(s), blind_origin_note(s)):
        if note:
            notes.append(note)
    return s, notes


def idle_note(s: Scenario) -> str | None:
    """A line naming the robots the scenario gives no mission (they hold station where they
    start), or None if every robot has one: a first scene with ``placement = "random"`` and no
    ``[[missions]]`` is a swarm that never moves, which nothing else would say."""
    given = {mi.robot for mi in s.missions}
    idle = [k for k in s.robot_ids if k not in given and k != s.map.origin_id]
    if not idle:
        return None
    return (f"{_ids(idle)}: no mission in scenario {s.name!r}: holding station where they start "
            f"(a [[missions]] entry with kind = \"patrol\" or \"waypoints\" moves one)")


def unseen_note(s: Scenario) -> str | None:
    """A line naming the robots that start where no robot that can be placed sees them
    (:mod:`tagswarm.protocol.sightlines`), or None: they stay unplaced until someone drives by."""
    unseen = unseen_at_start(s)
    if not unseen:
        return None
    return (f"{_ids(unseen)}: at the start no robot that can be placed in scenario {s.name!r} is within sight "
            f"(a camera reads a cube to about {reading_range_m(s):.1f} m here; obstacles as tall as the cubes "
            f"hide one): unplaced until a mission brings one within sight of a placed robot, and time localised "
            f"counts that time as lost")


def blind_origin_note(s: Scenario) -> str | None:
    """A line if the origin robot, which anchors the map, starts with no robot in its cameras'
    view (:func:`~tagswarm.protocol.layout.in_view`) though some are in reach and sight, else
    None: the map's heading then rests on the others' views of its cube alone."""
    k = s.map.origin_id
    if not anchors_map(s, k) or not s.robot.cameras or not 0 <= k < s.robots.count:
        return None
    poses = start_poses(s)
    if in_view(s, poses, k):
        return None
    yaw = origin_heading(s, poses)
    if yaw is None:
        return None  # nobody in reach: unseen_note says so
    return (f"robot {k}, the map's origin, starts with no robot in its cameras' view in scenario {s.name!r}: the "
            f"map's heading then rests on the others' views of its cube, whose faces tell it only to a few degrees "
            f"(a turned map: 1.4 degrees is 10 cm at 4 m; measured on a store room, fused RMSE 10 cm against "
            f"1.2 cm facing the swarm); facing {len(in_view(s, poses, k, yaw))} robot(s), e.g. yaw_rad = "
            f"{yaw:.2f} in the arena frame, ties it to the swarm")


def mission_path(start: XY, mission: Mission | None) -> Path:
    """The straight legs (arena frame) a robot drives from ``start`` on ``mission``:
    a single zero-length leg for a robot that holds."""
    pts = [start]
    if mission is not None and mission.kind != "hold":
        pts += [(float(x), float(y)) for x, y in mission.waypoints]
        if (mission.loop or mission.kind == "leapfrog") and len(mission.waypoints) > 1:
            pts.append(pts[1])
    if len(pts) == 1:
        return [(start, start)]
    return list(itertools.pairwise(pts))


def fill_robots(s: Scenario) -> tuple[Scenario, str | None]:
    """Start poses and missions for the robots beyond an explicit start list (see the
    module docstring); the scenario unchanged and None if there are none."""
    given = [(p.x_m, p.y_m) for p in s.robots.start]
    n_new = s.robots.count - len(given)
    if s.robots.placement != "explicit" or n_new <= 0:
        return s, None
    r = footprint_radius(s.robot)
    missions = {mi.robot: mi for mi in s.missions}
    paths: list[Path] = [mission_path(p, missions.get(k)) for k, p in enumerate(given)]
    spacing, points, in_paths = _lattice_for(s, paths, n_new, r)
    origin = given[s.map.origin_id] if s.map.origin_id < len(given) else None
    new_ids = range(len(given), s.robots.count)
    occupied: list[Path] = [*paths, *([(p, p)] for p in points)]
    starts: list[tuple[XY, float]] = []
    added: list[Mission] = []
    patrolling: list[int] = []
    faced_origin = True
    for i, (rid, p) in enumerate(zip(new_ids, points, strict=True)):
        aims = _aims(s, p, origin, given or [q for q, _ in starts] or [(0.0, 0.0)])
        lane = None
        if rid not in missions and rid != s.map.origin_id:
            lane = next((ln for aim in aims if (ln := _patrol_lane(s, p, aim, occupied, len(paths) + i, r))), None)
        aim = lane[1] if lane else aims[0]
        faced_origin = faced_origin and origin is not None and _heading(p, aim) == _heading(p, origin)
        starts.append((p, _heading(p, aim)))
        if lane is not None:
            occupied[len(paths) + i] = [lane]
            patrolling.append(rid)
            added.append(Mission(robot=rid, kind="patrol", waypoints=lane))
        elif rid not in missions:
            added.append(Mission(robot=rid, kind="hold"))
    robots = msgspec.structs.replace(s.robots, start=(*s.robots.start, *(
        StartPose(x_m=round(p[0], 6), y_m=round(p[1], 6), yaw_rad=round(yaw, 6)) for p, yaw in starts)))
    filled = msgspec.structs.replace(s, robots=robots, missions=(*s.missions, *added))
    holding = [m.robot for m in added if m.kind == "hold"]
    faced = f"robot {s.map.origin_id}" if faced_origin else "the origin robot or else the nearest robot in sight"
    note = (f"{_ids(list(new_ids))}: no start pose/mission in scenario {s.name!r}: placed at free poses on a "
            f"{spacing:.2f} m lattice beside its robots, facing {faced}; patrolling (up to {PATROL_LENGTHS_M[0]} m "
            f"towards the robot faced and back): {_ids(patrolling) if patrolling else 'none'}; holding: "
            f"{_ids(holding) if holding else 'none'}"
            + (f"; {in_paths} stand in other robots' paths (no room elsewhere)" if in_paths else ""))
    return filled, note


def _spacings(min_gap: float) -> Iterator[float]:
    sp = MAX_SPACING_M
    while sp > min_gap + 1e-9:
        yield sp
        sp = round(sp - SPACING_STEP_M, 6)
    yield min_gap


def _lattice(s: Scenario, spacing: float, r: float) -> list[XY]:
    """Points of a square lattice of ``spacing`` centred in the arena, clear of the walls."""
    a = s.arena
    out: list[XY] = []
    half_x = a.size_x_m / 2 - a.wall_thickness_m / 2 - r - MARGIN_M
    half_y = a.size_y_m / 2 - a.wall_thickness_m / 2 - r - MARGIN_M
    if half_x < 0 or half_y < 0:
        return out
    nx, ny = math.floor(2 * half_x / spacing + 1e-9) + 1, math.floor(2 * half_y / spacing + 1e-9) + 1
    for j in range(ny):
        for i in range(nx):
            out.append((round((i - (nx - 1) / 2) * spacing, 6), round((j - (ny - 1) / 2) * spacing, 6)))
    return out


def _static_clear(s: Scenario, a: XY, b: XY, r: float, landmark_gap: float = 0.0) -> bool:
    """A robot's footprint along ``a``-``b`` stays ``MARGIN_M`` clear of walls and
    obstacles, and its centre ``landmark_gap`` (at least ``r + MARGIN_M`` plus half
    the tag) from every landmark tag."""
    need = r + MARGIN_M
    if min(wall_clearance(a, s.arena), wall_clearance(b, s.arena)) < need:
        return False
    if obstacle_clearance(a, b, s.arena) < need:
        return False
    return all(segment_distance(a, b, (lm.x_m, lm.y_m), (lm.x_m, lm.y_m)) >= max(landmark_gap, need + lm.size_m / 2)
               for lm in s.landmarks)


def _clear_of(a: XY, b: XY, paths: Sequence[Path], gap: float) -> bool:
    return all(segment_distance(a, b, c, d) >= gap for path in paths for c, d in path)


def _lattice_for(s: Scenario, paths: list[Path], n: int, r: float) -> tuple[float, list[XY], int]:
    """The widest lattice spacing with ``n`` free points, those points (nearest to the
    scenario's robots first), and how many of them stand in another robot's path.

    The points keep a spacing away from the other robots' paths if any spacing has
    room for that; otherwise points that merely clear the other robots' start poses
    are used, those off the paths first, at the spacing that puts the fewest in a path."""
    min_gap = math.ceil((2 * r + MARGIN_M) * 1000) / 1000  # whole mm: lattice points are rounded to um
    starts = [path[:1] for path in paths]
    most = 0

    def near(p: XY) -> tuple[float, float, float]:
        d = min((segment_distance(p, p, c, e) for path in paths for c, e in path), default=math.hypot(*p))
        return (round(d, 6), p[1], p[0])

    crowded: tuple[float, list[XY], int] | None = None  # fewest robots in a path, then the widest spacing
    for spacing in _spacings(min_gap):
        gap = max(spacing, min_gap)
        # a robot parked in front of a landmark would hide it: keep landmarks a spacing away too
        free = [p for p in _lattice(s, spacing, r) if _static_clear(s, p, p, r, spacing)
                and _clear_of(p, p, starts, gap)]
        off = sorted((p for p in free if _clear_of(p, p, paths, gap)), key=near)
        most = max(most, len(free))
        if len(off) >= n:
            return spacing, off[:n], 0
        if len(free) >= n and (crowded is None or n - len(off) < crowded[2]):
            on = sorted((p for p in free if p not in off), key=near)
            crowded = (spacing, (off + on)[:n], n - len(off))
    if crowded is not None:
        return crowded
    given = len(paths)
    raise ScenarioError(
        f"robots.count={s.robots.count}: scenario {s.name!r} places {given} robots and has room for only {most} more "
        f"({given + most} in all) in its {s.arena.size_x_m:g} m x {s.arena.size_y_m:g} m arena, clear of walls, "
        f"obstacles and the other robots"
    )


def _heading(p: XY, q: XY) -> float:
    return round(math.atan2(q[1] - p[1], q[0] - p[0]), 6) if q != p else 0.0


def _aims(s: Scenario, p: XY, origin: XY | None, others: Sequence[XY]) -> list[XY]:
    """The points a placed robot at ``p`` may face, best first (see the module
    docstring): the origin robot if in reach and in sight, then the other robots in
    reach and in sight by distance; if there are none, the nearest robot."""
    tall, reach = s.robot.cube_center_z_m, REACH_SHARE * s.agent.max_range_m
    ranked = sorted(others, key=lambda q: (round(math.dist(p, q), 6), q[1], q[0]))
    seen = [q for q in ranked if math.dist(p, q) <= reach and not sight_blocked(p, q, s.arena, tall)]
    if origin is not None and origin in seen:
        seen.remove(origin)
        seen.insert(0, origin)
    return seen or ranked[:1]


def _patrol_lane(s: Scenario, p: XY, aim: XY, occupied: list[Path], me: int, r: float) -> tuple[XY, XY] | None:
    """Waypoints (start, end) of a patrol from ``p`` straight towards ``aim`` that is
    clear of everything, or None."""
    others = occupied[:me] + occupied[me + 1:]
    gap = 2 * r + MARGIN_M + PATROL_CLEARANCE_M
    yaw = math.atan2(aim[1] - p[1], aim[0] - p[0])
    for length in PATROL_LENGTHS_M:
        q = (round(p[0] + length * math.cos(yaw), 6), round(p[1] + length * math.sin(yaw), 6))
        if math.dist(q, aim) >= MIN_SIGHT_M and _static_clear(s, p, q, r) and _clear_of(p, q, others, gap):
            return (p, q)
    return None


def _ids(ids: list[int]) -> str:
    """``robots 4-7, 9`` / ``robot 4``: consecutive ids as ranges."""
    runs: list[list[int]] = []
    for k in ids:
        if runs and k == runs[-1][-1] + 1:
            runs[-1].append(k)
        else:
            runs.append([k])
    text = ", ".join(f"{r[0]}-{r[-1]}" if len(r) > 1 else str(r[0]) for r in runs)
    return ("robots " if len(ids) > 1 else "robot ") + text


def fit_tag_ids(s: Scenario, own: int) -> tuple[Scenario, str | None]:
    """The scenario with a tag scheme that gives every robot six IDs of the family
    that no landmark uses (see the module docstring), and a note if it changed.  The
    scheme is only changed when it suits the scenario's ``own`` first robots and just
    not the extra ones: a scheme that clashes anyway is the author's to fix, and
    :func:`tagswarm.protocol.scenario.validate` names the clash."""
    n, fam = s.robots.count, s.tags.family
    size = tags.family_size(fam)
    base, stride = s.tags.id_base, s.tags.id_stride
    taken = {lm.id for lm in s.landmarks}

    def clash(b: int, st: int, robots: int) -> bool:
        if robots < 1:
            return False
        ids = tags.robot_tag_ids(robots - 1, b, st)
        return ids[-1] >= size or any(t in taken for k in range(robots) for t in tags.robot_tag_ids(k, b, st))

    if stride < len(tags.Face) or not clash(base, stride, n) or clash(base, stride, min(own, n)):
        return s, None
    six = len(tags.Face)
    for b in (base, *range(size)):
        if not clash(b, six, n):
            why = (f"up to {tags.robot_tag_ids(n - 1, base, stride)[-1]} but {fam} has 0..{size - 1}"
                   if tags.robot_tag_ids(n - 1, base, stride)[-1] >= size else "that landmarks use")
            note = (f"tags: {n} robots at tags.id_base={base}, tags.id_stride={stride} would need tag IDs {why}: "
                    f"using tags.id_base={b}, tags.id_stride={six} (robot k carries {b}+6k .. {b + 5}+6k)")
            return msgspec.structs.replace(s, tags=msgspec.structs.replace(s.tags, id_base=b, id_stride=six)), note
    free_run = longest = 0
    for t in range(size):
        free_run = 0 if t in taken else free_run + 1
        longest = max(longest, free_run)
    raise ScenarioError(
        f"robots.count={n}: {fam} has {size} tag IDs"
        + (f" ({len(taken)} used by landmarks)" if taken else "")
        + f", room for at most {longest // six} robots at {six} IDs each (tags.family, robots.count)"
    )
