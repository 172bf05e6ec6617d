"""Evaluation of re-localisation (tagswarm.evaluation.recovery via tagswarm.evaluation.metrics) on synthetic run
folders whose answers are known by construction: time localised, kidnaps and the time
to recover from them, re-localisation events, contacts and NEES; and the recorder's
new files read back by the run-folder reader."""

from __future__ import annotations

import math
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tagswarm.evaluation.covframe import position_cov_in_map
from tagswarm.evaluation.metrics import RunFolderError, compute_metrics, load_run
from tagswarm.evaluation.recovery import sigma_median
from tagswarm.evaluation.runformat import (
    FUSED_COV_HEADER,
    INTERVENTIONS_HEADER,
    RELOC_HEADER,
    WORLD_COMMANDS_HEADER,
)
from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import Inbox
from tagswarm.protocol.keys import Keys
from tagswarm.protocol.scenario import load_scenario
from tagswarm.recording.runrecorder import RunRecorder
from tests.unit.evaluation.test_metrics import Poses, circle, make_run, static

T10 = np.arange(101) / 10.0  # 0 .. 10 s at 10 Hz, both ends included: a 10 s truth span


def offset_where(p: Poses, t: np.ndarray, lo: float, hi: float, dx: float) -> Poses:
    """``p`` moved by ``dx`` along x at the samples with lo <= t < hi."""
    out = p.copy()
    out[(t >= lo - 1e-9) & (t < hi - 1e-9), 0] += dx
    return out


def write_cov(root: Path, k: int, t: np.ndarray, cov: np.ndarray) -> None:
    """``fused_cov_<k>.csv`` with one (3, 3) covariance per stamp (``cov`` (3, 3) or (N, 3, 3))."""
    cov = np.broadcast_to(cov, (len(t), 3, 3))
    rows = [",".join(FUSED_COV_HEADER)]
    rows += [",".join([str(round(ti * 1e9)), *(repr(float(v)) for v in c.ravel())])
             for ti, c in zip(t, cov, strict=True)]
    (root / "trajectories" / f"fused_cov_{k}.csv").write_text("\n".join(rows) + "\n")


def write_relocs(root: Path, rows: list[tuple[float, int, float, int, str]]) -> None:
    """``relocalisations.csv`` rows (t_s, robot, jump_m, evidence, observers)."""
    lines = [",".join(RELOC_HEADER)]
    lines += [f"{round(t * 1e9)},{r},{j},0,0,0,1,0,0,{ev},{obs}" for t, r, j, ev, obs in rows]
    (root / "relocalisations.csv").write_text("\n".join(lines) + "\n")


def write_commands(root: Path, rows: list[tuple[float, int, str, float]]) -> None:
    """``world_commands.csv`` rows (stamp_s, robot, action, received_s)."""
    lines = [",".join(WORLD_COMMANDS_HEADER)]
    lines += [f"{round(t * 1e9)},{r},{a},1.0,0.0,0.0,{round(rx * 1e9)}" for t, r, a, rx in rows]
    (root / "world_commands.csv").write_text("\n".join(lines) + "\n")


# --------------------------------------------------------------------------- time localised


def test_time_localised_is_the_time_weighted_share_under_10_cm(tmp_path: Path) -> None:
    truth = {k: (T10, circle(k, T10)) for k in range(3)}
    fused: dict[int, Any] = {
        0: (T10, offset_where(truth[0][1], T10, 3.0, 5.0, 0.2)),  # 0.2 m off for 2 s of 10
        1: (T10, offset_where(truth[1][1], T10, 0.0, 10.1, 0.099)),  # always just inside
    }  # robot 2: never localised
    m = compute_metrics(make_run(tmp_path, truth, fused=fused))
    r = m["robots"]
    assert r["0"]["fused"]["time_localised"] == pytest.approx(0.8, abs=1e-9)
    assert r["1"]["fused"]["time_localised"] == pytest.approx(1.0, abs=1e-9)
    assert r["2"]["fused"]["time_localised"] == 0.0
    assert m["swarm"]["fused"]["time_localised"] == pytest.approx((8 + 10 + 0) / 30, abs=1e-9)
    assert r["0"]["odom"]["time_localised"] == pytest.approx(1.0)  # odom = truth here
    assert m["settings"]["localised_m"] == 0.10


