"""Fusion checkpoints: the whole state of a :class:`~tagswarm.server.fusion.Fusion` as bytes, and back.

A checkpoint lets a restarted server skip the journal records before it (see
:mod:`tagswarm.server.journal`).  It is a *full* snapshot, not a summary: the smoother's
factor graph (odometry, observation and prior factors of the lag window, and the
``LinearContainerFactor`` marginals of what was marginalised), its linearisation
point and key timestamps, in GTSAM's own serialisation (boost text archive, doubles
printed with 17 significant digits, so they read back bit-exact), plus the Python
side of the fusion: per-robot keyframe/odometry bookkeeping, queued events,
placement candidates, edges, watermark and counters.

:func:`restore` rebuilds a fusion from a snapshot by feeding the saved graph to a
fresh :class:`~tagswarm.server.smoother.FixedLagSmoother` (one batch update from the saved
linearisation point, at the same phase of iSAM2's relinearisation schedule).  Its
Bayes tree and partial-relinearisation state are not carried over, so it is not
always bit-identical to the smoother that was saved; the server therefore restores
its *own* fusion from every checkpoint it writes: live and replayed fusions go
through the same restore and stay identical (same decisions, same estimates), and
the live fusion stays within ~1 mm of one that was never restored (measured in
bench/journal.py: at most 0.4 mm over 600 s of 4 robots, 1.1 mm over 60 s of 16 robots).

Odometry history is trimmed to what later inputs can still ask for: observations
are only accepted after the watermark, and placement candidates live
``init_window_s``, so samples older than that (plus a margin) are never read.

Encoding: msgpack (msgspec) of :class:`FusionState`, zlib-compressed.  The blob is
opaque to :mod:`tagswarm.server.journal_format` (a ``bytes`` field of the Checkpoint record).

This module reads and writes the fusion's private state on purpose: it is the
fusion's persistence, kept out of fusion.py only for size.  A field added to
``Fusion`` or ``Robot`` (server/keyframes.py) must be added here too (tests/unit/server/test_checkpoint.py
compares a restored fusion with the live one at every update).
"""

from __future__ import annotations

import zlib
from collections import deque
from typing import Final, Literal

import gtsam
import msgspec
import numpy as np

from tagswarm.protocol.errors import TagswarmError
from tagswarm.protocol.geometry import Pose2
from tagswarm.server import odomcal, rangebias
from tagswarm.server.fusion import Fusion, _Event
from tagswarm.server.keyframes import PairView, Robot
from tagswarm.server.placement import Candidate
from tagswarm.server.smoother import FixedLagSmoother

P3 = tuple[float, float, float]
# odometry kept before the watermark beyond the placement window: odom_at tolerates 0.2 s
ODOM_MARGIN_S: Final = 1.0
ZLIB_LEVEL: Final = 1


class CheckpointError(TagswarmError, ValueError):
    """A snapshot blob that does not decode (never raised for a journal that passed its CRC
    unless the writer was a different version)."""


class RobotState(msgspec.Struct, frozen=True, array_like=True):
    """One robot's bookkeeping (see ``tagswarm.server.keyframes.Robot``); covariances row-major (9)."""

    odom: list[tuple[int, float, float, float]]  # (stamp_ns, x_m, y_m, yaw_rad) in the robot's odom frame
    chain: int
    kf_index: int
    kf_key: int | None
    kf_stamp: int
    kf_odom: P3
    estimate: P3 | None
    cov: tuple[float, ...]
    drift_cov: tuple[float, ...]
    latest_odom: tuple[int, float, float, float] | None
    last_fix_ns: int
    accepted: int
    last_distance: float
    reset_hint: P3 | None
    slip_m: float = 0.0
    kf_slip_m: float = 0.0
    # odometry calibration (absent in older snapshots): key, generation, estimate (3), covariance (9, or none)
    cal_key: int | None = None
    cal_gen: int = 0
    cal: P3 = (0.0, 0.0, 0.0)
    cal_cov: tuple[float, ...] = ()


class EventState(msgspec.Struct, frozen=True, array_like=True):
    """A queued (not yet applied) input: ``ints`` are the robot/landmark ids, ``floats``
    the pose and distance (odometry) or relative pose and row-major covariance."""

    stamp_ns: int
    rank: int
    order: tuple[int, ...]
    kind: Literal["odom", "obs", "landmark"]
    ints: tuple[int, ...]
    floats: tuple[float, ...]


