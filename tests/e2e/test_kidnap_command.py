"""``tagswarm kidnap`` against a real lockstep world process: the pushed robot's ground
truth jumps by exactly the commanded amount at the commanded step while its encoders
stand still; a push the world must refuse is counted, not applied."""

from __future__ import annotations

import math
import subprocess
from pathlib import Path

import pytest

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import Received
from tagswarm.protocol.keys import Keys
from tagswarm.runtime.lockstep import Participant
from tests.harness import client, endpoint, process, script, world_argv

SCENE = ['clock.mode="lockstep"', 'clock.participants=["agent/0"]', "clock.ack_timeout_s=60",
         "clock.command_timeout_s=5", "robots.count=2", 'robots.placement="explicit"', "seed=5",
         "robots.start=[{x_m=-1.0, y_m=0.0, yaw_rad=0.0}, {x_m=1.0, y_m=0.5, yaw_rad=3.0}]",
         'robot.cameras=[{name="front", width=64, height=48, rate_hz=1}]', "duration_s=60"]
PUSH = (0.3, -0.2, 0.4)  # m, m, rad in the arena frame
AT_STEP = 30  # --at 1.0 at 30 Hz
LAST_STEP = 45


def kidnap(ep: str, run: str, *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen([script("tagswarm"), "kidnap", *args, "--connect", ep, "--run", run, "--timeout", "30"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_kidnap_pushes_a_robot_at_the_commanded_step_and_its_encoders_do_not_see_it(tmp_path: Path) -> None:
    ep, run = endpoint(), "kidnap"
    keys = Keys(run)
    truths: dict[tuple[int, int], m.GroundTruthPose] = {}
    encoders: dict[int, list[tuple[int, int, int]]] = {0: [], 1: []}
    status: list[m.AgentStatus] = []
    argv = world_argv(ep, run, *SCENE, extra=("--status-period", "0.1"))
    with process(argv, tmp_path / "world.log") as world, client(ep) as bus:
        truth_in, enc_in = bus.subscribe(keys.truth()), bus.subscribe(keys.encoders())
        status_in, tick_in = bus.subscribe(keys.world_status()), bus.subscribe(keys.tick())
        bus.declare_token(keys.alive("agent/0"))
        me = Participant(bus, keys, "agent/0")
        pending: list[Received[bytes]] = []

        def got() -> bool:  # runs under the inbox lock: only drain
            pending.extend(tick_in.drain())
            return bool(pending)

        procs: list[subprocess.Popen[str]] = []
        seq, last = 0, -1
        while last < LAST_STEP:
            assert bus.wait_for(got, 60), f"world stopped ticking after step {last}; rc={world.poll()}"
            ticks, pending[:] = [codec.decode(m.Tick, it.value) for it in pending], []
            for tick in ticks:
                last = tick.step
                if tick.step == 2:  # sent long before they are due, by processes that take a while to start
                    procs.append(kidnap(ep, run, "1", str(PUSH[0]), str(PUSH[1]), "--yaw", str(PUSH[2]), "--push",
                                        "--at", "1.0"))
                    procs.append(kidnap(ep, run, "1", "-0.8", "0.0", "--at", "1.2"))  # onto robot 0: refused
                if tick.step == 20:  # hold the lockstep world until both commands are out
                    for p in procs:
                        out, err = p.communicate(timeout=60)
                        assert p.returncode == 0, err
                        assert "in the arena frame sent on tagswarm/kidnap/world/command" in out, out
                bus.put(keys.cmd(0), codec.encode(m.WheelCommand(seq=seq, stamp_ns=tick.stamp_ns, robot_id=0,
                                                                 left_rad_s=3.0, right_rad_s=3.5)))
                me.ack(tick)
                seq += 1
        for it in truth_in.drain():
            t = codec.decode(m.GroundTruthPose, it.value)
            truths[(t.robot_id, t.step)] = t
        for it in enc_in.drain():
            e = codec.decode(m.EncoderTicks, it.value)
            encoders[e.robot_id].append((e.stamp_ns, e.left_ticks, e.right_ticks))
        status = [codec.decode(m.AgentStatus, it.value) for it in status_in.drain()]

    # robot 1 never drives: its pose is constant but for the one push, which lands exactly at step 30
    before, after = truths[(1, AT_STEP - 1)], truths[(1, AT_STEP)]
    assert after.stamp_ns == AT_STEP * 33_333_333
    assert (after.x_m - before.x_m, after.y_m - before.y_m) == pytest.approx(PUSH[:2], abs=1e-6)
    assert math.remainder(after.yaw_rad - before.yaw_rad - PUSH[2], 2 * math.pi) == pytest.approx(0.0, abs=1e-6)
    for k in range(1, LAST_STEP + 1):
        if k != AT_STEP:
            prev, cur = truths[(1, k - 1)], truths[(1, k)]
            assert math.dist((prev.x_m, prev.y_m), (cur.x_m, cur.y_m)) < 1e-4, f"robot 1 moved at step {k}"
    # its wheels never turned: the encoders stay within the one tick a standing robot's slip noise may flip
    enc1 = encoders[1]
    assert len(enc1) >= LAST_STEP
    assert all(abs(left - enc1[0][1]) <= 1 and abs(right - enc1[0][2]) <= 1 for _, left, right in enc1)
    # robot 0 drove all along, its wheels did turn
    assert encoders[0][-1][1] - encoders[0][0][1] > 500
    final = status[-1].counters
    assert (final["world_commands"], final["world_command_rejected"]) == (1, 1), final
    assert final["contacts_robot_robot"] == 0 and final["contacts_robot_1"] == 0
    log = (tmp_path / "world.log").read_text()
    assert "command: push robot 1 by (0.300 m, -0.200 m, 0.400 rad)" in log
    assert "would overlap robot 0" in log


def test_kidnap_bad_arguments_exit_2_and_no_world_exits_1() -> None:
    bad = subprocess.run([script("tagswarm"), "kidnap", "1", "nan", "0"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2
    assert bad.stderr.strip().splitlines() == ["tagswarm kidnap: error: X and Y must be finite numbers (metres), "
                                               "got nan, 0.0"]
    lonely = subprocess.run([script("tagswarm"), "kidnap", "1", "0", "0", "--connect", endpoint(), "--run", "nobody",
                             "--timeout", "0.5"], capture_output=True, text=True, timeout=60)
    assert lonely.returncode == 1
    assert "the world is not alive on run 'nobody'" in lonely.stderr and len(lonely.stderr.splitlines()) == 1
