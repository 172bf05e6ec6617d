"""The fusion's fixed-lag smoother (server/smoother.py): one sequence of updates gives one
result, the same as GTSAM's IncrementalFixedLagSmoother up to rounding (no network)."""

from __future__ import annotations

import gzip
import hashlib
import math
from pathlib import Path

import gtsam
import numpy as np
import pytest

from tagswarm.server import journal as jr
from tagswarm.server.config import build_config
from tagswarm.server.node import make_fusion
from tagswarm.server.smoother import BayesTree, FixedLagSmoother, SmootherError, keys_to_reeliminate

# A corridor run's server journal from its 60.2 s checkpoint to the 65.43 s advance whose smoother
# update marginalises 4 keys at once.  With GTSAM's own smoother, 40 replays of it in one process
# gave one of two results (35 : 5): the keys it re-eliminates reached iSAM2 in an order that
# followed the cliques' memory addresses.
KNIFE = Path(__file__).parents[2] / "data" / "corridor_marginalise4.journal.gz"


def _fingerprint(records: list[jr.Record]) -> str:
    fusion = make_fusion(build_config(["--scenario", "corridor", "--clock", "lockstep"], {}))
    for rec in records:
        jr.apply(fusion, rec)
    h = hashlib.sha1()
    for rid, r in sorted(fusion.robots.items()):
        h.update(repr((rid, r.estimate)).encode())
        h.update(np.asarray(r.cov).tobytes())
    return h.hexdigest()


def _churn(n: int) -> None:
    """Leave the heap in another state: a throw-away smoother of ``n`` poses, most of it freed."""
    junk = FixedLagSmoother(0.5, gtsam.ISAM2Params())
    noise = gtsam.noiseModel.Isotropic.Sigma(3, 0.1)
    for i in range(n):
        g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if i == 0:
            g.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(), noise))
        else:
            g.add(gtsam.BetweenFactorPose2(i - 1, i, gtsam.Pose2(0.1, 0.0, 0.01), noise))
        v.insert(i, gtsam.Pose2(0.1 * i, 0.0, 0.0))
        junk.update(g, v, {i: 0.1 * i})


def test_a_journal_replayed_again_and_again_in_one_process_gives_the_same_bits(tmp_path: Path) -> None:
    journal = tmp_path / "server.journal"
    journal.write_bytes(gzip.decompress(KNIFE.read_bytes()))
    records, reader = jr.read_journal(journal)
    assert reader.problem is None
    body = records[1:]  # after the header: the checkpoint first
    assert isinstance(body[0], jr.Checkpoint)
    prints = set()
    for k in range(30):
        _churn(7 + 13 * k % 50)
        prints.add(_fingerprint(body))
    assert len(prints) == 1


def _swarm_updates(n_robots: int = 4, seconds: float = 8.0, dt: float = 0.1):  # type: ignore[no-untyped-def]
    """Each robot drives a circle; every ``dt`` each gets a keyframe (all at the same stamp, so
    several leave the window at once), tied by odometry and by a view of the next robot."""
    rng = np.random.default_rng(4)
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.01, 0.01, 0.005]))
    view = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.03, 0.03, 0.02]))
    truth = [gtsam.Pose2(2.0 * r, 0.0, 0.3 * r) for r in range(n_robots)]
    step = gtsam.Pose2(0.05, 0.0, 0.04)
    for k in range(round(seconds / dt)):
        g, v, stamps = gtsam.NonlinearFactorGraph(), gtsam.Values(), {}
        for r in range(n_robots):
            key = r * 100_000 + k
            if k == 0:
                sigma = 0.001 if r == 0 else 1.0
                g.add(gtsam.PriorFactorPose2(key, truth[r], gtsam.noiseModel.Isotropic.Sigma(3, sigma)))
            else:
                truth[r] = truth[r].compose(step)
                meas = step.compose(gtsam.Pose2(*rng.normal(0.0, [0.01, 0.01, 0.005])))
                g.add(gtsam.BetweenFactorPose2(key - 1, key, meas, noise))
            v.insert(key, truth[r].compose(gtsam.Pose2(*rng.normal(0.0, 0.02, 3))))
            stamps[key] = k * dt
        for r in range(n_robots):
            a, b = r * 100_000 + k, ((r + 1) % n_robots) * 100_000 + k
            rel = truth[r].between(truth[(r + 1) % n_robots]).compose(gtsam.Pose2(*rng.normal(0.0, 0.01, 3)))
            g.add(gtsam.BetweenFactorPose2(a, b, rel, view))
        yield g, v, stamps


