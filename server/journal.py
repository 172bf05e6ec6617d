"""The server's write-ahead journal: an append-only log of every input it accepted.

The fusion state is a deterministic function of the sequence of calls made on
:class:`~tagswarm.server.fusion.Fusion` (``add_odometry``, ``add_observation``,
``add_landmark_observation`` and ``advance``), so the journal records exactly
that sequence: every accepted odometry sample and observation, and every
``advance(watermark)``.  Replaying it through :func:`apply` (the same function
the live server uses) rebuilds the same graph: the same keyframes, factors,
gate and placement decisions, and estimates equal to floating-point rounding
(GTSAM/Eigen results may differ in the last bits between processes — measured
up to 3e-7 m after 60 s of 16 robots, usually exactly 0).  Roster, origin, landmark
poses and fusion parameters come from the scenario; the header record stores
them so that a journal is never replayed into a different map.

The file format (magic, length + CRC32 framing, the record structs) and its
reader live in :mod:`tagswarm.server.journal_format`, what the records mean to the
fusion (:func:`apply`, :func:`header_for`, the record counters) in
:mod:`tagswarm.server.journal_records`; both are re-exported here.  A crash can
leave a torn last frame (power loss mid-write); reading stops at the first bad
frame, and :class:`Journal` truncates the file there before appending again.
Writes go to the OS at every :meth:`Journal.flush` (so a SIGKILLed server loses
nothing it accepted); ``fsync`` (durability against power loss) is batched every
``sync_every`` records or ``sync_interval_s`` and runs in a thread of its own, so
the server's loop never waits for the disk.

Checkpoints bound the rebuild time.  A :class:`Checkpoint` record holds the whole
fusion state (:mod:`tagswarm.server.checkpoint`) plus the server's bookkeeping and the
journal's record counts up to it; opening a journal replays from its last complete
checkpoint, and the records before it are not even read.  To find it without
reading the file, the offsets of the two newest checkpoints are kept in a small
side file ``PATH.index`` (rewritten, not fsynced, after each checkpoint); it is only
a hint — an entry counts only if a checkpoint with that number really starts
there — and without a usable one the file is scanned (decoding only, no fusion).
A torn or corrupt newest checkpoint falls back to the previous one; a checkpoint
that does not restore is skipped (the replay starts at an earlier one, or at the
first record, and passes over it, as the live server did).  The file itself is
never rewritten or split: it stays the single source of truth.
"""

from __future__ import annotations

import fcntl
import logging
import os
import time
from collections.abc import Callable
from pathlib import Path

from tagswarm.protocol.errors import UsageError
from tagswarm.server import checkpoint as ckpt
from tagswarm.server.fusion import Fusion
from tagswarm.server.journal_format import (
    MAGIC,
    MAX_RECORD_BYTES,
    VERSION,
    Advance,
    Checkpoint,
    Header,
    NewRun,
    Observation,
    Odometry,
    Reader,
    Record,
    RobotId,
    StampNs,
    frame,
    read_index,
    read_journal,
    write_index,
)
from tagswarm.server.journal_records import COUNTED, _count, _mismatch, apply, header_for
from tagswarm.server.journal_sync import Syncer, fsync_dir

CheckpointError = ckpt.CheckpointError

__all__ = [
    "COUNTED", "MAGIC", "MAX_RECORD_BYTES", "VERSION", "Advance", "Checkpoint", "CheckpointError", "Header", "Journal",
    "JournalError", "NewRun",
    "Observation", "Odometry", "Reader", "Record", "RobotId", "StampNs", "apply", "frame", "header_for",
    "make_checkpoint", "read_journal",
]

log = logging.getLogger("tagswarm.server.journal")
INDEX_KEEP = 2  # checkpoint offsets kept in the side file: the newest, and one to fall back to


class JournalError(UsageError, ValueError):
    """The journal cannot be used (not a journal, or written for another map); one line."""


