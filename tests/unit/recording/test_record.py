"""MCAP recording and replay helpers without a network: what ``tagswarm record`` writes
for a synthetic two-robot run, that the mcap library's own readers accept it, and the
pieces ``tagswarm replay`` reads it with."""

from __future__ import annotations

import argparse
import math
import struct
import time
from pathlib import Path

import msgspec
import numpy as np
import pytest

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.scenario import load_scenario
from tagswarm.recording.mcapio import (
    RecordingError,
    is_command,
    is_world_stream,
    iter_raw,
    keyexpr_matches,
    message_type_for_key,
    recorded_command_key,
    remap_run,
    verify,
)
from tagswarm.recording.record import McapRecording, RecordOptions, scale_image, with_recorder, without_recorders
from tagswarm.recording.replay import recorded_participants, recorded_scenario, scenario_for_replay

RUN = "r1"
STEPS = 12
DT_NS = 33_333_333
P = f"tagswarm/{RUN}"


def _image(rid: int, step: int, w: int = 32, h: int = 24) -> m.CameraImage:
    pixels = (np.arange(w * h, dtype=np.uint32) * (rid + 3) + step).astype(np.uint8)
    return m.CameraImage(seq=step, stamp_ns=step * DT_NS, robot_id=rid, camera="front", step=step, width=w, height=h,
                         fx_px=40.0, fy_px=40.0, cx_px=16.0, cy_px=11.0, mount=m.Pose3(x_m=0.1, y_m=0.0, z_m=0.5),
                         data=pixels.tobytes())


def _world_step(step: int) -> list[tuple[str, m.Msg]]:
    """One synthetic world step for robots 0 and 1: truth, encoders, an image every 3rd
    step, then the tick (as world/node.py publishes them)."""
    ns = step * DT_NS
    out: list[tuple[str, m.Msg]] = []
    cams = []
    for rid in (0, 1):
        out.append((f"{P}/robot/{rid}/truth", m.GroundTruthPose(
            seq=step, stamp_ns=ns, robot_id=rid, step=step, x_m=0.1 * step, y_m=float(rid), yaw_rad=0.5,
            pose=m.Pose3(x_m=0.1 * step, y_m=float(rid), z_m=0.0, qz=math.sin(0.25), qw=math.cos(0.25)))))
        out.append((f"{P}/robot/{rid}/encoders", m.EncoderTicks(seq=step, stamp_ns=ns, robot_id=rid, left_ticks=step,
                                                                 right_ticks=2 * step, ticks_per_rev=4096)))
        if step % 3 == 0:
            out.append((f"{P}/robot/{rid}/camera/front", _image(rid, step)))
            cams.append(f"{rid}/front")
    out.append((f"{P}/world/tick", m.Tick(seq=step, stamp_ns=ns, run_id="w", step=step, dt_ns=DT_NS,
                                          mode="lockstep", cameras_rendered=tuple(cams))))
    return out


def _agent_outputs(step: int) -> list[tuple[str, m.Msg]]:
    ns, cov = step * DT_NS, (0.01, 0, 0, 0, 0.01, 0, 0, 0, 0.01)
    out: list[tuple[str, m.Msg]] = []
    for rid in (0, 1):
        out.append((f"{P}/robot/{rid}/odometry", m.OdometryEstimate(seq=step, stamp_ns=ns, robot_id=rid, x_m=0.5,
                                                                     y_m=0.25, yaw_rad=0.1, cov=cov, distance_m=1.0)))
        out.append((f"{P}/robot/{rid}/correction", m.Correction(
            seq=step, stamp_ns=ns, robot_id=rid, map_odom_x_m=1.5, map_odom_y_m=-2.0, map_odom_yaw_rad=0.2, x_m=3.25,
            y_m=4.5, yaw_rad=0.3, cov=cov)))
        out.append((f"{P}/world/ack/agent/{rid}", m.TickAck(seq=step, stamp_ns=ns, participant=f"agent/{rid}",
                                                             step=step)))
    out.append((f"{P}/server/map", m.GlobalMap(seq=step, stamp_ns=ns, origin_id=0, edges=((0, 1),), robots=tuple(
        m.MapEntry(robot_id=r, x_m=float(r), y_m=0.0, yaw_rad=0.0, cov=cov, last_seen_ns=ns, alive=True)
        for r in (0, 1)))))
    return out


