"""Teleports and pushes: the schedule (world/interventions.py), the world node applying
WorldCommands and scenario events (on an in-memory bus), scenario ``[[events]]``
validation and ``tagswarm kidnap``'s argument handling.  No network."""

from __future__ import annotations

import logging
import math
import threading
from typing import Any, cast

import msgspec
import pytest

from tagswarm.operator import kidnap, reach
from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import Bus, BusConfig, Inbox
from tagswarm.protocol.keys import Keys
from tagswarm.protocol.scenario import Scenario, ScenarioError, load_scenario, validate
from tagswarm.world.config import WorldConfig
from tagswarm.world.interventions import MAX_PENDING, Schedule
from tagswarm.world.node import WorldNode

DT = 33_333_333  # ns, 30 Hz
BASE = ["robots.count=2", 'robots.placement="explicit"', "clock.command_timeout_s=1000",
        "robots.start=[{x_m=-1.0, y_m=0.0, yaw_rad=0.0}, {x_m=1.0, y_m=0.5, yaw_rad=3.0}]",
        'robot.cameras=[{name="front", width=32, height=24, rate_hz=1}]']


def command(robot: int, action: str, x: float, y: float, yaw: float = 0.0, stamp_ns: int = 0) -> m.WorldCommand:
    return m.WorldCommand(seq=0, stamp_ns=stamp_ns, robot_id=robot, action=action,  # type: ignore[arg-type]
                          x_m=x, y_m=y, yaw_rad=yaw)


# ---------------------------------------------------------------------------------------------- schedule


def test_schedule_orders_by_due_time_then_arrival_with_events_first() -> None:
    s = load_scenario("paper", [*BASE, 'events=[{at_s=1.0, robot=0, action="push", x_m=0.1, y_m=0.0},'
                                       ' {at_s=0.1, robot=1, action="teleport", x_m=0.0, y_m=1.0, yaw_rad=7.0}]'])
    sched = Schedule(s.events, tick_hz=30.0, dt_ns=DT)
    assert sched.add(command(1, "push", 0.2, 0.0, stamp_ns=30 * DT))
    assert sched.add(command(0, "teleport", 0.0, 0.0, stamp_ns=0))
    first = sched.pop_due(0)
    assert [iv.source for iv in first] == ["command"] and first[0].robot_id == 0  # stamp 0: the next step
    assert sched.pop_due(2 * DT) == []
    due3 = sched.pop_due(3 * DT)  # at_s=0.1 is tick 3 (0.1 * 30 = 3.0000000000000004)
    assert [iv.source for iv in due3] == ["events[1]"]
    assert due3[0].target(5.0, 5.0, 1.0) == pytest.approx((0.0, 1.0, 7.0 - 2 * math.pi))
    assert sched.pop_due(29 * DT) == []
    # at_s=1.0 is tick 30 although its stamp is 0.99999999 s; the command stamped 30 * DT comes after it
    due30 = sched.pop_due(30 * DT)
    assert [iv.source for iv in due30] == ["events[0]", "command"]
    assert due30[0].target(1.0, 2.0, 3.0) == pytest.approx((1.1, 2.0, 3.0))
    assert due30[1].target(1.0, 2.0, 3.0) == pytest.approx((1.2, 2.0, 3.0))
    assert len(sched) == 0


def test_schedule_refuses_beyond_its_capacity() -> None:
    sched = Schedule((), tick_hz=30.0, dt_ns=DT)
    assert all(sched.add(command(0, "push", 0.0, 0.0, stamp_ns=10**15)) for _ in range(MAX_PENDING))
    assert not sched.add(command(0, "push", 0.0, 0.0))
    assert len(sched) == MAX_PENDING


# ---------------------------------------------------------------------------------------------- world node


