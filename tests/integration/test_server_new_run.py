"""A restarted world's first inputs can reach the server before that world's first
tick does (the server drains its inboxes in between).  They belong to the new run:
the server must carry them into the fresh map instead of losing them with the old
one.  When it lost them, a lockstep server then waited ``ack_timeout_s`` for
odometry it had already consumed, and the new run's map differed from a fresh
one's in the last digits (a flaky byte-for-byte comparison in the world-restart
end-to-end test).

The server node runs in this process, stepped by hand, so that the interleaving
is forced rather than left to chance."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import Bus, BusConfig, open_bus
from tagswarm.protocol.keys import Keys
from tagswarm.server import journal as jr
from tagswarm.server.config import build_config
from tagswarm.server.node import ServerNode
from tests.harness import client, endpoint

COV = (1e-4, 0, 0, 0, 1e-4, 0, 0, 0, 1e-4)
RUN = "newrun"
DT = 100_000_000
NEW_TICKS = 6


def _odom(rid: int, k: int, x: float) -> m.OdometryEstimate:
    return m.OdometryEstimate(seq=k, stamp_ns=k * DT, robot_id=rid, x_m=x, y_m=0.0, yaw_rad=0.0, cov=COV,
                              distance_m=abs(x))


def _obs(k: int) -> m.RelativeObservation:
    return m.RelativeObservation(seq=k, stamp_ns=k * DT, robot_id=0, target_kind="robot", target_id=1,
                                 x_m=2.0, y_m=1.0, yaw_rad=3.0, cov=COV, pose=m.Pose3(x_m=2.0, y_m=1.0, z_m=0.0),
                                 reprojection_rms_px=0.3, tag_ids=(11,), camera="front")


def _tick(run_id: str, k: int) -> m.Tick:
    return m.Tick(seq=k, stamp_ns=k * DT, run_id=run_id, step=k, dt_ns=DT, mode="lockstep")


class Rig:
    """A lockstep server node stepped by the test, two agents' tokens and a world session."""

    def __init__(self, ep: str, server_bus: Bus, agents: Bus, journal: Path | None) -> None:
        argv = ["--listen", ep, "--run", RUN, "--set", "robots.count=2", "--set", 'robots.placement="ring"',
                "--set", "missions=[]", "--set", 'clock.mode="lockstep"', "--set", "clock.ack_timeout_s=3.0"]
        if journal is not None:
            argv += ["--journal", str(journal)]
        self.keys = Keys(RUN)
        self.agents = agents
        for rid in (0, 1):
            agents.declare_token(self.keys.alive(f"agent/{rid}"))
        self.corr = agents.subscribe(self.keys.correction(1))
        self.node = ServerNode(build_config(argv, {}), server_bus)
        self._reached: list[Bus] = []
        assert server_bus.wait_for(lambda: self._presence() == {0, 1}, 10), "agent tokens never seen"

    def _presence(self) -> set[int]:
        self.node._drain()
        return self.node.alive

    def put(self, bus: Bus, key: str, msg: m.Msg) -> None:
        bus.put(key, codec.encode(msg))

    def inputs(self, k: int, x: float, *, observe: bool) -> None:
        for rid in (0, 1):
            self.put(self.agents, self.keys.odometry(rid), _odom(rid, k, x if rid == 1 else 0.0))
        if observe:
            self.put(self.agents, self.keys.observation(0), _obs(k))

    def wait_queued(self, n: int) -> None:
        def queued() -> bool:
            return len(self.node.odom_in) + len(self.node.obs_in) >= n

        assert self.node.bus.wait_for(queued, 10), "inputs never arrived"

    def reach(self, world: Bus) -> None:
        """Wait until ``world``'s session knows the server's tick subscription: a tick put before that is
        dropped.  Probe ticks are drained unread (the node never steps on one); one session's puts
        arrive in order, so once the last one sent is in, none is still on its way."""
        for probe in range(100):
            self.put(world, self.keys.tick(), m.Tick(seq=probe, stamp_ns=0, run_id="probe", step=0, dt_ns=DT,
                                                     mode="lockstep"))
            self.node.bus.wait_for(lambda: len(self.node.tick_in) > 0, 0.1)
            if probe in [codec.decode(m.Tick, it.value).seq for it in self.node.tick_in.drain()]:
                return
        raise AssertionError("the world's probe ticks never reached the server")

    def tick(self, world: Bus, run_id: str, k: int) -> None:
        if world not in self._reached:
            self.reach(world)
            self._reached.append(world)
        self.put(world, self.keys.tick(), _tick(run_id, k))
        assert self.node.bus.wait_for(lambda: len(self.node.tick_in) > 0, 10), "tick never arrived"
        assert self.node.step()

    def corrections(self) -> list[tuple[int, float, float, float]]:
        out = []
        for it in self.corr.drain():
            c = codec.decode(m.Correction, it.value)
            out.append((c.stamp_ns, c.x_m, c.y_m, c.yaw_rad))
        return out


@pytest.fixture
def net() -> Iterator[tuple[str, Bus, Bus]]:
    ep = endpoint()
    with open_bus(BusConfig(listen=(ep,))) as server_bus, client(ep) as agents:
        yield ep, server_bus, agents


