"""tagswarm.protocol.codec: round trips and typed rejects, case by case (no network; the
property-based fuzzing of every decoder is in test_codec_fuzz.py)."""

from __future__ import annotations

import math
import typing
from typing import Any

import msgspec
import numpy as np
import pytest
from hypothesis import HealthCheck, settings

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m

KINDS = {"oversized", "malformed", "non_finite", "inconsistent"}
FUZZ = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])

MOUNT = m.Pose3(x_m=0.15, y_m=0.0, z_m=0.22, qx=-0.5, qy=0.5, qz=-0.5, qw=0.5)
COV = (0.01, 0.001, 0.0, 0.001, 0.02, 0.0, 0.0, 0.0, 0.005)


def _entry(rid: int, x: float, alive: bool = True) -> m.MapEntry:
    return m.MapEntry(robot_id=rid, x_m=x, y_m=-0.5 * x, yaw_rad=0.3 * rid, cov=COV, last_seen_ns=1_500_000_000,
                      alive=alive)


SAMPLES: list[m.Msg] = [
    m.Tick(seq=41, stamp_ns=1_366_666_666, run_id="default-1a2b3c4d", step=41, dt_ns=33_333_333, mode="lockstep",
           cameras_rendered=("0/front", "3/front")),
    m.TickAck(seq=7, stamp_ns=233_333_331, participant="agent/3", step=7),
    m.CameraImage(seq=4, stamp_ns=400_000_000, robot_id=2, camera="front", step=12, width=32, height=24,
                  fx_px=277.1, fy_px=277.1, cx_px=15.5, cy_px=11.5, mount=MOUNT, data=bytes(range(256)) * 3),
    m.EncoderTicks(seq=90, stamp_ns=3_000_000_000, robot_id=1, left_ticks=123_456, right_ticks=-9_876,
                   ticks_per_rev=4096),
    m.WheelCommand(seq=3, stamp_ns=100_000_000, robot_id=0, left_rad_s=4.5, right_rad_s=-2.25),
    m.GroundTruthPose(seq=5, stamp_ns=166_666_665, robot_id=3, step=5, x_m=1.5, y_m=-0.25, yaw_rad=3.1,
                      pose=m.Pose3(x_m=1.5, y_m=-0.25, z_m=0.07, qz=0.9995, qw=0.0292), v_m_s=0.4, omega_rad_s=-0.1),
    m.RelativeObservation(seq=11, stamp_ns=900_000_000, robot_id=0, target_kind="robot", target_id=2, x_m=2.1,
                          y_m=0.3, yaw_rad=-1.2, cov=COV, pose=m.Pose3(x_m=2.1, y_m=0.3, z_m=0.0, qz=-0.56, qw=0.83),
                          reprojection_rms_px=0.42, tag_ids=(21, 23), camera="front"),
    m.OdometryEstimate(seq=60, stamp_ns=2_000_000_000, robot_id=1, x_m=0.8, y_m=0.05, yaw_rad=0.02, cov=COV,
                       distance_m=0.81),
    m.Correction(seq=2, stamp_ns=2_000_000_000, robot_id=1, map_odom_x_m=0.0, map_odom_y_m=1.5,
                 map_odom_yaw_rad=-1.5707963, x_m=0.05, y_m=2.3, yaw_rad=-1.55, cov=COV),
    m.GlobalMap(seq=9, stamp_ns=3_000_000_000, origin_id=0, robots=(_entry(0, 0.0), _entry(1, 1.25, alive=False)),
                edges=((0, 1), (1, 0))),
    m.AgentStatus(seq=1, stamp_ns=1_000_000_000, robot_id=2, role="agent", mode="lockstep",
                  counters={"frames_processed": 10, "rejected_malformed": 1}),
    m.AgentStatus(seq=0, stamp_ns=0, role="world", mode="realtime"),
    m.RenderPoses(seq=8, stamp_ns=266_666_664, step=8, robot_ids=(0, 1),
                  poses=(MOUNT, m.Pose3(x_m=-1.0, y_m=2.0, z_m=0.07)), cameras=("1/front",)),
    m.Goal(seq=9, stamp_ns=5, robot_id=2, x_m=1.5, y_m=-0.5, tolerance_m=0.2),
    m.WorldCommand(seq=1, stamp_ns=2_000_000_000, robot_id=4, action="teleport", x_m=1.0, y_m=-0.5, yaw_rad=0.5),
    m.Relocalisation(seq=0, stamp_ns=3_000_000_000, robot_id=4, from_x_m=2.7, from_y_m=-0.3, from_yaw_rad=0.1,
                     to_x_m=3.6, to_y_m=-1.3, to_yaw_rad=0.15, jump_m=1.35, evidence=6, observers=(0, 2, -1)),
    m.ClaimReply(seq=2, stamp_ns=0, robot_id=3, robots=6, user="agent3", password="Zq9-long-random-secret"),
]
BY_TYPE: dict[type[m.Msg], m.Msg] = {type(s): s for s in SAMPLES}