def test_a_gap_in_the_corrections_counts_after_the_hold_time(tmp_path: Path) -> None:
    truth = {0: (T10, static(1.0, 2.0, T10))}
    keep = (T10 < 6.0 - 1e-9) | (T10 >= 7.0 - 1e-9)  # no correction in [6, 7): the 5.9 s one holds 0.5 s
    m = compute_metrics(make_run(tmp_path, truth, fused={0: (T10[keep], truth[0][1][keep])}))
    assert m["robots"]["0"]["fused"]["time_localised"] == pytest.approx(0.95, abs=1e-9)
    assert m["settings"]["localised_hold_s"] == 0.5


def test_time_before_the_first_fix_is_not_localised(tmp_path: Path) -> None:
    truth = {0: (T10, static(0.0, 0.0, T10))}
    late = T10 >= 2.5 - 1e-9
    m = compute_metrics(make_run(tmp_path, truth, fused={0: (T10[late], truth[0][1][late])}))
    assert m["robots"]["0"]["fused"]["time_localised"] == pytest.approx(0.75, abs=1e-9)
    assert m["robots"]["0"]["fused"]["time_localised_placed"] == pytest.approx(1.0)


def test_time_localised_once_placed_leaves_out_start_up_and_robots_never_placed(tmp_path: Path) -> None:
    """Robot 0 is placed at 2.5 s and 20 cm off from 7.5 s on; robot 1 is never placed."""
    truth = {0: (T10, static(0.0, 0.0, T10)), 1: (T10, static(1.0, 0.0, T10))}
    late = T10 >= 2.5 - 1e-9
    est = offset_where(truth[0][1], T10, 7.5, 11.0, 0.2)[late]
    m = compute_metrics(make_run(tmp_path, truth, fused={0: (T10[late], est)}))
    r0, r1 = m["robots"]["0"]["fused"], m["robots"]["1"]["fused"]
    assert r0["time_localised"] == pytest.approx(0.5, abs=1e-9)  # 2.5 .. 7.5 s of 10 s
    assert r0["time_localised_placed"] == pytest.approx(5.0 / 7.5, abs=1e-9)  # 2.5 .. 7.5 s of 2.5 .. 10 s
    assert r1["time_localised"] == 0.0 and r1["time_localised_placed"] is None
    assert m["swarm"]["fused"]["time_localised"] == pytest.approx(5.0 / 20.0, abs=1e-9)
    assert m["swarm"]["fused"]["time_localised_placed"] == pytest.approx(5.0 / 7.5, abs=1e-9)


# --------------------------------------------------------------------------- kidnaps and events


def kidnap_run(root: Path, **info: Any) -> Path:
    """Robot 1 stands at (1, 0) and is carried to (2, 0) at t = 5 s (truth jumps after the
    5.0 s sample); its fused estimate stays at (1, 0) until 6.4 s and is 5 cm off from 6.5 s
    on.  Robot 2 is carried off at 8.5 s and never found again.  Robot 0 is left alone."""
    t = T10
    p1 = static(1.0, 0.0, t)
    p1[t > 5.0 + 1e-9, 0] = 2.0
    f1 = static(1.0, 0.0, t)
    f1[t >= 6.5 - 1e-9, 0] = 2.05
    p2 = static(0.0, 3.0, t)
    p2[t > 8.5 + 1e-9, 1] = 4.5
    truth = {0: (t, static(0.0, 0.0, t)), 1: (t, p1), 2: (t, p2)}
    fused = {0: truth[0], 1: (t, f1), 2: (t, static(0.0, 3.0, t))}
    return make_run(root, truth, fused=fused, **info)


