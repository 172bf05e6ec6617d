"""The wire contract as data, for any Zenoh client: which message type each key carries,
with what quality of service, who sends it and who reads it, and the Zenoh encoding
string every publication sets (pure: no Zenoh import; :mod:`tagswarm.protocol.bus`
applies it, :mod:`tagswarm.docs` turns it into ``docs/protocol.md``).

Encoding: ``application/msgpack;<MessageType>`` (``application/msgpack;EncoderTicks``):
the payload is one msgpack map, the tagswarm message named after the ``;``.  The bus
finds the type from the payload itself (:func:`message_type_of`: the ``type`` entry
that msgspec writes first in every message), so raw republished bytes (a replay) carry
the right encoding too; a payload that is not a tagswarm message goes out as plain
``zenoh/bytes``.  Receivers may check the encoding against the decoded type, but must
not reject a payload for a missing encoding (older recordings and senders set none).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Final, Literal

from tagswarm.protocol import messages as m
from tagswarm.protocol.keys import Keys

MEDIA_TYPE: Final = "application/msgpack"

#: Every wire message type, in documentation order.
MESSAGE_TYPES: Final[tuple[type[m.Msg], ...]] = (
    m.Tick, m.TickAck, m.RenderPoses, m.WorldCommand, m.CameraImage, m.EncoderTicks, m.WheelCommand,
    m.GroundTruthPose, m.RelativeObservation, m.OdometryEstimate, m.Correction, m.Goal, m.AgentStatus,
    m.GlobalMap, m.Relocalisation, m.ClaimReply,
)
_BY_NAME: Final = {cls.__name__: cls for cls in MESSAGE_TYPES}
_BY_TAG: Final[dict[bytes, type[m.Msg]]] = {str(cls.__struct_config__.tag).encode(): cls for cls in MESSAGE_TYPES}
_TYPE_KEY: Final = b"\xa4type"  # msgpack fixstr "type": the tag field, always the first map entry


def encoding_of(cls: type[m.Msg]) -> str:
    """The Zenoh encoding string of message type ``cls``: ``application/msgpack;<name>``."""
    return f"{MEDIA_TYPE};{cls.__name__}"


def type_of_encoding(encoding: str) -> type[m.Msg] | None:
    """The message type an encoding string names, or None (not ours, or no schema)."""
    media, _, name = encoding.partition(";")
    return _BY_NAME.get(name) if media == MEDIA_TYPE else None


def message_head(payload: bytes) -> tuple[type[m.Msg], int] | None:
    """The message type of a msgpack payload and the length of its head (map header,
    ``type`` key and tag string), read without decoding the rest; None if the payload
    does not start like a tagswarm message.  Every payload of one type starts with the
    same head (msgspec writes every field, the tag first), so a publisher compares heads."""
    if not payload:
        return None
    b0 = payload[0]
    if 0x80 <= b0 <= 0x8F:  # fixmap
        i = 1
    elif b0 == 0xDE:  # map 16
        i = 3
    elif b0 == 0xDF:  # map 32
        i = 5
    else:
        return None
    if payload[i : i + 5] != _TYPE_KEY or len(payload) <= i + 5:
        return None
    s0 = payload[i + 5]
    if 0xA0 <= s0 <= 0xBF:  # fixstr
        start, n = i + 6, s0 & 0x1F
    elif s0 == 0xD9 and len(payload) > i + 6:  # str 8
        start, n = i + 7, payload[i + 6]
    else:
        return None
    cls = _BY_TAG.get(bytes(payload[start : start + n]))
    return None if cls is None else (cls, start + n)


def message_type_of(payload: bytes) -> type[m.Msg] | None:
    """The message type a payload claims in its ``type`` entry, or None (see :func:`message_head`)."""
    head = message_head(payload)
    return None if head is None else head[0]


Qos = Literal["block", "drop_realtime", "none"]


@dataclass(frozen=True)
class KeySpec:
    """One key of the wire: ``pattern(keys)`` is its key expression with ``*`` for each
    variable chunk, named in order by ``placeholders``; ``qos``: ``block`` (BLOCK
    congestion control, express), ``drop_realtime`` (DROP, not express, in realtime runs;
    BLOCK in lockstep runs, where nothing may be lost), ``none`` (liveliness tokens)."""

    pattern: Callable[[Keys], str]
    placeholders: tuple[str, ...]
    message: type[m.Msg] | None
    qos: Qos
    sender: str
    receivers: str
    note: str = ""

    def display(self) -> str:
        """The key with ``<run>`` and named placeholders, e.g. ``tagswarm/<run>/robot/<id>/cmd``."""
        parts = self.pattern(Keys("RUN")).split("/")
        parts[1] = "<run>"
        names = iter(self.placeholders)
        return "/".join(next(names) if p == "*" else p for p in parts)


def _last_wild(key: str) -> str:
    return key.rsplit("/", 1)[0] + "/*"


KEYS: Final[tuple[KeySpec, ...]] = (
    KeySpec(lambda k: k.tick(), (), m.Tick, "block", "world", "agents, server, render workers, tools",
            "closes a simulation step: sent after every sensor message of that step"),
    KeySpec(lambda k: k.acks(), ("<role>", "<id>"), m.TickAck, "block", "lockstep participants",
            "world, server (agents' acks)", "lockstep only: the participant finished a step"),
    KeySpec(lambda k: _last_wild(k.render(0)), ("<worker>",), m.RenderPoses, "block", "world",
            "render worker <worker>", "only with render.workers > 0"),
    KeySpec(lambda k: k.world_status(), (), m.AgentStatus, "block", "world", "tools", "about once a second"),
    KeySpec(lambda k: k.world_command(), (), m.WorldCommand, "block", "operator (tagswarm kidnap)", "world"),
    KeySpec(lambda k: k.world_applied(), (), m.WorldCommand, "block", "world", "tools",
            "each teleport or push the world applied (a command or a scenario event), stamped with its step; "
            "refused ones never appear"),
    KeySpec(lambda k: k.images(), ("<id>", "<name>"), m.CameraImage, "drop_realtime", "world or render worker",
            "agent <id>, tools", "one key per camera of the robot"),
    KeySpec(lambda k: k.encoders(), ("<id>",), m.EncoderTicks, "block", "world", "agent <id>"),
    KeySpec(lambda k: k.cmd(), ("<id>",), m.WheelCommand, "block", "agent <id>", "world"),
    KeySpec(lambda k: k.recorded_cmd(), ("<id>",), m.WheelCommand, "block", "replay (tagswarm replay, up --replay)",
            "agent <id>", "a recording's cmd messages: what drove the wheels, for the agent's slip check"),
    KeySpec(lambda k: k.truth(), ("<id>",), m.GroundTruthPose, "block", "world", "tools",
            "evaluation only: agents and server never read it"),
    KeySpec(lambda k: k.observation(), ("<id>",), m.RelativeObservation, "block", "agent <id> (the observer)",
            "server"),
    KeySpec(lambda k: k.odometry(), ("<id>",), m.OdometryEstimate, "block", "agent <id>", "server"),
    KeySpec(lambda k: k.correction(), ("<id>",), m.Correction, "block", "server", "agent <id>"),
    KeySpec(lambda k: k.goal(), ("<id>",), m.Goal, "block", "operator (tagswarm goto)", "agent <id>"),
    KeySpec(lambda k: k.robot_status(), ("<id>",), m.AgentStatus, "block", "agent <id>", "tools"),
    KeySpec(lambda k: k.map(), (), m.GlobalMap, "block", "server", "agents, tools",
            "also a queryable: a Zenoh get on it answers the current map"),
    KeySpec(lambda k: k.server_status(), (), m.AgentStatus, "block", "server", "tools"),
    KeySpec(lambda k: k.relocalisation(), (), m.Relocalisation, "block", "server", "tools",
            "one per re-localisation event"),
    KeySpec(lambda k: k.claim(), (), m.ClaimReply, "block", "claim authority (tagswarm record-run)",
            "agent containers (tagswarm claim)", "compose only: a query; the reply carries a robot id and its login"),
    KeySpec(lambda k: k.alive_all().removesuffix("/**") + "/*/*", ("<role>", "<id>"), None, "none",
            "every process", "every process", "Zenoh liveliness tokens, no payload"),
)


def spec_for_key(keys: Keys, key: str) -> KeySpec | None:
    """The :class:`KeySpec` a concrete key of run ``keys.run`` falls under, or None."""
    parts = key.split("/")
    for spec in KEYS:
        pat = spec.pattern(keys).split("/")
        if len(pat) == len(parts) and all(p in ("*", q) for p, q in zip(pat, parts, strict=True)):
            return spec
    return None
