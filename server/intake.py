"""What the map server takes in, checked before anything reaches the fusion.

Decodes the agents' odometry, relative observations and lockstep tick acks (as drained
from the node's inboxes) and drops (counted, logged once per kind by the
:class:`~tagswarm.runtime.streams.RejectCounter`) anything malformed, spoofed (the robot id
in the payload is not the one of its key) or from a robot outside the roster.  What passes
is handed on as journal records (map frame is not involved: odometry is in the robot's own
odom frame, observations in the observer's base_link; metres, radians, simulation ns).
No fusion state lives here; :mod:`tagswarm.server.node` decides what to do with a record.
:class:`OdometryWait` is the lockstep bookkeeping of whose odometry of a tick is still to come,
:class:`AckLog` of which ticks an agent has acknowledged.
"""

from __future__ import annotations

from collections import Counter, deque
from collections.abc import Container, Iterable, Iterator, Mapping, Sequence

from tagswarm.protocol import messages as m
from tagswarm.protocol.inbox import Received
from tagswarm.protocol.keys import Keys
from tagswarm.runtime import streams
from tagswarm.server import journal as jr


class Intake:
    """The checks on the server's inputs (see the module docstring)."""

    def __init__(self, keys: Keys, roster: set[int], rejects: streams.RejectCounter,
                 gaps: streams.GapCounter, counters: Counter[str]) -> None:
        self.keys, self.roster = keys, roster
        self.rejects, self.gaps, self.counters = rejects, gaps, counters

    def robot_from_key(self, key: str, claimed: int) -> int | None:
        """The robot id of ``key`` if it is ``claimed`` and in the roster, else None (counted)."""
        rid = self.keys.robot_id_of(key)
        if rid is None or rid != claimed:
            self.rejects.reject("spoofed", f"{key} carries robot_id {claimed}")
            return None
        if rid not in self.roster:
            self.rejects.reject("unknown_robot", f"{key}: robot {rid} is not in the roster")
            return None
        return rid

    def acks(self, rid: int, items: Sequence[Received[bytes]]) -> Iterator[tuple[int, int]]:
        """(step, stamp_ns) of every tick ack in ``items`` (drained from robot ``rid``'s agent's ack key)
        that its agent sent."""
        for item, ack in self.rejects.decoded(items, m.TickAck):
            if ack.participant != f"agent/{rid}":
                self.rejects.reject("spoofed", f"{item.key} carries participant {ack.participant!r}")
                continue
            yield ack.step, ack.stamp_ns

    def odometry(self, items: Sequence[Received[bytes]]) -> Iterator[tuple[str, jr.Odometry, int]]:
        """(key, record, seq) of every odometry message in ``items`` from a roster robot on its own key."""
        for item, od in self.rejects.decoded(items, m.OdometryEstimate):
            sender = self.robot_from_key(item.key, od.robot_id)
            if sender is None:
                continue
            yield item.key, jr.Odometry(robot_id=sender, stamp_ns=od.stamp_ns, x_m=od.x_m, y_m=od.y_m,
                                        yaw_rad=od.yaw_rad, distance_m=od.distance_m, slip_m=od.slip_m), od.seq

    def observations(self, items: Sequence[Received[bytes]]) -> Iterator[jr.Observation]:
        """Every relative observation in ``items`` by a roster robot on its own key, of a landmark or
        of another roster robot (never of itself)."""
        for item, ob in self.rejects.decoded(items, m.RelativeObservation):
            observer = self.robot_from_key(item.key, ob.robot_id)
            if observer is None:
                continue
            if ob.target_kind == "robot" and (ob.target_id not in self.roster or ob.target_id == observer):
                self.rejects.reject("unknown_robot", f"observation of robot {ob.target_id}")
                continue
            self.gaps.seen(item.key, ob.seq, f"observations_robot{observer}")
            if ob.target_kind == "landmark" and len(set(ob.tag_ids)) > 1:
                # an agent's self-localisation solved jointly from several field tags (agents/landmarkfix.py)
                self.counters["multi_landmark_fixes"] += 1
            yield jr.Observation(observer=observer, target_kind=ob.target_kind, target_id=ob.target_id,
                                 stamp_ns=ob.stamp_ns, x_m=ob.x_m, y_m=ob.y_m, yaw_rad=ob.yaw_rad,
                                 cov=tuple(float(v) for v in ob.cov))