def scheduled(*events: tuple[float, int, str]) -> dict[str, Any]:
    return {"events": [{"at_s": at, "robot": r, "action": a, "x_m": 2.0, "y_m": 0.0, "yaw_rad": 0.0}
                       for at, r, a in events]}


def test_kidnap_time_to_relocalise_from_the_scenario_events(tmp_path: Path) -> None:
    run = kidnap_run(tmp_path, scenario=scheduled((5.0, 1, "teleport"), (8.5, 2, "push")))
    write_relocs(run, [(6.45, 1, 1.02, 4, "0 2 -1")])
    m = compute_metrics(run)
    k1, k2 = m["kidnaps"]
    assert (k1["t_s"], k1["robot"], k1["action"], k1["source"]) == (5.0, 1, "teleport", "scenario")
    assert k1["displacement_m"] == pytest.approx(1.0, abs=1e-9)
    assert k1["time_to_relocalise_s"] == pytest.approx(1.5, abs=1e-9)  # under 10 cm from 6.5 s, and it stays
    assert k1["first_relocalisation_s"] == pytest.approx(1.45, abs=1e-9)
    assert (k2["robot"], k2["displacement_m"]) == (2, pytest.approx(1.5, abs=1e-9))
    assert k2["time_to_relocalise_s"] is None and k2["first_relocalisation_s"] is None
    (ev,) = m["relocalisations"]
    assert ev == {"t_s": pytest.approx(6.45), "robot": 1, "jump_m": pytest.approx(1.02), "evidence": 4,
                  "observers": [0, 2, -1], "error_before_m": pytest.approx(1.0), "error_after_m": pytest.approx(0.05)}
    r = m["robots"]
    assert [r[k]["relocalisations"] for k in "012"] == [1 if k == "1" else 0 for k in "012"]
    assert [r[k]["kidnaps"] for k in "012"] == [0, 1, 1]
    assert m["swarm"]["relocalisations"] == 1
    assert m["swarm"]["kidnaps"] == {"count": 2, "recovered": 1, "mean_time_to_relocalise_s": pytest.approx(1.5),
                                     "max_time_to_relocalise_s": pytest.approx(1.5)}
    assert not [w for w in m["warnings"] if "event" in w or "kidnap" in w], m["warnings"]


def test_recovery_must_last_a_second(tmp_path: Path) -> None:
    """Back under 10 cm at 6.5 s but off again from 7.2 s to 7.4 s: the recovery that counts starts at 7.4 s."""
    t = T10
    p1 = static(1.0, 0.0, t)
    p1[t > 5.0 + 1e-9, 0] = 2.0
    f1 = static(1.0, 0.0, t)
    f1[t >= 6.5 - 1e-9, 0] = 2.0
    f1[(t >= 7.2 - 1e-9) & (t < 7.4 - 1e-9), 0] = 2.3
    run = make_run(tmp_path, {1: (t, p1)}, fused={1: (t, f1)}, scenario=scheduled((5.0, 1, "teleport")))
    (k,) = compute_metrics(run)["kidnaps"]
    assert k["time_to_relocalise_s"] == pytest.approx(2.4, abs=1e-9)


def test_recorded_world_commands_are_kidnaps_and_merge_with_scheduled_ones(tmp_path: Path) -> None:
    run = kidnap_run(tmp_path, scenario=scheduled((5.0, 1, "teleport")))
    # the same kidnap seen on the network (merged), and robot 2's sent by a tool that stamps 0
    write_commands(run, [(5.02, 1, "teleport", 5.1), (0.0, 2, "push", 8.5)])
    ks = compute_metrics(run)["kidnaps"]
    assert [(k["t_s"], k["robot"], k["source"]) for k in ks] == [(5.0, 1, "scenario"), (8.5, 2, "command")]
    assert ks[1]["displacement_m"] == pytest.approx(1.5, abs=1e-9)


