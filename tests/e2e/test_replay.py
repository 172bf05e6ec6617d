"""Recording and replay with real processes: ``tagswarm up --record`` writes a valid MCAP
of a lockstep run; ``tagswarm up --replay`` feeds its world streams to fresh agents and a
fresh server and gets byte-identical fused trajectories; ``tagswarm record`` and
``tagswarm replay`` on their own."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import time
import urllib.request
from collections import Counter, defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgspec
import pytest
from mcap.reader import make_reader

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import Bus
from tagswarm.protocol.geometry import se2_compose
from tagswarm.protocol.keys import Keys
from tagswarm.protocol.layout import arena_to_map
from tagswarm.protocol.scenario import load_scenario
from tagswarm.recording.mcapio import iter_raw, keyexpr_matches, remap_run, verify
from tagswarm.recording.replay import recorded_scenario
from tests.harness import client, endpoint, free_port, process, script, wait_alive

RUN_ARGS = ["--clock", "lockstep", "--seed", "3", "--duration", "20", "--robots", "3", "--no-live", "--no-report"]


def _up(*args: str) -> None:
    res = subprocess.run([script("tagswarm"), "up", *args], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(run folder, recording) of the original run."""
    base = tmp_path_factory.mktemp("original")
    _up(*RUN_ARGS, "--out", str(base / "run"), "--record", str(base / "run.mcap"))
    return base / "run", base / "run.mcap"


