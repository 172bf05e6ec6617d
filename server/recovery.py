"""Recovery from gross error: re-localising a pushed, slipping or kidnapped robot (pure logic).

The fusion's χ² gate compares each observation with the current estimate of the
two robots involved.  Once a robot's estimate is wrong by more than the gate
(it was pushed, its wheels slipped against an obstacle, it was carried away),
every true observation of it fails the gate, and a gate alone would reject them
forever.  Here the rejected observations are kept as *evidence* and judged by
their consistency with each other, as pairwise consistency maximisation (PCM,
Mangelson et al. 2018; Kimera-Multi) does for loop closures:

- every rejected observation between robots ``a`` and ``b`` is evidence about
  both: "``b`` is where ``a`` sees it" (witness ``a``) and "``a`` is where ``b``
  says" (witness ``b``).  Each piece of evidence is expressed as the map pose of
  the suspect's *odometry origin* (placed pose ⊕ odometry⁻¹), so evidence from
  different instants compares directly while the suspect moves on odometry;
- only a *trusted* witness gives evidence: a landmark, the origin robot, or a
  robot that agrees with a third robot (an accepted observation with somebody
  other than the suspect within ``reloc_trust_s``), or a robot far surer of where it puts
  the suspect than the suspect is of itself (its σ there, heading levered by the range,
  under ``reloc_trust_sigma_ratio`` of the suspect's).  A robot that is wrong itself
  therefore cannot drag its observers along.
  The second rule is for two robots out of everyone's view: neither agrees with a third,
  yet one may have been seen a moment ago and the other not for many seconds (measured in
  the hall, seed 2: a robot 22-30 cm off for 8 s saw two robots whose estimates were right
  to 4-9 cm, σ 10-15 cm against its own 20-25 cm, and their views did not count);
- the evidence about a suspect forms a consistent set when enough of it agrees
  (the same median test that places a robot the first time:
  :func:`tagswarm.server.placement.choose`): at least ``reloc_min`` pieces from two or more
  witnesses spread over ``reloc_span_many_s``, or ``reloc_min_single`` pieces spread over
  ``reloc_span_s`` from one witness (the same anchored observer, again and again).  The
  span is the time a copy has to give itself away: until the robot is seen where the map
  has it again, a copy of its cube looks exactly like the robot carried away (measured:
  robots turning to look around glimpsed a copy cube for 0.2 s, two witnesses, and won two
  re-localisations of a robot nobody saw in those 0.2 s).  A witness and the suspect that
  see each other where the evidence says need only ``reloc_span_mutual_s``: a copy of a cube
  has no camera, so the suspect's own views of the witness cannot come from one (measured:
  the kidnap scene's teleported robot, facing the origin robot, back in 0.6 s instead of 1.1 s);
- accepted observations of the suspect during that time are counter-evidence:
  a robot that is still seen where the map has it (a decoy tag of its ID on a
  wall, a spoofed stream) is not moved while more than a third as many
  observations keep agreeing with its estimate;
- a robot cannot be in two places: evidence older than an accepted observation
  of the suspect is void (it was seen where the map has it after that) where that
  observation's own placement of the suspect rules the evidence out, and if
  the voided evidence agreed on one place, that place is remembered as a *decoy
  site* of the suspect (a copy of its cube, a poster of its tag): later evidence
  that puts it there again is dropped for the rest of the run.  Measured on the
  copy-cube scene: the origin robot saw a static copy of a patrolling robot every
  frame, and without this rule the copy won six re-localisations;
- the move must be significant: the consensus of the agreeing evidence (their
  mean, weighted by certainty) must differ from the suspect's estimate by more
  than both can be wrong together (3 σ in position, or more than
  ``reloc_min_turn_rad`` in yaw).  Each piece's spread is the measurement's plus its
  witness's own uncertainty carried to the suspect, heading levered by the range
  (:func:`tagswarm.server.noise.relative_cov`): a witness whose heading drifted 9° while it
  turned on the spot otherwise re-localised a correctly placed robot 5.5 m away 0.84 m the
  wrong way on 12 views that agreed only because they shared that heading.  Far observations lever the yaw error by the
  range, so several of them can agree on a pose tens of centimetres off; a
  robot 10 cm off would otherwise be re-localised 25 cm the other way (measured
  in a 10-robot hall).  Such a set does not move the robot: its observation is
  *admitted* as an ordinary (robust) factor instead (``reloc_admit``), so the graph
  weighs it against everything else it knows.  Without that, a robot whose heading
  was 8° off kept rejecting 3.6 s of 1 cm-accurate views of the origin robot, and
  its error grew from 12 to 20 cm until the origin saw it (hall, seed 0).

A single wrong observation, a mis-decoded tag or a spoofed one never forms a
consistent set, so it stays rejected.  The origin robot is never re-localised:
its first pose *is* the map frame.
"""

