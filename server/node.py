"""The map server process (the only I/O of ``server``).

Takes every robot's odometry and relative observations, feeds the
:class:`~tagswarm.server.fusion.Fusion`, publishes each robot's correction after every
update and the global map at ``map_rate_hz``, and answers map queries (late
joiners).  Accepts data only from roster robots on their own keys.

With ``--journal PATH`` every accepted input (and every fusion update) is
written ahead to :mod:`tagswarm.server.journal`; a server started on an existing journal
first replays it through the same fusion code, so a crashed server comes back
with the graph it had (same decisions, estimates equal to rounding), then
declares itself alive and resumes.  Every ``--journal-checkpoint`` simulated
seconds it also journals a checkpoint of its whole state and restores its own
fusion from it; a restart then replays only from the last checkpoint on, through
the very same restore, so rebuild time does not grow with the run.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter, deque
from collections.abc import Mapping, Sequence

from tagswarm.protocol import codec
from tagswarm.protocol import messages as m
from tagswarm.protocol.bus import Bus
from tagswarm.protocol.keys import Keys
from tagswarm.runtime import streams
from tagswarm.runtime.lockstep import Participant
from tagswarm.runtime.presence import Presence, RunEnd, silence_ns
from tagswarm.runtime.process import serve_node
from tagswarm.server import journal as jr
from tagswarm.server import outputs
from tagswarm.server.config import ServerConfig, build_config
from tagswarm.server.estimator import Estimator, learnt, make_estimator
from tagswarm.server.estimator import make_fusion as make_fusion  # re-exported: tests build a server's fusion from here
from tagswarm.server.fusion import Fusion
from tagswarm.server.intake import AckLog, Intake, OdometryWait, SilentRobots
from tagswarm.server.nodejournal import NodeJournal

log = logging.getLogger("tagswarm.server")
# realtime only: fresh observations trigger a fusion update at most this often (wall seconds)
EAGER_UPDATE_MIN_S = 0.02
IDLE_STATUS_MIN_S = 0.5  # an idle server reports changed counters at most this often (wall)
# inputs kept since the last tick of the run we follow: a restarted world's first data can be
# drained just before its first tick, and must then be carried into the fresh map
RECENT_MAX = 4096
# lockstep: an agent publishes its odometry of a tick before its ack of that tick, on one session, so
# once the ack is here the odometry is either here too or lost on the way.  This grace (wall seconds;
# plus any receive delay injected on this process) only covers the two taking different network paths
# (e.g. right after start-up, while the peers are still meshing); it bounds what a lost odometry
# message costs the run, instead of ``clock.ack_timeout_s``
ODOMETRY_GRACE_S = 0.03
ACKS_KEPT = 64  # per agent; see AckLog


class ServerNode(NodeJournal):
    """See the module docstring (its journal methods in :mod:`tagswarm.server.nodejournal`)."""

    def __init__(self, config: ServerConfig, bus: Bus) -> None:
        self.cfg = config
        self.s = s = config.scenario
        self.bus = bus
        self.keys = Keys(config.run)
        self.roster = set(s.robot_ids)
        self.method = s.server.method
        self.fusion: Estimator = make_estimator(config)
        # the paper's stitching has no honest covariance to judge by: it claims what it places
        self._claim_sigma_m = s.server.claim_sigma_m if self.method == "graph" else 0.0
        self._vouching = outputs.Vouching(self._claim_sigma_m)  # logs when the server starts or stops vouching
        self.rejects = streams.RejectCounter(log)
        self.gaps = streams.GapCounter()  # messages lost on the way, per sender (lossy networks)
        self.counters: Counter[str] = Counter()
        self._status_sig: tuple[int, int] = (-1, -1)  # (inputs counted, rejects) at the last status
        self._status_wall = 0.0  # when it went out (monotonic s)
        self.seq = streams.Sequencer()
        self.participant = Participant(bus, self.keys, config.participant, self.seq)  # lockstep acks
        # agents with a token that still send odometry (realtime: see tagswarm/runtime/presence.py)
        # an agent sends odometry at the encoder rate (30 Hz): half a second beyond the lease is plenty
        self.presence: Presence[int] = Presence(
            0 if s.clock.mode == "lockstep" else silence_ns(config.bus.lease_ms, config.bus.delay_ms, 0.5))
        self.latest_rx: dict[int, int] = {}
        self.time_ns = 0
        self._next_map_ns = 0
        self._next_update_ns = 0
        self.lockstep = s.clock.mode == "lockstep"
        self._obs_pending = False
        self._last_update_wall = 0.0
        self._sent: dict[int, m.Correction] = {}  # each robot's last correction sent
        self._recent: deque[jr.Odometry | jr.Observation] = deque(maxlen=RECENT_MAX)
        self._checkpoint_every_ns = int(config.journal_checkpoint_s * 1e9)
        self._next_checkpoint_ns = self._checkpoint_every_ns
        self.intake = Intake(self.keys, self.roster, self.rejects, self.gaps, self.counters)
        self.obs_in = bus.subscribe(self.keys.observation())
        self.odom_in = bus.subscribe(self.keys.odometry())
        self.tick_in = bus.subscribe(self.keys.tick())
        # each roster agent's tick acks (lockstep): they tell a lost odometry message from a late one
        self.ack_in = {rid: bus.subscribe(self.keys.ack(f"agent/{rid}")) for rid in sorted(self.roster)}
        # robot -> (step, stamp_ns) of its agent's acks from the tick being waited for on
        self.acked: dict[int, AckLog] = {rid: AckLog(ACKS_KEPT) for rid in self.roster}
        self.silent = SilentRobots(self.s.clock.ack_stall_after)
        self.odometry_grace_s = ODOMETRY_GRACE_S + config.bus.delay_ms / 1e3
        self.alive_in = bus.watch_liveliness(self.keys.alive_role("agent"))
        self.world_alive_in = bus.watch_liveliness(self.keys.alive_role("world"))
        self.runs = streams.RunFollower()  # the world instance whose ticks we follow
        self.query_in = bus.queryable(self.keys.map())
        # subscribed before the replay, so what arrives meanwhile waits in the inboxes; alive only after
        # it, so a lockstep world does not wait for acks from a server still rebuilding its graph
        if config.journal and not isinstance(self.fusion, Fusion):
            # the journal's replay and checkpoints are the pose graph's (its decisions depend on the update
            # sequence); the stitched map holds only the newest edges, so a restarted stitch server simply
            # re-stitches from the observations that follow
            log.warning("--journal %s ignored: server.method = %r keeps no journal (graph only)", config.journal,
                        self.method)
        self.journal = self._open_journal() if config.journal and isinstance(self.fusion, Fusion) else None
        bus.declare_token(self.keys.alive(config.participant))
        log.info("server up: method %s, %d robots, origin %d, %s clock, lag %.0f s, journal %s, start poses %s",
                 self.method, len(self.roster), s.map.origin_id, s.clock.mode, config.lag_s,
                 (config.journal or "off") if self.journal is not None or not config.journal else "off",
                 f"known (sigma {s.server.start_prior_sigma:g})" if s.server.start_prior_sigma else "unknown")

    def _publish(self, key: str, msg: m.Msg) -> None:
        self.bus.put(key, codec.encode(msg))

    # ------------------------------------------------------------------ inputs
    @property
    def alive(self) -> set[int]:
        """Robots whose agent is alive: its token is up and (realtime) its odometry keeps coming."""
        return self.presence.alive_set()

    def _drain(self) -> None:
        for change in self.alive_in.drain():
            who = self.keys.participant_of(change.key)
            if who and who.startswith("agent/") and who[6:].isdigit():
                agent = int(who[6:])
                self.presence.token(agent, change.value, self.time_ns)
                self.silent.forget(agent)  # gone or (back) up: a stall, if any, ends with it
                if not change.value:
                    log.info("robot %d's agent is gone; its last pose stays in the map", agent)
        # acks before odometry: an agent's odometry of a tick was enqueued before its ack of that tick
        # (one session, one receive thread), so it is drained below, however late this drain runs
        self._drain_acks()
        for key, od, seq in self.intake.odometry(self.odom_in.drain()):
            sender = od.robot_id
            if od.stamp_ns <= self.fusion.latest_odom_ns(sender) and not self._world_left():
                # older than this robot's odometry already fused (e.g. taken for lost in lockstep, then late):
                # the poses are cumulative, so the newer one holds its increment; applying it now would put
                # the robot's odometry out of order.  (Before the gap count: its old number is no restart.)
                # Once the world has left, an early stamp is a restarted world's: kept, to be carried over.
                self.counters["odometry_late"] += 1
                continue
            self.gaps.seen(key, seq, f"odometry_robot{sender}")
            self._accept(od)
            self.presence.heard(sender, od.stamp_ns)
            self.counters["odometry"] += 1
        for ob in self.intake.observations(self.obs_in.drain()):
            self._accept(ob)
            self.counters["observations"] += 1
        self.presence.update(self.time_ns, log, "robot {}'s agent")
        if self.presence.silences:
            self.counters["agent_silences"] = self.presence.silences
        if self.journal is not None:
            self.journal.flush()  # accepted inputs reach the OS before anything they influence goes out
        for q in self.query_in.drain():
            self.bus.reply(q.value, self.keys.map(), codec.encode(self.global_map()))
            self.counters["map_queries"] += 1

    def _drain_acks(self) -> None:
        for rid, inbox in self.ack_in.items():
            # only ever compared with the tick being waited for: an ack of any other step (a forged one
            # of a future step too) excuses no odometry
            self.acked[rid].extend(self.intake.acks(rid, inbox.drain()))

    def _accept_tick(self, tick: m.Tick) -> bool:
        """Whether ``tick`` belongs to the world run we follow.  A new run_id after the
        world's liveliness token vanished is a restarted world (clock back at 0): start
        a fresh map.  A new run_id while the world is alive is foreign: rejected."""
        self._world_left()
        previous = self.runs.run_id
        verdict = self.runs.accept(tick.run_id)
        if verdict == "foreign":
            self.rejects.reject("foreign_run", f"tick of run {tick.run_id!r} while {previous!r} is live")
            return False
        if verdict == "restart":
            # the new run's inputs drained before this tick (stamped up to it: the old run's last ones
            # are later) went into the old map; they belong to the new one
            carried = [r for r in self._recent if r.stamp_ns <= tick.stamp_ns]
            log.warning("the world restarted (new run %s): starting a fresh map (%d input(s) of the new run "
                        "carried over)", tick.run_id, len(carried))
            self.counters["world_restarts"] += 1
            self.counters["restart_carried"] += len(carried)
            self._sent.clear()
            self._drain_acks()  # the old run's last acks, still queued, go with the rest of it
            for acks in self.acked.values():
                acks.restart(tick.step)
            record = jr.NewRun(run_id=tick.run_id)
            if self.journal is not None:
                self.journal.append(record)
            self._replay(record)
            for r in carried:
                self._accept(r)
        return True

    # ------------------------------------------------------------------ outputs
    def global_map(self) -> m.GlobalMap:
        return outputs.global_map(self.fusion, sorted(self.roster), self.s.map.origin_id, self.time_ns,
                                  self.latest_rx, self.alive, self.seq.peek(self.keys.map()), self._claim_sigma_m)

    def _publish_relocalisations(self) -> None:
        for ev in self.fusion.take_relocalisations():
            log.warning("robot %d re-localised at t=%.2f s: moved %.2f m (%d observations from %s agreed, its "
                        "estimate did not)", ev.robot_id, ev.stamp_ns / 1e9, ev.jump_m, ev.evidence,
                        ", ".join("landmark" if w < 0 else f"robot {w}" for w in ev.observers))
            key = self.keys.relocalisation()
            self._publish(key, outputs.relocalisation(ev, self.seq.next(key)))

    def _publish_corrections(self, all_robots: bool) -> None:
        """Every placed robot's correction (``localised`` if vouched for); with ``all_robots`` the others' too.
        Realtime sends only those :func:`~tagswarm.server.outputs.correction_due` (lockstep: every one,
        every tick, as the agents wait for them)."""
        for rid in sorted(self.roster):
            key = self.keys.correction(rid)
            msg = outputs.correction(self.fusion, rid, self.time_ns, self.seq.peek(key), self._claim_sigma_m)
            line = self._vouching.update(self.fusion, rid, msg, self.time_ns)
            if line:
                log.info("%s", line)
                self.counters["unvouched_events"] = self._vouching.unvouched_events
            if not (msg.localised or all_robots or any(msg.cov)):
                continue
            if not self.lockstep and not outputs.correction_due(self._sent.get(rid), msg):
                self.counters["corrections_held"] += 1
                continue
            self._publish(key, msg)
            self.seq.next(key)
            self._sent[rid] = msg
            if msg.localised:
                self.counters["corrections"] += 1

    def _maybe_publish_map(self) -> None:
        if self.time_ns >= self._next_map_ns:
            key = self.keys.map()
            self._publish(key, self.global_map())
            self.seq.next(key)
            self._next_map_ns = self.time_ns + int(1e9 / self.cfg.map_rate_hz)
            self._publish_status()

    def _status_signature(self) -> tuple[int, int]:
        return (sum(self.counters.values()), sum(self.rejects.counts.values()))

    def _publish_status(self) -> None:
        self._status_sig, self._status_wall = self._status_signature(), time.monotonic()
        counters = outputs.status_counters(self.counters, self.fusion, self.rejects.as_counters(),
                                           self.gaps.as_counters(), self.bus.fault_stats(),
                                           None if self.journal is None else self.journal.as_counters(),
                                           alive=len(self.alive))
        key = self.keys.server_status()
        self._publish(key, m.AgentStatus(seq=self.seq.next(key), stamp_ns=self.time_ns, role="server",
                                         mode=self.s.clock.mode, counters=counters))

    # ------------------------------------------------------------------ cycle
    def _watermark(self) -> int:
        """Time up to which every live robot's odometry has arrived."""
        live = [self.latest_rx[r] for r in self.alive if r in self.latest_rx]
        if not live:
            return max(self.latest_rx.values(), default=-1)
        newest = max(live)
        # a robot more than a second behind the others is not waited for
        return min(t for t in live if newest - t < 1_000_000_000)

    def step(self) -> bool:
        """Handle what has arrived; in lockstep, one fusion update per world tick."""
        obs_before = self.counters["observations"]
        # ticks first: a restarted world's first tick must reset the map before its data is fused
        ticks: list[m.Tick] = []
        for _, tick in self.rejects.decoded(self.tick_in.drain(), m.Tick):
            restarts = self.counters["world_restarts"]
            if self._accept_tick(tick):
                if self.counters["world_restarts"] != restarts:
                    ticks.clear()  # ticks of the run that just ended are not waited for
                ticks.append(tick)
        if ticks:
            self._recent.clear()
        self._drain()
        if self.lockstep:
            return self._step_lockstep(ticks)
        self._obs_pending |= self.counters["observations"] > obs_before
        wm = self._watermark()
        if wm < 0:
            return False
        # nothing new below the watermark: report idle so run() sleeps until data arrives
        # instead of spinning a core
        progressed = wm > self.time_ns
        self.time_ns = max(self.time_ns, wm)
        # an observation usually lands just after the update its tick's odometry triggered; fusing it
        # at once (rate-limited in wall time) rather than on the next scheduled update saves up to a
        # whole update period of image-to-correction latency
        wall = time.monotonic()
        eager = self._obs_pending and wall - self._last_update_wall >= EAGER_UPDATE_MIN_S
        if self.time_ns >= self._next_update_ns or eager:
            self._obs_pending = False
            self._last_update_wall = wall
            progressed = True
            self._advance(wm)
            self._publish_corrections(all_robots=False)
            self._next_update_ns = self.time_ns + int(1e9 / self.cfg.update_rate_hz)
        self._maybe_publish_map()
        return progressed

    def _world_left(self) -> bool:
        """Whether the world we follow has gone (its liveliness token vanished)."""
        for change in self.world_alive_in.drain():
            self.runs.world_presence(change.value)
        return self.runs.world_left

    def _await_odometry(self, tick: m.Tick) -> None:
        """Wait until every live robot's odometry of ``tick`` has arrived (and, for a robot
        whose cameras rendered in ``tick``, its agent's ack, which follows the observations of
        those frames) or is known to be lost: its agent acknowledged ``tick`` and the odometry,
        published before that ack, is still missing ``odometry_grace_s`` later (counted in ``odometry_lost``; fusion
        then merges that increment with the next, see :mod:`tagswarm.server.fusion`).  A robot
        whose agent does not answer at all is waited for up to ``clock.ack_timeout_s``
        (``odometry_wait_timeouts``), as the world waits for its ack, and after
        ``clock.ack_stall_after`` such waits in a row not at all until its odometry comes again
        (``odometry_stalls``; :class:`~tagswarm.server.intake.SilentRobots`)."""
        for acks in self.acked.values():
            acks.expect(tick.step, tick.stamp_ns, tick.dt_ns)
        wait = OdometryWait(tick.step, tick.stamp_ns, self.odometry_grace_s,
                            time.monotonic() + self.s.clock.ack_timeout_s, set(tick.cameras_of()))
        done = [False]
        armed = [wait.deadline]  # what the current wait runs until
        self.silent.release(self.latest_rx)

        def settled() -> bool:
            self._drain()
            done[0] = self._world_left() or wait.settled(time.monotonic(), self.silent.waited(self.alive),
                                                         self.latest_rx, self.acked)
            return done[0]

        def woken() -> bool:  # settled, or a grace began that ends before the current wait does
            return settled() or wait.next_at < armed[0]

        while True:
            arrived = self.bus.wait_for(woken, max(0.0, armed[0] - time.monotonic()))
            if done[0]:
                break
            if not arrived and armed[0] >= wait.deadline:
                self.counters["odometry_wait_timeouts"] += 1
                break
            armed[0] = wait.next_at
        if self._world_left():
            return
        waited = self.silent.waited(self.alive)
        late = set() if done[0] else {r for r in waited if self.latest_rx.get(r, -1) < tick.stamp_ns
                                      and (tick.step, tick.stamp_ns) not in self.acked[r]}
        for r in self.silent.settled(waited, late, self.latest_rx):
            self.counters["odometry_stalls"] += 1
            log.warning("robot %d's odometry missed %d ticks in a row (its agent alive but silent: a step that "
                        "hangs?); not waiting for it any more until its odometry comes again", r,
                        self.silent.stall_after)
        self.counters["odometry_lost"] += len(wait.lost(self.alive, self.latest_rx, self.acked))

    def _step_lockstep(self, ticks: list[m.Tick]) -> bool:
        self.participant.serve(ticks, self._lockstep_tick)
        return bool(ticks)

    def _lockstep_tick(self, tick: m.Tick) -> bool:
        """One lockstep step: every live robot's odometry of ``tick`` in (or known lost), one
        fusion update at its stamp, every robot's correction and (when due) the map; False
        abandons the step."""
        self._await_odometry(tick)
        if self._world_left():
            # the world died after this tick reached us but before every agent answered it: its run is
            # over, so neither fuse, correct nor acknowledge it (that would only feed stale poses to
            # whoever listens while the next world starts)
            self.counters["ticks_abandoned"] += 1
            return False
        self.time_ns = max(self.time_ns, tick.stamp_ns)
        self._advance(tick.stamp_ns)
        self._publish_corrections(all_robots=True)
        self._maybe_publish_map()
        return True

    def run(self, stop_event: threading.Event) -> int:
        end_ns = int(self.s.duration_s * 1e9)
        end = RunEnd(end_ns)  # realtime: the world left at the end, the agents' last odometry lost on the way
        while not stop_event.is_set() and self.time_ns < end_ns:
            if not self.step():
                self._world_left()  # drains the world's token changes
                if not self.lockstep and end.over(self.time_ns, self.runs.world_alive, time.monotonic()):
                    log.warning("the world left at the end of the run (t=%.2f s here): stopping", self.time_ns / 1e9)
                    break
                if self.journal is not None:
                    self.journal.maybe_sync()
                # status otherwise goes out with the map, i.e. only when data moves the clock on: an
                # idle server reports what it counted since, or the last inputs of a burst stay unseen
                if (not self.lockstep and time.monotonic() - self._status_wall >= IDLE_STATUS_MIN_S
                        and self._status_signature() != self._status_sig):
                    self._publish_status()
                self.bus.wait(0.1)
        self._publish_status()
        log.info("server stopping at t=%.2f s: %s", self.time_ns / 1e9,
                 {k: v for k, v in self.fusion.counters.items()})
        for line in learnt(self.fusion):
            log.info("%s", line)
        return 0

    def close(self) -> None:
        """Flush and fsync the journal (called on every way out, see serve_node)."""
        if self.journal is not None:
            self.journal.close()


def main(argv: Sequence[str] | None = None, environ: Mapping[str, str] | None = None) -> int:
    """Console script ``tagswarm-server``."""

    return serve_node("tagswarm-server", lambda: build_config(argv, environ), lambda c: "server", ServerNode)


if __name__ == "__main__":
    raise SystemExit(main())

