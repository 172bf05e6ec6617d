"""Stitching and factor-graph fusion on synthetic data (no network)."""

from __future__ import annotations

import math

import numpy as np

from tagswarm.protocol.geometry import se2_between, se2_compose
from tagswarm.server.fusion import Fusion, FusionParams
from tagswarm.server.stitch import Edge, stitch
from tests.synthetic import SyntheticSwarm

COV = np.diag([1e-4, 1e-4, 1e-4])


def test_stitching_is_exact_on_noise_free_chains() -> None:
    truth = {0: (0.0, 0.0, 0.0), 1: (2.0, 1.0, 0.5), 2: (3.0, -1.0, -2.0), 3: (-1.0, 2.0, 3.0), 4: (5.0, 5.0, 0.0)}
    edges = [
        Edge(0, 1, se2_between(truth[0], truth[1]), COV),
        Edge(2, 1, se2_between(truth[2], truth[1]), COV),   # 2 is reached only through 1 (observed by 2)
        Edge(2, 3, se2_between(truth[2], truth[3]), COV),   # 3 only through a chain of two
    ]
    placed = stitch(edges, origin=0)
    assert set(placed) == {0, 1, 2, 3}  # robot 4 is seen by nobody: left out, not put at (0, 0)
    for rid, pose in placed.items():
        assert np.allclose(pose[:2], truth[rid][:2], atol=1e-9)
        assert abs(math.remainder(pose[2] - truth[rid][2], 2 * math.pi)) < 1e-9


def test_stitching_prefers_the_more_certain_edge() -> None:
    good, bad = se2_between((0, 0, 0), (1.0, 0.0, 0.0)), (1.5, 0.3, 0.2)
    placed = stitch([Edge(0, 1, bad, COV * 100), Edge(0, 1, good, COV)], origin=0)
    assert np.allclose(placed[1], (1.0, 0.0, 0.0))


def _run(sw: SyntheticSwarm, seconds: float, params: FusionParams | None = None) -> tuple[Fusion, list, list, int]:
    fed_outliers = 0
    fusion = Fusion(params or FusionParams(odom_scale_sigma=0.05), 0, tuple(range(sw.n)))
    fused_err, odom_err = [], []
    dt = 1.0 / sw.rate_hz
    steps = int(seconds * sw.rate_hz)
    for k in range(steps + 1):
        t = k * dt
        stamp = round(t * 1e9)
        odom, obs = sw.step(t)
        for rid, pose in enumerate(odom):
            fusion.add_odometry(rid, stamp, pose, distance_m=0.2 * t * rid)
        if k % 5 == 0:
            for i, j, z, cov, outlier in obs:
                fusion.add_observation(i, j, stamp, z, cov)
                fed_outliers += outlier
        fusion.advance(stamp)
    for rid in range(1, sw.n):
        truth = sw.truth(rid, steps * dt)
        est = fusion.pose(rid)
        assert est is not None
        fused_err.append(math.hypot(est[0][0] - truth[0], est[0][1] - truth[1]))
        start = sw.truth(rid, 0.0)
        dr = se2_compose(start, odom[rid])
        odom_err.append(math.hypot(dr[0] - truth[0], dr[1] - truth[1]))
    return fusion, fused_err, odom_err, fed_outliers


def test_fusion_beats_odometry_5x_and_rejects_outliers() -> None:
    sw = SyntheticSwarm(n=4, seed=1, outlier_rate=0.05)
    fusion, fused_err, odom_err, outliers = _run(sw, 120.0)
    assert outliers > 20
    assert float(np.mean(fused_err)) * 5 < float(np.mean(odom_err)), (fused_err, odom_err)
    assert max(fused_err) < 0.1
    rejected = fusion.counters["rejected_gate"]
    # every outlier caught, at most 2% of the inliers refused
    assert outliers * 0.95 <= rejected <= outliers + 0.02 * fusion.counters["accepted_observations"], \
        (fusion.counters, outliers)


def test_memory_is_bounded_by_the_lag() -> None:
    sw = SyntheticSwarm(n=3, seed=2, outlier_rate=0.0)
    fusion, _, _, _ = _run(sw, 200.0, FusionParams(lag_s=10.0, odom_scale_sigma=0.05))
    live = fusion.smoother.calculateEstimate().size()
    assert fusion.counters["keyframes"] > 5 * live, (fusion.counters["keyframes"], live)
    assert live < 3 * 10 * 12  # ~ robots x lag x keyframes/s


