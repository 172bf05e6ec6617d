"""The server node's write-ahead journal plumbing (:class:`NodeJournal`, mixed into
:class:`~tagswarm.server.node.ServerNode`; see that module's docstring for ``--journal``).

Every accepted input and every fusion update is journalled before it is fused; the
node-side bookkeeping of a record (newest odometry stamps, counters, clock, a new
world run) is shared by live input and replay, so a server rebuilt from its journal
comes back with the state it had.  Every ``--journal-checkpoint`` simulated seconds a
checkpoint is journalled and then restored into the live fusion, so the live server
and a rebuilt one go through the very same restore.  Times are simulation ns.
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections import Counter, deque

from tagswarm.protocol.scenario import Scenario
from tagswarm.runtime import streams
from tagswarm.runtime.config import ConfigError
from tagswarm.server import journal as jr
from tagswarm.server.config import ServerConfig
from tagswarm.server.estimator import Estimator, apply_input
from tagswarm.server.fusion import Fusion
from tagswarm.server.intake import SilentRobots

log = logging.getLogger("tagswarm.server")  # the node's logger: these are its log lines


class NodeJournal(ABC):
    """The journal methods of :class:`~tagswarm.server.node.ServerNode`, on the node's
    state (declared here, set up by the node)."""

    cfg: ServerConfig
    s: Scenario
    fusion: Estimator
    journal: jr.Journal | None
    roster: set[int]
    rejects: streams.RejectCounter
    counters: Counter[str]
    latest_rx: dict[int, int]  # robot -> stamp of its newest odometry accepted
    silent: SilentRobots
    time_ns: int
    _recent: deque[jr.Odometry | jr.Observation]
    _next_map_ns: int
    _next_update_ns: int
    _checkpoint_every_ns: int
    _next_checkpoint_ns: int

    @abstractmethod
    def _publish_relocalisations(self) -> None:
        """The node's: it sends the re-localisations an update made."""

    def _open_journal(self) -> jr.Journal:
        """Open (and replay) the journal; a journal of another map is a usage error
        (:class:`~tagswarm.server.journal.JournalError`, exit 2)."""
        path = str(self.cfg.journal)
        assert isinstance(self.fusion, Fusion)
        try:
            journal = jr.Journal(path, jr.header_for(self.cfg.run, self.fusion), replay=self._replay,
                                 sync_every=self.cfg.journal_sync_every,
                                 sync_interval_s=self.cfg.journal_sync_ms / 1e3)
        except OSError as exc:
            raise ConfigError(f"--journal {path}: {exc.strerror or exc}") from None
        c = journal.counters
        if c["replayed"]:
            log.info("replayed %d journal records from %s in %.0f ms (%d before its last checkpoint skipped; in all "
                     "%d odometry, %d observations, %d updates); map at t=%.2f s, %d robot(s) localised",
                     c["replayed"], path, journal.replay_s * 1e3, c["replay_skipped"], c["odometry"],
                     c["observations"], c["advances"], self.time_ns / 1e9, len(self.fusion.localised()))
        return journal

    def _accept(self, record: jr.Odometry | jr.Observation) -> None:
        """One input that passed every check: journal it first, then fuse it."""
        if self.journal is not None:
            self.journal.append(record)
        self._recent.append(record)
        self._note(record)
        self._apply(record)

    def _apply(self, record: jr.Record) -> None:
        """The estimator call ``record`` stands for (the journal's own for the graph)."""
        if isinstance(self.fusion, Fusion):
            jr.apply(self.fusion, record)
        else:
            apply_input(self.fusion, record)

    def _advance(self, watermark_ns: int) -> None:
        """One fusion update (journalled too: the update sequence shapes the iSAM2 state)."""
        if self.journal is not None:
            self.journal.append(jr.Advance(watermark_ns=watermark_ns))
            self.journal.flush()
        self.fusion.advance(watermark_ns)
        self._publish_relocalisations()
        if self._checkpoint_every_ns and self.fusion.watermark_ns >= self._next_checkpoint_ns:
            self._checkpoint()

    def _checkpoint(self) -> None:
        """Journal a checkpoint, then restore from it: the live fusion goes through the
        same restore a rebuilt server will, so both stay identical (same decisions,
        same estimates) and a restart only replays what follows."""
        if self.journal is None or self.journal.failed:
            return
        node = {"time_ns": self.time_ns, "accepted_odometry": self.counters["accepted_odometry"],
                "accepted_observations": self.counters["accepted_observations"]}
        assert isinstance(self.fusion, Fusion)  # a journal runs only with the graph
        record = jr.make_checkpoint(self.journal, self.fusion, node, self.latest_rx)
        self.journal.append(record)
        self.journal.flush()
        try:
            self._replay(record)
        except jr.CheckpointError as exc:
            # nothing changed: carry on unrestored, as a rebuild will (it skips a checkpoint that does not restore)
            self.counters["checkpoint_errors"] += 1
            log.error("checkpoint at t=%.2f s does not restore (%s); continuing without it", self.time_ns / 1e9, exc)
            self._next_checkpoint_ns = record.watermark_ns + self._checkpoint_every_ns
            return
        self.counters["checkpoints"] += 1

    def _note(self, record: jr.Record) -> None:
        """Node-side bookkeeping of a record, shared by live input and replay."""
        if isinstance(record, jr.Odometry):
            self.latest_rx[record.robot_id] = max(self.latest_rx.get(record.robot_id, -1), record.stamp_ns)
            self.counters["accepted_odometry"] += 1
        elif isinstance(record, jr.Observation):
            self.counters["accepted_observations"] += 1
        elif isinstance(record, jr.Advance):
            self.time_ns = max(self.time_ns, record.watermark_ns)
        elif isinstance(record, jr.NewRun):
            # (self.acked is kept: a new run's first acks may be in already; an old one matches no tick of
            # the new run before the agent's next acks replace it)
            self.latest_rx.clear()
            self.silent = SilentRobots(self.s.clock.ack_stall_after)
            self.time_ns = self._next_map_ns = self._next_update_ns = 0
            self._next_checkpoint_ns = self._checkpoint_every_ns
        elif isinstance(record, jr.Checkpoint):
            self.latest_rx = dict(record.latest_rx)
            self.time_ns = record.node.get("time_ns", record.watermark_ns)
            for key in ("accepted_odometry", "accepted_observations"):
                self.counters[key] = record.node.get(key, 0)
            self._next_checkpoint_ns = record.watermark_ns + self._checkpoint_every_ns

    def _replay(self, record: jr.Record) -> None:
        """Rebuild state from one journal record (its header matched this map)."""
        rid = record.robot_id if isinstance(record, jr.Odometry) else (
            record.observer if isinstance(record, jr.Observation) else None)
        if rid is not None and rid not in self.roster:
            self.rejects.reject("journal_unknown_robot", f"journal record of robot {rid}")
            return
        self._apply(record)  # first: a checkpoint that does not restore must change nothing
        self.fusion.take_relocalisations()  # went out before the restart
        self._note(record)
