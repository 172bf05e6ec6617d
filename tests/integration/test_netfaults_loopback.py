"""Fault injection through real Zenoh sessions on loopback: a lossy, late subscriber
next to a clean one, the clock untouched, the loss pattern the same on every run, and
odometry lost by default while the acks sent after it all arrive, never before it."""

from __future__ import annotations

import math
import time

from tagswarm.protocol.bus import Bus, BusConfig, Inbox, open_bus
from tagswarm.protocol.keys import Keys
from tagswarm.protocol.netfaults import NetFaults
from tests.harness import endpoint

N = 600
LOSS = 0.3
KEYS = Keys("faults")


def receive_all(bus: Bus, inbox: Inbox[bytes], n: int) -> list[int]:
    """Sequence numbers received until ``n`` were received or dropped."""
    got: list[int] = []

    def done() -> bool:
        got.extend(int(item.value) for item in inbox.drain())
        return len(got) + inbox.fault_dropped >= n

    assert bus.wait_for(done, 30), (len(got), inbox.fault_dropped)
    return got


def until_linked(pub: Bus, sub: Bus, key: str) -> Inbox[bytes]:
    """Publish on ``key`` (not a fault key) until ``sub`` hears it: from then on its subscriptions
    are known to the publisher.  Returns that inbox (holding the probes)."""
    probe = sub.subscribe(key)
    for _ in range(100):
        pub.put(key, b"0")
        if sub.wait_for(lambda: len(probe) > 0, 0.1):
            break
    return probe


def lossy_run(seed: int) -> tuple[list[int], list[int], int]:
    """Publish N observations and N ticks; return what a lossy subscriber (seed ``seed``)
    received of each, and how many observations a clean subscriber received."""
    ep = endpoint()
    lossy = BusConfig(connect=(ep,), loss=LOSS, fault_seed=seed)
    with open_bus(BusConfig(listen=(ep,))) as pub, open_bus(lossy) as sub, open_bus(BusConfig(connect=(ep,))) as clean:
        obs, tick = sub.subscribe(KEYS.observation()), sub.subscribe(KEYS.tick())
        ref = clean.subscribe(KEYS.observation())
        until_linked(pub, sub, KEYS.robot_status(1))
        for i in range(N):
            pub.put(KEYS.observation(1), str(i).encode())
            pub.put(KEYS.tick(), str(i).encode())
        got_obs = receive_all(sub, obs, N)
        got_tick = receive_all(sub, tick, N)
        clean_obs = receive_all(clean, ref, N)
        assert sub.fault_stats()["net_dropped"] == obs.fault_dropped == N - len(got_obs)
        assert tick.fault_dropped == 0
        return got_obs, got_tick, len(clean_obs)


def test_loss_applies_to_observations_only_and_repeats_with_the_seed() -> None:
    obs, ticks, clean = lossy_run(seed=11)
    assert ticks == list(range(N))  # the clock is never impaired by default
    assert clean == N  # faults belong to one subscriber, not to the network
    lost = N - len(obs)
    assert abs(lost - N * LOSS) <= 5 * math.sqrt(N * LOSS * (1 - LOSS)), lost
    assert obs == sorted(obs)
    again, _, _ = lossy_run(seed=11)
    assert again == obs  # same seed, same pattern, on a new network
    other, _, _ = lossy_run(seed=12)
    assert other != obs


def test_delay_holds_matching_samples_but_not_the_clock() -> None:
    ep = endpoint()
    delay_ms = 1000.0  # long enough that "still held when the tick is here" cannot race on a busy machine
    late = BusConfig(connect=(ep,), delay_ms=delay_ms, fault_keys=(KEYS.correction(),))  # not a default key
    with open_bus(BusConfig(listen=(ep,))) as pub, open_bus(late) as sub:
        corr, tick = sub.subscribe(KEYS.correction(2)), sub.subscribe(KEYS.tick())
        for _ in range(100):
            pub.put(KEYS.tick(), b"-1")
            if sub.wait_for(lambda: len(tick) > 0, 0.1):
                break
        tick.drain()
        sent = time.monotonic()
        for i in range(10):
            pub.put(KEYS.correction(2), str(i).encode())
        pub.put(KEYS.tick(), b"0")
        assert sub.wait_for(lambda: len(tick) > 0, 10)
        assert len(corr) == 0  # the tick, sent after them, is already here: the corrections are held
        got = receive_all(sub, corr, 10)
        assert time.monotonic() - sent >= delay_ms / 1000  # never early (no upper bound: noisy machine)
        assert got == list(range(10))
        assert sub.fault_stats() == {"net_dropped": 0, "net_delayed": 10}


def test_odometry_is_lost_by_default_and_never_overtakes_the_ack_sent_after_it() -> None:
    """What a lockstep server relies on to stop waiting for a lost odometry message: an agent's
    odometry of a tick goes out before its ack of that tick on one session, acks are never
    impaired, and an odometry message that is not lost is in its inbox by the time the ack is in
    its own (drained acks first, then odometry)."""
    ep = endpoint()
    lossy = BusConfig(connect=(ep,), loss=LOSS, fault_seed=5)
    with open_bus(BusConfig(listen=(ep,))) as agent, open_bus(lossy) as server:
        odom, acks = server.subscribe(KEYS.odometry()), server.subscribe(KEYS.ack("agent/1"))
        until_linked(agent, server, KEYS.robot_status(1))
        for i in range(N):
            agent.put(KEYS.odometry(1), str(i).encode())
            agent.put(KEYS.ack("agent/1"), str(i).encode())
        # the seeded pattern the server's injector follows (protocol/netfaults.py), replayed here
        pattern = NetFaults(loss=LOSS, delay_s=0.0, seed=5, matches=lambda key: True)
        dropped = {i for i in range(N) if not pattern.admit(KEYS.odometry(), KEYS.odometry(1))}
        got_odom: set[int] = set()
        got_acks: list[int] = []

        def done() -> bool:
            new_acks = [int(item.value) for item in acks.drain()]  # acks first ...
            got_odom.update(int(item.value) for item in odom.drain())  # ... then what was sent before them
            for i in new_acks:  # the odometry message sent before this ack is here already, or lost for good
                assert (i in got_odom) != (i in dropped), i
            got_acks.extend(new_acks)
            return len(got_acks) >= N and len(got_odom) + odom.fault_dropped >= N

        assert server.wait_for(done, 30), (len(got_acks), len(got_odom), odom.fault_dropped)
        assert got_acks == list(range(N))  # the clock is never impaired by default
        assert got_odom == set(range(N)) - dropped
        lost = N - len(got_odom)
        assert lost == odom.fault_dropped == server.fault_stats()["net_dropped"]
        assert abs(lost - N * LOSS) <= 5 * math.sqrt(N * LOSS * (1 - LOSS)), lost
