"""MCAP plumbing shared by ``tagswarm record`` and ``tagswarm replay`` (pure: no Zenoh).

Layout of a tagswarm recording:

- one *raw* channel per Zenoh key, topic = the key itself (``tagswarm/<run>/robot/1/encoders``),
  message encoding ``msgpack``: every payload exactly as it came off the wire, so a replay is
  byte-exact.  Which type a key carries comes from :mod:`tagswarm.protocol.wire` (every key of
  a run, ``world/command`` and ``server/relocalisation`` included); the channel's schema
  (encoding ``jsonschema``, name ``tagswarm.EncoderTicks``...) is that type's JSON Schema in
  its msgpack form (:mod:`tagswarm.wireschema`: ``bytes`` are msgpack bin, not base64), and
  the channel metadata says ``zenoh_key``, ``tagswarm_type``, ``zenoh_encoding``
  (``application/msgpack;EncoderTicks``), ``qos``, ``sender`` and ``readers``.  Files written
  before held msgspec's JSON-form schemas and fewer metadata entries: replay reads only the
  raw payloads and never needs either.
- Foxglove channels (protobuf, well-known ``foxglove.*`` schemas) for viewing, topics starting
  with ``/`` (see :mod:`tagswarm.recording.foxglove_views`).
- log time = the message's simulation time ``stamp_ns``; publish time = the recorder's wall
  clock at reception (ns since the Unix epoch).
- a ``tagswarm`` metadata record (run, key expression, options, the resolved scenario as JSON
  when known) and, at the end, ``tagswarm.stats`` (counts, rejects, drops).
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from functools import cache, lru_cache
from pathlib import Path
from typing import Any, Final

from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, ChunkIndex, DataEnd, Footer, Message, Metadata, Schema, Statistics
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from tagswarm import wireschema
from tagswarm.protocol import messages as m
from tagswarm.protocol import wire
from tagswarm.protocol.errors import UsageError
from tagswarm.protocol.keys import ROOT, KeyNameError, Keys

RAW_ENCODING: Final = "msgpack"
SCHEMA_ENCODING: Final = "jsonschema"
SCHEMA_DIALECT: Final = "https://json-schema.org/draft/2020-12/schema"
META_RUN: Final = "tagswarm"
META_STATS: Final = "tagswarm.stats"
COMPRESSION: Final = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}

_WORLD: Final = Keys("RUN")
#: What the world process (and its render workers) publishes: the sensor streams a replay
#: feeds to fresh agents and a fresh server (tick, world status, images, encoders, truth).
#: Acks, render requests, world commands and every agent or server output are not in it.
_WORLD_STREAMS: Final = frozenset(
    spec for spec in wire.KEYS
    if spec.pattern(_WORLD) in {_WORLD.tick(), _WORLD.world_status(), _WORLD.images(), _WORLD.encoders(),
                                _WORLD.truth()})


@lru_cache(maxsize=8192)  # a run has a few keys per robot, looked up for every message
def spec_of(key: str) -> wire.KeySpec | None:
    """The :class:`~tagswarm.protocol.wire.KeySpec` (message type, QoS, sender, readers) of
    a concrete tagswarm key of any run, or None for a foreign or unknown key."""
    run = run_of(key)
    if run is None:
        return None
    try:
        keys = Keys(run)
    except KeyNameError:
        return None
    return wire.spec_for_key(keys, key)


def message_type_for_key(key: str) -> type[m.Msg] | None:
    """The tagswarm message type a key carries (from :mod:`tagswarm.protocol.wire`), or None."""
    spec = spec_of(key)
    return None if spec is None else spec.message


def is_world_stream(key: str) -> bool:
    """True for the world's sensor streams: tick, world status, images, encoders, truth."""
    return spec_of(key) in _WORLD_STREAMS


def is_command(key: str) -> bool:
    """True for an agent's wheel command key (``.../robot/<id>/cmd``): what drove the recorded wheels."""
    spec = spec_of(key)
    return spec is not None and spec.message is m.WheelCommand and spec.sender.startswith("agent")


def recorded_command_key(key: str) -> str:
    """The replay's key for a recorded wheel command ``key`` (same run): ``.../robot/<id>/recorded_cmd``."""
    run, rid = run_of(key), robot_id_of(key)
    if run is None or rid is None or not is_command(key):
        raise ValueError(f"{key!r} is not a wheel command key")
    return Keys(run).recorded_cmd(rid)


