"""docs/messages.schema.json describes the msgpack form: every message type, encoded by the
codec and decoded by plain msgpack-python, validates against it (built examples and
hypothesis-generated ones) and round-trips back through msgpack-python; docs/protocol.md
speaks plain words, not msgspec."""

from __future__ import annotations

import json
import re
from typing import Any

import jsonschema
import msgpack
import msgspec
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tagswarm import docs, wireschema
from tagswarm.protocol import codec, wire
from tagswarm.protocol import messages as m
from tests.unit.protocol.test_codec_fuzz import EXAMPLES, _example, valid

SCHEMA = json.loads((docs.DOCS / "messages.schema.json").read_text())  # the committed file, not a fresh one
VALIDATOR = wireschema.validator(SCHEMA)
SOME = settings(max_examples=30, deadline=None, suppress_health_check=list(HealthCheck))


def _plain(payload: bytes) -> Any:
    """What a msgpack decoder in another language sees (bin -> bytes, str -> str)."""
    return msgpack.unpackb(payload, raw=False)


def _errors(obj: Any, cls: type[m.Msg] | None = None) -> list[str]:
    schema = SCHEMA if cls is None else {**SCHEMA, "oneOf": [{"$ref": f"#/$defs/{cls.__name__}"}]}
    return [f"{list(e.absolute_path)}: {e.message}" for e in wireschema.validator(schema).iter_errors(obj)]


def test_the_schema_is_valid_json_schema_and_covers_every_type() -> None:
    jsonschema.Draft202012Validator.check_schema(SCHEMA)
    assert [r["$ref"] for r in SCHEMA["oneOf"]] == [f"#/$defs/{c.__name__}" for c in wire.MESSAGE_TYPES]
    for cls in wire.MESSAGE_TYPES:
        assert SCHEMA["$defs"][cls.__name__]["x-zenoh-encoding"] == wire.encoding_of(cls)
    assert "contentEncoding" not in json.dumps(SCHEMA)


@pytest.mark.parametrize("cls", wire.MESSAGE_TYPES, ids=lambda c: c.__name__)
def test_built_examples_validate_and_round_trip_through_msgpack_python(cls: type[m.Msg]) -> None:
    for salt in range(3):
        msg = _example(cls, salt)
        obj = _plain(codec.encode(msg))
        assert obj["type"] == cls.__struct_config__.tag
        assert _errors(obj, cls) == [] and VALIDATOR.is_valid(obj)
        assert codec.decode(cls, msgpack.packb(obj, use_bin_type=True)) == msg


@pytest.mark.parametrize("cls", wire.MESSAGE_TYPES, ids=lambda c: c.__name__)
@SOME
@given(data=st.data())
def test_generated_messages_validate_and_round_trip(cls: type[m.Msg], data: st.DataObject) -> None:
    msg = data.draw(valid(cls))
    obj = _plain(codec.encode(msg))
    assert _errors(obj, cls) == []
    assert codec.decode(cls, msgpack.packb(obj, use_bin_type=True)) == msg


def test_image_data_is_binary_not_a_string() -> None:
    obj = _plain(codec.encode(EXAMPLES[m.CameraImage]))
    assert isinstance(obj["data"], bytes)
    as_text = {**obj, "data": "AAEC"}  # what the old schema (base64 strings) described
    assert any("data" in e for e in _errors(as_text, m.CameraImage))
    assert not VALIDATOR.is_valid(as_text)


def test_the_schema_rejects_what_the_codec_rejects_by_shape() -> None:
    good = _plain(codec.encode(EXAMPLES[m.Correction]))
    assert not VALIDATOR.is_valid({k: v for k, v in good.items() if k != "x_m"})  # a required field missing
    assert not VALIDATOR.is_valid({**good, "type": "nope"})
    assert not VALIDATOR.is_valid({**good, "robot_id": -1})
    assert not VALIDATOR.is_valid({**good, "cov": "0,0,0"})
    assert not VALIDATOR.is_valid([good])


def test_old_senders_without_the_optional_fields_still_validate() -> None:
    for cls in wire.MESSAGE_TYPES:
        info = msgspec.inspect.type_info(cls)
        assert isinstance(info, msgspec.inspect.StructType)
        optional = {f.name for f in info.fields if not f.required}
        obj = {k: v for k, v in _plain(codec.encode(EXAMPLES[cls])).items() if k not in optional}
        assert _errors(obj, cls) == [], cls.__name__


# --------------------------------------------------------------------------- docs/protocol.md


def test_protocol_md_lists_every_key_and_type_with_its_encoding_in_plain_words() -> None:
    text = docs.markdown()
    for spec in wire.KEYS:
        assert f"`{spec.display()}`" in text
    for cls in wire.MESSAGE_TYPES:
        assert f"### {cls.__name__}" in text and f"`{wire.encoding_of(cls)}`" in text
    for jargon in ("vartuple", "struct", "msgspec", "Struct"):
        assert not re.search(rf"\b{jargon}\b", text), jargon
    assert "DROP in realtime runs" in text and "BLOCK, express" in text
    assert "binary (msgpack bin)" in text and "[xx, xy, xθ, yx, yy, yθ, θx, θy, θθ]" in text


def test_field_notes_name_real_fields() -> None:
    owners = {c.__name__: c for c in (*wire.MESSAGE_TYPES, m.Pose3, m.MapEntry, m.Msg)}
    for owner, field in docs.FIELD_NOTES:
        assert field in owners[owner].__struct_fields__, (owner, field)


def test_units_come_from_field_names() -> None:
    assert [docs.unit_of(f) for f in ("x_m", "yaw_rad", "left_rad_s", "v_m_s", "stamp_ns", "fx_px", "seq")] == [
        "metres", "radians", "rad/s", "m/s", "nanoseconds", "pixels", ""]