def test_restarted_odometry_starts_a_new_chain_near_the_old_pose() -> None:
    fusion = Fusion(FusionParams(), 0, (0, 1))
    for k in range(30):
        fusion.add_odometry(0, k * 10**8, (0.0, 0.0, 0.0), 0.0)
        fusion.add_odometry(1, k * 10**8, (0.01 * k, 0.0, 0.0), 0.01 * k)
        if 5 <= k <= 7:  # three agreeing observations place robot 1
            fusion.add_observation(0, 1, k * 10**8, (1.0 + 0.01 * k, 0.0, 0.0), COV)
        fusion.advance(k * 10**8)
    before = fusion.pose(1)
    assert before is not None
    for k in range(30, 40):  # agent 1 restarted: odometry from zero, distance reset
        fusion.add_odometry(0, k * 10**8, (0.0, 0.0, 0.0), 0.0)
        fusion.add_odometry(1, k * 10**8, (0.0, 0.0, 0.0), 0.0)
        fusion.advance(k * 10**8)
    after = fusion.pose(1)
    assert fusion.counters["odometry_restarts"] == 1 and fusion.counters["deferred_init"] == 2
    assert after is not None and math.dist(before[0][:2], after[0][:2]) < 0.05


def test_a_lone_flipped_first_observation_does_not_place_a_robot() -> None:
    fusion = Fusion(FusionParams(), 0, (0, 1))
    true_rel = (2.0, 0.5, 3.0)
    for k in range(12):
        fusion.add_odometry(0, k * 10**8, (0.0, 0.0, 0.0), 0.0)
        fusion.add_odometry(1, k * 10**8, (0.0, 0.0, 0.0), 0.0)
        if k == 2:
            fusion.add_observation(0, 1, k * 10**8, (2.6, -0.4, 0.2), COV)  # a flipped pose
        elif k > 2:
            fusion.add_observation(0, 1, k * 10**8, true_rel, COV)
        fusion.advance(k * 10**8)
    est = fusion.pose(1)
    assert est is not None and math.dist(est[0][:2], true_rel[:2]) < 0.01
    assert fusion.counters["init_discarded"] == 1


def _late_run(delay_steps: int, params: FusionParams) -> tuple[Fusion, float]:
    """Robot 0 holds at the origin, robot 1 drives along x at 0.5 m/s (30 Hz odometry,
    exact); robot 0's observations of robot 1 (every 0.1 s, exact) reach the fusion
    ``delay_steps`` odometry steps after their stamp, as in a realtime run where the
    image still had to be rendered and detected.  Returns the fusion and robot 1's final
    position error (m)."""
    fusion = Fusion(params, 0, (0, 1))
    dt, start = 1e9 / 30, (1.0, 0.5, 0.0)
    queue: list[tuple[int, int, tuple[float, float, float]]] = []
    pose = start
    for k in range(150):
        t = round(k * dt)
        pose = (start[0] + 0.5 * k / 30, start[1], 0.0)
        fusion.add_odometry(0, t, (0.0, 0.0, 0.0), 0.0)
        fusion.add_odometry(1, t, (0.5 * k / 30, 0.0, 0.0), 0.5 * k / 30)
        if k % 3 == 0:
            queue.append((k + delay_steps, t, pose))  # robot 0 sits at the origin: relative = absolute
        while queue and queue[0][0] <= k:
            _, stamp, rel = queue.pop(0)
            fusion.add_observation(0, 1, stamp, rel, COV)
        fusion.advance(t)
    est = fusion.pose(1)
    assert est is not None
    return fusion, math.dist(est[0][:2], pose[:2])


def test_late_observations_within_the_window_are_fused_at_their_own_instant() -> None:
    on_time, err0 = _late_run(0, FusionParams())
    late, err = _late_run(6, FusionParams())  # 0.2 s late (robot 1 moved 10 cm since); the last 2 never land
    assert on_time.counters["late_observations"] == 0
    assert late.counters["late_observations"] == 48 and late.counters["rejected_late"] == 0
    assert late.counters["accepted_observations"] >= on_time.counters["accepted_observations"] - 2
    # fused where it was seen, not where it is when the message lands (that would be 10 cm off)
    assert err0 < 0.005 and err < 0.005, (err0, err)
    # beyond the window they are dropped, and the robot is never placed
    dropped = Fusion(FusionParams(late_obs_s=0.1), 0, (0, 1))
    for k in range(40):
        dropped.add_odometry(0, k * 10**8, (0.0, 0.0, 0.0), 0.0)
        dropped.add_odometry(1, k * 10**8, (0.0, 0.0, 0.0), 0.0)
        if k >= 3:  # 0.2 s behind the watermark when it lands
            dropped.add_observation(0, 1, (k - 3) * 10**8, (2.0, 0.0, 0.0), COV)
        dropped.advance(k * 10**8)
    assert dropped.counters["rejected_late"] == 37 and dropped.pose(1) is None
