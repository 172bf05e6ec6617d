"""What the journal's records mean to the server: the :class:`~tagswarm.server.fusion.Fusion` call
each one stands for (:func:`apply`, for the live server and the replay alike), the header a server
writes and the check of an existing journal's header against it, and the record counters a checkpoint
carries.  :mod:`tagswarm.server.journal` re-exports all of it.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from tagswarm.server import checkpoint as ckpt
from tagswarm.server.estimator import apply_input
from tagswarm.server.fusion import Fusion
from tagswarm.server.journal_format import Advance, Checkpoint, Header, NewRun, Observation, Odometry, Record

# the record counters a checkpoint carries (everything in the file before it)
COUNTED = ("records", "odometry", "observations", "advances", "new_runs", "checkpoints")


def apply(fusion: Fusion, record: Record) -> None:
    """Make the :class:`Fusion` call a record stands for (the live server and the
    replay both go through here, so they cannot diverge): a checkpoint restores the
    fusion's state, every other record is an input (:func:`~tagswarm.server.estimator.apply_input`)."""
    if isinstance(record, Checkpoint):
        ckpt.restore(fusion, record.fusion)
    else:
        apply_input(fusion, record)


def _count(counters: dict[str, int], record: Record) -> None:
    """Count one record (not the header) into ``counters``."""
    if isinstance(record, Advance):
        counters["advances"] += 1
    elif isinstance(record, NewRun):
        counters["new_runs"] += 1
    elif isinstance(record, Checkpoint):
        counters["checkpoints"] += 1
    elif isinstance(record, Odometry | Observation):
        counters["records"] += 1
        counters["odometry" if isinstance(record, Odometry) else "observations"] += 1


def _mismatch(want: Header, got: Header) -> str | None:
    """First difference between the journal's header and this server's, or None."""
    if got.version != want.version:
        return f"format version {got.version} (this server writes {want.version})"
    for name in ("run", "origin_id", "robot_ids", "landmarks", "params"):
        a, b = getattr(got, name), getattr(want, name)
        if a != b:
            if name == "params":
                diff = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
                return f"fusion parameters differ ({', '.join(diff)})"
            return f"{name} {a!r} (this server: {b!r})"
    return None


def header_for(run: str, fusion: Fusion) -> Header:
    """The header a server with this ``fusion`` writes (and expects)."""
    params: dict[str, Any] = {k: float(v) for k, v in dataclasses.asdict(fusion.p).items()}
    return Header(run=run, origin_id=fusion.origin_id, robot_ids=tuple(sorted(fusion.robots)),
                  landmarks={k: (float(v[0]), float(v[1]), float(v[2])) for k, v in fusion.landmarks.items()},
                  params=params)
