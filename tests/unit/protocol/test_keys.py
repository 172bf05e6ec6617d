"""tagswarm.protocol.keys: the key layout, parsing keys back and validation."""

from __future__ import annotations

from collections.abc import Callable

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tagswarm.protocol import keys
from tagswarm.protocol.keys import Keys

RUN = "run-1"
P = f"tagswarm/{RUN}"


@pytest.fixture
def k() -> Keys:
    return Keys(RUN)


# --------------------------------------------------------------------------- layout


def test_prefix_and_root(k: Keys) -> None:
    assert keys.ROOT == "tagswarm"
    assert k.prefix == P
    assert k.run == RUN


def test_world_keys(k: Keys) -> None:
    assert k.tick() == f"{P}/world/tick"
    assert k.ack("agent/3") == f"{P}/world/ack/agent/3"
    assert k.ack("server/0") == f"{P}/world/ack/server/0"
    assert k.acks() == f"{P}/world/ack/*/*"
    assert k.render(0) == f"{P}/world/render/0"
    assert k.render(5) == f"{P}/world/render/5"
    assert k.world_status() == f"{P}/world/status"


def test_robot_keys(k: Keys) -> None:
    assert k.robot(3) == f"{P}/robot/3"
    assert k.image(3, "front") == f"{P}/robot/3/camera/front"
    assert k.image(0, "rear_left.2") == f"{P}/robot/0/camera/rear_left.2"
    assert k.images(3) == f"{P}/robot/3/camera/*"
    assert k.images() == f"{P}/robot/*/camera/*"
    assert k.encoders(1) == f"{P}/robot/1/encoders"
    assert k.cmd(1) == f"{P}/robot/1/cmd"
    assert k.truth(1) == f"{P}/robot/1/truth"
    assert k.observation(1) == f"{P}/robot/1/observation"
    assert k.odometry(1) == f"{P}/robot/1/odometry"
    assert k.correction(1) == f"{P}/robot/1/correction"
    assert k.robot_status(1) == f"{P}/robot/1/status"


def test_robot_leaf_wildcards(k: Keys) -> None:
    assert k.encoders() == f"{P}/robot/*/encoders"
    assert k.cmd() == f"{P}/robot/*/cmd"
    assert k.truth() == f"{P}/robot/*/truth"
    assert k.observation() == f"{P}/robot/*/observation"
    assert k.odometry() == f"{P}/robot/*/odometry"
    assert k.correction() == f"{P}/robot/*/correction"
    assert k.robot_status() == f"{P}/robot/*/status"


def test_robot_id_zero_is_not_a_wildcard(k: Keys) -> None:
    assert k.cmd(0) == f"{P}/robot/0/cmd"
    assert k.images(0) == f"{P}/robot/0/camera/*"


def test_server_and_presence_keys(k: Keys) -> None:
    assert k.map() == f"{P}/server/map"
    assert k.server_status() == f"{P}/server/status"
    assert k.alive("agent/2") == f"{P}/alive/agent/2"
    assert k.alive("render/1") == f"{P}/alive/render/1"
    assert k.alive_all() == f"{P}/alive/**"


def test_keys_are_values() -> None:
    assert Keys("a") == Keys("a")
    assert Keys("a") != Keys("b")
    with pytest.raises(AttributeError):
        Keys("a").run = "b"  # type: ignore[misc]


# --------------------------------------------------------------------------- robot_id_of

ROBOT_LEAVES: list[Callable[[Keys, int], str]] = [
    lambda k, r: k.robot(r),
    lambda k, r: k.image(r, "front"),
    lambda k, r: k.encoders(r),
    lambda k, r: k.cmd(r),
    lambda k, r: k.truth(r),
    lambda k, r: k.observation(r),
    lambda k, r: k.odometry(r),
    lambda k, r: k.correction(r),
    lambda k, r: k.robot_status(r),
]


