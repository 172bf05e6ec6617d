"""A placed robot is claimed (its correction says localised) only while the fused position is
surer than ``[server] claim_sigma_m`` (server/outputs.py: correction, position_sigma_m)."""

from __future__ import annotations

import math

import numpy as np

from tagswarm.server.fusion import Fusion, FusionParams
from tagswarm.server.outputs import Vouching, correction, global_map, position_sigma_m, unvouched_reason

# a far cube seen face-on: its bearing and range are good to centimetres, its yaw to 14 degrees
FAR = np.diag([0.035**2, 0.02**2, math.radians(14.0) ** 2])
REL = (4.0, 0.0, math.pi)  # robot 1 stands 4 m ahead of the origin, facing it (and sees it the same way)


def _run(origin_sees_it: bool) -> Fusion:
    """Robot 1 sees the origin robot 4 m away for 1 s; with ``origin_sees_it`` the origin sees
    robot 1 back from then on, whose bearing pins robot 1's position."""
    fusion = Fusion(FusionParams(), 0, (0, 1))
    for k in range(120):
        t = round(k * 1e9 / 30)
        fusion.add_odometry(0, t, (0.0, 0.0, 0.0), 0.0)
        fusion.add_odometry(1, t, (0.0, 0.0, 0.0), 0.0)
        if k % 3 == 0 and k < 30:
            fusion.add_observation(1, 0, t, REL, FAR)  # type: ignore[arg-type]
        if k % 3 == 0 and k >= 30 and origin_sees_it:
            fusion.add_observation(0, 1, t, REL, FAR)  # type: ignore[arg-type]
        fusion.advance(t)
    return fusion


def test_position_sigma_is_the_worst_axis() -> None:
    assert position_sigma_m(np.diag([0.04, 0.01, 1.0])) == 0.2
    assert position_sigma_m(np.array([[0.02, 0.01, 0], [0.01, 0.02, 0], [0, 0, 0]])) == math.sqrt(0.03)
    assert position_sigma_m(np.diag([np.nan, 0.01, 0.0])) == math.inf


def test_a_robot_placed_from_one_far_view_is_in_the_map_but_not_claimed() -> None:
    fusion = _run(origin_sees_it=False)
    est = fusion.pose(1)
    assert est is not None  # placed: its own view put it on a 4 m arc around the origin
    sigma = position_sigma_m(est[1])
    assert sigma > 0.5, sigma  # the arc: 4 m x 14 degrees
    loose = correction(fusion, 1, fusion.watermark_ns, 0, claim_sigma_m=0.5)
    assert not loose.localised
    # not vouched for, but the map's estimate goes out with it (the robot may drive on it slowly)
    assert abs(loose.x_m - est[0][0]) < 1e-9 and position_sigma_m(np.asarray(loose.cov).reshape(3, 3)) > 0.5
    assert loose.map_odom_x_m != 0.0 or loose.map_odom_y_m != 0.0
    # the global map lists it too, flagged the same way
    entries = {e.robot_id: e for e in global_map(fusion, (0, 1), 0, fusion.watermark_ns, {}, set(), 0, 0.5).robots}
    assert entries[0].localised and not entries[1].localised and entries[1].x_m == loose.x_m
    assert global_map(fusion, (0, 1), 0, fusion.watermark_ns, {}, set(), 0, 0.0).robots[1].localised
    claimed = correction(fusion, 1, fusion.watermark_ns, 0, claim_sigma_m=0.0)
    assert claimed.localised and abs(claimed.x_m - 4.0) < 0.3
    assert correction(fusion, 0, fusion.watermark_ns, 0, claim_sigma_m=0.5).localised  # the origin
    reason = unvouched_reason(fusion, 1, est[1], 0.5)  # what the server's log says
    assert reason is not None and reason.startswith("position sigma "), reason
    assert unvouched_reason(fusion, 1, est[1], 0.0) is None
    origin = fusion.pose(0)
    assert origin is not None and unvouched_reason(fusion, 0, origin[1], 0.5) is None


def test_the_bearing_of_a_view_back_makes_it_claimed() -> None:
    fusion = _run(origin_sees_it=True)
    est = fusion.pose(1)
    assert est is not None and position_sigma_m(est[1]) < 0.1, est
    c = correction(fusion, 1, fusion.watermark_ns, 0, claim_sigma_m=0.5)
    assert c.localised and math.hypot(c.x_m - 4.0, c.y_m) < 0.05, c
    assert position_sigma_m(np.asarray(c.cov).reshape(3, 3)) < 0.1


NEAR = np.diag([0.005**2, 0.005**2, math.radians(1.0) ** 2])


