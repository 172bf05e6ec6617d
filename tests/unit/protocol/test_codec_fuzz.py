"""Property-based fuzzing of every wire decoder (no network).

The property, for every message type ``cls`` in ``tagswarm.protocol.messages`` and for
``decode_any``: ``codec.decode(cls, payload)`` returns a valid ``cls`` (it round
trips) or raises ``codec.DecodeError`` whose ``kind`` is one of
``codec.DECODE_KINDS`` -- never any other exception, whatever the bytes.

Valid messages are generated from the structs' own type information (so a new
field or type is fuzzed without touching this file), then attacked: random and
truncated bytes, the wrong type or tag, msgpack headers declaring gigantic
arrays / maps / strings / binaries, NaN and +-inf in every float field (nested
ones too: Pose3, MapEntry, covariances), values below the schema's bounds in
every constrained integer, inconsistent contents and payloads over the per-type
size limit (which must be rejected before any decoding).
"""

from __future__ import annotations

import math
import struct
import typing
from collections.abc import Iterator
from typing import Any

import msgspec
import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import Received
from tagswarm.runtime import streams

TYPES: list[type[m.Msg]] = list(codec.MAX_BYTES)
KINDS = codec.DECODE_KINDS
# float fields with a bound in the schema: NaN / -inf there fail the bound check first ("malformed")
BOUNDED_FLOATS = {"fx_px", "fy_px", "tolerance_m", "slip_m", "jump_m"}
FEW = settings(max_examples=25, deadline=None, suppress_health_check=list(HealthCheck))
SOME = settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))

Path = tuple[str | int, ...]


def _ids(cls: Any) -> str:
    return getattr(cls, "__name__", str(cls))


# --------------------------------------------------------------------------- valid messages from type info

finite = st.floats(allow_nan=False, allow_infinity=False)


@st.composite
def unit_quaternion(draw: st.DrawFn) -> tuple[float, float, float, float]:
    q = np.array(draw(st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4)))
    n = float(np.linalg.norm(q))
    assume(n > 1e-3)
    return tuple(float(v) for v in q / n)  # type: ignore[return-value]


@st.composite
def pose3(draw: st.DrawFn) -> m.Pose3:
    qx, qy, qz, qw = draw(unit_quaternion())
    return m.Pose3(x_m=draw(finite), y_m=draw(finite), z_m=draw(finite), qx=qx, qy=qy, qz=qz, qw=qw)


@st.composite
def covariance(draw: st.DrawFn) -> tuple[float, ...]:
    """A symmetric positive semi-definite 3x3 matrix, row-major (sometimes all zero)."""
    if draw(st.booleans()) and draw(st.booleans()):
        return (0.0,) * 9
    a = np.array(draw(st.lists(st.floats(-10.0, 10.0), min_size=9, max_size=9))).reshape(3, 3)
    c = a @ a.T + np.eye(3) * draw(st.floats(0.0, 1.0))
    return tuple(float(v) for v in c.ravel())


def _strategy(info: msgspec.inspect.Type) -> st.SearchStrategy[Any]:
    """Values of one msgspec type that satisfy its constraints."""
    i = msgspec.inspect
    if isinstance(info, i.IntType):
        lo = info.ge if info.ge is not None else (info.gt + 1 if info.gt is not None else -(2**63))
        hi = info.le if info.le is not None else (info.lt - 1 if info.lt is not None else 2**63 - 1)
        return st.integers(lo, hi)
    if isinstance(info, i.FloatType):
        flo = info.ge if info.ge is not None else info.gt
        fhi = info.le if info.le is not None else info.lt
        return st.floats(min_value=flo, max_value=fhi, exclude_min=info.gt is not None,
                         exclude_max=info.lt is not None, allow_nan=False, allow_infinity=False)
    if isinstance(info, i.StrType):
        return st.text(max_size=12)
    if isinstance(info, i.BytesType):
        return st.binary(max_size=32)
    if isinstance(info, i.BoolType):
        return st.booleans()
    if isinstance(info, i.NoneType):
        return st.none()
    if isinstance(info, i.LiteralType):
        return st.sampled_from(info.values)
    if isinstance(info, i.VarTupleType):
        return st.lists(_strategy(info.item_type), max_size=3).map(tuple)
    if isinstance(info, i.TupleType):
        return st.tuples(*(_strategy(t) for t in info.item_types))
    if isinstance(info, i.DictType):
        return st.dictionaries(_strategy(info.key_type), _strategy(info.value_type), max_size=3)
    if isinstance(info, i.UnionType):
        return st.one_of(*(_strategy(t) for t in info.types))
    if isinstance(info, i.StructType):
        return struct_strategy(info.cls)
    raise AssertionError(f"no strategy for {info!r}: extend the fuzzer")


