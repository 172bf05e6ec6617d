"""Noise models of the fusion (pure maths): its tuning, the odometry increment
covariance, and the observation covariance moved into GTSAM's tangent space."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from tagswarm.protocol.geometry import Pose2

Cov = NDArray[np.float64]
CHI2_3DOF_999 = 16.27


@dataclass(frozen=True)
class FusionParams:
    """Tuning of the fusion; defaults suit the shipped scenarios."""

    wheel_base_m: float = 0.22
    odom_wheel_sigma: float = 0.02  # sqrt(m), wheel-travel noise (from [server]: odomcal.odometry_sigmas)
    odom_scale_sigma: float = 0.02  # extra per-metre systematic share (wheel radius/base miscalibration)
    # each robot's wheel radii and base as variables of the graph (server/odomcal.py), known beforehand to
    # these shares; the systematic share above then only covers what that model leaves out
    odom_calibration: bool = False
    odom_cal_sigma_radius: float = 0.01
    odom_cal_sigma_base: float = 0.02
    # no relative observation is trusted better than this (m, position): the detector's systematic error at a
    # viewpoint, which repeated sightings do not average out ([server] obs_sigma_floor_m)
    obs_sigma_floor_m: float = 0.0
    # the views' shared range bias coefficient (m^-2; bias = b r^3 along the line of sight) as one graph
    # variable with this prior sigma; 0: none, plain between-factors (server/rangebias.py)
    range_bias_sigma: float = 0.0
    # each robot's known start pose (map frame) pins its first keyframe with this sigma (m and rad); 0: robots
    # are placed only by the views that link them to the origin ([server] start_prior_sigma)
    start_prior_sigma: float = 0.0
    kf_dist_m: float = 0.2
    kf_angle_rad: float = 0.2
    kf_max_interval_s: float = 2.0
    lag_s: float = 30.0
    # variables leave the window in batches, once the oldest is this much older than the lag: each
    # marginalisation reads iSAM2's Bayes tree (~14 ms at 16 robots), so doing it every update cost more
    # than the update (server/smoother.py)
    lag_batch_s: float = 0.5
    huber_k: float = 1.345
    chi2_gate: float = CHI2_3DOF_999
    gate_floor_m: float = 0.05  # gate tolerance never below this (estimates are never perfect)
    gate_after: int = 8  # observations a robot needs in the graph before the chi² gate tightens for it
    gate_young_floor_m: float = 0.3  # the gate's floor (m; half of it in rad) before that
    origin_sigma: float = 1e-4
    # the robot holding the map frame (the origin, without landmarks) standing still: an increment under
    # still_m and still_rad in which the agent saw no slip is held to this sigma (m and rad, about the
    # encoders' resolution) instead of the numerical floor, whose 1 mm / 1 mrad random walk per keyframe let
    # the whole map turn with it (paper scenario, 300 s: the origin ended 0.17 deg off, 0.72 -> 0.38 cm)
    frame_still_sigma: float = 1e-5
    still_m: float = 1e-3
    still_rad: float = 3e-3
    odom_buffer: int = 4096
    cov_period_s: float = 1.0  # marginal covariances are recomputed at most this often (simulated time)
    init_min: int = 3  # agreeing observations needed to place a robot for the first time
    init_agree_m: float = 0.15
    init_window_s: float = 3.0
    # consecutive frames of one pair share their errors (same viewpoint, same tag pixels): fusing every
    # frame buys little accuracy and costs graph size, so each (observer, target) pair is thinned to this
    obs_min_interval_s: float = 0.3
    # a pair's observation that repeats its newest factor's view (neither robot moved, the measurement
    # within this chi² (3 dof, 99 %) of it) adds no factor: its error is the same error again
    repeat_chi2: float = 11.34
    # an observation reaches the server after its observer's odometry of later instants (the image had to be
    # rendered, sent and detected) and often after the watermark passed its stamp; within this window it
    # is still fused, tied to the keyframes through the odometry buffered around its stamp
    late_obs_s: float = 1.0
    # re-localisation from gated-out observations that agree with each other (server/recovery.py): evidence
    # lives reloc_window_s (within init_window_s, where placement candidates live); it takes reloc_min agreeing
    # observations from two or more witnesses over reloc_span_many_s, or reloc_min_single from one witness over
    # reloc_span_s; a witness is trusted if it agreed with a third robot within reloc_trust_s
    reloc_window_s: float = 1.5
    reloc_min: int = 4
    reloc_min_single: int = 5
    reloc_span_s: float = 1.0
    reloc_span_many_s: float = 1.0
    # ... or reloc_min over this span when a witness and the suspect see each other where the evidence says
    reloc_span_mutual_s: float = 0.3
    reloc_trust_s: float = 3.0
    # a witness is also trusted when its position sigma is under this share of the suspect's (0: never):
    # two robots out of everyone's view are both untrusted, yet the one far surer of itself can judge the other
    reloc_trust_sigma_ratio: float = 0.5
    reloc_min_turn_rad: float = 0.25  # a consensus this far off in yaw is significant whatever the distance
    # gated-out observations that form such a consistent set but call for too small a move to re-localise
    # are admitted as factors (robust): the graph, not a jump, corrects an estimate a little off in yaw
    reloc_admit: bool = True
    # an established robot's observation within the gate but beyond this floor (m; half of it in rad) is
    # evidence as well as a factor: a consistent set of them loosens the robot's odometry (0: off)
    surprise_floor_m: float = 0.02
    # slip evidence (the agents' OdometryEstimate.slip_m, metres of unexplained wheel travel) widens an
    # odometry increment: this many metres of position sigma (and sigma / (wheel base / 2) of yaw) per metre
    odom_slip_sigma: float = 1.0
    # a robot whose contradicting observations put it this far from its estimate (m), twice with none agreeing
    # since, is in dispute: the server does not vouch for its pose until that is resolved (server/recovery.py)
    dispute_shift_m: float = 0.1


def odom_increment_cov(delta: Pose2, p: FusionParams, slip_m: float = 0.0) -> Cov:
    """(3, 3) covariance of an odometry increment ``delta`` (in the start frame);
    ``slip_m`` is the slip evidence gathered over it (m of wheel travel)."""
    ds = math.hypot(delta[0], delta[1])
    dth = abs(delta[2])
    b = p.wheel_base_m
    wheel = p.odom_wheel_sigma**2 * (ds + dth * b / 2)  # variance per wheel (sum of |dl|, |dr| / 2)
    var_s = wheel / 2 + (p.odom_scale_sigma * ds) ** 2
    var_th = 2 * wheel / b**2 + (p.odom_scale_sigma * (dth + ds / b)) ** 2
    var_lat = var_th * ds**2 / 4
    slip = (p.odom_slip_sigma * max(slip_m, 0.0)) ** 2
    var_s, var_lat, var_th = var_s + slip, var_lat + slip, var_th + slip / (b / 2) ** 2
    return np.diag([var_s + 1e-6, var_lat + 1e-6, var_th + 1e-6])


def still_increment_cov(delta: Pose2, p: FusionParams, slip_m: float = 0.0) -> Cov | None:
    """(3, 3) covariance of an odometry increment ``delta`` of the robot holding the map frame
    if it stood still over it (under ``p.still_m`` and ``p.still_rad``, no slip evidence), else None."""
    if slip_m > 0.0 or math.hypot(delta[0], delta[1]) >= p.still_m or abs(delta[2]) >= p.still_rad:
        return None
    return np.eye(3) * p.frame_still_sigma**2


def reported_cov(cov: Cov) -> Cov:
    """A fused pose's (3, 3) covariance (x, y, yaw; tangent space) as the server reports it: the
    graph's linearised marginal plus the second-order term of its heading uncertainty.  A pose
    whose position is uncertain because a rotation by phi ~ N(0, s_phi^2) about a point r away
    carries it (a cluster of robots hanging on a far view's heading) moves r phi along the arc's
    tangent, which the linearised covariance holds (s_t = r s_phi), and r phi^2 / 2 towards that
    point, which it leaves out: at s_phi = 17 deg and r = 5 m, 22 cm across an ellipse a few cm wide
    (measured: the depot's start-up, NEES 16.7).  Its mean square, 3/4 s_t^2 s_phi^2, is added along
    the position block's minor axis (s_phi^2 capped at 1 rad^2, where the arc is no longer short).
    Negligible once the heading is known to a few degrees."""
    out = np.array(cov, float).reshape(3, 3)
    if not np.all(np.isfinite(out)):
        return out
    var_phi = min(max(float(out[2, 2]), 0.0), 1.0)
    vals, vecs = np.linalg.eigh(out[:2, :2])
    if not vals[1] > 0.0 or var_phi == 0.0:
        return out
    extra = 0.75 * float(vals[1]) * var_phi
    if vals[1] - vals[0] <= extra:
        # a round ellipse has no tangent: the bow may point anywhere, and the minor axis would jump
        # between directions for a rounding's difference
        out[:2, :2] += extra * np.eye(2)
    else:
        minor = vecs[:, 0]
        out[:2, :2] += extra * np.outer(minor, minor)
    return out


def floored_obs_cov(cov: Cov, p: FusionParams) -> Cov:
    """(3, 3) observation covariance (x, y, yaw in the observer's axes) with the position floor
    ``obs_sigma_floor_m`` added isotropically (so it is the same in any frame)."""
    out = np.array(cov, float).reshape(3, 3)
    out[0, 0] += p.obs_sigma_floor_m**2
    out[1, 1] += p.obs_sigma_floor_m**2
    return out


def tangent_cov(rel: Pose2, cov: Cov) -> Cov:
    """The agents' (3, 3) covariance of (x, y, yaw) — translation errors along the
    observer's axes — expressed in GTSAM's tangent space of the Pose2 ``rel``, whose
    translation part lives in rel's own (the target's) axes."""
    c, s = math.cos(rel[2]), math.sin(rel[2])
    j = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    return np.asarray(j @ cov @ j.T)


def inverse_cov(rel: Pose2, cov: Cov) -> Cov:
    """(3, 3) covariance of rel⁻¹ given that of ``rel`` (first order)."""
    ci, si = math.cos(rel[2]), math.sin(rel[2])
    j = -np.array([[ci, si, rel[0] * si - rel[1] * ci], [-si, ci, rel[0] * ci + rel[1] * si], [0, 0, 1.0]])
    return np.asarray(j @ cov @ j.T)


def relative_cov(rel: Pose2, cov_from: Cov, cov_to: Cov) -> Cov:
    """(3, 3) covariance, in GTSAM's tangent space of ``rel`` = from⁻¹ ⊕ to, of the relative
    pose of two independent poses whose own (tangent-space) covariances are ``cov_from`` and
    ``cov_to`` (first order: Ad(rel⁻¹) cov_from Ad(rel⁻¹)ᵀ + cov_to).  Unlike a plain sum, the
    heading error of ``from`` moves a pose ``r`` metres away by about r·σ_yaw sideways."""
    c, s = math.cos(rel[2]), math.sin(rel[2])
    x, y = -(c * rel[0] + s * rel[1]), s * rel[0] - c * rel[1]  # the translation of rel⁻¹
    ad = np.array([[c, s, y], [-s, c, -x], [0.0, 0.0, 1.0]])  # Pose2::AdjointMap of rel⁻¹ (rotation -yaw)
    return np.asarray(ad @ np.asarray(cov_from, float) @ ad.T + np.asarray(cov_to, float))
