"""The schemas and channel metadata of a recording come from the wire contract
(:mod:`tagswarm.protocol.wire`, :mod:`tagswarm.wireschema`): every key of a run is covered,
each channel's schema describes the msgpack payloads it holds (real payloads validate,
bytes are msgpack bin, not base64), and a file written in the old layout (msgspec JSON-form
schemas, fewer metadata entries) still replays."""

from __future__ import annotations

import json
import time
from pathlib import Path

import msgpack
import msgspec
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from tagswarm import wireschema
from tagswarm.protocol import codec, wire
from tagswarm.protocol import messages as m
from tagswarm.protocol.keys import Keys
from tagswarm.recording import replay
from tagswarm.recording.mcapio import (
    channel_metadata,
    is_world_stream,
    iter_raw,
    message_type_for_key,
    raw_topics,
    verify,
)
from tagswarm.recording.record import McapRecording, RecordOptions
from tests.harness import endpoint
from tests.unit.protocol.test_codec_fuzz import EXAMPLES

RUN = "sch"
KEYS = Keys(RUN)
FILL = {"<id>": "3", "<name>": "front", "<worker>": "0", "<role>": "agent"}


def _concrete(spec: wire.KeySpec) -> str:
    """A concrete key of ``spec`` (``*`` chunks filled in placeholder order)."""
    names = iter(spec.placeholders)
    return "/".join(FILL[next(names)] if p == "*" else p for p in spec.pattern(KEYS).split("/"))


MESSAGE_KEYS = [(_concrete(s), s) for s in wire.KEYS if s.message is not None]


def _channels(path: Path) -> dict[str, tuple[str, bytes, dict[str, str]]]:
    """topic -> (schema name, schema data, channel metadata) of every raw channel."""
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    return {c.topic: (summary.schemas[c.schema_id].name if c.schema_id else "",
                      summary.schemas[c.schema_id].data if c.schema_id else b"", dict(c.metadata))
            for c in summary.channels.values() if c.message_encoding == "msgpack"}


@pytest.mark.parametrize(("key", "spec"), MESSAGE_KEYS, ids=[s.display() for _, s in MESSAGE_KEYS])
def test_every_wire_key_has_its_message_type(key: str, spec: wire.KeySpec) -> None:
    assert message_type_for_key(key) is spec.message
    meta = channel_metadata(key)
    assert spec.message is not None
    assert meta["tagswarm_type"] == spec.message.__name__
    assert meta["zenoh_encoding"] == f"application/msgpack;{spec.message.__name__}"
    assert meta["qos"] == spec.qos and meta["sender"] == spec.sender and meta["readers"] == spec.receivers


def test_the_keys_the_old_table_lacked_are_covered() -> None:
    assert message_type_for_key(KEYS.world_command()) is m.WorldCommand
    assert message_type_for_key(KEYS.render(2)) is m.RenderPoses
    assert message_type_for_key(KEYS.relocalisation()) is m.Relocalisation
    assert message_type_for_key(KEYS.alive("agent/1")) is None  # liveliness tokens carry no message
    assert message_type_for_key(f"{KEYS.prefix}/robot/1/nonsense") is None
    assert message_type_for_key("tagswarm/bad run!/world/tick") is None
    assert not is_world_stream(KEYS.world_command()) and not is_world_stream(KEYS.relocalisation())


