"""The paper's stitched map as a live estimator (server/stitchmap.py): chains from the
origin, the freshest edge wins, odometry carries robots between sightings, unseen
robots stay out, landmarks place robots in the arena frame, covariances grow along
the chain."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tagswarm.protocol.geometry import Pose2, se2_between, se2_compose
from tagswarm.server.estimator import Estimator
from tagswarm.server.fusion import Fusion, FusionParams
from tagswarm.server.stitchmap import StitchMap

S = 1_000_000_000
COV = np.diag([1e-4, 1e-4, 1e-4])


def close(a: Pose2 | None, b: Pose2, tol: float = 1e-9) -> bool:
    assert a is not None
    return math.dist(a[:2], b[:2]) < tol and abs(math.remainder(a[2] - b[2], math.tau)) < tol


def rel(truth: dict[int, Pose2], o: int, g: int) -> Pose2:
    return se2_between(truth[o], truth[g])


def make(n: int = 4, landmarks: dict[int, Pose2] | None = None) -> StitchMap:
    return StitchMap(FusionParams(), 0, tuple(range(n)), landmarks)


def odom_all(sm: StitchMap, stamp: int, odom: dict[int, Pose2]) -> None:
    for rid, pose in odom.items():
        sm.add_odometry(rid, stamp, pose, distance_m=stamp / S)


def test_both_classes_satisfy_the_estimator_protocol() -> None:
    ests: list[Estimator] = [make(), Fusion(FusionParams(), 0, (0, 1))]
    assert all(e.localised() == [] for e in ests)


def test_chain_places_every_robot_reachable_from_the_origin() -> None:
    # odom frames = start poses, so at t=0 every robot's odometry is zero; truth in the map frame (robot 0's)
    truth = {0: (0.0, 0.0, 0.0), 1: (1.0, 0.5, 0.3), 2: (2.0, -0.5, -1.0), 3: (5.0, 5.0, 2.0)}
    sm = make()
    odom_all(sm, 0, dict.fromkeys(truth, (0.0, 0.0, 0.0)))
    sm.add_observation(0, 1, 0, rel(truth, 0, 1), COV)  # 0 sees 1
    sm.add_observation(2, 1, 0, rel(truth, 2, 1), COV)  # 2 sees 1: places 2 through the inverse
    sm.advance(0)
    assert sorted(sm.localised()) == [0, 1, 2]
    for rid in (0, 1, 2):
        est = sm.pose(rid)
        assert est is not None and close(est[0], truth[rid], 1e-9)
        assert close(sm.map_to_odom(rid), truth[rid], 1e-9)  # odometry zero at the start pose
    # unseen robot 3: never placed (not at (0, 0)), no pose, no correction
    assert sm.pose(3) is None and sm.map_to_odom(3) is None and sm.last_fix_ns(3) == -1
    # covariance grows along the chain 0 -> 1 -> 2
    tr = [float(np.trace(sm.pose(r)[1][:2, :2])) for r in (0, 1, 2)]  # type: ignore[index]
    assert tr[0] < tr[1] < tr[2]
    assert sm.edges == {(0, 1): 0, (2, 1): 0}


def test_odometry_carries_a_robot_between_sightings() -> None:
    truth1 = (1.0, 0.0, math.pi / 2)
    sm = make(2)
    odom_all(sm, 0, {0: (0.0, 0.0, 0.0), 1: (0.0, 0.0, 0.0)})
    sm.add_observation(0, 1, 0, truth1, COV)
    sm.advance(0)
    cov_then = sm.pose(1)[1]  # type: ignore[index]
    # robot 1 drives 2 m forward (its +x = map +y); nobody sees it any more
    for k in range(1, 21):
        odom_all(sm, k * S // 10, {0: (0.0, 0.0, 0.0), 1: (k * 0.1, 0.0, 0.0)})
        sm.advance(k * S // 10)
    est = sm.pose(1)
    assert est is not None and close(est[0], (1.0, 2.0, math.pi / 2), 1e-9)
    assert est[1][0, 0] + est[1][1, 1] > cov_then[0, 0] + cov_then[1, 1]  # odometry drift adds uncertainty
    assert sm.last_fix_ns(1) == 0


def test_the_freshest_edge_wins_and_stale_ones_are_forgotten() -> None:
    sm = StitchMap(FusionParams(), 0, (0, 1), None, memory_s=5.0)
    odom_all(sm, 0, {0: (0.0, 0.0, 0.0), 1: (0.0, 0.0, 0.0)})
    sm.add_observation(0, 1, 0, (1.0, 0.0, 0.0), COV)
    sm.advance(0)
    # robot 1's odometry says it stood still, yet a later sighting finds it elsewhere (drift, or a push):
    # the newest observation replaces the old one
    odom_all(sm, 2 * S, {0: (0.0, 0.0, 0.0), 1: (0.0, 0.0, 0.0)})
    sm.add_observation(0, 1, 2 * S, (1.5, 0.2, 0.1), COV)
    sm.advance(2 * S)
    assert close(sm.pose(1)[0], (1.5, 0.2, 0.1))  # type: ignore[index]
    assert sm.last_fix_ns(1) == 2 * S
    # an observation arriving late, older than the pair's newest, does not replace it
    sm.add_observation(0, 1, int(1.9 * S), (9.0, 9.0, 0.0), COV)
    sm.advance(2 * S)
    assert close(sm.pose(1)[0], (1.5, 0.2, 0.1))  # type: ignore[index]
    assert sm.counters["superseded_observations"] == 1
    # 10 s later the edge is forgotten, but robot 1 keeps its last placement (carried by odometry)
    for k in range(3, 13):
        odom_all(sm, k * S, {0: (0.0, 0.0, 0.0), 1: (0.1 * (k - 2), 0.0, 0.0)})
        sm.advance(k * S)
    sm.add_observation(1, 0, 12 * S, se2_between(sm.pose(1)[0], (0.0, 0.0, 0.0)), COV)  # type: ignore[index]
    sm.advance(12 * S)
    assert sm.counters["forgotten_edges"] == 1


def test_a_fresh_path_beats_a_stale_direct_edge() -> None:
    # 0 saw 2 long ago (2 has driven 3 m since, odometry drift makes that edge uncertain); 0 sees 1 and 1 sees 2
    # now: the chain through 1 places 2
    sm = make(3)
    odom_all(sm, 0, {0: (0.0, 0.0, 0.0), 1: (0.0, 0.0, 0.0), 2: (0.0, 0.0, 0.0)})
    sm.add_observation(0, 2, 0, (2.0, 0.0, 0.0), COV)
    sm.advance(0)
    for k in range(1, 31):
        odom_all(sm, k * S // 10, {0: (0.0, 0.0, 0.0), 1: (0.0, 0.0, 0.0), 2: (k * 0.1, 0.0, 0.0)})
        sm.advance(k * S // 10)
    sm.add_observation(0, 1, 3 * S, (1.0, 0.0, 0.0), COV)
    sm.add_observation(1, 2, 3 * S, (4.2, 0.1, 0.0), COV)  # truth: 2 slipped, it is at (5.2, 0.1)
    sm.advance(3 * S)
    assert close(sm.pose(2)[0], (5.2, 0.1, 0.0))  # type: ignore[index]


def test_landmarks_place_robots_in_the_arena_frame() -> None:
    lm = (3.0, 1.0, math.pi)
    sm = make(3, landmarks={7: lm})
    truth = {0: (1.0, 1.0, 0.0), 1: (0.0, 0.0, 0.5), 2: (-1.0, 0.0, 0.0)}
    odom_all(sm, 0, dict.fromkeys(truth, (0.0, 0.0, 0.0)))
    sm.add_landmark_observation(0, 7, 0, se2_between(truth[0], lm), COV)
    sm.add_observation(0, 1, 0, rel(truth, 0, 1), COV)
    sm.add_landmark_observation(0, 99, 0, (1.0, 0.0, 0.0), COV)  # unknown landmark
    sm.advance(0)
    assert sorted(sm.localised()) == [0, 1]  # robot 2: no chain (the origin is not anchored when landmarks pin it)
    assert close(sm.pose(0)[0], truth[0], 1e-9) and close(sm.pose(1)[0], truth[1], 1e-9)  # type: ignore[index]
    assert sm.counters["rejected_unknown_landmark"] == 1 and sm.counters["accepted_landmarks"] == 1


def test_observation_before_any_odometry_is_rejected_and_reset_forgets() -> None:
    sm = make(2)
    sm.add_observation(0, 1, 0, (1.0, 0.0, 0.0), COV)
    sm.advance(0)
    assert sm.counters["rejected_no_odometry"] == 1 and sm.pose(1) is None
    odom_all(sm, S, {0: (0.0, 0.0, 0.0), 1: (0.0, 0.0, 0.0)})
    sm.add_observation(0, 1, S, (1.0, 0.0, 0.0), COV)
    sm.advance(S)
    assert sorted(sm.localised()) == [0, 1]
    sm.reset()
    assert sm.localised() == [] and sm.edges == {} and sm.latest_odom_ns(0) == -1


@pytest.mark.parametrize("yaw", [0.0, 1.0, -2.5])
def test_chain_covariance_matches_monte_carlo(yaw: float) -> None:
    # first-order propagation against sampling the chain 0 -> 1 -> 2
    rng = np.random.default_rng(0)
    z1, z2 = (1.5, 0.3, yaw), (1.0, -0.4, 0.7)
    cov = np.diag([4e-4, 1e-4, 4e-4])
    sm = make(3)
    odom_all(sm, 0, {0: (0.0, 0.0, 0.0), 1: (0.0, 0.0, 0.0), 2: (0.0, 0.0, 0.0)})
    sm.add_observation(0, 1, 0, z1, cov)
    sm.add_observation(1, 2, 0, z2, cov)
    sm.advance(0)
    mean, c = sm.pose(2)  # type: ignore[misc]
    errs = []
    for _ in range(4000):
        n1, n2 = rng.multivariate_normal(np.zeros(3), cov, 2)
        p = se2_compose(se2_compose((0.0, 0.0, 0.0), tuple(np.add(z1, n1))), tuple(np.add(z2, n2)))  # type: ignore[arg-type]
        e = se2_between(mean, p)
        errs.append(e)
    sample = np.cov(np.array(errs).T)
    assert np.allclose(np.diag(sample), np.diag(c), rtol=0.15)


def test_server_method_from_set_and_environment() -> None:
    from tagswarm.protocol.scenario import ScenarioError
    from tagswarm.server.config import build_config
    from tagswarm.server.node import make_estimator

    assert isinstance(make_estimator(build_config([], {})), Fusion)  # default: the graph
    cfg = build_config(["--set", 'server.method="stitch"'], {})
    assert cfg.scenario.server.method == "stitch" and isinstance(make_estimator(cfg), StitchMap)
    env = build_config([], {"TAGSWARM_SET": 'server.method="stitch"'})
    assert isinstance(make_estimator(env), StitchMap)
    with pytest.raises(ScenarioError, match=r"server\.method"):
        build_config(["--set", 'server.method="kalman"'], {})
