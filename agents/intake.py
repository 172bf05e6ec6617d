"""What one robot's agent takes in, checked before it reaches odometry, vision or behaviour.

Pure code over items drained from the node's inboxes (:mod:`tagswarm.agents.node` does
the I/O).  Malformed payloads, messages for another robot than the one of this agent
(``spoofed``) and encoder counts of another resolution (``inconsistent``) are dropped and
counted by the :class:`~tagswarm.runtime.streams.RejectCounter`.  Encoder counts and
camera frames stamped before the newest one taken (simulation ns), or after ``upto_ns``
when a new world run starts, belong to another run of the world: dropped and counted in
``stale_encoders`` / ``stale_frames``.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Iterator
from typing import Any, TypeVar

from tagswarm.protocol import messages as m
from tagswarm.protocol.geometry import worst_axis_sigma_m
from tagswarm.protocol.inbox import Received
from tagswarm.runtime import streams

M = TypeVar("M", m.Correction, m.Goal, m.WheelCommand)
# the server's clock never runs ahead of our odometry by more than its watermark slack (1 s, server/node.py)
CORRECTION_AHEAD_NS = 1_000_000_000


def sigma_lapsed(c: m.Correction, claim_sigma_m: float) -> bool:
    """Whether the server does not vouch for ``c`` because its position σ grew to ``claim_sigma_m``
    (the robot drove out of everyone's view): the agent then drives on the map's newest estimate,
    slowly.  A correction unvouched with a small σ is a dispute (its latest views put it elsewhere):
    a robot vouched for before drives on as it was, since moving gives the views that settle it
    (measured: a yard of 10, a patrol slowed in a 0.2 s dispute turned away from the robot whose
    views would have settled it, and three robots stayed unvouched to the end)."""
    return not c.localised and len(c.cov) == 9 and worst_axis_sigma_m(c.cov) >= claim_sigma_m


class AgentIntake:
    """The checks on one agent's inputs (see the module docstring)."""

    def __init__(self, robot_id: int, ticks_per_rev: int, rejects: streams.RejectCounter,
                 counters: Counter[str]) -> None:
        self.rid, self.ticks_per_rev = robot_id, ticks_per_rev
        self.rejects, self.counters = rejects, counters
        self.reset()

    def reset(self) -> None:
        """A new world run: its clock starts again."""
        self._last_enc_ns = -1
        self._last_frame_ns: dict[str, int] = {}

    def encoders(self, items: Iterable[Received[bytes]], upto_ns: int | None = None
                 ) -> Iterator[tuple[str, m.EncoderTicks]]:
        """(key, counts) of this robot's encoder messages, in order, none older than the last."""
        for item, enc in self.rejects.decoded(items, m.EncoderTicks):
            if enc.robot_id != self.rid:
                self.rejects.reject("spoofed", f"{item.key} carries robot_id {enc.robot_id}")
                continue
            if enc.ticks_per_rev != self.ticks_per_rev:
                self.rejects.reject("inconsistent", f"ticks_per_rev {enc.ticks_per_rev} != configured")
                continue
            if enc.stamp_ns < self._last_enc_ns or (upto_ns is not None and enc.stamp_ns > upto_ns):
                # counts of another world run (its clock restarted): integrating them would jump the pose
                self.counters["stale_encoders"] += 1
                continue
            self._last_enc_ns = enc.stamp_ns
            yield item.key, enc

    def frames(self, camera: str, items: Iterable[Received[bytes]], upto_ns: int | None = None
               ) -> Iterator[m.CameraImage]:
        """This robot's frames of ``camera``, none older than the last one taken."""
        for item, img in self.rejects.decoded(items, m.CameraImage):
            if img.robot_id != self.rid or img.camera != camera:
                self.rejects.reject("spoofed", f"{item.key} carries robot {img.robot_id}/{img.camera}")
                continue
            if img.stamp_ns < self._last_frame_ns.get(camera, -1) or (upto_ns is not None and img.stamp_ns > upto_ns):
                self.counters["stale_frames"] += 1  # of another world run
                continue
            self._last_frame_ns[camera] = img.stamp_ns
            yield img

    def placement(self, c: m.Correction, odom_since_ns: int | None, time_ns: int) -> bool:
        """Whether ``c`` places this robot (vouched for or not) in our odometry frame: not one made
        before the server had our odometry (``odom_since_ns``: our first odometry's stamp in this run)
        or ahead of our clock ``time_ns`` (a previous world run), whose map -> odom is for another odom
        frame (counted as ``stale_corrections``)."""
        if not (c.localised or any(c.cov)):
            return False  # the server cannot place us yet
        if odom_since_ns is None or c.stamp_ns < odom_since_ns or c.stamp_ns > time_ns + CORRECTION_AHEAD_NS:
            self.counters["stale_corrections"] += 1
            return False
        return True

    def own(self, items: Iterable[Received[bytes]], cls: type[M]) -> Iterator[tuple[str, M]]:
        """(key, message) of the ``cls`` messages (corrections, goals, recorded commands) for this robot."""
        for item, msg in self.rejects.decoded(items, cls):
            robot: Any = msg.robot_id
            if robot != self.rid:
                self.rejects.reject("spoofed", f"{cls.__name__.lower()} for robot {robot} on {item.key}")
                continue
            yield item.key, msg
