"""The server's write-ahead journal: format, torn and corrupt tails, exact replay (no network)."""

from __future__ import annotations

import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from tagswarm.server import journal as jr
from tagswarm.server.config import build_config
from tagswarm.server.fusion import Fusion, FusionParams
from tests.synthetic import SyntheticSwarm

COV9 = (1e-4, 0.0, 0.0, 0.0, 1e-4, 0.0, 0.0, 0.0, 1e-4)


def _fusion(n: int = 3) -> Fusion:
    return Fusion(FusionParams(odom_scale_sigma=0.05), 0, tuple(range(n)))


def _records(n: int) -> list[jr.Odometry | jr.Observation | jr.Advance]:
    out: list[jr.Odometry | jr.Observation | jr.Advance] = []
    for k in range(n):
        stamp = k * 100_000_000
        out.append(jr.Odometry(robot_id=k % 3, stamp_ns=stamp, x_m=0.1 * k, y_m=-0.2 * k, yaw_rad=0.01 * k,
                               distance_m=0.1 * k))
        if k % 3 == 0:
            out.append(jr.Observation(observer=0, target_kind="robot", target_id=1, stamp_ns=stamp, x_m=1.0 + k,
                                      y_m=0.5, yaw_rad=math.pi, cov=COV9))
        if k % 5 == 4:
            out.append(jr.Advance(watermark_ns=stamp))
    return out


def _write(path: Path, records: list[jr.Odometry | jr.Observation | jr.Advance], run: str = "r") -> jr.Journal:
    j = jr.Journal(path, jr.header_for(run, _fusion()))
    for rec in records:
        j.append(rec)
        j.flush()
    j.close()
    return j


def test_round_trip_keeps_every_record_and_counts_them(tmp_path: Path) -> None:
    path = tmp_path / "j"
    recs = _records(40)
    j = _write(path, recs)
    got, reader = jr.read_journal(path)
    assert got[0] == jr.header_for("r", _fusion())
    assert got[1:] == recs
    assert reader.problem is None and reader.valid_bytes == path.stat().st_size == j.counters["bytes"]
    measurements = sum(not isinstance(r, jr.Advance) for r in recs)
    assert j.counters["records"] == measurements and j.counters["advances"] == len(recs) - measurements
    # reopening replays the same records in order and appends after them
    seen: list[jr.Record] = []
    again = jr.Journal(path, jr.header_for("r", _fusion()), replay=seen.append)
    assert seen == recs and again.counters["replayed"] == len(recs) and again.counters["records"] == measurements
    extra = jr.Advance(watermark_ns=10**10)
    again.append(extra)
    again.close()
    assert jr.read_journal(path)[0][1:] == [*recs, extra]


def test_flushed_records_survive_without_close(tmp_path: Path) -> None:
    """What a SIGKILLed server leaves: everything flushed is readable, fsync or not."""
    path = tmp_path / "j"
    j = jr.Journal(path, jr.header_for("r", _fusion()), sync_every=10**6, sync_interval_s=1e9)
    recs = _records(10)
    for rec in recs:
        j.append(rec)
    j.flush()
    assert j.counters["fsyncs"] == 1  # only the new file's header so far
    assert jr.read_journal(path)[0][1:] == recs
    j.close()


def test_fsync_is_batched_by_record_count(tmp_path: Path) -> None:
    j = jr.Journal(tmp_path / "j", jr.header_for("r", _fusion()), sync_every=10, sync_interval_s=1e9,
                   background_sync=False)
    for rec in _records(20)[:25]:
        j.append(rec)
        j.flush()
    assert j.counters["fsyncs"] == 1 + 2  # header, then after records 10 and 20
    j.close()
    assert j.counters["fsyncs"] == 1 + 3  # close syncs the remaining 5
    # in the background (the default) the loop does not wait; requests made during an fsync coalesce
    path = tmp_path / "bg"
    j = jr.Journal(path, jr.header_for("r", _fusion()), sync_every=10, sync_interval_s=1e9)
    recs = _records(40)
    for rec in recs:
        j.append(rec)
        j.flush()
    j.close()
    assert 1 + 1 <= j.counters["fsyncs"] <= 1 + len(recs) // 10 + 1
    assert jr.read_journal(path)[0][1:] == recs


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full (a disk that is always full)")
def test_a_full_disk_stops_journalling_not_the_server(tmp_path: Path) -> None:
    path = tmp_path / "j"
    j = jr.Journal(path, jr.header_for("r", _fusion()), background_sync=False)
    recs = _records(9)
    good, bad = recs[:4], recs[4:]
    for rec in good:
        j.append(rec)
    j.flush()
    os.close(j._fd)
    j._fd = os.open("/dev/full", os.O_WRONLY)  # every write now fails with ENOSPC
    for rec in bad:
        j.append(rec)
    j.flush()  # no exception: the server keeps serving
    j.append(good[0])
    j.flush()
    j.close()
    assert j.failed and j.counters["write_errors"] == 1
    assert j.counters["records"] == sum(not isinstance(r, jr.Advance) for r in good)
    assert j.counters["lost"] == sum(not isinstance(r, jr.Advance) for r in bad) + 1
    assert jr.read_journal(path)[0][1:] == good


