"""tagswarm.view.state: messages -> what the live view draws, resets, malformed input (no network)."""

from __future__ import annotations

import json
import math

import msgspec
import pytest

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.geometry import se2_compose
from tagswarm.protocol.keys import Keys
from tagswarm.protocol.layout import arena_to_map, start_poses
from tagswarm.protocol.scenario import load_scenario
from tagswarm.view.state import EDGE_TTL_NS, ELLIPSE_SCALE_95, MAX_ROBOTS, ViewState, covariance_ellipse

KEYS = Keys("vt")
COV = (0.0004, 0.0, 0.0, 0.0, 0.0001, 0.0, 0.0, 0.0, 0.0009)
P3 = m.Pose3(x_m=0.0, y_m=0.0, z_m=0.0)


@pytest.fixture
def state() -> ViewState:
    return ViewState(load_scenario("paper"), KEYS)


def tick(stamp_ns: int, run_id: str = "vt-aaaa", step: int = 0) -> m.Tick:
    return m.Tick(seq=step, stamp_ns=stamp_ns, run_id=run_id, step=step, dt_ns=33_333_333, mode="lockstep")


def truth(rid: int, x: float, y: float, yaw: float, stamp_ns: int = 0) -> m.GroundTruthPose:
    return m.GroundTruthPose(seq=0, stamp_ns=stamp_ns, robot_id=rid, step=0, x_m=x, y_m=y, yaw_rad=yaw, pose=P3)


def corr(rid: int, x: float, y: float, stamp_ns: int, localised: bool = True) -> m.Correction:
    return m.Correction(seq=0, stamp_ns=stamp_ns, robot_id=rid, map_odom_x_m=0.0, map_odom_y_m=0.0,
                        map_odom_yaw_rad=0.0, x_m=x, y_m=y, yaw_rad=0.1, cov=COV, last_fix_ns=stamp_ns,
                        localised=localised)


def gmap(stamp_ns: int, *entries: tuple[int, float, float], alive: bool = True) -> m.GlobalMap:
    return m.GlobalMap(seq=0, stamp_ns=stamp_ns, origin_id=0, robots=tuple(
        m.MapEntry(robot_id=r, x_m=x, y_m=y, yaw_rad=0.2, cov=COV, last_seen_ns=stamp_ns, alive=alive)
        for r, x, y in entries))


def obs(observer: int, target: int, stamp_ns: int, kind: str = "robot") -> m.RelativeObservation:
    return m.RelativeObservation(seq=0, stamp_ns=stamp_ns, robot_id=observer, target_kind=kind,  # type: ignore[arg-type]
                                 target_id=target, x_m=1.0, y_m=0.5, yaw_rad=0.0, cov=COV, pose=P3,
                                 reprojection_rms_px=0.3, tag_ids=(11,), camera="front")


def robot(snap: dict, rid: int) -> dict:
    (r,) = [r for r in snap["robots"] if r["id"] == rid]
    return r


def test_truth_is_drawn_in_the_map_frame(state: ViewState) -> None:
    s = state.s
    start0 = start_poses(s)[0]  # the origin robot's start is the map frame's origin
    state.apply(truth(0, *start0), KEYS.truth(0))
    state.apply(truth(1, 1.2, 0.9, math.pi), KEYS.truth(1))
    snap = state.snapshot()
    assert robot(snap, 0)["truth"] == pytest.approx([0.0, 0.0, 0.0], abs=1e-6)
    expect = se2_compose(arena_to_map(s), (1.2, 0.9, math.pi))
    assert robot(snap, 1)["truth"][:2] == pytest.approx(expect[:2], abs=1e-6)
    assert robot(snap, 1)["truth"][0] == pytest.approx(2.7, abs=1e-6)  # 1.2 - (-1.5)
    # and the scene places the map frame back in the arena
    assert state.scene()["map_in_arena"] == pytest.approx([-1.5, 0.0, 0.0], abs=1e-6)


