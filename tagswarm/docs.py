"""Generate ``docs/protocol.md`` (keys, QoS, encoding, every message field in plain words)
and ``docs/messages.schema.json`` (JSON Schema of the msgpack form, see
:mod:`tagswarm.wireschema`) from the protocol package, so the documentation cannot drift
from the code (tests/unit/test_docs.py checks they are current).  The reader it is written
for uses another language: plain zenoh and a msgpack library, no tagswarm code.

Usage: python -m tagswarm.docs [--check]
"""

from __future__ import annotations

import re
import sys
from pathlib import Path
from typing import Any, Final

import msgspec
from msgspec import inspect as mi

from tagswarm import wireschema
from tagswarm.protocol import messages as m
from tagswarm.protocol import wire
from tagswarm.protocol.codec import MAX_BYTES

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"

_COV = "3×3 covariance of (x_m, y_m, yaw_rad), row-major: 9 floats [xx, xy, xθ, yx, yy, yθ, θx, θy, θθ]"
_FUSED_COV = _COV + "; the position block is in the robot's own axes (x forward, y left): rotate it by yaw_rad for the map frame"  # noqa: E501
#: What a field means where its name and type do not say it all: (message, field) -> note.
FIELD_NOTES: Final[dict[tuple[str, str], str]] = {
    ("Msg", "seq"): "per-publisher sequence number on this key, +1 per message (gaps = lost messages)",
    ("Msg", "stamp_ns"): "simulation time of the data, nanoseconds since the world started",
    ("Tick", "step"): "index of the simulation step just finished",
    ("Tick", "dt_ns"): "length of one step",
    ("Tick", "run_id"): "names the world instance; a restarted world has a new one",
    ("Tick", "mode"): "the clock: realtime, or lockstep (the world waits for every participant's ack)",
    ("Tick", "cameras_rendered"): 'cameras with an image of this step, each `"<robot id>/<camera name>"`',
    ("TickAck", "participant"): '`"<role>/<id>"`, e.g. `"agent/3"`',
    ("TickAck", "step"): "the world step this participant finished",
    ("RenderPoses", "poses"): "poses[i] is robot robot_ids[i]'s base in the arena frame",
    ("RenderPoses", "cameras"): 'cameras this worker renders, each `"<robot id>/<camera name>"`',
    ("WorldCommand", "x_m"): "arena frame: target (teleport) or displacement (push)",
    ("CameraImage", "camera"): "camera name (the last chunk of the key)",
    ("CameraImage", "step"): "world step the image belongs to",
    ("CameraImage", "fx_px"): "pinhole intrinsics (OpenCV: pixel centres at integer coordinates)",
    ("CameraImage", "data"): "height × width bytes, row-major, one byte per pixel (mono8)",
    ("CameraImage", "mount"): "camera optical frame (z out of the lens, x right, y down) in the robot base frame",
    ("EncoderTicks", "left_ticks"): "cumulative count since the world started; positive = forward",
    ("EncoderTicks", "right_ticks"): "cumulative count since the world started; positive = forward",
    ("EncoderTicks", "ticks_per_rev"): "encoder ticks per wheel revolution",
    ("WheelCommand", "left_rad_s"): "wheel angular speed; positive drives forward",
    ("WheelCommand", "right_rad_s"): "wheel angular speed; positive drives forward",
    ("GroundTruthPose", "x_m"): "arena frame",
    ("GroundTruthPose", "pose"): "the same pose in 3-D, arena frame",
    ("GroundTruthPose", "v_m_s"): "forward speed",
    ("GroundTruthPose", "omega_rad_s"): "turn rate, counter-clockwise",
    ("RelativeObservation", "target_id"): "robot id, or landmark tag id",
    ("RelativeObservation", "x_m"): "target in the observer's base frame (x forward, y left)",
    ("RelativeObservation", "cov"): _COV,
    ("RelativeObservation", "pose"): "the same measurement in 3-D: T_observer-base_target",
    ("RelativeObservation", "tag_ids"): "tags the estimate used",
    ("RelativeObservation", "robot_id"): "the observer",
    ("RelativeObservation", "reprojection_rms_px"): "RMS reprojection error of the tag corners",
    ("RelativeObservation", "camera"): "camera name, or the rig's",
    ("OdometryEstimate", "x_m"): "base_link in this robot's odom frame (its start pose)",
    ("OdometryEstimate", "cov"): _COV,
    ("OdometryEstimate", "distance_m"): "distance travelled since the start",
    ("OdometryEstimate", "slip_m"): "cumulative evidence of wheel slip (commanded vs measured wheel travel)",
    ("Correction", "map_odom_x_m"): "the map → odom transform of this robot (x, y, yaw)",
    ("Correction", "x_m"): "fused pose of the robot's base, map frame",
    ("Correction", "cov"): _FUSED_COV,
    ("Correction", "last_fix_ns"): "simulation time of the newest observation involving this robot",
    ("MapEntry", "pose_stamp_ns"): "simulation time of this pose: the robot's newest odometry fused (0: the "
                                   "map's stamp_ns)",
    ("Correction", "pose_stamp_ns"): "simulation time of the fused pose: this robot's newest odometry fused "
                                     "(0: stamp_ns)",
    ("Correction", "localised"): "false: the server cannot place this robot yet (pose fields are zero)",
    ("Goal", "x_m"): "map frame",
    ("Goal", "tolerance_m"): "the robot stops within this distance of the goal",
    ("AgentStatus", "robot_id"): "nil for processes that are not a robot's (world, server)",
    ("AgentStatus", "role"): "world, agent, server, render, ...",
    ("AgentStatus", "mode"): "what the process is doing (e.g. an agent's mission state)",
    ("AgentStatus", "counters"): "counter name → value (frames processed, rejected payloads by kind, ...)",
    ("GlobalMap", "origin_id"): "the robot whose first pose is the map frame's origin",
    ("GlobalMap", "robots"): "one map entry per robot (MapEntry below)",
    ("GlobalMap", "edges"): "[observer, observed] robot id pairs seen recently",
    ("MapEntry", "x_m"): "fused pose, map frame",
    ("MapEntry", "cov"): _FUSED_COV,
    ("MapEntry", "last_seen_ns"): "simulation time of the robot's newest data",
    ("MapEntry", "alive"): "whether the robot's agent process is alive (its liveliness token)",
    ("Relocalisation", "from_x_m"): "map frame, before the re-localisation",
    ("Relocalisation", "to_x_m"): "map frame, after",
    ("Relocalisation", "jump_m"): "distance between the poses before and after",
    ("Relocalisation", "evidence"): "observations in the consistent set",
    ("Relocalisation", "observers"): "robots whose observations formed the evidence; -1 = a landmark",
    ("Pose3", "x_m"): "translation",
    ("Pose3", "qx"): "unit quaternion (qx, qy, qz, qw)",
}
_UNITS: Final = (("_rad_s", "rad/s"), ("_m_s", "m/s"), ("_ns", "nanoseconds"), ("_rad", "radians"),
                 ("_px", "pixels"), ("_m", "metres"), ("_ticks", "encoder ticks"))