def _new_run(rig: Rig, ep: str, *, early: bool) -> list[tuple[int, float, float, float]]:
    """Run ``old`` for 5 ticks, kill its world, start run ``new``; with ``early`` the new
    run's tick-0 inputs are drained by the server before it sees the new tick."""
    with client(ep) as world:
        world.declare_token(rig.keys.alive("world/0"))
        for k in range(5):
            rig.inputs(k, 0.5 + 0.1 * k, observe=True)
            rig.wait_queued(3)
            rig.tick(world, "old-1", k)
    # the old world is gone (its session closed); wait until the server saw its token vanish
    assert rig.node.bus.wait_for(lambda: len(rig.node.world_alive_in) > 0, 10), "the old world never left"
    rig.corrections()  # the old run's
    with client(ep) as world:
        world.declare_token(rig.keys.alive("world/0"))
        rig.inputs(0, 0.0, observe=True)
        rig.wait_queued(3)
        if early:
            assert not rig.node.step()  # no tick yet: the inputs go into the old map
            assert len(rig.node.odom_in) == 0
        for k in range(NEW_TICKS):
            if k:
                rig.inputs(k, 0.0, observe=True)
                rig.wait_queued(3)
            rig.tick(world, "new-2", k)
    return rig.corrections()


@pytest.mark.parametrize("with_journal", [False, True])
def test_new_runs_early_inputs_are_carried_into_the_fresh_map(net: tuple[str, Bus, Bus], tmp_path: Path,
                                                              with_journal: bool) -> None:
    ep, server_bus, agents = net
    journal = tmp_path / "server.journal" if with_journal else None
    rig = Rig(ep, server_bus, agents, journal)
    got = _new_run(rig, ep, early=True)
    c = rig.node.counters
    assert c["world_restarts"] == 1
    assert c["restart_carried"] == 3  # two odometry samples and one observation
    assert c["odometry_wait_timeouts"] == 0
    assert [s for s, *_ in got] == [k * DT for k in range(NEW_TICKS)]
    # robot 1 stands where robot 0 sees it: placed from the new run's observations alone
    assert abs(got[-1][1] - 2.0) < 0.01 and abs(got[-1][2] - 1.0) < 0.01, got
    if journal is not None:
        # the journal rebuilds the new run's map only: a NewRun record resets it, carried inputs follow it
        rig.node.close()
        records = list(jr.Reader(str(journal)))
        kinds = [type(r).__name__ for r in records]
        assert kinds.count("NewRun") == 1
        after = kinds[kinds.index("NewRun") + 1:]
        assert after[:3] == ["Odometry", "Odometry", "Observation"]
        fresh = build_config(["--run", RUN, "--set", "robots.count=2", "--set", 'robots.placement="ring"',
                              "--set", "missions=[]"], {})
        from tagswarm.server.node import make_fusion

        fusion = make_fusion(fresh)
        for r in records[1:]:
            jr.apply(fusion, r)
        pose = fusion.pose(1)
        assert pose is not None
        (x, y, _), _cov = pose
        assert (x, y) == pytest.approx(got[-1][1:3], abs=1e-9)


def test_new_run_matches_a_fresh_server_whatever_the_interleaving(net: tuple[str, Bus, Bus]) -> None:
    ep, server_bus, agents = net
    early = _new_run(Rig(ep, server_bus, agents, None), ep, early=True)
    ep2 = endpoint()
    with open_bus(BusConfig(listen=(ep2,))) as server_bus2, client(ep2) as agents2:
        late = _new_run(Rig(ep2, server_bus2, agents2, None), ep2, early=False)
    assert early == late


def test_a_tick_whose_world_died_is_abandoned_not_waited_for(net: tuple[str, Bus, Bus]) -> None:
    """The world dies after its tick reached the server but before the agents answered it: the
    server stops waiting at once (not after ``ack_timeout_s``) and neither fuses, corrects nor
    acknowledges that tick; the next world's run then starts normally."""
    ep, server_bus, agents = net
    rig = Rig(ep, server_bus, agents, None)
    acks = agents.subscribe(rig.keys.ack("server/0"))
    with client(ep) as world:
        world.declare_token(rig.keys.alive("world/0"))
        for k in range(3):
            rig.inputs(k, 0.0, observe=True)
            rig.wait_queued(3)
            rig.tick(world, "old-1", k)
        rig.put(world, rig.keys.tick(), _tick("old-1", 3))  # no agent answers this one
        assert rig.node.bus.wait_for(lambda: len(rig.node.tick_in) > 0, 10), "tick never arrived"
    assert rig.node.bus.wait_for(lambda: len(rig.node.world_alive_in) > 0, 10), "the old world never left"
    rig.node.step()
    assert rig.node.counters["ticks_abandoned"] == 1
    assert rig.node.counters["odometry_wait_timeouts"] == 0
    with client(ep) as world:
        world.declare_token(rig.keys.alive("world/0"))
        rig.inputs(0, 0.0, observe=True)
        rig.wait_queued(3)
        rig.tick(world, "new-2", 0)
    assert rig.node.counters["world_restarts"] == 1
    # the server's messages reach us in the order it sent them: every ack it sent came before the new one
    got: list[tuple[int, int]] = []

    def new_run_acked() -> bool:
        got.extend((a.step, a.stamp_ns) for a in (codec.decode(m.TickAck, it.value) for it in acks.drain()))
        return len(got) >= 4

    assert agents.wait_for(new_run_acked, 10), got
    assert [s for s, _ in got] == [0, 1, 2, 0]
    assert 3 * DT not in [s for s, *_ in rig.corrections()]
