"""msgpack codec for the wire messages, with the checks every receiver needs.

One encoder and one decoder per message type are built once at import.  Decoding
never raises anything but :class:`DecodeError`, whose ``kind`` says why the
payload was rejected: ``oversized`` (checked before decoding), ``malformed`` (not
msgpack, wrong type, out-of-range field), ``non_finite`` (NaN/inf anywhere) or
``inconsistent`` (fields that contradict each other: image size, covariance
not a symmetric positive semi-definite 3x3 matrix, quaternion not of unit norm,
render poses not one per robot id).  Receivers count rejects with
:class:`tagswarm.runtime.streams.RejectCounter`; the nodes add their own kinds
for messages that decode but must not be used (``spoofed``: robot id or
participant not matching its key; ``foreign_run``: a tick of another world
instance while the followed one is alive; ``unknown_robot`` /
``unknown_participant``: not in the roster; ``inconsistent``: contradicts the
receiver's state, e.g. an ack of a step not sent yet).
"""

from __future__ import annotations

import math
from typing import Any, Final, TypeVar

import msgspec
import numpy as np

from tagswarm.protocol import messages as m
from tagswarm.protocol.errors import TagswarmError

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
    m.WorldCommand: 4 * _KB,
    m.Relocalisation: 16 * _KB,
    m.ClaimReply: 2 * _KB,
}

_ENCODER: Final = msgspec.msgpack.Encoder()
_DECODERS: Final[dict[type[Any], msgspec.msgpack.Decoder[Any]]] = {
    cls: msgspec.msgpack.Decoder(cls) for cls in MAX_BYTES
}
_ANY_DECODER: Final = msgspec.msgpack.Decoder(m.AnyMessage)  # type: ignore[arg-type]
_MAX_ANY: Final = max(MAX_BYTES.values())


class DecodeError(TagswarmError):
    """A payload was rejected; ``kind`` is one of the reject kinds above."""

    def __init__(self, kind: str, detail: str) -> None:
        super().__init__(f"{kind}: {detail}")
        self.kind = kind
        self.detail = detail


def encode(msg: m.Msg) -> bytes:
    """Serialise a message to msgpack bytes."""
    return _ENCODER.encode(msg)


#: Kinds :func:`decode` and :func:`decode_any` raise.
DECODE_KINDS: Final = frozenset({"oversized", "malformed", "non_finite", "inconsistent"})
_QUAT_NORM_TOL: Final = 1e-2  # senders normalise; this only catches degenerate (e.g. all-zero) rotations
_COV_SYM_RTOL: Final = 1e-6  # GTSAM marginals and J P J^T products are symmetric to ~1e-15 relative
_COV_PSD_RTOL: Final = 1e-9


_isfinite = math.isfinite
_PLAIN: Final = (int, str, bool, bytes, type(None))


def _all_finite(value: Any) -> bool:
    # every decoded message passes through here: floats inline and tuples of numbers in one C loop
    # (the generic recursion cost more than the decode itself)
    t = type(value)
    if t is float:
        return _isfinite(value)
    if isinstance(value, msgspec.Struct):
        for f in value.__struct_fields__:
            v = getattr(value, f)
            tv = type(v)
            if tv is float:
                if not _isfinite(v):
                    return False
            elif tv not in _PLAIN and not _all_finite(v):
                return False
        return True
    if t is tuple or t is list:
        try:
            return all(map(_isfinite, value))
        except TypeError:  # not all numbers (structs, strings): one by one
            return all(_all_finite(v) for v in value)
    return True


def _clearly_positive_definite(a: tuple[float, ...]) -> bool:
    """Whether the symmetric 3x3 ``a`` (row-major, entries in [-1, 1]) is positive definite by
    a wide margin (Sylvester: every leading minor above 1e-12, 10^4 times the rounding of these products), checked in
    plain floats: the common case, accepted without an eigen decomposition."""
    a00, a01, a02, _, a11, a12, _, _, a22 = a
    m2 = a00 * a11 - a01 * a01
    det = a00 * (a11 * a22 - a12 * a12) - a01 * (a01 * a22 - a12 * a02) + a02 * (a01 * a12 - a11 * a02)
    return a00 > 1e-12 and m2 > 1e-12 and det > 1e-12