class OdometryWait:
    """Lockstep: whose odometry of one world tick (``step``, ``stamp_ns``) the server still
    waits for (pure bookkeeping; the node drains and sleeps).  A live robot is settled once
    its odometry stamped at or after the tick is in, or once its agent's ack of the tick
    (sent after that odometry, on the same session) has been here ``grace_s`` (wall seconds)
    without it: then it is lost on the way, not late.  A robot whose cameras rendered in this
    tick (``with_frames``) is settled only once its ack is in as well: the agent publishes the
    tick's observations after its odometry and before its ack, so an advance on the odometry
    alone could leave an observation of the tick to arrive late, and the run would then depend
    on how fast the network delivered it (``late_observations``)."""

    def __init__(self, step: int, stamp_ns: int, grace_s: float, deadline: float,
                 with_frames: Container[int] = frozenset()) -> None:
        self.step, self.stamp_ns, self.grace_s, self.deadline = step, stamp_ns, grace_s, deadline
        self.with_frames = with_frames
        self._acked_at: dict[int, float] = {}  # robot -> when its ack of this tick was first seen here (wall)
        #: after :meth:`settled`: the earliest moment a grace runs out, else the deadline
        self.next_at = deadline

    def settled(self, now: float, alive: set[int], latest_rx: Mapping[int, int],
                acked: Mapping[int, Container[tuple[int, int]]]) -> bool:
        """Whether no live robot is still worth waiting for at ``now`` (monotonic s)."""
        self.next_at = self.deadline
        done = True
        for r in alive:
            ack = (self.step, self.stamp_ns) in acked[r]
            if latest_rx.get(r, -1) >= self.stamp_ns:
                if ack or r not in self.with_frames:
                    continue
                done = False  # its odometry is in, the observations of its frames may not be yet
                continue
            if ack:
                until = self._acked_at.setdefault(r, now) + self.grace_s
                if now >= until:
                    continue  # lost
                self.next_at = min(self.next_at, until)
            done = False
        return done

    def lost(self, alive: set[int], latest_rx: Mapping[int, int],
             acked: Mapping[int, Container[tuple[int, int]]]) -> list[int]:
        """The live robots whose agent acked the tick but whose odometry of it never came."""
        return [r for r in sorted(alive)
                if latest_rx.get(r, -1) < self.stamp_ns and (self.step, self.stamp_ns) in acked[r]]


