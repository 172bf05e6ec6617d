"""Inbox: which arrivals wake the owner's loop (protocol/inbox.py)."""

from __future__ import annotations

import threading

from tagswarm.protocol.bus import Inbox


class CountingCondition(threading.Condition):
    def __init__(self) -> None:
        super().__init__()
        self.notified = 0

    def notify_all(self) -> None:
        self.notified += 1
        super().notify_all()


def test_an_inbox_wakes_the_loop_on_every_arrival_by_default() -> None:
    cond = CountingCondition()
    inbox: Inbox[bytes] = Inbox(cond, newest_only=False, capacity=8)
    inbox.put("k", b"a")
    inbox.put("k", b"b")
    assert cond.notified == 2
    assert [r.value for r in inbox.drain()] == [b"a", b"b"]


def test_a_quiet_inbox_keeps_its_items_without_waking() -> None:
    cond = CountingCondition()
    quiet: Inbox[bytes] = Inbox(cond, newest_only=False, capacity=8, wakes=False)
    newest: Inbox[bytes] = Inbox(cond, newest_only=True, capacity=8, wakes=False)
    for v in (b"a", b"b", b"c"):
        quiet.put("k", v)
        newest.put("k", v)
    assert cond.notified == 0
    assert [r.value for r in quiet.drain()] == [b"a", b"b", b"c"]
    assert [r.value for r in newest.drain()] == [b"c"]
    assert (quiet.received, newest.received) == (3, 3)