def _ids(msg: Any) -> str:
    return type(msg).__name__


def _fields(msg: m.Msg) -> dict[str, Any]:
    """The message as a msgpack-encodable dict (struct values stay structs)."""
    out: dict[str, Any] = {"type": type(msg).__struct_config__.tag}
    out.update({f: getattr(msg, f) for f in msg.__struct_fields__})
    return out


# --------------------------------------------------------------------------- coverage of the sample set


def test_samples_cover_every_wire_type() -> None:
    union = set(typing.get_args(m.AnyMessage))
    assert set(codec.MAX_BYTES) == union
    assert set(BY_TYPE) == union


# --------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("msg", SAMPLES, ids=_ids)
def test_round_trip_typed(msg: m.Msg) -> None:
    payload = codec.encode(msg)
    assert isinstance(payload, bytes)
    out = codec.decode(type(msg), payload)
    assert type(out) is type(msg)
    assert out == msg


@pytest.mark.parametrize("msg", SAMPLES, ids=_ids)
def test_round_trip_any(msg: m.Msg) -> None:
    out = codec.decode_any(codec.encode(msg))
    assert type(out) is type(msg)
    assert out == msg


@pytest.mark.parametrize("wrap", [bytes, bytearray, memoryview], ids=lambda w: w.__name__)
def test_decode_accepts_buffers(wrap: Any) -> None:
    msg = BY_TYPE[m.CameraImage]
    payload = wrap(codec.encode(msg))
    assert codec.decode(m.CameraImage, payload) == msg
    assert codec.decode_any(payload) == msg


def test_round_trip_keeps_values_exactly() -> None:
    img = codec.decode(m.CameraImage, codec.encode(BY_TYPE[m.CameraImage]))
    assert img.data == bytes(range(256)) * 3
    assert len(img.data) == img.width * img.height == 768
    assert img.mount.qx == -0.5 and img.mount.qw == 0.5
    status = codec.decode(m.AgentStatus, codec.encode(BY_TYPE[m.AgentStatus]))
    assert status.robot_id is None and status.counters == {}
    gm = codec.decode(m.GlobalMap, codec.encode(BY_TYPE[m.GlobalMap]))
    assert gm.edges == ((0, 1), (1, 0))
    assert [e.alive for e in gm.robots] == [True, False]


def test_payload_is_tagged() -> None:
    raw = msgspec.msgpack.decode(codec.encode(BY_TYPE[m.WheelCommand]))
    assert raw["type"] == "wheel_command"
    assert raw["left_rad_s"] == 4.5


def test_ints_are_accepted_for_float_fields() -> None:
    payload = msgspec.msgpack.encode({"type": "wheel_command", "seq": 0, "stamp_ns": 0, "robot_id": 0,
                                      "left_rad_s": 2, "right_rad_s": -1})
    cmd = codec.decode(m.WheelCommand, payload)
    assert cmd.left_rad_s == 2.0 and isinstance(cmd.left_rad_s, float)


# --------------------------------------------------------------------------- oversized


@pytest.mark.parametrize("cls", list(codec.MAX_BYTES), ids=lambda c: c.__name__)
def test_oversized_is_checked_before_decoding(cls: type[m.Msg]) -> None:
    limit = codec.MAX_BYTES[cls]
    # not msgpack at all: if it were decoded first this would be "malformed"
    with pytest.raises(codec.DecodeError) as exc:
        codec.decode(cls, b"\xc1" * (limit + 1))
    assert exc.value.kind == "oversized"
    assert cls.__name__ in exc.value.detail


@pytest.mark.parametrize("cls", [c for c in codec.MAX_BYTES if c is not m.CameraImage], ids=lambda c: c.__name__)
def test_at_limit_is_decoded_not_oversized(cls: type[m.Msg]) -> None:
    with pytest.raises(codec.DecodeError) as exc:
        codec.decode(cls, b"\xc1" * codec.MAX_BYTES[cls])
    assert exc.value.kind == "malformed"