def test_fused_pose_takes_the_newest_estimate_and_the_map_on_a_tie(state: ViewState) -> None:
    state.apply(corr(1, 0.5, 0.25, 100), KEYS.correction(1))
    f = robot(state.snapshot(), 1)["fused"]
    assert (f["x"], f["y"], f["stamp_ns"], f["source"]) == (0.5, 0.25, 100, "correction")
    state.apply(gmap(100, (1, 0.51, 0.26)))
    f = robot(state.snapshot(), 1)["fused"]
    assert (f["x"], f["stamp_ns"], f["source"]) == (0.51, 100, "map")
    state.apply(corr(1, 0.52, 0.27, 100), KEYS.correction(1))  # same stamp: the map's copy stays
    assert robot(state.snapshot(), 1)["fused"]["source"] == "map"
    state.apply(corr(1, 0.6, 0.3, 133), KEYS.correction(1))
    f = robot(state.snapshot(), 1)["fused"]
    assert (f["x"], f["stamp_ns"], f["source"]) == (0.6, 133, "correction")
    state.apply(gmap(120, (1, 9.0, 9.0)))  # a late, older map never overrides
    assert robot(state.snapshot(), 1)["fused"]["x"] == 0.6
    # 95 % ellipse of diag(0.0004, 0.0001) in the robot's axes: semi-axes 2.4477 * (0.02, 0.01)
    # along the robot's heading (0.1 rad: the covariance is in its own axes)
    a, b, ang = robot(state.snapshot(), 1)["fused"]["ellipse"]
    assert (a, b) == pytest.approx((ELLIPSE_SCALE_95 * 0.02, ELLIPSE_SCALE_95 * 0.01), rel=1e-4)
    assert ang == pytest.approx(0.1, abs=1e-9)


def test_unlocalised_robot_has_no_fused_pose(state: ViewState) -> None:
    state.apply(corr(2, 0.0, 0.0, 50, localised=False), KEYS.correction(2))
    r = robot(state.snapshot(), 2)
    assert r["fused"] is None and r["localised"] is False


def test_a_map_entry_the_server_does_not_vouch_for_is_not_shown_as_localised(state: ViewState) -> None:
    loose = m.MapEntry(robot_id=2, x_m=1.0, y_m=1.0, yaw_rad=0.0, cov=COV, last_seen_ns=50, alive=True,
                       localised=False)
    state.apply(m.GlobalMap(seq=0, stamp_ns=50, origin_id=0, robots=(loose,)), KEYS.map())
    r = robot(state.snapshot(), 2)
    assert r["fused"] is None and r["localised"] is False
    state.apply(gmap(60, (2, 1.5, 1.0)), KEYS.map())  # vouched for
    r = robot(state.snapshot(), 2)
    assert r["fused"] is not None and r["localised"] is True


def test_error_compares_with_the_truth_at_the_fused_stamp(state: ViewState) -> None:
    a2m = arena_to_map(state.s)
    for k, x in enumerate((0.0, 0.1, 0.2)):  # arena x; map x = arena x + 1.5
        state.apply(truth(1, x, 0.0, 0.0, stamp_ns=k * 100), KEYS.truth(1))
    state.apply(corr(1, 0.1 + 1.5 + 0.03, a2m[1], 100), KEYS.correction(1))
    assert robot(state.snapshot(), 1)["error_m"] == pytest.approx(0.03, abs=1e-6)


def test_a_pose_older_than_its_message_is_compared_with_the_truth_at_its_own_time(state: ViewState) -> None:
    """Robot 1's odometry reached the server late: the correction at 200 holds its pose of 100 (and
    so does the map at 300)."""
    a2m = arena_to_map(state.s)
    for k, x in enumerate((0.0, 0.1, 0.2, 0.3)):
        state.apply(truth(1, x, 0.0, 0.0, stamp_ns=k * 100), KEYS.truth(1))
    late = msgspec.structs.replace(corr(1, 0.1 + 1.5 + 0.03, a2m[1], 200), pose_stamp_ns=100)
    state.apply(late, KEYS.correction(1))
    assert robot(state.snapshot(), 1)["error_m"] == pytest.approx(0.03, abs=1e-6)  # at 200: 0.07
    g = gmap(300, (1, 0.1 + 1.5 + 0.02, a2m[1]))
    g = msgspec.structs.replace(g, robots=(msgspec.structs.replace(g.robots[0], pose_stamp_ns=100),))
    state.apply(g, KEYS.map())
    assert robot(state.snapshot(), 1)["error_m"] == pytest.approx(0.02, abs=1e-6)  # at 300: 0.18