def make_checkpoint(journal: Journal, fusion: Fusion, node: dict[str, int], latest_rx: dict[int, int]) -> Checkpoint:
    """The checkpoint record of the state now (call right after ``fusion.advance``, with
    its Advance already appended).  The server appends it and then *applies* it to its
    own fusion, so the live state and any later rebuild go through the same restore."""
    return Checkpoint(seq=journal.last_seq + 1, watermark_ns=fusion.watermark_ns, counts=journal.record_counts(),
                      node=dict(node), latest_rx=dict(latest_rx), fusion=ckpt.snapshot(fusion))


class Journal:
    """An open journal: validates and replays what is there, then appends.

    ``replay`` is called for every record after the header, in order (the
    server rebuilds its state with it), starting at the last usable checkpoint if
    there is one (``counters["replay_skipped"]`` records before it are not read;
    ``replay`` must raise :class:`~tagswarm.server.checkpoint.CheckpointError` without
    changing anything if a checkpoint does not restore).  Raises
    :class:`JournalError` if the file is not a journal or belongs to another map;
    truncates a torn or corrupt tail (counted in ``counters["truncated_bytes"]``).
    """

    def __init__(self, path: str | os.PathLike[str], header: Header, *,
                 replay: Callable[[Record], None] | None = None, sync_every: int = 64,
                 sync_interval_s: float = 0.1, background_sync: bool = True) -> None:
        self.path = Path(path)
        self.header = header
        self.sync_every = max(1, sync_every)
        self.sync_interval_s = sync_interval_s
        self.counters: dict[str, int] = dict.fromkeys(
            (*COUNTED, "replayed", "replay_skipped", "bad_checkpoints", "fsyncs", "bytes", "truncated_bytes",
             "write_errors", "lost", "index_errors"), 0)
        self.index_path = Path(f"{self.path}.index")
        self.checkpoints: list[tuple[int, int]] = []  # (offset, seq) of the newest checkpoints in the file
        self.last_seq = 0  # of the newest checkpoint in the file (or queued)
        self._queued_checkpoints: list[tuple[int, int]] = []
        self._bad: set[int] = set()  # offsets of checkpoints that did not restore
        self.failed = False  # set by a write error: journalling stops, the server serves on
        self._pending: list[Record] = []  # queued, counted once written
        self.sync_s_total = 0.0  # wall time spent in fsync (bench/report only, never logic)
        self._buffer = bytearray()
        self._unsynced = 0
        self._unsynced_since = 0.0
        self._syncer: Syncer | None = None
        self.replay_s = 0.0
        existed = self.path.exists()
        self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT, 0o644)
        try:
            # one writer per journal: a second server on the same file would interleave records (the
            # kernel drops the lock with the process, so a SIGKILLed server does not leave it behind)
            try:
                fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise JournalError(f"journal {self.path} is in use by another server") from None
            keep = self._open_existing(replay) if existed else 0
            self.counters["bytes"] = keep
            if os.fstat(self._fd).st_size != keep:
                os.ftruncate(self._fd, keep)
            os.lseek(self._fd, keep, os.SEEK_SET)
            if keep == 0:
                # a new journal: the header goes to disk (and the file's directory entry) at once; an index
                # left by an earlier journal of this name means nothing for this one
                self.checkpoints, self.last_seq = [], 0
                self._write_index()
                data = MAGIC + frame(header)
                os.write(self._fd, data)
                self.counters["bytes"] = len(data)
                self._fsync()
                fsync_dir(self.path.parent)
        except BaseException:
            os.close(self._fd)
            self._fd = -1
            raise
        if background_sync:
            self._syncer = Syncer(self._fsync)

    def _open_existing(self, replay: Callable[[Record], None] | None) -> int:
        """Check the header, replay from the last usable checkpoint (or the start);
        returns the length of the good prefix."""
        reader = Reader(self.path)
        t0 = time.perf_counter()
        first = next(iter(reader), None)
        if reader.bad_magic:
            raise JournalError(f"journal {self.path} is not a tagswarm journal; refusing to overwrite it")
        if first is None:  # empty, or torn before the header was complete: start afresh
            if reader.file_bytes:
                self.counters["truncated_bytes"] = reader.file_bytes
                log.warning("journal %s holds no complete header (%d bytes); starting a new one", self.path,
                            reader.file_bytes)
            return 0
        if not isinstance(first, Header):
            raise JournalError(f"journal {self.path} does not start with a header")
        why = _mismatch(self.header, first)
        if why is not None:
            raise JournalError(f"journal {self.path} was written for another map: {why}")
        body = reader.valid_bytes  # where the first record after the header starts
        # checkpoints: those the index names that really are there, then any later ones in the file
        hinted = read_index(self.path, self.index_path, body)
        scan_from = hinted[-1][0] if hinted else body
        candidates = sorted(set(hinted) | set(self._scan(scan_from)))
        self.last_seq = max((seq for _, seq in candidates), default=0)
        replayed = None
        while replayed is None:
            if not candidates and scan_from > body:  # every known one failed: look for older ones
                candidates = [c for c in self._scan(body) if c[0] < scan_from and c[0] not in self._bad]
                scan_from = body
            start = candidates.pop() if candidates else (body, 0)
            replayed = self._replay_from(start[0], start[1] == 0, replay)
            if replayed is None:
                self._bad.add(start[0])
                log.warning("journal %s: checkpoint %d at byte %d does not restore; falling back to %s", self.path,
                            start[1], start[0], "the previous one" if candidates else
                            "an earlier one" if scan_from > body else "a full replay")
            elif start[1]:
                candidates.append(start)
        assert replayed is not None  # the full replay never fails
        self.counters["bad_checkpoints"] = len(self._bad)
        self.replay_s = time.perf_counter() - t0
        if replayed.problem is not None:
            lost = replayed.file_bytes - replayed.valid_bytes
            self.counters["truncated_bytes"] = lost
            log.warning("journal %s: %s record after %d good ones; truncating %d bytes", self.path,
                        replayed.problem, self.counters["replayed"], lost)
        kept = [c for c in candidates if c[0] < replayed.valid_bytes][-INDEX_KEEP:]
        if kept != hinted[-INDEX_KEEP:] or not self.index_path.exists():
            self.checkpoints = kept
            self._write_index()
        self.checkpoints = kept
        return replayed.valid_bytes

    def _scan(self, offset: int) -> list[tuple[int, int]]:
        """(offset, seq) of every checkpoint from ``offset`` to the end of the good prefix
        (decoding only: no replay)."""
        reader = Reader(self.path, offset)
        return [(reader.offset, rec.seq) for rec in reader if isinstance(rec, Checkpoint)]

    def _replay_from(self, offset: int, full: bool, replay: Callable[[Record], None] | None) -> Reader | None:
        """Replay the records from ``offset`` (the first record after the header when
        ``full``, else a checkpoint) to the end of the good prefix; None if the
        checkpoint there does not restore (nothing was replayed then)."""
        reader = Reader(self.path, offset)
        for key in (*COUNTED, "replayed", "replay_skipped"):
            self.counters[key] = 0
        for record in reader:
            if isinstance(record, Header):  # only ever the first record
                reader.problem = "malformed"
                break
            starting = not full and reader.offset == offset
            if starting:
                assert isinstance(record, Checkpoint)
                for key in COUNTED:
                    self.counters[key] = record.counts.get(key, 0)
                self.counters["replay_skipped"] = sum(record.counts.get(k, 0) for k in COUNTED if k != "records")
            if replay is not None:
                try:
                    replay(record)
                except ckpt.CheckpointError as exc:
                    if starting:
                        return None
                    # in the middle of a replay the state is rebuilt from the records anyway
                    if reader.offset not in self._bad:
                        self._bad.add(reader.offset)
                        log.warning("journal %s: skipping a checkpoint that does not restore (%s)", self.path, exc)
            _count(self.counters, record)
            self.counters["replayed"] += 1
        return reader

    def _write_index(self) -> None:
        """Replace the side index with ``self.checkpoints`` (not fsynced: a lost or stale
        index only makes the next open scan more of the file)."""
        try:
            write_index(self.index_path, self.checkpoints)
        except OSError as exc:
            if not self.counters["index_errors"]:
                log.warning("journal %s: cannot write its index %s (%s); a restart will scan the journal",
                            self.path, self.index_path, exc)
            self.counters["index_errors"] += 1

    def record_counts(self) -> dict[str, int]:
        """The record counters of everything appended so far, written or still queued
        (what a checkpoint stores)."""
        counts = {k: self.counters[k] for k in COUNTED}
        for record in self._pending:
            _count(counts, record)
        return counts

    # ------------------------------------------------------------------ writing
    def append(self, record: Odometry | Observation | Advance | NewRun | Checkpoint) -> None:
        """Queue one record; it reaches the OS at the next :meth:`flush`."""
        if self.failed:
            self.counters["lost"] += isinstance(record, Odometry | Observation)
            return
        if isinstance(record, Checkpoint):
            self._queued_checkpoints.append((self.counters["bytes"] + len(self._buffer), record.seq))
            self.last_seq = max(self.last_seq, record.seq)
        self._buffer += frame(record)
        self._pending.append(record)
        if not self._unsynced:
            self._unsynced_since = time.monotonic()
        self._unsynced += 1

    def flush(self) -> None:
        """Hand queued records to the OS (they survive a killed process from here
        on) and fsync if a batch is due."""
        if self._syncer is not None and self._syncer.error is not None and not self.failed:
            self._fail(self._syncer.error)
        if self._buffer and not self.failed:
            data = bytes(self._buffer)
            self._buffer.clear()
            try:
                done = 0
                while done < len(data):  # os.write may write less than asked
                    done += os.write(self._fd, data[done:])
            except OSError as exc:
                self._fail(exc)
                return
            self.counters["bytes"] += len(data)
            for record in self._pending:
                _count(self.counters, record)
            self._pending.clear()
            if self._queued_checkpoints:
                self.checkpoints = (self.checkpoints + self._queued_checkpoints)[-INDEX_KEEP:]
                self._queued_checkpoints.clear()
                self._write_index()
        self.maybe_sync()

    def _fail(self, exc: OSError) -> None:
        """A write or fsync failed (disk full, I/O error): stop journalling rather than
        stop the server; what was queued and what follows is counted as lost."""
        self.failed = True
        self.counters["write_errors"] += 1
        self.counters["lost"] += sum(isinstance(r, Odometry | Observation) for r in self._pending)
        self._pending.clear()
        self._buffer.clear()
        self._queued_checkpoints.clear()
        log.error("journal %s: %s; journalling stops here (the map is still served, but a restart would "
                  "rebuild it only up to this point)", self.path, exc)

    def maybe_sync(self) -> None:
        """fsync if ``sync_every`` records or ``sync_interval_s`` have passed since
        the oldest record not yet on disk (call it from the loop, also when idle)."""
        if self._unsynced and not self._buffer and not self.failed and (
                self._unsynced >= self.sync_every
                or time.monotonic() - self._unsynced_since >= self.sync_interval_s):
            if self._syncer is not None:
                self._unsynced = 0
                self._syncer.request()
                return
            self._unsynced = 0
            try:
                self._fsync()
            except OSError as exc:
                self._fail(exc)

    def _fsync(self) -> None:
        """fsync now, in this thread (the header, batches without the background
        thread, the last batch at close)."""
        t0 = time.perf_counter()
        os.fsync(self._fd)
        self.sync_s_total += time.perf_counter() - t0
        self.counters["fsyncs"] += 1

    def __enter__(self) -> Journal:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Flush, fsync and close (idempotent)."""
        if self._fd < 0:
            return
        try:
            self.flush()
            if self._syncer is not None:
                self._syncer.stop()  # finishes a pending fsync first
                if self._syncer.error is not None and not self.failed:
                    self._fail(self._syncer.error)
            if self._unsynced and not self.failed:
                self._unsynced = 0
                try:
                    self._fsync()
                except OSError as exc:
                    self._fail(exc)
        finally:
            os.close(self._fd)
            self._fd = -1

    def as_counters(self, prefix: str = "journal_") -> dict[str, int]:
        """Counters for the server's status (``journal_records`` = measurements in the
        file, replayed ones included)."""
        out = {prefix + k: v for k, v in self.counters.items()}
        out[prefix + "replay_ms"] = round(self.replay_s * 1e3)
        return out