def _cov_problem(cov: tuple[float, ...]) -> str | None:
    """Why ``cov`` (row-major 3x3, finite) cannot be a covariance, or None."""
    if len(cov) != 9:
        return f"covariance has {len(cov)} entries, expected 9"
    scale = max(map(abs, cov))
    if scale == 0.0:
        return None  # "unknown yet" (e.g. a Correction with localised=False)
    a = tuple(v / scale for v in cov)  # entries in [-1, 1]: no overflow in the eigen decomposition even for 1e308
    if max(abs(a[1] - a[3]), abs(a[2] - a[6]), abs(a[5] - a[7])) > _COV_SYM_RTOL:
        return "covariance is not symmetric"
    if _clearly_positive_definite(a):
        return None
    # a negative variance turns into NaN sigmas inside GTSAM (no exception), poisoning the whole map
    if float(np.linalg.eigvalsh(np.asarray(a, dtype=float).reshape(3, 3)).min()) < -_COV_PSD_RTOL:
        return "covariance is not positive semi-definite"
    return None


def _pose_problem(p: m.Pose3) -> str | None:
    norm = math.sqrt(p.qx * p.qx + p.qy * p.qy + p.qz * p.qz + p.qw * p.qw)
    if abs(norm - 1.0) > _QUAT_NORM_TOL:
        return f"quaternion norm {norm:.3g} is not 1"
    return None


def _poses(msg: m.Msg) -> list[m.Pose3]:
    if isinstance(msg, m.CameraImage):
        return [msg.mount]
    if isinstance(msg, (m.GroundTruthPose, m.RelativeObservation)):
        return [msg.pose]
    if isinstance(msg, m.RenderPoses):
        return list(msg.poses)
    return []


def _check(msg: m.Msg) -> None:
    name = type(msg).__name__
    if not _all_finite(msg):
        raise DecodeError("non_finite", f"{name} has NaN or inf")
    if isinstance(msg, m.CameraImage) and len(msg.data) != msg.width * msg.height:
        raise DecodeError("inconsistent", f"image {msg.width}x{msg.height} carries {len(msg.data)} bytes")
    if isinstance(msg, m.RenderPoses) and len(msg.robot_ids) != len(msg.poses):
        raise DecodeError("inconsistent", f"{name}: {len(msg.robot_ids)} robot ids but {len(msg.poses)} poses")
    covs = [e.cov for e in msg.robots] if isinstance(msg, m.GlobalMap) else [getattr(msg, "cov", None)]
    for cov in covs:
        why = None if cov is None else _cov_problem(cov)
        if why is not None:
            raise DecodeError("inconsistent", f"{name}: {why}")
    for pose in _poses(msg):
        why = _pose_problem(pose)
        if why is not None:
            raise DecodeError("inconsistent", f"{name}: {why}")


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
    """Decode a payload of unknown type (recordings, journals, spy) or raise
    :class:`DecodeError`.  The largest per-type limit is checked before decoding,
    the message's own limit right after (the type is only known then)."""
    if len(payload) > _MAX_ANY:
        raise DecodeError("oversized", f"payload of {len(payload)} B > {_MAX_ANY} B")
    try:
        msg: m.AnyMessage = _ANY_DECODER.decode(payload)
    except (msgspec.DecodeError, msgspec.ValidationError) as exc:
        raise DecodeError("malformed", str(exc)) from None
    except Exception as exc:
        raise DecodeError("malformed", f"{type(exc).__name__}: {exc}") from None
    limit = MAX_BYTES[type(msg)]
    if len(payload) > limit:
        raise DecodeError("oversized", f"{type(msg).__name__} payload of {len(payload)} B > {limit} B")
    _check(msg)
    return msg
