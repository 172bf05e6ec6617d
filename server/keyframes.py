"""The store of the fusion's pose graph (pure code, GTSAM): one chain of ``Pose2`` keyframes
per robot in the map frame, the factors and values staged for the next update, and the
iSAM2 fixed-lag smoother they go to.

:class:`~tagswarm.server.fusion.Fusion` decides what goes in (which observation, which
prior, when a robot is placed or taken out); this module keeps each robot's bookkeeping,
makes keyframes (with the odometry factor from the previous one), finds the keyframe an
observation hangs on, and after each update reads every robot's newest estimate back (its
covariance every ``cov_period_s`` of simulated time).  If iSAM2 refuses an update (an
ill-conditioned system), the staged batch is dropped and a fresh smoother starts from every
robot's newest keyframe, pinned at its estimate and covariance (:meth:`KeyframeGraph.update`).
Poses are (x_m, y_m, yaw_rad) in the
map frame; odometry poses are ``base_link`` in the robot's ``odom`` frame; covariances are
3x3 in GTSAM's tangent space.
"""

from __future__ import annotations

import logging
import math
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import NamedTuple

import gtsam
import numpy as np
from numpy.typing import NDArray

from tagswarm.protocol.geometry import Pose2, se2_between, se2_compose, se2_inverse
from tagswarm.server import odomcal, rangebias
from tagswarm.server.noise import Cov, FusionParams, odom_increment_cov, still_increment_cov
from tagswarm.server.smoother import FixedLagSmoother

log = logging.getLogger(__name__)
# smallest variance a reset prior carries (m^2, rad^2): a placeholder or marginal covariance
# near singular would make the fresh smoother as ill-conditioned as the one it replaces
RESET_MIN_VAR = 1e-6


@dataclass
class Robot:
    """One robot's keyframe chain and odometry (checkpointed field by field, see
    :mod:`tagswarm.server.checkpoint`)."""

    odom: deque[tuple[int, Pose2]] = field(default_factory=lambda: deque(maxlen=4096))
    chain: int = 0  # bumped when the robot's odometry restarts
    kf_index: int = -1
    kf_key: int | None = None
    kf_stamp: int = -1
    kf_odom: Pose2 = (0.0, 0.0, 0.0)
    estimate: Pose2 | None = None  # of the last keyframe
    cov: Cov = field(default_factory=lambda: np.diag([1e-4, 1e-4, 1e-4]))
    drift_cov: Cov = field(default_factory=lambda: np.zeros((3, 3)))  # odometry since the last keyframe
    latest_odom: tuple[int, Pose2] | None = None
    last_fix_ns: int = 0
    accepted: int = 0  # observations involving this robot in the graph
    last_distance: float = 0.0
    reset_hint: Pose2 | None = None
    slip_m: float = 0.0  # the agent's cumulative slip evidence at the latest odometry
    kf_slip_m: float = 0.0  # ... at the last keyframe
    # odometry calibration ([server] odom_calibration, server/odomcal.py): the graph variable, how many
    # the robot has had, and its latest estimate (e_left, e_right, e_base) and (3, 3) marginal covariance
    cal_key: int | None = None
    cal_gen: int = 0
    cal: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    cal_cov: Cov | None = None


class PairView(NamedTuple):
    """What the newest factor between robots a and b saw: both robots' keyframe chains,
    their odometry poses (each in its own ``odom`` frame) and the measurement (b in a's
    frame, x_m, y_m, yaw_rad)."""

    chain_a: int
    chain_b: int
    odom_a: Pose2
    odom_b: Pose2
    rel: Pose2