def robot_id_of(key: str) -> int | None:
    """The robot id of a tagswarm key under ``.../robot/<id>/...`` of its own run, else None."""
    run = run_of(key)
    return None if run is None else Keys(run).robot_id_of(key)


def is_ack(key: str) -> bool:
    """True for a lockstep acknowledgement key (``.../world/ack/<role>/<id>``)."""
    return message_type_for_key(key) is m.TickAck


def is_tick(key: str) -> bool:
    return message_type_for_key(key) is m.Tick


def run_of(key: str) -> str | None:
    """The run id chunk of a tagswarm key, or None for a foreign key."""
    parts = key.split("/")
    return parts[1] if len(parts) >= 3 and parts[0] == ROOT else None


def remap_run(key: str, run: str) -> str:
    """``key`` moved to run ``run`` (foreign keys are returned unchanged)."""
    parts = key.split("/")
    if len(parts) < 3 or parts[0] != ROOT:
        return key
    return "/".join([ROOT, run, *parts[2:]])


def keyexpr_matches(pattern: str, key: str) -> bool:
    """Whether the concrete ``key`` matches the Zenoh key expression ``pattern``
    (``*`` = one chunk, ``**`` = any number of chunks, ``$*`` inside a chunk = any text)."""

    def chunk_ok(p: str, k: str) -> bool:
        if p == "*":
            return True
        if "$*" not in p:
            return p == k
        pieces = p.split("$*")
        if not (k.startswith(pieces[0]) and k.endswith(pieces[-1])) or len(k) < len(pieces[0]) + len(pieces[-1]):
            return False
        pos = len(pieces[0])
        for piece in pieces[1:-1]:
            found = k.find(piece, pos, len(k) - len(pieces[-1]))
            if found < 0:
                return False
            pos = found + len(piece)
        return True

    pat, ks = pattern.split("/"), key.split("/")

    def match(i: int, j: int) -> bool:
        if i == len(pat):
            return j == len(ks)
        if pat[i] == "**":
            return any(match(i + 1, jj) for jj in range(j, len(ks) + 1))
        return j < len(ks) and chunk_ok(pat[i], ks[j]) and match(i + 1, j + 1)

    return match(0, 0)


@cache
def _wire_defs() -> dict[str, Any]:
    return dict(wireschema.schema_dict()["$defs"])


def _refs(node: Any) -> Iterator[str]:
    if isinstance(node, dict):
        ref = node.get("$ref")
        if isinstance(ref, str) and ref.startswith("#/$defs/"):
            yield ref.removeprefix("#/$defs/")
        for v in node.values():
            yield from _refs(v)
    elif isinstance(node, list):
        for v in node:
            yield from _refs(v)


@cache
def json_schema(cls: type[m.Msg]) -> bytes:
    """The JSON Schema (draft 2020-12) of one message type in its msgpack form, the one
    ``docs/messages.schema.json`` holds (:mod:`tagswarm.wireschema`): a map with string
    keys, ``bytes`` fields as msgpack bin (``"format": "binary"``, not base64 strings),
    self-contained (only the definitions it needs).  Recordings made before this wrote
    msgspec's JSON form (base64 strings); readers never need the schema to replay."""
    defs = _wire_defs()
    needed, todo = set(), [cls.__name__]
    while todo:
        name = todo.pop()
        if name not in needed:
            needed.add(name)
            todo.extend(_refs(defs[name]))
    schema = {
        "$schema": SCHEMA_DIALECT,
        "title": f"tagswarm.{cls.__name__} (msgpack form)",
        "$ref": f"#/$defs/{cls.__name__}",
        "$defs": {name: defs[name] for name in sorted(needed)},
        "x-zenoh-encoding": wire.encoding_of(cls),
    }
    return json.dumps(schema, sort_keys=True).encode()


def channel_metadata(key: str) -> dict[str, str]:
    """The metadata of the raw channel of ``key``: its Zenoh key, message type, Zenoh
    encoding, QoS, sender and readers (from :mod:`tagswarm.protocol.wire`; empty strings
    for a key the wire does not know)."""
    spec = spec_of(key)
    cls = None if spec is None else spec.message
    return {"zenoh_key": key, "tagswarm_type": "" if cls is None else cls.__name__,
            "zenoh_encoding": "" if cls is None else wire.encoding_of(cls),
            "qos": "" if spec is None else spec.qos, "sender": "" if spec is None else spec.sender,
            "readers": "" if spec is None else spec.receivers}