def test_valid_but_oversized_message_is_rejected() -> None:
    tick = msgspec.structs.replace(BY_TYPE[m.Tick], cameras_rendered=tuple(f"{i}/front" for i in range(20_000)))
    payload = codec.encode(tick)
    assert len(payload) > codec.MAX_BYTES[m.Tick]
    with pytest.raises(codec.DecodeError) as exc:
        codec.decode(m.Tick, payload)
    assert exc.value.kind == "oversized"
    with pytest.raises(codec.DecodeError) as exc:
        codec.decode_any(payload)  # the type's own limit applies once the tag is known
    assert exc.value.kind == "oversized"
    assert "Tick" in exc.value.detail


def test_decode_any_oversized() -> None:
    with pytest.raises(codec.DecodeError) as exc:
        codec.decode_any(b"\x00" * (max(codec.MAX_BYTES.values()) + 1))
    assert exc.value.kind == "oversized"


# --------------------------------------------------------------------------- malformed


GARBAGE = [b"", b"\xc1", b"not msgpack at all", b"\xff" * 64, b"\x92\x01", bytes(range(256))]


@pytest.mark.parametrize("payload", GARBAGE)
@pytest.mark.parametrize("cls", list(codec.MAX_BYTES), ids=lambda c: c.__name__)
def test_garbage_is_malformed(cls: type[m.Msg], payload: bytes) -> None:
    with pytest.raises(codec.DecodeError) as exc:
        codec.decode(cls, payload)
    assert exc.value.kind == "malformed"
    assert str(exc.value).startswith("malformed: ")


@pytest.mark.parametrize("payload", GARBAGE)
def test_garbage_is_malformed_any(payload: bytes) -> None:
    with pytest.raises(codec.DecodeError) as exc:
        codec.decode_any(payload)
    assert exc.value.kind == "malformed"


def test_wrong_message_type_is_malformed() -> None:
    with pytest.raises(codec.DecodeError) as exc:
        codec.decode(m.CameraImage, codec.encode(BY_TYPE[m.EncoderTicks]))
    assert exc.value.kind == "malformed"
    assert "CameraImage" in exc.value.detail


@pytest.mark.parametrize("msg", SAMPLES, ids=_ids)
def test_every_other_type_rejects_the_payload(msg: m.Msg) -> None:
    payload = codec.encode(msg)
    for cls in codec.MAX_BYTES:
        if cls is type(msg):
            continue
        with pytest.raises(codec.DecodeError) as exc:
            codec.decode(cls, payload)
        assert exc.value.kind == "malformed", cls


@pytest.mark.parametrize("obj", [42, -1, 1.5, "tick", None, True, [1, 2, 3], {}, {"type": "tick"},
                                 {"type": "no_such_type", "seq": 0, "stamp_ns": 0}])
def test_valid_msgpack_of_wrong_shape_is_malformed(obj: Any) -> None:
    payload = msgspec.msgpack.encode(obj)
    for cls in codec.MAX_BYTES:
        with pytest.raises(codec.DecodeError) as exc:
            codec.decode(cls, payload)
        assert exc.value.kind == "malformed", cls
    with pytest.raises(codec.DecodeError) as exc:
        codec.decode_any(payload)
    assert exc.value.kind == "malformed"


@pytest.mark.parametrize("msg", SAMPLES, ids=_ids)
@pytest.mark.parametrize("field", ["seq", "stamp_ns"])
def test_negative_seq_or_stamp_is_malformed(msg: m.Msg, field: str) -> None:
    payload = codec.encode(msgspec.structs.replace(msg, **{field: -1}))
    with pytest.raises(codec.DecodeError) as exc:
        codec.decode(type(msg), payload)
    assert exc.value.kind == "malformed"
    assert field in exc.value.detail
    with pytest.raises(codec.DecodeError) as exc:
        codec.decode_any(payload)
    assert exc.value.kind == "malformed"


@pytest.mark.parametrize(
    ("cls", "changes"),
    [
        (m.WheelCommand, {"robot_id": 100_001}),
        (m.WheelCommand, {"robot_id": -1}),
        (m.CameraImage, {"width": 0, "data": b""}),
        (m.CameraImage, {"width": 8193}),
        (m.CameraImage, {"encoding": "rgb8"}),
        (m.Tick, {"dt_ns": 0}),
        (m.Tick, {"mode": "fast"}),
        (m.EncoderTicks, {"ticks_per_rev": 0}),
        (m.RelativeObservation, {"target_kind": "wall"}),
        (m.TickAck, {"step": -3}),
        (m.GlobalMap, {"robots": (msgspec.structs.replace(_entry(0, 0.0), last_seen_ns=-5),)}),
    ],
)
def test_out_of_range_fields_are_malformed(cls: type[m.Msg], changes: dict[str, Any]) -> None:
    payload = codec.encode(msgspec.structs.replace(BY_TYPE[cls], **changes))
    with pytest.raises(codec.DecodeError) as exc:
        codec.decode(cls, payload)
    assert exc.value.kind == "malformed"


