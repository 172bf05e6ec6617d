"""A server node restarted on a journal with checkpoints comes back with the dead
one's node-side bookkeeping (accepted counts, newest odometry stamps, clock) and
map, having replayed only the records after its last checkpoint.

The nodes run in this process and are fed through their accept/advance path (what
``step`` does with drained inputs), so the test decides exactly where the
checkpoints fall; each node has a loopback session of its own."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from tagswarm.protocol.bus import BusConfig, open_bus
from tagswarm.server import checkpoint as ckpt
from tagswarm.server import journal as jr
from tagswarm.server.config import build_config
from tagswarm.server.node import ServerNode
from tests.harness import endpoint

COV = (1e-4, 0.0, 0.0, 0.0, 1e-4, 0.0, 0.0, 0.0, 1e-4)
DT = 100_000_000
TICKS = 31  # 3 s at 10 Hz: checkpoints at 0.5, 1.0, ... 3.0 s
SILENT_FROM = 26  # robot 1 sends no odometry after the 2.5 s checkpoint: its newest stamp is only in there


def _argv(ep: str, journal: Path) -> list[str]:
    return ["--listen", ep, "--run", "ckpt", "--set", "robots.count=2", "--set", 'robots.placement="ring"',
            "--set", "missions=[]", "--journal", str(journal), "--journal-checkpoint", "0.5"]


def _feed(node: ServerNode, k: int) -> None:
    """Tick ``k``: both robots' odometry (robot 1 drives along x, and falls silent at
    ``SILENT_FROM``), robot 0 sees robot 1 every other tick."""
    stamp = k * DT
    for rid in (0, 1) if k < SILENT_FROM else (0,):
        x = 0.02 * k * rid
        node._accept(jr.Odometry(robot_id=rid, stamp_ns=stamp, x_m=x, y_m=0.0, yaw_rad=0.0, distance_m=x))
    if k % 2 == 0:
        node._accept(jr.Observation(observer=0, target_kind="robot", target_id=1, stamp_ns=stamp,
                                    x_m=2.0 + 0.02 * k, y_m=1.0, yaw_rad=math.pi, cov=COV))
    node.time_ns = stamp
    node._advance(stamp)


def test_a_restarted_node_resumes_from_its_last_checkpoint(tmp_path: Path) -> None:
    journal = tmp_path / "server.journal"
    ep = endpoint()
    with open_bus(BusConfig(listen=(ep,))) as bus:
        first = ServerNode(build_config(_argv(ep, journal), {}), bus)
        for k in range(TICKS - 2):
            _feed(first, k)  # the last checkpoint comes at 2.5 s; two more ticks follow it
        assert first.counters["checkpoints"] == 5
        first.close()  # what a SIGKILL leaves is the same: every record was flushed
        before = (first.global_map(), dict(first.latest_rx), first.time_ns, first.counters["accepted_odometry"],
                  first.counters["accepted_observations"], first.fusion.counters.copy())
        assert len(before[0].robots) == 2  # both localised
    ep = endpoint()
    with open_bus(BusConfig(listen=(ep,))) as bus:
        second = ServerNode(build_config(_argv(ep, journal), {}), bus)
        assert second.journal is not None
        c = second.journal.counters
        # the 5th checkpoint, then ticks 26..28: robot 0's odometry, observations at 26 and 28, the updates
        assert c["replayed"] == 1 + 3 * 2 + 2
        assert c["replay_skipped"] == 26 * 3 + 13 + 4  # ticks 0..25, their 13 observations, 4 checkpoints
        after = (second.global_map(), dict(second.latest_rx), second.time_ns,
                 second.counters["accepted_odometry"], second.counters["accepted_observations"],
                 second.fusion.counters.copy())
        assert after == before
        assert c["records"] == before[3] + before[4] == 2 * 26 + 3 + 15
        assert before[1] == {0: 28 * DT, 1: 25 * DT}
        # it carries on from there: the next checkpoint falls where the first server's would have
        for k in range(TICKS - 2, TICKS):
            _feed(second, k)
        assert second.counters["checkpoints"] == 1 and second.journal.last_seq == 6
        second.close()
    records = jr.read_journal(journal)[0]
    assert [r.watermark_ns for r in records if isinstance(r, jr.Checkpoint)] == [k * 5 * DT for k in range(1, 7)]


def test_a_new_world_run_restarts_the_checkpoint_schedule(tmp_path: Path) -> None:
    """After a world restart (NewRun: clock back at 0) the next checkpoint is due
    ``--journal-checkpoint`` into the new run, and a restart rebuilds the new run's map."""
    journal = tmp_path / "server.journal"
    ep = endpoint()
    with open_bus(BusConfig(listen=(ep,))) as bus:
        first = ServerNode(build_config(_argv(ep, journal), {}), bus)
        for k in range(12):  # checkpoints at 0.5 and 1.0 s of the first run
            _feed(first, k)
        record = jr.NewRun(run_id="world-2")  # what _accept_tick journals and applies on a new run
        assert first.journal is not None
        first.journal.append(record)
        first._replay(record)
        for k in range(8):  # 0.7 s of the new run: one checkpoint, at 0.5 s
            _feed(first, k)
        assert first.counters["checkpoints"] == 3
        first.close()
        before = (first.global_map(), dict(first.latest_rx), first.time_ns)
    records = jr.read_journal(journal)[0]
    kinds = [type(r).__name__ for r in records]
    assert kinds.count("Checkpoint") == 3 and kinds.index("NewRun") < len(kinds) - 1 - kinds[::-1].index("Checkpoint")
    assert [r.watermark_ns for r in records if isinstance(r, jr.Checkpoint)] == [5 * DT, 10 * DT, 5 * DT]
    ep = endpoint()
    with open_bus(BusConfig(listen=(ep,))) as bus:
        second = ServerNode(build_config(_argv(ep, journal), {}), bus)
        # the new run's checkpoint, then ticks 6 (odometry x2, observation, update) and 7 (odometry x2, update)
        assert second.journal is not None and second.journal.counters["replayed"] == 1 + (2 + 1 + 1) + (2 + 1)
        assert (second.global_map(), dict(second.latest_rx), second.time_ns) == before
        second.close()


