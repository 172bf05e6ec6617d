"""Receive-side fault injection (protocol/netfaults.py) and its configuration (flags,
environment, validation).  No Zenoh session: the injector is pure logic; the real
bus path is in tests/integration/test_netfaults_loopback.py."""

from __future__ import annotations

import functools
import math
import threading
import time

import pytest

from tagswarm.deploy import router
from tagswarm.protocol.bus import BusConfig, BusError, default_fault_keys, key_matches, net_faults
from tagswarm.protocol.keys import Keys
from tagswarm.protocol.netfaults import NetFaults
from tagswarm.runtime.config import ConfigError
from tagswarm.world.config import build_config

N = 4000


def binomial_ok(lost: int, n: int, p: float, z: float = 5.0) -> bool:
    """``lost`` of ``n`` is within z standard deviations of a Binomial(n, p) mean."""
    return abs(lost - n * p) <= z * math.sqrt(n * p * (1 - p))


def pattern(faults: NetFaults, sub: str, key: str, n: int) -> list[bool]:
    return [faults.admit(sub, key) for _ in range(n)]


def everything(key: str) -> bool:
    return True


# --------------------------------------------------------------------------- loss


@pytest.mark.parametrize("loss", [0.05, 0.3, 0.9])
def test_the_lost_share_is_within_binomial_bounds(loss: float) -> None:
    f = NetFaults(loss=loss, delay_s=0.0, seed=7, matches=everything)
    admitted = pattern(f, "a/*", "a/b", N)
    lost = admitted.count(False)
    assert f.dropped == lost
    assert binomial_ok(lost, N, loss), (lost, N * loss)


def test_no_loss_and_full_loss_are_exact() -> None:
    assert all(pattern(NetFaults(loss=0.0, delay_s=0.0, seed=1, matches=everything), "a", "a", 500))
    assert not any(pattern(NetFaults(loss=1.0, delay_s=0.0, seed=1, matches=everything), "a", "a", 500))


def test_the_pattern_is_reproducible_per_seed_and_independent_of_interleaving() -> None:
    a = NetFaults(loss=0.3, delay_s=0.0, seed=3, matches=everything)
    b = NetFaults(loss=0.3, delay_s=0.0, seed=3, matches=everything)
    # a sees the two keys interleaved, b one after the other: each key's pattern is the same
    inter = [(k, a.admit("r/*", k)) for _ in range(200) for k in ("r/1", "r/2")]
    seq = {k: pattern(b, "r/*", k, 200) for k in ("r/1", "r/2")}
    for k in ("r/1", "r/2"):
        assert [ok for key, ok in inter if key == k] == seq[k]
    assert seq["r/1"] != seq["r/2"]  # keys have their own streams
    other = NetFaults(loss=0.3, delay_s=0.0, seed=4, matches=everything)
    assert pattern(other, "r/*", "r/1", 200) != seq["r/1"]


def test_the_pattern_does_not_depend_on_the_run_id() -> None:
    """``tagswarm up`` names each run differently: the same seed must still lose the same messages."""
    a, b = (NetFaults(loss=0.3, delay_s=0.0, seed=5, matches=everything) for _ in range(2))
    ka, kb = Keys("up123"), Keys("up456")
    assert pattern(a, ka.cmd(), ka.cmd(1), 300) == pattern(b, kb.cmd(), kb.cmd(1), 300)


def test_only_matching_keys_are_impaired() -> None:
    f = NetFaults(loss=1.0, delay_s=0.0, seed=0, matches=lambda key: key.endswith("/obs"))
    assert not f.admit("x/**", "x/1/obs")
    assert f.admit("x/**", "x/tick")
    assert f.dropped == 1


# --------------------------------------------------------------------------- delay