def repeats(prev: PairView, now: PairView, cov: Cov, p: FusionParams) -> bool:
    """Whether ``now`` repeats ``prev``: the same chains, neither robot's odometry moved
    more than a quarter of a keyframe step, and the measurement moved by no more than
    its noise (chi² of the difference under twice ``cov``, (3, 3) tangent space, within
    ``p.repeat_chi2``).  A robot pushed while its wheels stood still changes the
    measurement, so it is not a repeat."""
    if (prev.chain_a, prev.chain_b) != (now.chain_a, now.chain_b):
        return False
    for before, after in ((prev.odom_a, now.odom_a), (prev.odom_b, now.odom_b)):
        d = se2_between(before, after)
        if math.hypot(d[0], d[1]) >= p.kf_dist_m / 4 or abs(d[2]) >= p.kf_angle_rad / 4:
            return False
    e = np.array(se2_between(prev.rel, now.rel))
    return float(e @ np.linalg.solve(2 * cov, e)) <= p.repeat_chi2


def robot_key(rid: int, chain: int, index: int) -> int:
    """The GTSAM key of keyframe ``index`` of chain ``chain`` of robot ``rid``."""
    return int(gtsam.symbol("x", (rid << 40) | (chain << 24) | index))


class KeyframeGraph:
    """The robots' keyframe chains, what is staged for the smoother, and the smoother.
    ``counters`` is the fusion's (``keyframes`` is counted here); ``frame_holder`` is the robot
    whose first chain holds the map frame (the origin without landmarks), None if none does."""

    def __init__(self, params: FusionParams, robot_ids: tuple[int, ...], counters: Counter[str],
                 frame_holder: int | None = None) -> None:
        self.p = params
        self.counters = counters
        self.frame_holder = frame_holder
        self.robots = {rid: Robot(odom=deque(maxlen=params.odom_buffer)) for rid in robot_ids}
        self.smoother = self._new_smoother()
        self.factors = gtsam.NonlinearFactorGraph()
        self.values = gtsam.Values()
        self.stamps: dict[int, float] = {}
        self.next_cov_ns = 0
        self.updates = 0
        # (keyframe a, keyframe b) -> (calibration key, increment, covariance) of each calibrated odometry
        # factor: a Python factor GTSAM cannot serialise, so a checkpoint saves these and rebuilds it
        self.cal_factors: dict[tuple[int, int], tuple[int, Pose2, Cov]] = {}
        # the views' shared range bias ([server] range_bias_sigma, server/rangebias.py): its variable, how many
        # there have been, its latest estimate and variance and stamp; and (keyframe a, keyframe b) -> the
        # (bias key, da, view, db, covariance) of each view factor through it, in the order they were added
        self.bias_key: int | None = None
        self.bias_gen = 0
        self.bias = 0.0
        self.bias_var: float | None = None
        self.bias_stamp = 0.0
        self.view_factors: dict[tuple[int, int], list[tuple[int, Pose2, Pose2, Pose2, Cov]]] = {}

    def _new_smoother(self) -> FixedLagSmoother:
        isam = gtsam.ISAM2Params()
        isam.setRelinearizeThreshold(0.01)
        isam.relinearizeSkip = 5
        return FixedLagSmoother(self.p.lag_s, isam, self.p.lag_batch_s)

    def staged(self) -> bool:
        """Whether factors or values wait for the next update."""
        return bool(self.factors.size() or self.values.size())

    def add(self, factor: gtsam.NonlinearFactor) -> None:
        """Stage ``factor`` for the next update."""
        self.factors.add(factor)

    def robust(self, cov: Cov) -> gtsam.noiseModel.Base:
        """Huber-robust Gaussian noise of covariance ``cov``."""
        base = gtsam.noiseModel.Gaussian.Covariance(cov)
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(self.p.huber_k), base)

    def odom_at(self, rid: int, stamp_ns: int) -> Pose2 | None:
        """Odometry pose of ``rid`` at ``stamp_ns`` (nearest sample within 0.2 s)."""
        best = None
        for t, pose in reversed(self.robots[rid].odom):
            if best is None or abs(t - stamp_ns) < abs(best[0] - stamp_ns):
                best = (t, pose)
            if t < stamp_ns:
                break
        if best is None or abs(best[0] - stamp_ns) > 200_000_000:
            return None
        return best[1]

    def current(self, rid: int) -> Pose2 | None:
        """Best current map pose of ``rid``: last keyframe ⊕ odometry since."""
        r = self.robots[rid]
        if r.estimate is None or r.latest_odom is None:
            return None
        return se2_compose(r.estimate, se2_between(r.kf_odom, r.latest_odom[1]))

    def new_keyframe(self, rid: int, stamp_ns: int, odom_pose: Pose2, initial: Pose2 | None = None,
                     prior: float | None = None, disturbed: Cov | None = None) -> int:
        """Add a keyframe variable for ``rid`` at ``stamp_ns`` (odometry ``odom_pose``): tied to
        the previous keyframe by the odometry between them, else started at ``initial``;
        ``prior`` (m and rad) pins it with an isotropic prior.  ``disturbed``: (3, 3) covariance
        added to that odometry increment, for a robot moved without its wheels knowing."""
        r = self.robots[rid]
        if r.kf_key is not None and r.kf_stamp == stamp_ns:
            return r.kf_key
        r.kf_index += 1
        key = robot_key(rid, r.chain, r.kf_index)
        if r.kf_key is not None and r.estimate is not None:
            delta = se2_between(r.kf_odom, odom_pose)
            slip = r.slip_m - r.kf_slip_m
            held = still_increment_cov(delta, self.p, slip) if rid == self.frame_holder and r.chain == 0 else None
            cov = odom_increment_cov(delta, self.p, slip) if held is None else held
            if disturbed is not None:
                cov = cov + disturbed
            if self.p.odom_calibration:
                ck = self._cal_key(rid, r, stamp_ns)
                self.cal_factors[(r.kf_key, key)] = (ck, delta, cov)
                self.factors.add(odomcal.factor(r.kf_key, key, ck, delta, cov, self.p.wheel_base_m))
                cd = odomcal.corrected(delta, r.cal, self.p.wheel_base_m)
                guess = se2_compose(r.estimate, (cd.x(), cd.y(), cd.theta()))
            else:
                self.factors.add(gtsam.BetweenFactorPose2(r.kf_key, key, gtsam.Pose2(*delta),
                                                          gtsam.noiseModel.Gaussian.Covariance(cov)))
                guess = se2_compose(r.estimate, delta)
            r.cov = r.cov + cov
        else:
            assert initial is not None
            guess = initial
            # a chain's first keyframe: its covariance is not known until the smoother has it, so read it
            # at the next update rather than a cov_period_s later (until then r.cov is a placeholder, and a
            # robot placed 0.7 m off was reported with 1 cm sigma for up to a second)
            self.next_cov_ns = 0
        if prior is not None:
            self.factors.add(gtsam.PriorFactorPose2(key, gtsam.Pose2(*guess),
                                                    gtsam.noiseModel.Isotropic.Sigma(3, prior)))
            r.cov = np.eye(3) * prior**2
        self.values.insert(key, gtsam.Pose2(*guess))
        self.stamps[key] = stamp_ns / 1e9
        r.kf_key, r.kf_stamp, r.kf_odom, r.estimate = key, stamp_ns, odom_pose, guess
        r.kf_slip_m = r.slip_m
        self.counters["keyframes"] += 1
        return key

    def _cal_key(self, rid: int, r: Robot, stamp_ns: int) -> int:
        """The key of ``rid``'s calibration variable, kept in the window by ``stamp_ns``; a new one
        (with a prior at the last estimate and covariance, or the nominal wheels' uncertainty) when the
        robot has none in the smoother: its first odometry factor, or after a reset."""
        if r.cal_key is None or (r.cal_key not in self.smoother and r.cal_key not in self.stamps):
            r.cal_gen += 1
            r.cal_key = int(gtsam.symbol("c", (rid << 16) | r.cal_gen))
            cov = r.cal_cov if r.cal_cov is not None else odomcal.prior_cov(self.p)
            self.factors.add(gtsam.PriorFactorVector(r.cal_key, np.asarray(r.cal, float),
                                                     gtsam.noiseModel.Gaussian.Covariance(np.asarray(cov, float))))
            self.values.insert(r.cal_key, np.asarray(r.cal, float))
        self.stamps[r.cal_key] = stamp_ns / 1e9
        return r.cal_key

    def add_view(self, ka: int, kb: int, da: Pose2, rel: Pose2, db: Pose2, cov: Cov, stamp_ns: int) -> None:
        """Stage the factor of a view ``rel`` (target in the observer's frame) between keyframes ``ka`` and
        ``kb``, which the two robots have moved ``da`` and ``db`` from (odometry), with (3, 3) tangent-space
        covariance ``cov``: a plain between-factor, or one through the shared range bias."""
        if self.p.range_bias_sigma <= 0 or math.hypot(rel[0], rel[1]) < rangebias.MIN_RANGE_M:
            z = se2_compose(se2_compose(da, rel), se2_inverse(db))
            self.factors.add(gtsam.BetweenFactorPose2(ka, kb, gtsam.Pose2(*z), self.robust(cov)))
            return
        if self.bias_key is None or (self.bias_key not in self.smoother and self.bias_key not in self.stamps):
            self.bias_gen += 1
            self.bias_key = rangebias.key(self.bias_gen)
            sigma = self.p.range_bias_sigma if self.bias_var is None else math.sqrt(self.bias_var)
            self.factors.add(rangebias.prior(self.bias_key, self.bias, sigma))
            self.values.insert(self.bias_key, rangebias.value(self.bias))
        self.bias_stamp = max(self.bias_stamp, stamp_ns / 1e9)  # a late view must not age it
        self.stamps[self.bias_key] = self.bias_stamp
        self.factors.add(rangebias.factor(ka, kb, self.bias_key, da, rel, db, self.robust(cov)))
        self.view_factors.setdefault((ka, kb), []).append((self.bias_key, da, rel, db, np.asarray(cov, float)))

    def anchor(self, rid: int, stamp_ns: int, odom_pose: Pose2, guess: Pose2) -> tuple[int, Pose2, Cov]:
        """Keyframe an observation at ``stamp_ns`` attaches to: the robot's latest
        keyframe if it has barely moved since or ``stamp_ns`` is older than it (a late
        observation), returning the odometry offset from it and that offset's
        covariance; else a new keyframe at ``stamp_ns``.  Reusing
        keyframes keeps the graph small when many robots see each other every frame."""
        r = self.robots[rid]
        if r.kf_key is not None and r.estimate is not None:
            delta = se2_between(r.kf_odom, odom_pose)
            small = math.hypot(delta[0], delta[1]) < self.p.kf_dist_m / 4 and abs(delta[2]) < self.p.kf_angle_rad / 4
            # a late observation older than the keyframe hangs off it backwards: a keyframe before the
            # latest would fork the robot's odometry chain
            if small or stamp_ns < r.kf_stamp:
                return r.kf_key, delta, odom_increment_cov(delta, self.p)
        return self.new_keyframe(rid, stamp_ns, odom_pose, initial=guess), (0.0, 0.0, 0.0), np.zeros((3, 3))

    def update(self, watermark_ns: int) -> None:
        """Hand what is staged to the smoother and read each robot's newest keyframe back
        (its marginal covariance too once ``cov_period_s`` has passed since the last time)."""
        if self.factors.size() == 0 and self.values.size() == 0:
            return
        try:
            self.smoother.update(self.factors, self.values, self.stamps)
        except RuntimeError as exc:
            self._reset(str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__)
        self.factors = gtsam.NonlinearFactorGraph()
        self.values = gtsam.Values()
        self.stamps = {}
        if self.cal_factors and self.updates % 64 == 0:  # forget the factors marginalisation has taken
            self.cal_factors = {ab: v for ab, v in self.cal_factors.items() if ab[1] in self.smoother}
        if self.view_factors and self.updates % 64 == 0:
            self.view_factors = {ab: v for ab, v in self.view_factors.items()
                                 if ab[0] in self.smoother and ab[1] in self.smoother}
        if self.bias_key is not None and self.bias_key in self.smoother:
            try:
                self.bias = float(self.smoother.isam.calculateEstimateVector(self.bias_key)[0])
                if watermark_ns >= self.next_cov_ns:
                    self.bias_var = float(self.smoother.marginalCovariance(self.bias_key)[0, 0])
            except RuntimeError:
                pass
        # only each robot's newest keyframe is needed; per-key retrieval avoids
        # materialising every variable of the window on every update
        with_cov = watermark_ns >= self.next_cov_ns
        for r in self.robots.values():
            if r.kf_key is None:
                continue
            try:
                p = self.smoother.calculateEstimatePose2(r.kf_key)
            except RuntimeError:
                continue
            r.estimate = (p.x(), p.y(), p.theta())
            if r.cal_key is not None and r.cal_key in self.smoother:
                try:
                    r.cal = np.asarray(self.smoother.isam.calculateEstimateVector(r.cal_key), float)
                except RuntimeError:
                    pass
            if with_cov:
                try:
                    r.cov = self.smoother.marginalCovariance(r.kf_key)
                except RuntimeError:
                    pass
                if r.cal_key is not None and r.cal_key in self.smoother:
                    try:
                        r.cal_cov = self.smoother.marginalCovariance(r.cal_key)
                    except RuntimeError:
                        pass
        if with_cov:
            self.next_cov_ns = watermark_ns + int(self.p.cov_period_s * 1e9)
        self.updates += 1

    def _reset(self, why: str) -> None:
        """iSAM2 refused the staged batch (it threw, e.g. an indeterminate linear system) and
        its Bayes tree may hold part of it: drop the batch (its observations are lost, counted
        as ``smoother_resets``) and start a fresh smoother in which each robot's newest
        keyframe is pinned by a prior at its last estimate and covariance.  The chains go on
        from those keyframes, so nothing else changes; a replayed journal meets the same
        failure and takes the same path.  Should even that be refused, every robot starts a new
        chain at its last estimate with a loose prior, as after an agent restart
        (``smoother_rebuild_failures``)."""
        self.counters["smoother_resets"] += 1
        log.warning("the smoother refused an update (%s): dropped that batch and restarted it from "
                    "every robot's last estimate", why)
        self.smoother = self._new_smoother()
        self.cal_factors.clear()
        self.view_factors.clear()
        self.bias_key = None  # a new bias variable at the next view, from self.bias / self.bias_var
        factors, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        stamps: dict[int, float] = {}
        for r in self.robots.values():
            if r.kf_key is None or r.estimate is None:
                continue
            cov = 0.5 * (r.cov + r.cov.T)
            w, v = np.linalg.eigh(cov)
            cov = (v * np.maximum(w, RESET_MIN_VAR)) @ v.T
            factors.add(gtsam.PriorFactorPose2(r.kf_key, gtsam.Pose2(*r.estimate),
                                               gtsam.noiseModel.Gaussian.Covariance(cov)))
            values.insert(r.kf_key, gtsam.Pose2(*r.estimate))
            stamps[r.kf_key] = r.kf_stamp / 1e9
            r.cov = cov
            r.cal_key = None  # a new calibration variable at the next odometry factor, from r.cal / r.cal_cov
        try:
            self.smoother.update(factors, values, stamps)
        except RuntimeError:
            self.counters["smoother_rebuild_failures"] += 1
            log.error("the smoother refused its restart as well: every robot starts a new chain at its last estimate")
            self.smoother = self._new_smoother()
            for r in self.robots.values():
                if r.estimate is not None:
                    r.reset_hint = r.estimate
                r.chain += 1
                r.kf_key, r.kf_index, r.estimate = None, -1, None
