"""The other robots as obstacles, from the server's global map and, for a robot the map does not
have yet, from this agent's own sightings (pure code, no I/O).

The server publishes its :class:`~tagswarm.protocol.messages.GlobalMap` at a low rate
(``map_rate_hz``, 2 Hz by default), so each robot's entry is extrapolated to
the agent's time with a velocity estimated from the previous map in which it
appeared, and its circle is widened by its position uncertainty and by how
far a velocity error could have carried it since.  Robots whose agent is gone
(``alive`` false) stay obstacles at rest: the world stops a robot whose
commands stop.

Lockstep determinism: which map an agent uses must not depend on when the map
happened to arrive, so maps wait in :meth:`NeighbourTracker.offer` and are
adopted in stamp order only once their stamp is at or before the bound the
caller passes to :meth:`NeighbourTracker.neighbours` (one whose maps must have
arrived by then; no bound in realtime).

Frames and units: map frame, metres, seconds, nanosecond stamps.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

from tagswarm.agents.avoid import Neighbour
from tagswarm.protocol.geometry import Pose2, se2_compose, se2_inverse
from tagswarm.protocol.messages import MapEntry

MAX_PENDING = 8  # maps not yet usable (bounded memory under a flood)
MAX_EXTRAPOLATE_S = 1.0  # never predict further than this past a map
VELOCITY_MAX_DT_S = 1.5  # two maps further apart than this give no velocity
SIGMA_WIDEN = 2.0  # the circle grows by this many standard deviations of the position ...
SIGMA_WIDEN_MAX_M = 0.15  # ... at most
AGE_WIDEN = 0.25  # ... and by this share of the distance extrapolated (velocity error)
#: a sighting further than this beyond a robot's circle is one the map contradicts (a copy of its cube)
SIGHTING_GATE_M = 0.5
#: a robot this agent saw itself but the map does not have (not placed yet) stays an obstacle, at rest
#: where it was seen, this long (s): else a robot drives into a neighbour nobody has placed
SIGHTED_KEEP_S = 3.0


@dataclass(frozen=True)
class _Track:
    stamp_ns: int
    x_m: float
    y_m: float
    vx_m_s: float
    vy_m_s: float
    sigma_m: float
    alive: bool


@dataclass
class NeighbourTracker:
    """Newest map-frame poses and velocities of the other robots."""

    robot_id: int
    footprint_m: float
    max_speed_m_s: float
    pending: list[tuple[int, tuple[MapEntry, ...]]] = field(default_factory=list)
    tracks: dict[int, _Track] = field(default_factory=dict)
    adopted_ns: int = -1
    maps_adopted: int = 0
    sighted: dict[int, tuple[int, float, float]] = field(default_factory=dict)  # robot -> (stamp, x, y)

    def saw(self, robot_id: int, x_m: float, y_m: float, stamp_ns: int) -> None:
        """Our own camera put robot ``robot_id`` at (x_m, y_m) (map frame, through our pose) at
        ``stamp_ns``: an obstacle even while the map does not have it (see :data:`SIGHTED_KEEP_S`)."""
        if robot_id != self.robot_id:
            self.sighted[robot_id] = (stamp_ns, x_m, y_m)

    def offer(self, stamp_ns: int, entries: Sequence[MapEntry]) -> None:
        """A received map; older than the one in use, or a repeat, is ignored."""
        if stamp_ns <= self.adopted_ns or any(s == stamp_ns for s, _ in self.pending):
            return
        self.pending.append((stamp_ns, tuple(entries)))
        self.pending.sort(key=lambda p: p[0])
        del self.pending[:-MAX_PENDING]

    def _adopt(self, stamp_ns: int, entries: tuple[MapEntry, ...]) -> None:
        tracks = {}
        for e in sorted(entries, key=lambda e: e.robot_id):
            if e.robot_id == self.robot_id:
                continue
            # the pose's own time: a robot whose odometry reached the server late is that far behind the map
            at_ns = e.pose_time_at(stamp_ns)
            vx = vy = 0.0
            prev = self.tracks.get(e.robot_id)
            if prev is not None and e.alive:
                dt = (at_ns - prev.stamp_ns) / 1e9
                if 0 < dt <= VELOCITY_MAX_DT_S:
                    vx, vy = (e.x_m - prev.x_m) / dt, (e.y_m - prev.y_m) / dt
                    speed = math.hypot(vx, vy)
                    if speed > self.max_speed_m_s:  # a jump of the estimate, not motion
                        vx, vy = vx * self.max_speed_m_s / speed, vy * self.max_speed_m_s / speed
            var = max(e.cov[0], e.cov[4], 0.0) if len(e.cov) == 9 else 0.0
            tracks[e.robot_id] = _Track(at_ns, e.x_m, e.y_m, vx, vy, math.sqrt(var), e.alive)
        self.tracks = tracks
        self.adopted_ns = stamp_ns
        self.maps_adopted += 1

    def where(self, robot_id: int, now_ns: int) -> Neighbour | None:
        """Robot ``robot_id`` predicted to ``now_ns`` from the map in use (none adopted here), or None
        if that map does not have it."""
        tr = self.tracks.get(robot_id)
        return None if tr is None else self._predict(robot_id, tr, now_ns)

    def contradicts(self, robot_id: int, seen_x_m: float, seen_y_m: float, now_ns: int) -> bool:
        """Whether the map in use has robot ``robot_id`` more than :data:`SIGHTING_GATE_M` beyond its
        circle from where a sighting puts it (map frame); False if the map does not have it."""
        n = self.where(robot_id, now_ns)
        return n is not None and math.hypot(seen_x_m - n.x_m, seen_y_m - n.y_m) > n.radius_m + SIGHTING_GATE_M

    def expected(self, me: Pose2, now_ns: int, me_sigma_m: float = 0.0,
                 ) -> dict[tuple[str, int], tuple[float, float, float]]:
        """Where the map in use has the other robots at ``now_ns`` as seen from map pose ``me``
        (position sigma ``me_sigma_m``): (x_m, y_m, radius_m) in our base frame, the radius their
        circle plus :data:`SIGHTING_GATE_M` plus 3 sigma of both positions, uncapped, so a poorly
        known robot or observer decides nothing (for
        :meth:`tagswarm.agents.cubepose.CubePoseEstimator.estimate`)."""
        back = se2_inverse(me)
        out = {}
        for rid, tr in sorted(self.tracks.items()):
            n = self._predict(rid, tr, now_ns)
            x, y, _ = se2_compose(back, (n.x_m, n.y_m, 0.0))
            out[("robot", rid)] = (x, y, n.radius_m + SIGHTING_GATE_M + 3.0 * math.hypot(tr.sigma_m, me_sigma_m))
        return out

    def _predict(self, rid: int, tr: _Track, now_ns: int) -> Neighbour:
        age = min(max((now_ns - tr.stamp_ns) / 1e9, 0.0), MAX_EXTRAPOLATE_S)
        speed = math.hypot(tr.vx_m_s, tr.vy_m_s)
        widen = min(SIGMA_WIDEN * tr.sigma_m, SIGMA_WIDEN_MAX_M) + AGE_WIDEN * speed * age
        return Neighbour(rid, tr.x_m + tr.vx_m_s * age, tr.y_m + tr.vy_m_s * age, tr.vx_m_s, tr.vy_m_s,
                         self.footprint_m + widen)

    def neighbours(self, now_ns: int, usable_until_ns: int | None = None) -> tuple[Neighbour, ...]:
        """The other robots predicted to ``now_ns``, in robot-id order, after adopting every waiting
        map stamped at or before ``usable_until_ns`` (all of them if None)."""
        while self.pending and (usable_until_ns is None or self.pending[0][0] <= usable_until_ns):
            stamp, entries = self.pending.pop(0)
            self._adopt(stamp, entries)
        keep_ns = int(SIGHTED_KEEP_S * 1e9)
        self.sighted = {r: v for r, v in self.sighted.items() if now_ns - v[0] <= keep_ns and r not in self.tracks}
        mapped = [self._predict(rid, tr, now_ns) for rid, tr in self.tracks.items()]
        seen = [Neighbour(r, x, y, 0.0, 0.0, self.footprint_m) for r, (_, x, y) in self.sighted.items()]
        return tuple(sorted(mapped + seen, key=lambda n: n.robot_id))