class CandidateState(msgspec.Struct, frozen=True, array_like=True):
    """A first-placement candidate; ``kind`` says which measurement shape ``meas`` had."""

    stamp_ns: int
    origin: P3
    trace: float
    kind: Literal["robot", "landmark"]
    ints: tuple[int, ...]  # (observer, target) for a robot pair, () for a landmark
    floats: tuple[float, ...]  # relative pose (robot) or map pose (landmark), then covariance (9)


class FusionState(msgspec.Struct, frozen=True, kw_only=True):
    """Everything a :class:`Fusion` holds beyond its constructor arguments."""

    robots: dict[int, RobotState]
    events: list[EventState]
    order: int
    counters: dict[str, int]
    edges: list[tuple[int, int, int]]  # (observer, target, last stamp_ns), in insertion order
    watermark_ns: int
    updates: int
    next_cov_ns: int
    init: dict[int, list[CandidateState]]
    # re-localisation evidence (server/recovery.py): contradicting candidates per suspect, accepted partners
    reloc_robot: dict[int, list[CandidateState]] = {}
    reloc_landmark: dict[int, list[CandidateState]] = {}
    partners: dict[int, list[tuple[int, int]]] = {}
    reloc_where: dict[int, list[tuple[int, float, float]]] = {}  # (stamp_ns, x_m, y_m) per suspect
    decoy_sites: dict[int, list[tuple[float, float]]] = {}
    # (stamp_ns, place) of accepted observations per robot, place = (origin (3), variance m², odometry (3)) or
    # None; a snapshot of an older version restores without them (its voids then followed the old rule)
    seen_at: dict[int, list[tuple[int, tuple[P3, float, P3] | None]]] = {}
    # (stamp_ns, other robot) of observations that contradicted the map, per robot (absent in older snapshots)
    disputes: dict[int, list[tuple[int, int]]] = {}
    # (stamp_ns, witness, metres) how far each of those put the robot from its estimate (absent in older snapshots)
    shifts: dict[int, list[tuple[int, int, float]]] = {}
    # the view of each pair's newest factor: (a, b, chain a, chain b, odom a (3), odom b (3), rel (3)); a
    # snapshot of an older version (its pair_factors held keyframe keys) restores without them
    pair_views: list[tuple[int, int, int, int, P3, P3, P3]] = []
    factors: str  # gtsam NonlinearFactorGraph.serialize() of the smoother's live factors
    # the calibrated odometry factors among them (GTSAM cannot serialise them): (position among the live
    # factors, keyframe a, keyframe b, calibration key, increment (3), covariance (9)); absent in older snapshots
    cal_factors: list[tuple[int, int, int, int, P3, tuple[float, ...]]] = []
    # the view factors through the shared range bias (server/rangebias.py), likewise: (position, keyframe a,
    # keyframe b, bias key, da (3), view (3), db (3), covariance (9)); and the bias variable's (key or None,
    # generation, estimate, variance or None, stamp s); absent in older snapshots
    view_factors: list[tuple[int, int, int, int, P3, P3, P3, tuple[float, ...]]] = []
    bias: tuple[int | None, int, float, float | None, float] = (None, 0, 0.0, None, 0.0)
    theta: str  # gtsam Values.serialize() of the smoother's linearisation point
    stamps: list[tuple[int, float]]  # (key, seconds) of every variable in the smoother


_ENC: Final = msgspec.msgpack.Encoder()
_DEC: Final = msgspec.msgpack.Decoder(FusionState)


def _p3(p: Pose2) -> P3:
    return (float(p[0]), float(p[1]), float(p[2]))


def _flat(cov: np.ndarray) -> tuple[float, ...]:
    return tuple(float(v) for v in np.asarray(cov, float).ravel())


def _mat(values: tuple[float, ...] | list[float]) -> np.ndarray:
    return np.asarray(values, float).reshape(3, 3)


def _robot_state(r: Robot, keep_from_ns: int) -> RobotState:
    samples = list(r.odom)
    first = 0
    for i in range(len(samples) - 1, -1, -1):  # newest first: keep one sample older than keep_from_ns
        if samples[i][0] < keep_from_ns:
            first = i
            break
    odom = [(int(t), *_p3(p)) for t, p in samples[first:]]
    lo = None if r.latest_odom is None else (int(r.latest_odom[0]), *_p3(r.latest_odom[1]))
    return RobotState(odom=odom, chain=r.chain, kf_index=r.kf_index, kf_key=r.kf_key, kf_stamp=r.kf_stamp,
                      kf_odom=_p3(r.kf_odom), estimate=None if r.estimate is None else _p3(r.estimate),
                      cov=_flat(r.cov), drift_cov=_flat(r.drift_cov), latest_odom=lo, last_fix_ns=r.last_fix_ns,
                      accepted=r.accepted, last_distance=float(r.last_distance),
                      reset_hint=None if r.reset_hint is None else _p3(r.reset_hint),
                      slip_m=float(r.slip_m), kf_slip_m=float(r.kf_slip_m), cal_key=r.cal_key, cal_gen=r.cal_gen,
                      cal=(float(r.cal[0]), float(r.cal[1]), float(r.cal[2])),
                      cal_cov=() if r.cal_cov is None else _flat(r.cal_cov))