_QOS: Final = {"block": "BLOCK, express", "drop_realtime": "DROP in realtime runs (BLOCK in lockstep runs)",
               "none": "—"}


def schema() -> str:
    """JSON Schema of every wire message in its msgpack form."""
    return wireschema.schema_text()


def unit_of(field: str) -> str:
    """The unit a field name ends with (``yaw_rad`` → radians), or ``""``."""
    return next((unit for suffix, unit in _UNITS if field.endswith(suffix)), "")


def _bounds(t: Any) -> str:
    if getattr(t, "ge", None) == -(2**63) and getattr(t, "le", None) == 2**63 - 1:
        return " (64-bit signed)"
    parts = []
    for attr, sign in (("ge", "≥"), ("gt", ">"), ("le", "≤"), ("lt", "<")):
        v = getattr(t, attr, None)
        if v is not None:
            parts.append(f"{sign} {v:,}")
    if getattr(t, "max_length", None) is not None:
        parts.append(f"at most {t.max_length} items")
    return f" ({', '.join(parts)})" if parts else ""


def plain_type(t: mi.Type) -> str:
    """A wire type in plain words (what a msgpack decoder sees)."""
    if isinstance(t, mi.IntType):
        return "integer" + _bounds(t)
    if isinstance(t, mi.FloatType):
        return "float64" + _bounds(t)
    if isinstance(t, mi.StrType):
        return "string"
    if isinstance(t, mi.BytesType):
        return "binary (msgpack bin)"
    if isinstance(t, mi.BoolType):
        return "boolean"
    if isinstance(t, mi.NoneType):
        return "nil"
    if isinstance(t, mi.LiteralType):
        return "string, one of " + ", ".join(f'"{v}"' for v in t.values)
    if isinstance(t, (mi.VarTupleType, mi.ListType)):
        return f"array of {plain_type(t.item_type)}" + _bounds(t)
    if isinstance(t, mi.TupleType):
        return f"array of exactly {len(t.item_types)}: [" + ", ".join(plain_type(i) for i in t.item_types) + "]"
    if isinstance(t, mi.DictType):
        return f"map from {plain_type(t.key_type)} to {plain_type(t.value_type)}"
    if isinstance(t, mi.StructType):
        return f"map: {t.cls.__name__}"
    if isinstance(t, mi.UnionType):
        return " or ".join(plain_type(x) for x in t.types)
    raise TypeError(f"no plain words for {t!r}")  # a new field type: teach this function


