"""AgentNode driven step by step over a loopback Zenoh network."""

from __future__ import annotations

import itertools
import math

from tagswarm.agents.config import build_config
from tagswarm.agents.node import AgentNode
from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import BusConfig, open_bus
from tagswarm.protocol.geometry import se2_compose
from tagswarm.protocol.keys import Keys
from tests.harness import endpoint, wait_alive


def test_corrections_move_the_map_pose_but_never_the_odometry() -> None:
    ep, run = endpoint(), "agentnode"
    keys = Keys(run)
    cfg = build_config(["--robot-id", "1", "--run", run, "--listen", ep, "--fetch-map-timeout", "0",
                        "--set", "robots.count=2"], environ={})
    with open_bus(cfg.bus) as node_bus, open_bus(BusConfig(connect=(ep,))) as bus:
        node = AgentNode(cfg, node_bus)
        odom_out = bus.subscribe(keys.odometry(1))
        wait_alive(bus, keys, "agent/1")
        tpr = cfg.scenario.encoders.ticks_per_rev
        odoms: list[m.OdometryEstimate] = []
        pose_before = None
        for k in range(60):
            ticks = k * tpr // 100  # both wheels: straight ahead, ~3 mm per step
            bus.put(keys.encoders(1), codec.encode(m.EncoderTicks(seq=k, stamp_ns=k * 33_333_333, robot_id=1,
                                                                  left_ticks=ticks, right_ticks=ticks,
                                                                  ticks_per_rev=tpr)))
            if k == 30:
                pose_before = node.map_pose
                bus.put(keys.correction(1), codec.encode(m.Correction(
                    seq=0, stamp_ns=k * 33_333_333, robot_id=1, map_odom_x_m=2.0, map_odom_y_m=-1.0,
                    map_odom_yaw_rad=0.5, x_m=0.0, y_m=0.0, yaw_rad=0.0, cov=(0.01, 0, 0, 0, 0.01, 0, 0, 0, 0.01),
                    last_fix_ns=k * 33_333_333)))
            assert node_bus.wait_for(lambda: len(node.enc_in) > 0, 5)
            if k == 30:
                assert node_bus.wait_for(lambda: len(node.corr_in) > 0, 5)
            node.step()
        assert bus.wait_for(lambda: len(odom_out) >= 60, 5)
        odoms = [codec.decode(m.OdometryEstimate, it.value) for it in odom_out.drain()]
    steps = [math.hypot(b.x_m - a.x_m, b.y_m - a.y_m) for a, b in itertools.pairwise(odoms)]
    assert max(steps) < 0.005  # smooth: no jump at the correction
    assert pose_before is None  # robot 1 is not the origin: unlocalised before its first correction
    final = node.map_pose
    assert final is not None
    expected = se2_compose((2.0, -1.0, 0.5), (odoms[-1].x_m, odoms[-1].y_m, odoms[-1].yaw_rad))
    assert math.dist(final[:2], expected[:2]) < 1e-9
    assert node.behaviour.fixes >= 1  # a correction built on a new observation counts as a visual fix
    assert odoms[-1].cov[0] > odoms[1].cov[0] > 0  # covariance grows with distance
