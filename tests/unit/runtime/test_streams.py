"""tagswarm.runtime.streams: reject counts per kind (logged once each), sequence gaps per
sender, and the world run a node follows (no network)."""

from __future__ import annotations

import logging
import math

import msgspec
import pytest

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import Received
from tagswarm.runtime import streams
from tests.unit.protocol.test_codec import BY_TYPE


def test_reject_counter_counts_per_kind_and_logs_once_per_kind(caplog: pytest.LogCaptureFixture) -> None:
    logger = logging.getLogger("tests.unit.streams.rejects")
    counter = streams.RejectCounter(logger)
    with caplog.at_level(logging.WARNING, logger=logger.name):
        for i in range(3):
            counter.reject("malformed", f"garbage #{i}")
        counter.reject("non_finite", "nan in x_m")
        counter.reject("malformed", "garbage #3")
        counter.reject("spoofed", "robot 2 on robot 1's key")
    records = [r for r in caplog.records if r.name == logger.name]
    assert len(records) == 3
    assert all(r.levelno == logging.WARNING for r in records)
    messages = [r.getMessage() for r in records]
    assert "malformed" in messages[0] and "garbage #0" in messages[0]
    assert "non_finite" in messages[1] and "nan in x_m" in messages[1]
    assert "spoofed" in messages[2]
    assert not any("garbage #1" in msg or "garbage #3" in msg for msg in messages)
    assert counter.counts == {"malformed": 4, "non_finite": 1, "spoofed": 1}
    assert counter.total() == 6
    assert counter.as_counters() == {"rejected_malformed": 4, "rejected_non_finite": 1, "rejected_spoofed": 1}
    assert list(counter.as_counters("bad.")) == ["bad.malformed", "bad.non_finite", "bad.spoofed"]


def test_reject_counter_defaults_to_its_module_logger(caplog: pytest.LogCaptureFixture) -> None:
    counter = streams.RejectCounter()
    assert counter.total() == 0
    assert counter.as_counters() == {}
    with caplog.at_level(logging.WARNING, logger="tagswarm.runtime.streams"):
        counter.reject("oversized", "9 MB")
        counter.reject("oversized", "10 MB")
    records = [r for r in caplog.records if r.name == "tagswarm.runtime.streams"]
    assert [r.getMessage().count("oversized") for r in records] == [1]
    assert counter.counts["oversized"] == 2


def test_reject_counter_with_real_decode_errors() -> None:
    counter = streams.RejectCounter(logging.getLogger("tests.unit.streams.real"))
    payloads = [b"\xc1", codec.encode(msgspec.structs.replace(BY_TYPE[m.WheelCommand], left_rad_s=math.nan)),
                codec.encode(BY_TYPE[m.WheelCommand]), b"\x00" * (codec.MAX_BYTES[m.WheelCommand] + 1)]
    ok = 0
    for p in payloads:
        try:
            codec.decode(m.WheelCommand, p)
            ok += 1
        except codec.DecodeError as exc:
            counter.reject(exc.kind, exc.detail)
    assert ok == 1
    assert counter.counts == {"malformed": 1, "non_finite": 1, "oversized": 1}


def test_reject_counter_decoded_yields_good_and_counts_bad() -> None:
    good = BY_TYPE[m.TickAck]
    items = [Received("k/1", codec.encode(good)), Received("k/2", b"\xff\x00"), Received("k/3", b"\xc1")]
    rc = streams.RejectCounter()
    out = list(rc.decoded(items, m.TickAck))
    assert [(it.key, msg) for it, msg in out] == [("k/1", good)]
    assert rc.total() == 2 and rc.counts["malformed"] == 2


def test_gap_counter_counts_lost_messages_per_label_and_survives_restarts() -> None:
    g = streams.GapCounter()
    assert [g.seen("k/1", s, "robot1") for s in (0, 1, 2, 5, 6, 9)] == [0, 0, 0, 2, 0, 2]
    assert g.seen("k/2", 7, "robot2") == 0  # the first number seen is no gap
    assert g.seen("k/2", 9, "robot2") == 1
    assert g.seen("k/1", 0, "robot1") == 0  # a restarted publisher begins again
    assert g.seen("k/1", 3, "robot1") == 2
    assert g.as_counters() == {"seq_gaps_robot1": 6, "seq_gaps_robot2": 1}


def test_run_follower_follows_one_world_and_accepts_a_new_one_only_after_it_left() -> None:
    f = streams.RunFollower()
    assert f.accept("a") == "first" and f.accept("a") == "same"
    assert f.accept("b") == "foreign" and f.run_id == "a"  # the world is still alive: a forged tick
    f.world_presence(True)
    assert f.accept("b") == "foreign"
    f.world_presence(False)
    assert f.accept("b") == "restart" and f.run_id == "b"
    assert f.accept("c") == "foreign"  # the new world is alive again (no departure since)
    # the same world cut off and back (a partition, a router restart): followed again, not left for good
    f.world_presence(False)
    assert f.world_left and f.accept("b") == "same" and f.world_left  # its token is still gone
    f.world_presence(True)
    assert f.accept("b") == "same" and not f.world_left
    assert f.accept("d") == "foreign"