@pytest.fixture(scope="module")
def replayed(recorded: tuple[Path, Path], tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(run folder, recording) of fresh agents and server fed the recorded world streams."""
    base = tmp_path_factory.mktemp("replayed")
    _up("--replay", str(recorded[1]), "--out", str(base / "run"), "--record", str(base / "run.mcap"), "--no-live",
        "--no-report")
    return base / "run", base / "run.mcap"


def _by_channel(path: Path) -> dict[str, list[bytes]]:
    """Raw payloads per key, keys moved to one run name so two runs compare."""
    out: dict[str, list[bytes]] = defaultdict(list)
    for r in iter_raw(path, lambda _: True):
        out[remap_run(r.key, "x")].append(r.data)
    return out


def test_recording_of_a_lockstep_run_is_valid_and_complete(recorded: tuple[Path, Path]) -> None:
    _, mcap = recorded
    v = verify(mcap)  # CRC-checked read of every record; statistics agree
    run = v.metadata["tagswarm"]["run"]
    p = f"tagswarm/{run}"
    ticks = [codec.decode(m.Tick, r.data) for r in iter_raw(mcap, lambda k: k == f"{p}/world/tick")]
    steps = len(ticks)
    assert [t.step for t in ticks] == list(range(steps)) and steps >= 600  # from step 0: the world waited for us
    frames = Counter(pair for t in ticks for pair in t.cameras_rendered)
    for rid in range(3):
        assert v.counts[f"{p}/robot/{rid}/truth"] == steps
        assert v.counts[f"{p}/robot/{rid}/encoders"] == steps  # encoders run at the tick rate here
        assert v.counts[f"{p}/robot/{rid}/camera/front"] == frames[f"{rid}/front"] > 190
        assert v.counts[f"{p}/robot/{rid}/correction"] == steps
        assert v.counts[f"{p}/world/ack/agent/{rid}"] == steps
        for view, schema in (("truth", "foxglove.PoseInFrame"), ("fused", "foxglove.PoseInFrame"),
                             ("odometry", "foxglove.PoseInFrame"), ("camera/front", "foxglove.RawImage")):
            assert v.schemas[f"/{run}/robot/{rid}/{view}"] == schema
            assert v.counts[f"/{run}/robot/{rid}/{view}"] > 0
    assert v.schemas[f"{p}/robot/0/camera/front"] == "tagswarm.CameraImage"
    assert v.schemas[f"/{run}/map"] == "foxglove.SceneUpdate" and v.counts[f"/{run}/map"] == v.counts[f"{p}/server/map"]
    stats = v.metadata["tagswarm.stats"]
    assert stats["inbox_overflow"] == "0" and stats["images_missing"] == "0"
    assert not any(k.startswith("rejected_") for k in stats)
    table = recorded_scenario(mcap)
    assert table is not None and "record/0" not in table["clock"]["participants"]
    with open(mcap, "rb") as f:  # log time = simulation time, publish time = wall clock at reception
        for _, _ch, msg in make_reader(f).iter_messages(topics=[f"{p}/robot/1/truth"]):
            assert msg.log_time == codec.decode_any(msg.data).stamp_ns
            assert abs(msg.publish_time / 1e9 - time.time()) < 3600


def test_replay_into_fresh_agents_and_server_reproduces_the_fused_trajectories(
        recorded: tuple[Path, Path], replayed: tuple[Path, Path]) -> None:
    (orig, _), (again, _) = recorded, replayed
    for rid in range(3):
        for kind in ("fused", "odom", "truth"):
            a = (orig / "trajectories" / f"{kind}_{rid}.tum").read_bytes()
            b = (again / "trajectories" / f"{kind}_{rid}.tum").read_bytes()
            assert a == b, f"{kind}_{rid}.tum differs"
            assert a.count(b"\n") >= 590  # ~every tick (fused: from the first fix on)
    # same observations; rows interleave across agents in arrival order, so compare them sorted
    rows = [sorted((d / "observations.csv").read_text().splitlines()) for d in (orig, again)]
    assert rows[0] == rows[1] and len(rows[0]) > 100


def test_replayed_agents_and_server_publish_the_same_bytes(recorded: tuple[Path, Path],
                                                           replayed: tuple[Path, Path]) -> None:
    a, b = _by_channel(recorded[1]), _by_channel(replayed[1])
    outputs = [k for k in a if k.rsplit("/", 1)[-1] in ("observation", "odometry", "correction", "cmd", "map")]
    assert len(outputs) == 3 * 4 + 1
    for key in outputs:
        first = next((i for i, (x, y) in enumerate(zip(a[key], b[key], strict=False)) if x != y), None)
        assert a[key] == b[key], f"{key}: {len(a[key])} vs {len(b[key])} payloads, first difference at {first}"
    # and the replay fed exactly the recorded world streams
    for key in ("tagswarm/x/world/tick", "tagswarm/x/robot/2/camera/front", "tagswarm/x/robot/2/encoders"):
        assert a[key] == b[key]


def test_a_replay_with_other_settings_sees_no_wheel_slip(recorded: tuple[Path, Path], tmp_path: Path) -> None:
    """The replayed agents drive nothing: with another top speed their commands differ from the recorded
    ones, and the slip check must compare the recorded wheels with the recorded commands (it reported
    ~3.4 m of slip per moving robot when it used the agents' own)."""
    _up("--replay", str(recorded[1]), "--set", "agent.max_speed_m_s=0.15", "--out", str(tmp_path / "run"),
        "--no-live", "--no-report")
    counters = json.loads((tmp_path / "run" / "run.json").read_text())["counters"]
    original = json.loads((recorded[0] / "run.json").read_text())["counters"]
    for rid in range(3):
        c, o = counters[f"agent/{rid}"], original[f"agent/{rid}"]
        assert (c["slip_mm"], c["slip_events"]) == (o["slip_mm"], o["slip_events"]) == (0, 0)
        assert c["frames_received"] == o["frames_received"] > 190 and c["fixes"] > 50  # the whole replay


@pytest.mark.parametrize(("extra", "says"), [
    (["--clock", "realtime"], "plays the recording in lockstep"),  # hung at x0.04 with ack timeouts
    (["--robots", "2"], "the recording holds robots 0, 1, 2, the scenario robots 0, 1"),
    (["--scenario", "hall"], "the recording holds robots 0, 1, 2, the scenario robots 0, 1, 2, 3, 4, 5"),
    (["--record", "{rec}"], "is the recording --replay reads"),  # it truncated the recording
    (["--record", "{other}"], "exists already"),
])
def test_a_replay_that_cannot_match_its_recording_is_refused(recorded: tuple[Path, Path], tmp_path: Path,
                                                              extra: list[str], says: str) -> None:
    other = tmp_path / "other.mcap"
    other.write_bytes(b"keep me")
    size = recorded[1].stat().st_size
    args = [a.replace("{rec}", str(recorded[1])).replace("{other}", str(other)) for a in extra]
    res = subprocess.run([script("tagswarm"), "up", "--replay", str(recorded[1]), *args, "--out", str(tmp_path / "run"),
                          "--no-live"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and says in res.stderr and res.stderr.count("\n") == 1, res.stderr
    assert recorded[1].stat().st_size == size and other.read_bytes() == b"keep me"
    assert not (tmp_path / "run").exists()


def test_a_replay_stops_at_the_duration_asked(recorded: tuple[Path, Path], tmp_path: Path) -> None:
    _up("--replay", str(recorded[1]), "--duration", "4", "--out", str(tmp_path / "run"), "--no-live", "--no-report")
    info = json.loads((tmp_path / "run" / "run.json").read_text())
    assert 4.0 < info["sim_time_s"] < 4.05  # as a world run of 4 s ends; the recording holds 20 s, all replayed before


def _publish(bus: Bus, key: str, msg: m.Msg) -> None:
    bus.put(key, codec.encode(msg))


def test_record_cli_joins_the_lockstep_counts_bad_payloads_and_stops_when_the_world_leaves(tmp_path: Path) -> None:
    ep, run, out = endpoint(), "rec1", tmp_path / "x.mcap"
    keys = Keys(run)
    argv = [script("tagswarm"), "record", "--out", str(out), "--listen", ep, "--run", run, "--participant", "record/0",
            "--compression", "lz4"]
    with process(argv, tmp_path / "record.log") as proc, client(ep) as bus:
        acks = bus.subscribe(keys.ack("record/0"))
        wait_alive(bus, keys, "record/0")
        with client(ep) as world:  # a stand-in world: its token, some steps, garbage
            wait_alive(world, keys, "record/0")  # the recorder's subscription is known to this session too
            world.declare_token(keys.alive("world/0"))
            for step in range(5):
                _publish(world, keys.encoders(1), m.EncoderTicks(seq=step, stamp_ns=step * 10, robot_id=1,
                                                                 left_ticks=step, right_ticks=step, ticks_per_rev=64))
                world.put(keys.truth(1), b"\x00garbage")
                _publish(world, keys.tick(), m.Tick(seq=step, stamp_ns=step * 10, run_id="w", step=step, dt_ns=10,
                                                    mode="lockstep"))

                def acked(step: int = step) -> bool:
                    return any(codec.decode(m.TickAck, a.value).step == step for a in acks.drain())

                assert bus.wait_for(acked, 20), f"no ack for step {step}"
        assert proc.wait(timeout=30) == 0  # the world's token went away: the recorder closed the file
    v = verify(out)
    assert v.counts[keys.tick()] == 5 and v.counts[keys.encoders(1)] == 5 and v.counts[keys.truth(1)] == 5
    assert v.metadata["tagswarm.stats"]["rejected_malformed"] == "5"
    assert b"\x00garbage" in [r.data for r in iter_raw(out, lambda k: k == keys.truth(1))]


def _truth(rid: int, step: int) -> m.GroundTruthPose:
    return m.GroundTruthPose(seq=step, stamp_ns=step * 10, robot_id=rid, step=step, x_m=0.5 * step, y_m=float(rid),
                             yaw_rad=0.25, pose=m.Pose3(x_m=0.5 * step, y_m=float(rid), z_m=0.0))


def _tick(step: int) -> m.Tick:
    return m.Tick(seq=step, stamp_ns=step * 10, run_id="w", step=step, dt_ns=10, mode="lockstep")


def test_record_cli_closes_a_valid_file_on_sigint(tmp_path: Path) -> None:
    """Interrupted while the world still runs: what was received is all there, in a file the
    mcap readers accept (summary, statistics, CRCs), with its schemas, channels and stats."""
    ep, out, run = endpoint(), tmp_path / "x.mcap", "rec2"
    keys = Keys(run)
    sent: dict[str, list[bytes]] = defaultdict(list)
    with process([script("tagswarm"), "record", "--out", str(out), "--listen", ep, "--run", run,
                  "--participant", "record/0"], tmp_path / "record.log") as proc, client(ep) as bus:
        acks = bus.subscribe(keys.ack("record/0"))
        wait_alive(bus, keys, "record/0")
        for step in range(3):
            for key, msg in ((keys.truth(1), _truth(1, step)), (keys.tick(), _tick(step))):
                sent[key].append(codec.encode(msg))
                bus.put(key, sent[key][-1])

            def acked(step: int = step) -> bool:  # the recorder has the step in hand
                return any(codec.decode(m.TickAck, a.value).step == step for a in acks.drain())

            assert bus.wait_for(acked, 20), f"no ack for step {step}"
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 0
    v = verify(out)  # CRC-checked read of every record; the summary's statistics agree with them
    assert v.counts[keys.tick()] == 3 and v.counts[keys.truth(1)] == 3
    assert v.schemas[keys.tick()] == "tagswarm.Tick" and v.schemas[keys.truth(1)] == "tagswarm.GroundTruthPose"
    assert v.encodings[keys.tick()] == "msgpack"
    assert v.schemas[f"/{run}/robot/1/truth"] == "foxglove.PoseInFrame" and v.counts[f"/{run}/robot/1/truth"] == 3
    own_acks = v.counts[keys.ack("record/0")]  # the whole run is recorded: the recorder's own acks too
    assert sorted(t for t in v.counts if t.startswith("tagswarm/")) == sorted([*sent, keys.ack("record/0")])
    assert 1 <= own_acks <= 3 and v.schemas[keys.ack("record/0")] == "tagswarm.TickAck"
    for key, payloads in sent.items():
        assert [r.data for r in iter_raw(out, key.__eq__)] == payloads  # byte for byte
    assert (v.start_ns, v.end_ns) == (0, 20)  # log time = simulation time
    meta, stats = v.metadata["tagswarm"], v.metadata["tagswarm.stats"]
    assert meta["run"] == run and meta["keyexpr"] == keys.all() and meta["recorder"] == "tagswarm record"
    assert v.messages == 9 + own_acks and stats["mcap_messages"] == str(v.messages)  # + 3 truth views
    assert stats["messages_Tick"] == "3" and stats["messages_GroundTruthPose"] == "3"
    assert stats["messages_TickAck"] == str(own_acks)
    assert stats["inbox_overflow"] == "0" and not any(k.startswith("rejected_") for k in stats)


def test_record_cli_records_only_the_keys_of_its_key_expression(tmp_path: Path) -> None:
    ep, run, out = endpoint(), "rec3", tmp_path / "k.mcap"
    keys = Keys(run)
    pattern = f"tagswarm/{run}/robot/*/truth"
    argv = [script("tagswarm"), "record", pattern, "--out", str(out), "--listen", ep, "--run", run,
            "--participant", "record/0"]  # a participant only for its token: then the test knows it listens
    with process(argv, tmp_path / "record.log") as proc, client(ep) as bus:
        wait_alive(bus, keys, "record/0")
        with client(ep) as world:  # a stand-in world: matching and other keys, then it leaves
            wait_alive(world, keys, "record/0")
            world.declare_token(keys.alive("world/0"))
            for step in range(4):
                for rid in (1, 2):
                    _publish(world, keys.truth(rid), _truth(rid, step))
                    _publish(world, keys.encoders(rid), m.EncoderTicks(
                        seq=step, stamp_ns=step * 10, robot_id=rid, left_ticks=step, right_ticks=step,
                        ticks_per_rev=64))
                _publish(world, keys.tick(), _tick(step))
                _publish(world, Keys("other").truth(1), _truth(1, step))  # another run's robot
        assert proc.wait(timeout=30) == 0  # the world's token went away: the recorder closed the file
    v = verify(out)
    raw = sorted(t for t in v.counts if t.startswith("tagswarm/"))
    assert raw == [keys.truth(1), keys.truth(2)], raw
    assert v.counts[keys.truth(1)] == v.counts[keys.truth(2)] == 4
    assert sorted(t for t in v.counts if not t.startswith("tagswarm/")) == [f"/{run}/robot/1/truth",
                                                                           f"/{run}/robot/2/truth"]
    assert v.metadata["tagswarm"]["keyexpr"] == pattern


def test_timed_replay_moves_the_run_and_filters_keys(recorded: tuple[Path, Path], tmp_path: Path) -> None:
    _, mcap = recorded
    ep, keys = endpoint(), Keys("moved")
    argv = [script("tagswarm"), "replay", str(mcap), "--speed", "40", "--run", "moved", "--listen", ep,
            "--keys", "tagswarm/*/robot/1/truth", "--keys", "**/world/tick", "--wait-for", "test/0"]
    with process(argv, tmp_path / "replay.log") as proc, client(ep) as bus:
        inbox = bus.subscribe(keys.all())
        bus.declare_token(keys.alive("test/0"))
        want = _by_channel(mcap)
        total = len(want["tagswarm/x/world/tick"]) + len(want["tagswarm/x/robot/1/truth"])
        assert bus.wait_for(lambda: len(inbox) >= total, 60)
        assert proc.wait(timeout=30) == 0
        got: dict[str, list[bytes]] = defaultdict(list)
        for item in inbox.drain():
            got[item.key].append(item.value)
    assert sorted(got) == [keys.truth(1), keys.tick()]
    assert got[keys.tick()] == want["tagswarm/x/world/tick"]
    assert got[keys.truth(1)] == want["tagswarm/x/robot/1/truth"]


def test_timed_replay_keeps_time_order_and_stamps(recorded: tuple[Path, Path], tmp_path: Path) -> None:
    """``--speed X``: a recording spanning S simulated seconds takes at least S/X wall seconds
    (each message no earlier than its simulated offset / X after the first), and everything
    arrives in the recorded order with its recorded bytes (so its stamps)."""
    _, mcap = recorded
    speed, slack_s = 8.0, 0.3
    patterns = ("tagswarm/*/world/tick", "tagswarm/*/robot/*/truth")
    want = [(remap_run(r.key, "paced"), r.data, r.log_time_ns)
            for r in iter_raw(mcap, lambda k: any(keyexpr_matches(p, k) for p in patterns))]
    span_s = (want[-1][2] - want[0][2]) / 1e9
    assert span_s > 19 and len(want) > 2000
    ep, keys = endpoint(), Keys("paced")
    argv = [script("tagswarm"), "replay", str(mcap), "--speed", str(speed), "--run", "paced", "--listen", ep,
            "--wait-for", "test/0", *(a for p in patterns for a in ("--keys", p))]
    got: list[tuple[float, str, bytes]] = []  # (wall time of arrival, key, payload)
    with process(argv, tmp_path / "replay.log") as proc, client(ep) as bus:
        inbox = bus.subscribe(keys.all())
        bus.declare_token(keys.alive("test/0"))  # the replay starts once it sees us (subscribed by then)

        def take() -> bool:  # re-checked on every arrival: the arrival time is known to a few ms
            now = time.monotonic()
            got.extend((now, item.key, item.value) for item in inbox.drain())
            return len(got) >= len(want)

        assert bus.wait_for(take, 60 + span_s), f"{len(got)} of {len(want)} messages"
        assert proc.wait(timeout=30) == 0
    assert [(k, d) for _, k, d in got] == [(k, d) for k, d, _ in want]  # order and bytes as recorded
    stamps = [codec.decode_any(d).stamp_ns for _, _, d in got]
    assert stamps == [t for _, _, t in want] and stamps == sorted(stamps)
    t0 = got[0][0]
    early = max((want[i][2] - want[0][2]) / 1e9 / speed - (got[i][0] - t0) for i in range(len(got)))
    wall_s = got[-1][0] - t0
    print(f"replayed {span_s:.2f} simulated s at x{speed:g} in {wall_s:.2f} s wall (ideal {span_s / speed:.2f} s); "
          f"at most {max(early, 0) * 1000:.0f} ms ahead of schedule")
    assert early < slack_s, f"a message came {early:.2f} s before its time"
    assert wall_s >= span_s / speed - slack_s
    assert wall_s < span_s / 2  # the speed is applied (x1 would take span_s)


def _view_state(port: int) -> dict[str, Any]:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/state.json", timeout=10) as r:
        state: dict[str, Any] = json.loads(r.read())
        return state


def _until(cond: Callable[[], bool], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)  # polling a condition with a deadline


def _listening(ep: str) -> bool:
    host, port = ep.removeprefix("tcp/").rsplit(":", 1)
    with socket.socket() as s:
        s.settimeout(0.2)
        return s.connect_ex((host, int(port))) == 0


def test_view_shows_the_robots_of_a_replay(recorded: tuple[Path, Path], tmp_path: Path) -> None:
    """``tagswarm view`` of a ``tagswarm replay``: live while it plays, and at its end every robot
    at its last recorded true pose (in the map frame) and fused pose, at the last tick's time."""
    _, mcap = recorded
    scen = tmp_path / "recorded-scenario.json"
    scen.write_bytes(msgspec.json.encode(recorded_scenario(mcap)))
    a2m = arena_to_map(load_scenario(str(scen)))
    truth: dict[int, m.GroundTruthPose] = {}
    fused: dict[int, m.Correction] = {}
    last_tick: m.Tick | None = None
    for r in iter_raw(mcap, lambda k: k.endswith(("/truth", "/correction", "/world/tick"))):
        msg = codec.decode_any(r.data)
        if isinstance(msg, m.GroundTruthPose):
            truth[msg.robot_id] = msg
        elif isinstance(msg, m.Correction) and msg.localised:
            fused[msg.robot_id] = msg
        elif isinstance(msg, m.Tick):
            last_tick = msg
    assert last_tick is not None and sorted(truth) == sorted(fused) == [0, 1, 2]
    ep, port, run = endpoint(), free_port(), "replayview"
    replay_argv = [script("tagswarm"), "replay", str(mcap), "--speed", "5", "--run", run, "--listen", ep,
                   "--wait-for", "test/0"]
    view_argv = [script("tagswarm"), "view", "--connect", ep, "--run", run, "--port", str(port),
                 "--scenario", str(scen)]
    live: list[dict[str, Any]] = []
    with process(replay_argv, tmp_path / "replay.log") as replay:
        _until(lambda: _listening(ep) or replay.poll() is not None, 30, "the replay's endpoint")
        with process(view_argv, tmp_path / "view.log") as view, client(ep) as bus:
            _until(lambda: _serving(port) or view.poll() is not None, 30, "the view's HTTP port")
            assert view.poll() is None, (tmp_path / "view.log").read_text()
            bus.declare_token(Keys(run).alive("test/0"))  # the view is subscribed: start the replay

            def sample() -> bool:
                state = _view_state(port)
                if state["robots"]:
                    live.append(state)
                return replay.poll() is not None

            _until(sample, 60, "the replay to end")
            assert replay.returncode == 0, (tmp_path / "replay.log").read_text()[-2000:]
            _until(lambda: _view_state(port)["sim_ns"] == last_tick.stamp_ns, 10, "the view to show the last tick")
            final = _view_state(port)
    # live: robots drawn while the replay played, simulated time moving on
    assert len({s["sim_ns"] for s in live if s["sim_ns"] < last_tick.stamp_ns}) >= 3, [s["sim_ns"] for s in live]
    assert final["run"] == run and final["run_id"] == last_tick.run_id and final["clock"] == "lockstep"
    assert final["rejected"] == {}
    assert [r["id"] for r in final["robots"]] == [0, 1, 2]
    for r in final["robots"]:
        t, c = truth[r["id"]], fused[r["id"]]
        want_truth = se2_compose(a2m, (t.x_m, t.y_m, t.yaw_rad))
        assert r["truth"] == pytest.approx(list(want_truth), abs=1e-5), (r["id"], r["truth"], want_truth)
        f = r["fused"]
        assert f["stamp_ns"] == c.stamp_ns == last_tick.stamp_ns, (f, c.stamp_ns)
        assert [f["x"], f["y"], f["yaw"]] == pytest.approx([c.x_m, c.y_m, c.yaw_rad], abs=1e-5), (f, c)
        assert r["error_m"] is not None and r["error_m"] < 0.5  # fused vs truth at the same time, as recorded


def _serving(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.2)
        return s.connect_ex(("127.0.0.1", port)) == 0


@pytest.mark.parametrize("argv", [
    ["replay", "/nonexistent.mcap"],
    ["replay", "{junk}"],
    ["replay", "{junk}", "--speed", "0"],
    ["record"],
    ["record", "--out", "{tmp}/x.mcap", "--image-scale", "2"],
    ["record", "--out", "/nonexistent/dir/x.mcap"],
    ["up", "--replay", "{junk}", "--out", "{tmp}/run"],
])
def test_bad_arguments_exit_2_with_one_line(argv: list[str], tmp_path: Path) -> None:
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap")
    args = [a.replace("{junk}", str(junk)).replace("{tmp}", str(tmp_path)) for a in argv]
    res = subprocess.run([script("tagswarm"), *args], capture_output=True, text=True, timeout=60)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2 and len(lines) == 1 and "error" in lines[0], res.stderr
    assert not (tmp_path / "run").exists()
