"""Recovery from gross error, end to end (``tagswarm up``, lockstep, fixed seeds):
kidnapped robots are re-localised from other robots' observations, and a robot
pushed by another is brought back."""

from __future__ import annotations

import csv
import json
import math
import subprocess
from pathlib import Path

import numpy as np
import pytest

from tests.harness import script


def _up(out: Path, *args: str) -> Path:
    res = subprocess.run([script("tagswarm"), "up", "--clock", "lockstep", "--out", str(out), "--no-live", *args],
                         capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    return out


def _final_error(run: Path, rid: int) -> float:
    truth = np.loadtxt(run / "trajectories" / f"truth_{rid}.tum", ndmin=2)
    fused = np.loadtxt(run / "trajectories" / f"fused_{rid}.tum", ndmin=2)
    i = int(np.argmin(np.abs(fused[:, 0] - truth[-1, 0])))
    assert abs(fused[i, 0] - truth[-1, 0]) < 0.1
    return math.hypot(fused[i, 1] - truth[-1, 1], fused[i, 2] - truth[-1, 2])


def _error_at(run: Path, rid: int, t_s: float) -> float:
    """Error (m) of the newest fused pose at or before ``t_s`` (a robot the server does not vouch for,
    such as one just carried away, has no new fused pose until it is placed again)."""
    truth = np.loadtxt(run / "trajectories" / f"truth_{rid}.tum", ndmin=2)
    fused = np.loadtxt(run / "trajectories" / f"fused_{rid}.tum", ndmin=2)
    i = max(int(np.searchsorted(fused[:, 0], t_s, side="right")) - 1, 0)
    j = int(np.argmin(np.abs(truth[:, 0] - fused[i, 0])))
    return math.hypot(fused[i, 1] - truth[j, 1], fused[i, 2] - truth[j, 2])


def _thrown_off(run: Path, rid: int, at_s: float, by_s: float, min_m: float) -> bool:
    """Whether the push of ``rid`` at ``at_s`` threw the map off by ``by_s``: the newest fused pose
    then is more than ``min_m`` wrong, or the server stopped vouching for the robot (no fused pose
    since the push: its views put it elsewhere).  It was localised before the push."""
    fused = np.loadtxt(run / "trajectories" / f"fused_{rid}.tum", ndmin=2)
    before = fused[fused[:, 0] <= at_s]
    assert len(before) and at_s - before[-1, 0] < 0.1, (rid, at_s)
    since = fused[(fused[:, 0] > at_s) & (fused[:, 0] <= by_s)]
    return len(since) == 0 or _error_at(run, rid, by_s) > min_m


def _in_view(run: Path, times: tuple[float, ...], window_s: float = 1.0) -> list[tuple[int, float]]:
    """(robot, t) for every robot that took part in a robot-robot observation (as observer or target)
    within ``window_s`` before each t."""
    with open(run / "observations.csv") as f:
        rows = [(int(r["stamp_ns"]) / 1e9, int(r["observer"]), int(r["target_id"]))
                for r in csv.DictReader(f) if r["target_kind"] == "robot"]
    return sorted({(rid, t) for t in times for stamp, o, g in rows if t - window_s <= stamp <= t for rid in (o, g)})


@pytest.fixture(scope="module")
def kidnap_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _up(tmp_path_factory.mktemp("kidnap") / "run", "--scenario", "kidnap", "--duration", "30")


def test_kidnapped_robots_are_relocalised_within_3_s(kidnap_run: Path) -> None:
    metrics = json.loads((kidnap_run / "metrics.json").read_text())
    kidnaps = {1: 10.0, 2: 25.0}  # the scene's [[events]]
    for rid, at_s in kidnaps.items():
        assert _thrown_off(kidnap_run, rid, at_s, at_s + 0.5, 0.5), "the kidnap did not throw the estimate off"
        # within 10 cm again within 3 s of simulated time, and staying there
        truth = np.loadtxt(kidnap_run / "trajectories" / f"truth_{rid}.tum", ndmin=2)
        later = [t for t in truth[:, 0] if at_s + 3.0 <= t <= min(at_s + 5.0, truth[-1, 0])]
        assert later and max(_error_at(kidnap_run, rid, t) for t in later[::5]) < 0.10, rid
    assert metrics["swarm"]["kidnaps"]["recovered"] == 2
    assert metrics["swarm"]["kidnaps"]["max_time_to_relocalise_s"] <= 3.0
    with open(kidnap_run / "relocalisations.csv") as f:
        events = list(csv.DictReader(f))
    by_robot = {int(e["robot_id"]): e for e in events}
    assert set(by_robot) == {1, 2}, events  # nobody else was moved
    assert abs(float(by_robot[1]["jump_m"]) - 1.0) < 0.1
    assert abs(float(by_robot[2]["jump_m"]) - math.hypot(0.5, 0.5)) < 0.1
    for rid, at_s in kidnaps.items():
        assert at_s < int(by_robot[rid]["stamp_ns"]) / 1e9 <= at_s + 3.0
    for rid in range(4):
        assert _final_error(kidnap_run, rid) < 0.10, rid


def test_the_grid_robots_all_end_within_10cm(tmp_path: Path) -> None:
    # a user's first command: 8 robots on a grid; before re-localisation a station-holding robot pushed by a
    # patrol ended 1.35 m wrong (its true observations were all gated out)
    run = _up(tmp_path / "run", "--robots", "8", "--set", 'robots.placement="grid"', "--duration", "30",
              "--seed", "2")
    errors = {rid: _final_error(run, rid) for rid in range(8)}
    assert max(errors.values()) < 0.10, errors
    # the run folder holds the poses the grid drew, not the draw (protocol/layout.pinned)
    robots = json.loads((run / "scenario.json").read_text())["robots"]
    assert robots["placement"] == "explicit" and len(robots["start"]) == 8
    firsts = [np.loadtxt(run / "trajectories" / f"truth_{rid}.tum", ndmin=2)[0] for rid in (0, 5)]
    assert firsts[0][1:4] == pytest.approx([0.0, 0.0, 0.0], abs=1e-3)  # truth in the map frame: the origin's start
    start0, start5 = robots["start"][0], robots["start"][5]
    d = math.hypot(start5["x_m"] - start0["x_m"], start5["y_m"] - start0["y_m"])
    assert math.hypot(firsts[1][1], firsts[1][2]) == pytest.approx(d, abs=1e-3)


def test_nudged_robots_follow_their_views_within_3_s(tmp_path: Path) -> None:
    # the nudge scene: robot 1 nudged 15 cm at 8 s and pushed 20 cm at 23 s, robot 2 turned 0.15 rad at 16 s.
    # The nudge passes the fusion's gate: before the odometry was loosened on consistent evidence, the views from
    # before it held robot 1 4-6 cm off until the push at 23 s (nudged at 10 s instead: 14 cm off for 20 s)
    run = _up(tmp_path / "run", "--scenario", "nudge")
    m = json.loads((run / "metrics.json").read_text())
    pushes = {(round(k["t_s"]), k["robot"]): k for k in m["kidnaps"]}
    assert set(pushes) == {(8, 1), (16, 2), (23, 1)}, pushes
    for at_s, rid in ((8, 1), (23, 1)):
        assert _thrown_off(run, rid, at_s, at_s + 0.2, 0.10), "the nudge did not throw the estimate off"
        back = pushes[(at_s, rid)]["time_to_relocalise_s"]
        assert back is not None and back <= 3.0, pushes[(at_s, rid)]
    # the nudge and the turn are followed, not re-placed (the 20 cm push may be either); nobody else is moved
    assert all(r["robot"] == 1 and r["t_s"] > 23.0 for r in m["relocalisations"]), m["relocalisations"]
    settled = {t: round(_error_at(run, 1, t), 3) for t in range(11, 23)}
    assert max(settled.values()) < 0.03, settled
    for rid in range(4):
        assert _final_error(run, rid) < 0.05, rid
    assert m["swarm"]["fused"]["time_localised"] >= 0.95


def test_a_depot_bay_dropped_at_random_ends_with_every_robot_within_10cm(tmp_path: Path) -> None:
    # a user's scene as written (depot_as_written.toml): 8 robots at random in a 10 m x 4 m bay; the first
    # placements chain through far views and leave the cluster 19 deg off (sigma 17 deg) for the first 7 s.
    # With a gate that left the observer's heading lever out of the predicted relative pose, the near views of
    # the origin that fix it were rejected, and three robots stayed 10-17 cm off to the end (time localised
    # 57 % over 45 s)
    scene = Path(__file__).with_name("depot_as_written.toml")
    # 36 s: after the push robot 1 sees only robot 4 until robot 5 sees robot 1 at 27.5 s, and a pair that
    # disagrees with nobody else waits for a third robot (server/recovery.py, lone_pair); robot 1 is back at 31.9 s
    run = _up(tmp_path / "run", "--scenario", str(scene), "--duration", "36")
    errors = {rid: _final_error(run, rid) for rid in range(8)}
    assert max(errors.values()) < 0.10, errors
    m = json.loads((run / "metrics.json").read_text())
    # every robot in somebody's view (or seeing somebody) within the last second; a patrol out of everyone's view
    # drifts on its odometry (robot 6: 8-20 cm at times between 11 and 27 s, depending on its route)
    seen = _in_view(run, (9.0, 22.0))
    late = {(rid, t): round(_error_at(run, rid, t), 3) for rid, t in seen}
    assert len(late) >= 12 and max(late.values()) < 0.10, late
    assert m["swarm"]["fused"]["time_localised"] >= 0.70


def test_a_pushed_robot_sure_of_itself_is_put_right_and_moves_nobody_it_sees(tmp_path: Path) -> None:
    # a user's scene as written (yard_as_written.toml): 10 robots at random among four pillars; robot 1 holds
    # station, sure of itself to 5 mm, and is pushed 16 cm and 0.1 rad at 25 s.  It sees robots 4, 5 and 8, which
    # nobody else sees then.  Trusting it, the server re-localised those three 0.36-0.43 m the wrong way and left
    # robot 1 itself 16 cm off (and robot 8, driving on its wrong estimate, later ran into a pillar)
    scene = Path(__file__).with_name("yard_as_written.toml")
    # 36 s: after the push robot 1 sees only robot 4 until robot 5 sees robot 1 at 27.5 s, and a pair that
    # disagrees with nobody else waits for a third robot (server/recovery.py, lone_pair); robot 1 is back at 31.9 s
    run = _up(tmp_path / "run", "--scenario", str(scene), "--duration", "36")
    m = json.loads((run / "metrics.json").read_text())
    assert [(round(k["t_s"]), k["robot"]) for k in m["kidnaps"]] == [(25, 1)]
    assert _thrown_off(run, 1, 25.0, 25.2, 0.10), "the push did not throw the estimate off"
    assert all(r["robot"] == 1 for r in m["relocalisations"]), m["relocalisations"]  # nobody it sees is moved
    errors = {rid: _final_error(run, rid) for rid in range(10)}
    assert max(errors.values()) < 0.05, errors  # measured: all within 1.8 cm at 36 s
    # the robots robot 1 sees after the push (4, 5 and 8 when the test was written; robot 8's patrol now goes
    # round the pillar by a planned way and leaves its view at 20 s, drifting 8 cm unseen)
    with (run / "observations.csv").open() as fh:
        after = {int(r["target_id"]) for r in csv.DictReader(fh)
                 if r["observer"] == "1" and r["target_kind"] == "robot" and float(r["stamp_ns"]) >= 25.5e9}
    assert after >= {4, 5}, after
    # none of them is moved by robot 1's views: no further off than at the push (robot 8, out of everyone's view
    # since 20 s, is 8 cm off then and 2 cm by 28 s; believing robot 1 moved them 0.36-0.43 m)
    seen = {(rid, t): round(_error_at(run, rid, t) - _error_at(run, rid, 25.0), 3)
            for rid in sorted(after) for t in (26.0, 27.0, 28.0, 29.0)}
    assert max(seen.values()) < 0.02, seen