def test_only_what_the_world_applied_is_a_kidnap_at_the_step_it_applied_it(tmp_path: Path) -> None:
    """A run folder with interventions.csv: refused commands, an event due after the end and a command
    whose ``at_s`` had passed count as the world applied them (they were all kidnaps at their asked time)."""
    run = kidnap_run(tmp_path, scenario=scheduled((5.0, 1, "teleport"), (30.0, 2, "push")))
    # robot 2's push sent for 1.0 s when it was 8.4 s: applied at 8.5 s; two refused teleports
    write_commands(run, [(1.0, 2, "push", 8.4), (0.0, 1, "teleport", 6.0), (0.0, 2, "teleport", 7.0)])
    lines = [",".join(INTERVENTIONS_HEADER), f"{round(5.0 * 1e9)},1,teleport,2.0,0.0,0.0",
             f"{round(8.5 * 1e9)},2,push,1.5,0.0,0.0"]
    (run / "interventions.csv").write_text("\n".join(lines) + "\n")
    m = compute_metrics(run)
    ks = m["kidnaps"]
    assert [(k["t_s"], k["robot"], k["source"]) for k in ks] == [(5.0, 1, "scenario"), (8.5, 2, "command")]
    assert ks[1]["displacement_m"] == pytest.approx(1.5, abs=1e-9)  # at 1.0 s it read ~0: nothing had moved
    assert m["swarm"]["kidnaps"]["count"] == 2
    assert any("3 kidnap(s) asked for were not applied" in w for w in m["warnings"]), m["warnings"]
    (run / "interventions.csv").write_text(",".join(INTERVENTIONS_HEADER) + "\n")  # nothing applied at all
    assert compute_metrics(run)["kidnaps"] == []


def test_no_events_no_kidnaps_and_bad_rows_are_named(tmp_path: Path) -> None:
    run = kidnap_run(tmp_path)
    m = compute_metrics(run)
    assert m["kidnaps"] == [] and m["relocalisations"] == []
    assert m["swarm"]["kidnaps"] == {"count": 0, "recovered": 0, "mean_time_to_relocalise_s": None,
                                     "max_time_to_relocalise_s": None}
    write_commands(run, [(1.0, 1, "juggle", 1.0)])
    with pytest.raises(RunFolderError, match=r"world_commands\.csv:2: action"):
        compute_metrics(run)
    (run / "world_commands.csv").unlink()
    (run / "relocalisations.csv").write_text("stamp_ns,robot\n1,1\n")
    with pytest.raises(RunFolderError, match=r"relocalisations\.csv: header"):
        compute_metrics(run)


def test_scenario_events_that_are_not_kidnaps_are_warnings(tmp_path: Path) -> None:
    run = kidnap_run(tmp_path, scenario={"events": [{"at_s": 2.0, "robot": 1, "action": "dance"},
                                                    {"at_s": 3.0, "robot": 7, "action": "push"}]})
    m = compute_metrics(run)
    assert m["kidnaps"] == []
    assert any("scenario event 0" in w for w in m["warnings"])
    assert any("robot 7" in w for w in m["warnings"])


# --------------------------------------------------------------------------- contacts


def test_contacts_from_the_world_counters(tmp_path: Path) -> None:
    counters = {"world": {"frames_rendered": 10, "contacts_robot_robot": 3, "contacts_robot_wall": 1,
                          "contacts_robot_0": 2, "contacts_robot_1": 1}}
    m = compute_metrics(kidnap_run(tmp_path / "a", counters=counters))
    assert m["swarm"]["contacts"] == {"robot_robot": 3, "robot_obstacle": 0, "robot_wall": 1}
    assert [m["robots"][k]["contacts"] for k in "012"] == [2, 1, 0]
    m = compute_metrics(kidnap_run(tmp_path / "b", counters={"world": {"frames_rendered": 10}}))
    assert m["swarm"]["contacts"] == {"robot_robot": None, "robot_obstacle": None, "robot_wall": None}
    assert m["robots"]["0"]["contacts"] is None


