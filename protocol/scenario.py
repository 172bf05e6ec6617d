"""The scenario: everything every process must agree on about one simulated world.

A scenario is a TOML file (built-ins live in ``protocol/scenarios/``).  Process
configs embed it and layer environment variables and CLI flags on top through
dotted overrides such as ``clock.mode=lockstep`` (see :func:`apply_override`).
Types and ranges are checked by msgspec; cross-field rules by :func:`validate`.
Every problem is reported as a :class:`ScenarioError` with a one-line message
naming the field.  The section structs (:class:`Scenario`, :class:`Arena`,
:class:`Robot`, :class:`Camera`, ...) and :class:`ScenarioError` are defined in
:mod:`tagswarm.protocol.scenario_schema` (the camera sections in
:mod:`tagswarm.protocol.scenario_camera`, their base in :mod:`tagswarm.protocol.scenario_spec`)
and re-exported here; this module loads,
overrides and validates them (with the geometry of :mod:`tagswarm.protocol.layout`).
"""

from __future__ import annotations

import logging
import math
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

import msgspec

from tagswarm.protocol import tags
from tagswarm.protocol.freespace import segment_box_distance
from tagswarm.protocol.keys import KeyNameError, check_name, split_participant
from tagswarm.protocol.layout import footprint_radius, stand_problem, start_poses
from tagswarm.protocol.robotfill import complete
from tagswarm.protocol.scenario_schema import (
    LENS_COEFFICIENTS,
    Agent,
    Arena,
    CalibrationError,
    Camera,
    CameraSensor,
    Clock,
    Decoy,
    Encoders,
    Event,
    Landmark,
    MapFrame,
    Mission,
    NonNeg,
    Obstacle,
    Pos,
    Render,
    Robot,
    Robots,
    Scenario,
    ScenarioError,
    Spec,
    StartPose,
    TagScheme,
)

__all__ = [
    "Agent", "Arena", "CalibrationError", "Camera", "CameraSensor", "Clock", "Decoy",
    "Encoders", "Event", "Landmark", "MapFrame", "Mission", "NonNeg", "Obstacle",
    "Pos", "Render", "Robot", "Robots", "Scenario", "ScenarioError", "Spec", "StartPose", "TagScheme", "apply_override",
    "builtin_descriptions", "builtin_names", "convert", "load_scenario", "parse_value", "read_scenario_dict",
    "validate",
]


log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- loading


def builtin_names() -> list[str]:
    """Names of the scenarios shipped in the package."""
    folder = resources.files("tagswarm.protocol") / "scenarios"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def builtin_descriptions() -> dict[str, str]:
    """Each built-in scenario's one-line description: the first comment line of its TOML."""
    out = {}
    for name in builtin_names():
        text = (resources.files("tagswarm.protocol") / "scenarios" / f"{name}.toml").read_text()
        first = next((ln for ln in text.splitlines() if ln.strip()), "")
        out[name] = first.lstrip("#").strip() if first.lstrip().startswith("#") else ""
    return out


def read_scenario_dict(name_or_path: str) -> dict[str, Any]:
    """The raw table of a built-in scenario name, a ``.toml`` path, or a ``.json``
    path (a resolved scenario handed from one process to another)."""
    path = Path(name_or_path)
    try:
        if path.suffix == ".json":
            table: dict[str, Any] = msgspec.json.decode(path.read_bytes())
            return table
        if path.suffix == ".toml" or path.is_file():
            text = path.read_text()
        elif name_or_path in builtin_names():
            text = (resources.files("tagswarm.protocol") / "scenarios" / f"{name_or_path}.toml").read_text()
        else:
            raise ScenarioError(
                f"unknown scenario {name_or_path!r} (built-ins: {', '.join(builtin_names())}; or a .toml path)"
            )
        return tomllib.loads(text)
    except OSError as exc:
        raise ScenarioError(f"cannot read scenario {name_or_path!r}: {exc.strerror}") from None
    except (tomllib.TOMLDecodeError, msgspec.DecodeError) as exc:
        raise ScenarioError(f"scenario {name_or_path!r} cannot be parsed: {exc}") from None