def _record(path: Path, options: RecordOptions | None = None, garbage: bool = True) -> dict[str, int]:
    scenario = with_recorder(load_scenario("paper", ["robots.count=2", "missions=[]", 'clock.mode="lockstep"',
                                                     'clock.participants=["agent/0", "agent/1"]']))
    rec = McapRecording(path, options or RecordOptions(), run=RUN, keyexpr=f"{P}/**", scenario=scenario)
    for step in range(STEPS):
        for key, msg in [*_world_step(step), *_agent_outputs(step)]:
            rec.add(key, codec.encode(msg), time.time_ns())
        if garbage and step == 5:
            rec.add(f"{P}/robot/0/encoders", b"\xc1not msgpack", time.time_ns())  # bad payload on a known key
            rec.add(f"{P}/robot/0/odometry", codec.encode(m.OdometryEstimate(
                seq=99, stamp_ns=1, robot_id=0, x_m=math.nan, y_m=0.0, yaw_rad=0.0, cov=(0.0,) * 9, distance_m=0.0)),
                time.time_ns())
    return rec.close()


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, int]]:
    path = tmp_path_factory.mktemp("rec") / "run.mcap"
    stats = _record(path)
    return path, stats


def test_recording_passes_mcap_validation_with_expected_channels_and_counts(
        recording: tuple[Path, dict[str, int]]) -> None:
    path, stats = recording
    v = verify(path)
    assert v.counts[f"{P}/world/tick"] == STEPS
    for rid in (0, 1):
        assert v.counts[f"{P}/robot/{rid}/truth"] == STEPS
        assert v.counts[f"{P}/robot/{rid}/camera/front"] == len(range(0, STEPS, 3))
        assert v.counts[f"{P}/robot/{rid}/odometry"] == STEPS + (1 if rid == 0 else 0)  # + the NaN one, kept raw
    assert v.counts[f"{P}/robot/0/encoders"] == STEPS + 1 and v.counts[f"{P}/robot/1/encoders"] == STEPS
    assert v.schemas[f"{P}/robot/0/encoders"] == "tagswarm.EncoderTicks"
    assert v.encodings[f"{P}/robot/0/encoders"] == "msgpack"
    assert v.schemas[f"{P}/world/tick"] == "tagswarm.Tick"
    # the Foxglove views, one per source message
    assert v.schemas[f"/{RUN}/robot/1/truth"] == "foxglove.PoseInFrame" and v.counts[f"/{RUN}/robot/1/truth"] == STEPS
    assert v.schemas[f"/{RUN}/robot/0/camera/front"] == "foxglove.RawImage"
    assert v.counts[f"/{RUN}/robot/0/camera/front"] == 4
    assert v.schemas[f"/{RUN}/map"] == "foxglove.SceneUpdate" and v.counts[f"/{RUN}/map"] == STEPS
    assert v.schemas[f"/{RUN}/tf"] == "foxglove.FrameTransform"
    # map->arena once, map->odom per correction, odom->base per odometry, base->camera per image
    assert v.counts[f"/{RUN}/tf"] == 1 + 2 * STEPS + 2 * STEPS + 2 * 4
    assert v.encodings[f"/{RUN}/tf"] == "protobuf"
    assert v.start_ns == 0 and v.end_ns == (STEPS - 1) * DT_NS
    assert stats["rejected_malformed"] == 1 and stats["rejected_non_finite"] == 1
    assert stats["messages_undecodable"] == 2 and stats["messages_Tick"] == STEPS
    assert stats["images_missing"] == 0
    assert v.metadata["tagswarm.stats"]["rejected_malformed"] == "1"
    assert v.metadata["tagswarm"]["run"] == RUN


def test_raw_payloads_replay_byte_exact_in_time_order_with_ticks_last(recording: tuple[Path, dict[str, int]]) -> None:
    path, _ = recording
    got = list(iter_raw(path, is_world_stream))
    junk = [i for i, r in enumerate(got) if r.data == b"\xc1not msgpack"]
    assert len(junk) == 1 and got[junk[0]].log_time_ns == 5 * DT_NS  # at the newest simulation time seen
    got.pop(junk[0])
    want = [(k, codec.encode(msg)) for step in range(STEPS) for k, msg in _world_step(step)]
    assert [(r.key, r.data) for r in got] == want
    assert [r.log_time_ns for r in got] == [codec.decode_any(d).stamp_ns for _, d in want]