class AckLog:
    """Lockstep: the ``(step, stamp_ns)`` of one agent's tick acks that a wait may still ask
    about (:class:`OdometryWait` only ever looks up the tick being waited for).

    Bounded against a flood, but never at the cost of the genuine ack of the tick being waited
    for.  Once :meth:`expect` names that tick (its step, stamp and the clock's step ``dt_ns``),
    only acks that could be genuine are kept: of that step or a later one, stamped where the
    world's clock puts that step (``stamp_ns`` = step x ``dt_ns``, the lockstep world's time).
    Each is kept once, and beyond ``capacity`` the one of the *latest* step goes, so the
    waited tick's own ack, the earliest possible, is never pushed out.  A forged ack (it passes
    the intake: its participant matches its key) can then only be of a far future step, and
    leaves first however often it is sent; a first-in-first-out buffer let 72 copies of one
    push the real ack out, and the tick then waited ``clock.ack_timeout_s`` for it."""

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self.capacity = capacity
        self._acks: set[tuple[int, int]] = set()
        self._expected: tuple[int, int, int] | None = None  # (step, stamp_ns, dt_ns) of the waited tick
        # acks of steps before the waited one, aside: a restarted world's first acks can come before its
        # first tick does (then they are the new run's, see restart); never looked up otherwise
        self._earlier: deque[tuple[int, int]] = deque(maxlen=capacity)

    def __contains__(self, ack: object) -> bool:
        return ack in self._acks

    def __len__(self) -> int:
        return len(self._acks)

    def _plausible(self, ack: tuple[int, int]) -> bool:
        if self._expected is None:
            return True
        step, stamp, dt = self._expected
        return ack[0] >= step and ack[1] == stamp + (ack[0] - step) * dt

    def extend(self, acks: Iterable[tuple[int, int]]) -> None:
        """Keep each plausible ``(step, stamp_ns)`` of ``acks`` (dropping the latest steps beyond capacity)."""
        for ack in acks:
            if not self._plausible(ack):
                if self._expected is not None and ack[0] < self._expected[0]:
                    self._earlier.append(ack)
                continue
            self._acks.add(ack)
            if len(self._acks) > self.capacity:
                self._acks.remove(max(self._acks))

    def expect(self, step: int, stamp_ns: int, dt_ns: int) -> None:
        """The tick now waited for (ticks are waited for in order): forget the acks that cannot be of
        it or of a later tick of the same clock."""
        self._expected = (step, stamp_ns, dt_ns)
        self._acks = {a for a in self._acks if self._plausible(a)}

    def restart(self, step: int) -> None:
        """A restarted world's first tick, ``step``: its clock starts again, so forget the acks of later
        steps (the old run's: they would excuse the new run's ticks of the same step) and the old
        expectation, and take back those of steps up to ``step`` that came while the old run's tick was
        still expected (the new run's first acks can overtake its first tick: dropping them made that
        tick wait ``clock.ack_timeout_s``, seen once in CI)."""
        self._expected = None
        self._acks = {a for a in (*self._acks, *self._earlier) if a[0] <= step}
        self._earlier.clear()


class SilentRobots:
    """Lockstep: robots whose agent is alive but silent (a controller whose step hangs: the
    process and its liveliness token live on, its odometry stops).  After ``stall_after``
    odometry waits in a row ran out for a robot, it is *stalled*: not waited for until its
    odometry comes again, so it costs the run a few ``clock.ack_timeout_s`` rather than one
    per tick, as the world treats its ack (:class:`tagswarm.world.lockstep.AckTracker`).
    ``stall_after`` 0 never stalls anyone."""

    def __init__(self, stall_after: int) -> None:
        self.stall_after = stall_after
        self.missed: dict[int, int] = {}  # waits in a row that ran out
        self.stalled: dict[int, int] = {}  # robot -> its newest odometry stamp when stalled

    def release(self, latest_rx: Mapping[int, int]) -> None:
        """A stalled robot is back once newer odometry than when it stalled arrived."""
        for r, stamp in list(self.stalled.items()):
            if latest_rx.get(r, -1) > stamp:
                self.forget(r)

    def waited(self, alive: set[int]) -> set[int]:
        """The live robots to wait for."""
        return alive - self.stalled.keys()

    def forget(self, robot: int) -> None:
        """``robot``'s agent went or came (its liveliness token changed): whatever it missed is over."""
        self.missed.pop(robot, None)
        self.stalled.pop(robot, None)

    def settled(self, waited: set[int], late: set[int], latest_rx: Mapping[int, int]) -> list[int]:
        """After one tick's wait: ``late`` are the waited robots whose odometry did not come
        before the deadline (empty if it did not run out).  Returns the robots stalled now."""
        now_stalled = []
        for r in waited - late:
            self.missed.pop(r, None)
        for r in sorted(late):
            self.missed[r] = self.missed.get(r, 0) + 1
            if self.stall_after and self.missed[r] >= self.stall_after:
                self.stalled[r] = latest_rx.get(r, -1)
                now_stalled.append(r)
        return now_stalled