def test_missing_required_field_is_malformed() -> None:
    fields = _fields(BY_TYPE[m.OdometryEstimate])
    del fields["cov"]
    with pytest.raises(codec.DecodeError) as exc:
        codec.decode(m.OdometryEstimate, msgspec.msgpack.encode(fields))
    assert exc.value.kind == "malformed"
    assert "cov" in exc.value.detail


# --------------------------------------------------------------------------- non-finite


def _nan_cases() -> list[tuple[str, m.Msg]]:
    r = msgspec.structs.replace
    nan, inf = math.nan, math.inf
    cmd, gt = BY_TYPE[m.WheelCommand], BY_TYPE[m.GroundTruthPose]
    obs, odo, cor = BY_TYPE[m.RelativeObservation], BY_TYPE[m.OdometryEstimate], BY_TYPE[m.Correction]
    img, gm, rp = BY_TYPE[m.CameraImage], BY_TYPE[m.GlobalMap], BY_TYPE[m.RenderPoses]
    bad_cov = (*COV[:4], inf, *COV[5:])
    return [
        ("wheel_nan", r(cmd, left_rad_s=nan)),
        ("wheel_inf", r(cmd, right_rad_s=inf)),
        ("wheel_minus_inf", r(cmd, right_rad_s=-inf)),
        ("truth_x_nan", r(gt, x_m=nan)),
        ("truth_pose_qw_nan", r(gt, pose=r(gt.pose, qw=nan))),
        ("truth_pose_z_inf", r(gt, pose=r(gt.pose, z_m=inf))),
        ("truth_omega_inf", r(gt, omega_rad_s=-inf)),
        ("obs_rms_nan", r(obs, reprojection_rms_px=nan)),
        ("obs_pose_inf", r(obs, pose=r(obs.pose, y_m=inf))),
        ("obs_cov_nan", r(obs, cov=(nan,) * 9)),
        ("odom_cov_inf", r(odo, cov=bad_cov)),
        ("odom_distance_nan", r(odo, distance_m=nan)),
        ("correction_yaw_inf", r(cor, map_odom_yaw_rad=-inf)),
        ("correction_cov_inf", r(cor, cov=bad_cov)),
        ("image_fx_inf", r(img, fx_px=inf)),
        ("image_mount_nan", r(img, mount=r(img.mount, qx=nan))),
        ("map_entry_x_nan", r(gm, robots=(gm.robots[0], r(gm.robots[1], x_m=nan)))),
        ("map_entry_cov_inf", r(gm, robots=(r(gm.robots[0], cov=bad_cov),))),
        ("render_pose_inf", r(rp, poses=(rp.poses[0], r(rp.poses[1], qx=inf)))),
    ]


@pytest.mark.parametrize(("name", "msg"), _nan_cases(), ids=[c[0] for c in _nan_cases()])
def test_non_finite_is_rejected(name: str, msg: m.Msg) -> None:
    payload = codec.encode(msg)
    with pytest.raises(codec.DecodeError) as exc:
        codec.decode(type(msg), payload)
    assert exc.value.kind == "non_finite", name
    assert type(msg).__name__ in exc.value.detail
    with pytest.raises(codec.DecodeError) as exc:
        codec.decode_any(payload)
    assert exc.value.kind == "non_finite", name


def test_huge_but_finite_floats_are_fine() -> None:
    cmd = msgspec.structs.replace(BY_TYPE[m.WheelCommand], left_rad_s=1e308, right_rad_s=-5e-324)
    assert codec.decode(m.WheelCommand, codec.encode(cmd)) == cmd


# --------------------------------------------------------------------------- inconsistent


@pytest.mark.parametrize("n_bytes", [0, 767, 769, 32 * 32])
def test_image_size_mismatch_is_inconsistent(n_bytes: int) -> None:
    img = msgspec.structs.replace(BY_TYPE[m.CameraImage], data=b"\x80" * n_bytes)
    payload = codec.encode(img)
    with pytest.raises(codec.DecodeError) as exc:
        codec.decode(m.CameraImage, payload)
    assert exc.value.kind == "inconsistent"
    assert f"{n_bytes} bytes" in exc.value.detail and "32x24" in exc.value.detail
    with pytest.raises(codec.DecodeError) as exc:
        codec.decode_any(payload)
    assert exc.value.kind == "inconsistent"