def test_ticks_follow_their_step_even_when_received_first(tmp_path: Path) -> None:
    path = tmp_path / "late.mcap"
    rec = McapRecording(path, RecordOptions(foxglove=False), run=RUN, keyexpr=f"{P}/**")
    step = _world_step(3)  # truth 0, enc 0, image 0, truth 1, enc 1, image 1, tick
    tick, image = step[-1], step[2]
    for key, msg in [tick, *[s for s in step[:-1] if s is not image], image]:  # an image from a render worker late
        rec.add(key, codec.encode(msg), time.time_ns())
    rec.close()
    keys = [r.key for r in iter_raw(path, lambda _: True)]
    assert keys[-1] == f"{P}/world/tick" and f"{P}/robot/0/camera/front" in keys[:-1] and len(keys) == len(step)


def test_frames_promised_by_a_tick_but_never_received_are_counted(tmp_path: Path) -> None:
    rec = McapRecording(tmp_path / "lossy.mcap", RecordOptions(), run=RUN, keyexpr=f"{P}/**")
    for step in range(6):
        for key, msg in _world_step(step):
            if not (step == 3 and key.endswith("1/camera/front")):
                rec.add(key, codec.encode(msg), time.time_ns())
    assert rec.close()["images_missing"] == 1


def test_undecodable_payloads_are_recorded_raw(recording: tuple[Path, dict[str, int]]) -> None:
    path, _ = recording
    enc0 = [r.data for r in iter_raw(path, lambda k: k == f"{P}/robot/0/encoders")]
    assert b"\xc1not msgpack" in enc0 and len(enc0) == STEPS + 1


def test_image_scale_downsamples_pixels_and_intrinsics(tmp_path: Path) -> None:
    img = _image(0, 0, 64, 48)
    half = scale_image(img, 0.5)
    assert (half.width, half.height) == (32, 24) and len(half.data) == 32 * 24
    assert half.fx_px == pytest.approx(20.0) and half.cx_px == pytest.approx((16.0 + 0.5) / 2 - 0.5)
    big = np.frombuffer(img.data, np.uint8).reshape(48, 64).astype(float)
    small = np.frombuffer(half.data, np.uint8).reshape(24, 32).astype(float)
    assert np.abs(small - big.reshape(24, 2, 32, 2).mean(axis=(1, 3))).max() <= 1.0  # area average
    path = tmp_path / "half.mcap"
    _record(path, RecordOptions(image_scale=0.5), garbage=False)
    raw = [codec.decode(m.CameraImage, r.data) for r in iter_raw(path, lambda k: "/camera/" in k)]
    assert {(i.width, i.height) for i in raw} == {(16, 12)}
    assert raw[0].data == scale_image(_image(raw[0].robot_id, raw[0].step), 0.5).data
    # the Foxglove RawImage carries the same (scaled) pixels: a protobuf bytes field is stored verbatim
    fox = next(r for r in _iter_all(path) if r[0] == f"/{RUN}/robot/{raw[0].robot_id}/camera/front")
    assert raw[0].data in fox[1]


def test_no_images_and_no_foxglove(tmp_path: Path) -> None:
    path = tmp_path / "lean.mcap"
    stats = _record(path, RecordOptions(images=False, foxglove=False), garbage=False)
    v = verify(path)
    assert not any("/camera/" in t for t in v.counts) and not any(t.startswith("/") for t in v.counts)
    assert stats["skipped_images"] == 2 * 4 and v.counts[f"{P}/world/tick"] == STEPS


def test_foxglove_poses_carry_the_message_values(recording: tuple[Path, dict[str, int]]) -> None:
    path, _ = recording
    fused = next(d for t, d in _iter_all(path) if t == f"/{RUN}/robot/1/fused")
    assert struct.pack("<d", 3.25) in fused and struct.pack("<d", 4.5) in fused  # x_m, y_m of the Correction


def _iter_all(path: Path) -> list[tuple[str, bytes]]:
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return [(ch.topic, msg.data) for _, ch, msg in make_reader(f).iter_messages()]


