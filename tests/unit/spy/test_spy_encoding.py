"""``tagswarm spy`` shows each key's Zenoh encoding and counts samples whose encoding does not
match their message: in the statistics, the plain snapshot, the --echo lines, and on real
samples over loopback (a tagswarm publisher's and a foreign one's with a wrong encoding)."""

from __future__ import annotations

import json
import math
import threading

import msgspec
import pytest
import zenoh

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import BusConfig, open_bus
from tagswarm.protocol.keys import Keys
from tagswarm.spy import spy
from tests.harness import endpoint

TICK = codec.encode(m.Tick(seq=0, stamp_ns=2_000_000_000, run_id="r", step=60, dt_ns=33_333_333, mode="lockstep"))
GOAL = codec.encode(m.Goal(seq=0, stamp_ns=0, robot_id=1, x_m=0.5, y_m=-1.0))
NAN_CMD = codec.encode(m.WheelCommand(seq=0, stamp_ns=0, robot_id=1, left_rad_s=math.nan, right_rad_s=0.0))
GARBAGE = b"\xc1 not msgpack"


@pytest.mark.parametrize(("encoding", "payload", "mismatch"), [
    ("application/msgpack;Tick", TICK, False),
    ("application/msgpack;Goal", TICK, True),  # names another type
    ("zenoh/bytes", TICK, True),  # no encoding (an older sender)
    ("application/json;Tick", TICK, True),  # not the msgpack media type
    ("application/msgpack;WheelCommand", NAN_CMD, False),  # undecodable (NaN), but it is a WheelCommand
    ("application/msgpack;Goal", NAN_CMD, True),
    ("zenoh/bytes", GARBAGE, False),  # what the bus sends for a non-message
    ("application/msgpack;Goal", GARBAGE, True),
    ("application/msgpack;Tick", msgspec.msgpack.encode({"type": "nope", "seq": 0}), True),
])
def test_encoding_mismatch(encoding: str, payload: bytes, mismatch: bool) -> None:
    assert spy.encoding_mismatch(encoding, payload, spy.decode(payload)) is mismatch


def test_traffic_keeps_each_keys_encoding_and_counts_mismatches() -> None:
    t = spy.Traffic(window_s=1.0, started=0.0)
    t.add("tagswarm/r/world/tick", TICK, 0.1, "application/msgpack;Tick")
    t.add("tagswarm/r/world/tick", TICK, 0.2, "application/msgpack;Goal")
    t.add("tagswarm/r/world/tick", TICK, 0.3, "application/msgpack;Tick")
    t.add("tagswarm/r/robot/1/goal", GOAL, 0.4, "zenoh/bytes")
    t.add("tagswarm/r/robot/1/cmd", NAN_CMD, 0.5, "application/msgpack;WheelCommand")
    t.add("tagswarm/r/robot/2/goal", GOAL, 0.6)  # encoding not known: not checked
    rows = {r.key: r for r in t.rows(now=1.0)}
    assert (rows["tagswarm/r/world/tick"].encoding, rows["tagswarm/r/world/tick"].mismatched) == (
        "application/msgpack;Tick", 1)
    goal1, goal2, cmd = rows["tagswarm/r/robot/1/goal"], rows["tagswarm/r/robot/2/goal"], rows["tagswarm/r/robot/1/cmd"]
    assert (goal1.encoding, goal1.mismatched) == ("zenoh/bytes", 1)
    assert cmd.mismatched == 0 and cmd.kind == "undecodable:non_finite"
    assert (goal2.encoding, goal2.mismatched) == ("", 0)
    assert t.mismatched == 2

    text = spy.plain_snapshot(t.rows(now=1.0), set(), "title")
    lines = text.splitlines()
    names = lines[1].split()
    assert names[:5] == ["KEY", "TYPE", "ENCODING", "MSGS", "BAD_ENC"] and names[-1] == "LAST"
    cells = [ln.split(maxsplit=len(names) - 1) for ln in lines if ln.startswith("tagswarm/")]
    table = {p[0]: dict(zip(names, p, strict=True)) for p in cells}
    tick = table["tagswarm/r/world/tick"]
    assert (tick["TYPE"], tick["ENCODING"], tick["MSGS"], tick["BAD_ENC"]) == (
        "Tick", "application/msgpack;Tick", "3", "1")
    assert tick["LAST"].startswith("step 60 lockstep")
    assert table["tagswarm/r/robot/2/goal"]["ENCODING"] == "-"


