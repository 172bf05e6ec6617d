"""What :class:`~tagswarm.server.fusion.Fusion` does with an observation that contradicts
its estimate (pure code, no I/O).

The observation becomes evidence about both robots (:mod:`tagswarm.server.recovery`
judges it); a consistent set either loosens a robot moved a little without its wheels
knowing (:func:`disturbed`) or takes it out of the map to be placed again
(:func:`unplace`), and a re-placement is queued as a :class:`RelocEvent`.  Poses are
in the map frame (metres, radians) unless named odometry poses (the robot's own odom
frame); times are simulation ns.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from tagswarm.protocol.geometry import Pose2, se2_between, se2_compose
from tagswarm.server.keyframes import KeyframeGraph, PairView, Robot
from tagswarm.server.noise import Cov
from tagswarm.server.placement import Candidate
from tagswarm.server.recovery import Recovery, Verdict, consensus, views


@dataclass(frozen=True)
class RelocEvent:
    """A robot re-localised from a consistent set of contradicting observations:
    map poses before and after at ``stamp_ns``, the witnesses (robot ids,
    ``-1`` for a landmark) and how many observations agreed."""

    stamp_ns: int
    robot_id: int
    before: Pose2
    after: Pose2
    evidence: int
    observers: tuple[int, ...]

    @property
    def jump_m(self) -> float:
        return math.dist(self.before[:2], self.after[:2])


def contradiction(robots: Mapping[int, Robot], recovery: Recovery, init: dict[int, list[Candidate]], observer: int,
                  target: int, stamp_ns: int, rel: Pose2, cov: Cov, po: Pose2, pg: Pose2, oo: Pose2,
                  go: Pose2) -> Verdict | None:
    """A gated-out observation as evidence about both robots (see
    :mod:`tagswarm.server.recovery`); the verdict if it completes a consistent set.
    ``po``/``pg`` are the observer's and the target's map poses at ``stamp_ns``,
    ``oo``/``go`` their odometry poses; ``init`` the fusion's placement candidates."""
    var = {rid: float(robots[rid].cov[0, 0] + robots[rid].cov[1, 1]) / 2 for rid in (observer, target)}
    recovery.disputed(observer, target, stamp_ns)
    seen = views(observer, target, stamp_ns, rel, cov, po, pg, oo, go, robots[observer].cov,
                 robots[target].cov)
    for v in seen:
        placed = se2_compose(v.cand.origin, v.odom)
        if not recovery.at_decoy_site(v.suspect, placed[0], placed[1]):  # a known copy disputes nothing
            recovery.shifted(v.suspect, target if v.suspect == observer else observer, stamp_ns,
                             math.dist(placed[:2], v.now[:2]))
    for v in seen:
        verdict = recovery.add(v.suspect, v.cand, current=(v.now, v.odom, var[v.suspect]),
                               witness_var_m2=v.witness_var_m2)
        if verdict is not None:
            if not verdict.admit:
                # initial_pose (placement) adds the triggering observation itself
                init[v.suspect] = [c for c in verdict.agree if c is not v.cand]
            return verdict
    return None


def disturbed(graph: KeyframeGraph, counters: Counter[str], pair_factors: dict[tuple[int, int], PairView],
              verdict: Verdict, stamp_ns: int, now: Pose2, odom: Pose2) -> None:
    """The suspect of an admitted ``verdict`` was moved a little without its wheels knowing (nudged,
    turned on the spot, slipped): a new keyframe whose odometry from the last one is loosened by the
    move the evidence calls for, so the views after the move are not outweighed by the views before
    it, which the odometry would otherwise carry over as if nothing had happened.  Measured: a
    standing robot seen by three, turned 0.15 rad on the spot, kept 0.13 rad of it for 7 s with
    the admitted views alone.  ``now``/``odom``: its map and odometry pose at ``stamp_ns``;
    ``pair_factors`` the fusion's newest factor of each pair."""
    rid = verdict.suspect
    r = graph.robots[rid]
    if r.kf_key is None or stamp_ns <= r.kf_stamp:
        return  # a late view, or a keyframe at this very instant: its factors already hang on it
    e = se2_between(now, consensus(verdict.agree, odom))
    graph.new_keyframe(rid, stamp_ns, odom, disturbed=np.diag(np.square(e)))
    counters["disturbances"] += 1
    # the views since the move repeat what the pairs' newest factors say, but those hang on keyframes
    # before the loosened link: let the next view of each pair add its factor on this side of it
    for pair in [pair for pair in pair_factors if rid in pair]:
        del pair_factors[pair]


def unplace(robots: Mapping[int, Robot], recovery: Recovery, counters: Counter[str], rid: int,
            verdict: Verdict) -> None:
    """Take ``rid`` out of the map to be placed again: a new chain of keyframes (no
    odometry factor across the jump), the gate off until it is established again."""
    r = robots[rid]
    r.chain += 1
    r.kf_key, r.kf_index, r.estimate = None, -1, None
    r.accepted = 0
    recovery.forget(rid)
    counters["relocalisations"] += 1
    counters["relocalisation_evidence"] += len(verdict.agree)


def note_relocalisation(relocalisations: list[RelocEvent], verdict: Verdict, stamp_ns: int, before: Pose2,
                        after: Pose2) -> None:
    """Queue the re-placement of ``verdict``'s suspect (map poses ``before`` and ``after``)."""
    ev = RelocEvent(stamp_ns, verdict.suspect, before, after, len(verdict.agree), verdict.witnesses)
    relocalisations.append(ev)