# fields whose valid values have structure beyond their type
OVERRIDES: dict[tuple[type[Any], str], st.SearchStrategy[Any]] = {
    (m.CameraImage, "width"): st.integers(1, 24),
    (m.CameraImage, "height"): st.integers(1, 24),
}


def struct_strategy(cls: type[Any]) -> st.SearchStrategy[Any]:
    """Valid instances of a struct (message or nested), consistent as the codec requires."""
    if cls is m.Pose3:
        return pose3()
    info = msgspec.inspect.type_info(cls)
    assert isinstance(info, msgspec.inspect.StructType)
    required: dict[str, st.SearchStrategy[Any]] = {}
    optional: dict[str, st.SearchStrategy[Any]] = {}
    for f in info.fields:
        strat = OVERRIDES.get((cls, f.name))
        if strat is None:
            strat = covariance() if f.name == "cov" else _strategy(f.type)
        (required if f.required else optional)[f.name] = strat
    return st.fixed_dictionaries(required, optional=optional).map(lambda kw: _consistent(cls(**kw)))


def _consistent(msg: Any) -> Any:
    r = msgspec.structs.replace
    if isinstance(msg, m.CameraImage):
        return r(msg, data=bytes((7 * i) % 256 for i in range(msg.width * msg.height)))
    if isinstance(msg, m.RenderPoses):
        n = min(len(msg.robot_ids), len(msg.poses))
        return r(msg, robot_ids=msg.robot_ids[:n], poses=msg.poses[:n])
    return msg


def valid(cls: type[m.Msg]) -> st.SearchStrategy[m.Msg]:
    return struct_strategy(cls)


