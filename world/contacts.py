"""Contact events between robots and the arena: ground truth for evaluation (no I/O).

An *event* is a pair of bodies that starts touching, counted once however long
they keep touching.  After every physics step the pairs whose nearest contact
point in pybullet's manifold is within :data:`TOUCH_M` start touching; a touching
pair stops touching only once it is more than :data:`RELEASE_M` apart.  The gap
matters: a robot driven into a wall or another robot is pushed out by the solver
by a fraction of a millimetre, drops out of the manifold for a physics step and
comes back (several times a second), which would otherwise count every bounce.

Floor contacts never count.  Kinds: robot–robot, robot–obstacle, robot–wall;
per robot, every event it takes part in (a robot–robot event counts for both).

Cost: one ``getContactPoints`` call for the whole world returns the floor
contacts too (four per robot) and cost 30 µs (8 robots) to 65 µs (16) per physics
step.  Instead, once per tick :meth:`ContactCounter.begin_tick` keeps the pairs
whose footprint circles could meet within the tick (robots' centres against each
other and against the wall and obstacle boxes, in plain floats), and each physics
step asks pybullet about those pairs alone (2–3 µs each; usually there are none).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Final

from tagswarm.world._pybullet import pb

TOUCH_M: Final = 1e-3
"""A pair starts touching when its nearest contact point is at most this far apart
(m; pybullet reports points up to a fraction of a millimetre before they touch)."""
RELEASE_M: Final = 5e-3
"""A touching pair stops touching when it is more than this far apart (m)."""
KINDS: Final = ("robot_robot", "robot_obstacle", "robot_wall")


@dataclass(frozen=True)
class StaticBox:
    """A wall or obstacle for the broad phase: body id, kind (``"wall"`` /
    ``"obstacle"``), centre (m) and yaw (rad) in the arena frame, half extents in x, y (m)."""

    body: int
    kind: str
    x_m: float
    y_m: float
    yaw_rad: float
    half_x_m: float
    half_y_m: float


class ContactCounter:
    """Counts contact events in one pybullet world.  ``robots`` maps body id to
    robot id; every robot's footprint lies within ``radius_m`` of its centre;
    ``statics`` are the walls and obstacles (any other body, the floor, is ignored);
    ``reach_m`` bounds how much closer a robot and anything else can get within one
    tick (both speeds times the tick, plus slack)."""

    def __init__(self, cid: int, robots: Mapping[int, int], statics: Sequence[StaticBox], radius_m: float,
                 reach_m: float) -> None:
        self.cid = cid
        self._robot_of = dict(robots)
        self._kind_of: dict[int, str] = {b: "robot" for b in robots}
        self._kind_of.update({st.body: st.kind for st in statics})
        # (body, x, y, cos yaw, sin yaw, half x, half y): begin_tick runs every tick over every robot and box
        self._boxes = [(st.body, st.x_m, st.y_m, math.cos(st.yaw_rad), math.sin(st.yaw_rad), st.half_x_m,
                        st.half_y_m) for st in statics]
        self._radius = radius_m
        self._reach = reach_m + RELEASE_M
        self.candidates: list[tuple[int, int]] = []
        self.touching: set[tuple[int, int]] = set()
        self.events: dict[str, int] = dict.fromkeys(KINDS, 0)
        self.per_robot: dict[int, int] = dict.fromkeys(sorted(robots.values()), 0)

    def begin_tick(self, centres: Mapping[int, tuple[float, float]]) -> None:
        """Before a tick's physics steps: keep the pairs that may touch during it,
        from each robot body's centre (x_m, y_m) in the arena frame."""
        near_robot = 2 * self._radius + self._reach
        near_robot2 = near_robot * near_robot
        near = self._radius + self._reach
        near2 = near * near
        items = sorted(centres.items())
        pairs: list[tuple[int, int]] = []
        for i, (a, (xa, ya)) in enumerate(items):
            for b, (xb, yb) in items[i + 1:]:
                dx, dy = xa - xb, ya - yb
                if dx * dx + dy * dy < near_robot2:
                    pairs.append((a, b))
            for body, x0, y0, c, s, hx, hy in self._boxes:
                dx, dy = xa - x0, ya - y0
                # distance outside the box along its own axes (negative: within its extent)
                ox, oy = abs(c * dx + s * dy) - hx, abs(c * dy - s * dx) - hy
                if ox < near and oy < near and (ox <= 0 or oy <= 0 or ox * ox + oy * oy < near2):
                    pairs.append((a, body) if a < body else (body, a))
        self.candidates = pairs

    def update(self) -> None:
        """After every ``stepSimulation``: count the pairs that started touching."""
        now: set[tuple[int, int]] = set()
        for a, b in self.candidates:
            points = pb.getContactPoints(bodyA=a, bodyB=b, physicsClientId=self.cid)
            if points and min(p[8] for p in points) <= TOUCH_M:
                now.add((a, b))
        for pair in now - self.touching:
            self._count(*pair)
        for a, b in self.touching - now:
            if not pb.getClosestPoints(bodyA=a, bodyB=b, distance=RELEASE_M, physicsClientId=self.cid):
                self.touching.discard((a, b))
        self.touching |= now

    def _count(self, a: int, b: int) -> None:
        ka, kb = self._kind_of[a], self._kind_of[b]
        self.events[f"robot_{kb if ka == 'robot' else ka}"] += 1
        for body in (a, b):
            rid = self._robot_of.get(body)
            if rid is not None:
                self.per_robot[rid] += 1

    def as_counters(self) -> dict[str, int]:
        """Status counters: ``contacts_robot_robot``, ``contacts_robot_obstacle``,
        ``contacts_robot_wall`` (world totals) and ``contacts_robot_<id>`` per robot
        (every event it took part in); all present, zero included."""
        out = {f"contacts_{k}": v for k, v in self.events.items()}
        out.update({f"contacts_robot_{rid}": v for rid, v in self.per_robot.items()})
        return out

