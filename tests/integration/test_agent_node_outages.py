"""AgentNode (realtime) when the server or the world goes away and comes back,
driven step by step by a fake world and a fake server on a loopback network."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager

import pytest

from tagswarm.agents.behaviour import Mode
from tagswarm.agents.config import build_config
from tagswarm.agents.node import AgentNode
from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import Bus, BusConfig, open_bus
from tagswarm.protocol.keys import Keys
from tests.harness import endpoint, wait_alive

RID = 1
DT = 33_333_333


@contextmanager
def _peer(ep: str, token: str | None, keys: Keys) -> Iterator[Bus]:
    """A process of its own on the network (its token vanishes when it closes)."""
    with open_bus(BusConfig(connect=(ep,))) as bus:
        if token is not None:
            bus.declare_token(keys.alive(token))
        yield bus


class Rig:
    """The agent under test plus helpers to feed it."""

    def __init__(self, stack: ExitStack, run: str) -> None:
        self.ep, self.keys = endpoint(), Keys(run)
        cfg = build_config(["--robot-id", str(RID), "--run", run, "--listen", self.ep, "--fetch-map-timeout", "0",
                            "--set", "robots.count=2"], environ={})
        self.bus = stack.enter_context(open_bus(cfg.bus))
        self.node = AgentNode(cfg, self.bus)
        self.tpr = cfg.scenario.encoders.ticks_per_rev
        self.status = self.bus.subscribe(self.keys.robot_status(RID))

    def settle(self, pred: Callable[[], bool], what: str) -> None:
        def check() -> bool:
            self.node.step()
            return pred()

        assert self.bus.wait_for(check, 10), what

    def encoders(self, world: Bus, k: int, ticks: int) -> None:
        world.put(self.keys.encoders(RID), codec.encode(m.EncoderTicks(
            seq=k, stamp_ns=k * DT, robot_id=RID, left_ticks=ticks, right_ticks=ticks, ticks_per_rev=self.tpr)))
        assert self.bus.wait_for(lambda: len(self.node.enc_in) > 0, 5)
        self.node.step()

    def tick(self, world: Bus, k: int, run_id: str) -> None:
        world.put(self.keys.tick(), codec.encode(m.Tick(seq=k, stamp_ns=k * DT, run_id=run_id, step=k, dt_ns=DT,
                                                        mode="realtime")))
        assert self.bus.wait_for(lambda: len(self.node.tick_in) > 0, 5)
        self.node.step()

    def correction(self, server: Bus, k: int, x: float, var: float = 1e-4, localised: bool = True) -> None:
        server.put(self.keys.correction(RID), codec.encode(m.Correction(
            seq=k, stamp_ns=k * DT, robot_id=RID, map_odom_x_m=x, map_odom_y_m=0.0, map_odom_yaw_rad=0.0,
            x_m=x, y_m=0.0, yaw_rad=0.0, cov=(var, 0, 0, 0, var, 0, 0, 0, 1e-4), last_fix_ns=k * DT,
            localised=localised)))
        assert self.bus.wait_for(lambda: len(self.node.corr_in) > 0, 5)
        self.node.step()

    def last_status(self) -> m.AgentStatus:
        self.node._publish_status()
        got: list[m.AgentStatus] = []

        def arrived() -> bool:
            got.extend(codec.decode(m.AgentStatus, it.value) for it in self.status.drain())
            return bool(got)

        assert self.bus.wait_for(arrived, 5)
        return got[-1]


@pytest.fixture
def rig() -> Iterator[Rig]:
    with ExitStack() as stack:
        yield Rig(stack, "agentfaults")


def test_without_a_server_the_agent_runs_on_odometry_and_takes_corrections_again_later(rig: Rig) -> None:
    node, keys = rig.node, rig.keys
    cmds = rig.bus.subscribe(keys.cmd(RID))
    with _peer(rig.ep, "world/0", keys) as world:
        wait_alive(world, keys, f"agent/{RID}")
        k = 0
        with _peer(rig.ep, "server/0", keys) as server:
            rig.settle(lambda: node.server_alive, "server token never seen")
            for k in range(5):
                rig.encoders(world, k, ticks=k * 20)
            rig.correction(server, 4, x=1.0)
            rig.encoders(world, 5, ticks=100)  # the next control cycle takes the fix
            assert node.map_odom == (1.0, 0.0, 0.0) and node.behaviour.mode == Mode.VISUAL
            searches = node.behaviour.searches  # one at start-up, before the first correction
        rig.settle(lambda: not node.server_alive, "server loss never noticed")
        # long past the point where it would search for a fix: it keeps its mission on odometry instead
        for k in range(6, 6 + 2 * node.s.agent.fix_threshold):
            rig.encoders(world, k, ticks=k * 20)
        st = rig.last_status()
        assert st.mode == "odometry" and st.counters["server_alive"] == 0 and st.counters["server_lost"] == 1, st
        assert st.counters["searches"] == searches and node.behaviour.counter > node.s.agent.fix_threshold
        assert node.map_odom == (1.0, 0.0, 0.0)  # the last correction still holds
        assert rig.bus.wait_for(lambda: len(cmds) >= k, 5)  # it kept commanding its wheels
        speeds = [codec.decode(m.WheelCommand, it.value) for it in cmds.drain()][-10:]
        assert all(c.left_rad_s != 0 or c.right_rad_s != 0 for c in speeds)
        # a server comes back: its corrections are taken, and the long blind stretch triggers a search
        with _peer(rig.ep, "server/0", keys) as server:
            rig.settle(lambda: node.server_alive, "returning server never seen")
            k += 1
            rig.encoders(world, k, ticks=k * 20)
            assert node.behaviour.mode == Mode.SEARCHING
            rig.correction(server, k, x=2.0)
            rig.encoders(world, k + 1, ticks=(k + 1) * 20)
            assert node.map_odom == (2.0, 0.0, 0.0) and node.counters["corrections"] == 2
            st = rig.last_status()
            assert st.counters["server_alive"] == 1 and st.mode == "visual", st


def test_a_restarted_world_resets_the_agent_and_a_foreign_run_is_rejected(rig: Rig) -> None:
    node, keys = rig.node, rig.keys
    with _peer(rig.ep, "server/0", keys) as server:
        with _peer(rig.ep, "world/0", keys) as world:
            wait_alive(world, keys, f"agent/{RID}")
            for k in range(40):
                rig.encoders(world, k, ticks=k * 40)
                rig.tick(world, k, "run-a")
            rig.correction(server, 39, x=1.0)
            moved = node.odom.x_m
            assert moved > 0.1 and node.map_odom is not None and node.run_id == "run-a"
            rig.tick(world, 40, "intruder")  # while the world is alive: foreign, ignored
            assert node.rejects.as_counters()["rejected_foreign_run"] == 1 and node.run_id == "run-a"
        rig.settle(lambda: node.runs.world_left, "world loss never noticed")
        with _peer(rig.ep, "world/0", keys) as world:
            # the new world's first counts may arrive before its first tick: not integrated as motion
            rig.encoders(world, 0, ticks=0)
            assert node.odom.x_m == moved and node.counters["stale_encoders"] == 1
            rig.tick(world, 0, "run-b")
            assert node.counters["world_restarts"] == 1 and node.run_id == "run-b"
            assert node.odom.x_m == 0.0 and node.map_odom is None and node.time_ns == 0
            assert node.behaviour.fixes == 0 and not node.pending_frames
            for k in range(1, 10):
                rig.encoders(world, k, ticks=k * 40)
            assert 0.0 < node.odom.x_m < moved  # integrates from the new counts, no jump
            # a correction the server made for the previous run is not applied to the new odometry
            rig.correction(server, 80, x=5.0)
            assert node.map_odom is None and node.counters["stale_corrections"] == 1


def test_a_placement_the_server_does_not_vouch_for_is_only_a_loose_pose_until_a_vouched_one(rig: Rig) -> None:
    node, keys = rig.node, rig.keys
    with _peer(rig.ep, "world/0", keys) as world, _peer(rig.ep, "server/0", keys) as server:
        rig.settle(lambda: node.server_alive, "server token never seen")
        for k in range(5):
            rig.encoders(world, k, ticks=k * 20)
        rig.correction(server, 4, x=3.0, var=0.8, localised=False)  # placed, sigma 0.9 m: not vouched for
        rig.encoders(world, 5, ticks=100)
        assert node.map_odom is None and node.loose_map_odom == (3.0, 0.0, 0.0)
        assert node.counters["corrections"] == 0 and node.behaviour.fixes == 0  # neither a fix nor a correction
        assert rig.last_status().counters["localised"] == 0
        rig.correction(server, 6, x=2.0)  # vouched for
        rig.encoders(world, 7, ticks=140)
        assert node.map_odom == (2.0, 0.0, 0.0) and node.counters["corrections"] == 1
        assert rig.last_status().counters["localised"] == 1 and node.vouched
        # in dispute (unvouched, its sigma small): ignored, it drives on as it was
        rig.correction(server, 8, x=2.7, var=1e-4, localised=False)
        rig.encoders(world, 9, ticks=180)
        assert node.map_odom == (2.0, 0.0, 0.0) and node.vouched
        # no longer vouched for (its sigma grew): the map's newest estimate and its sigma, flagged, not a correction
        rig.correction(server, 10, x=2.5, var=0.8, localised=False)
        rig.encoders(world, 11, ticks=220)
        assert node.map_odom == (2.5, 0.0, 0.0) and not node.vouched and node.map_cov is not None
        assert node.map_cov[0] == 0.8 and node.counters["corrections"] == 1 and node.loose_map_odom == (3.0, 0.0, 0.0)
        assert rig.last_status().counters["localised"] == 0
        rig.correction(server, 12, x=2.4)  # vouched for again
        rig.encoders(world, 13, ticks=260)
        assert node.vouched and node.map_odom == (2.4, 0.0, 0.0) and rig.last_status().counters["localised"] == 1


def _run_returns_within(node: AgentNode, timeout_s: float) -> bool:
    """Start ``node.run`` in a thread; whether it returned by itself within ``timeout_s`` (it is stopped after)."""
    import threading

    stop = threading.Event()
    t = threading.Thread(target=node.run, args=(stop,), daemon=True)
    t.start()
    t.join(timeout_s)
    returned = not t.is_alive()
    stop.set()
    t.join(10)
    return returned


def test_the_world_leaving_at_the_end_ends_the_run_even_if_its_last_counts_were_lost(rig: Rig) -> None:
    """The world's last encoder counts (stamped at the run's end) never arrive, e.g. lost when it closed
    over a lossy link: once it has been gone 2 s, the agent stops instead of running for ever."""
    keys, near_end = rig.keys, int(59.5e9 / DT)  # 0.5 s before the scenario's 60 s
    with _peer(rig.ep, "world/0", keys) as world:
        rig.tick(world, near_end, "w1")
        rig.encoders(world, near_end, 0)
    assert rig.node.time_ns < int(60e9)
    assert _run_returns_within(rig.node, 8.0)


def test_the_world_leaving_mid_run_is_waited_for(rig: Rig) -> None:
    keys = rig.keys
    with _peer(rig.ep, "world/0", keys) as world:
        rig.tick(world, 30, "w1")
        rig.encoders(world, 30, 0)
    assert not _run_returns_within(rig.node, 4.0)  # a restarted world may come back: the agent waits
