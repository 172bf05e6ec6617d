"""One-line and JSON views of decoded wire messages for ``tagswarm spy``.

Never shows raw bytes: images are summarised as ``320x240 mono8 robot 1 front``,
every bytes field of ``--echo`` JSON is replaced by ``<N bytes>``.  Poses are shown
as ``(x m, y m, yaw °)`` in the frame the message states.  Pure code (no bus).
"""

from __future__ import annotations

import math
from typing import Any

import msgspec

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.geometry import position_sigma_m


def _pose(x: float, y: float, yaw: float) -> str:
    return f"({x:+.2f}, {y:+.2f}, {math.degrees(yaw):+.0f}°)"


def type_name(msg: m.Msg) -> str:
    """The message's class name (``CameraImage``, ``Tick`` ...)."""
    return type(msg).__name__


def image_summary(img: m.CameraImage) -> str:
    """``320x240 mono8 robot 1 front``: what an image is, without its pixels."""
    return f"{img.width}x{img.height} {img.encoding} robot {img.robot_id} {img.camera}"


def summarise(msg: m.Msg) -> str:
    """A short one-line view of a decoded message (never its raw bytes)."""
    if isinstance(msg, m.CameraImage):
        return f"{image_summary(msg)} step {msg.step}"
    if isinstance(msg, m.Tick):
        return f"step {msg.step} {msg.mode} dt {msg.dt_ns / 1e6:g} ms, {len(msg.cameras_rendered)} frame(s)"
    if isinstance(msg, m.TickAck):
        return f"{msg.participant} acked step {msg.step}"
    if isinstance(msg, m.EncoderTicks):
        return f"robot {msg.robot_id} L {msg.left_ticks} R {msg.right_ticks} ticks ({msg.ticks_per_rev}/rev)"
    if isinstance(msg, m.WheelCommand):
        return f"robot {msg.robot_id} L {msg.left_rad_s:+.2f} R {msg.right_rad_s:+.2f} rad/s"
    if isinstance(msg, m.GroundTruthPose):
        return f"robot {msg.robot_id} {_pose(msg.x_m, msg.y_m, msg.yaw_rad)} v {msg.v_m_s:+.2f} m/s"
    if isinstance(msg, m.RelativeObservation):
        return (f"robot {msg.robot_id} sees {msg.target_kind} {msg.target_id} at "
                f"{_pose(msg.x_m, msg.y_m, msg.yaw_rad)} rms {msg.reprojection_rms_px:.2f} px ({msg.camera})")
    if isinstance(msg, m.OdometryEstimate):
        return f"robot {msg.robot_id} {_pose(msg.x_m, msg.y_m, msg.yaw_rad)} travelled {msg.distance_m:.2f} m"
    if isinstance(msg, m.Correction):
        if not msg.localised:
            if not any(msg.cov):
                return f"robot {msg.robot_id} not localised"
            sigma = position_sigma_m(msg.cov) or 0.0
            return (f"robot {msg.robot_id} not localised: placed at {_pose(msg.x_m, msg.y_m, msg.yaw_rad)} (map), "
                    f"not vouched for (sigma {sigma:.2f} m)")
        return f"robot {msg.robot_id} at {_pose(msg.x_m, msg.y_m, msg.yaw_rad)} (map)"
    if isinstance(msg, m.GlobalMap):
        alive = sum(1 for e in msg.robots if e.alive)
        return f"origin {msg.origin_id}, {len(msg.robots)} robot(s) ({alive} alive), {len(msg.edges)} edge(s)"
    if isinstance(msg, m.AgentStatus):
        who = msg.role if msg.robot_id is None else f"{msg.role} {msg.robot_id}"
        counters = " ".join(f"{k}={v}" for k, v in list(msg.counters.items())[:4])
        return f"{who} {msg.mode} {counters}".rstrip()
    if isinstance(msg, m.RenderPoses):
        return f"step {msg.step}: {len(msg.robot_ids)} robot(s), {len(msg.cameras)} camera(s)"
    if isinstance(msg, m.Goal):
        return f"robot {msg.robot_id} -> ({msg.x_m:+.2f}, {msg.y_m:+.2f}) ±{msg.tolerance_m:g} m"
    return type_name(msg)  # pragma: no cover - every wire type is listed above


def _strip_bytes(value: Any, image: m.CameraImage | None) -> Any:
    if isinstance(value, (bytes, bytearray, memoryview)):
        size = len(value)
        return f"<{image_summary(image)}: {size} bytes>" if image is not None else f"<{size} bytes>"
    if isinstance(value, dict):
        return {k: _strip_bytes(v, image) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_strip_bytes(v, image) for v in value]
    return value


def message_json(msg: m.Msg) -> Any:
    """The message as JSON-ready builtins with every bytes field replaced by a summary."""
    raw = msgspec.to_builtins(msg, builtin_types=(bytes, bytearray, memoryview))
    return _strip_bytes(raw, msg if isinstance(msg, m.CameraImage) else None)


def decode(payload: bytes) -> m.Msg | codec.DecodeError:
    """Decode any wire message; a bad payload comes back as the error, never raised."""
    try:
        msg: m.Msg = codec.decode_any(payload)
        return msg
    except codec.DecodeError as exc:
        return exc
    except Exception as exc:  # decode_any wraps everything; this is the spy's own "never crash"
        return codec.DecodeError("malformed", f"{type(exc).__name__}: {exc}")


def echo_line(key: str, size: int, decoded: m.Msg | codec.DecodeError, encoding: str | None = None,
              mismatch: bool = False) -> str:
    """One JSON line for ``--echo``; ``encoding`` (the sample's Zenoh encoding) is included
    when known, and ``"encoding_mismatch": true`` when it does not match the message."""
    doc: dict[str, Any] = {"key": key, "size": size}
    if encoding is not None:
        doc["encoding"] = encoding
        if mismatch:
            doc["encoding_mismatch"] = True
    if isinstance(decoded, codec.DecodeError):
        doc["error"] = {"kind": decoded.kind, "detail": decoded.detail}
    else:
        doc["msg"] = message_json(decoded)
    return msgspec.json.encode(doc).decode()