def _full(obj: Any) -> bool:
    """Every list/tuple/dict in ``obj`` non-empty (so nested fields exist to attack)."""
    if isinstance(obj, dict):
        return bool(obj) and all(_full(v) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return bool(obj) and all(_full(v) for v in obj)
    return obj is not None


def _builtins(msg: m.Msg) -> dict[str, Any]:
    out = msgspec.to_builtins(msg, builtin_types=(bytes,))
    assert isinstance(out, dict) and out["type"] == type(msg).__struct_config__.tag
    return out


def _example_value(info: msgspec.inspect.Type, salt: int) -> Any:
    """A deterministic valid value of one msgspec type, with every container holding two items."""
    i = msgspec.inspect
    if isinstance(info, i.IntType):
        lo = info.ge if info.ge is not None else (info.gt + 1 if info.gt is not None else -5)
        hi = info.le if info.le is not None else (info.lt - 1 if info.lt is not None else 2**40)
        return min(max(lo + 3 + salt, lo), hi)
    if isinstance(info, i.FloatType):
        return 0.25 + 0.5 * salt  # > 0 for the bounded ones
    if isinstance(info, i.StrType):
        return f"s{salt}"
    if isinstance(info, i.BytesType):
        return bytes(range(salt + 3))
    if isinstance(info, i.BoolType):
        return salt % 2 == 0
    if isinstance(info, i.LiteralType):
        return info.values[salt % len(info.values)]
    if isinstance(info, i.VarTupleType):
        return tuple(_example_value(info.item_type, salt + k) for k in range(2))
    if isinstance(info, i.TupleType):
        return tuple(_example_value(t, salt + k) for k, t in enumerate(info.item_types))
    if isinstance(info, i.DictType):
        return {_example_value(info.key_type, salt + k): _example_value(info.value_type, salt + k) for k in range(2)}
    if isinstance(info, i.UnionType):
        return _example_value(next(t for t in info.types if not isinstance(t, i.NoneType)), salt)
    if isinstance(info, i.StructType):
        return _example(info.cls, salt)
    raise AssertionError(f"no example for {info!r}: extend the fuzzer")


def _example(cls: type[Any], salt: int = 0) -> Any:
    if cls is m.Pose3:
        return m.Pose3(x_m=1.0 + salt, y_m=-0.5, z_m=0.25, qx=0.5, qy=-0.5, qz=0.5, qw=0.5)
    info = msgspec.inspect.type_info(cls)
    assert isinstance(info, msgspec.inspect.StructType)
    kw: dict[str, Any] = {}
    for f in info.fields:
        if (cls, f.name) in OVERRIDES:
            kw[f.name] = 3 + salt
        elif f.name == "cov":
            kw[f.name] = (0.04, 0.01, 0.0, 0.01, 0.09, 0.002, 0.0, 0.002, 0.01)
        else:
            kw[f.name] = _example_value(f.type, salt)
    return _consistent(cls(**kw))


#: One deterministic, fully populated example per type (nested structs and containers non-empty).
EXAMPLES: dict[type[m.Msg], m.Msg] = {cls: _example(cls) for cls in TYPES}


# --------------------------------------------------------------------------- helpers


def _leaves(obj: Any, path: Path = ()) -> Iterator[tuple[Path, Any]]:
    """(path, value) of every scalar inside a builtins tree."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _leaves(v, (*path, k))
    elif isinstance(obj, (list, tuple)):
        for j, v in enumerate(obj):
            yield from _leaves(v, (*path, j))
    else:
        yield path, obj


def _set(obj: Any, path: Path, value: Any) -> Any:
    """A copy of ``obj`` with the leaf at ``path`` replaced (tuples become lists)."""
    if not path:
        return value
    head, rest = path[0], path[1:]
    if isinstance(obj, dict):
        return {**obj, head: _set(obj[head], rest, value)}
    out = list(obj)
    out[int(head)] = _set(out[int(head)], rest, value)
    return out


def _field_info(cls: type[Any], path: Path) -> msgspec.inspect.Type:
    """The msgspec type of the leaf at ``path`` inside a ``cls`` builtins tree."""
    info: msgspec.inspect.Type = msgspec.inspect.type_info(cls)
    for step in path:
        if isinstance(info, msgspec.inspect.UnionType):
            info = next(t for t in info.types if not isinstance(t, msgspec.inspect.NoneType))
        if isinstance(info, msgspec.inspect.StructType):
            if step == "type":
                return msgspec.inspect.StrType()
            info = next(f.type for f in info.fields if f.name == step)
        elif isinstance(info, msgspec.inspect.VarTupleType):
            info = info.item_type
        elif isinstance(info, msgspec.inspect.TupleType):
            info = info.item_types[int(step)]
        elif isinstance(info, msgspec.inspect.DictType):
            info = info.value_type
        else:
            raise AssertionError(f"cannot descend {path} at {step!r} in {info!r}")
    if isinstance(info, msgspec.inspect.UnionType):
        info = next(t for t in info.types if not isinstance(t, msgspec.inspect.NoneType))
    return info


def _outcome(cls: type[m.Msg] | None, payload: bytes | bytearray | memoryview) -> str:
    """'ok' or the reject kind; fails the test on any other exception or a bad result."""
    try:
        out = codec.decode_any(payload) if cls is None else codec.decode(cls, payload)
    except codec.DecodeError as exc:
        assert exc.kind in KINDS, exc
        assert exc.detail
        return exc.kind
    if cls is not None:
        assert type(out) is cls
    assert type(out) in codec.MAX_BYTES
    assert codec.decode(type(out), codec.encode(out)) == out  # what is accepted is re-encodable, idempotently
    return "ok"


def _everywhere(payload: bytes) -> dict[str, str]:
    """The outcome for every type and for decode_any."""
    out = {cls.__name__: _outcome(cls, payload) for cls in TYPES}
    out["any"] = _outcome(None, payload)
    return out


def _pack(pairs: list[tuple[bytes, bytes]]) -> bytes:
    """A msgpack map from already-encoded keys and values."""
    n = len(pairs)
    head = bytes([0x80 | n]) if n < 16 else b"\xde" + struct.pack(">H", n)
    return head + b"".join(k + v for k, v in pairs)


# --------------------------------------------------------------------------- the generator covers the protocol


def test_every_wire_type_is_fuzzed() -> None:
    assert set(TYPES) == set(typing.get_args(m.AnyMessage))
    for cls, msg in EXAMPLES.items():
        assert type(msg) is cls
        assert codec.decode(cls, codec.encode(msg)) == msg
    # the examples hold nested structs and covariances to attack
    assert EXAMPLES[m.GlobalMap].robots and EXAMPLES[m.RenderPoses].poses  # type: ignore[attr-defined]
    floats = {cls: [p for p, v in _leaves(_builtins(msg)) if isinstance(v, float)] for cls, msg in EXAMPLES.items()}
    assert ("robots", 0, "cov", 8) in floats[m.GlobalMap]
    assert ("mount", "qw") in floats[m.CameraImage]
    assert ("poses", 0, "qx") in floats[m.RenderPoses]


# --------------------------------------------------------------------------- valid messages


@pytest.mark.parametrize("cls", TYPES, ids=_ids)
@FEW
@given(data=st.data())
def test_generated_messages_round_trip(cls: type[m.Msg], data: st.DataObject) -> None:
    msg = data.draw(valid(cls))
    payload = codec.encode(msg)
    assert codec.decode(cls, payload) == msg
    assert codec.decode_any(payload) == msg
    for other in TYPES:
        if other is not cls:
            assert _outcome(other, payload) == "malformed"  # the tag decides


# --------------------------------------------------------------------------- random and truncated bytes


@SOME
@given(st.binary(max_size=300))
def test_random_bytes(payload: bytes) -> None:
    _everywhere(payload)


@pytest.mark.parametrize("cls", TYPES, ids=_ids)
def test_every_truncation_of_a_valid_message_is_malformed(cls: type[m.Msg]) -> None:
    payload = codec.encode(EXAMPLES[cls])
    for cut in range(len(payload)):
        for wrap in (bytes, memoryview):
            assert _outcome(cls, wrap(payload[:cut])) == "malformed", cut
        assert _outcome(None, payload[:cut]) == "malformed", cut


@pytest.mark.parametrize("cls", TYPES, ids=_ids)
@FEW
@given(data=st.data())
def test_truncated_and_corrupted_generated_messages(cls: type[m.Msg], data: st.DataObject) -> None:
    payload = bytearray(codec.encode(data.draw(valid(cls))))
    cut = data.draw(st.integers(0, len(payload) - 1))
    assert _outcome(cls, bytes(payload[:cut])) == "malformed"
    for _ in range(data.draw(st.integers(1, 4))):
        payload[data.draw(st.integers(0, len(payload) - 1))] = data.draw(st.integers(0, 255))
    _everywhere(bytes(payload))


# --------------------------------------------------------------------------- wrong type, wrong tag


json_like = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats() | st.text(max_size=8)
    | st.binary(max_size=16),
    lambda kids: st.lists(kids, max_size=4) | st.dictionaries(st.text(max_size=8), kids, max_size=4),
    max_leaves=12,
)


@SOME
@given(json_like)
def test_valid_msgpack_of_any_shape(obj: Any) -> None:
    outcomes = _everywhere(msgspec.msgpack.encode(obj))
    if not isinstance(obj, dict):
        assert set(outcomes.values()) == {"malformed"}


@pytest.mark.parametrize("cls", TYPES, ids=_ids)
def test_every_other_tag_is_malformed_for_this_type(cls: type[m.Msg]) -> None:
    fields = _builtins(EXAMPLES[cls])
    for other in TYPES:
        retagged = msgspec.msgpack.encode({**fields, "type": other.__struct_config__.tag})
        if other is not cls:
            assert _outcome(cls, retagged) == "malformed", other
        _everywhere(retagged)  # as the other type it may even be valid, but nothing else may happen
    for tag in ["", "TICK", "no_such_type", 0, None, ["tick"]]:
        assert set(_everywhere(msgspec.msgpack.encode({**fields, "type": tag})).values()) == {"malformed"}
    del fields["type"]
    untagged = msgspec.msgpack.encode(fields)
    assert _outcome(None, untagged) == "malformed"  # the union needs the tag
    _everywhere(untagged)  # msgspec lets a lone struct type default its own tag: either outcome is fine


@pytest.mark.parametrize("cls", TYPES, ids=_ids)
@FEW
@given(data=st.data())
def test_a_field_of_the_wrong_type(cls: type[m.Msg], data: st.DataObject) -> None:
    fields = _builtins(data.draw(valid(cls)))
    paths = [p for p, _ in _leaves(fields) if p != ("type",)]
    path = data.draw(st.sampled_from(paths))
    _everywhere(msgspec.msgpack.encode(_set(fields, path, data.draw(json_like))))


@pytest.mark.parametrize("cls", TYPES, ids=_ids)
@FEW
@given(data=st.data())
def test_the_right_tag_and_field_names_with_random_values(cls: type[m.Msg], data: st.DataObject) -> None:
    """Struct-shaped maps: the type's tag, any subset of its field names, arbitrary values."""
    names = sorted(cls.__struct_fields__)
    obj: dict[str, Any] = {"type": cls.__struct_config__.tag}
    obj.update(data.draw(st.dictionaries(st.sampled_from(names), json_like, max_size=len(names))))
    _everywhere(msgspec.msgpack.encode(obj))


# --------------------------------------------------------------------------- huge declared sizes

HUGE_HEADERS = {
    "array32": b"\xdd\xff\xff\xff\xff",
    "map32": b"\xdf\xff\xff\xff\xff",
    "str32": b"\xdb\xff\xff\xff\xff",
    "bin32": b"\xc6\xff\xff\xff\xff",
    "ext32": b"\xc9\xff\xff\xff\xff\x01",
    "array16": b"\xdc\xff\xff",
    "map16": b"\xde\xff\xff",
}


@pytest.mark.parametrize("header", list(HUGE_HEADERS), ids=str)
@pytest.mark.parametrize("cls", TYPES, ids=_ids)
def test_headers_declaring_giant_sizes(cls: type[m.Msg], header: str) -> None:
    """A header claiming 4 G elements/bytes with a few bytes behind it: rejected
    as malformed at the top level and in place of every field (no huge allocation)."""
    hdr = HUGE_HEADERS[header]
    tails = [b"", b"\x00" * 7, bytes(range(64))]
    for tail in tails:
        assert set(_everywhere(hdr + tail).values()) == {"malformed"}
    fields = _builtins(EXAMPLES[cls])
    enc = {k: msgspec.msgpack.encode(k) for k in fields}
    for name in fields:
        pairs = [(enc[k], hdr + b"\x01\x02" if k == name else msgspec.msgpack.encode(v)) for k, v in fields.items()]
        payload = _pack(pairs)
        assert _outcome(cls, payload) == "malformed", name
        assert _outcome(None, payload) == "malformed", name
        # the same header as the LAST thing in the payload (nothing at all behind it)
        last = _pack([*(p for p in pairs if p[0] != enc[name]), (enc[name], hdr)])
        assert _outcome(cls, last) == "malformed", name


@pytest.mark.parametrize("depth", [1_000, 100_000])
def test_deep_nesting(depth: int) -> None:
    for opener in (b"\x91", b"\x81\xa1k"):
        payload = opener * depth + b"\x00"
        for cls in TYPES:
            assert _outcome(cls, payload) == ("oversized" if len(payload) > codec.MAX_BYTES[cls] else "malformed")
        assert _outcome(None, payload) == "malformed"


# --------------------------------------------------------------------------- non-finite floats, every field


def _float_paths(msg: m.Msg) -> list[Path]:
    return [p for p, v in _leaves(_builtins(msg)) if isinstance(v, float)]


FLOATY = [cls for cls in TYPES if _float_paths(EXAMPLES[cls])]


def _expect_non_finite(cls: type[m.Msg], fields: dict[str, Any], path: Path, bad: float) -> None:
    payload = msgspec.msgpack.encode(_set(fields, path, bad))
    for target in (cls, None):
        kind = _outcome(target, payload)
        bounded = any(p in BOUNDED_FLOATS for p in path)
        assert kind == "non_finite" or (bounded and kind == "malformed"), (path, bad, kind)


@pytest.mark.parametrize("cls", FLOATY, ids=_ids)
def test_nan_and_inf_in_every_float_field(cls: type[m.Msg]) -> None:
    fields = _builtins(EXAMPLES[cls])
    paths = _float_paths(EXAMPLES[cls])
    assert paths
    for path in paths:
        for bad in (math.nan, math.inf, -math.inf):
            _expect_non_finite(cls, fields, path, bad)


@pytest.mark.parametrize("cls", FLOATY, ids=_ids)
@FEW
@given(data=st.data())
def test_nan_and_inf_in_generated_messages(cls: type[m.Msg], data: st.DataObject) -> None:
    msg = data.draw(valid(cls))
    paths = _float_paths(msg)
    assume(paths)
    fields = _builtins(msg)
    chosen = data.draw(st.lists(st.sampled_from(paths), min_size=1, max_size=3, unique=True))
    bad = data.draw(st.sampled_from([math.nan, math.inf, -math.inf, -math.nan]))
    for path in chosen:
        fields = _set(fields, path, bad)
    kind = _outcome(cls, msgspec.msgpack.encode(fields))
    assert kind == "non_finite" or (kind == "malformed" and any(set(p) & BOUNDED_FLOATS for p in chosen)), kind


# --------------------------------------------------------------------------- below/above the schema's bounds


def _bounded_ints(cls: type[m.Msg]) -> list[tuple[Path, msgspec.inspect.IntType]]:
    out = []
    for path, value in _leaves(_builtins(EXAMPLES[cls])):
        if isinstance(value, bool) or not isinstance(value, int):
            continue
        info = _field_info(cls, path)
        if isinstance(info, msgspec.inspect.IntType) and any(
                b is not None for b in (info.ge, info.gt, info.le, info.lt)):
            out.append((path, info))
    return out


@pytest.mark.parametrize("cls", TYPES, ids=_ids)
def test_out_of_bounds_in_every_constrained_integer(cls: type[m.Msg]) -> None:
    """Negative sizes, ids, counts, sequence numbers and stamps (and too large ids /
    pixel sizes) are malformed, wherever the field sits."""
    fields = _builtins(EXAMPLES[cls])
    cases = _bounded_ints(cls)
    assert any(p[-1] == "seq" for p, _ in cases) and any(p[-1] == "stamp_ns" for p, _ in cases)
    for path, info in cases:
        bad: list[int] = []
        if (info.ge is not None and info.ge > -(2**63)) or info.gt is not None:
            bad.append(-(2**63))
        if info.ge is not None:
            bad.append(info.ge - 1)
        if info.gt is not None:
            bad.append(info.gt)
        if info.le is not None and info.le < 2**64 - 1:
            bad.append(info.le + 1)
        if info.lt is not None:
            bad.append(info.lt)
        if (info.ge is not None and info.ge >= 0) or (info.gt is not None and info.gt >= 0):
            bad.append(-1)
        for value in (v for v in bad if -(2**63) <= v <= 2**64 - 1):  # what msgpack can carry
            payload = msgspec.msgpack.encode(_set(fields, path, value))
            assert _outcome(cls, payload) == "malformed", (path, value)
            assert _outcome(None, payload) == "malformed", (path, value)


def test_ids_and_sizes_that_must_be_non_negative_are_constrained() -> None:
    """The schema itself forbids negative robot ids, tag ids, sizes and counts."""
    constrained = {p[-1] for cls in TYPES for p, _ in _bounded_ints(cls)}
    for name in ("robot_id", "target_id", "tag_ids", "width", "height", "step", "ticks_per_rev", "dt_ns",
                 "last_seen_ns", "last_fix_ns", "origin_id", "robot_ids", "edges", "seq", "stamp_ns"):
        assert name in constrained or any(name in p for cls in TYPES for p, _ in _bounded_ints(cls)), name


# --------------------------------------------------------------------------- inconsistent contents


@FEW
@given(valid(m.CameraImage), st.integers(0, 24 * 24 + 8))
def test_image_size_must_match(img: m.CameraImage, n: int) -> None:
    assume(n != img.width * img.height)
    payload = codec.encode(msgspec.structs.replace(img, data=b"\x01" * n))
    assert _outcome(m.CameraImage, payload) == _outcome(None, payload) == "inconsistent"


COV_TYPES = [m.RelativeObservation, m.OdometryEstimate, m.Correction]


def _with_cov(cls: type[m.Msg], cov: tuple[float, ...]) -> m.Msg:
    msg = EXAMPLES[cls]
    if cls is m.GlobalMap:
        gm = typing.cast(m.GlobalMap, msg)
        return msgspec.structs.replace(gm, robots=(msgspec.structs.replace(gm.robots[0], cov=cov), *gm.robots[1:]))
    return msgspec.structs.replace(msg, cov=cov)


@pytest.mark.parametrize("cls", [*COV_TYPES, m.GlobalMap], ids=_ids)
@FEW
@given(data=st.data())
def test_covariance_must_be_symmetric_positive_semi_definite(cls: type[m.Msg], data: st.DataObject) -> None:
    good = data.draw(covariance())
    assert _outcome(cls, codec.encode(_with_cov(cls, good))) == "ok"
    a = np.array(data.draw(st.lists(st.floats(-1e3, 1e3), min_size=9, max_size=9))).reshape(3, 3)
    sym = (a + a.T) / 2
    eig = np.linalg.eigvalsh(sym)
    scale = np.abs(sym).max()
    if scale > 0 and eig.min() < -1e-6 * scale:
        assert _outcome(cls, codec.encode(_with_cov(cls, tuple(float(v) for v in sym.ravel())))) == "inconsistent"
    if scale > 0 and np.abs(a - a.T).max() > 1e-3 * scale:
        assert _outcome(cls, codec.encode(_with_cov(cls, tuple(float(v) for v in a.ravel())))) == "inconsistent"
    n = data.draw(st.integers(0, 40).filter(lambda k: k != 9))
    assert _outcome(cls, codec.encode(_with_cov(cls, (0.5,) * n))) == "inconsistent"


@pytest.mark.parametrize("cls", [*COV_TYPES, m.GlobalMap], ids=_ids)
def test_negative_variance_and_huge_covariances(cls: type[m.Msg]) -> None:
    neg = (-1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    corr = (1.0, 5.0, 0.0, 5.0, 1.0, 0.0, 0.0, 0.0, 1.0)  # |correlation| > 1
    huge = (1e308, 0.0, 0.0, 0.0, 1e308, 0.0, 0.0, 0.0, 1e308)
    tiny = (5e-324, 0.0, 0.0, 0.0, 5e-324, 0.0, 0.0, 0.0, 5e-324)
    assert _outcome(cls, codec.encode(_with_cov(cls, neg))) == "inconsistent"
    assert _outcome(cls, codec.encode(_with_cov(cls, corr))) == "inconsistent"
    assert _outcome(cls, codec.encode(_with_cov(cls, huge))) == "ok"
    assert _outcome(cls, codec.encode(_with_cov(cls, tiny))) == "ok"


POSE_TYPES = [m.CameraImage, m.GroundTruthPose, m.RelativeObservation, m.RenderPoses]


def _with_quat(msg: m.Msg, q: tuple[float, float, float, float]) -> m.Msg:
    r = msgspec.structs.replace
    qx, qy, qz, qw = q
    if isinstance(msg, m.CameraImage):
        return r(msg, mount=r(msg.mount, qx=qx, qy=qy, qz=qz, qw=qw))
    if isinstance(msg, m.RenderPoses):
        return r(msg, poses=(*msg.poses[:-1], r(msg.poses[-1], qx=qx, qy=qy, qz=qz, qw=qw)))
    return r(msg, pose=r(msg.pose, qx=qx, qy=qy, qz=qz, qw=qw))  # type: ignore[attr-defined]


@pytest.mark.parametrize("cls", POSE_TYPES, ids=_ids)
@FEW
@given(q=st.tuples(finite, finite, finite, finite), q_ok=unit_quaternion())
def test_quaternions_must_have_unit_norm(cls: type[m.Msg], q: tuple[float, ...], q_ok: tuple[float, ...]) -> None:
    assert _outcome(cls, codec.encode(_with_quat(EXAMPLES[cls], q_ok))) == "ok"  # type: ignore[arg-type]
    with np.errstate(over="ignore"):
        norm = float(np.linalg.norm(np.array(q, dtype=np.float64)))
    kind = _outcome(cls, codec.encode(_with_quat(EXAMPLES[cls], q)))  # type: ignore[arg-type]
    assert kind == ("ok" if abs(norm - 1.0) <= 1e-2 else "inconsistent"), (q, norm)


@pytest.mark.parametrize("cls", POSE_TYPES, ids=_ids)
def test_zero_quaternion_is_inconsistent(cls: type[m.Msg]) -> None:
    assert _outcome(cls, codec.encode(_with_quat(EXAMPLES[cls], (0.0, 0.0, 0.0, 0.0)))) == "inconsistent"


@FEW
@given(valid(m.RenderPoses), st.integers(0, 5))
def test_render_poses_one_pose_per_robot(req: m.RenderPoses, extra: int) -> None:
    bad = msgspec.structs.replace(req, robot_ids=(*req.robot_ids, *range(extra + 1)))
    assert _outcome(m.RenderPoses, codec.encode(bad)) == "inconsistent"
    assert _outcome(m.RenderPoses, codec.encode(req)) == "ok"


# --------------------------------------------------------------------------- oversized, checked before decoding

SMALL = [cls for cls in TYPES if codec.MAX_BYTES[cls] <= 1 << 20]


@pytest.mark.parametrize("cls", SMALL, ids=_ids)
@settings(max_examples=8, deadline=None, suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_oversized_is_rejected_before_decoding(cls: type[m.Msg], data: st.DataObject) -> None:
    """Junk just over the limit is "oversized", not "malformed": the size is checked
    before the decoder sees a byte.  A valid message padded over the limit too."""
    limit = codec.MAX_BYTES[cls]
    extra = data.draw(st.integers(1, 64))
    junk = data.draw(st.binary(min_size=64, max_size=64))
    payload = (junk * (limit // 64 + 2))[: limit + extra]
    assert _outcome(cls, payload) == "oversized"
    assert _outcome(cls, bytearray(payload)) == "oversized"
    padded = codec.encode(data.draw(valid(cls)))
    padded += b"\xc1" * (limit + extra - len(padded))
    assert _outcome(cls, padded) == "oversized"
    # decode_any: its own (largest) limit first, then the message type's limit
    assert _outcome(None, padded) == "malformed"  # trailing junk, within the union limit
    valid_but_big = _big_valid(cls, limit + extra)
    if valid_but_big is not None:
        assert len(valid_but_big) > limit
        assert _outcome(cls, valid_but_big) == "oversized"
        assert _outcome(None, valid_but_big) == "oversized"


def _big_valid(cls: type[m.Msg], size: int) -> bytes | None:
    """A well-formed ``cls`` payload of at least ``size`` bytes, if the type has a
    variable-length string/bytes/tuple field to grow."""
    fields = _builtins(EXAMPLES[cls])
    info = msgspec.inspect.type_info(cls)
    assert isinstance(info, msgspec.inspect.StructType)
    for f in info.fields:
        if isinstance(f.type, msgspec.inspect.StrType):
            fields[f.name] = "x" * size
            return msgspec.msgpack.encode(fields)
        if isinstance(f.type, msgspec.inspect.DictType):
            fields[f.name] = {f"k{i}": i for i in range(size // 8 + 1)}
            return msgspec.msgpack.encode(fields)
    return None


@pytest.mark.parametrize("cls", [c for c in TYPES if c not in SMALL], ids=_ids)
def test_oversized_large_types(cls: type[m.Msg]) -> None:
    limit = codec.MAX_BYTES[cls]
    assert _outcome(cls, b"\xc1" * (limit + 1)) == "oversized"
    assert _outcome(cls, memoryview(b"\x00" * (limit + 1))) == "oversized"


def test_decode_any_rejects_beyond_the_largest_limit() -> None:
    biggest = max(codec.MAX_BYTES.values())
    assert _outcome(None, b"\xc1" * (biggest + 1)) == "oversized"


# --------------------------------------------------------------------------- the counter never lets anything through


@SOME
@given(st.lists(st.binary(max_size=64) | st.sampled_from([codec.encode(EXAMPLES[c]) for c in TYPES]), max_size=8))
def test_reject_counter_decoded_counts_every_bad_payload(payloads: list[bytes]) -> None:
    for cls in (m.Tick, m.RelativeObservation, m.CameraImage):
        rc = streams.RejectCounter()
        items = [Received(f"k/{i}", p) for i, p in enumerate(payloads)]
        good = [(it.key, msg) for it, msg in rc.decoded(items, cls)]
        assert all(type(msg) is cls for _, msg in good)
        assert len(good) + rc.total() == len(payloads)
        assert set(rc.counts) <= KINDS