def _event_state(ev: _Event) -> EventState:
    if ev.kind == "odom":
        rid, pose, distance, slip = ev.data
        return EventState(ev.stamp_ns, ev.rank, ev.order, ev.kind, (rid,), (*_p3(pose), float(distance),
                                                                            float(slip)))
    a, b, rel, cov = ev.data
    return EventState(ev.stamp_ns, ev.rank, ev.order, ev.kind, (a, b), (*_p3(rel), *_flat(cov)))


def _candidate_state(c: Candidate) -> CandidateState:
    if len(c.meas) == 4:  # (observer, target, rel, cov)
        obs, tgt, rel, cov = c.meas
        return CandidateState(c.stamp_ns, _p3(c.origin), float(c.trace), "robot", (obs, tgt),
                              (*_p3(rel), *_flat(cov)))
    pose, cov_map = c.meas  # landmark: (pose in the map, covariance)
    return CandidateState(c.stamp_ns, _p3(c.origin), float(c.trace), "landmark", (), (*_p3(pose), *_flat(cov_map)))


def _live_factors(smoother: FixedLagSmoother) -> tuple[gtsam.NonlinearFactorGraph, list[tuple[int, int, int, int]]]:
    """The smoother's factors without the empty slots marginalisation leaves behind, and apart from
    them its Python factors (calibrated odometry, views through the range bias) as (position among
    the live factors, keyframe a, keyframe b, third key)."""
    graph = smoother.getFactors()
    out = gtsam.NonlinearFactorGraph()
    custom: list[tuple[int, int, int, int]] = []
    live = 0
    for i in range(graph.size()):
        if graph.exists(i):
            f = graph.at(i)
            if isinstance(f, gtsam.CustomFactor):
                keys = f.keys()
                custom.append((live, int(keys[0]), int(keys[1]), int(keys[2])))
            else:
                out.add(f)
            live += 1
    return out, custom


def snapshot(fusion: Fusion) -> bytes:
    """The state of ``fusion`` as a compressed blob.  Call it right after
    :meth:`Fusion.advance` (nothing staged for the smoother); raises otherwise."""
    if fusion.graph.staged():
        raise RuntimeError("snapshot with factors staged for the smoother: take it right after advance()")
    keep_from = fusion.watermark_ns - int((fusion.p.init_window_s + ODOM_MARGIN_S) * 1e9)
    stamps = [(int(k), float(t)) for k, t in sorted(fusion.smoother.timestamps().items())]
    live, custom = _live_factors(fusion.smoother) if stamps else (gtsam.NonlinearFactorGraph(), [])
    g = fusion.graph
    cal, views = g.cal_factors, {ab: iter(v) for ab, v in g.view_factors.items()}
    cal_factors, view_factors = [], []
    try:
        for i, a, b, k in custom:
            if rangebias.is_bias_key(k):
                kb, da, rel, db, cov = next(views[(a, b)])
                view_factors.append((i, a, b, kb, _p3(da), _p3(rel), _p3(db), _flat(cov)))
            else:
                cal_factors.append((i, a, b, cal[(a, b)][0], _p3(cal[(a, b)][1]), _flat(cal[(a, b)][2])))
    except (KeyError, StopIteration) as exc:
        raise RuntimeError(f"a Python factor the fusion does not know of: {exc!r}") from None
    state = FusionState(
        robots={rid: _robot_state(r, keep_from) for rid, r in fusion.robots.items()},
        events=[_event_state(ev) for ev in fusion._events],  # heap order as is: a valid heap again
        order=fusion._order, counters=dict(fusion.counters),
        edges=[(a, b, t) for (a, b), t in fusion.edges.items()], watermark_ns=fusion.watermark_ns,
        updates=fusion.updates, next_cov_ns=fusion.graph.next_cov_ns,
        init={rid: [_candidate_state(c) for c in cands] for rid, cands in fusion._init.items()},
        reloc_robot={rid: [_candidate_state(c) for c in ev] for rid, ev in fusion.recovery.robot_ev.items()},
        reloc_landmark={rid: [_candidate_state(c) for c in ev] for rid, ev in fusion.recovery.landmark_ev.items()},
        partners={rid: [(int(t), int(o)) for t, o in q] for rid, q in fusion.recovery.partners.items()},
        reloc_where={rid: [(int(t), float(x), float(y)) for t, (x, y) in w.items()]
                     for rid, w in fusion.recovery.where.items()},
        decoy_sites={rid: [(float(x), float(y)) for x, y in sites]
                     for rid, sites in fusion.recovery.decoy_sites.items()},
        seen_at={rid: [(int(t), None if pl is None else (_p3(pl[0]), float(pl[1]), _p3(pl[2]))) for t, pl in q]
                 for rid, q in fusion.recovery.seen_at.items()},
        disputes={rid: [(int(t), int(o)) for t, o in q] for rid, q in fusion.recovery.disputes.items()},
        shifts={rid: [(int(t), int(w), float(d)) for t, w, d in q] for rid, q in fusion.recovery.shifts.items()},
        pair_views=[(a, b, v.chain_a, v.chain_b, _p3(v.odom_a), _p3(v.odom_b), _p3(v.rel))
                    for (a, b), v in fusion._pair_factors.items()],
        factors=live.serialize() if stamps else "", cal_factors=cal_factors, view_factors=view_factors,
        bias=(g.bias_key, g.bias_gen, float(g.bias), g.bias_var, float(g.bias_stamp)),
        theta=fusion.smoother.getLinearizationPoint().serialize() if stamps else "", stamps=stamps)
    return zlib.compress(_ENC.encode(state), ZLIB_LEVEL)