from __future__ import annotations

import math
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from tagswarm.protocol.geometry import Pose2, se2_compose, se2_inverse
from tagswarm.server.noise import Cov, FusionParams, inverse_cov, relative_cov
from tagswarm.server.placement import Candidate, choose

LANDMARK_WITNESS = -1


def witness_of(suspect: int, cand: Candidate) -> int:
    """The robot whose estimate (or the landmark whose known pose) produced ``cand``."""
    meas = cand.meas
    if len(meas) != 4:
        return LANDMARK_WITNESS
    observer, target = meas[0], meas[1]
    return int(target if observer == suspect else observer)


class View(NamedTuple):
    """What one observation says of one of its two robots (the suspect): ``cand`` puts the
    suspect's odometry origin in the map (its spread: the measurement's plus the witness's own
    position and heading levered by the range); ``odom`` is the suspect's odometry pose then,
    ``now`` its estimated map pose then, ``witness_var_m2`` the witness's share of the spread per axis."""

    suspect: int
    cand: Candidate
    odom: Pose2
    now: Pose2
    witness_var_m2: float


def views(observer: int, target: int, stamp_ns: int, rel: Pose2, cov: Cov, po: Pose2, pg: Pose2,
          oo: Pose2, go: Pose2, cov_o: Cov, cov_g: Cov) -> tuple[View, View]:
    """The observation ``rel`` (target in the observer's frame, covariance ``cov``) as a view of
    the target (witness: the observer) and of the observer (witness: the target); ``po``/``pg``
    are their estimated map poses, ``oo``/``go`` their odometry poses, ``cov_o``/``cov_g`` their
    tangent-space covariances (3, 3)."""
    meas = (observer, target, rel, cov)
    inv = inverse_cov(rel, cov)
    # where a witness puts the suspect is as uncertain as the witness's own position plus its heading
    # levered by the range: a robot 5.5 m away seen by one whose heading had drifted 9 deg while it
    # turned on the spot was re-localised 0.84 m the wrong way on 12 "agreeing" views (static trial 16)
    zero = np.zeros((3, 3))
    w_o = float(np.trace(relative_cov(rel, cov_o, zero)[:2, :2]))
    w_g = float(np.trace(relative_cov(se2_inverse(rel), cov_g, zero)[:2, :2]))
    placed_g, placed_o = se2_compose(po, rel), se2_compose(pg, se2_inverse(rel))
    return (View(target, Candidate(stamp_ns, se2_compose(placed_g, se2_inverse(go)), float(cov[0, 0] + cov[1, 1]) + w_o,
                                   meas), go, pg, w_o / 2),
            View(observer, Candidate(stamp_ns, se2_compose(placed_o, se2_inverse(oo)),
                                     float(inv[0, 0] + inv[1, 1]) + w_g, meas), oo, po, w_g / 2))


# where an accepted observation put a robot: (odometry origin in the map, its variance m² per axis, the
# robot's odometry pose then); None where it is not known (a landmark's view, a snapshot of an older version)
Place = tuple[Pose2, float, Pose2] | None


def consensus(agree: list[Candidate], odom: Pose2) -> Pose2:
    """Where the evidence ``agree`` puts its suspect when its odometry reads ``odom``
    (map frame): each piece carried there, weighted by its certainty (circular mean of yaw)."""
    now = [se2_compose(c.origin, odom) for c in agree]
    w = np.array([1.0 / max(c.trace / 2, 1e-6) for c in agree])
    mean = (w[:, None] * np.array([p[:2] for p in now])).sum(axis=0) / w.sum()
    yaw = math.atan2(float((w * np.sin([p[2] for p in now])).sum()), float((w * np.cos([p[2] for p in now])).sum()))
    return float(mean[0]), float(mean[1]), yaw