def parse_value(text: str) -> Any:
    """A TOML value (``3``, ``true``, ``[1, 2]``, ``"x"``); bare words become strings."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def apply_override(table: dict[str, Any], assignment: str) -> None:
    """Apply ``dotted.key=value`` to a nested dict in place."""
    if "=" not in assignment:
        raise ScenarioError(f"override {assignment!r} must look like 'section.field=value'")
    dotted, value = assignment.split("=", 1)
    parts = [p.strip() for p in dotted.strip().split(".")]
    if not all(parts):
        raise ScenarioError(f"override {assignment!r} has an empty field name")
    node = table
    for p in parts[:-1]:
        nxt = node.setdefault(p, {})
        if not isinstance(nxt, dict):
            raise ScenarioError(f"override {assignment!r}: {p!r} is not a section")
        node = nxt
    node[parts[-1]] = parse_value(value.strip())


def convert(table: dict[str, Any], cls: type[Any], what: str) -> Any:
    """msgspec-convert a TOML table, turning errors into one-line messages."""
    try:
        return msgspec.convert(table, cls)
    except msgspec.ValidationError as exc:
        # msgspec says "... - at `$.clock.mode`"; rephrase with the field first
        text = str(exc)
        if " - at `$." in text:
            msg, path = text.rsplit(" - at `$.", 1)
            raise ScenarioError(f"{what}: field '{path.rstrip('`')}': {msg}") from None
        raise ScenarioError(f"{what}: {text}") from None


def _trim_to_count(table: dict[str, Any], scenario_count: int | None = None) -> None:
    """``robots.count`` below the length of an explicit start list keeps the first
    robots and their missions and events, so ``--robots 2`` works on any scenario.
    Only the missions and events of robots that were cut go (those of robots
    ``count .. scenario_count - 1``): one naming a robot the scenario never had
    stays, and fails validation with its field named."""
    robots = table.get("robots")
    if not isinstance(robots, dict):
        return
    count, start = robots.get("count"), robots.get("start")
    if not isinstance(count, int):
        return
    if isinstance(start, list) and len(start) > count and robots.get("placement", "ring") == "explicit":
        robots["start"] = start[:count]
    cut = range(count, max(count, scenario_count if scenario_count is not None else count))
    for section in ("missions", "events"):
        items = table.get(section)
        if isinstance(items, list):
            table[section] = [it for it in items if not isinstance(it, dict) or it.get("robot", 0) not in cut]


def _start_means_explicit(robots: Any, strict: str | None) -> None:
    """A ``robots.start`` list without ``robots.placement`` means explicit placement (and, without
    ``robots.count``, as many robots as poses): the default ring would silently move the robots from
    where the file puts them.  ``strict`` (the file's name): a start list beside another placement in
    the same file is an error (an override may switch placement on purpose)."""
    if not isinstance(robots, dict) or not isinstance(robots.get("start"), list) or not robots["start"]:
        return
    placement = robots.get("placement")
    if placement is None:
        robots["placement"] = "explicit"
        robots.setdefault("count", len(robots["start"]))
        log.info("robots.start given without robots.placement: placement = \"explicit\"")
    elif placement != "explicit" and strict is not None:
        raise ScenarioError(f"{strict}: robots.start is used only with robots.placement = \"explicit\", not "
                            f"{placement!r}: set placement to \"explicit\" or remove start")


def load_scenario(name_or_path: str = "paper", overrides: tuple[str, ...] | list[str] = ()) -> Scenario:
    """Load, override and validate a scenario.  Robots beyond an explicit start list
    get free start poses and missions, and the tag-ID scheme is compacted if it has
    no room for them (:mod:`tagswarm.protocol.robotfill`); each such step is logged at INFO."""
    table = read_scenario_dict(name_or_path)
    # a resolved scenario (the run folder's scenario.json) keeps the start list of the file it came from
    _start_means_explicit(table.get("robots"), None if str(name_or_path).endswith(".json")
                          else f"scenario {name_or_path!r}")
    robots = table.get("robots")
    toml_count = robots.get("count") if isinstance(robots, dict) else None
    for o in overrides:
        apply_override(table, o)
    _start_means_explicit(table.get("robots"), None)
    _trim_to_count(table, toml_count if isinstance(toml_count, int) else None)
    scenario: Scenario = convert(table, Scenario, f"scenario {name_or_path!r}")
    scenario, notes = complete(scenario, toml_count if isinstance(toml_count, int) else Robots().count)
    # a resolved scenario (scenario.json, what tagswarm up hands its children) was completed and its notes
    # logged where it was resolved: every child saying so again is noise
    for note in notes if not str(name_or_path).endswith(".json") else ():
        log.info("%s", note)
    scenario = _expand_agents(scenario)
    validate(scenario)
    return scenario


#: in ``clock.participants``, every robot's agent (``agent/0`` .. ``agent/<count-1>``):
#: a deployment whose robot count is chosen at start (compose ``--scale``) names them so
AGENTS_WILDCARD = "agent/*"


def _expand_agents(s: Scenario) -> Scenario:
    """``s`` with :data:`AGENTS_WILDCARD` in ``clock.participants`` replaced by one agent per robot."""
    if AGENTS_WILDCARD not in s.clock.participants:
        return s
    out: list[str] = []
    for p in s.clock.participants:
        for q in ([f"agent/{r}" for r in s.robot_ids] if p == AGENTS_WILDCARD else [p]):
            if q not in out:
                out.append(q)
    return msgspec.structs.replace(s, clock=msgspec.structs.replace(s.clock, participants=tuple(out)))


# --------------------------------------------------------------------------- rules


def validate(s: Scenario) -> None:
    """Cross-field rules; raises :class:`ScenarioError` naming the field."""
    bad = _non_finite(s, "")
    if bad:
        raise ScenarioError(f"field '{bad}' must be a finite number")
    fam_n = tags.family_size(s.tags.family)
    need = tags.min_face_for_tag(s.tags.family, s.tags.size_m)
    if need > s.robot.cube_edge_m + 1e-9:
        raise ScenarioError(
            f"tags.size_m={s.tags.size_m} leaves no white quiet zone on a {s.robot.cube_edge_m} m cube "
            f"(robot.cube_edge_m must be >= {need:.3f})"
        )
    owner: dict[int, str] = {}
    for rid in s.robot_ids:
        for face, tid in zip(tags.Face, s.tag_ids(rid), strict=True):
            _claim(owner, tid, f"robot {rid} {face.name.lower()}", fam_n, s.tags.family, "tags")
    for i, lm in enumerate(s.landmarks):
        _claim(owner, lm.id, f"landmark {i}", fam_n, s.tags.family, f"landmarks[{i}].id")
        # on a wall's face or in the arena; a tag behind a wall is seen by nobody
        lim_x, lim_y = s.arena.size_x_m / 2 + s.arena.wall_thickness_m, s.arena.size_y_m / 2 + s.arena.wall_thickness_m
        if abs(lm.x_m) > lim_x or abs(lm.y_m) > lim_y:
            raise ScenarioError(f"landmarks[{i}]: ({lm.x_m}, {lm.y_m}) is outside the arena's walls (arena frame, "
                                f"|x| <= {lim_x:g}, |y| <= {lim_y:g})")
    for k, ob in enumerate(s.arena.obstacles):
        if abs(ob.x_m) > s.arena.size_x_m / 2 or abs(ob.y_m) > s.arena.size_y_m / 2:
            raise ScenarioError(f"arena.obstacles[{k}]: its centre ({ob.x_m}, {ob.y_m}) is outside the arena "
                                f"(arena frame, |x| <= {s.arena.size_x_m / 2:g}, |y| <= {s.arena.size_y_m / 2:g})")
    _validate_decoys(s)
    names = [c.name for c in s.robot.cameras]
    if not names:
        raise ScenarioError("robot.cameras: a robot needs at least one camera")
    if len(set(names)) != len(names):
        raise ScenarioError(f"robot.cameras: camera names must be unique, got {names}")
    for i, c in enumerate(s.robot.cameras):
        try:
            check_name(c.name, f"robot.cameras[{i}].name")
        except KeyNameError as exc:
            raise ScenarioError(str(exc)) from None
        if c.far_m <= c.near_m:
            raise ScenarioError(f"robot.cameras[{i}]: far_m must exceed near_m")
        if c.rate_hz > s.clock.tick_hz:
            raise ScenarioError(f"robot.cameras[{i}].rate_hz={c.rate_hz} exceeds clock.tick_hz={s.clock.tick_hz}")
        _validate_lens(c, i)
    if s.encoders.rate_hz > s.clock.tick_hz:
        raise ScenarioError(f"encoders.rate_hz={s.encoders.rate_hz} exceeds clock.tick_hz={s.clock.tick_hz}")
    if s.robot.wheel_base_m < s.robot.wheel_radius_m:
        raise ScenarioError("robot.wheel_base_m must be at least robot.wheel_radius_m")
    for p in s.clock.participants:
        try:
            split_participant(p)
        except KeyNameError as exc:
            raise ScenarioError(f"clock.participants: {exc}") from None
    if s.robots.placement == "explicit" and len(s.robots.start) != s.robots.count:
        raise ScenarioError(
            f"robots.start has {len(s.robots.start)} poses but robots.count={s.robots.count} (placement=explicit)"
        )
    seen_missions = [mi.robot for mi in s.missions]
    for i, mi in enumerate(s.missions):
        if mi.robot not in s.robot_ids:
            raise ScenarioError(f"missions[{i}].robot={mi.robot} is not a robot of this scenario "
                                f"(0..{s.robots.count - 1})")
        if seen_missions.count(mi.robot) > 1:
            raise ScenarioError(f"missions[{i}]: robot {mi.robot} has more than one mission")
        if mi.kind != "hold" and not mi.waypoints:
            raise ScenarioError(f"missions[{i}]: a {mi.kind} mission needs waypoints")
    if s.map.origin_id not in s.robot_ids:
        raise ScenarioError(f"map.origin_id={s.map.origin_id} is not a robot of this scenario")
    _validate_events(s)
    poses = start_poses(s)
    half_x = s.arena.size_x_m / 2 - s.arena.wall_thickness_m / 2
    half_y = s.arena.size_y_m / 2 - s.arena.wall_thickness_m / 2
    r = footprint_radius(s.robot)
    for rid, (x, y, _) in zip(s.robot_ids, poses, strict=True):
        if abs(x) + r > half_x or abs(y) + r > half_y:
            raise ScenarioError(f"robot {rid} starts at ({x:.2f}, {y:.2f}), outside the arena")
    for i in range(len(poses)):
        for j in range(i):
            if math.dist(poses[i][:2], poses[j][:2]) < 2 * r:
                raise ScenarioError(f"robots {j} and {i} start overlapping (robots.placement/start)")
        for k, ob in enumerate(s.arena.obstacles):
            if segment_box_distance(poses[i][:2], poses[i][:2], ob) < r:
                raise ScenarioError(f"robot {i} starts on arena.obstacles[{k}] (robots.placement/start)")
    for i, mi in enumerate(s.missions):
        _validate_waypoints(s, i, mi.waypoints)


def _validate_waypoints(s: Scenario, i: int, waypoints: tuple[tuple[float, float], ...]) -> None:
    """Every waypoint of ``missions[i]`` is a place the robot can stand (else it stops short of
    it for the rest of the run)."""
    for j, (x, y) in enumerate(waypoints):
        why = stand_problem(s, x, y)
        if why is not None:
            raise ScenarioError(f"missions[{i}].waypoints[{j}]=({x:g}, {y:g}): {why}")


def _validate_decoys(s: Scenario) -> None:
    """``[[decoys]]``: a tag ID of its family, inside the arena (they may repeat any ID: that is what they are for)."""
    for i, d in enumerate(s.decoys):
        family = d.family or s.tags.family
        n = tags.family_size(family)
        if not 0 <= d.tag_id < n:
            raise ScenarioError(f"decoys[{i}].tag_id={d.tag_id}: {family} has IDs 0..{n - 1}")
        if abs(d.x_m) > s.arena.size_x_m / 2 or abs(d.y_m) > s.arena.size_y_m / 2:
            raise ScenarioError(f"decoys[{i}]: ({d.x_m}, {d.y_m}) is outside the arena")


#: the widest ray a lens may reach in its image corners: the lens is rendered as a wider
#: pinhole view, which needs tan(angle) pixels (world/lens.py)
MAX_LENS_HALF_ANGLE_DEG = 80.0


def _validate_lens(c: Camera, i: int) -> None:
    """A lens's coefficient count, and a field of view a pinhole render can cover."""
    if c.lens == "auto":
        if c.distortion and len(c.distortion) not in (4, 5):
            raise ScenarioError(f"robot.cameras[{i}].distortion: an auto lens takes 5 (Brown-Conrady) or 4 "
                                f"(fisheye) coefficients, got {len(c.distortion)}")
    else:
        want = LENS_COEFFICIENTS[c.lens]
        if c.distortion and len(c.distortion) != want:
            raise ScenarioError(f"robot.cameras[{i}].distortion: lens {c.lens!r} takes {want} coefficients "
                                f"{'(k1, k2, p1, p2, k3)' if want == 5 else '(k1, k2, k3, k4)' if want else ''}, "
                                f"got {len(c.distortion)}")
    if c.lens == "fisheye" or (c.lens == "auto" and c.hfov_deg >= 120.0):
        diag = math.hypot(c.width, c.height) / c.width * c.hfov_deg / 2.0  # equidistant: angle ~ radius
        if diag > MAX_LENS_HALF_ANGLE_DEG:
            raise ScenarioError(f"robot.cameras[{i}]: a fisheye of hfov_deg={c.hfov_deg} reaches {diag:.0f} deg "
                                f"off-axis in its corners, more than the {MAX_LENS_HALF_ANGLE_DEG:.0f} deg a "
                                "rendered pinhole view can cover (lower hfov_deg)")


def _validate_events(s: Scenario) -> None:
    """``[[events]]``: a robot of the scenario, a time >= 0, and a teleport inside the
    arena walls (by the footprint circle, like start poses; the world checks the exact
    footprint and overlaps when it applies the event)."""
    half_x = s.arena.size_x_m / 2 - s.arena.wall_thickness_m / 2
    half_y = s.arena.size_y_m / 2 - s.arena.wall_thickness_m / 2
    r = footprint_radius(s.robot)
    for i, ev in enumerate(s.events):
        if ev.robot not in s.robot_ids:
            raise ScenarioError(f"events[{i}].robot={ev.robot} is not a robot of this scenario "
                                f"(0..{s.robots.count - 1})")
        if ev.at_s < 0:
            raise ScenarioError(f"events[{i}].at_s={ev.at_s} must be >= 0 (simulation seconds)")
        if ev.action == "teleport" and (abs(ev.x_m) + r > half_x or abs(ev.y_m) + r > half_y):
            raise ScenarioError(f"events[{i}]: teleport to ({ev.x_m:.2f}, {ev.y_m:.2f}) is outside the arena")


def _non_finite(value: Any, path: str) -> str | None:
    """Dotted path of the first NaN/inf float in a scenario, else None."""
    if isinstance(value, float):
        return None if math.isfinite(value) else path
    if isinstance(value, msgspec.Struct):
        for f in value.__struct_fields__:
            hit = _non_finite(getattr(value, f), f"{path}.{f}" if path else f)
            if hit:
                return hit
    if isinstance(value, tuple):
        for i, v in enumerate(value):
            hit = _non_finite(v, f"{path}[{i}]")
            if hit:
                return hit
    return None


def _claim(owner: dict[int, str], tid: int, who: str, fam_n: int, family: str, field: str) -> None:
    if not 0 <= tid < fam_n:
        raise ScenarioError(f"{field}: {who} would carry tag ID {tid}, but {family} has IDs 0..{fam_n - 1}")
    if tid in owner:
        raise ScenarioError(f"{field}: tag ID {tid} is used twice ({owner[tid]} and {who})")
    owner[tid] = who