def _note(cls: type, field: str) -> str:
    for owner in (cls.__name__, "Msg"):
        if (owner, field) in FIELD_NOTES:
            return FIELD_NOTES[(owner, field)]
    base = re.sub(r"^(map_odom_|from_|to_)?(x|y|z|yaw)(_m|_rad)$", r"\1x_m", field)  # y_m, yaw_rad: as x_m
    base = re.sub(r"^(fy|cx|cy)_px$", "fx_px", re.sub(r"^q[yzw]$", "qx", base))
    return FIELD_NOTES.get((cls.__name__, base), "") if base != field else ""


def _prose(doc: str | None) -> str:
    text = " ".join((doc or "").split())
    text = re.sub(r":\w+:`~?([\w.]+)`", r"`\1`", text)  # :class:`Correction` -> `Correction`
    return text.replace("``", "`")


def _default(f: mi.Field) -> Any:
    return f.default if f.default is not msgspec.NODEFAULT else f.default_factory()


def _field_table(cls: type[msgspec.Struct]) -> list[str]:
    info = mi.type_info(cls)
    assert isinstance(info, mi.StructType)
    out = ["| field | type | unit | required | meaning |", "|---|---|---|---|---|"]
    tag = cls.__struct_config__.tag
    if tag is not None:
        out.append(f'| `type` | string, always "{tag}" | | yes | the message type (first entry of the map) |')
    for f in info.fields:
        required = "yes" if f.required else f"no (default {msgspec.json.encode(_default(f)).decode()})"
        out.append(f"| `{f.name}` | {plain_type(f.type)} | {unit_of(f.name)} | {required} | {_note(cls, f.name)} |")
    return out


