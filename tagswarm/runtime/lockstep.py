"""A participant's side of the lockstep clock (docs/architecture.md, "Clocks").

In lockstep the world hands out one step at a time and goes on only once every
participant has acknowledged it.  A participant takes each step's request (a
:class:`~tagswarm.protocol.messages.Tick`; for a render worker the world's
:class:`~tagswarm.protocol.messages.RenderPoses`), waits for that step's inputs, does
its work, publishes what it owes for the step, and only then acknowledges it with a
:class:`~tagswarm.protocol.messages.TickAck` on its own ack key.  Acknowledging after
the work is what makes a lockstep run repeat byte for byte: the world never runs ahead
of its slowest participant.

:class:`Participant` is that cycle, "accept step -> work -> ack", for every process that
takes part (server, agents, render workers, the MCAP recorder, test helpers); each brings
its own acceptance (run following, stale steps) and its own waiting and work.  Acks go
out with BLOCK congestion control (the bus's default): they must arrive.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Protocol, TypeVar

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.keys import Keys
from tagswarm.runtime.streams import Sequencer


class Step(Protocol):
    """What a step's request carries: the world's step number and its simulation time (ns)."""

    @property
    def step(self) -> int: ...

    @property
    def stamp_ns(self) -> int: ...


class Publisher(Protocol):
    """The part of :class:`tagswarm.protocol.bus.Bus` an ack needs."""

    def put(self, key: str, payload: bytes) -> None: ...


R = TypeVar("R", bound=Step)


class Participant:
    """Participant ``name`` (``agent/0``, ``server/0``, ``render/1``, ``record/0`` ...) of the
    lockstep of ``keys``' run.  ``seq`` numbers its acks (the node's own sequencer, so one
    publisher numbers every key it sends on the same way; a fresh one by default)."""

    def __init__(self, bus: Publisher, keys: Keys, name: str, seq: Sequencer | None = None) -> None:
        self.name = name
        self.key = keys.ack(name)
        self._bus = bus
        self._seq = seq if seq is not None else Sequencer()

    def ack(self, request: Step) -> None:
        """Acknowledge ``request``'s step: everything this participant owes for it is out."""
        self._bus.put(self.key, codec.encode(m.TickAck(seq=self._seq.next(self.key), stamp_ns=request.stamp_ns,
                                                       participant=self.name, step=request.step)))

    def serve(self, requests: Iterable[R], work: Callable[[R], bool],
              acked: Callable[[R], None] | None = None) -> int:
        """Accept -> work -> ack, one step at a time: ``requests`` yields the accepted steps in
        order (a generator is consumed lazily, so accepting a step may depend on the work done
        for the previous one); ``work(request)`` waits for the step's inputs and does it, and
        returns False to abandon the step (nothing of it is wanted any more: no ack);
        ``acked(request)`` runs after the ack (bookkeeping that must not hold the world up).
        Returns the number of steps acknowledged."""
        done = 0
        for request in requests:
            if not work(request):
                continue
            self.ack(request)
            done += 1
            if acked is not None:
                acked(request)
        return done