def test_odometry_only_pose_starts_at_the_robots_start(state: ViewState) -> None:
    odo = m.OdometryEstimate(seq=0, stamp_ns=10, robot_id=1, x_m=0.5, y_m=0.0, yaw_rad=0.0, cov=COV, distance_m=0.5)
    state.apply(odo, KEYS.odometry(1))
    start = se2_compose(arena_to_map(state.s), start_poses(state.s)[1])  # (2.7, 0.9, pi): facing -x
    assert robot(state.snapshot(), 1)["odom"][:2] == pytest.approx([start[0] - 0.5, start[1]], abs=1e-4)


def test_modes_statuses_and_who_sees_whom(state: ViewState) -> None:
    state.apply(tick(2_000_000_000), now_s=0.0)
    state.apply(m.AgentStatus(seq=0, stamp_ns=0, robot_id=3, role="agent", mode="search",
                              counters={"fixes": 7, "frames_processed": 40}), KEYS.robot_status(3))
    state.apply(m.AgentStatus(seq=0, stamp_ns=0, role="server", mode="lockstep", counters={"localised": 4}),
                KEYS.server_status())
    state.apply(obs(0, 3, 2_000_000_000), KEYS.observation(0))
    state.apply(obs(1, 2, 2_000_000_000 - EDGE_TTL_NS - 1), KEYS.observation(1))  # too old to draw
    snap = state.snapshot()
    r3 = robot(snap, 3)
    assert (r3["mode"], r3["fixes"], r3["frames"]) == ("search", 7, 40)
    assert snap["processes"]["server"]["counters"] == {"localised": 4}
    assert [(e["from"], e["kind"], e["to"]) for e in snap["sees"]] == [(0, "robot", 3)]


def test_real_time_factor_from_ticks_and_wall_time(state: ViewState) -> None:
    for k in range(11):  # 0.1 s of wall time per 0.05 s of simulation: RTF 0.5
        state.apply(tick(k * 50_000_000, step=k), now_s=100.0 + 0.1 * k)
    snap = state.snapshot()
    assert snap["rtf"] == pytest.approx(0.5, rel=1e-6)
    assert snap["sim_ns"] == 500_000_000 and snap["clock"] == "lockstep"


def test_new_run_id_resets(state: ViewState) -> None:
    state.apply(tick(1_000_000_000, "vt-aaaa"))
    state.apply(corr(1, 0.5, 0.5, 1_000_000_000), KEYS.correction(1))
    epoch = state.epoch
    state.apply(tick(1_100_000_000, "vt-bbbb"))
    snap = state.snapshot()
    assert snap["epoch"] == epoch + 1 and snap["run_id"] == "vt-bbbb"
    assert snap["robots"] == []


def test_clock_going_back_resets(state: ViewState) -> None:
    state.apply(tick(5_000_000_000))
    state.apply(truth(0, 0.0, 0.0, 0.0), KEYS.truth(0))
    state.apply(tick(33_333_333))  # same run id, but the clock restarted (a replay started again)
    snap = state.snapshot()
    assert snap["epoch"] == 1 and snap["robots"] == [] and snap["sim_ns"] == 33_333_333


def test_without_ticks_a_map_going_back_resets(state: ViewState) -> None:
    state.apply(gmap(5_000_000_000, (1, 1.0, 1.0)))
    assert state.epoch == 0 and state.snapshot()["sim_ns"] == 5_000_000_000
    state.apply(gmap(1_000_000_000, (2, 1.0, 1.0)))
    snap = state.snapshot()
    assert snap["epoch"] == 1 and [r["id"] for r in snap["robots"]] == [2]