# --------------------------------------------------------------------------- writing


class McapSink:
    """A thin owner of one MCAP :class:`~mcap.writer.Writer`: schemas and channels are
    registered on first use, raw tagswarm channels and Foxglove (protobuf) channels alike."""

    def __init__(self, path: Path, *, compression: str = "zstd", chunk_size: int = 4 * 1024 * 1024) -> None:
        self.path = path
        self._file = open(path, "wb")
        # data CRCs let `verify` (and `mcap doctor`) prove the file intact end to end
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=COMPRESSION[compression],
                              enable_data_crcs=True)
        self._writer.start(profile="", library="tagswarm record (mcap-python)")
        self._schemas: dict[tuple[str, str], int] = {}
        self._channels: dict[str, int] = {}
        self.messages = 0
        self.bytes = 0
        self._closed = False

    def _schema(self, name: str, encoding: str, data: bytes) -> int:
        sid = self._schemas.get((name, encoding))
        if sid is None:
            sid = self._schemas[(name, encoding)] = self._writer.register_schema(name, encoding, data)
        return sid

    def raw_channel(self, key: str) -> int:
        """The channel of Zenoh key ``key`` (msgpack payloads, the msgpack-form JSON schema of its type)."""
        cid = self._channels.get(key)
        if cid is None:
            cls = message_type_for_key(key)
            sid = 0 if cls is None else self._schema(f"tagswarm.{cls.__name__}", SCHEMA_ENCODING, json_schema(cls))
            meta = channel_metadata(key)
            cid = self._channels[key] = self._writer.register_channel(key, RAW_ENCODING, sid, meta)
        return cid

    def foxglove_channel(self, topic: str, schema: Any) -> int:
        """The channel of a Foxglove topic; ``schema`` is a ``foxglove.Schema`` (protobuf)."""
        cid = self._channels.get(topic)
        if cid is None:
            sid = self._schema(schema.name, schema.encoding, schema.data)
            cid = self._channels[topic] = self._writer.register_channel(topic, "protobuf", sid)
        return cid

    def write(self, channel: int, data: bytes, *, log_time_ns: int, publish_time_ns: int, sequence: int = 0) -> None:
        self._writer.add_message(channel, log_time_ns, data, publish_time_ns, sequence & 0xFFFFFFFF)
        self.messages += 1
        self.bytes += len(data)

    def metadata(self, name: str, data: dict[str, str]) -> None:
        self._writer.add_metadata(name, data)

    def close(self) -> None:
        """Write the summary (statistics, indexes) and close the file; idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            self._writer.finish()
        finally:
            self._file.close()


# --------------------------------------------------------------------------- reading


class RecordingError(UsageError):
    """A file that is not a readable, complete MCAP recording."""


@dataclass(frozen=True)
class RawMessage:
    """One raw tagswarm payload of a recording."""

    key: str
    log_time_ns: int
    data: bytes


def read_metadata(path: Path) -> dict[str, dict[str, str]]:
    """Every metadata record of the file by name (later records of one name win)."""
    try:
        with open(path, "rb") as f:
            return {md.name: dict(md.metadata) for md in make_reader(f).iter_metadata()}
    except (McapError, OSError, ValueError, EOFError) as exc:
        raise RecordingError(f"{path}: not a readable MCAP file ({type(exc).__name__}: {exc})") from None


def raw_topics(path: Path) -> list[str]:
    """Topics of the raw tagswarm channels (message encoding ``msgpack``) in the summary."""
    try:
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
    except (McapError, OSError, ValueError, EOFError) as exc:
        raise RecordingError(f"{path}: not a readable MCAP file ({type(exc).__name__}: {exc})") from None
    if summary is None:
        raise RecordingError(f"{path}: no summary section (was the recording closed properly?)")
    return sorted({c.topic for c in summary.channels.values() if c.message_encoding == RAW_ENCODING})


def iter_raw(path: Path, accept: Callable[[str], bool], *, end_ns: int | None = None) -> Iterator[RawMessage]:
    """Raw payloads of the accepted topics in log-time order.  Among messages of one log
    time, ticks come last: a Tick promises that every sensor message of its step was
    published before it, whatever order the recorder happened to receive them in."""
    topics = [t for t in raw_topics(path) if accept(t)]
    if not topics:
        return
    group: list[RawMessage] = []
    try:
        with open(path, "rb") as f:
            for _schema, channel, msg in make_reader(f).iter_messages(topics=topics, log_time_order=True,
                                                                     ending_at=end_ns):
                if group and msg.log_time != group[0].log_time_ns:
                    yield from _ticks_last(group)
                    group = []
                group.append(RawMessage(channel.topic, msg.log_time, msg.data))
    except (McapError, OSError, ValueError, EOFError) as exc:
        raise RecordingError(f"{path}: cannot read messages ({type(exc).__name__}: {exc})") from None
    yield from _ticks_last(group)


def _ticks_last(group: list[RawMessage]) -> Iterable[RawMessage]:
    return [r for r in group if not is_tick(r.key)] + [r for r in group if is_tick(r.key)]


@dataclass
class Verified:
    """What :func:`verify` found in a valid file."""

    messages: int = 0
    counts: Counter[str] = field(default_factory=Counter)  # per topic
    schemas: dict[str, str] = field(default_factory=dict)  # topic -> schema name
    encodings: dict[str, str] = field(default_factory=dict)  # topic -> message encoding
    chunks: int = 0
    start_ns: int = 0
    end_ns: int = 0
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)


def verify(path: Path) -> Verified:
    """Check a recording with the mcap library's own readers: read every record
    sequentially with CRC validation (chunk and data-section CRCs), check that every
    message's channel and schema are defined, that a Statistics record, chunk indexes and
    the footer are present and that the statistics agree with what was read.  Raises
    :class:`RecordingError` naming the first problem."""
    out = Verified()
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    stats: Statistics | None = None
    chunk_indexes = 0
    footer = data_end = False
    per_channel: Counter[int] = Counter()
    first = last = None
    try:
        for rec in StreamReader(str(path), validate_crcs=True).records:
            if isinstance(rec, Schema):
                schemas[rec.id] = rec
            elif isinstance(rec, Channel):
                if rec.schema_id and rec.schema_id not in schemas:
                    raise RecordingError(f"channel {rec.topic!r} names unknown schema {rec.schema_id}")
                channels[rec.id] = rec
            elif isinstance(rec, Message):
                if rec.channel_id not in channels:
                    raise RecordingError(f"message on undefined channel {rec.channel_id}")
                per_channel[rec.channel_id] += 1
                first = rec.log_time if first is None else min(first, rec.log_time)
                last = rec.log_time if last is None else max(last, rec.log_time)
            elif isinstance(rec, Chunk):  # pragma: no cover - StreamReader unpacks chunks
                out.chunks += 1
            elif isinstance(rec, ChunkIndex):
                chunk_indexes += 1
            elif isinstance(rec, Statistics):
                stats = rec
            elif isinstance(rec, Metadata):
                out.metadata[rec.name] = dict(rec.metadata)
            elif isinstance(rec, DataEnd):
                data_end = True
            elif isinstance(rec, Footer):
                footer = True
    except RecordingError:
        raise
    except (McapError, OSError, ValueError, EOFError) as exc:
        raise RecordingError(f"{path}: {type(exc).__name__}: {exc}") from None
    if not (data_end and footer):
        raise RecordingError(f"{path}: truncated (no data end / footer record)")
    if stats is None:
        raise RecordingError(f"{path}: no Statistics record in the summary")
    total = sum(per_channel.values())
    if stats.message_count != total or dict(stats.channel_message_counts) != {k: v for k, v in per_channel.items()
                                                                                if v}:
        raise RecordingError(f"{path}: statistics say {stats.message_count} messages "
                             f"({dict(stats.channel_message_counts)}), the file holds {total} ({dict(per_channel)})")
    if total and (stats.message_start_time != first or stats.message_end_time != last):
        raise RecordingError(f"{path}: statistics time range disagrees with the messages")
    if stats.chunk_count and chunk_indexes != stats.chunk_count:
        raise RecordingError(f"{path}: {stats.chunk_count} chunks but {chunk_indexes} chunk indexes")
    out.chunks = stats.chunk_count
    out.messages = total
    out.start_ns, out.end_ns = first or 0, last or 0
    for cid, ch in channels.items():
        out.counts[ch.topic] += per_channel[cid]
        out.encodings[ch.topic] = ch.message_encoding
        out.schemas[ch.topic] = schemas[ch.schema_id].name if ch.schema_id else ""
    return out
