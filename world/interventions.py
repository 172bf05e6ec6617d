"""Teleports and pushes waiting to be applied to the world (pure logic, no I/O).

Two sources feed one schedule: :class:`tagswarm.protocol.messages.WorldCommand` messages
(operator, tests; due at their ``stamp_ns``, 0 meaning "the next step") and the
scenario's ``[[events]]`` (due at ``at_s``, taken as the first tick ``k`` with
``k / tick_hz >= at_s``: a tick's ``stamp_ns`` is ``k`` times the rounded tick
length, so 30 ticks at 30 Hz are 0.99999999 s, and ``at_s = 1`` means tick 30).
The world applies every
intervention due at the first step whose simulation time is >= its due time, in
due-time order, then arrival order (scenario events first); so a command sent
ahead of its stamp lands on the same step in every lockstep run.
"""

from __future__ import annotations

import heapq
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Final, Literal

from tagswarm.protocol import messages as m
from tagswarm.protocol.geometry import wrap_angle
from tagswarm.protocol.scenario import Event

MAX_PENDING: Final = 1024
"""Interventions waiting at most; more are refused (a flood of far-future commands)."""


@dataclass(frozen=True, order=True)
class Intervention:
    """Move ``robot_id``: ``teleport`` to (x_m, y_m, yaw_rad) in the arena frame,
    or ``push`` by (x_m, y_m) in the arena frame and yaw_rad, from simulation time
    ``due_ns`` on.  ``source`` names it in logs (``"command"``, ``"events[2]"``)."""

    due_ns: int
    order: int
    robot_id: int = field(compare=False)
    action: Literal["teleport", "push"] = field(compare=False)
    x_m: float = field(compare=False)
    y_m: float = field(compare=False)
    yaw_rad: float = field(compare=False)
    source: str = field(compare=False)

    @property
    def from_event(self) -> bool:
        return self.source != "command"

    def target(self, x_m: float, y_m: float, yaw_rad: float) -> tuple[float, float, float]:
        """The pose (arena frame, m and rad) it puts a robot at that is now at (x_m, y_m, yaw_rad)."""
        if self.action == "teleport":
            return self.x_m, self.y_m, wrap_angle(self.yaw_rad)
        return x_m + self.x_m, y_m + self.y_m, wrap_angle(yaw_rad + self.yaw_rad)

    def describe(self) -> str:
        what = "to" if self.action == "teleport" else "by"
        return (f"{self.source}: {self.action} robot {self.robot_id} {what} ({self.x_m:.3f} m, {self.y_m:.3f} m, "
                f"{self.yaw_rad:.3f} rad)")


class Schedule:
    """Pending interventions, popped when due (see module docstring)."""

    def __init__(self, events: Sequence[Event], *, tick_hz: float, dt_ns: int) -> None:
        self._heap: list[Intervention] = []
        self._order = itertools.count()
        for i, ev in enumerate(events):
            step = max(0, math.ceil(ev.at_s * tick_hz - 1e-9))
            self._push(Intervention(due_ns=step * dt_ns, order=next(self._order),
                                    robot_id=ev.robot, action=ev.action, x_m=ev.x_m, y_m=ev.y_m,
                                    yaw_rad=ev.yaw_rad, source=f"events[{i}]"))

    def add(self, cmd: m.WorldCommand) -> bool:
        """Queue a world command; False (not queued) if :data:`MAX_PENDING` are waiting."""
        if len(self._heap) >= MAX_PENDING:
            return False
        self._push(Intervention(due_ns=cmd.stamp_ns, order=next(self._order), robot_id=cmd.robot_id,
                                action=cmd.action, x_m=cmd.x_m, y_m=cmd.y_m, yaw_rad=cmd.yaw_rad, source="command"))
        return True

    def _push(self, iv: Intervention) -> None:
        heapq.heappush(self._heap, iv)

    def pop_due(self, time_ns: int) -> list[Intervention]:
        """Every intervention due at or before ``time_ns``, in order."""
        out = []
        while self._heap and self._heap[0].due_ns <= time_ns:
            out.append(heapq.heappop(self._heap))
        return out

    def __len__(self) -> int:
        return len(self._heap)