def test_verify_rejects_truncated_and_corrupted_files(recording: tuple[Path, dict[str, int]], tmp_path: Path) -> None:
    data = recording[0].read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(RecordingError):
        verify(cut)
    bad = tmp_path / "flip.mcap"
    flipped = bytearray(data)
    flipped[len(data) // 3] ^= 0xFF  # inside a compressed chunk: its CRC (or decompression) must catch it
    bad.write_bytes(bytes(flipped))
    with pytest.raises(RecordingError):
        verify(bad)
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    with pytest.raises(RecordingError):
        verify(junk)


def test_recorded_scenario_and_participants_drive_a_replay(recording: tuple[Path, dict[str, int]]) -> None:
    path, _ = recording
    table = recorded_scenario(path)
    assert table is not None and table["robots"]["count"] == 2
    assert table["clock"]["participants"] == ["agent/0", "agent/1"]  # the recorder itself is left out
    assert recorded_participants(path) == ("agent/0", "agent/1")  # from the recorded acks
    args = argparse.Namespace(scenario=None, clock=None, overrides=["agent.max_range_m=2.5"], seed=None,
                              robots=None, duration=None)

    def resolve(a: argparse.Namespace, env: dict[str, str]) -> object:
        from tagswarm.runtime.config import scenario_from

        return scenario_from(a, env)

    s = scenario_for_replay(path, args, {}, resolve)  # type: ignore[arg-type]
    assert s.robots.count == 2 and s.clock.mode == "lockstep" and s.agent.max_range_m == 2.5
    assert args.scenario is None  # the temporary file is not left behind in the namespace


def test_recorder_participant_joins_only_lockstep_runs() -> None:
    lock = load_scenario("paper", ['clock.mode="lockstep"', 'clock.participants=["server/0"]',
                                   'clock.observers=["up/0"]'])
    assert with_recorder(lock).clock.participants == ("server/0", "record/0")
    stored = without_recorders(with_recorder(lock)).clock  # what a recording keeps of the run
    assert stored.participants == ("server/0",) and stored.observers == ()
    real = load_scenario("paper")
    assert with_recorder(real).clock.participants == ()


@pytest.mark.parametrize(("pattern", "key", "ok"), [
    ("tagswarm/r/**", "tagswarm/r/robot/1/truth", True),
    ("tagswarm/r/robot/*/truth", "tagswarm/r/robot/12/truth", True),
    ("tagswarm/r/robot/*/truth", "tagswarm/r/robot/1/camera/front", False),
    ("tagswarm/**/camera/*", "tagswarm/r/robot/1/camera/front", True),
    ("tagswarm/r/robot/1/**", "tagswarm/r/robot/1", True),
    ("tagswarm/r/robot/$*1/truth", "tagswarm/r/robot/21/truth", True),
    ("tagswarm/r/robot/$*1/truth", "tagswarm/r/robot/12/truth", False),
    ("tagswarm/x/**", "tagswarm/r/world/tick", False),
])
def test_keyexpr_matching(pattern: str, key: str, ok: bool) -> None:
    assert keyexpr_matches(pattern, key) is ok


def test_key_shapes_and_run_remap() -> None:
    assert message_type_for_key("tagswarm/a/robot/3/camera/left") is m.CameraImage
    assert message_type_for_key("tagswarm/a/world/ack/agent/3") is m.TickAck
    assert message_type_for_key("tagswarm/a/server/status") is m.AgentStatus
    assert message_type_for_key("tagswarm/a/robot/3/nonsense") is None
    assert message_type_for_key("other/a/world/tick") is None
    assert is_world_stream("tagswarm/a/robot/3/encoders") and is_world_stream("tagswarm/a/world/status")
    assert not is_world_stream("tagswarm/a/robot/3/cmd") and not is_world_stream("tagswarm/a/world/ack/agent/1")
    assert not is_world_stream("tagswarm/a/world/render/0")
    assert is_command("tagswarm/a/robot/3/cmd") and not is_command("tagswarm/a/robot/3/recorded_cmd")
    assert not is_command("tagswarm/a/robot/3/encoders") and not is_command("other/a/robot/3/cmd")
    assert recorded_command_key("tagswarm/a/robot/3/cmd") == "tagswarm/a/robot/3/recorded_cmd"
    with pytest.raises(ValueError):
        recorded_command_key("tagswarm/a/robot/3/odometry")
    assert remap_run("tagswarm/a/robot/3/truth", "b") == "tagswarm/b/robot/3/truth"
    assert remap_run("other/a/x", "b") == "other/a/x"


def test_recording_metadata_holds_a_loadable_scenario(recording: tuple[Path, dict[str, int]]) -> None:
    from tagswarm.protocol.scenario import Scenario

    table = recorded_scenario(recording[0])
    s = msgspec.convert(table, Scenario)
    assert s.clock.mode == "lockstep" and s.robots.count == 2
