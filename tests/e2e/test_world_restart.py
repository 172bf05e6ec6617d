"""The world crashes and a new world starts with the same scenario (new run id,
clock back at 0) under the same server and agents (real processes, lockstep).

The agents and the server notice the new run (a new ``run_id`` after the world's
liveliness token vanished) and reset.  The reset is complete when the second
world's run is exactly a fresh run: its trajectories are byte-identical to a
fault-free run of the same seed, which also shows the swarm localised again.
"""

from __future__ import annotations

import json
import math

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.testing import SwarmFactory
from tagswarm.testing.trajectories import recorded_errors as errors

KILL_AT_S = 6.0
#: the fault-free reference run (shared with the determinism and agent-restart tests: reuse=True)
PAPER_SEED = 3
PAPER_DURATION_S = 24.0


def test_agents_and_server_reset_on_a_new_world_and_localise_again(swarm: SwarmFactory) -> None:
    clean = swarm("paper", seed=PAPER_SEED, duration_s=PAPER_DURATION_S, reuse=True)
    with swarm.start("paper", seed=PAPER_SEED, duration_s=PAPER_DURATION_S, launch=False) as sw:
        scen = sw.scenario
        statuses = sw.bus.subscribe(sw.keys.robot_status())
        server_status = sw.bus.subscribe(sw.keys.server_status())
        ticks = sw.bus.subscribe(sw.keys.tick())
        sw.launch()
        first = sw.process("world")
        sw.wait_sim(KILL_AT_S)
        sw.kill("world")
        assert first.returncode != 0
        sw.recorder.poll()
        before = {rid: sw.recorder.fused_error(rid) for rid in scen.robot_ids}
        # everything of the first world is in; record the second one from scratch
        for series in (sw.recorder.truth, sw.recorder.odom, sw.recorder.fused):
            series.clear()
        sw.recorder.sim_ns = 0
        runs = {codec.decode(m.Tick, it.value).run_id for it in ticks.drain()}
        sw.spawn("world")
        sw.wait_exit()
        # a message of the first world still in flight when the series were cleared (stamped seconds
        # later than the second world's first ones) is not part of the second run
        leftovers = {rid: 0 for rid in scen.robot_ids}
        for series in (sw.recorder.truth, sw.recorder.odom, sw.recorder.fused):
            for rid, samples in series.items():
                cut = max((i for i in range(1, len(samples)) if samples[i][0] < samples[i - 1][0]), default=0)
                leftovers[rid] += cut
                del samples[:cut]
        restarted = sw.write()
        runs |= {codec.decode(m.Tick, it.value).run_id for it in ticks.drain()}
        agents = {}
        for it in statuses.drain():
            st = codec.decode(m.AgentStatus, it.value)
            agents[st.robot_id] = st.counters
        server = [codec.decode(m.AgentStatus, it.value).counters for it in server_status.drain()][-1]

    assert len(runs) == 2  # two world instances, both seen
    assert all(e is not None and e < 0.1 for e in before.values()), before  # localised before the crash
    for rid in scen.robot_ids:
        assert agents[rid]["world_restarts"] == 1, agents[rid]
        assert agents[rid].get("rejected_foreign_run", 0) == 0, agents[rid]
    assert server["world_restarts"] == 1, server
    # localised again after the restart, from scratch: small error a few seconds in ...
    errs = {rid: errors(sw.recorder.truth[rid], sw.recorder.fused[rid]) for rid in scen.robot_ids}
    for rid, es in errs.items():
        late = [e for t, e in es if t >= 5.0]
        assert len(late) > 100 and max(late) < 0.10, (rid, max(late, default=None))
    print(json.dumps({"error_before_kill_m": before,
                      "max_error_after_5s_m": {r: max(e for t, e in es if t >= 5.0) for r, es in errs.items()},
                      "stale_encoders_dropped": {r: c.get("stale_encoders", 0) for r, c in agents.items()},
                      "first_fused_s": {r: es[0][0] if es else math.nan for r, es in errs.items()},
                      "frames_missing": {r: c.get("frames_missing", 0) for r, c in agents.items()},
                      "stale_frames": {r: c.get("stale_frames", 0) for r, c in agents.items()},
                      "odometry_wait_timeouts": server.get("odometry_wait_timeouts", 0),
                      "restart_carried": server.get("restart_carried", 0),
                      "ticks_abandoned": {"server": server.get("ticks_abandoned", 0),
                                          **{r: c.get("ticks_abandoned", 0) for r, c in agents.items()}},
                      "first_world_leftovers": leftovers}, indent=1))
    # the new run's first inputs may reach the server before its first tick: they are carried into the
    # fresh map, not lost (losing them made the server wait ack_timeout_s for them, and the map differ)
    assert server.get("odometry_wait_timeouts", 0) == 0, server
    # ... and exactly as a fresh run: nothing of the first world leaked into the second
    for rid in scen.robot_ids:
        for kind in ("truth", "odom", "fused"):
            mine = (restarted.run_dir / "trajectories" / f"{kind}_{rid}.tum").read_bytes()
            ref = (clean.run_dir / "trajectories" / f"{kind}_{rid}.tum").read_bytes()
            assert mine == ref, f"{kind}_{rid}.tum after the restart differs from a fresh run"