def decode(blob: bytes) -> FusionState:
    """The :class:`FusionState` in a snapshot blob; :class:`CheckpointError` if it does not decode."""
    try:
        return _DEC.decode(zlib.decompress(blob))
    except (zlib.error, msgspec.DecodeError, msgspec.ValidationError) as exc:
        raise CheckpointError(f"checkpoint does not decode: {exc}") from None


def _robot(s: RobotState, maxlen: int) -> Robot:
    return Robot(odom=deque(((t, (x, y, a)) for t, x, y, a in s.odom), maxlen=maxlen), chain=s.chain,
                  kf_index=s.kf_index, kf_key=s.kf_key, kf_stamp=s.kf_stamp, kf_odom=s.kf_odom,
                  estimate=s.estimate, cov=_mat(s.cov), drift_cov=_mat(s.drift_cov),
                  latest_odom=None if s.latest_odom is None else (s.latest_odom[0], s.latest_odom[1:]),
                  last_fix_ns=s.last_fix_ns, accepted=s.accepted, last_distance=s.last_distance,
                  reset_hint=s.reset_hint, slip_m=s.slip_m, kf_slip_m=s.kf_slip_m, cal_key=s.cal_key,
                  cal_gen=s.cal_gen, cal=np.asarray(s.cal, float), cal_cov=_mat(s.cal_cov) if s.cal_cov else None)


def _event(s: EventState) -> _Event:
    f = s.floats
    if s.kind == "odom":
        data: tuple = (s.ints[0], f[:3], f[3], f[4] if len(f) > 4 else 0.0)  # type: ignore[type-arg]
    else:
        data = (s.ints[0], s.ints[1], f[:3], _mat(f[3:]))
    return _Event(s.stamp_ns, s.rank, s.order, s.kind, data)


def _candidate(s: CandidateState) -> Candidate:
    f = s.floats
    meas: tuple = (s.ints[0], s.ints[1], f[:3], _mat(f[3:])) if s.kind == "robot" else (f[:3], _mat(f[3:]))  # type: ignore[type-arg]
    return Candidate(s.stamp_ns, s.origin, s.trace, meas)


def _smoother_input(state: FusionState) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, dict[int, float]]:
    graph, theta = gtsam.NonlinearFactorGraph(), gtsam.Values()
    stamps: dict[int, float] = {}
    if state.stamps:
        try:
            graph.deserialize(state.factors)
            theta.deserialize(state.theta)
        except Exception as exc:  # boost archive errors surface as assorted RuntimeErrors
            raise CheckpointError(f"checkpoint graph does not load: {exc}") from None
        stamps = {int(key): float(t) for key, t in state.stamps}
    return graph, theta, stamps