_INTRO: Final = """\
# tagswarm wire protocol

Generated by `python -m tagswarm.docs` from `protocol/` (`protocol/wire.py`,
`protocol/messages.py`, `protocol/keys.py`); do not edit by hand.  Written for a
client in any language with a Zenoh library and a msgpack library: nothing here
needs tagswarm's code.  A complete reader in plain Python (zenoh + msgpack):
[`examples/raw_subscriber.py`](../examples/raw_subscriber.py).

## Encoding

Every sample is **one msgpack map** with string keys, and every publication sets
the Zenoh encoding **`{media};<MessageType>`**, e.g.
`{example}`.  The map's first entry, `type`, holds the
message's short tag (`"encoder_ticks"`); either one tells the message type.

- Integers are msgpack integers, floats are float64, strings are UTF-8 str,
  `binary` fields are msgpack **bin** (raw bytes, never base64), arrays are
  msgpack arrays, nested messages (`Pose3`, `MapEntry`) are maps, `nil` is msgpack nil.
- Every field is written by current senders.  Fields marked *not required*
  may be absent from older senders and recordings: use the default shown.
  Ignore keys you do not know (later versions may add fields).
- A missing encoding (an older recording republished) is not an error: read
  `type` from the map.
- JSON Schema of this msgpack form: [`messages.schema.json`](messages.schema.json)
  (JSON Schema 2020-12; its root is a `oneOf` over every message).  JSON has no
  binary type: `binary` fields are marked `"format": "binary"`; give your
  validator a format check "is raw bytes" for it.

## Conventions

- **Units**: SI, the unit in the field name: `_m` metres, `_rad` radians,
  `_rad_s` rad/s, `_m_s` m/s, `_ns` nanoseconds, `_px` pixels.
- **Time**: `stamp_ns` is *simulation* time (ns since the world started), the
  only clock; `seq` counts each publisher's messages per key.
- **Frames**: right-handed.  `arena`: the simulated world (origin at the arena
  centre, z up; ground truth, start poses, teleports).  `map`: the fused map
  (the origin robot's first pose, or the arena frame when the scenario has
  landmark tags).  `odom_k`: robot k's dead-reckoning frame (its start pose).
  `base_link`: on the floor at the chassis centre, x forward, y left, z up.
  Camera optical frame: z out of the lens, x right, y down (OpenCV).
- **Poses**: planar poses are (`x_m`, `y_m`, `yaw_rad`), yaw counter-clockwise
  from x.  3-D poses (`Pose3`) are a translation and a unit quaternion
  (`qx`, `qy`, `qz`, `qw`), the transform T_parent_child: p_parent = R p_child + t.
- **Covariances** (`cov`): 9 floats, the 3×3 covariance of (x, y, yaw),
  row-major: `[xx, xy, xθ, yx, yy, yθ, θx, θy, θθ]` (m², m·rad, rad²),
  symmetric positive semi-definite.  In `Correction` and `MapEntry` the position
  block is in the robot's own axes (x forward, y left): rotate it by `yaw_rad`
  for the map frame.  All zeros: unknown yet.
- **QoS**: keys marked BLOCK use Zenoh's BLOCK congestion control (never dropped
  by Zenoh under load) and are express (sent at once); camera images use DROP
  in realtime runs (a slow reader skips frames), BLOCK in lockstep runs.
  Priority is Zenoh's default everywhere.

## Keys

Every key starts with `tagswarm/<run>/`; `<run>` isolates runs that share a
network (`tagswarm up --run ID`).  Subscribe to `tagswarm/<run>/**` for all of a run.
"""


def _keys_table() -> list[str]:
    out = ["| key expression | message | QoS | sent by | read by | note |", "|---|---|---|---|---|---|"]
    for spec in wire.KEYS:
        msg = f"[`{spec.message.__name__}`](#{spec.message.__name__.lower()})" if spec.message else "(no payload)"
        who = [re.sub(r"(<[a-z ]+>)", r"`\1`", text) for text in (spec.sender, spec.receivers, spec.note)]
        out.append(f"| `{spec.display()}` | {msg} | {_QOS[spec.qos]} | {' | '.join(who)} |")
    return out


def markdown() -> str:
    """The whole ``docs/protocol.md``."""
    example = wire.encoding_of(m.EncoderTicks)
    out = [_INTRO.format(media=wire.MEDIA_TYPE, example=example), *_keys_table(), "", "## Messages", ""]
    for cls in wire.MESSAGE_TYPES:
        out += [f"### {cls.__name__}", "",
                f"Encoding `{wire.encoding_of(cls)}`, `type` = `\"{cls.__struct_config__.tag}\"`, "
                f"at most {MAX_BYTES[cls]:,} bytes.  Keys: "
                + ", ".join(f"`{s.display()}`" for s in wire.KEYS if s.message is cls) + ".", "",
                _prose(cls.__doc__), "", *_field_table(cls), ""]
    out += ["## Nested maps", ""]
    for nested in (m.Pose3, m.MapEntry):
        out += [f"### {nested.__name__}", "", _prose(nested.__doc__), "", *_field_table(nested), ""]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    files = {DOCS / "protocol.md": markdown(), DOCS / "messages.schema.json": schema()}
    if "--check" in args:
        stale = [str(p) for p, text in files.items() if not p.exists() or p.read_text() != text]
        if stale:
            print("out of date: " + ", ".join(stale) + " (run python -m tagswarm.docs)")
            return 1
        return 0
    DOCS.mkdir(exist_ok=True)
    for p, text in files.items():
        p.write_text(text)
        print("wrote", p)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