def test_torn_last_record_at_every_byte_offset(tmp_path: Path) -> None:
    src = tmp_path / "full"
    recs = _records(12)
    _write(src, recs)
    size = src.stat().st_size
    last = len(jr.frame(recs[-1]))
    for cut in range(size - last, size):
        path = tmp_path / f"cut{cut}"
        shutil.copyfile(src, path)
        with open(path, "r+b") as f:
            f.truncate(cut)
        got, reader = jr.read_journal(path)
        assert got[1:] == recs[:-1], cut
        assert reader.valid_bytes == size - last
        assert reader.problem == (None if cut == size - last else "torn"), cut
        # reopening truncates the torn bytes and appends cleanly after the good prefix
        j = jr.Journal(path, jr.header_for("r", _fusion()))
        assert j.counters["truncated_bytes"] == cut - (size - last)
        j.append(recs[-1])
        j.close()
        assert path.stat().st_size == size
        assert jr.read_journal(path)[0][1:] == recs
        path.unlink()


def test_crc_corruption_stops_reading_there(tmp_path: Path) -> None:
    path = tmp_path / "j"
    recs = _records(12)
    _write(path, recs)
    data = bytearray(path.read_bytes())
    # flip one payload byte of record 5 (after the magic, the header frame and 5 record frames)
    offset = len(jr.MAGIC) + len(jr.frame(jr.header_for("r", _fusion()))) + sum(len(jr.frame(r)) for r in recs[:5])
    data[offset + 8 + 3] ^= 0x40
    path.write_bytes(bytes(data))
    got, reader = jr.read_journal(path)
    assert got[1:] == recs[:5] and reader.problem == "crc" and reader.valid_bytes == offset
    j = jr.Journal(path, jr.header_for("r", _fusion()))
    assert j.counters["replayed"] == 5 and j.counters["truncated_bytes"] == len(data) - offset
    j.close()
    assert path.stat().st_size == offset
    # an absurd length field is not trusted either (no giant allocation, reading just stops)
    data = bytearray(path.read_bytes()) + jr.frame(recs[5])
    data[offset:offset + 4] = (2**31).to_bytes(4, "little")
    path.write_bytes(bytes(data))
    got, reader = jr.read_journal(path)
    assert got[1:] == recs[:5] and reader.problem == "oversized"


def test_a_journal_of_another_map_or_not_a_journal_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "j"
    _write(path, _records(5), run="one")
    before = path.read_bytes()
    with pytest.raises(jr.JournalError, match="run 'one'"):
        jr.Journal(path, jr.header_for("two", _fusion()))
    with pytest.raises(jr.JournalError, match="robot_ids"):
        jr.Journal(path, jr.header_for("one", _fusion(4)))
    other = Fusion(FusionParams(odom_scale_sigma=0.05, lag_s=10.0), 0, (0, 1, 2))
    with pytest.raises(jr.JournalError, match="lag_s"):
        jr.Journal(path, jr.header_for("one", other))
    assert path.read_bytes() == before  # refused, untouched
    with jr.Journal(path, jr.header_for("one", _fusion())) as _, pytest.raises(jr.JournalError, match="in use"):
        jr.Journal(path, jr.header_for("one", _fusion()))  # a second server on the same journal
    jr.Journal(path, jr.header_for("one", _fusion())).close()  # free again once the first one closed
    notes = tmp_path / "notes.txt"
    notes.write_text("my precious notes\n")
    with pytest.raises(jr.JournalError, match="not a tagswarm journal"):
        jr.Journal(notes, jr.header_for("one", _fusion()))
    assert notes.read_text() == "my precious notes\n"
    # an empty file or one cut inside the magic is a fresh journal
    for stub in (b"", jr.MAGIC[:3]):
        fresh = tmp_path / f"fresh{len(stub)}"
        fresh.write_bytes(stub)
        jr.Journal(fresh, jr.header_for("one", _fusion())).close()
        assert jr.read_journal(fresh)[0] == [jr.header_for("one", _fusion())]