@pytest.mark.parametrize("cls", [m.RelativeObservation, m.OdometryEstimate, m.Correction], ids=lambda c: c.__name__)
@pytest.mark.parametrize("n", [0, 3, 8, 10, 36])
def test_cov_of_wrong_length_is_inconsistent(cls: type[m.Msg], n: int) -> None:
    payload = codec.encode(msgspec.structs.replace(BY_TYPE[cls], cov=(0.1,) * n))
    with pytest.raises(codec.DecodeError) as exc:
        codec.decode(cls, payload)
    assert exc.value.kind == "inconsistent"
    assert f"{n} entries" in exc.value.detail
    with pytest.raises(codec.DecodeError) as exc:
        codec.decode_any(payload)
    assert exc.value.kind == "inconsistent"


def test_global_map_entry_cov_of_wrong_length_is_inconsistent() -> None:
    gm = BY_TYPE[m.GlobalMap]
    bad = msgspec.structs.replace(gm, robots=(msgspec.structs.replace(gm.robots[0], cov=(1.0,)),))
    with pytest.raises(codec.DecodeError) as exc:
        codec.decode(m.GlobalMap, codec.encode(bad))
    assert exc.value.kind == "inconsistent"


def test_decode_error_carries_kind_and_detail() -> None:
    err = codec.DecodeError("oversized", "too big")
    assert err.kind == "oversized"
    assert err.detail == "too big"
    assert str(err) == "oversized: too big"
    assert isinstance(err, Exception)


# --------------------------------------------------------------------------- covariance checks
def _reference_cov_problem(cov: tuple[float, ...]) -> str | None:
    """The plain definition: symmetric to 1e-6 and no eigenvalue below -1e-9, relative to the largest entry."""
    a = np.asarray(cov, dtype=float).reshape(3, 3)
    scale = float(np.abs(a).max())
    if scale == 0.0:
        return None
    a = a / scale
    if float(np.abs(a - a.T).max()) > 1e-6:
        return "covariance is not symmetric"
    if float(np.linalg.eigvalsh(a).min()) < -1e-9:
        return "covariance is not positive semi-definite"
    return None


@pytest.mark.parametrize("cov, why", [
    ((1e-4, 0, 0, 0, 1e-4, 0, 0, 0, 1e-5), None),                       # the common case (fast path)
    ((1.0, 0, 0, 0, 1e-9, 0, 0, 0, 1.0), None),                         # PSD, nearly singular: exact path
    ((1.0, 1.0, 0, 1.0, 1.0, 0, 0, 0, 1.0), None),                       # singular PSD (eigenvalue 0)
    ((1.0, 1.1, 0, 1.1, 1.0, 0, 0, 0, 1.0), "not positive semi-definite"),  # leading minor < 0
    ((1.0, 0, 0, 0, 1.0, 0, 0, 0, -1e-3), "not positive semi-definite"),   # negative variance last
    ((-1e-3, 0, 0, 0, 1.0, 0, 0, 0, 1.0), "not positive semi-definite"),   # negative variance first
    ((1.0, 0, 0.5, 0, 1.0, 0, 0, 0, 1.0), "not symmetric"),
    ((1e300, 0, 0, 0, 1e300, 0, 0, 0, 1e300), None),                     # huge but valid: no overflow
    ((0.0,) * 9, None),                                                   # "unknown yet"
])
def test_cov_check_cases(cov: tuple[float, ...], why: str | None) -> None:
    got = codec._cov_problem(tuple(float(v) for v in cov))
    assert (got is None) == (why is None), got
    if why is not None:
        assert got is not None and why in got
    assert got == _reference_cov_problem(cov)


def test_cov_check_agrees_with_the_eigenvalue_definition_on_random_matrices() -> None:
    # the fast path (Sylvester with a margin) must never accept what the eigenvalue test rejects
    rng = np.random.default_rng(7)
    seen = {None: 0, "covariance is not positive semi-definite": 0}
    for i in range(3000):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        eig = rng.normal(size=3) * 10.0 ** rng.uniform(-12, 0, size=3)
        if i % 3 == 0:
            eig = np.abs(eig)  # PSD, often badly conditioned
        a = q @ np.diag(eig) @ q.T
        a = 0.5 * (a + a.T) * 10.0 ** rng.uniform(-8, 3)
        cov = tuple(float(v) for v in a.ravel())
        got = codec._cov_problem(cov)
        assert got == _reference_cov_problem(cov), (cov, got)
        seen[got] = seen.get(got, 0) + 1
    assert min(seen.values()) > 300  # both answers well represented