# --------------------------------------------------------------------------- NEES


def nees_run(root: Path, scale: float, seed: int = 7, n: int = 4000) -> Path:
    """One robot on a circle (its heading turns through every direction) whose fused
    position error is drawn from P_body = [[16, 6], [6, 4]] cm² in the ROBOT's axes; the
    recorded covariance is P_body / ``scale`` (so NEES ≈ scale)."""
    t = np.arange(n) / 10.0
    truth = circle(0, t, radius=2.0)
    p_body = np.array([[0.0016, 0.0006], [0.0006, 0.0004]])
    rng = np.random.default_rng(seed)
    e_body = rng.multivariate_normal([0.0, 0.0], p_body, size=n)
    c, s = np.cos(truth[:, 2]), np.sin(truth[:, 2])
    e_map = np.column_stack([c * e_body[:, 0] - s * e_body[:, 1], s * e_body[:, 0] + c * e_body[:, 1]])
    fused = truth + np.column_stack([e_map, np.zeros(n)])
    run = make_run(root, {0: (t, truth)}, fused={0: (t, fused)})
    cov = np.zeros((3, 3))
    cov[:2, :2] = p_body / scale
    cov[2, 2] = 0.01
    write_cov(run, 0, t, cov)
    return run


@pytest.mark.parametrize("scale", [1.0, 4.0])
def test_nees_of_errors_drawn_from_the_covariance(tmp_path: Path, scale: float) -> None:
    m = compute_metrics(nees_run(tmp_path, scale))
    nees = m["robots"]["0"]["fused"]["nees"]
    assert nees["count"] == 4000
    # mean of 4000 chi2(2)/2 draws: standard deviation 1/sqrt(4000) = 0.016 (times scale)
    assert nees["mean"] == pytest.approx(scale, rel=0.06)
    assert nees["median"] == pytest.approx(scale * math.log(2), rel=0.08)  # chi2(2)/2 is Exp(1): median ln 2
    assert m["swarm"]["fused"]["nees"] == nees


def test_nees_is_null_without_covariance_and_skips_singular_ones(tmp_path: Path) -> None:
    run = kidnap_run(tmp_path)
    m = compute_metrics(run)
    assert m["robots"]["1"]["fused"]["nees"] is None and m["swarm"]["fused"]["nees"] is None
    write_cov(run, 1, T10, np.zeros((3, 3)))  # all singular: nothing to evaluate
    cov0 = np.diag([0.0025, 0.0025, 0.01])
    write_cov(run, 0, T10[:50], cov0)  # robot 0: error 0, covariance for half its samples
    m = compute_metrics(run)
    assert m["robots"]["1"]["fused"]["nees"] is None
    assert m["robots"]["0"]["fused"]["nees"] == {"mean": 0.0, "median": 0.0, "count": 50}


def test_sigma_median_is_the_larger_position_axis_in_any_frame(tmp_path: Path) -> None:
    run = kidnap_run(tmp_path)
    assert compute_metrics(run)["robots"]["0"]["fused"]["sigma_median_m"] is None  # no covariance recorded
    # 3 samples at sigma 0.2 x 0.1 m (a correlated block: eigenvalues 0.04 and 0.01) and 2 at 0.5 m: median 0.2
    c, s = math.cos(0.6), math.sin(0.6)
    rot = np.array([[c, -s], [s, c]])
    block = rot @ np.diag([0.04, 0.01]) @ rot.T
    tilted = np.zeros((3, 3))
    tilted[:2, :2], tilted[2, 2] = block, 0.01
    write_cov(run, 0, T10[:5], np.stack([tilted] * 3 + [np.diag([0.25, 0.25, 0.01])] * 2))
    assert compute_metrics(run)["robots"]["0"]["fused"]["sigma_median_m"] == pytest.approx(0.2, abs=1e-9)
    assert sigma_median(None) is None


