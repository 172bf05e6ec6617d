"""The live view's recent events: the server's re-localisations and kidnaps (world
commands), for :class:`tagswarm.view.state.ViewState`.  Pure code.

Positions are in the MAP frame (metres, radians): a re-localisation carries its
own map-frame poses; a teleport's target arrives in the ARENA frame and is
converted with T_map_arena; a push is placed at the robot's true pose when it
arrived.  Times are nanoseconds of simulation time.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any, Final

from tagswarm.protocol import messages as m
from tagswarm.protocol.geometry import Pose2, se2_compose

#: Events kept for the page's list (the newest ones).
EVENTS_KEPT: Final = 20
#: The page draws an event's marker at the robot while it is younger than this (simulation time).
MARKER_TTL_S: Final = 3.0


def _num(x: float, digits: int = 6) -> float | None:
    return round(x, digits) if math.isfinite(x) else None


class EventLog:
    """The newest :data:`EVENTS_KEPT` events and how many of each kind there were."""

    def __init__(self) -> None:
        self.events: deque[dict[str, Any]] = deque(maxlen=EVENTS_KEPT)
        self.relocalisations = 0
        self.kidnaps = 0

    def relocalisation(self, r: m.Relocalisation) -> None:
        self.relocalisations += 1
        self.events.append({
            "kind": "relocalisation", "robot": r.robot_id, "stamp_ns": r.stamp_ns, "jump_m": _num(r.jump_m, 4),
            "evidence": r.evidence, "observers": list(r.observers),
            "from": [_num(r.from_x_m), _num(r.from_y_m)],
            "at": [_num(r.to_x_m), _num(r.to_y_m), _num(r.to_yaw_rad)],
        })

    def kidnap(self, c: m.WorldCommand, stamp_ns: int, a2m: Pose2, truth: Pose2 | None) -> None:
        """A world command stamped ``stamp_ns``; ``a2m`` is T_map_arena, ``truth`` the
        robot's true map-frame pose when it arrived (None if unknown)."""
        self.kidnaps += 1
        if c.action == "teleport":
            at: Pose2 | None = se2_compose(a2m, (c.x_m, c.y_m, c.yaw_rad))
        else:
            at = truth
        self.events.append({
            "kind": "kidnap", "robot": c.robot_id, "stamp_ns": stamp_ns, "action": c.action,
            "at": None if at is None else [_num(v) for v in at],
        })

    def to_json(self, now_ns: int) -> list[dict[str, Any]]:
        """The kept events, newest first, each with its ``age_s`` at ``now_ns``."""
        return [{**e, "age_s": _num(max(now_ns - e["stamp_ns"], 0) / 1e9, 3)} for e in reversed(self.events)]
