"""tagswarm.runtime.lockstep.Participant: accept -> work -> ack, in order, with the acks on the
participant's own key and numbered per key (no network: a recording publisher)."""

from __future__ import annotations

from collections.abc import Iterator

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.keys import Keys
from tagswarm.runtime.lockstep import Participant
from tagswarm.runtime.streams import Sequencer

KEYS = Keys("t")


class Wire:
    """Records every put, and the order of events around them."""

    def __init__(self) -> None:
        self.events: list[str] = []
        self.acks: list[m.TickAck] = []

    def put(self, key: str, payload: bytes) -> None:
        assert key == KEYS.ack("agent/2")
        ack = codec.decode(m.TickAck, payload)
        self.acks.append(ack)
        self.events.append(f"ack {ack.step}")


def _tick(step: int) -> m.Tick:
    return m.Tick(seq=step, step=step, stamp_ns=step * 100, dt_ns=100, run_id="r", mode="lockstep")


def test_each_step_is_worked_then_acked_and_abandoned_steps_are_not() -> None:
    wire = Wire()
    p = Participant(wire, KEYS, "agent/2")

    def work(t: m.Tick) -> bool:
        wire.events.append(f"work {t.step}")
        return t.step != 2  # step 2 abandoned

    done = p.serve([_tick(1), _tick(2), _tick(3)], work, acked=lambda t: wire.events.append(f"after {t.step}"))
    assert done == 2
    assert wire.events == ["work 1", "ack 1", "after 1", "work 2", "work 3", "ack 3", "after 3"]
    assert [(a.seq, a.step, a.stamp_ns, a.participant) for a in wire.acks] == [(0, 1, 100, "agent/2"),
                                                                              (1, 3, 300, "agent/2")]


def test_acceptance_is_lazy_so_it_sees_the_previous_steps_work() -> None:
    wire = Wire()
    p = Participant(wire, KEYS, "agent/2")
    last: list[int] = []

    def accepted() -> Iterator[m.Tick]:
        for t in (_tick(4), _tick(4), _tick(5)):  # a repeated step must not be acted on twice
            wire.events.append(f"accept {t.step}")
            if not last or t.step > last[-1]:
                yield t

    def work(t: m.Tick) -> bool:
        last.append(t.step)
        return True

    assert p.serve(accepted(), work) == 2
    assert wire.events == ["accept 4", "ack 4", "accept 4", "accept 5", "ack 5"]


def test_acks_share_the_nodes_sequencer_per_key() -> None:
    wire = Wire()
    seq = Sequencer()
    seq.next("other/key")
    key = KEYS.ack("agent/2")
    seq.next(key)  # the node already sent one ack on this key
    p = Participant(wire, KEYS, "agent/2", seq)
    p.ack(_tick(7))
    p.ack(m.RenderPoses(seq=0, step=8, stamp_ns=800, robot_ids=(), poses=(), cameras=()))
    assert [(a.seq, a.step) for a in wire.acks] == [(1, 7), (2, 8)]
    assert seq.peek(key) == 3 and seq.peek("other/key") == 1
