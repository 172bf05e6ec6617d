"""The wire contract of protocol/wire.py and the encoding the bus sets per message type
(no network: the bus's Publisher is driven with a fake zenoh publisher)."""

from __future__ import annotations

import typing
from typing import Any

import msgspec
import pytest
import zenoh

from tagswarm.protocol import bus, codec, wire
from tagswarm.protocol import messages as m
from tagswarm.protocol.keys import Keys
from tests.unit.protocol.test_codec_fuzz import EXAMPLES, _example

K = Keys("r1")


def test_every_message_type_is_on_the_wire_list() -> None:
    union = set(typing.get_args(m.AnyMessage))
    assert set(wire.MESSAGE_TYPES) == union == set(codec.MAX_BYTES)
    assert len(wire.MESSAGE_TYPES) == len(union)


@pytest.mark.parametrize("cls", wire.MESSAGE_TYPES, ids=lambda c: c.__name__)
def test_encoding_names_the_message_type(cls: type[m.Msg]) -> None:
    enc = wire.encoding_of(cls)
    assert enc == f"application/msgpack;{cls.__name__}"
    assert wire.type_of_encoding(enc) is cls
    assert str(bus.encoding_for(codec.encode(EXAMPLES[cls]))) == enc


def test_foreign_encodings_name_no_type() -> None:
    for enc in ("", "zenoh/bytes", "application/msgpack", "application/json;Tick", "application/msgpack;Nope",
                "application/msgpack;tick"):
        assert wire.type_of_encoding(enc) is None


@pytest.mark.parametrize("cls", wire.MESSAGE_TYPES, ids=lambda c: c.__name__)
def test_the_head_of_every_payload_names_its_type_and_is_the_same_for_every_instance(cls: type[m.Msg]) -> None:
    a, b = codec.encode(_example(cls, 0)), codec.encode(_example(cls, 1))
    head_a, head_b = wire.message_head(a), wire.message_head(b)
    assert head_a is not None and head_b is not None
    assert head_a[0] is cls and head_a == head_b and a[: head_a[1]] == b[: head_b[1]]
    tag = str(cls.__struct_config__.tag).encode()
    assert a[: head_a[1]].endswith(tag)


def test_payloads_that_are_not_tagswarm_messages_have_no_type() -> None:
    msgpack = msgspec.msgpack.encode
    for payload in (b"", b"\x80", b"\xc1garbage", b"0", msgpack([1, 2]), msgpack({"type": "nope", "seq": 1}),
                    msgpack({"seq": 1, "type": "tick"}), msgpack({"type": 3}), b"\x81\xa4type", b"\x81\xa4type\xa4ti"):
        assert wire.message_type_of(payload) is None, payload
        assert bus.encoding_for(payload) == zenoh.Encoding.ZENOH_BYTES


def test_map16_and_str8_heads_are_read() -> None:
    big = {"type": "goal", **{f"f{i}": i for i in range(20)}}  # > 15 entries: a map 16 header
    assert msgspec.msgpack.encode(big)[0] == 0xDE
    assert wire.message_type_of(msgspec.msgpack.encode(big)) is m.Goal
    long_tag = b"\x81\xa4type\xd9\x04goal"  # the tag as a str 8
    assert wire.message_head(long_tag) == (m.Goal, len(long_tag))


class FakePub:
    def __init__(self, encoding: zenoh.Encoding) -> None:
        self.declared = encoding
        self.puts: list[tuple[bytes, Any]] = []

    def put(self, payload: bytes, *, encoding: Any = None) -> None:
        self.puts.append((payload, encoding))


def _publisher() -> tuple[bus.Publisher, list[FakePub]]:
    declared: list[FakePub] = []

    def declare(encoding: zenoh.Encoding) -> FakePub:
        declared.append(FakePub(encoding))
        return declared[-1]

    return bus.Publisher(declare), declared


def test_the_publisher_is_declared_with_the_first_payloads_encoding_and_later_puts_pass_none() -> None:
    pub, declared = _publisher()
    ticks = [codec.encode(_example(m.EncoderTicks, i)) for i in range(3)]
    for t in ticks:
        pub.put(t)
    assert len(declared) == 1 and str(declared[0].declared) == "application/msgpack;EncoderTicks"
    assert declared[0].puts == [(t, None) for t in ticks]  # the declared encoding: nothing per put


