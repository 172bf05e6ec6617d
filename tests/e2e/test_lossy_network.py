"""Lossy network (issue 7): every process drops a seeded share of what it receives
on the default fault keys (encoders, commands, goals, observations, odometry, map;
see ``protocol/netfaults.py``).  Lockstep runs of ``tagswarm up --net-loss`` against
a clean run of the same seed: the fused error stays close at 10 % loss of
observations AND odometry, the run converges at 30 %, the losses are reported as
sequence gaps per sender that match the drops each process injected, the lockstep
server learns of every lost odometry message from the agent's tick ack instead of
waiting ``clock.ack_timeout_s`` for it, and a seeded loss pattern repeats byte for
byte."""

from __future__ import annotations

import json
import math
import subprocess
from pathlib import Path

import numpy as np
import pytest

from tests.harness import script

DURATION_S = 20
MAP_RATE_HZ = 2.0  # the server's default --map-rate


def _run(out: Path, *extra: str) -> dict:
    res = subprocess.run([script("tagswarm"), "up", "--duration", str(DURATION_S), "--clock", "lockstep",
                          "--seed", "3", "--out", str(out), "--no-live", *extra],
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    return {"metrics": json.loads((out / "metrics.json").read_text()),
            "run": json.loads((out / "run.json").read_text())}


def _final_error(out: Path, rid: int) -> float:
    truth = np.loadtxt(out / "trajectories" / f"truth_{rid}.tum", ndmin=2)
    fused = np.loadtxt(out / "trajectories" / f"fused_{rid}.tum", ndmin=2)
    i = int(np.argmin(np.abs(fused[:, 0] - truth[-1, 0])))
    return math.hypot(fused[i, 1] - truth[-1, 1], fused[i, 2] - truth[-1, 2])


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, dict]]:
    base = tmp_path_factory.mktemp("lossy")
    out = {}
    for name, extra in (("clean", ()), ("loss10", ("--net-loss", "0.1")), ("loss30", ("--net-loss", "0.3")),
                        ("loss30_again", ("--net-loss", "0.3"))):
        out[name] = (base / name, _run(base / name, *extra))
    return out


def _ate(r: dict) -> float:
    return float(r["metrics"]["swarm"]["fused"]["ate_unaligned"]["rmse"])


def test_ten_percent_loss_keeps_the_fused_error_within_twice_the_clean_run(runs) -> None:
    clean, lossy = _ate(runs["clean"][1]), _ate(runs["loss10"][1])
    # 5 mm of slack: the clean ATE is itself only ~5 mm, so "twice" alone would hinge on a few mm
    # that the loss pattern (which observations go) moves either way
    assert lossy <= 2.0 * clean + 0.005, (clean, lossy)


def test_thirty_percent_loss_still_converges(runs) -> None:
    path, r = runs["loss30"]
    assert _ate(r) < 0.05, _ate(r)
    for rid in r["run"]["robots"]:
        assert _final_error(path, rid) < 0.10, rid


def test_a_seeded_loss_pattern_repeats_byte_for_byte(runs) -> None:
    """Lockstep with loss is still deterministic: the server gives up on an odometry message once
    the agent's ack (sent after it) is in and a short grace has passed; a message the injector
    dropped never comes, so which ones are fused does not depend on timing."""
    first, again = runs["loss30"][0], runs["loss30_again"][0]
    for rid in runs["loss30"][1]["run"]["robots"]:
        for kind in ("truth", "odom", "fused"):
            name = f"trajectories/{kind}_{rid}.tum"
            assert (first / name).read_bytes() == (again / name).read_bytes(), name
    assert runs["loss30"][1]["run"]["counters"]["server"]["odometry_lost"] == \
        runs["loss30_again"][1]["run"]["counters"]["server"]["odometry_lost"]


@pytest.mark.parametrize("name, share", [("loss10", 0.1), ("loss30", 0.3)])
def test_losses_are_reported_as_sequence_gaps_matching_the_drops(runs, name: str, share: float) -> None:
    counters = runs[name][1]["run"]["counters"]
    clean = runs["clean"][1]["run"]["counters"]
    robots = runs[name][1]["run"]["robots"]
    for rid in robots:
        a = counters[f"agent/{rid}"]
        assert not any(k.startswith("seq_gaps") for k in clean[f"agent/{rid}"]), clean[f"agent/{rid}"]
        # the agent's faulted inputs are its encoders and the server's map (collision avoidance; no
        # goals are sent): every encoder drop but the trailing ones shows as a gap, and the map
        # (MAP_RATE_HZ, not sequence-counted by the agent) loses at most as large a share of its messages
        maps = DURATION_S * MAP_RATE_HZ + 1
        map_drops = math.ceil(1.6 * share * maps)
        assert a["net_dropped"] - 2 - map_drops <= a.get("seq_gaps_encoders", 0) <= a["net_dropped"], a
        rate = json.loads((runs[name][0] / "scenario.json").read_text())["encoders"]["rate_hz"]
        ticks = DURATION_S * rate
        assert 0.5 * share * ticks <= a["net_dropped"] <= 1.6 * share * (ticks + maps), a
    server, clean_server = counters["server"], clean["server"]
    assert not any(k.startswith("seq_gaps") for k in clean_server), clean_server
    assert clean_server.get("odometry_lost", 0) == 0, clean_server
    # the server's faulted inputs are observations and odometry.  Every agent sends one odometry
    # message per tick, as many as in the clean run (lockstep, same seed): what the lossy server
    # did not accept was dropped by its injector
    sent = clean_server["accepted_odometry"]
    odom_dropped = sent - server["accepted_odometry"]
    assert server.get("odometry_late", 0) == 0, server
    assert 0.5 * share * sent <= odom_dropped <= 1.6 * share * sent, (odom_dropped, sent)
    # every one is reported: found lost at its tick (the agent's ack came, the odometry did not), but for a
    # drop in a robot's last tick, whose ack the run's end may cut off (seen once in ~10 runs: 721 of 722) ...
    assert odom_dropped - len(robots) <= server["odometry_lost"] <= odom_dropped, (server["odometry_lost"],
                                                                                   odom_dropped)
    odom_gaps = {rid: server.get(f"seq_gaps_odometry_robot{rid}", 0) for rid in robots}
    assert all(g > 0 for g in odom_gaps.values()), odom_gaps
    # ... and as sequence gaps per robot (all but each robot's trailing drops)
    assert odom_dropped - len(robots) <= sum(odom_gaps.values()) <= odom_dropped, (odom_gaps, odom_dropped)
    obs_dropped = server["net_dropped"] - odom_dropped
    obs_gaps = sum(v for k, v in server.items() if k.startswith("seq_gaps_observations_robot"))
    assert obs_dropped > 0
    assert obs_dropped - len(robots) ** 2 <= obs_gaps <= obs_dropped, server
    # and the lost odometry cost no waiting: the server stopped waiting at each agent's ack, the
    # world never had to skip anyone (each timeout would have cost clock.ack_timeout_s = 5 s)
    assert server.get("odometry_wait_timeouts", 0) == 0, server
    assert counters["world"].get("ack_timeouts", 0) == 0, counters["world"]
