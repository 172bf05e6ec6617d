"""What the map server publishes, built from its fusion (pure code: state in, messages out;
:mod:`tagswarm.server.node` numbers and sends them).

Poses are in the map frame (metres, radians); covariances are the fusion's with the second-order
term of a loose heading added (:func:`~tagswarm.server.noise.reported_cov`), 3x3 row-major in
the robot's own axes (see :class:`~tagswarm.protocol.messages.Correction`); times are
simulation nanoseconds.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping

import numpy as np

from tagswarm.protocol import messages as m
from tagswarm.protocol.geometry import worst_axis_sigma_m, wrap_angle
from tagswarm.server.estimator import Estimator
from tagswarm.server.fusion import RelocEvent
from tagswarm.server.noise import Cov, reported_cov

#: an observation edge stays in the map this long after it was last seen (simulation ns)
EDGE_MEMORY_NS = 5_000_000_000
#: realtime: a robot's correction whose map -> odom moved less than this (m, rad) since the last one
#: sent, with no new fix, waits up to CORRECTION_KEEPALIVE_NS (its agent composes the same pose)
CORRECTION_MOVE_M = 1e-3
CORRECTION_TURN_RAD = 1e-3
CORRECTION_KEEPALIVE_NS = 100_000_000


def pose_time_ns(fusion: Estimator, rid: int, time_ns: int) -> int:
    """Simulation time of ``rid``'s fused pose at the server's clock ``time_ns``: its newest odometry
    fused (``time_ns`` if none).  It lags the clock while that odometry is late (a realtime link
    retransmitting): read at the clock's time, a pose 0.5 s old was 16 cm off on a patrol at 0.3 m/s."""
    odom_ns = fusion.latest_odom_ns(rid)
    return time_ns if odom_ns < 0 else min(time_ns, odom_ns)


def global_map(fusion: Estimator, robot_ids: Iterable[int], origin_id: int, time_ns: int,
               latest_rx: Mapping[int, int], alive: set[int], seq: int, claim_sigma_m: float = 0.0) -> m.GlobalMap:
    """Every placed robot of ``robot_ids`` (in that order) with its fused pose (at :func:`pose_time_ns`),
    whether the server vouches for it (:func:`unvouched_reason`), when its odometry last arrived and whether its agent
    is alive, and the recent observation edges."""
    entries = []
    for rid in robot_ids:
        est = fusion.pose(rid)
        if est is None:
            continue
        (x, y, yaw), graph_cov = est
        cov = reported_cov(graph_cov)
        entries.append(m.MapEntry(robot_id=rid, x_m=x, y_m=y, yaw_rad=yaw,
                                  cov=tuple(float(v) for v in cov.ravel()),
                                  last_seen_ns=max(latest_rx.get(rid, 0), 0), alive=rid in alive,
                                  localised=unvouched_reason(fusion, rid, cov, claim_sigma_m) is None,
                                  pose_stamp_ns=pose_time_ns(fusion, rid, time_ns)))
    edges = tuple(sorted(e for e, t in fusion.edges.items() if time_ns - t <= EDGE_MEMORY_NS))
    return m.GlobalMap(seq=seq, stamp_ns=time_ns, origin_id=origin_id, robots=tuple(entries), edges=edges)


position_sigma_m = worst_axis_sigma_m  # the server's measure of a reported covariance (protocol.geometry)


def unvouched_reason(fusion: Estimator, rid: int, cov: Cov, claim_sigma_m: float) -> str | None:
    """Why the server does not vouch for placed robot ``rid`` (reported covariance ``cov``), None if it
    does: its position is less sure than ``claim_sigma_m`` (:func:`position_sigma_m`), or its estimate
    is in dispute (:meth:`~tagswarm.server.estimator.Estimator.in_dispute`); 0 vouches for every
    placed robot."""
    if claim_sigma_m <= 0:
        return None
    if fusion.in_dispute(rid):
        return "its latest views put it elsewhere"
    sigma = position_sigma_m(cov)
    if sigma >= claim_sigma_m:
        return f"position sigma {sigma:.2f} m >= claim_sigma_m {claim_sigma_m:g} m"
    return None


def correction(fusion: Estimator, rid: int, time_ns: int, seq: int, claim_sigma_m: float = 0.0) -> m.Correction:
    """Robot ``rid``'s ``map -> odom`` correction at the server's clock ``time_ns`` and its fused pose,
    at the newest odometry of it the fusion applied (``pose_stamp_ns``); ``localised=False`` while the
    fusion cannot place it (every pose field zero) or does not vouch for it (:func:`unvouched_reason`;
    the fields then hold the map's loose estimate)."""
    est, mo = fusion.pose(rid), fusion.map_to_odom(rid)
    cov = None if est is None else reported_cov(est[1])
    # stamp_ns stays the clock: a lockstep agent waits for the correction of each tick, also when its
    # odometry of that tick was lost
    if est is None or mo is None or cov is None:
        return m.Correction(seq=seq, stamp_ns=time_ns, robot_id=rid, map_odom_x_m=0.0, map_odom_y_m=0.0,
                            map_odom_yaw_rad=0.0, x_m=0.0, y_m=0.0, yaw_rad=0.0, cov=(0.0,) * 9, localised=False)
    x, y, yaw = est[0]
    vouched = unvouched_reason(fusion, rid, cov, claim_sigma_m) is None
    return m.Correction(seq=seq, stamp_ns=time_ns, robot_id=rid, map_odom_x_m=mo[0], map_odom_y_m=mo[1],
                        map_odom_yaw_rad=mo[2], x_m=x, y_m=y, yaw_rad=yaw, cov=tuple(float(v) for v in cov.ravel()),
                        last_fix_ns=fusion.last_fix_ns(rid), localised=vouched,
                        pose_stamp_ns=pose_time_ns(fusion, rid, time_ns))


