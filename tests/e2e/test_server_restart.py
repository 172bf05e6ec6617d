"""Server crash and restart from its journal (real processes, lockstep, paper scenario).

World + 4 agents + a server writing ``--journal`` run in lockstep; the test
SIGKILLs the server mid-run, checks the swarm keeps running without it, starts a
new server on the same journal and checks that it resumes corrections quickly,
that no robot's fused pose jumps, that the rebuilt graph is the one the dead
server had (to floating-point rounding), and that every accepted measurement is in the journal.

Lockstep survives the kill: the world stops waiting for acks of a participant
whose liveliness token vanished, agents stop waiting for corrections of a dead
server, and the new server declares its token only after its replay (so the world
never waits on a server still rebuilding).
"""

from __future__ import annotations

import json
import math
import shutil
import signal
import time
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import BusConfig, open_bus
from tagswarm.protocol.geometry import Pose2, se2_compose, se2_inverse
from tagswarm.protocol.keys import Keys
from tagswarm.protocol.layout import arena_to_map
from tagswarm.server import journal as jr
from tagswarm.server.config import build_config
from tagswarm.server.node import make_fusion
from tests.harness import endpoint, process, script

ROBOTS = (0, 1, 2, 3)
DURATION_S = 24.0
KILL_AT_S = 10.0
OUTAGE_S = 3.0


def _scenario_args() -> list[str]:
    parts = json.dumps([f"agent/{r}" for r in ROBOTS] + ["server/0"])
    return ["--clock", "lockstep", "--seed", "3", "--duration", f"{DURATION_S:g}",
            "--set", f"clock.participants={parts}"]


def _dist(a: Pose2, b: Pose2) -> float:
    return math.hypot(a[0] - b[0], a[1] - b[1])