@pytest.mark.parametrize("leaf", range(len(ROBOT_LEAVES)))
@pytest.mark.parametrize("rid", [0, 1, 7, 42, 100_000, 999_999])
def test_robot_id_of_parses_ids_back(k: Keys, leaf: int, rid: int) -> None:
    assert k.robot_id_of(ROBOT_LEAVES[leaf](k, rid)) == rid


@pytest.mark.parametrize(
    "key",
    [
        "tagswarm/run-2/robot/3/cmd",  # another run
        "tagswarm/run-10/robot/3/cmd",  # run id that merely starts with ours
        "tagswarm/run/robot/3/cmd",
        "other/run-1/robot/3/cmd",
        f"{P}/robot/abc/cmd",
        f"{P}/robot/-1/cmd",
        f"{P}/robot/1.5/cmd",
        f"{P}/robot/0x1/cmd",
        f"{P}/robot/ 1/cmd",
        f"{P}/robot//cmd",
        f"{P}/robot/",
        f"{P}/robot/1234567/cmd",  # more than 6 digits
        f"{P}/robot/*/cmd",
        f"{P}/robot/**",
        f"{P}/robot/$*/cmd",
        f"{P}/world/tick",
        f"{P}/server/map",
        f"{P}/alive/agent/3",
        f"{P}/robots/3/cmd",
        "",
    ],
)
def test_robot_id_of_rejects_other_keys(k: Keys, key: str) -> None:
    assert k.robot_id_of(key) is None


def test_robot_id_of_wildcard_keys_built_by_keys(k: Keys) -> None:
    for key in (k.cmd(), k.encoders(), k.images(), k.robot_status(), k.truth()):
        assert k.robot_id_of(key) is None, key


def test_robot_id_of_other_run_object() -> None:
    a, b = Keys("alpha"), Keys("beta")
    assert a.robot_id_of(b.cmd(2)) is None
    assert b.robot_id_of(b.cmd(2)) == 2


@pytest.mark.parametrize("chunk", ["\u00b2", "\u0661", "\uff11"])
def test_robot_id_of_rejects_non_ascii_digits(k: Keys, chunk: str) -> None:
    assert k.robot_id_of(f"{P}/robot/{chunk}/cmd") is None


# --------------------------------------------------------------------------- participant_of


@pytest.mark.parametrize("who", ["agent/0", "agent/12", "server/0", "render/3", "eval.tool/x-1", "a_b/c.d"])
def test_participant_of_ack_and_alive_keys(k: Keys, who: str) -> None:
    assert k.participant_of(k.ack(who)) == who
    assert k.participant_of(k.alive(who)) == who


@pytest.mark.parametrize(
    "key",
    [
        "tagswarm/run-2/world/ack/agent/0",
        "tagswarm/run-2/alive/agent/0",
        "tagswarm/run-10/alive/agent/0",
        f"{P}/world/ack/*/*",
        f"{P}/alive/**",
        f"{P}/alive/agent",
        f"{P}/alive/agent/0/extra",
        f"{P}/world/ack/agent",
        f"{P}/world/ack/agent/",
        f"{P}/alive//0",
        f"{P}/alive/ag ent/0",
        f"{P}/world/tick",
        f"{P}/robot/0/cmd",
        f"{P}/world/render/0",
        "",
    ],
)
def test_participant_of_rejects_other_keys(k: Keys, key: str) -> None:
    assert k.participant_of(key) is None


def test_participant_of_wildcards_built_by_keys(k: Keys) -> None:
    assert k.participant_of(k.acks()) is None
    assert k.participant_of(k.alive_all()) is None


# --------------------------------------------------------------------------- validation


@pytest.mark.parametrize("run", ["", "a/b", "a b", "*", "**", "$*", "run#1", "x" * 65, "ünïcode", "a\tb", "a?b"])
def test_invalid_run_ids(run: str) -> None:
    with pytest.raises(keys.KeyNameError) as exc:
        Keys(run)
    assert "run id" in str(exc.value)
    assert isinstance(exc.value, ValueError)