def test_position_cov_in_map_rotates_the_robot_axes() -> None:
    body = (0.04, 0.0, 0.0, 0.0, 0.01, 0.0, 0.0, 0.0, 0.001)
    sxx, sxy, syy = position_cov_in_map(body, math.pi / 2)  # heading +y: its x axis is the map's y
    assert (sxx, sxy, syy) == pytest.approx((0.01, 0.0, 0.04), abs=1e-12)
    sxx, sxy, syy = position_cov_in_map(body, math.pi / 4)
    assert (sxx, sxy, syy) == pytest.approx((0.025, 0.015, 0.025), abs=1e-12)


# --------------------------------------------------------------------------- the recorder's files


class FakeBus:
    """What RunRecorder needs of a Bus: subscriptions whose inboxes a test fills by hand."""

    def __init__(self) -> None:
        self.inboxes: dict[str, Inbox[bytes]] = {}

    def subscribe(self, key: str, *, newest_only: bool = False, capacity: int = 65536) -> Inbox[bytes]:
        self.inboxes[key] = Inbox(threading.Condition(), newest_only=newest_only, capacity=capacity)
        return self.inboxes[key]


def test_recorder_writes_what_the_reader_reads(tmp_path: Path) -> None:
    scenario = load_scenario("paper")
    keys, bus = Keys("rt"), FakeBus()
    rec = RunRecorder(bus, keys, scenario)  # type: ignore[arg-type]
    cov = (0.0004, 0.0001, 0.0, 0.0001, 0.0009, 0.0, 0.0, 0.0, 0.0025)
    for i in range(3):
        bus.inboxes[keys.correction()].put(keys.correction(1), codec.encode(m.Correction(
            seq=i, stamp_ns=i * 100_000_000, robot_id=1, map_odom_x_m=0.0, map_odom_y_m=0.0, map_odom_yaw_rad=0.0,
            x_m=1.0, y_m=0.5, yaw_rad=0.2, cov=cov)))
    bus.inboxes[keys.relocalisation()].put(keys.relocalisation(), codec.encode(m.Relocalisation(
        seq=0, stamp_ns=2_500_000_000, robot_id=2, from_x_m=1.0, from_y_m=0.0, from_yaw_rad=0.0, to_x_m=2.0,
        to_y_m=0.5, to_yaw_rad=0.1, jump_m=1.118, evidence=5, observers=(0, 1, -1))))
    bus.inboxes[keys.relocalisation()].put(keys.relocalisation(), b"\xc1garbage")
    obs_cov = (0.0001, 0.00002, 0.00003, 0.00002, 0.0004, 0.00005, 0.00003, 0.00005, 0.01)
    for target, c in ((2, obs_cov), (3, (0.0,) * 9)):
        bus.inboxes[keys.observation()].put(keys.observation(1), codec.encode(m.RelativeObservation(
            seq=target, stamp_ns=1_000_000_000, robot_id=1, target_kind="robot", target_id=target, x_m=2.0,
            y_m=-0.5, yaw_rad=0.3, cov=c, pose=m.Pose3(x_m=0.0, y_m=0.0, z_m=0.0), reprojection_rms_px=0.2,
            tag_ids=(target,), camera="front")))
    bus.inboxes[keys.world_command()].put(keys.world_command(), codec.encode(m.WorldCommand(
        seq=0, stamp_ns=2_000_000_000, robot_id=2, action="teleport", x_m=1.0, y_m=-1.0, yaw_rad=0.5)))
    bus.inboxes[keys.world_command()].put(keys.world_command(), codec.encode(m.WorldCommand(
        seq=1, stamp_ns=0, robot_id=99, action="push", x_m=1.0, y_m=0.0)))  # not a robot of this run
    rec.poll()
    assert rec.rejected == 2
    rec.write(tmp_path, {"wall_time_s": 1.0})
    run = load_run(tmp_path)
    (ev,) = run.relocalisations
    assert (ev.stamp_s, ev.robot, ev.jump_m, ev.evidence, ev.observers) == (2.5, 2, 1.118, 5, (0, 1, -1))
    assert ev.to_pose == (2.0, 0.5, 0.1)
    (wc,) = run.world_commands
    assert (wc.stamp_s, wc.robot, wc.action, wc.x_m, wc.y_m, wc.yaw_rad) == (2.0, 2, "teleport", 1.0, -1.0, 0.5)
    ct = run.fused_cov[1]
    assert ct is not None and ct.stamp_s.tolist() == [0.0, 0.1, 0.2]
    assert ct.cov[2].ravel().tolist() == list(cov)
    assert run.fused_cov[0] is None  # a header and no row
    obs = run.observations
    assert obs.target_id.tolist() == [2, 3] and obs.rel[0].tolist() == [2.0, -0.5, 0.3]
    assert obs.covariances()[0].ravel().tolist() == list(obs_cov)
    assert obs.covariances()[1].ravel().tolist() == [0.0] * 9