def restore(fusion: Fusion, blob: bytes | FusionState) -> None:
    """Make ``fusion`` (same parameters, origin, roster and landmarks as the one
    snapshotted: the journal header guarantees it) continue from the snapshot.
    Per-robot estimates are the saved ones until the next update reads the new
    smoother, so the published poses do not move at the restore itself.
    All or nothing: raises :class:`CheckpointError`, leaving ``fusion`` as it was,
    if the blob is unusable or the smoother cannot take the saved graph."""
    state = decode(blob) if isinstance(blob, bytes) else blob
    unknown = set(state.robots) - set(fusion.robots)
    if unknown:
        raise CheckpointError(f"checkpoint holds robots {sorted(unknown)} outside the roster")
    graph, theta, stamps = _smoother_input(state)
    new = Fusion(fusion.p, fusion.origin_id, tuple(fusion.robots), fusion.landmarks)  # built aside
    if state.cal_factors or state.view_factors:  # back into their places: the order is iSAM2's order of elimination
        merged, plain = gtsam.NonlinearFactorGraph(), iter(range(graph.size()))
        custom: dict[int, gtsam.NonlinearFactor] = {
            i: odomcal.factor(a, b, c, delta, _mat(cov), fusion.p.wheel_base_m)
            for i, a, b, c, delta, cov in state.cal_factors}
        custom.update({i: rangebias.factor(a, b, kb, da, rel, db, new.graph.robust(_mat(cov)))
                       for i, a, b, kb, da, rel, db, cov in state.view_factors})
        for i in range(graph.size() + len(custom)):
            merged.add(custom[i] if i in custom else graph.at(next(plain)))
        graph = merged
    for rid, rs in state.robots.items():
        new.robots[rid] = _robot(rs, new.p.odom_buffer)
    new._events = [_event(e) for e in state.events]
    new._order = state.order
    new.counters.update(state.counters)  # the same Counter the graph counts keyframes in
    new.edges = {(a, b): t for a, b, t in state.edges}
    new.watermark_ns = state.watermark_ns
    new.graph.updates = state.updates
    new.graph.next_cov_ns = state.next_cov_ns
    new._init = {rid: [_candidate(c) for c in cands] for rid, cands in state.init.items()}
    new.recovery.robot_ev = {rid: [_candidate(c) for c in ev] for rid, ev in state.reloc_robot.items()}
    new.recovery.landmark_ev = {rid: [_candidate(c) for c in ev] for rid, ev in state.reloc_landmark.items()}
    new.recovery.partners = {rid: deque(q, maxlen=256) for rid, q in state.partners.items()}
    new.recovery.where = {rid: {t: (x, y) for t, x, y in w} for rid, w in state.reloc_where.items()}
    new.recovery.decoy_sites = {rid: list(sites) for rid, sites in state.decoy_sites.items()}
    new.recovery.seen_at = {rid: deque(((t, None if pl is None else (tuple(pl[0]), pl[1], tuple(pl[2])))  # type: ignore[misc]
                                        for t, pl in q), maxlen=256) for rid, q in state.seen_at.items()}
    new.recovery.disputes = {rid: deque(q, maxlen=256) for rid, q in state.disputes.items()}
    new.recovery.shifts = {rid: deque(((t, w, d) for t, w, d in q), maxlen=256) for rid, q in state.shifts.items()}
    new.graph.cal_factors = {(a, b): (c, delta, _mat(cov)) for _, a, b, c, delta, cov in state.cal_factors}
    for _, a, b, kb, da, rel, db, cov in state.view_factors:
        new.graph.view_factors.setdefault((a, b), []).append((kb, da, rel, db, _mat(cov)))
    new.graph.bias_key, new.graph.bias_gen, new.graph.bias, new.graph.bias_var, new.graph.bias_stamp = state.bias
    new._pair_factors = {(a, b): PairView(ca, cb, oa, ob, rel) for a, b, ca, cb, oa, ob, rel in state.pair_views}
    if state.stamps:
        try:
            # iSAM2 relinearises on every relinearizeSkip-th update; keep that phase (a fresh smoother
            # counts from 0), or a large correction lands some updates earlier or later than it would
            # have (measured: transient 10 cm gaps with 16 robots).  Empty updates only count.
            skip = max(1, int(new.smoother.params().relinearizeSkip))
            for _ in range((state.updates - 1) % skip):
                new.smoother.update()
            # every variable is within the lag of the newest one (older ones were marginalised when the
            # snapshot was taken), so this update marginalises nothing
            new.smoother.update(graph, theta, stamps)
        except RuntimeError as exc:  # e.g. an indeterminant system
            raise CheckpointError(f"the smoother does not take the checkpoint's graph: {exc}") from None
    vars(fusion).update(vars(new))