def test_server_killed_mid_run_resumes_from_its_journal(tmp_path: Path) -> None:
    ep, mine, run = endpoint(), endpoint(), "srvrestart"
    # every process connects to the world and to the test's own endpoint: what the test observes does not
    # depend on gossip discovery between peers (the processes still find each other as in any run)
    links = ["--connect", ep, "--connect", mine]
    keys = Keys(run)
    scen = _scenario_args()
    journal = tmp_path / "server.journal"
    # checkpoints every 4 simulated s: the restart replays from the last one before the kill (at >= 10 s)
    server_argv = [script("tagswarm-server"), *links, "--run", run, *scen, "--journal", str(journal),
                   "--journal-checkpoint", "4"]
    config = build_config(server_argv[1:], {})
    t_map_arena = arena_to_map(config.scenario)
    with ExitStack() as st:
        st.enter_context(process([script("tagswarm-world"), "--listen", ep, "--run", run, *scen],
                                 tmp_path / "world.log"))
        bus = st.enter_context(open_bus(BusConfig(listen=(mine,), connect=(ep,))))
        ticks = bus.subscribe(keys.tick())
        corr_in = bus.subscribe(keys.correction())
        truth_in = bus.subscribe(keys.truth())
        status_in = bus.subscribe(keys.server_status())
        robot_status_in = bus.subscribe(keys.robot_status())
        server_alive = bus.watch_liveliness(keys.alive("server/0"))
        server = st.enter_context(process(server_argv, tmp_path / "server1.log"))
        for rid in ROBOTS:
            st.enter_context(process([script("tagswarm-agent"), *links, "--run", run, *scen,
                                      "--robot-id", str(rid)], tmp_path / f"agent{rid}.log"))

        now_ns = 0
        last: dict[int, m.Correction] = {}  # newest localised correction per robot
        truth: dict[tuple[int, int], Pose2] = {}  # (robot, stamp) -> true pose in the map frame
        status: dict[str, int] = {}
        agents: dict[int, m.AgentStatus] = {}
        modes: dict[int, set[str]] = {r: set() for r in ROBOTS}
        first_after: dict[int, m.Correction] = {}
        restart_from_ns = -1
        before: dict[int, m.Correction] = {}  # the dead server's last correction of each robot
        wall0 = 0.0
        first_wall: dict[int, float] = {}  # wall s from the restart to each robot's first new correction

        def pump() -> None:
            nonlocal now_ns
            for it in ticks.drain():
                now_ns = max(now_ns, codec.decode(m.Tick, it.value).stamp_ns)
            for it in truth_in.drain():
                t = codec.decode(m.GroundTruthPose, it.value)
                truth[(t.robot_id, t.stamp_ns)] = se2_compose(t_map_arena, (t.x_m, t.y_m, t.yaw_rad))
            for it in corr_in.drain():
                c = codec.decode(m.Correction, it.value)
                if c.localised:
                    last[c.robot_id] = c
                    # the first that carries odometry newer than the dead server had: one sent before the new
                    # server heard from this robot is stamped with its last pose of the old run
                    if restart_from_ns >= 0 and c.robot_id not in first_after \
                            and c.pose_time_ns > before[c.robot_id].pose_time_ns:
                        first_after[c.robot_id] = c
                        first_wall[c.robot_id] = round(time.monotonic() - wall0, 2)
            for it in status_in.drain():
                status.clear()
                status.update(codec.decode(m.AgentStatus, it.value).counters)
            for it in robot_status_in.drain():
                a = codec.decode(m.AgentStatus, it.value)
                if a.robot_id is not None:
                    agents[a.robot_id] = a
                    modes[a.robot_id].add(a.mode)

        def until(pred: Callable[[], bool], timeout_s: float, what: str) -> None:
            def check() -> bool:
                pump()
                return pred()

            assert bus.wait_for(check, timeout_s), \
                f"{what} (t={now_ns / 1e9:.1f} s, corrected {sorted(last)}, server {status})"

        # ---- run with the first server until every robot is localised and the journal has observations
        until(lambda: now_ns >= KILL_AT_S * 1e9 and set(last) == set(ROBOTS)
              and status.get("accepted_observations", 0) > 20, 120, "swarm never got localised")
        server.send_signal(signal.SIGKILL)
        server.wait(10)
        kill_ns = now_ns
        gone = False

        def server_gone() -> bool:
            nonlocal gone
            gone = gone or any(not c.value for c in server_alive.drain())
            return gone

        until(server_gone, 10, "the server's liveliness never went away")
        status_before = dict(status)
        snapshot = tmp_path / "at_kill.journal"  # what the new server will find (it appends to the original)
        shutil.copyfile(journal, snapshot)

        # ---- the swarm keeps running on odometry: the world ticks on, agents keep processing frames.
        # Counted from when every agent has noticed the loss: until then a sighting (or a correction
        # in flight) is still a fix and may reset its odometry-only count
        until(lambda: all(agents[r].counters.get("server_alive") == 0 and agents[r].stamp_ns > kill_ns
                          for r in ROBOTS), 30, "agents never noticed the server was gone")
        agents_at_kill = {r: dict(a.counters) for r, a in agents.items()}
        for r in ROBOTS:
            modes[r].clear()  # from here on: the modes seen during the outage
        until(lambda: now_ns >= kill_ns + OUTAGE_S * 1e9, 60, "the world stopped without its server")
        until(lambda: all(agents[r].stamp_ns > kill_ns + 1e9 for r in ROBOTS), 30, "agents stopped reporting")
        for r in ROBOTS:
            c0, c1 = agents_at_kill[r], agents[r].counters
            assert c1["frames_processed"] > c0["frames_processed"], (r, c0, c1)
            assert c1["odometry_cycles"] >= c0["odometry_cycles"], (r, c0, c1)
        # nobody corrected them meanwhile (allowing for the tick the test had not seen yet at the kill)
        before.update(last)
        assert all(c.stamp_ns <= kill_ns + 1e8 for c in before.values()), (kill_ns, before)
        outage_modes = {r: sorted(modes[r]) for r in ROBOTS}
        # every agent said so in its status: on odometry alone, not searching or lost
        assert outage_modes == {r: ["odometry"] for r in ROBOTS}, outage_modes
        corrections_in_outage = {r: agents[r].counters.get("corrections", 0) for r in ROBOTS}

        # ---- a new server on the same journal
        restart_from_ns = now_ns
        wall0 = time.monotonic()
        server = st.enter_context(process(server_argv, tmp_path / "server2.log"))
        token_wall_s = -1.0  # start-up, imports, journal replay: until its liveliness token is back

        def resumed() -> bool:
            nonlocal token_wall_s
            if token_wall_s < 0 and any(c.value for c in server_alive.drain()):
                token_wall_s = time.monotonic() - wall0
            return set(first_after) == set(ROBOTS)

        until(resumed, 30, "the restarted server never corrected every robot")
        resume_wall_s = time.monotonic() - wall0
        resume_sim_s = (max(c.stamp_ns for c in first_after.values()) - restart_from_ns) / 1e9
        assert resume_sim_s < 3.0, resume_sim_s
        # In wall time (reported, not asserted): 0.9-2.5 s from the restart to every robot's correction with one
        # test at a time on this 2-core machine, 3-4 s with two more swarms running.  Nearly all of it is the new
        # process starting (interpreter and imports: ~0.6 s alone, gtsam ~0.15 s of it) before its token is back;
        # the journal rebuild is 50-200 ms (reported below) and the first corrections follow the token in ~40 ms

        jumps, drift, err_before, err_after = {}, {}, {}, {}
        for r in ROBOTS:
            b, a = before[r], first_after[r]
            # what the old correction would say now: the robot's odometry pose at the new stamp
            # (map->odom^-1 of the new fused pose) carried by the old map->odom
            odom_now = se2_compose(se2_inverse((a.map_odom_x_m, a.map_odom_y_m, a.map_odom_yaw_rad)),
                                   (a.x_m, a.y_m, a.yaw_rad))
            predicted = se2_compose((b.map_odom_x_m, b.map_odom_y_m, b.map_odom_yaw_rad), odom_now)
            jumps[r] = _dist(predicted, (a.x_m, a.y_m, a.yaw_rad))
            tb, ta = truth.get((r, b.pose_time_ns)), truth.get((r, a.pose_time_ns))
            assert tb is not None and ta is not None, (r, b.pose_time_ns, a.pose_time_ns)
            err_before[r] = _dist((b.x_m, b.y_m, b.yaw_rad), tb)
            err_after[r] = _dist((a.x_m, a.y_m, a.yaw_rad), ta)
            drift[r] = _dist(predicted, ta)  # the old correction carried over the outage: odometry drift
        numbers = {"restart_at_s": restart_from_ns / 1e9, "resume_sim_s": resume_sim_s, "jump_m": jumps,
                   "drift_m": drift, "err_before_m": err_before, "err_after_m": err_after}
        # The first new correction continues the dead server's map: it moves a robot no further than the
        # drift it corrects (a re-anchored map would move it by its own, unrelated offset).  The drift grows
        # with the outage, whose length in simulated time depends on how fast the machine restarts a process
        # (a lockstep world ticks on meanwhile), so neither is bounded on its own
        for r in ROBOTS:
            assert jumps[r] < drift[r] + 0.03, (r, numbers)
            assert err_after[r] < 0.15, (r, numbers)
        # and one simulated second later, with new observations fused, every robot is where it is
        settle_ns = max(c.stamp_ns for c in first_after.values()) + int(1e9)
        until(lambda: all(last[r].stamp_ns >= settle_ns for r in ROBOTS), 30, "no corrections after the restart")
        err_settled = {}
        for r in ROBOTS:
            t_now = truth.get((r, last[r].pose_time_ns))
            assert t_now is not None, (r, last[r].pose_time_ns)
            err_settled[r] = _dist((last[r].x_m, last[r].y_m, last[r].yaw_rad), t_now)
        assert max(err_settled.values()) < 0.05, (err_settled, numbers)

        # ---- the rebuilt graph is the dead server's: replaying the journal copied at the kill
        # reproduces its last published correction of every robot (to rounding).  The replay starts at
        # the last checkpoint, which holds the state right after its update (the Advance before it is
        # not replayed)
        fusion = make_fusion(config)
        rebuilt: dict[int, Pose2] = {}
        want = {r: before[r].stamp_ns for r in ROBOTS}

        def on_record(rec: jr.Record) -> None:
            jr.apply(fusion, rec)
            if isinstance(rec, jr.Advance | jr.Checkpoint):
                for r, stamp in want.items():
                    est = fusion.pose(r)
                    if rec.watermark_ns == stamp and est is not None:
                        rebuilt[r] = est[0]

        jr.Journal(snapshot, jr.header_for(run, fusion), replay=on_record).close()
        replay_gap = {r: _dist(rebuilt[r], (before[r].x_m, before[r].y_m, before[r].yaw_rad)) for r in ROBOTS}
        assert max(replay_gap.values()) < 1e-6, replay_gap
        at_kill = jr.read_journal(snapshot)[0]
        assert status_before["accepted"] <= sum(isinstance(x, jr.Odometry | jr.Observation) for x in at_kill)

        # ---- to the end: every accepted measurement (before and after the crash) is in the journal
        until(lambda: server.poll() is not None, 120, "the restarted server did not finish the run")
        assert server.returncode == 0
        records = jr.read_journal(journal)[0]
        measurements = sum(isinstance(x, jr.Odometry | jr.Observation) for x in records)
        until(lambda: status.get("journal_records") == measurements, 10,
              f"final status {status} vs {measurements} journal records")
        assert status["accepted"] == status["journal_records"] == measurements
        assert status["accepted"] > status_before["accepted"] and status["journal_truncated_bytes"] == 0
        # the restart replayed from a checkpoint, not from the start
        assert status["journal_replay_skipped"] > 0 and status["journal_checkpoints"] >= 2, status
        # and the agents took the new server's corrections
        assert all(agents[r].counters.get("corrections", 0) > corrections_in_outage[r] for r in ROBOTS), \
            (corrections_in_outage, {r: agents[r].counters for r in ROBOTS})
        print(json.dumps({"kill_at_s": kill_ns / 1e9, "resume_wall_s": round(resume_wall_s, 2),
                          "token_back_wall_s": round(token_wall_s, 2), "first_correction_wall_s": first_wall,
                          "resume_sim_s": round(resume_sim_s, 3), "replayed": status["journal_replayed"],
                          "replay_ms": status["journal_replay_ms"], "replay_skipped": status["journal_replay_skipped"],
                          "jump_m": jumps, "drift_m": drift, "err_before_m": err_before,
                          "err_after_m": err_after, "err_settled_m": err_settled, "accepted": status["accepted"],
                          "journal_records": measurements,
                          "fsyncs": status["journal_fsyncs"], "outage_modes": outage_modes}))