def test_it_follows_gtsams_own_smoother_to_rounding() -> None:
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(0.01)
    params.relinearizeSkip = 5
    ours, theirs = FixedLagSmoother(1.0, params), gtsam.IncrementalFixedLagSmoother(1.0, params)
    for g, v, stamps in _swarm_updates():
        ours.update(g, v, stamps)
        s = gtsam.FixedLagSmootherKeyTimestampMap()
        for key, t in stamps.items():
            s.insert((key, t))
        theirs.update(g, v, s)
    window = sorted(ours.timestamps())
    assert window == sorted(int(k) for k in theirs.timestamps())
    assert len(window) == 4 * 11  # 1 s of keyframes at 10 Hz for 4 robots (stamps 6.9..7.9 s)
    worst, worst_cov = 0.0, 0.0
    for key in window:
        a, b = ours.calculateEstimatePose2(key), theirs.calculateEstimatePose2(key)
        worst = max(worst, math.hypot(a.x() - b.x(), a.y() - b.y()), abs(a.theta() - b.theta()))
        ca, cb = ours.marginalCovariance(key), np.asarray(theirs.marginalCovariance(key))
        worst_cov = max(worst_cov, float(np.abs(ca - cb).max() / np.abs(cb).max()))
    assert worst < 1e-9
    assert worst_cov < 1e-6


# kept variables: 2, 5, 6, 7, 10, 11; marginal: 1, 3, 4, 8, 9
TREE = """digraph G{
10[label="10, 11"];
10->1
1[label="1, 5 : 10"];
1->2
2[label="2 : 1, 5"];
10->6
6[label="6, 3 : 10, 11"];
6->7
7[label="7 : 3"];
10->4
4[label="4 : 10"];
10->8
8[label="8 : 10"];
8->9
9[label="9 : 8"];
}"""


def test_the_keys_to_re_eliminate_are_those_between_marginal_and_kept_variables() -> None:
    tree = BayesTree(TREE)
    assert tree.frontals("6") == [6, 3] and tree.parents("7") == {3} and tree.children["10"] == ["1", "6", "4", "8"]
    # 1 has a kept child below it (2 depends on it): 1's clique and 2's; 3 comes after the kept 6 in
    # its clique: 6's clique and 7's, which depends on 3; 4 and the 8-9 subtree are leaves already
    assert keys_to_reeliminate(tree, [1, 3, 4, 8, 9]) == [1, 2, 3, 5, 6, 7]
    assert keys_to_reeliminate(tree, [4]) == []
    assert keys_to_reeliminate(tree, [8]) == [8, 9]  # 9 is kept and hangs on 8


def test_the_tree_read_from_isam2_holds_every_variable_once() -> None:
    ours = FixedLagSmoother(100.0, gtsam.ISAM2Params())
    for g, v, stamps in _swarm_updates(seconds=1.0):
        ours.update(g, v, stamps)
    tree = BayesTree.of(ours.isam)
    frontals = [k for c in tree.labels for k in tree.frontals(c)]
    assert sorted(frontals) == sorted(ours.timestamps())
    for c, kids in tree.children.items():
        for ch in kids:  # a child's separator lies in its parent's variables or above
            assert tree.parents(ch), (c, ch)


def test_a_refused_update_raises_the_smoothers_error() -> None:
    ours = FixedLagSmoother(1.0, gtsam.ISAM2Params())
    g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
    g.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(), gtsam.noiseModel.Diagonal.Sigmas(np.array([1e-9, 1e9, 1e9]))))
    v.insert(0, gtsam.Pose2())
    with pytest.raises(SmootherError):
        ours.update(g, v, {0: 0.0})


def test_in_batches_the_window_spans_the_lag_to_the_lag_plus_the_batch() -> None:
    ours = FixedLagSmoother(1.0, gtsam.ISAM2Params(), batch_s=0.5)
    spans = []
    for g, v, stamps in _swarm_updates(seconds=4.0):
        ours.update(g, v, stamps)
        t = sorted(set(ours.timestamps().values()))
        spans.append(round(t[-1] - t[0], 6))
    # 10 Hz keyframes: the window grows to 1.5 s, then drops back to 1.0 s at once (0.9 s where the
    # stamps' rounding puts the oldest kept one a hair past the lag, as in GTSAM's own comparison)
    assert spans[:16] == [round(0.1 * k, 6) for k in range(16)]
    assert spans[16] == 1.0 and spans.count(1.5) >= 3
    assert all(0.9 <= s <= 1.5 for s in spans[16:])
    assert len(ours.timestamps()) in range(4 * 10, 4 * 16 + 1)
