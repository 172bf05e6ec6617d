"""AgentNode's own account of what a frame costs (status counters read by bench/speed.py)."""

from __future__ import annotations

from tagswarm.agents.config import build_config
from tagswarm.agents.node import AgentNode
from tagswarm.protocol import codec
from tagswarm.protocol.bus import BusConfig, open_bus
from tagswarm.protocol.keys import Keys
from tagswarm.world.render import Renderer, image_message, pose_matrix
from tagswarm.world.sim import Sim
from tests.harness import endpoint, wait_alive


def test_the_agent_counts_the_cpu_of_its_frames_and_of_detect_and_pose_within_them() -> None:
    ep, run = endpoint(), "framecost"
    keys = Keys(run)
    cfg = build_config(["--robot-id", "0", "--run", run, "--listen", ep, "--fetch-map-timeout", "0",
                        "--set", "robots.count=2"], environ={})
    s = cfg.scenario
    cam = s.robot.cameras[0]
    with Sim(s) as sim, Renderer(s) as renderer:
        for rid in sim.robots:
            renderer.set_pose(rid, *sim.base_pose(rid))
        img = renderer.render(0, cam, pose_matrix(*sim.base_pose(0)))
    with open_bus(cfg.bus) as node_bus, open_bus(BusConfig(connect=(ep,))) as bus:
        node = AgentNode(cfg, node_bus)
        wait_alive(bus, keys, "agent/0")
        before = node.status_counters()
        assert (before["cpu_frames_us"], before["cpu_detect_pose_us"]) == (0, 0)
        for k in range(3):
            bus.put(keys.image(0, cam.name), codec.encode(image_message(s, 0, cam, img, seq=k, step=3 * k,
                                                                        stamp_ns=k * 100_000_000)))
            assert node_bus.wait_for(lambda: len(node.images[cam.name]) > 0, 5)
            node.step()
        c = node.status_counters()
    assert c["frames_processed"] == 3
    assert c["observations"] == 3  # robot 1 stands in robot 0's view at the start
    assert 0 < c["cpu_detect_pose_us"] < c["cpu_frames_us"]
