"""``tagswarm spy`` and ``tagswarm goto`` against a small running system (``tagswarm up``,
2 robots, realtime), plus the spy's views, rates and JSON lines on hand-made payloads."""

from __future__ import annotations

import io
import json
import math
import os
import re
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import msgspec
import pytest

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import Inbox
from tagswarm.protocol.keys import Keys
from tagswarm.spy import spy
from tests.harness import client, endpoint, script, wait_alive

ROBOTS = (0, 1)


@dataclass
class System:
    endpoint: str
    run: str
    keys: Keys
    out: Path
    proc: subprocess.Popen[bytes]


def _port_open(ep: str) -> bool:
    host, port = ep.removeprefix("tcp/").rsplit(":", 1)
    with socket.socket() as s:
        s.settimeout(0.2)
        return s.connect_ex((host, int(port))) == 0


@pytest.fixture(scope="module")
def system(tmp_path_factory: pytest.TempPathFactory) -> Iterator[System]:
    ep = endpoint()
    run = f"spy{os.getpid()}"
    out = tmp_path_factory.mktemp("spy") / "run"
    log = open(out.parent / "up.log", "wb")
    proc = subprocess.Popen([script("tagswarm"), "up", "--duration", "120", "--robots", str(len(ROBOTS)),
                             "--set", 'robots.placement="ring"', "--set", "missions=[]", "--listen", ep,
                             "--run", run, "--out", str(out), "--no-live", "--no-report"],
                            stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 40
        while not _port_open(ep):  # the world (started last) listens on ep
            assert proc.poll() is None, (out.parent / "up.log").read_text()
            assert time.monotonic() < deadline, "the world never listened"
            time.sleep(0.2)
        keys = Keys(run)
        with client(ep) as bus:
            for who in ("world/0", "server/0", *(f"agent/{r}" for r in ROBOTS)):
                wait_alive(bus, keys, who)
        yield System(ep, run, keys, out, proc)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        log.close()


def tagswarm(*argv: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run([script("tagswarm"), *argv], capture_output=True, text=True, timeout=timeout,
                          env={k: v for k, v in os.environ.items() if not k.startswith("TAGSWARM_")})


def parse_snapshot(text: str, prefix: str) -> tuple[dict[str, dict[str, str]], list[str]]:
    """Rows of a plain snapshot by key, and the liveliness tokens it lists."""
    rows, alive = {}, []
    lines = text.splitlines()
    header = next(line for line in lines if line.startswith("KEY "))
    names = header.split()
    for line in lines:
        if line.startswith(prefix):
            parts = line.split(maxsplit=len(names) - 1)
            rows[parts[0]] = dict(zip(names, parts, strict=False))
        elif line.startswith("alive "):
            alive.append(line.split()[1])
    return rows, alive


# --------------------------------------------------------------------------- against the running system


def test_spy_once_lists_world_agent_and_server_keys_with_rates(system: System) -> None:
    k = system.keys
    res = tagswarm("spy", "--once", "--window", "2", "--connect", system.endpoint, "--run", system.run)
    assert res.returncode == 0, res.stderr
    rows, alive = parse_snapshot(res.stdout, k.prefix)
    expected = {
        k.tick(): "Tick",  # world
        k.image(0, "front"): "CameraImage",
        k.truth(1): "GroundTruthPose",
        k.encoders(1): "EncoderTicks",
        k.cmd(0): "WheelCommand",  # agents
        k.odometry(1): "OdometryEstimate",
        k.robot_status(0): "AgentStatus",
        k.correction(1): "Correction",  # server
        k.server_status(): "AgentStatus",
    }
    for key, kind in expected.items():
        assert key in rows, f"{key} missing from:\n{res.stdout}"
        assert rows[key]["TYPE"] == kind
        assert int(rows[key]["MSGS"]) > 0 and float(rows[key]["RATE_HZ"]) > 0, rows[key]
    # 30 Hz ticks, 10 Hz cameras: the rates are measured, not just non-zero. How fast the
    # world runs depends on the (shared, noisy) machine, so assert on what does not: a camera
    # renders every third tick, and a rate is the messages counted over the window.
    tick_hz, image_hz = float(rows[k.tick()]["RATE_HZ"]), float(rows[k.image(0, "front")]["RATE_HZ"])
    assert 2.2 < tick_hz / image_hz < 5.0, (tick_hz, image_hz)  # images may be dropped, never extra
    assert 3 < tick_hz <= 40, tick_hz  # not stalled, not faster than realtime
    assert rows[k.image(0, "front")]["LAST"].startswith("320x240 mono8 robot 0 front")
    assert rows[k.image(0, "front")]["BANDWIDTH"].endswith("KB/s")
    assert not [r for r in rows.values() if r["TYPE"].startswith("undecodable")]
    # up/0: the `tagswarm up` recorder running the system
    assert sorted(alive) == sorted(k.alive(p) for p in ("world/0", "server/0", "agent/0", "agent/1", "up/0"))


def test_spy_echo_prints_json_lines_without_pixels(system: System) -> None:
    k = system.keys
    res = tagswarm("spy", k.images(1), "--echo", "--once", "--window", "1.5", "--no-alive",
                   "--connect", system.endpoint, "--run", system.run)
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    assert len(lines) >= 5  # 10 Hz for 1.5 s
    for line in lines:
        assert len(line) < 2000
        doc = json.loads(line)
        assert doc["key"] == k.image(1, "front") and doc["size"] > 320 * 240
        assert doc["msg"]["type"] == "camera_image" and doc["msg"]["robot_id"] == 1
        assert doc["msg"]["data"] == f"<320x240 mono8 robot 1 front: {320 * 240} bytes>"


def test_goto_reaches_the_agent(system: System) -> None:
    res = tagswarm("goto", "1", "0.5", "-0.25", "--tolerance", "0.2", "--connect", system.endpoint,
                   "--run", system.run)
    assert res.returncode == 0, res.stderr
    assert f"sent to agent/1 on {system.keys.goal(1)}" in res.stdout
    log = system.out / "logs" / "agent1.log"
    deadline = time.monotonic() + 10
    while "new goal (0.50, -0.25)" not in log.read_text():
        assert time.monotonic() < deadline, log.read_text()[-2000:]
        time.sleep(0.2)
    assert "new goal" not in (system.out / "logs" / "agent0.log").read_text()
    assert res.stdout.rstrip().endswith(", taken by the agent"), res.stdout


def test_goto_where_no_robot_can_stand_is_refused_by_the_agent(system: System) -> None:
    res = tagswarm("goto", "1", "50", "50", "--connect", system.endpoint, "--run", system.run)
    assert res.returncode == 1, res.stdout + res.stderr
    assert res.stderr.strip().splitlines() == [
        "tagswarm goto: error: agent/1 refused the goal (50.00, 50.00) ±0.1 m in the map frame: a robot cannot "
        "stand there (beyond the arena walls or on an obstacle; the agent's log says which)"]
    log = (system.out / "logs" / "agent1.log").read_text()
    assert "goal (50.00, 50.00) in the map frame refused: a robot there would not be inside the arena walls" in log
    assert "new goal (50.00" not in log


def test_goto_an_agent_that_is_not_alive_exits_1(system: System) -> None:
    res = tagswarm("goto", "7", "0", "0", "--timeout", "1", "--connect", system.endpoint, "--run", system.run)
    assert res.returncode == 1
    assert res.stderr.strip().splitlines() == [
        f"tagswarm goto: error: agent/7 is not alive on run '{system.run}' "
        f"(no liveliness token {system.keys.alive('agent/7')} after 1 s)"]


# --------------------------------------------------------------------------- bad usage


def test_bad_flags_exit_2_with_one_line_from_the_console_script() -> None:
    procs = [subprocess.Popen([script("tagswarm"), *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for argv in (["spy", "--bogus"], ["goto", "1", "nan", "0"])]
    for p, name in zip(procs, ("spy", "goto"), strict=True):
        out, err = p.communicate(timeout=60)
        assert p.returncode == 2 and out == ""
        assert len(err.strip().splitlines()) == 1 and err.startswith(f"tagswarm {name}: error: "), err


@pytest.mark.parametrize("argv", [
    ["spy", "--window", "0"], ["spy", "--once", "--window", "nan"], ["spy", "--window", "x"], ["spy", "a", "b"],
    ["spy", "--run", "bad/run"], ["goto", "1", "0", "inf"], ["goto", "x", "0", "0"], ["goto", "-1", "0", "0"],
    ["goto", "1", "0"], ["goto", "1", "0", "0", "--tolerance", "0"], ["goto", "1", "0", "0", "--timeout", "-1"],
    ["spy", "--log-level", "LOUD"], ["goto", "1", "0", "0", "--log-level", "LOUD"],
])
def test_bad_arguments_exit_2_with_one_line(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    from tagswarm import cli

    try:
        code = cli.main(argv)
    except SystemExit as exc:  # argparse errors exit from inside parse_args
        code = int(exc.code or 0)
    err = capsys.readouterr().err
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and err.startswith(f"tagswarm {argv[0]}: error: "), err


def test_goto_accepts_negative_coordinates() -> None:
    from tagswarm.operator import goto

    args = goto.parser().parse_args(["2", "-1.5", "-0.25", "--tolerance", "0.3"])
    g = goto.make_goal(args.robot, args.x, args.y, args.tolerance, 7)
    assert (g.robot_id, g.x_m, g.y_m, g.tolerance_m, g.stamp_ns) == (2, -1.5, -0.25, 0.3, 7)
    assert codec.decode(m.Goal, codec.encode(g)) == g


# --------------------------------------------------------------------------- views, rates, JSON lines


def _image(rid: int = 1, w: int = 64, h: int = 48) -> m.CameraImage:
    return m.CameraImage(seq=3, stamp_ns=2_500_000_000, robot_id=rid, camera="front", step=75, width=w, height=h,
                         fx_px=50.0, fy_px=50.0, cx_px=32.0, cy_px=24.0, mount=m.Pose3(x_m=0.15, y_m=0.0, z_m=0.22),
                         data=bytes(w * h))


def test_image_is_summarised_never_dumped() -> None:
    img = _image()
    assert spy.summarise(img) == "64x48 mono8 robot 1 front step 75"
    line = spy.echo_line("k", 3100, img)
    doc = json.loads(line)
    assert doc["msg"]["data"] == "<64x48 mono8 robot 1 front: 3072 bytes>"
    assert doc["msg"]["width"] == 64 and doc["msg"]["mount"]["x_m"] == 0.15 and doc["size"] == 3100
    assert len(line) < 600


def test_undecodable_payloads_are_shown_not_raised() -> None:
    t = spy.Traffic(window_s=2.0, started=0.0)
    garbage = t.add("a", b"\xc1\xc1 not msgpack", now=0.1)
    assert isinstance(garbage, codec.DecodeError) and garbage.kind == "malformed"
    nan = codec.encode(m.WheelCommand(seq=0, stamp_ns=0, robot_id=1, left_rad_s=math.nan, right_rad_s=0.0))
    assert isinstance(t.add("b", nan, now=0.2), codec.DecodeError)
    t.add("c", msgspec.msgpack.encode({"type": "nope", "seq": 0}), now=0.3)
    rows = {r.key: r for r in t.rows(now=0.5)}
    assert rows["a"].kind == "undecodable:malformed" and rows["b"].kind == "undecodable:non_finite"
    assert rows["c"].kind == "undecodable:malformed" and rows["c"].stamp_s is None
    doc = json.loads(spy.echo_line("b", len(nan), spy.decode(nan)))
    assert doc["error"]["kind"] == "non_finite" and "msg" not in doc


def test_rates_and_bandwidth_over_the_window() -> None:
    t = spy.Traffic(window_s=2.0, started=0.0)
    tick = codec.encode(m.Tick(seq=0, stamp_ns=1_000_000_000, run_id="r", step=30, dt_ns=33_333_333,
                               mode="lockstep"))
    for i in range(40):  # 20 Hz for 2 s
        t.add("tick", tick, now=0.05 * (i + 1))
    (row,) = t.rows(now=2.0)
    assert row.kind == "Tick" and row.count == 40
    assert row.rate_hz == pytest.approx(20.0)
    assert row.bytes_per_s == pytest.approx(20.0 * len(tick))
    assert row.stamp_s == pytest.approx(1.0)
    assert row.last.startswith("step 30 lockstep")
    (later,) = t.rows(now=3.0)  # one second later only the last second's 20 messages count
    assert later.rate_hz == pytest.approx(10.0) and later.count == 40
    early = spy.Traffic(window_s=2.0, started=10.0)
    early.add("x", tick, now=10.4)
    assert early.rows(now=10.5)[0].rate_hz == pytest.approx(2.0)  # 1 message in the first 0.5 s


def test_plain_snapshot_round_trips_through_the_parser() -> None:
    t = spy.Traffic(window_s=1.0, started=0.0)
    t.add("tagswarm/r/robot/1/camera/front", codec.encode(_image()), now=0.5)
    t.add("tagswarm/r/robot/1/goal", codec.encode(m.Goal(seq=0, stamp_ns=0, robot_id=1, x_m=0.5, y_m=-1.0)), now=0.6)
    t.liveliness("tagswarm/r/alive/agent/1", True)
    t.liveliness("tagswarm/r/alive/agent/2", True)
    t.liveliness("tagswarm/r/alive/agent/2", False)
    text = spy.plain_snapshot(t.rows(now=1.0), t.alive, "title")
    rows, alive = parse_snapshot(text, "tagswarm/")
    cam = rows["tagswarm/r/robot/1/camera/front"]
    assert cam["TYPE"] == "CameraImage" and cam["MSGS"] == "1" and cam["RATE_HZ"] == "1.00"
    assert cam["BANDWIDTH"] == spy.human_rate(len(codec.encode(_image())))
    assert cam["SIM_T_S"] == "2.500" and cam["LAST"] == "64x48 mono8 robot 1 front step 75"
    assert rows["tagswarm/r/robot/1/goal"]["LAST"] == "robot 1 -> (+0.50, -1.00) ±0.1 m"
    assert alive == ["tagswarm/r/alive/agent/1"]
    assert [spy.human_rate(v) for v in (12, 12_345, 3_456_789)] == ["12B/s", "12.3KB/s", "3.5MB/s"]


def test_every_wire_type_has_a_short_view() -> None:
    pose = m.Pose3(x_m=0.0, y_m=0.0, z_m=0.0)
    cov = (0.0,) * 9
    msgs: list[m.Msg] = [
        m.TickAck(seq=0, stamp_ns=0, participant="agent/1", step=4),
        m.EncoderTicks(seq=0, stamp_ns=0, robot_id=1, left_ticks=10, right_ticks=-3, ticks_per_rev=4096),
        m.GroundTruthPose(seq=0, stamp_ns=0, robot_id=1, step=0, x_m=1.0, y_m=2.0, yaw_rad=math.pi / 2, pose=pose),
        m.RelativeObservation(seq=0, stamp_ns=0, robot_id=0, target_kind="robot", target_id=2, x_m=1.0, y_m=0.0,
                              yaw_rad=0.0, cov=cov, pose=pose, reprojection_rms_px=0.25, tag_ids=(21,),
                              camera="front"),
        m.OdometryEstimate(seq=0, stamp_ns=0, robot_id=1, x_m=0.0, y_m=0.0, yaw_rad=0.0, cov=cov, distance_m=1.5),
        m.Correction(seq=0, stamp_ns=0, robot_id=3, map_odom_x_m=0.0, map_odom_y_m=0.0, map_odom_yaw_rad=0.0,
                     x_m=0.0, y_m=0.0, yaw_rad=0.0, cov=cov, localised=False),
        m.Correction(seq=0, stamp_ns=0, robot_id=4, map_odom_x_m=0.0, map_odom_y_m=0.0, map_odom_yaw_rad=0.0,
                     x_m=1.0, y_m=0.5, yaw_rad=0.0, cov=(0.36, 0, 0, 0, 0.04, 0, 0, 0, 0.01), localised=False),
        m.GlobalMap(seq=0, stamp_ns=0, origin_id=0, robots=(), edges=((0, 1),)),
        m.AgentStatus(seq=0, stamp_ns=0, role="server", mode="lockstep", counters={"odometry": 5}),
        m.RenderPoses(seq=0, stamp_ns=0, step=2, robot_ids=(0, 1), poses=(pose, pose), cameras=("0/front",)),
    ]
    views = [spy.summarise(x) for x in msgs]
    assert views == [
        "agent/1 acked step 4",
        "robot 1 L 10 R -3 ticks (4096/rev)",
        "robot 1 (+1.00, +2.00, +90°) v +0.00 m/s",
        "robot 0 sees robot 2 at (+1.00, +0.00, +0°) rms 0.25 px (front)",
        "robot 1 (+0.00, +0.00, +0°) travelled 1.50 m",
        "robot 3 not localised",
        "robot 4 not localised: placed at (+1.00, +0.50, +0°) (map), not vouched for (sigma 0.60 m)",
        "origin 0, 0 robot(s) (0 alive), 1 edge(s)",
        "server lockstep odometry=5",
        "step 2: 2 robot(s), 1 camera(s)",
    ]
    for x in msgs:  # and every one survives the JSON line
        assert json.loads(spy.echo_line("k", 1, x))["msg"]["type"] == type(x).__struct_config__.tag


def _no_ansi(text: str) -> str:
    return re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", text)


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


class _FakeBus:
    """Just enough of tagswarm.protocol.bus.Bus for a Spy: two inboxes fed by the test."""

    def __init__(self) -> None:
        wake = threading.Condition()
        self.data: Inbox[tuple[str, bytes]] = Inbox(wake, newest_only=False, capacity=100)  # (encoding, payload)
        self.alive: Inbox[bool] = Inbox(wake, newest_only=False, capacity=100)

    def subscribe_encoded(self, key: str, **_: object) -> Inbox[tuple[str, bytes]]:
        return self.data

    def watch_liveliness(self, key: str) -> Inbox[bool]:
        return self.alive


def test_terminal_output_is_a_rich_table_and_data_is_never_markup(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("COLUMNS", "160")
    bus = _FakeBus()
    s = spy.Spy(bus, "tagswarm/r/**", 1.0)  # type: ignore[arg-type]
    bus.data.put("tagswarm/r/[bold]odd", ("zenoh/bytes", b"\xc1 [red]not markup[/]"))
    bus.data.put("tagswarm/r/robot/1/camera/front", ("application/msgpack;CameraImage", codec.encode(_image())))
    bus.alive.put("tagswarm/r/alive/agent/1", True)
    out = _Tty()
    assert spy.run_spy(s, keyexpr="tagswarm/r/**", once=True, window_s=0.3, echo=False, plain=False,
                       stop=threading.Event(), out=out) == 0
    text = _no_ansi(out.getvalue())
    assert "┃ key" in text and "┃  Hz ┃" in text and "┃ t [s] ┃" in text  # a rich table, headers intact
    assert "│ [bold]odd " in text and "undecodable:malformed" in text  # keys shown under tagswarm/r/
    assert "│ robot/1/camera/front │ CameraImage " in text and "64x48 mono8 robot 1 front step 75" in text
    assert "│ alive/agent/1 " in text and "tagswarm/r/**" in text


def test_live_mode_refreshes_until_stopped() -> None:
    bus = _FakeBus()
    s = spy.Spy(bus, "tagswarm/r/**", 1.0)  # type: ignore[arg-type]
    stop = threading.Event()
    tick = codec.encode(m.Tick(seq=0, stamp_ns=0, run_id="r", step=0, dt_ns=1, mode="realtime"))

    def feed() -> None:
        for _ in range(10):
            bus.data.put("tagswarm/r/world/tick", ("application/msgpack;Tick", tick))
            time.sleep(0.05)
        time.sleep(0.3)
        stop.set()

    threading.Thread(target=feed, daemon=True).start()
    out = _Tty()
    t0 = time.monotonic()
    assert spy.run_spy(s, keyexpr="tagswarm/r/**", once=False, window_s=1.0, echo=False, plain=False, stop=stop,
                       out=out) == 0
    assert 0.6 < time.monotonic() - t0 < 5
    assert s.traffic.keys["tagswarm/r/world/tick"].count == 10
    text = _no_ansi(out.getvalue())
    assert "│ world/tick " in text and "│ Tick " in text and "Ctrl-C to quit" in text