def test_nominal_nees_leaves_out_a_kidnapped_robot_until_it_is_found_again(tmp_path: Path) -> None:
    run = kidnap_run(tmp_path, scenario=scheduled((5.0, 1, "teleport"), (8.5, 2, "push")))
    cov = np.diag([0.05**2, 0.05**2, 0.01])
    for k in (1, 2):
        write_cov(run, k, T10, cov)
    m = compute_metrics(run)
    r1, r2 = m["robots"]["1"]["fused"], m["robots"]["2"]["fused"]
    # robot 1: error 0 until 5.0 s, 1 m (NEES 200) from 5.1 to 6.4 s, 5 cm (NEES 0.5) from 6.5 s on;
    # found again at 6.5 s, so only 5.0 .. 6.5 s are left out
    assert r1["nees"]["count"] == 101 and r1["nees"]["mean"] > 20
    assert r1["nees_nominal"]["count"] == 101 - 16
    assert r1["nees_nominal"]["mean"] == pytest.approx(0.5 * 35 / 85)  # 0 .. 4.9 s at 0, 6.6 .. 10 s at 0.5
    # robot 2 is never found again: everything from its kidnap on is left out
    assert r2["nees_nominal"]["count"] == 85 and r2["nees_nominal"]["mean"] == 0.0
    assert m["swarm"]["fused"]["nees_nominal"]["count"] == 85 + 85
    # the position error outside the same windows: robot 1 is 1 m off only inside its window
    a1 = r1["ate_unaligned_nominal"]
    assert a1["count"] == 85 and a1["max"] == pytest.approx(0.05) and r1["ate_unaligned"]["max"] == pytest.approx(1.0)
    assert a1["rmse"] == pytest.approx(0.05 * math.sqrt(35 / 85))
    assert r2["ate_unaligned_nominal"]["count"] == 85 and r2["ate_unaligned_nominal"]["max"] == pytest.approx(0.0)
    sw = m["swarm"]["fused"]["ate_unaligned_nominal"]
    assert sw["count"] == 85 + 85 + m["robots"]["0"]["fused"]["ate_unaligned"]["count"]
    assert sw["rmse"] < 0.05 < m["swarm"]["fused"]["ate_unaligned"]["rmse"]


def test_nominal_nees_window_opens_at_the_kidnap_tick_whatever_the_stamp_rounding(tmp_path: Path) -> None:
    """The truth is written after the kidnap's tick and a fused sample stamped a hair earlier
    is paired with it: that sample belongs to the kidnap, not to the nominal NEES."""
    t = T10
    p1 = static(1.0, 0.0, t)
    p1[t >= 5.0 - 1e-9, 0] = 2.0  # the 5.0 s truth sample is already carried off
    f1 = static(1.0, 0.0, t)
    f1[t >= 6.5 - 1e-9, 0] = 2.0
    run = make_run(tmp_path, {0: (t, static(0.0, 0.0, t)), 1: (t, p1)},
                   fused={0: (t, static(0.0, 0.0, t)), 1: (t - 1e-8, f1)}, scenario=scheduled((5.0, 1, "teleport")))
    write_cov(run, 1, t - 1e-8, np.diag([0.05**2, 0.05**2, 0.01]))
    r1 = compute_metrics(run)["robots"]["1"]["fused"]
    assert r1["nees"]["mean"] > 20  # 15 samples 1 m off (NEES 200 each)
    assert r1["nees_nominal"]["mean"] == 0.0, r1["nees_nominal"]