def test_a_checkpoint_that_does_not_restore_is_skipped_live_and_on_rebuild(tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """If restoring from a checkpoint just written fails (it should not), the server carries
    on unrestored; a rebuild skips that checkpoint too and so ends in the same state."""
    journal = tmp_path / "server.journal"
    ep = endpoint()
    real = ckpt.snapshot
    with open_bus(BusConfig(listen=(ep,))) as bus:
        first = ServerNode(build_config(_argv(ep, journal), {}), bus)
        for k in range(TICKS - 2):
            if k == 20:  # the checkpoints at 2.0 and 2.5 s are unusable
                monkeypatch.setattr(ckpt, "snapshot", lambda fusion: b"\x78\x01garbage")
            _feed(first, k)
        assert first.counters["checkpoints"] == 3 and first.counters["checkpoint_errors"] == 2
        first.close()
        before = (first.global_map(), dict(first.latest_rx), first.time_ns, first.fusion.counters.copy())
    monkeypatch.setattr(ckpt, "snapshot", real)
    ep = endpoint()
    with open_bus(BusConfig(listen=(ep,))) as bus:
        second = ServerNode(build_config(_argv(ep, journal), {}), bus)
        assert second.journal is not None
        c = second.journal.counters
        assert c["bad_checkpoints"] == 2 and c["checkpoints"] == 5
        assert c["replay_skipped"] == 16 * 3 + 8 + 2  # before the 1.5 s checkpoint: ticks 0..15, 2 checkpoints
        assert (second.global_map(), dict(second.latest_rx), second.time_ns, second.fusion.counters) == before
        second.close()
