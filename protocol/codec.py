"""msgpack codec for the wire messages, with the checks every receiver needs.

One encoder and one decoder per message type are built once at import.  Decoding
never raises anything but :class:`DecodeError`, whose ``kind`` says why the
payload was rejected: ``oversized`` (checked before decoding), ``malformed`` (not
msgpack, wrong type, out-of-range field), ``non_finite`` (NaN/inf anywhere) or
``inconsistent`` (fields that contradict each other, e.g. image size).
Receivers count rejects with :class:`RejectCounter`.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Iterable, Iterator
from typing import Any, Final, TypeVar

import msgspec

from protocol import messages as m

T = TypeVar("T", bound=m.Msg)

_KB: Final = 1024
#: Largest accepted payload per message type, checked before decoding.
MAX_BYTES: Final[dict[type[m.Msg], int]] = {
    m.Tick: 64 * _KB,
    m.TickAck: 4 * _KB,
    m.CameraImage: 8192 * 8192 + 64 * _KB,
    m.EncoderTicks: 4 * _KB,
    m.WheelCommand: 4 * _KB,
    m.GroundTruthPose: 4 * _KB,
    m.RelativeObservation: 16 * _KB,
    m.OdometryEstimate: 4 * _KB,
    m.Correction: 4 * _KB,
    m.GlobalMap: 4 * _KB * _KB,
    m.AgentStatus: 64 * _KB,
    m.RenderPoses: 1 * _KB * _KB,
    m.Goal: 4 * _KB,
}

_ENCODER: Final = msgspec.msgpack.Encoder()
_DECODERS: Final[dict[type[Any], msgspec.msgpack.Decoder[Any]]] = {
    cls: msgspec.msgpack.Decoder(cls) for cls in MAX_BYTES
}
_ANY_DECODER: Final = msgspec.msgpack.Decoder(m.AnyMessage)  # type: ignore[arg-type]

log = logging.getLogger(__name__)


class DecodeError(Exception):
    """A payload was rejected; ``kind`` is one of the reject kinds above."""

    def __init__(self, kind: str, detail: str) -> None:
        super().__init__(f"{kind}: {detail}")
        self.kind = kind
        self.detail = detail


def encode(msg: m.Msg) -> bytes:
    """Serialise a message to msgpack bytes."""
    return _ENCODER.encode(msg)


def _all_finite(value: Any) -> bool:
    if isinstance(value, float):
        return math.isfinite(value)
    if isinstance(value, msgspec.Struct):
        return all(_all_finite(getattr(value, f)) for f in value.__struct_fields__)
    if isinstance(value, (tuple, list)):
        return all(_all_finite(v) for v in value)
    return True


def _check(msg: m.Msg) -> None:
    if not _all_finite(msg):
        raise DecodeError("non_finite", f"{type(msg).__name__} has NaN or inf")
    if isinstance(msg, m.CameraImage) and len(msg.data) != msg.width * msg.height:
        raise DecodeError(
            "inconsistent",
            f"image {msg.width}x{msg.height} carries {len(msg.data)} bytes",
        )
    covs = [e.cov for e in msg.robots] if isinstance(msg, m.GlobalMap) else [getattr(msg, "cov", None)]
    for cov in covs:
        if cov is not None and len(cov) != 9:
            raise DecodeError("inconsistent", f"covariance has {len(cov)} entries, expected 9")


def decode(cls: type[T], payload: bytes | bytearray | memoryview) -> T:
    """Decode ``payload`` as ``cls`` or raise :class:`DecodeError`."""
    limit = MAX_BYTES[cls]
    if len(payload) > limit:
        raise DecodeError("oversized", f"{cls.__name__} payload of {len(payload)} B > {limit} B")
    try:
        msg: T = _DECODERS[cls].decode(payload)
    except (msgspec.DecodeError, msgspec.ValidationError) as exc:
        raise DecodeError("malformed", f"{cls.__name__}: {exc}") from None
    except Exception as exc:
        raise DecodeError("malformed", f"{cls.__name__}: {type(exc).__name__}: {exc}") from None
    _check(msg)
    return msg


def decode_any(payload: bytes | bytearray | memoryview) -> m.AnyMessage:
    """Decode a payload of unknown type (recordings, journals, spy)."""
    if len(payload) > max(MAX_BYTES.values()):
        raise DecodeError("oversized", f"payload of {len(payload)} B")
    try:
        msg: m.AnyMessage = _ANY_DECODER.decode(payload)
    except (msgspec.DecodeError, msgspec.ValidationError) as exc:
        raise DecodeError("malformed", str(exc)) from None
    except Exception as exc:
        raise DecodeError("malformed", f"{type(exc).__name__}: {exc}") from None
    _check(msg)
    return msg


class RejectCounter:
    """Counts rejected payloads per kind and logs the first of each kind once."""

    def __init__(self, logger: logging.Logger | None = None) -> None:
        self.counts: Counter[str] = Counter()
        self._log = logger or log

    def reject(self, kind: str, detail: str) -> None:
        """Record one rejected payload."""
        if self.counts[kind] == 0:
            self._log.warning("dropping bad payload (%s): %s; further ones are only counted", kind, detail)
        self.counts[kind] += 1

    def decoded(self, items: Iterable[Any], cls: type[T]) -> Iterator[tuple[Any, T]]:
        """Decode inbox items (``.key``, ``.value``) as ``cls``, yielding (item, message)
        and counting every payload that fails (the loop body never sees it)."""
        for item in items:
            try:
                yield item, decode(cls, item.value)
            except DecodeError as exc:
                self.reject(exc.kind, f"{item.key}: {exc.detail}")

    def total(self) -> int:
        """All rejects so far."""
        return sum(self.counts.values())

    def as_counters(self, prefix: str = "rejected_") -> dict[str, int]:
        """Counters for an :class:`~protocol.messages.AgentStatus`."""
        return {prefix + k: v for k, v in sorted(self.counts.items())}


class Sequencer:
    """Per-key sequence numbers of one publisher (receivers can count gaps)."""

    def __init__(self) -> None:
        self._seq: Counter[str] = Counter()

    def next(self, key: str) -> int:
        """The number for the next message on ``key``."""
        seq = self._seq[key]
        self._seq[key] += 1
        return seq

    def peek(self, key: str) -> int:
        """The number the next message on ``key`` will get, without taking it."""
        return self._seq[key]
