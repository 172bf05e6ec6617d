"""The paper's map as a live estimator: ``[server] method = "stitch"`` (pure code, no I/O).

The map is the composition of the *latest* relative observations along the chain of
who-sees-whom from the origin robot (see :mod:`tagswarm.server.stitch`): an observation
(observer o sees target g at ``z`` in o's base frame, time t) places g at
``pose_o(t) ⊕ z``, or o at ``pose_g(t) ⊕ z⁻¹``; between sightings each robot is carried
by its own odometry (``pose(now) = pose(t) ⊕ odom(t)⁻¹ ⊕ odom(now)``).  There is no
factor graph, no gate and no smoothing: the correction pushed to a robot is its
stitched pose, whatever the newest chain says.

After every :meth:`StitchMap.advance` that applied an observation the map is stitched
again from scratch: a search from the roots (the origin robot at its odometry, which
*is* the map frame; or, when the scenario has landmarks, every robot's newest sighting
of each landmark, which places it in the arena frame) over the newest edge of every
pair, cheapest first, where the cost of a placement is the position variance it
gives the robot *now* (so a fresh edge beats a stale one: its odometry since the
sighting adds less).  Edges older than ``memory_s`` are forgotten; a robot no chain
reaches keeps its last placement and its odometry carries it on.

Covariances are propagated along the chain to first order, in the robot's own axes
(GTSAM's tangent convention, as the graph method's): composing ``A ⊕ B`` gives
``Ad(B⁻¹) Σ_A Ad(B⁻¹)ᵀ + Σ_B``, the observation's covariance is moved into that
convention with :func:`~tagswarm.server.noise.tangent_cov`, odometry adds
:func:`~tagswarm.server.noise.odom_increment_cov`.  Frames: map (metres, radians),
times simulation nanoseconds.
"""

from __future__ import annotations

import bisect
import heapq
import math
from collections import Counter, deque
from dataclasses import dataclass, field

import numpy as np

from tagswarm.protocol.geometry import Pose2, se2_between, se2_compose, se2_inverse
from tagswarm.server.fusion import RelocEvent
from tagswarm.server.noise import Cov, FusionParams, odom_increment_cov, tangent_cov

#: odometry samples kept per robot (observations are looked up at their stamp)
ODOM_BUFFER = 4096
#: an observation's stamp is matched to the nearest odometry sample within this (ns)
ODOM_MATCH_NS = 200_000_000
#: covariance of the origin robot's (exact) map frame: keeps every matrix invertible
TINY = 1e-10


def adjoint(p: Pose2) -> Cov:
    """SE(2) adjoint of ``p`` (GTSAM's ``Pose2.AdjointMap``)."""
    c, s = math.cos(p[2]), math.sin(p[2])
    return np.array([[c, -s, p[1]], [s, c, -p[0]], [0.0, 0.0, 1.0]])


def compose_cov(a_cov: Cov, b: Pose2, b_cov: Cov) -> Cov:
    """Covariance of ``A ⊕ B`` (first order, independent A and B, tangent convention)."""
    ad = adjoint(se2_inverse(b))
    return np.asarray(ad @ a_cov @ ad.T + b_cov)


def inverse_tangent_cov(p: Pose2, cov: Cov) -> Cov:
    """Covariance of ``p⁻¹`` given that of ``p``, both in the tangent convention."""
    ad = adjoint(p)
    return np.asarray(ad @ cov @ ad.T)


@dataclass(frozen=True)
class Anchor:
    """Where the stitch put a robot: its map ``pose`` at ``stamp_ns`` (covariance ``cov``),
    when its odometry read ``odom``; ``via`` the robot (or ``-1`` for a landmark, ``None``
    for the origin) whose sighting placed it."""

    stamp_ns: int
    pose: Pose2
    odom: Pose2
    cov: Cov
    via: int | None

    @property
    def map_to_odom(self) -> Pose2:
        return se2_compose(self.pose, se2_inverse(self.odom))