def correction_due(last: m.Correction | None, msg: m.Correction,
                   keepalive_ns: int = CORRECTION_KEEPALIVE_NS) -> bool:
    """Whether ``msg`` must go out in realtime, ``last`` being the robot's previous correction
    sent: a change of localisation, a new fix (the agent counts it; latency is measured on it),
    ``map -> odom`` moved by at least :data:`CORRECTION_MOVE_M` / :data:`CORRECTION_TURN_RAD`, or
    ``keepalive_ns`` of simulation time since ``last`` (the fused trajectory, the live view).  At
    16 robots and 50 updates/s, sending every one was 800 messages/s for the server to publish
    and every agent and recorder to take in."""
    if last is None or last.localised != msg.localised or last.last_fix_ns != msg.last_fix_ns:
        return True
    if not 0 <= msg.stamp_ns - last.stamp_ns < keepalive_ns:  # due, or a restarted world's clock
        return True
    turn = abs(wrap_angle(msg.map_odom_yaw_rad - last.map_odom_yaw_rad))
    return (math.hypot(msg.map_odom_x_m - last.map_odom_x_m, msg.map_odom_y_m - last.map_odom_y_m)
            >= CORRECTION_MOVE_M or turn >= CORRECTION_TURN_RAD)


def relocalisation(ev: RelocEvent, seq: int) -> m.Relocalisation:
    """The event of a robot re-localised by the fusion."""
    return m.Relocalisation(seq=seq, stamp_ns=ev.stamp_ns, robot_id=ev.robot_id,
                            from_x_m=ev.before[0], from_y_m=ev.before[1], from_yaw_rad=ev.before[2],
                            to_x_m=ev.after[0], to_y_m=ev.after[1], to_yaw_rad=ev.after[2], jump_m=ev.jump_m,
                            evidence=ev.evidence, observers=ev.observers)


def status_counters(node: Mapping[str, int], fusion: Estimator, rejects: Mapping[str, int], gaps: Mapping[str, int],
                    faults: Mapping[str, int], journal: Mapping[str, int] | None, alive: int) -> dict[str, int]:
    """The server's status counters, in this order: its own, the fusion's (prefixed
    ``fusion_``), rejects, sequence gaps, network faults, the inputs accepted in all, the
    journal's, and how many robots are localised and alive."""
    counters = dict(node)
    counters.update({f"fusion_{k}": v for k, v in fusion.counters.items()})
    counters.update(rejects)
    counters.update(gaps)
    counters.update(faults)
    counters["accepted"] = counters.get("accepted_odometry", 0) + counters.get("accepted_observations", 0)
    if journal is not None:
        counters.update(journal)
    counters["localised"] = len(fusion.localised())
    counters["alive"] = alive
    return counters


class Vouching:
    """Whether the server vouches for each robot the map has, to log the changes (not every tick)."""

    def __init__(self, claim_sigma_m: float) -> None:
        self.claim_sigma_m = claim_sigma_m
        self.state: dict[int, str] = {}  # robot -> "unplaced" / "unvouched" / "vouched"
        self.unvouched_events = 0  # times a placed robot went (or started) unvouched

    def update(self, fusion: Estimator, rid: int, msg: m.Correction, time_ns: int) -> str | None:
        """Robot ``rid``'s correction ``msg`` is going out: the log line if the server started or
        stopped vouching for it (with why), else None."""
        # an unvouched correction carries the map's estimate and its reported covariance, an unplaced one zeros
        state = "vouched" if msg.localised else ("unvouched" if any(msg.cov) else "unplaced")
        if state == self.state.get(rid, "unplaced"):
            return None
        self.state[rid] = state
        if state == "unvouched":  # why, worked out once per change
            self.unvouched_events += 1
            reason = unvouched_reason(fusion, rid, np.asarray(msg.cov).reshape(3, 3), self.claim_sigma_m)
            return f"robot {rid} is in the map but not reported localised at t={time_ns / 1e9:.2f} s: {reason}"
        if state == "vouched":
            return (f"robot {rid} reported localised at t={time_ns / 1e9:.2f} s "
                    f"(position sigma {position_sigma_m(msg.cov):.3f} m)")
        return None