def test_delay_holds_each_sample_at_least_the_delay_and_keeps_order() -> None:
    delay_s = 0.05
    f = NetFaults(loss=0.0, delay_s=delay_s, seed=0, matches=lambda key: key != "now")
    got: list[tuple[int, float]] = []
    done = threading.Event()
    sent: dict[int, float] = {}

    def arrive(i: int) -> None:
        got.append((i, time.monotonic()))
        if i == 19:
            done.set()

    try:
        for i in range(20):
            sent[i] = time.monotonic()
            f.hold("late", functools.partial(arrive, i))
        f.hold("now", lambda: arrive(-1))
        assert got and got[0][0] == -1  # not held: delivered at once, before any delayed one
        assert done.wait(10), got
        assert [i for i, _ in got[1:]] == list(range(20))
        assert all(t - sent[i] >= delay_s for i, t in got[1:])  # never early (no upper bound: noisy machine)
        assert f.delayed == 20
    finally:
        f.close()


class _Line:
    """Stands in for the delay line: records each sample's due time."""

    def __init__(self) -> None:
        self.dues: list[float] = []

    def push(self, due: float, _deliver: object) -> None:
        self.dues.append(due)

    def close(self) -> None:
        pass


def _jittered_dues(seed: int, key: str, n: int, monkeypatch: pytest.MonkeyPatch) -> tuple[list[float], list[float]]:
    """Delays (s after the sample arrived) and due times of ``n`` samples on ``key`` arriving 1 ms apart."""
    clock = iter(k * 0.001 for k in range(n))
    monkeypatch.setattr("tagswarm.protocol.netfaults.time.monotonic", lambda: next(clock))
    f = NetFaults(loss=0.0, delay_s=0.020, jitter_s=0.005, seed=seed, matches=everything)
    line = f._line = _Line()  # type: ignore[assignment]
    for _ in range(n):
        f.hold(key, lambda: None)
    return [due - k * 0.001 for k, due in enumerate(line.dues)], line.dues


def test_jitter_spreads_the_delay_keeps_each_keys_order_and_repeats_per_seed(monkeypatch: pytest.MonkeyPatch) -> None:
    late, dues = _jittered_dues(4, "tagswarm/r1/robot/1/encoders", 400, monkeypatch)
    assert dues == sorted(dues)  # never overtakes a sample of its key that arrived earlier
    assert 0.015 - 1e-9 <= min(late) and max(late) <= 0.025 + 0.002  # delay ± jitter (+ order hold-back)
    assert max(late) - min(late) > 0.008  # really spread, not a fixed delay
    assert dues == _jittered_dues(4, "tagswarm/r2/robot/1/encoders", 400, monkeypatch)[1]  # seeded, run id left out
    assert dues != _jittered_dues(5, "tagswarm/r1/robot/1/encoders", 400, monkeypatch)[1]
    with pytest.raises(ValueError, match="jitter"):
        NetFaults(loss=0.0, delay_s=0.01, jitter_s=0.02, seed=0, matches=everything)


def test_close_discards_what_is_still_held() -> None:
    f = NetFaults(loss=0.0, delay_s=30.0, seed=0, matches=everything)
    got: list[int] = []
    f.hold("k", lambda: got.append(1))
    f.close()
    assert got == [] and f.delayed == 1


def test_bad_parameters_are_refused() -> None:
    for loss in (-0.1, 1.5, math.nan):
        with pytest.raises(ValueError, match="loss"):
            NetFaults(loss=loss, delay_s=0.0, seed=0, matches=everything)
    with pytest.raises(ValueError, match="delay"):
        NetFaults(loss=0.0, delay_s=-1.0, seed=0, matches=everything)
    with pytest.raises(BusError, match="key expression"):
        net_faults(BusConfig(loss=0.1, fault_keys=("a//b",)))


# --------------------------------------------------------------------------- default keys


