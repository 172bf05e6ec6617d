"""The Zenoh encoding on real samples over loopback: a plain zenoh session (what a client in
another language sees) receives every message the Bus publishes with
``application/msgpack;<MessageType>``, the same key switching type carries each payload's
own, a non-message payload goes out as ``zenoh/bytes``, and the reply to a query (the
server's map queryable) carries the encoding too."""

from __future__ import annotations

import json
import queue
import threading
import time

import zenoh

from tagswarm.protocol import codec, wire
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import BusConfig, open_bus
from tagswarm.protocol.keys import Keys
from tests.harness import endpoint
from tests.unit.protocol.test_codec_fuzz import EXAMPLES

KEYS = Keys("enc")


def _plain_session(ep: str) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps([ep]))
    return zenoh.open(conf)


def test_a_plain_zenoh_subscriber_sees_each_message_types_encoding() -> None:
    ep = endpoint()
    got: queue.Queue[tuple[str, str, bytes]] = queue.Queue()
    with open_bus(BusConfig(listen=(ep,))) as bus, _plain_session(ep) as plain:
        plain.declare_subscriber(f"{KEYS.prefix}/**",
                                 lambda s: got.put((str(s.key_expr), str(s.encoding), s.payload.to_bytes())))
        probe = KEYS.world_status()
        linked = threading.Event()
        for _ in range(100):  # until the subscription is known to the publisher
            bus.put(probe, codec.encode(EXAMPLES[m.AgentStatus]))
            try:
                got.get(timeout=0.1)
                linked.set()
                break
            except queue.Empty:
                pass
        assert linked.is_set(), "the plain session never heard the bus"
        while not got.empty():
            got.get_nowait()
        sent: list[tuple[str, str, bytes]] = []
        for i, cls in enumerate(wire.MESSAGE_TYPES):
            payload = codec.encode(EXAMPLES[cls])
            sent.append((KEYS.robot_status(i), wire.encoding_of(cls), payload))
        mixed = KEYS.goal(99)  # one key, several payload kinds in a row
        for payload, enc in ((codec.encode(EXAMPLES[m.Goal]), "application/msgpack;Goal"),
                             (codec.encode(EXAMPLES[m.Tick]), "application/msgpack;Tick"),
                             (b"\xc1 not msgpack", "zenoh/bytes"),
                             (codec.encode(EXAMPLES[m.Goal]), "application/msgpack;Goal")):
            sent.append((mixed, enc, payload))
        dropping = [x for x in sent if x[0].endswith("/0/status")]  # one DROP publisher too
        for key, enc, payload in sent:
            bus.put(key, payload, drop=(key, enc, payload) in dropping)
        received = [got.get(timeout=10) for _ in sent[len(dropping):]]
        # a DROP publisher may drop under congestion (a burst of BLOCK samples beside it, a loaded CI
        # machine: lost there once): what is checked is its encoding, so it is put again until it arrives
        deadline = time.monotonic() + 10.0
        while len(received) < len(sent) and time.monotonic() < deadline:
            try:
                received.append(got.get(timeout=0.5))
            except queue.Empty:
                for key, _, payload in dropping:
                    if not any(r[0] == key for r in received):
                        bus.put(key, payload, drop=True)
        assert sorted(received) == sorted(sent)  # the DROP (not express) sample may come later
        assert [r for r in received if r[0] == mixed] == [s for s in sent if s[0] == mixed]


def test_the_reply_to_a_query_carries_the_encoding() -> None:
    ep = endpoint()
    payload = codec.encode(EXAMPLES[m.GlobalMap])
    with open_bus(BusConfig(listen=(ep,))) as bus, _plain_session(ep) as plain:
        queries = bus.queryable(KEYS.map())
        stop = threading.Event()

        def answer() -> None:
            while not stop.is_set():
                bus.wait_for(lambda: len(queries) > 0 or stop.is_set(), 0.2)
                for q in queries.drain():
                    bus.reply(q.value, KEYS.map(), payload)

        t = threading.Thread(target=answer, daemon=True)
        t.start()
        try:
            replies = []
            # A get that no known queryable matches returns at once, so a count of tries
            # is no wait at all on a loaded machine: wait by the clock until the plain
            # session has learnt of the queryable.
            deadline = time.monotonic() + 30.0
            while not replies and time.monotonic() < deadline:
                replies = [r.ok for r in plain.get(KEYS.map(), timeout=1.0) if r.ok is not None]
                if not replies:
                    stop.wait(0.05)
        finally:
            stop.set()
            t.join(timeout=5)
        assert [(str(r.encoding), r.payload.to_bytes()) for r in replies] == [
            ("application/msgpack;GlobalMap", payload)]