def test_replay_rebuilds_exactly_the_live_graph(tmp_path: Path) -> None:
    """The live path (journal then fuse) and a replay of the journal make the same
    decisions (identical counters, edges, fix times) and the same estimates and
    covariances at every update, to floating-point rounding (GTSAM/Eigen may differ
    in the last bits between runs; usually they are bit-identical)."""
    sw = SyntheticSwarm(n=4, seed=5, outlier_rate=0.05)
    live = Fusion(FusionParams(odom_scale_sigma=0.05, lag_s=10.0), 0, tuple(range(4)))
    path = tmp_path / "j"
    j = jr.Journal(path, jr.header_for("r", live))
    history: list[dict[int, tuple[float, ...] | None]] = []

    def snapshot(f: Fusion) -> dict[int, tuple[float, ...] | None]:
        out: dict[int, tuple[float, ...] | None] = {}
        for rid in range(4):
            est = f.pose(rid)
            out[rid] = None if est is None else (*est[0], *np.asarray(est[1]).ravel())
        return out

    def feed(rec: jr.Odometry | jr.Observation | jr.Advance) -> None:
        j.append(rec)
        jr.apply(live, rec)

    for k in range(301):  # 30 s at 10 Hz: beyond the 10 s lag, so marginalisation is replayed too
        stamp = k * 100_000_000
        odom, obs = sw.step(k / 10)
        for rid, pose in enumerate(odom):
            feed(jr.Odometry(robot_id=rid, stamp_ns=stamp, x_m=pose[0], y_m=pose[1], yaw_rad=pose[2],
                             distance_m=0.02 * k * rid))
        if k % 3 == 0:
            for i, t, z, cov, _ in obs:
                feed(jr.Observation(observer=i, target_kind="robot", target_id=t, stamp_ns=stamp, x_m=z[0], y_m=z[1],
                                    yaw_rad=z[2], cov=tuple(float(v) for v in cov.ravel())))
        feed(jr.Advance(watermark_ns=stamp))
        j.flush()
        history.append(snapshot(live))
    j.close()
    assert live.counters["accepted_observations"] > 100 and live.counters["rejected_gate"] > 0

    rebuilt = Fusion(FusionParams(odom_scale_sigma=0.05, lag_s=10.0), 0, tuple(range(4)))
    replayed: list[dict[int, tuple[float, ...] | None]] = []

    def on_record(rec: jr.Record) -> None:
        jr.apply(rebuilt, rec)
        if isinstance(rec, jr.Advance):
            replayed.append(snapshot(rebuilt))

    again = jr.Journal(path, jr.header_for("r", rebuilt), replay=on_record)
    again.close()
    assert len(replayed) == len(history) == 301
    for k, (got, want) in enumerate(zip(replayed, history, strict=True)):  # at every update
        assert got.keys() == want.keys() and all((got[r] is None) == (want[r] is None) for r in got), k
        for r, g in got.items():
            w = want[r]
            if g is not None and w is not None:
                assert np.allclose(g, w, rtol=1e-6, atol=1e-9), (k, r, g, w)
    assert rebuilt.counters == live.counters
    for rid in range(4):
        a, b = rebuilt.map_to_odom(rid), live.map_to_odom(rid)
        assert a is not None and b is not None and np.allclose(a, b, rtol=0, atol=1e-9)
        assert rebuilt.last_fix_ns(rid) == live.last_fix_ns(rid)
    assert rebuilt.edges == live.edges


def test_journal_flags_are_validated(tmp_path: Path) -> None:
    from tagswarm.runtime.config import ConfigError

    cfg = build_config(["--journal", str(tmp_path / "s.journal"), "--journal-sync-every", "8"], {})
    assert cfg.journal == str(tmp_path / "s.journal") and cfg.journal_sync_every == 8
    assert build_config([], {"TAGSWARM_JOURNAL": str(tmp_path / "e.journal")}).journal == str(tmp_path / "e.journal")
    assert build_config([], {}).journal is None
    for argv, msg in ((["--journal", str(tmp_path)], "is a directory"),
                      (["--journal", str(tmp_path / "no" / "j")], "does not exist"),
                      (["--journal-sync-every", "0"], "journal-sync-every"),
                      (["--journal-sync-ms", "-1"], "journal-sync-ms"),
                      (["--journal-checkpoint", "-1"], "journal-checkpoint"),
                      (["--journal-checkpoint", "inf"], "journal-checkpoint")):
        with pytest.raises(ConfigError, match=msg):
            build_config(argv, {})
    # checkpoints: every 10 simulated s unless told otherwise (flag over env), 0 = off
    assert build_config([], {}).journal_checkpoint_s == 10.0
    assert build_config(["--journal-checkpoint", "0"], {}).journal_checkpoint_s == 0.0
    assert build_config([], {"TAGSWARM_JOURNAL_CHECKPOINT": "2.5"}).journal_checkpoint_s == 2.5
    assert build_config(["--journal-checkpoint", "4"], {"TAGSWARM_JOURNAL_CHECKPOINT": "2.5"}).journal_checkpoint_s == 4
    with pytest.raises(ConfigError, match="not a number"):
        build_config([], {"TAGSWARM_JOURNAL_CHECKPOINT": "often"})