class FakeBus:
    """The part of :class:`tagswarm.protocol.bus.Bus` the world node uses, in memory."""

    def __init__(self) -> None:
        self._wake = threading.Condition()
        self.inboxes: dict[str, Inbox[Any]] = {}
        self.sent: list[tuple[str, bytes]] = []

    def subscribe(self, key: str, *, newest_only: bool = False, capacity: int = 65536) -> Inbox[bytes]:
        inbox: Inbox[bytes] = Inbox(self._wake, newest_only=newest_only, capacity=capacity)
        self.inboxes[key] = inbox
        return inbox

    def watch_liveliness(self, key: str) -> Inbox[bool]:
        return Inbox(self._wake, newest_only=False, capacity=16)

    def declare_token(self, key: str) -> None:
        pass

    def put(self, key: str, payload: bytes, *, drop: bool = False) -> None:
        self.sent.append((key, payload))

    def wait_for(self, predicate: Any, timeout_s: float) -> bool:
        return bool(predicate())

    def fault_stats(self) -> dict[str, int]:
        return {"net_dropped": 0, "net_delayed": 0}


def make_node(s: Scenario) -> tuple[WorldNode, FakeBus, Keys]:
    bus = FakeBus()
    node = WorldNode(WorldConfig(scenario=s, bus=BusConfig(), run="t"), cast(Bus, bus))
    return node, bus, Keys("t")


def truth(bus: FakeBus, keys: Keys, rid: int) -> dict[int, m.GroundTruthPose]:
    """Robot ``rid``'s ground truth by step."""
    out = {}
    for key, payload in bus.sent:
        if key == keys.truth(rid):
            t = codec.decode(m.GroundTruthPose, payload)
            out[t.step] = t
    return out


def ticks(bus: FakeBus, keys: Keys, rid: int) -> list[tuple[int, int]]:
    return [(e.left_ticks, e.right_ticks) for key, p in bus.sent if key == keys.encoders(rid)
            for e in [codec.decode(m.EncoderTicks, p)]]


def status(node: WorldNode, bus: FakeBus, keys: Keys) -> dict[str, int]:
    node._publish_status()
    return codec.decode(m.AgentStatus, [p for k, p in bus.sent if k == keys.world_status()][-1]).counters


def test_world_applies_commands_and_events_at_their_step_and_refuses_bad_ones(
        caplog: pytest.LogCaptureFixture) -> None:
    s = load_scenario("paper", [*BASE, 'events=[{at_s=0.2, robot=0, action="teleport", x_m=0.5, y_m=-1.5,'
                                       ' yaw_rad=1.0}, {at_s=0.3, robot=0, action="push", x_m=9.0, y_m=0.0}]'])
    caplog.set_level(logging.INFO, logger="tagswarm.world")
    node, bus, keys = make_node(s)
    cmds = bus.inboxes[keys.world_command()]
    cmds.put(keys.world_command(), codec.encode(command(1, "push", -0.3, 0.2, -0.5, stamp_ns=10 * DT)))
    cmds.put(keys.world_command(), codec.encode(command(7, "teleport", 0.0, 0.0)))  # no robot 7
    cmds.put(keys.world_command(), codec.encode(command(1, "teleport", 3.44, 0.0, stamp_ns=12 * DT)))  # a wall
    cmds.put(keys.world_command(), b"\x93garbage")
    try:
        for _ in range(16):
            node.step()
        r0, r1 = truth(bus, keys, 0), truth(bus, keys, 1)
        assert (r0[5].x_m, r0[5].y_m) == pytest.approx((-1.0, 0.0), abs=1e-9)
        assert (r0[6].x_m, r0[6].y_m, round(r0[6].yaw_rad, 9)) == (0.5, -1.5, 1.0)  # the event, exactly
        assert (r0[9].x_m, r0[9].y_m) == pytest.approx((0.5, -1.5), abs=1e-4)  # the push into the wall was refused
        before, after = r1[9], r1[10]
        assert after.x_m - before.x_m == pytest.approx(-0.3, abs=1e-4)
        assert after.y_m - before.y_m == pytest.approx(0.2, abs=1e-4)
        assert math.remainder(after.yaw_rad - before.yaw_rad + 0.5, 2 * math.pi) == pytest.approx(0.0, abs=1e-4)
        assert (after.v_m_s, after.omega_rad_s) == (0.0, 0.0)
        assert r1[12].x_m == pytest.approx(r1[11].x_m, abs=1e-4)  # the teleport into the wall was refused
        for rid in (0, 1):  # the wheels never turned (a standing robot's slip noise may flip the last tick)
            enc = ticks(bus, keys, rid)
            assert len(enc) == 16 and all(abs(a - b) <= 1 for e in enc for a, b in zip(e, enc[0], strict=True))
        c = status(node, bus, keys)
        assert (c["world_commands"], c["world_events"], c["world_command_rejected"]) == (1, 1, 3)
        assert c["rejected_malformed"] == 1
        assert c["contacts_robot_wall"] == 0 and c["contacts_robot_0"] == 0 and c["contacts_robot_1"] == 0
    finally:
        node.close()
    log = caplog.text
    assert "events[0]: teleport robot 0 to (0.500 m, -1.500 m, 1.000 rad)" in log
    assert "robot 7 is not in the roster" in log
    assert "events[1]: push robot 0 by (9.000 m" in log and "would not be inside the arena walls" in log
    assert "refused command: teleport robot 1 to (3.440 m, 0.000 m, 0.000 rad)" in log