@pytest.mark.parametrize("run", ["a", "x" * 64, "default", "Run_2.b-3", "0", "..."])
def test_valid_run_ids(run: str) -> None:
    assert Keys(run).tick() == f"tagswarm/{run}/world/tick"


@pytest.mark.parametrize("camera", ["", "front/left", "*", "**", "a b", "cam$", "x" * 65, "caméra"])
def test_invalid_camera_names(k: Keys, camera: str) -> None:
    with pytest.raises(keys.KeyNameError) as exc:
        k.image(0, camera)
    assert "camera name" in str(exc.value)


@pytest.mark.parametrize(
    "participant",
    ["", "agent", "agent/0/1", "agent/", "/0", "ag ent/0", "agent/*", "*/0", "**", "agent/" + "9" * 65],
)
def test_invalid_participants(k: Keys, participant: str) -> None:
    with pytest.raises(keys.KeyNameError):
        k.ack(participant)
    with pytest.raises(keys.KeyNameError):
        k.alive(participant)
    with pytest.raises(keys.KeyNameError):
        keys.split_participant(participant)


def test_split_participant() -> None:
    assert keys.split_participant("agent/3") == ("agent", "3")
    assert keys.split_participant("render/worker.1") == ("render", "worker.1")


def test_check_name_returns_value_and_names_what() -> None:
    assert keys.check_name("front", "camera name") == "front"
    with pytest.raises(keys.KeyNameError) as exc:
        keys.check_name("a/b", "widget")
    assert str(exc.value).startswith("widget 'a/b'")


@pytest.mark.parametrize("bad", ["r1\n", "front\n"])
def test_trailing_newline_is_rejected(bad: str) -> None:
    with pytest.raises(keys.KeyNameError):
        Keys(bad)
    with pytest.raises(keys.KeyNameError):
        keys.check_name(bad, "camera name")


# --------------------------------------------------------------------------- run isolation


def _all_keys(k: Keys) -> set[str]:
    out = {k.tick(), k.acks(), k.world_status(), k.map(), k.server_status(), k.alive_all(), k.images()}
    for who in ("agent/0", "agent/1", "server/0", "render/0"):
        out |= {k.ack(who), k.alive(who)}
    out |= {k.render(w) for w in range(3)}
    for rid in (None, 0, 1, 17):
        out |= {k.encoders(rid), k.cmd(rid), k.truth(rid), k.observation(rid), k.odometry(rid), k.correction(rid),
                k.robot_status(rid), k.images(rid)}
        if rid is not None:
            out |= {k.robot(rid), k.image(rid, "front")}
    return out


run_ids = st.from_regex(r"[A-Za-z0-9_.-]{1,64}", fullmatch=True)


@settings(max_examples=200, deadline=None)
@given(run_ids, run_ids)
def test_two_runs_never_share_a_key(a: str, b: str) -> None:
    if a == b:
        return
    ka, kb = Keys(a), Keys(b)
    keys_a, keys_b = _all_keys(ka), _all_keys(kb)
    assert not keys_a & keys_b
    # and no key of one run falls under the other run's prefix or parses as the other run's
    assert not any(key.startswith(kb.prefix + "/") for key in keys_a)
    assert all(kb.robot_id_of(key) is None for key in keys_a)
    assert all(kb.participant_of(key) is None for key in keys_a)


def test_two_runs_concrete() -> None:
    ka, kb = Keys("run-1"), Keys("run-10")
    keys_a, keys_b = _all_keys(ka), _all_keys(kb)
    assert len(keys_a) == len(keys_b) > 40
    assert not keys_a & keys_b
    assert kb.robot_id_of(ka.cmd(3)) is None
    assert ka.robot_id_of(kb.cmd(3)) is None
