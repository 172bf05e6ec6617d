"""Short-lived operator commands reach late-joined readers (loopback, free port).

A command publishes once and exits.  Here the "world" (a session holding the world's
liveliness token, so the command's liveliness wait passes at once) subscribes to nothing;
the reader is another process-like session that subscribes just before each command runs,
so a command that published as soon as it saw the token would race the subscription's
propagation.  Each command waits for its key's matching status (tagswarm.operator.reach)
and must be received, 20 times in a row; with nobody subscribed it exits 2 after its
--timeout with one line."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tagswarm.operator import goto, kidnap
from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import Bus, BusConfig, open_bus
from tagswarm.protocol.keys import Keys
from tests.harness import endpoint

KEYS = Keys("opdeliver")
ROUNDS = 20


@pytest.fixture
def hub(monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[str, Bus]]:
    """A listening session holding the world's and agent 4's liveliness tokens, no subscriber."""
    for var in ("TAGSWARM_RUN", "TAGSWARM_ZENOH_MODE", "TAGSWARM_LISTEN", "TAGSWARM_CONNECT", "ZENOH_CONFIG"):
        monkeypatch.delenv(var, raising=False)
    ep = endpoint()
    with open_bus(BusConfig(listen=(ep,))) as bus:
        bus.declare_token(KEYS.alive("world/0"))
        bus.declare_token(KEYS.alive("agent/4"))
        yield ep, bus


def _net(ep: str) -> list[str]:
    return ["--connect", ep, "--run", KEYS.run, "--log-level", "WARNING"]


def test_a_subscriber_that_joins_just_before_the_command_gets_it_every_time(
        hub: tuple[str, Bus], capsys: pytest.CaptureFixture[str]) -> None:
    ep, _ = hub
    got: list[m.WorldCommand] = []
    for i in range(ROUNDS):
        with open_bus(BusConfig(connect=(ep,))) as reader:
            inbox = reader.subscribe(KEYS.world_command())
            # --at: no world status to confirm it here, and without --at the command waits 2.5 s for one
            code = kidnap.main([str(i), str(0.25 * i), "-1.5", "--push", "--at", "0", "--timeout", "20", *_net(ep)])
            assert code == 0, capsys.readouterr().err
            assert reader.wait_for(inbox.__len__, 10.0), f"round {i}: the command never arrived"
            items = inbox.drain()
            assert len(items) == 1, f"round {i}: {len(items)} commands"
            got.append(codec.decode(m.WorldCommand, items[0].value))
    assert [(c.robot_id, c.x_m, c.y_m, c.action) for c in got] == [
        (i, 0.25 * i, -1.5, "push") for i in range(ROUNDS)]


def test_a_goal_reaches_a_late_joined_reader(hub: tuple[str, Bus], capsys: pytest.CaptureFixture[str]) -> None:
    ep, _ = hub
    with open_bus(BusConfig(connect=(ep,))) as reader:
        inbox = reader.subscribe(KEYS.goal(4))
        assert goto.main(["4", "1.5", "2.5", "--timeout", "20", *_net(ep)]) == 0, capsys.readouterr().err
        assert reader.wait_for(lambda: len(inbox) > 0, 10.0)
        goal = codec.decode(m.Goal, inbox.drain()[0].value)
    assert (goal.robot_id, goal.x_m, goal.y_m) == (4, 1.5, 2.5)


@pytest.mark.parametrize("command", ["kidnap", "goto"])
def test_a_command_nobody_subscribes_to_exits_2_with_one_line(
        hub: tuple[str, Bus], command: str, capsys: pytest.CaptureFixture[str]) -> None:
    ep, _ = hub
    main, key = (kidnap.main, KEYS.world_command()) if command == "kidnap" else (goto.main, KEYS.goal(4))
    assert main(["4", "1.0", "2.0", "--timeout", "1", *_net(ep)]) == 2
    cap = capsys.readouterr()
    lines = cap.err.splitlines()
    assert len(lines) == 1, cap.err
    assert lines[0].startswith(f"tagswarm {command}: error: nobody subscribes to {key} (waited ")
    assert "sent" not in cap.out