def test_a_command_lands_on_its_stamped_step_whenever_it_arrives() -> None:
    """Lockstep repeatability: the same command, arriving before step 1 in one run and before
    step 9 in another, gives byte-identical ground truth and encoders."""
    s = load_scenario("paper", BASE)

    def run(arrive_before: int) -> list[tuple[str, bytes]]:
        node, bus, keys = make_node(s)
        try:
            for k in range(20):
                if k == arrive_before:
                    bus.inboxes[keys.world_command()].put(keys.world_command(), codec.encode(
                        command(1, "teleport", -0.5, 1.5, 2.0, stamp_ns=10 * DT)))
                for rid in (0, 1):
                    bus.inboxes[keys.cmd()].put(keys.cmd(rid), codec.encode(m.WheelCommand(
                        seq=k, stamp_ns=node.time_ns, robot_id=rid, left_rad_s=5.0, right_rad_s=6.0 + rid)))
                node.step()
            assert (truth(bus, keys, 1)[10].x_m, truth(bus, keys, 1)[10].y_m) == (-0.5, 1.5)
            return [(k, p) for k, p in bus.sent if k.endswith(("/truth", "/encoders"))]
        finally:
            node.close()

    a, b = run(1), run(9)
    assert len(a) > 40 and a == b


# ---------------------------------------------------------------------------------------------- scenario events


@pytest.mark.parametrize(("event", "message"), [
    ('{at_s=-0.5, robot=1, action="push", x_m=0.5, y_m=0.0}', "events[0].at_s=-0.5 must be >= 0"),
    ('{at_s=1.0, robot=1, action="fly", x_m=0.5, y_m=0.0}', "field 'events[0].action'"),
    ('{at_s=1.0, robot=1, action="teleport", x_m=3.4, y_m=0.0}', "events[0]: teleport to (3.40, 0.00) is outside"),
    ('{at_s=1.0, robot=1, action="teleport", x_m=nan, y_m=0.0}', "field 'events[0].x_m' must be a finite number"),
    ('{at_s=1.0, robot=1, action="teleport", x_m=0.0}', "field 'events[0]'"),  # y_m missing
    ('{at_s=1.0, robot=1, action="teleport", x_m=0.0, y_m=0.0, z_m=1.0}', "unknown field `z_m`"),
])
def test_scenario_events_are_validated_naming_the_field(event: str, message: str) -> None:
    with pytest.raises(ScenarioError) as exc:
        load_scenario("paper", [*BASE, f"events=[{event}]"])
    text = str(exc.value)
    assert message in text and "\n" not in text