def test_payload_for_another_robot_than_its_key_is_rejected(state: ViewState) -> None:
    state.apply(corr(2, 0.5, 0.5, 10), KEYS.correction(1))
    state.apply(truth(3, 0.0, 0.0, 0.0), "tagswarm/vt/robot/x/truth")
    snap = state.snapshot()
    assert snap["robots"] == []
    assert snap["rejected"] == {"mismatched_key": 2}


def test_robot_count_is_bounded(state: ViewState) -> None:
    for rid in range(MAX_ROBOTS + 10):
        state.apply(corr(rid, 0.0, 0.0, 10), KEYS.correction(rid))
    assert len(state.snapshot()["robots"]) == MAX_ROBOTS
    assert state.rejects.counts["too_many_robots"] == 10


def test_malformed_payloads_are_counted_and_the_state_keeps_working(state: ViewState) -> None:
    from tagswarm.protocol.bus import Received

    good = codec.encode(gmap(10, (1, 0.3, 0.4)))
    nan = codec.encode(gmap(20, (1, float("nan"), 0.4)))
    items = [Received(KEYS.map(), b"\xc1garbage"), Received(KEYS.map(), good), Received(KEYS.map(), nan),
             Received(KEYS.map(), b"x" * (5 * 1024 * 1024))]
    for _item, msg in state.rejects.decoded(items, m.GlobalMap):
        state.apply(msg)
    snap = state.snapshot()
    assert robot(snap, 1)["fused"]["x"] == 0.3
    assert snap["rejected"] == {"malformed": 1, "non_finite": 1, "oversized": 1}
    json.dumps(snap, allow_nan=False)  # the page always gets valid JSON


def test_snapshot_and_scene_are_strict_json(state: ViewState) -> None:
    state.apply(tick(1))
    state.apply(gmap(1, (0, 0.0, 0.0), (1, 1.0, 0.5)))
    state.apply(obs(0, 1, 1), KEYS.observation(0))
    text = json.dumps(state.snapshot(), allow_nan=False)
    assert json.loads(text)["robots"][1]["fused"]["y"] == 0.5
    scene = json.loads(json.dumps(state.scene(), allow_nan=False))
    assert scene["arena"]["size_x_m"] == 7.0 and len(scene["arena"]["walls"]) == 4
    assert scene["robot_ids"] == [0, 1, 2, 3]