@dataclass
class Verdict:
    """A consistent set of evidence that moves ``suspect``: the agreeing candidates
    (the best first) and the distinct witnesses behind them."""

    suspect: int
    agree: list[Candidate]
    witnesses: tuple[int, ...]
    #: the set is consistent but its move is not significant: admit the observation as a factor, do not jump
    admit: bool = False


@dataclass
class Recovery:
    """Evidence against each robot's estimate, and who agrees with whom lately."""

    p: FusionParams
    origin_id: int
    anchored_origin: bool  # the origin robot holds the map frame (no landmarks)
    # contradicting evidence per suspect; robot-pair and landmark evidence kept apart, since each re-places the
    # robot through its own path (a robot pair's factor, or a landmark prior)
    robot_ev: dict[int, list[Candidate]] = field(default_factory=dict)
    landmark_ev: dict[int, list[Candidate]] = field(default_factory=dict)
    # (stamp_ns, other robot or LANDMARK_WITNESS) of observations accepted lately, per robot
    partners: dict[int, deque[tuple[int, int]]] = field(default_factory=dict)
    # map position (x_m, y_m) where each piece of robot-pair evidence puts the suspect, by stamp_ns
    where: dict[int, dict[int, tuple[float, float]]] = field(default_factory=dict)
    # places where a robot's identity was seen while the map had it elsewhere (x_m, y_m), per robot
    decoy_sites: dict[int, list[tuple[float, float]]] = field(default_factory=dict)
    # (stamp_ns, place) of each robot's accepted observations lately, alongside ``partners``
    seen_at: dict[int, deque[tuple[int, Place]]] = field(default_factory=dict)
    # (stamp_ns, other robot) of each robot's observations lately that contradicted the map (gated out, or
    # surprising), alongside ``partners``
    disputes: dict[int, deque[tuple[int, int]]] = field(default_factory=dict)
    # (stamp_ns, witness, metres) how far each of those put the robot from its estimate
    shifts: dict[int, deque[tuple[int, int, float]]] = field(default_factory=dict)
    counters: Counter[str] = field(default_factory=Counter)  # the fusion's

    def accepted(self, a: int, b: int, stamp_ns: int, seen: tuple[View, ...] = ()) -> None:
        """An observation between ``a`` and ``b`` (``b`` = LANDMARK_WITNESS for a landmark) passed the
        gate; ``seen``: what it says of each robot (:func:`views`)."""
        by = {v.suspect: v for v in seen}
        for x, y in ((a, b), (b, a)):
            if x == LANDMARK_WITNESS:
                continue
            q = self.partners.setdefault(x, deque(maxlen=256))
            q.append((stamp_ns, y))
            v = by.get(x)
            place: Place = None if v is None else (v.cand.origin, v.cand.trace / 2, v.odom)
            self.seen_at.setdefault(x, deque(maxlen=256)).append((stamp_ns, place))
            self._void(x, stamp_ns, place)

    def disputed(self, a: int, b: int, stamp_ns: int) -> None:
        """An observation between robots ``a`` and ``b`` contradicted the map (gated out, or surprising)."""
        for x, y in ((a, b), (b, a)):
            self.disputes.setdefault(x, deque(maxlen=256)).append((stamp_ns, y))

    def doubtful(self, witness: int, stamp_ns: int) -> bool:
        """Whether ``witness`` disagrees lately with two or more robots and with nobody else agrees:
        one move of its own explains all its contradictions, where believing it would move each of the
        others.  Measured in a yard of 10 robots: a station-holding robot pushed 16 cm and turned 0.1
        rad, sure of itself to 5 mm, re-localised the three robots it saw 0.36-0.43 m the wrong way
        (each with its own repeated views), and stayed 16 cm off itself.  The origin robot holding the
        map frame and landmarks are never in doubt."""
        if witness == LANDMARK_WITNESS or (witness == self.origin_id and self.anchored_origin):
            return False
        horizon = stamp_ns - int(self.p.reloc_window_s * 1e9)
        recent = [(t, o) for t, o in self.disputes.get(witness, ()) if horizon <= t <= stamp_ns]
        if len({o for _, o in recent}) < 2:
            return False
        since = min(t for t, _ in recent)
        return not any(since <= t <= stamp_ns for t, _ in self.partners.get(witness, ()))

    def lone_pair(self, witness: int, suspect: int, stamp_ns: int) -> bool:
        """Whether ``witness`` and ``suspect`` disagree lately with each other only and the witness agrees
        with nobody since: either of them may have moved, so neither judges the other until a third
        robot (or the origin, or a landmark) does.  Measured in the yard of :meth:`doubtful` with honest
        view covariances: after the push the witness saw only one robot, which nobody else saw then,
        and re-localised it 0.36 m the wrong way (2026-12-07)."""
        horizon = stamp_ns - int(self.p.reloc_window_s * 1e9)
        mine = [(t, o) for t, o in self.disputes.get(witness, ()) if horizon <= t <= stamp_ns]
        theirs = {o for t, o in self.disputes.get(suspect, ()) if horizon <= t <= stamp_ns}
        if {o for _, o in mine} != {suspect} or theirs != {witness}:
            return False
        since = min(t for t, _ in mine)
        return not any(since <= t <= stamp_ns for t, _ in self.partners.get(witness, ()))

    def shifted(self, suspect: int, witness: int, stamp_ns: int, shift_m: float) -> None:
        """A contradicting observation (gated out, or surprising) puts ``suspect`` ``shift_m`` metres
        from its estimate, as ``witness`` sees it."""
        self.shifts.setdefault(suspect, deque(maxlen=256)).append((stamp_ns, witness, shift_m))

    def in_dispute(self, rid: int, stamp_ns: int) -> bool:
        """Whether two or more of the observations of (or by) ``rid`` within ``reloc_window_s`` before
        ``stamp_ns`` put it more than ``dispute_shift_m`` from its estimate and none passed the gate
        since the first of them: its position is in question until the evidence is judged (a
        re-localisation, a loosened odometry) or an observation agrees with it again.  Measured in
        the kidnap scene: the map kept a robot carried 1 m where it had been for the 1.1 s the
        evidence needs, its views rejected from the first frame.  A robot turned on the spot is
        not in dispute (its place is right).  The origin robot holding the map frame never is."""
        if rid == self.origin_id and self.anchored_origin:
            return False
        horizon = stamp_ns - int(self.p.reloc_window_s * 1e9)
        recent = [t for t, _, shift in self.shifts.get(rid, ())
                  if horizon <= t <= stamp_ns and shift > self.p.dispute_shift_m]
        if len(recent) < 2:
            return False
        since = min(recent)
        return not any(since <= t <= stamp_ns for t, _ in self.partners.get(rid, ()))

    def _contradicts(self, place: Place, c: Candidate) -> bool:
        """Whether an accepted observation that put its robot at ``place`` rules out the evidence ``c``
        (both carried to the robot's odometry pose of that observation).  A view that cannot tell the
        two places apart rules out nothing: a robot nudged 15 cm still saw the origin robot 2.5 m away
        as it expected (its own heading sigma levered by the range covers the shift), and that view,
        counted as "seen where the map has it", voided the origin's views of the nudge and made the
        robot's true place a decoy site."""
        if place is None:
            return True
        origin, var_m2, odom = place
        x, y, _ = se2_compose(origin, odom)
        cx, cy, _ = se2_compose(c.origin, odom)
        # each spread's whole trace, not its per-axis mean: a far view's is nearly all sideways (its heading
        # levered by the range), and a 2.5-sigma sideways view 2.5 m away ruled out its robot's true place
        return math.hypot(x - cx, y - cy) > 3 * math.sqrt(2 * var_m2 + c.trace)

    def _void(self, rid: int, stamp_ns: int, place: Place = None) -> None:
        """``rid`` was seen where the map has it at ``stamp_ns``, at ``place``: its older robot-pair
        evidence that this rules out is void, and the place it agreed on becomes a decoy site."""
        ev = self.robot_ev.get(rid)
        if not ev or min(c.stamp_ns for c in ev) > stamp_ns:
            return
        where = self.where.get(rid, {})
        void = {id(c) for c in ev if c.stamp_ns <= stamp_ns and self._contradicts(place, c)}
        if not void:
            return
        old = [where[c.stamp_ns] for c in ev if id(c) in void and c.stamp_ns in where]
        kept = [c for c in ev if id(c) not in void]
        self.counters["reloc_evidence_void"] += len(ev) - len(kept)
        self.robot_ev[rid] = kept
        self.where[rid] = {c.stamp_ns: where[c.stamp_ns] for c in kept if c.stamp_ns in where}
        if len(old) >= 2:
            pts = np.array(old)
            med = np.median(pts, axis=0)
            if float(np.max(np.hypot(*(pts - med).T))) < self.p.init_agree_m:
                sites = self.decoy_sites.setdefault(rid, [])
                if not any(math.dist(med, s) < self.p.init_agree_m for s in sites):
                    sites.append((float(med[0]), float(med[1])))
                    del sites[:-16]

    def at_decoy_site(self, rid: int, x_m: float, y_m: float) -> bool:
        """Whether (x_m, y_m) in the map is a remembered decoy site of ``rid``."""
        return any(math.hypot(x_m - sx, y_m - sy) < self.p.init_agree_m for sx, sy in self.decoy_sites.get(rid, ()))

    def trusted(self, witness: int, suspect: int, stamp_ns: int,
                variances: tuple[float, float] | None = None) -> bool:
        """Whether ``witness``'s estimate may judge ``suspect`` at ``stamp_ns``; ``variances``:
        the position variance (m², per axis) of the witness's and of the suspect's estimate."""
        if witness == LANDMARK_WITNESS:
            return True
        if witness == self.origin_id and self.anchored_origin:
            return True
        if self.doubtful(witness, stamp_ns) or self.lone_pair(witness, suspect, stamp_ns):
            return False
        if variances is not None and variances[0] < self.p.reloc_trust_sigma_ratio**2 * variances[1]:
            return True
        horizon = stamp_ns - int(self.p.reloc_trust_s * 1e9)
        return any(t >= horizon and other != suspect for t, other in self.partners.get(witness, ()))

    def _counter_evidence(self, suspect: int, since_ns: int, best: Candidate) -> int:
        return sum(1 for t, place in self.seen_at.get(suspect, ()) if t >= since_ns and self._contradicts(place, best))

    def add(self, suspect: int, cand: Candidate, landmark: bool = False,
            current: tuple[Pose2, Pose2, float] | None = None, witness_var_m2: float | None = None) -> Verdict | None:
        """Record one piece of contradicting evidence about ``suspect``; a verdict if
        the evidence now forms a consistent set that should re-localise it.
        ``current``: the suspect's estimated map pose at ``cand``'s instant, its odometry
        pose then and the variance (m², per axis) of its position, to judge whether the
        move is significant; ``witness_var_m2``: that of the witness's position."""
        if suspect == self.origin_id and self.anchored_origin:
            return None
        witness = witness_of(suspect, cand)
        variances = None if current is None or witness_var_m2 is None else (witness_var_m2, current[2])
        if not self.trusted(witness, suspect, cand.stamp_ns, variances):
            return None
        store = self.landmark_ev if landmark else self.robot_ev
        horizon = cand.stamp_ns - int(self.p.reloc_window_s * 1e9)
        if any(t >= cand.stamp_ns and self._contradicts(place, cand) for t, place in self.seen_at.get(suspect, ())):
            self.counters["reloc_evidence_void"] += 1  # the suspect was seen where the map has it after this
            return None
        ev = [c for c in store.get(suspect, []) if c.stamp_ns >= horizon]
        if not landmark and current is not None:
            x, y, _ = se2_compose(cand.origin, current[1])
            if self.at_decoy_site(suspect, x, y):
                self.counters["reloc_decoy_site"] += 1
                return None
            where = self.where.setdefault(suspect, {})
            where[cand.stamp_ns] = (x, y)
            for t in [t for t in where if t < horizon]:
                del where[t]
        ev.append(cand)
        store[suspect] = ev
        need = min(self.p.reloc_min, self.p.reloc_min_single)
        if len(ev) < need:
            return None
        # evidence a witness gave before it fell into doubt does not count while it is in doubt
        doubt = {w for w in {witness_of(suspect, c) for c in ev} if self.doubtful(w, cand.stamp_ns)}
        usable = [c for c in ev if witness_of(suspect, c) not in doubt] if doubt else ev
        if len(usable) < need:
            return None
        chosen = choose(usable, self.p)
        if chosen is None:
            return None
        best, agree = chosen
        witnesses = tuple(sorted({witness_of(suspect, c) for c in agree}))
        first = min(c.stamp_ns for c in agree)
        span_s = (max(c.stamp_ns for c in agree) - first) / 1e9
        many = len(agree) >= self.p.reloc_min and len(witnesses) >= 2 and span_s >= self.p.reloc_span_many_s
        repeated = len(agree) >= self.p.reloc_min_single and span_s >= self.p.reloc_span_s
        if not (many or repeated or (landmark and len(agree) >= self.p.reloc_min)
                or (self._mutual(suspect, agree) and span_s >= self.p.reloc_span_mutual_s)):
            return None
        if self._counter_evidence(suspect, first, best) * 3 > len(agree):
            return None
        admit = current is not None and not self.significant(agree, len(witnesses), *current)
        if admit and not self.p.reloc_admit:
            return None
        return Verdict(suspect, [best, *(c for c in agree if c is not best)], witnesses, admit=admit)

    def _mutual(self, suspect: int, agree: list[Candidate]) -> bool:
        """Whether ``agree`` holds at least ``reloc_min`` pieces, two or more of them each way between the
        suspect and one witness: the witness sees the suspect where the suspect's own view of the witness
        puts it (see the module docstring)."""
        if len(agree) < self.p.reloc_min:
            return False
        seen_by: Counter[int] = Counter()
        sees: Counter[int] = Counter()
        for c in agree:
            if len(c.meas) == 4:
                observer, target = c.meas[0], c.meas[1]
                if target == suspect:
                    seen_by[observer] += 1
                else:
                    sees[target] += 1
        return any(n >= 2 and sees[w] >= 2 for w, n in seen_by.items())

    def significant(self, agree: list[Candidate], n_witnesses: int, pose: Pose2, odom: Pose2, var_m2: float) -> bool:
        """Whether the consensus of ``agree`` is far enough from the estimated ``pose``
        (map frame, position variance ``var_m2`` per axis) to move the robot; ``odom`` is
        its odometry pose of that instant, which carries each piece of evidence there."""
        mean_x, mean_y, yaw = consensus(agree, odom)
        # observations from one witness share its error (its own pose, the same tag), so the
        # consensus is only as certain as its median piece over the number of witnesses
        var_cons = float(np.median([c.trace / 2 for c in agree])) / n_witnesses
        floor = self.p.gate_floor_m
        dist = math.hypot(mean_x - pose[0], mean_y - pose[1])
        turn = abs(math.remainder(yaw - pose[2], math.tau))
        return dist > 3 * math.sqrt(var_cons + var_m2 + floor**2) or turn > self.p.reloc_min_turn_rad

    def forget(self, rid: int) -> None:
        """After ``rid`` was re-localised: its evidence is used up, and evidence that
        came from its old (wrong) estimate about others is void."""
        self.robot_ev.pop(rid, None)
        self.landmark_ev.pop(rid, None)
        self.partners.pop(rid, None)
        self.seen_at.pop(rid, None)
        self.where.pop(rid, None)
        self.disputes.pop(rid, None)
        self.shifts.pop(rid, None)
        for other, q in self.disputes.items():
            # the contradictions with its old (wrong) estimate are explained
            self.disputes[other] = deque(((t, o) for t, o in q if o != rid), maxlen=256)
        for other, sq in self.shifts.items():
            self.shifts[other] = deque(((t, w, d) for t, w, d in sq if w != rid), maxlen=256)
        for store in (self.robot_ev,):
            for other, ev in list(store.items()):
                kept = [c for c in ev if witness_of(other, c) != rid]
                if kept:
                    store[other] = kept
                else:
                    del store[other]