def test_scenario_event_for_a_robot_not_in_the_scenario() -> None:
    # load_scenario drops the events of robots beyond robots.count (so --robots 2 works on any scenario);
    # a scenario built otherwise (JSON handed between processes, code) is checked by validate
    table = msgspec.to_builtins(load_scenario("paper", BASE))
    table["events"] = [{"at_s": 1.0, "robot": 2, "action": "push", "x_m": 0.5, "y_m": 0.0}]
    with pytest.raises(ScenarioError, match=r"^events\[0\]\.robot=2 is not a robot of this scenario \(0\.\.1\)$"):
        validate(msgspec.convert(table, Scenario))


def test_scenario_events_load_with_defaults() -> None:
    s = load_scenario("paper", [*BASE, 'events=[{at_s=0, robot=1, action="push", x_m=0.5, y_m=-0.25}]'])
    ev = s.events[0]
    assert (ev.at_s, ev.robot, ev.action, ev.x_m, ev.y_m, ev.yaw_rad) == (0.0, 1, "push", 0.5, -0.25, 0.0)
    assert load_scenario("paper").events == ()


# ---------------------------------------------------------------------------------------------- tagswarm kidnap


def test_kidnap_stamps_round_up_to_a_world_tick() -> None:
    assert kidnap.stamp_for(1.0, DT) == 30 * DT  # 1 s is tick 30 (0.99999999 s)
    assert kidnap.stamp_for(0.5, DT) == 15 * DT
    assert kidnap.stamp_for(0.51, DT) == 16 * DT
    assert kidnap.stamp_for(0.0, DT) == 0
    assert kidnap.stamp_for(0.25, None) == 250_000_000
    cmd = kidnap.make_command(3, 1.0, -2.0, 0.5, push=True, stamp_ns=7)
    assert (cmd.robot_id, cmd.action, cmd.x_m, cmd.y_m, cmd.yaw_rad, cmd.stamp_ns) == (3, "push", 1.0, -2.0, 0.5, 7)
    assert codec.decode(m.WorldCommand, codec.encode(cmd)) == cmd
    assert kidnap.make_command(3, 1.0, -2.0, 0.0, push=False).action == "teleport"


@pytest.mark.parametrize("argv", [
    ["1", "nan", "0"], ["1", "0"], ["-1", "0", "0"], ["x", "0", "0"], ["1", "0", "0", "--yaw", "inf"],
    ["1", "0", "0", "--at", "-1"], ["1", "0", "0", "--timeout", "0"], ["1", "0", "0", "--run", "bad/run"],
])
def test_kidnap_bad_arguments_exit_2_with_one_line(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    try:
        rc = kidnap.main(argv)
    except SystemExit as exc:  # argparse's own errors
        rc = exc.code  # type: ignore[assignment]
    assert rc == 2
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("tagswarm kidnap: error:"), err


def test_kidnap_reads_the_worlds_verdict_from_its_status_counters() -> None:
    """What ``tagswarm kidnap`` tells its user comes from the world's real status: applied, or refused
    with the likely reason (a robot the world does not have is named as such)."""
    s = load_scenario("paper", BASE)
    node, bus, keys = make_node(s)
    cmds = bus.inboxes[keys.world_command()]
    try:
        node.step()
        c0 = status(node, bus, keys)
        cmds.put(keys.world_command(), codec.encode(command(1, "push", 0.1, 0.0, 0.0)))
        node.step()
        c1 = status(node, bus, keys)
        cmds.put(keys.world_command(), codec.encode(command(7, "teleport", 0.0, 0.0)))
        node.step()
        c2 = status(node, bus, keys)
        cmds.put(keys.world_command(), codec.encode(command(1, "teleport", 3.44, 0.0)))  # into a wall
        node.step()
        c3 = status(node, bus, keys)
    finally:
        node.close()
    def outcome(a: dict[str, int], b: dict[str, int]) -> str | None:
        return reach.outcome(a, b, "world_commands", "world_command_rejected")

    assert outcome(c0, c0) is None
    assert outcome(c0, c1) == "applied"
    assert outcome(c1, c2) == "refused"
    assert kidnap.refusal(7, c2) == "robot 7 is not in the world's roster (robots 0, 1)"
    assert outcome(c2, c3) == "refused"
    assert "outside the arena walls or overlaps" in kidnap.refusal(1, c3)
