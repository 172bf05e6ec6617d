"""The router's authentication and ACL (tagswarm/deploy/acl.py) with real Zenoh sessions on loopback.

A router configured exactly as ``tagswarm router --users FILE --acl`` does it runs in
this process; each role logs in as a Zenoh client with its own password file.  A
forged message is shown NOT to arrive by publishing a legitimate control message
after it on a path that would have delivered the forgery first: the same session
(one link, in order) or, across sessions, after a round trip through the router."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

import pytest

from tagswarm.deploy import acl, router
from tagswarm.protocol.bus import Bus, BusConfig, BusError, Inbox, open_bus
from tagswarm.protocol.keys import Keys
from tests.harness import endpoint

ROBOTS = (0, 1, 2)
TIMEOUT_S = 10.0
SYNC = b"sync"


class Net:
    """A router with the ACL of run ``keys.run`` and ROBOTS, and a way to log in to it."""

    def __init__(self, ep: str, keys: Keys, secrets: Path) -> None:
        self.ep, self.keys, self.secrets = ep, keys, secrets

    def login(self, user: str, password_file: Path | None = None) -> BusConfig:
        pw = password_file or self.secrets / f"{user}{acl.PASSWORD_SUFFIX}"
        return BusConfig(mode="client", connect=(self.ep,), user=user, password_file=str(pw))


@pytest.fixture
def net(tmp_path: Path) -> Iterator[Net]:
    keys = Keys("acl")
    secrets = tmp_path / "secrets"
    acl.make_secrets(secrets, acl.users(ROBOTS))
    ep = endpoint()
    args = router.parser().parse_args(["--listen", ep, "--run", keys.run, "--robots", str(len(ROBOTS)),
                                       "--users", str(secrets / acl.USERS_FILE), "--acl"])
    cfg = router.router_config(args, {})
    assert cfg.mode == "router" and cfg.access_control is not None and cfg.users_file is not None
    with open_bus(cfg):
        yield Net(ep, keys, secrets)


@contextmanager
def sessions(net: Net, *users: str) -> Iterator[list[Bus]]:
    with ExitStack() as stack:
        yield [stack.enter_context(open_bus(net.login(u))) for u in users]


def collect(bus: Bus, inbox: Inbox[bytes], until: str, timeout_s: float = TIMEOUT_S) -> list[str]:
    """Keys received by ``inbox`` until one equals ``until`` (asserts it comes), late
    :func:`synced` probes left out."""
    got: list[str] = []

    def done() -> bool:
        got.extend(item.key for item in inbox.drain() if item.value != SYNC)
        return until in got

    assert bus.wait_for(done, timeout_s), f"{until} never arrived; got {got}"
    return got


def synced(sender: Bus, key: str, receiver: Bus, inbox: Inbox[bytes]) -> None:
    """Publish on ``key`` until ``inbox`` has it: the router has the subscription."""
    for _ in range(int(TIMEOUT_S / 0.1)):
        sender.put(key, SYNC)
        if receiver.wait_for(lambda: len(inbox) > 0, 0.1):
            inbox.drain()
            return
    raise AssertionError(f"{key} never reached the subscriber")


def test_agent_reaches_its_own_keys_and_nothing_else(net: Net) -> None:
    k = net.keys
    with sessions(net, "agent1", "server", "viewer") as (agent, server, viewer):
        seen = viewer.subscribe(k.all())
        at_server = server.subscribe(k.observation())
        synced(agent, k.robot_status(1), viewer, seen)
        synced(agent, k.observation(1), server, at_server)

        legit = [k.observation(1), k.odometry(1), k.robot_status(1)]
        forged = [k.correction(1), k.observation(2), k.truth(1), k.map(), k.tick(), k.image(1, "front"),
                  k.ack("agent/2")]
        for key in [*legit, *forged]:
            agent.put(key, b"x")
        control = k.cmd(1)  # after the forgeries, on the same link: they would have come first
        agent.put(control, b"control")
        got = collect(viewer, seen, control)
        assert got == [*legit, control]
        assert collect(server, at_server, k.observation(1)) == [k.observation(1)]
        assert not any(item.key == k.observation(2) for item in at_server.drain())


def test_agent_cannot_subscribe_to_another_robot_or_forge_presence(net: Net) -> None:
    k = net.keys
    with sessions(net, "agent1", "world") as (agent, world):
        mine = agent.subscribe(k.images(1))
        theirs = agent.subscribe(k.images(2))  # declaration denied by the router
        synced(world, k.image(1, "front"), agent, mine)
        world.put(k.image(2, "front"), b"not for agent 1")
        world.put(k.image(1, "front"), b"control")
        assert collect(agent, mine, k.image(1, "front")) == [k.image(1, "front")]
        assert theirs.received == 0

        presence = world.watch_liveliness(k.alive_all())
        agent.declare_token(k.alive("agent/2"))  # not its own: denied
        agent.declare_token(k.alive("agent/1"))
        assert world.wait_for(lambda: any(c.key == k.alive("agent/1") for c in presence.drain()), TIMEOUT_S)
        # a liveliness query through the router can come back empty while the token is still
        # propagating (seen under load): ask until it answers, then judge the answer
        deadline, tokens = time.monotonic() + TIMEOUT_S, []
        while not tokens and time.monotonic() < deadline:
            tokens = world.alive_now(k.alive_all())
        assert tokens == [k.alive("agent/1")]
        assert not any(c.key == k.alive("agent/2") for c in presence.drain())


def test_viewer_only_watches_and_operator_may_send_goals(net: Net) -> None:
    k = net.keys
    with sessions(net, "viewer", "operator", "agent1") as (viewer, operator, agent):
        seen = operator.subscribe(k.all())
        goals = agent.subscribe(k.goal(1))
        synced(agent, k.robot_status(1), operator, seen)
        for key in (k.observation(1), k.correction(1), k.goal(1), k.map(), k.tick(), k.truth(0)):
            viewer.put(key, b"x")
        viewer.declare_token(k.alive("viewer/0"))
        # a round trip through the router: it has handled (and denied) everything above
        assert viewer.alive_now(k.alive_all()) == [k.alive("viewer/0")]  # its own, local token only
        agent.put(k.robot_status(1), b"control")
        assert collect(operator, seen, k.robot_status(1)) == [k.robot_status(1)]
        assert operator.alive_now(k.alive_all()) == []  # the viewer's token never got out

        operator.put(k.goal(1), b"go")  # the operator role may steer
        assert collect(agent, goals, k.goal(1)) == [k.goal(1)]


def test_the_server_hears_the_agents_acks_but_not_the_render_workers(net: Net) -> None:
    """A lockstep server tells a lost odometry message from a late one by the agent's tick ack."""
    k = net.keys
    with sessions(net, "agent1", "world", "server") as (agent, world, server):
        acks = server.subscribe(k.ack("agent/1"))
        render = server.subscribe(k.ack("render/0"))  # declaration denied by the router
        synced(agent, k.ack("agent/1"), server, acks)
        world.put(k.ack("render/0"), b"not for the server")
        # a round trip through the router after the render ack: it has handled (and not forwarded) it
        assert world.alive_now(k.alive_all()) == []
        agent.put(k.ack("agent/1"), b"control")
        assert collect(server, acks, k.ack("agent/1")) == [k.ack("agent/1")]
        assert render.received == 0