def test_a_recording_of_every_key_has_msgpack_form_schemas_its_payloads_validate_against(tmp_path: Path) -> None:
    path = tmp_path / "all.mcap"
    rec = McapRecording(path, RecordOptions(foxglove=False), run=RUN, keyexpr=KEYS.all())
    sent = {}
    for key, spec in MESSAGE_KEYS:
        assert spec.message is not None
        payload = codec.encode(EXAMPLES[spec.message])
        sent[key] = payload
        rec.add(key, payload, time.time_ns())
    rec.close()
    verify(path)
    channels = _channels(path)
    assert set(channels) == set(sent)
    full = json.loads(wireschema.schema_text())  # as in docs/messages.schema.json
    for key, payload in sent.items():
        name, data, meta = channels[key]
        cls = message_type_for_key(key)
        assert cls is not None and name == f"tagswarm.{cls.__name__}"
        assert meta["zenoh_encoding"] == wire.encoding_of(cls) and meta["zenoh_key"] == key
        schema = json.loads(data)
        assert b"contentEncoding" not in data  # no base64 strings
        assert schema["$defs"][cls.__name__] == full["$defs"][cls.__name__]  # one source of truth
        validator = wireschema.validator(schema)
        decoded = msgpack.unpackb(payload)
        assert list(validator.iter_errors(decoded)) == []
        # and it can fail: another message type's payload does not validate
        other = m.Tick if cls is not m.Tick else m.Goal
        assert list(validator.iter_errors(msgpack.unpackb(codec.encode(EXAMPLES[other])))) != []
    image = json.loads(channels[_concrete(next(s for s in wire.KEYS if s.message is m.CameraImage))][1])
    assert image["$defs"]["CameraImage"]["properties"]["data"]["format"] == "binary"
    bad = msgpack.unpackb(sent[KEYS.image(3, "front")])
    bad["data"] = "AAAA"  # a base64 string where msgpack bin belongs
    assert list(wireschema.validator(image).iter_errors(bad)) != []


def _write_old_style(path: Path, messages: list[tuple[str, m.Msg]]) -> None:
    """A recording in the layout written before the wire schemas: msgspec's JSON-form
    schema (bytes as base64 strings), channel metadata with the key and type only."""
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="tagswarm record (mcap-python)")
        schemas: dict[str, int] = {}
        channels: dict[str, int] = {}
        for key, msg in messages:
            name = type(msg).__name__
            if name not in schemas:
                schemas[name] = w.register_schema(f"tagswarm.{name}", "jsonschema",
                                                  json.dumps(msgspec.json.schema(type(msg))).encode())
            if key not in channels:
                channels[key] = w.register_channel(key, "msgpack", schemas[name],
                                                   {"zenoh_key": key, "tagswarm_type": name})
            stamp = msg.stamp_ns  # type: ignore[attr-defined]
            w.add_message(channels[key], stamp, codec.encode(msg), time.time_ns(), 0)
        w.add_metadata("tagswarm", {"run": "old", "keyexpr": "tagswarm/old/**"})
        w.finish()


def _old_run() -> list[tuple[str, m.Msg]]:
    k = Keys("old")
    out: list[tuple[str, m.Msg]] = []
    for step in range(4):
        ns = step * 10_000_000
        out.append((k.encoders(0), m.EncoderTicks(seq=step, stamp_ns=ns, robot_id=0, left_ticks=step,
                                                   right_ticks=step, ticks_per_rev=4096)))
        if step == 0:
            out.append((k.image(0, "front"), m.CameraImage(
                seq=0, stamp_ns=0, robot_id=0, camera="front", step=0, width=2, height=2, fx_px=1.0, fy_px=1.0,
                cx_px=1.0, cy_px=1.0, mount=m.Pose3(x_m=0.0, y_m=0.0, z_m=0.5), data=b"\x01\x02\x03\x04")))
        out.append((k.ack("agent/0"), m.TickAck(seq=step, stamp_ns=ns, participant="agent/0", step=step)))
        out.append((k.tick(), m.Tick(seq=step, stamp_ns=ns, run_id="w", step=step, dt_ns=10_000_000,
                                     mode="lockstep", cameras_rendered=())))
    return out


def test_an_old_style_recording_still_replays(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "old.mcap"
    msgs = _old_run()
    _write_old_style(path, msgs)
    _, data, meta = _channels(path)[Keys("old").image(0, "front")]
    assert b"contentEncoding" in data and "zenoh_encoding" not in meta  # written the old way (base64)
    assert raw_topics(path) == sorted({k for k, _ in msgs})
    world = [(r.key, r.data) for r in iter_raw(path, is_world_stream)]
    assert world == [(k, codec.encode(x)) for k, x in msgs if not k.endswith("/agent/0")]
    assert replay.recorded_participants(path) == ("agent/0",)
    # the command itself, into the void of a private network: every message goes out
    assert replay.main([str(path), "--speed", "1000", "--listen", endpoint()]) == 0
    assert "13 messages, 4 ticks" in capsys.readouterr().err