def test_a_robot_carried_away_is_not_vouched_for_until_it_is_placed_again() -> None:
    """The origin sees robot 1 2 m ahead; at 4 s robot 1 is carried 1 m sideways (its wheels
    still).  The map keeps it where it was until the evidence re-localises it, a second later;
    meanwhile its correction says unlocalised from the second contradicting view on."""
    fusion = Fusion(FusionParams(), 0, (0, 1))
    states: list[tuple[float, bool, bool, float]] = []
    for k in range(200):
        t = round(k * 1e9 / 30)
        fusion.add_odometry(0, t, (0.0, 0.0, 0.0), 0.0)
        fusion.add_odometry(1, t, (0.0, 0.0, 0.0), 0.0)
        if k % 3 == 0:
            fusion.add_observation(0, 1, t, (2.0, 0.0 if k < 120 else 1.0, math.pi), NEAR)  # type: ignore[arg-type]
        fusion.advance(t)
        if fusion.pose(1) is not None:
            vouched = correction(fusion, 1, t, 0, claim_sigma_m=0.5)
            states.append((k / 30, vouched.localised, correction(fusion, 1, t, 0).localised, vouched.y_m))
            if k == 126:  # 4.2 s: in dispute
                pose = fusion.pose(1)
                assert pose is not None
                assert unvouched_reason(fusion, 1, pose[1], 0.5) == "its latest views put it elsewhere"
    before = [s for s in states if 1.0 <= s[0] < 4.0]
    assert before and all(s[1] for s in before)  # vouched for while views agree
    # the first contradicting view alone (a mis-decoded tag) does not cost it
    assert next(s for s in states if s[0] == 4.0)[1]
    unvouched = [s[0] for s in states if s[0] >= 4.0 and not s[1]]
    # from the second view the gate judges on (4.1 s is thinned: 0.2 s after the pair's last accepted one)
    assert unvouched and unvouched[0] <= 4.21, unvouched
    assert all(s[2] for s in states if s[0] in unvouched)  # claim_sigma_m = 0: the old behaviour
    assert fusion.counters["relocalisations"] == 1
    after = [s for s in states if s[0] > unvouched[-1]]
    assert after and all(s[1] and abs(s[3] - 1.0) < 0.02 for s in after), after[:3]
    assert unvouched[-1] - unvouched[0] < 1.5  # until the re-localisation


def test_a_robot_turned_on_the_spot_is_still_vouched_for() -> None:
    """Robot 1, 2 m ahead of the origin and seeing it, is turned 0.3 rad on the spot at 4 s: its
    views of the origin contradict its heading, but its place is right, so it stays vouched for."""
    fusion = Fusion(FusionParams(), 0, (0, 1))
    unvouched = []
    for k in range(200):
        t = round(k * 1e9 / 30)
        fusion.add_odometry(0, t, (0.0, 0.0, 0.0), 0.0)
        fusion.add_odometry(1, t, (0.0, 0.0, 0.0), 0.0)
        turn = 0.0 if k < 120 else 0.3
        if k % 3 == 0:
            fusion.add_observation(0, 1, t, (2.0, 0.0, math.pi + turn), NEAR)  # type: ignore[arg-type]
            # the origin in robot 1's frame: 2 m ahead when facing it, rotated by -turn
            c, s = math.cos(-turn), math.sin(-turn)
            fusion.add_observation(1, 0, t + 1, (2.0 * c, 2.0 * s, math.pi - turn), NEAR)  # type: ignore[arg-type]
        fusion.advance(t + 1)
        if k >= 120 and not correction(fusion, 1, t, 0, claim_sigma_m=0.5).localised:
            unvouched.append(k / 30)
    assert fusion.counters["rejected_gate"] + fusion.counters["surprising_observations"] >= 2, dict(fusion.counters)
    assert not unvouched, unvouched


def test_the_log_says_when_the_server_starts_and_stops_vouching_and_not_every_tick() -> None:
    loose, pinned = _run(origin_sees_it=False), _run(origin_sees_it=True)
    v = Vouching(0.5)
    t = loose.watermark_ns
    line = v.update(loose, 1, correction(loose, 1, t, 0, claim_sigma_m=0.5), t)
    assert line is not None and "robot 1 is in the map but not reported localised" in line and "position sigma" in line
    assert v.update(loose, 1, correction(loose, 1, t, 0, claim_sigma_m=0.5), t) is None  # no change, no line
    line = v.update(pinned, 1, correction(pinned, 1, t, 0, claim_sigma_m=0.5), t)
    assert line is not None and line.startswith("robot 1 reported localised at t=")
    assert v.unvouched_events == 1  # the server status counter unvouched_events
    assert v.update(loose, 0, correction(loose, 0, t, 0, claim_sigma_m=0.5), t) is not None  # the origin: vouched
    assert v.unvouched_events == 1
