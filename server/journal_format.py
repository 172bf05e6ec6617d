"""The journal's file format: record structs, framing and CRC, and a tolerant reader.

Pure bytes-in/bytes-out (no fusion, no locking, no fsync): :mod:`tagswarm.server.journal`
writes and replays through it, and tools (bench, tests) read journals with it.

File format (little endian)::

    b"TSWJRNL1"                                   8-byte magic
    [u32 length][u32 CRC32 of payload][payload]   one frame per record; payload is a
    ...                                            msgpack-encoded tagged Struct (below)

The first record is a :class:`Header`.  A crash can leave a torn last frame
(power loss mid-write); :class:`Reader` stops at the first frame that is short,
too long, fails its CRC or does not decode, and reports how long the good prefix is.
A :class:`Reader` can also start at any frame boundary (a checkpoint's offset).

Versions: 2 added NewRun records, 3 Checkpoint records.  The side index
(``PATH.index``, :func:`read_index` / :func:`write_index`) names where the newest
checkpoints start; it is a hint, the journal is the truth.
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated, Any, Final, Literal

import msgspec
import numpy as np

MAGIC: Final = b"TSWJRNL1"
VERSION: Final = 3  # 2: NewRun records, 3: Checkpoint records
_FRAME: Final = struct.Struct("<II")  # payload length in bytes, CRC32 of the payload
FRAME_BYTES: Final = _FRAME.size
# a checkpoint of a large swarm's 30 s window is a few MB (4 robots: ~0.2 MB); anything longer is corruption
MAX_RECORD_BYTES: Final = 1 << 26

StampNs = Annotated[int, msgspec.Meta(ge=0)]
RobotId = Annotated[int, msgspec.Meta(ge=0, le=100_000)]


class Header(msgspec.Struct, frozen=True, kw_only=True, tag="header"):
    """What the journal's records are valid for: the run id, the map (origin,
    roster, landmark poses ``(x_m, y_m, yaw_rad)`` in the arena frame) and the
    fusion parameters (``dataclasses.asdict(FusionParams)``)."""

    version: int = VERSION
    run: str
    origin_id: int
    robot_ids: tuple[int, ...]
    landmarks: dict[int, tuple[float, float, float]]
    params: dict[str, float]


class Odometry(msgspec.Struct, frozen=True, kw_only=True, tag="odom"):
    """Cumulative odometry of ``robot_id`` (base_link in its odom frame) at ``stamp_ns``."""

    robot_id: RobotId
    stamp_ns: StampNs
    x_m: float
    y_m: float
    yaw_rad: float
    distance_m: float
    slip_m: float = 0.0  # cumulative slip evidence (older journals: 0)


class Observation(msgspec.Struct, frozen=True, kw_only=True, tag="obs"):
    """Target (robot or landmark) in ``observer``'s base frame at ``stamp_ns``;
    ``cov`` is the row-major (3, 3) covariance of (x_m, y_m, yaw_rad)."""

    observer: RobotId
    target_kind: Literal["robot", "landmark"]
    target_id: int
    stamp_ns: StampNs
    x_m: float
    y_m: float
    yaw_rad: float
    cov: Annotated[tuple[float, ...], msgspec.Meta(min_length=9, max_length=9)]


class Advance(msgspec.Struct, frozen=True, kw_only=True, tag="advance"):
    """``Fusion.advance(watermark_ns)`` was called here."""

    watermark_ns: int


class NewRun(msgspec.Struct, frozen=True, kw_only=True, tag="new_run"):
    """The world restarted (new ``run_id``): the map starts afresh here (``Fusion.reset()``)."""

    run_id: str


class Checkpoint(msgspec.Struct, frozen=True, kw_only=True, tag="checkpoint"):
    """The server's whole state right after ``Fusion.advance(watermark_ns)``: a restarted
    server replays from its last checkpoint instead of from the first record.

    ``seq`` numbers the journal's checkpoints from 1.  ``counts`` are the journal's record
    counters (``records``, ``odometry``, ``observations``, ``advances``, ``new_runs``,
    ``checkpoints``) of everything before this record, so totals stay right without
    reading it.  ``node`` is the server's own bookkeeping (``time_ns`` and its
    ``accepted_*`` counters), ``latest_rx`` each robot's newest odometry stamp (ns), and
    ``fusion`` the snapshot of :mod:`tagswarm.server.checkpoint` (compressed, opaque here)."""

    seq: Annotated[int, msgspec.Meta(ge=1)]
    watermark_ns: int
    counts: dict[str, int]
    node: dict[str, int]
    latest_rx: dict[int, int]
    fusion: bytes


Record = Header | Odometry | Observation | Advance | NewRun | Checkpoint


def _enc_hook(obj: Any) -> Any:
    # numpy scalars (from callers doing maths on poses) are stored as plain numbers
    if isinstance(obj, np.floating | np.integer):
        return obj.item()
    raise NotImplementedError(f"cannot journal {type(obj).__name__}")


_ENCODER: Final = msgspec.msgpack.Encoder(enc_hook=_enc_hook)
_DECODER: Final = msgspec.msgpack.Decoder(Record)  # type: ignore[arg-type]


def frame(record: Record) -> bytes:
    """One record as it is stored: length, CRC32, msgpack payload."""
    payload = _ENCODER.encode(record)
    return _FRAME.pack(len(payload), zlib.crc32(payload)) + payload


class Reader:
    """Iterates the records of a journal file, stopping at the first bad frame.

    After iteration, ``valid_bytes`` is the length of the good prefix (magic
    included) and ``problem`` says why reading stopped early (``None`` at a clean
    end): ``"torn"`` (file ends inside a frame), ``"oversized"``, ``"crc"`` or
    ``"malformed"`` (CRC fine but the payload is not a record).  ``bad_magic`` is
    set if the file is not a journal at all (then nothing is yielded).

    With ``start`` (a frame boundary past the magic, e.g. a checkpoint's offset) the
    magic is still checked, then reading begins there; ``offset`` is where the last
    yielded record's frame starts.
    """

    def __init__(self, path: str | os.PathLike[str], start: int = 0) -> None:
        self.path = Path(path)
        self.start = start
        self.valid_bytes = 0
        self.file_bytes = 0
        self.offset = 0
        self.problem: str | None = None
        self.bad_magic = False

    def __iter__(self) -> Iterator[Record]:
        with open(self.path, "rb") as f:
            self.file_bytes = os.fstat(f.fileno()).st_size
            magic = f.read(len(MAGIC))
            if magic != MAGIC:
                # a file cut inside the magic is an empty journal, anything else is not ours
                self.bad_magic = not MAGIC.startswith(magic)
                self.problem = None if not magic else ("torn" if not self.bad_magic else "bad_magic")
                return
            self.valid_bytes = len(MAGIC)
            if self.start > len(MAGIC):
                if self.start > self.file_bytes:
                    self.problem = "torn"
                    return
                f.seek(self.start)
                self.valid_bytes = self.start
            while True:
                head = f.read(_FRAME.size)
                if not head:
                    return
                if len(head) < _FRAME.size:
                    self.problem = "torn"
                    return
                length, crc = _FRAME.unpack(head)
                if length > MAX_RECORD_BYTES:
                    self.problem = "oversized"
                    return
                payload = f.read(length)
                if len(payload) < length:
                    self.problem = "torn"
                    return
                if zlib.crc32(payload) != crc:
                    self.problem = "crc"
                    return
                try:
                    record: Record = _DECODER.decode(payload)
                except (msgspec.DecodeError, msgspec.ValidationError):
                    self.problem = "malformed"
                    return
                self.offset = self.valid_bytes
                self.valid_bytes += _FRAME.size + length
                yield record


def read_index(path: str | os.PathLike[str], index_path: str | os.PathLike[str], body: int) -> list[tuple[int, int]]:
    """The ``(offset, seq)`` entries of a journal's side index (JSON ``{"checkpoints":
    [[offset, seq], ...]}``) that point at a checkpoint with that ``seq`` in the journal at
    ``path``, past its header (which ends at ``body``), oldest first.  The index is only a
    hint: a missing, unreadable, stale or foreign one yields no (or fewer) entries."""
    try:
        entries = json.loads(Path(index_path).read_text())["checkpoints"]
        pairs = [(int(o), int(s)) for o, s in entries]
    except (OSError, ValueError, KeyError, TypeError):
        return []
    good = []
    for offset, seq in sorted(set(pairs)):
        if offset < body:
            continue
        rec = next(iter(Reader(path, offset)), None)
        if isinstance(rec, Checkpoint) and rec.seq == seq:
            good.append((offset, seq))
    return good


def write_index(index_path: str | os.PathLike[str], checkpoints: list[tuple[int, int]]) -> None:
    """Replace the side index with ``checkpoints`` (``(offset, seq)``, oldest first)
    atomically (temporary file, then rename); no entries removes it.  Raises OSError."""
    index = Path(index_path)
    if not checkpoints:
        index.unlink(missing_ok=True)
        return
    tmp = index.with_name(index.name + ".tmp")
    tmp.write_text(json.dumps({"checkpoints": [list(c) for c in checkpoints]}) + "\n")
    os.replace(tmp, index)


def read_journal(path: str | os.PathLike[str]) -> tuple[list[Record], Reader]:
    """Every good record of the journal at ``path`` (header first) and the reader
    (for ``valid_bytes`` / ``problem``).  Never raises on bad content."""
    reader = Reader(path)
    return list(reader), reader