@pytest.mark.parametrize(("cov", "expect"), [
    ((4.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0), (2.0, 1.0, 0.0)),
    ((1.0, 0.0, 0.0, 0.0, 4.0, 0.0, 0.0, 0.0, 1.0), (2.0, 1.0, math.pi / 2)),
    ((2.5, 1.5, 0.0, 1.5, 2.5, 0.0, 0.0, 0.0, 1.0), (2.0, 1.0, math.pi / 4)),
    ((-1e-9, 0.0, 0.0, 0.0, -1e-9, 0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),  # not quite PSD: clamped
])
def test_covariance_ellipse(cov: tuple[float, ...], expect: tuple[float, float, float]) -> None:
    a, b, ang = covariance_ellipse(cov, scale=1.0)
    assert (a, b) == pytest.approx(expect[:2], abs=1e-9)
    if expect[0] != expect[1]:
        assert math.cos(2 * (ang - expect[2])) == pytest.approx(1.0, abs=1e-9)  # axis direction, mod pi


# --------------------------------------------------------------------------- re-localisation and kidnaps


def reloc(rid: int, stamp_ns: int) -> m.Relocalisation:
    return m.Relocalisation(seq=0, stamp_ns=stamp_ns, robot_id=rid, from_x_m=1.0, from_y_m=0.0, from_yaw_rad=0.0,
                            to_x_m=2.0, to_y_m=0.5, to_yaw_rad=0.3, jump_m=1.118, evidence=4, observers=(0, -1))


def test_relocalisations_and_kidnaps_are_listed_newest_first(state: ViewState) -> None:
    a2m = arena_to_map(state.s)
    state.apply(tick(2_000_000_000, step=60))
    state.apply(truth(2, 0.5, 0.5, 0.0, 1_900_000_000), KEYS.truth(2))
    state.apply(m.WorldCommand(seq=0, stamp_ns=2_000_000_000, robot_id=2, action="teleport", x_m=1.0, y_m=-1.0,
                               yaw_rad=0.5), KEYS.world_command())
    state.apply(m.WorldCommand(seq=1, stamp_ns=0, robot_id=2, action="push", x_m=0.3, y_m=0.0), KEYS.world_command())
    state.apply(tick(3_000_000_000, step=90))
    state.apply(reloc(2, 2_900_000_000), KEYS.relocalisation())
    snap = state.snapshot()
    ev = snap["events"]
    assert [e["kind"] for e in ev] == ["relocalisation", "kidnap", "kidnap"]
    assert ev[0] == {"kind": "relocalisation", "robot": 2, "stamp_ns": 2_900_000_000, "jump_m": 1.118, "evidence": 4,
                     "observers": [0, -1], "from": [1.0, 0.0], "at": [2.0, 0.5, 0.3], "age_s": 0.1}
    assert ev[2]["at"] == pytest.approx(list(se2_compose(a2m, (1.0, -1.0, 0.5))), abs=1e-6)  # arena -> map
    assert ev[2]["age_s"] == 1.0
    assert ev[1]["stamp_ns"] == 2_000_000_000  # stamped 0: taken as the time it arrived
    assert ev[1]["at"] == pytest.approx(list(se2_compose(a2m, (0.5, 0.5, 0.0))), abs=1e-6)  # where the robot was
    assert snap["event_counts"] == {"relocalisations": 1, "kidnaps": 2}
    assert robot(snap, 2)["relocalisations"] == 1
    assert state.scene()["marker_ttl_s"] > 0
    state.apply(tick(1_000_000_000, run_id="vt-bbbb"))  # a new run forgets them
    assert state.snapshot()["events"] == [] and state.snapshot()["event_counts"]["relocalisations"] == 0


def test_time_localised_counts_truth_time_under_10_cm(state: ViewState) -> None:
    a2m = arena_to_map(state.s)
    dt = 100_000_000
    for i in range(101):  # 10 s at 10 Hz; the estimate is 0.2 m off for 2 s of them and absent for 1 s
        stamp = i * dt
        p = se2_compose(a2m, (1.0, 1.0, 0.0))
        off = 0.2 if 30 <= i < 50 else 0.0
        if not 70 <= i < 80:
            state.apply(corr(1, p[0] + off, p[1], stamp), KEYS.correction(1))
        state.apply(truth(1, 1.0, 1.0, 0.0, stamp), KEYS.truth(1))
    # 3.0-5.0 s off; the 6.9 s estimate holds 0.5 s into the gap, so 7.5-8.0 s count as not localised
    assert robot(state.snapshot(), 1)["time_localised"] == pytest.approx(0.75, abs=1e-9)
    # each truth sample is judged by the estimate standing when it arrives: one that lags a
    # sample behind (truth first, as in a lockstep run) shifts every verdict by that sample
    late = ViewState(state.s, KEYS)
    for i in range(101):
        late.apply(truth(1, 1.0, 1.0, 0.0, i * dt), KEYS.truth(1))
        p = se2_compose(a2m, (1.0, 1.0, 0.0))
        late.apply(corr(1, p[0] + (0.2 if 30 <= i < 50 else 0.0), p[1], i * dt), KEYS.correction(1))
    assert robot(late.snapshot(), 1)["time_localised"] == pytest.approx(0.79, abs=1e-9)  # 0-0.1 s, 3.1-5.1 s
    assert robot(state.snapshot(), 1)["error_m"] == pytest.approx(0.0, abs=1e-6)