@dataclass(frozen=True)
class Sighting:
    """The newest observation of one pair: ``target`` at ``rel`` in ``observer``'s base frame
    at ``stamp_ns`` (``cov`` in the tangent convention), with both robots' odometry then
    (``target_odom`` is None for a landmark)."""

    stamp_ns: int
    observer: int
    target: int
    rel: Pose2
    cov: Cov
    observer_odom: Pose2
    target_odom: Pose2 | None


@dataclass
class _Robot:
    stamps: deque[int] = field(default_factory=lambda: deque(maxlen=ODOM_BUFFER))
    poses: deque[Pose2] = field(default_factory=lambda: deque(maxlen=ODOM_BUFFER))
    last_distance: float = 0.0
    anchor: Anchor | None = None


@dataclass(order=True)
class _Event:
    stamp_ns: int
    rank: int  # odometry (0) before observations (1) and landmarks (2) of the same instant
    order: tuple[int, ...]
    kind: str = field(compare=False)
    data: tuple = field(compare=False)  # type: ignore[type-arg]


class StitchMap:
    """The paper's stitched map with odometry carry-over (see the module docstring); the
    same interface as :class:`~tagswarm.server.fusion.Fusion`
    (:class:`~tagswarm.server.estimator.Estimator`)."""

    def __init__(self, params: FusionParams, origin_id: int, robot_ids: tuple[int, ...],
                 landmarks: dict[int, Pose2] | None = None, memory_s: float | None = None) -> None:
        self.p = params
        self.origin_id = origin_id
        self.landmarks = dict(landmarks or {})
        self.memory_ns = int((params.lag_s if memory_s is None else memory_s) * 1e9)
        self.counters: Counter[str] = Counter()
        self.robots: dict[int, _Robot] = {rid: _Robot() for rid in robot_ids}
        self.sightings: dict[tuple[int, int], Sighting] = {}  # (observer, target) -> newest
        self.landmark_sightings: dict[tuple[int, int], Sighting] = {}  # (observer, landmark) -> newest
        self.edges: dict[tuple[int, int], int] = {}
        self.watermark_ns = -1
        self._events: list[_Event] = []
        self._order = 0

    def reset(self) -> None:
        """Forget everything: the empty map of the same scenario (a restarted world)."""
        self.__init__(self.p, self.origin_id, tuple(self.robots), self.landmarks,  # type: ignore[misc]
                      self.memory_ns / 1e9)

    # ------------------------------------------------------------------ input
    def _push(self, stamp_ns: int, kind: str, data: tuple) -> None:  # type: ignore[type-arg]
        if kind != "odom" and stamp_ns <= self.watermark_ns - self.p.late_obs_s * 1e9:
            self.counters["rejected_late"] += 1
            return
        ids = (data[0],) if kind == "odom" else (data[0], data[1])
        rank = {"odom": 0, "obs": 1, "landmark": 2}[kind]
        heapq.heappush(self._events, _Event(stamp_ns, rank, (*ids, self._order), kind, data))
        self._order += 1

    def add_odometry(self, rid: int, stamp_ns: int, pose: Pose2, distance_m: float, slip_m: float = 0.0) -> None:
        """Cumulative odometry of ``rid`` (base_link in its odom frame) at ``stamp_ns``."""
        self._push(stamp_ns, "odom", (rid, pose, distance_m))

    def add_observation(self, observer: int, target: int, stamp_ns: int, rel: Pose2, cov: Cov) -> None:
        """``target``'s base in ``observer``'s base frame at ``stamp_ns``; ``cov`` of (x, y, yaw)
        with x, y along the observer's axes (as the agents send it)."""
        self._push(stamp_ns, "obs", (observer, target, rel, np.asarray(cov, float).reshape(3, 3)))

    def add_landmark_observation(self, observer: int, landmark: int, stamp_ns: int, rel: Pose2, cov: Cov) -> None:
        """Landmark ``landmark``'s frame in ``observer``'s base frame."""
        if landmark not in self.landmarks:
            self.counters["rejected_unknown_landmark"] += 1
            return
        self._push(stamp_ns, "landmark", (observer, landmark, rel, np.asarray(cov, float).reshape(3, 3)))

    # ------------------------------------------------------------------ processing
    def latest_odom_ns(self, rid: int) -> int:
        r = self.robots[rid]
        return r.stamps[-1] if r.stamps else -1

    def odom_at(self, rid: int, stamp_ns: int) -> Pose2 | None:
        """Odometry pose of ``rid`` at ``stamp_ns``: the nearest sample within 0.2 s."""
        r = self.robots[rid]
        i = bisect.bisect_left(r.stamps, stamp_ns)
        near = [j for j in (i - 1, i) if 0 <= j < len(r.stamps)]
        if not near:
            return None
        best = min(near, key=lambda j: abs(r.stamps[j] - stamp_ns))
        if abs(r.stamps[best] - stamp_ns) > ODOM_MATCH_NS:
            return None
        return r.poses[best]

    def advance(self, watermark_ns: int) -> int:
        """Apply every queued input stamped at or before ``watermark_ns`` in time order,
        then stitch the map again if an observation came in.  Returns the inputs applied."""
        n = 0
        seen = False
        while self._events and self._events[0].stamp_ns <= watermark_ns:
            ev = heapq.heappop(self._events)
            if ev.kind == "odom":
                self._apply_odom(ev.stamp_ns, *ev.data)
            else:
                seen |= self._apply_obs(ev.stamp_ns, ev.kind == "landmark", *ev.data)
            n += 1
        self.watermark_ns = max(self.watermark_ns, watermark_ns)
        if seen or self._origin_pending():
            self._stitch()
        return n

    def _origin_pending(self) -> bool:
        o = self.robots.get(self.origin_id)
        return not self.landmarks and o is not None and o.anchor is None and bool(o.stamps)

    def _apply_odom(self, stamp_ns: int, rid: int, pose: Pose2, distance_m: float) -> None:
        if rid not in self.robots:
            self.counters["rejected_unknown_robot"] += 1
            return
        r = self.robots[rid]
        if distance_m + 1e-6 < r.last_distance or (r.stamps and stamp_ns <= r.stamps[-1]):
            if distance_m + 1e-6 < r.last_distance:
                # the agent restarted: a new odom frame, so nothing known about the old one holds
                self.counters["odometry_restarts"] += 1
                r.stamps.clear()
                r.poses.clear()
                r.anchor = None
                for key in [k for k in self.sightings if rid in k]:
                    del self.sightings[key]
                for key in [k for k in self.landmark_sightings if k[0] == rid]:
                    del self.landmark_sightings[key]
            else:
                self.counters["odometry_out_of_order"] += 1
                return
        r.last_distance = distance_m
        r.stamps.append(stamp_ns)
        r.poses.append(pose)

    def _apply_obs(self, stamp_ns: int, landmark: bool, observer: int, target: int, rel: Pose2, cov: Cov) -> bool:
        if observer not in self.robots or (not landmark and (target not in self.robots or target == observer)):
            self.counters["rejected_unknown_robot"] += 1
            return False
        oo = self.odom_at(observer, stamp_ns)
        go = None if landmark else self.odom_at(target, stamp_ns)
        if oo is None or (go is None and not landmark):
            self.counters["rejected_no_odometry"] += 1
            return False
        s = Sighting(stamp_ns, observer, target, rel, tangent_cov(rel, cov) + np.eye(3) * TINY, oo, go)
        table = self.landmark_sightings if landmark else self.sightings
        old = table.get((observer, target))
        if old is not None and old.stamp_ns > stamp_ns:
            self.counters["superseded_observations"] += 1  # a late one: the newer sighting stays
            return False
        table[(observer, target)] = s
        if not landmark:
            self.edges[(observer, target)] = stamp_ns
        self.counters["accepted_landmarks" if landmark else "accepted_observations"] += 1
        return True

    # ------------------------------------------------------------------ stitching
    def _carry(self, rid: int, a: Anchor, odom: Pose2) -> tuple[Pose2, Cov]:
        """``rid``'s map pose and covariance when its odometry reads ``odom``, from anchor ``a``."""
        d = se2_between(a.odom, odom)
        return se2_compose(a.pose, d), compose_cov(a.cov, d, odom_increment_cov(d, self.p))

    def _cost(self, rid: int, a: Anchor) -> float:
        """Position variance (m²) the anchor gives ``rid`` now."""
        r = self.robots[rid]
        _, cov = self._carry(rid, a, r.poses[-1])
        return float(cov[0, 0] + cov[1, 1])

    def _roots(self) -> list[tuple[int, Anchor]]:
        out: list[tuple[int, Anchor]] = []
        if self.landmarks:
            for (obs, lm), s in sorted(self.landmark_sightings.items()):
                pose = se2_compose(self.landmarks[lm], se2_inverse(s.rel))
                out.append((obs, Anchor(s.stamp_ns, pose, s.observer_odom, inverse_tangent_cov(s.rel, s.cov), -1)))
            return out
        o = self.robots.get(self.origin_id)
        if o is not None and o.stamps:
            # the origin's map frame is its odom frame (its first pose): exact
            out.append((self.origin_id, Anchor(o.stamps[0], o.poses[0], o.poses[0], np.eye(3) * TINY, None)))
        return out

    def _stitch(self) -> None:
        """Place every robot reachable from a root along the cheapest chain of newest edges."""
        horizon = self.watermark_ns - self.memory_ns
        for table in (self.sightings, self.landmark_sightings):
            for key in [k for k, s in table.items() if s.stamp_ns < horizon]:
                del table[key]
                self.counters["forgotten_edges"] += 1
        adj: dict[int, list[Sighting]] = {}
        for key in sorted(self.sightings):
            s = self.sightings[key]
            adj.setdefault(s.observer, []).append(s)
            adj.setdefault(s.target, []).append(s)
        heap: list[tuple[float, int, int, Anchor]] = []
        tie = 0
        for rid, a in self._roots():
            if self.robots[rid].stamps:
                heapq.heappush(heap, (self._cost(rid, a), tie, rid, a))
                tie += 1
        placed: dict[int, Anchor] = {}
        while heap:
            _, _, rid, a = heapq.heappop(heap)
            if rid in placed:
                continue
            placed[rid] = a
            for s in adj.get(rid, []):
                other = s.target if s.observer == rid else s.observer
                if other in placed or not self.robots[other].stamps:
                    continue
                assert s.target_odom is not None
                mine = s.observer == rid
                here, there = (s.observer_odom, s.target_odom) if mine else (s.target_odom, s.observer_odom)
                pose_t, cov_t = self._carry(rid, a, here)
                if mine:
                    step, step_cov = s.rel, s.cov
                else:
                    step, step_cov = se2_inverse(s.rel), inverse_tangent_cov(s.rel, s.cov)
                b = Anchor(s.stamp_ns, se2_compose(pose_t, step), there, compose_cov(cov_t, step, step_cov), rid)
                heapq.heappush(heap, (self._cost(other, b), tie, other, b))
                tie += 1
        for rid, a in placed.items():
            self.robots[rid].anchor = a
        self.counters["stitches"] += 1
        self.counters["stitch_unreached"] += sum(1 for rid, r in self.robots.items()
                                                 if rid not in placed and r.anchor is not None)

    # ------------------------------------------------------------------ output
    def pose(self, rid: int) -> tuple[Pose2, Cov] | None:
        """Stitched map pose of ``rid`` now (its anchor carried by odometry) and its (3, 3)
        covariance; None if no chain ever reached it."""
        r = self.robots[rid]
        if r.anchor is None or not r.poses:
            return None
        return self._carry(rid, r.anchor, r.poses[-1])

    def in_dispute(self, rid: int) -> bool:
        """Never: the paper's stitching has no gate, so nothing contradicts it."""
        return False

    def map_to_odom(self, rid: int) -> Pose2 | None:
        """The ``map -> odom_rid`` correction: anchor pose ⊕ (its odometry pose)⁻¹."""
        a = self.robots[rid].anchor
        return None if a is None else a.map_to_odom

    def last_fix_ns(self, rid: int) -> int:
        a = self.robots[rid].anchor
        return -1 if a is None else a.stamp_ns

    def localised(self) -> list[int]:
        return [rid for rid, r in self.robots.items() if r.anchor is not None]

    def take_relocalisations(self) -> list[RelocEvent]:
        """Always empty: the stitch has no notion of a contradiction, a kidnapped robot is
        simply placed wherever the newest chain puts it."""
        return []