def test_a_source_the_recorder_stopped_hearing_is_named_in_the_metrics(tmp_path: Path) -> None:
    """The server's corrections stop at 1.5 s of a 6 s run (its link lost under load): the
    metrics say so instead of reporting a shorter run as if it were whole; the world and an
    agent heard to the end are not named."""
    scenario = load_scenario("paper")
    keys, bus = Keys("rt"), FakeBus()
    rec = RunRecorder(bus, keys, scenario)  # type: ignore[arg-type]
    for i in range(61):
        t = i * 100_000_000
        bus.inboxes[keys.truth()].put(keys.truth(1), codec.encode(m.GroundTruthPose(
            seq=i, stamp_ns=t, step=i, robot_id=1, x_m=0.0, y_m=0.0, yaw_rad=0.0,
            pose=m.Pose3(x_m=0.0, y_m=0.0, z_m=0.0))))
        bus.inboxes[keys.odometry()].put(keys.odometry(1), codec.encode(m.OdometryEstimate(
            seq=i, stamp_ns=t, robot_id=1, x_m=0.0, y_m=0.0, yaw_rad=0.0, cov=(0.0,) * 9, distance_m=0.0)))
        if t <= 1_500_000_000:
            bus.inboxes[keys.correction()].put(keys.correction(1), codec.encode(m.Correction(
                seq=i, stamp_ns=t, robot_id=1, map_odom_x_m=0.0, map_odom_y_m=0.0, map_odom_yaw_rad=0.0,
                x_m=0.0, y_m=0.0, yaw_rad=0.0, cov=(0.0,) * 9)))
    rec.poll()
    rec.write(tmp_path, {"wall_time_s": 6.0})
    metrics = compute_metrics(tmp_path)
    assert metrics["run"]["silent_sources"] == {"server": 1.5}
    (warning,) = [w for w in metrics["warnings"] if "heard nothing" in w]
    assert "server after 1.5 s of the run's 6.0 s" in warning


def test_older_run_folders_without_last_heard_name_no_silent_source(tmp_path: Path) -> None:
    run = make_run(tmp_path, {1: (T10, static(0.0, 0.0, T10))}, sim_time_s=10.0)
    metrics = compute_metrics(run)
    assert metrics["run"]["silent_sources"] == {}
    assert not [w for w in metrics["warnings"] if "heard nothing" in w]


def test_a_robot_whose_own_controller_failed_or_was_slow_is_a_warning(tmp_path: Path) -> None:
    """A controller that raises every step leaves its robot standing, which is easy to localise: only its
    counters tell, so metrics.json names it (the pytest fixture's Run.metrics too)."""
    t = T10
    counters = {"agent/0": {"fixes": 3}, "agent/1": {"controller_cycles": 300, "controller_errors": 300},
                "agent/2": {"controller_cycles": 300, "controller_errors": 0, "controller_slow": 4}, "world": {}}
    run = make_run(tmp_path, {k: (t, static(float(k), 0.0, t)) for k in range(3)}, counters=counters)
    warnings = compute_metrics(run)["warnings"]
    assert [w for w in warnings if "controller" in w] == [
        "robot 1's controller: 300 of 300 steps failed and stopped the robot (traceback in logs/agent1.log)",
        "robot 2's controller: 4 of 300 steps took longer than a control period"]