def test_echo_lines_carry_the_encoding_and_flag_a_mismatch() -> None:
    good = json.loads(spy.echo_line("k", len(TICK), spy.decode(TICK), "application/msgpack;Tick", False))
    assert good["encoding"] == "application/msgpack;Tick" and "encoding_mismatch" not in good
    assert good["msg"]["step"] == 60
    bad = json.loads(spy.echo_line("k", len(GARBAGE), spy.decode(GARBAGE), "application/msgpack;Goal", True))
    assert bad["encoding_mismatch"] is True and bad["error"]["kind"] == "malformed"
    assert "encoding" not in json.loads(spy.echo_line("k", 1, spy.decode(TICK)))


def test_spy_on_real_samples_shows_encodings_and_counts_a_foreign_wrong_one() -> None:
    """A tagswarm Bus publisher (encodings set by the bus) and a plain zenoh session putting a
    Tick labelled as a Goal, read by a Spy over loopback; --once --echo output checked too."""
    keys = Keys("spyenc")
    ep = endpoint()
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps([ep]))
    with open_bus(BusConfig(listen=(ep,))) as reader, open_bus(BusConfig(connect=(ep,))) as writer, \
            zenoh.open(conf) as foreign:
        s = spy.Spy(reader, keys.all(), 5.0, alive=False)
        probe = keys.world_status()
        status = codec.encode(m.AgentStatus(seq=0, stamp_ns=0, role="world", mode="lockstep"))
        for _ in range(100):  # until both writers' puts reach the spy's subscription
            writer.put(probe, status)
            foreign.put(keys.robot_status(9), status, encoding="application/msgpack;AgentStatus")
            s.poll()
            if {probe, keys.robot_status(9)} <= set(s.traffic.keys):
                break
            threading.Event().wait(0.05)
        assert s.traffic.mismatched == 0
        writer.put(keys.tick(), TICK)
        writer.put(keys.goal(1), GOAL)
        writer.put(keys.goal(2), GARBAGE)
        foreign.put(keys.goal(3), TICK, encoding="application/msgpack;Goal")
        foreign.put(keys.goal(4), GOAL)  # no encoding at all
        want = {keys.tick(), keys.goal(1), keys.goal(2), keys.goal(3), keys.goal(4)}
        echoed: list[str] = []

        def arrived() -> bool:
            return want <= set(s.traffic.keys)

        deadline = threading.Event()
        for _ in range(200):
            s.poll(echoed.append)
            if arrived():
                break
            deadline.wait(0.05)
        assert arrived(), sorted(s.traffic.keys)
    rows = {r.key: r for r in s.traffic.rows(now=s.clock())}
    assert rows[keys.tick()].encoding == "application/msgpack;Tick" and rows[keys.tick()].mismatched == 0
    assert rows[keys.goal(1)].encoding == "application/msgpack;Goal" and rows[keys.goal(1)].mismatched == 0
    assert rows[keys.goal(2)].encoding == "zenoh/bytes" and rows[keys.goal(2)].mismatched == 0
    assert rows[keys.goal(3)].mismatched == 1 and rows[keys.goal(3)].kind == "Tick"
    assert rows[keys.goal(4)].encoding == "zenoh/bytes" and rows[keys.goal(4)].mismatched == 1
    assert s.traffic.mismatched == 2
    docs = [json.loads(line) for line in echoed]
    assert {d["key"]: d["encoding"] for d in docs}[keys.goal(1)] == "application/msgpack;Goal"
    flagged = sorted(d["key"] for d in docs if d.get("encoding_mismatch"))
    assert flagged == sorted([keys.goal(3), keys.goal(4)])