def test_default_keys_spare_the_clock_its_sync_points_images_truth_and_statuses() -> None:
    k = Keys("any-run")
    defaults = default_fault_keys()

    def faulty(key: str) -> bool:
        return any(key_matches(p, key) for p in defaults)

    # odometry too: a lockstep server learns of a lost one from the agent's ack and does not wait for it
    for key in (k.encoders(2), k.cmd(0), k.goal(1), k.observation(3), k.odometry(0), k.odometry(12), k.map()):
        assert faulty(key), key
    # the clock (acks included: the server relies on them to tell a lost odometry message from a late one),
    # and the corrections a lockstep agent waits for, are spared
    for key in (k.tick(), k.ack("agent/1"), k.ack("server/0"), k.ack("render/0"), k.render(0), k.image(1, "front"),
                k.truth(1), k.correction(5), k.robot_status(1), k.world_status(), k.server_status(),
                k.alive("agent/1")):
        assert not faulty(key), key
    f = net_faults(BusConfig(loss=0.5))
    assert f.matches(k.observation()) and f.matches(k.odometry())
    assert not f.matches(k.images()) and not f.matches(k.tick()) and not f.matches(k.acks())


# --------------------------------------------------------------------------- flags and environment


def test_flags_and_environment_reach_the_bus_config() -> None:
    c = build_config(["--net-loss", "0.25", "--net-delay-ms", "40", "--net-fault-keys", "tagswarm/*/robot/1/*",
                      "--net-fault-keys", "tagswarm/*/server/map", "--net-seed", "9"], {})
    assert (c.bus.loss, c.bus.delay_ms, c.bus.fault_seed) == (0.25, 40.0, 9)
    assert c.bus.fault_keys == ("tagswarm/*/robot/1/*", "tagswarm/*/server/map")
    env = {"TAGSWARM_NET_LOSS": "0.1", "TAGSWARM_NET_DELAY_MS": "5", "TAGSWARM_NET_SEED": "2",
           "TAGSWARM_NET_FAULT_KEYS": "a/**, b/*"}
    c = build_config([], env)
    assert (c.bus.loss, c.bus.delay_ms, c.bus.fault_seed, c.bus.fault_keys) == (0.1, 5.0, 2, ("a/**", "b/*"))
    assert build_config(["--net-loss", "0.3"], env).bus.loss == 0.3  # flag beats environment
    d = build_config([], {}).bus
    assert (d.loss, d.delay_ms, d.fault_keys, d.fault_seed) == (0.0, 0.0, (), 0)
    assert build_config(["--net-delay-ms", "20", "--net-jitter-ms", "5"], {}).bus.jitter_ms == 5.0
    assert build_config([], {"TAGSWARM_NET_DELAY_MS": "20", "TAGSWARM_NET_JITTER_MS": "5"}).bus.jitter_ms == 5.0


@pytest.mark.parametrize("argv,env,flag", [
    (["--net-loss", "1.5"], {}, "--net-loss"),
    (["--net-loss", "-0.1"], {}, "--net-loss"),
    ([], {"TAGSWARM_NET_LOSS": "lots"}, "--net-loss"),
    (["--net-loss", "nan"], {}, "--net-loss"),
    (["--net-delay-ms", "-3"], {}, "--net-delay-ms"),
    (["--net-delay-ms", "1e9"], {}, "--net-delay-ms"),
    (["--net-delay-ms", "10", "--net-jitter-ms", "15"], {}, "--net-jitter-ms"),
    (["--net-jitter-ms", "-1"], {}, "--net-jitter-ms"),
    (["--net-fault-keys", "a//b"], {}, "--net-fault-keys"),
    (["--net-seed", "x"], {}, "--net-seed"),
])
def test_bad_fault_settings_are_one_line_config_errors(argv: list[str], env: dict[str, str], flag: str) -> None:
    with pytest.raises(ConfigError) as info:
        build_config(argv, env)
    text = str(info.value)
    assert text.startswith(flag) and "\n" not in text


def test_bad_loss_exits_2_with_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    assert router.main(["--net-loss", "2", "--listen", "tcp/127.0.0.1:0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("tagswarm router: error: --net-loss 2: must be a share"), err