def test_map_queries_reach_the_server_only_from_allowed_roles(net: Net) -> None:
    k = net.keys
    with sessions(net, "server", "agent2", "world") as (server, agent, world):
        queries = server.queryable(k.map())
        stop = threading.Event()

        def answer() -> None:
            while not stop.is_set():
                for q in queries.drain():
                    server.reply(q.value, k.map(), b"map")
                server.wait(0.05)

        t = threading.Thread(target=answer, daemon=True)
        t.start()
        try:
            replies: list[bytes] = []
            # A get that no known queryable matches returns at once: wait by the clock,
            # not by a count of tries, until the router knows the queryable.
            deadline = time.monotonic() + 30.0
            while not replies and time.monotonic() < deadline:
                replies = [r.value for r in agent.get(k.map(), 0.5)]
                if not replies:
                    stop.wait(0.05)
            assert replies == [b"map"]
            assert world.get(k.map(), 0.5) == []  # the world has no business with the map
        finally:
            stop.set()
            t.join(5)


@pytest.mark.parametrize("user,password", [("agent1", "wrong"), ("nobody", "x"), ("agent1", None)])
def test_bad_credentials_cannot_connect(net: Net, tmp_path: Path, user: str, password: str | None) -> None:
    if password is None:  # no credentials at all
        cfg = BusConfig(mode="client", connect=(net.ep,))
    else:
        pw = tmp_path / "pw"
        pw.write_text(password + "\n")
        cfg = net.login(user, pw)
    with pytest.raises(BusError, match="cannot open Zenoh session"), open_bus(cfg):
        pass