def test_a_payload_of_another_type_or_garbage_carries_its_own_encoding() -> None:
    pub, declared = _publisher()
    enc, goal = codec.encode(EXAMPLES[m.EncoderTicks]), codec.encode(EXAMPLES[m.Goal])
    for payload in (enc, goal, b"\xc1junk", enc):
        pub.put(payload)
    (fake,) = declared
    assert [(p, None if e is None else str(e)) for p, e in fake.puts] == [
        (enc, None), (goal, "application/msgpack;Goal"), (b"\xc1junk", "zenoh/bytes"), (enc, None)]


def test_a_publisher_whose_first_payload_is_garbage_still_labels_real_messages() -> None:
    pub, declared = _publisher()
    tick = codec.encode(EXAMPLES[m.Tick])
    pub.put(b"not msgpack")
    pub.put(tick)
    (fake,) = declared
    assert str(fake.declared) == "zenoh/bytes"
    assert [(p, None if e is None else str(e)) for p, e in fake.puts] == [
        (b"not msgpack", None), (tick, "application/msgpack;Tick")]


def test_the_reply_to_a_map_query_carries_the_encoding() -> None:
    replies: list[tuple[str, bytes, str]] = []

    class FakeQuery:
        def __enter__(self) -> FakeQuery:
            return self

        def __exit__(self, *_: object) -> None:
            pass

        def reply(self, key: str, payload: bytes, *, encoding: zenoh.Encoding) -> None:
            replies.append((key, payload, str(encoding)))

    payload = codec.encode(EXAMPLES[m.GlobalMap])
    bus.Bus.reply(FakeQuery(), K.map(), payload)
    assert replies == [(K.map(), payload, "application/msgpack;GlobalMap")]


# --------------------------------------------------------------------------- keys


CONCRETE: dict[str, type[m.Msg] | None] = {
    K.tick(): m.Tick, K.ack("agent/3"): m.TickAck, K.ack("render/0"): m.TickAck, K.render(1): m.RenderPoses,
    K.world_status(): m.AgentStatus, K.world_command(): m.WorldCommand, K.image(2, "front"): m.CameraImage,
    K.encoders(2): m.EncoderTicks, K.cmd(2): m.WheelCommand, K.truth(2): m.GroundTruthPose,
    K.observation(2): m.RelativeObservation, K.odometry(2): m.OdometryEstimate, K.correction(2): m.Correction,
    K.goal(2): m.Goal, K.robot_status(2): m.AgentStatus, K.map(): m.GlobalMap, K.server_status(): m.AgentStatus,
    K.relocalisation(): m.Relocalisation, K.alive("agent/1"): None,
}


@pytest.mark.parametrize("key", list(CONCRETE))
def test_every_key_of_a_run_has_one_spec_with_its_message_type(key: str) -> None:
    spec = wire.spec_for_key(K, key)
    assert spec is not None and spec.message is CONCRETE[key]
    assert sum(1 for s in wire.KEYS if wire.spec_for_key(K, key) is s) == 1


def test_keys_of_other_runs_or_shapes_have_no_spec() -> None:
    for key in (Keys("other").tick(), "tagswarm/r1/robot/1/unknown", "tagswarm/r1/world", "foo/r1/world/tick"):
        assert wire.spec_for_key(K, key) is None


def test_every_message_type_has_a_key_and_displays_read_plainly() -> None:
    assert {s.message for s in wire.KEYS} - {None} == set(wire.MESSAGE_TYPES)
    shown = [s.display() for s in wire.KEYS]
    assert "tagswarm/<run>/robot/<id>/camera/<name>" in shown and "tagswarm/<run>/world/ack/<role>/<id>" in shown
    assert all("*" not in d for d in shown) and len(set(shown)) == len(shown)
    images = next(s for s in wire.KEYS if s.message is m.CameraImage)
    assert images.qos == "drop_realtime" and {s.qos for s in wire.KEYS if s is not images} <= {"block", "none"}
