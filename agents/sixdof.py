"""The 6-DOF core of the cube pose estimator: IPPE start, two-fold ambiguity, Gauss-Newton (pure code).

Steps 1-5 of :mod:`tagswarm.agents.cubepose`'s algorithm for one target: IPPE_SQUARE on the
largest tag (with the mirror of a single tag rebuilt when IPPE loses it), Gauss-Newton
on theta = (rvec, tvec) of ``T_c0_target`` (the pose of the target in the start
camera ``c0``'s optical frame) over every corner of every view, candidates scored by
a negative log-likelihood (chi^2 units), the ground-robot plausibility gate, and the
6-DOF answer with its covariance.  Frames and units as in :mod:`tagswarm.agents.cubegeom`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final, cast

import cv2
import numpy as np

from tagswarm.agents.cubegeom import (
    EYE4,
    Arr,
    CameraModel,
    Rejected,
    TagGeom,
    View,
    output_jacobian,
    rt_to_matrix,
    se2_jacobian,
)
from tagswarm.agents.detect import TagDetection
from tagswarm.protocol.geometry import Mat, wrap_angle

Prior = tuple[float, float, float] | None  # a caller's predicted (x_m, y_m, yaw_rad) of the target, if any

# IPPE_SQUARE wants the corners TL, TR, BR, BL; the contract order is TR, TL, BL, BR.
_TO_IPPE: Final = np.array([1, 0, 3, 2])
#: a losing candidate is kept (for the ambiguity term, weight exp(-gap/2)) only within this score gap
AMBIGUITY_GAP: Final = 20.0
# a single tag's winning start gets this many Gauss-Newton steps: one takes ~90% of the residual
# decrease IPPE leaves, and the valley along the two-fold ambiguity is too flat for more to pay
_SINGLE_TAG_ITERATIONS: Final = 1
# IPPE's second solution counts as the mirror of its first if their normals agree within 20 deg;
# a rebuilt mirror starts off the residual minimum and gets a few more steps
_MIRROR_COS: Final = math.cos(math.radians(20.0))
_MIRROR_ITERATIONS: Final = 3


@dataclass(slots=True)
class Solution:
    """A candidate pose: T_c0_target (4, 4), its theta = (rvec, tvec) and the residuals'
    Jacobian (2M, 6) w.r.t. theta (None until needed: an unrefined single-tag alternative),
    sum of squared residuals (px^2), ``T_base_target`` with its (x, y, yaw), height z and
    R22 (cos of tilt), and its score."""

    T_c0_target: Mat
    rvec: Arr | None
    tvec: Arr | None
    jac: Arr | None
    sse: float
    T_base_target: Mat
    se2: tuple[float, float, float]
    z: float
    r22: float
    cost: float

    def theta(self) -> tuple[Arr, Arr]:
        if self.rvec is None or self.tvec is None:
            self.rvec, self.tvec = cv2.Rodrigues(self.T_c0_target[:3, :3])[0].ravel(), self.T_c0_target[:3, 3].copy()
        return self.rvec, self.tvec


@dataclass(frozen=True, slots=True)
class SixDofAnswer:
    """The 6-DOF result: ``T_base_target`` (4, 4), its (x, y, yaw), ``cov`` (3, 3) of them,
    reprojection RMS (px) and the ambiguity weight folded into ``cov``."""

    T_base_target: Mat
    se2: tuple[float, float, float]
    cov: Mat
    rms_px: float
    ambiguity: float


def residuals(vlist: list[View], rvec: Arr, tvec: Arr) -> tuple[Arr, Arr]:
    """Stacked residuals (2M,) projected - detected (px) and their Jacobian (2M, 6) w.r.t.
    theta = (rvec, tvec) of T_c0_target."""
    v = vlist[0]
    proj, jac = cv2.projectPoints(v.obj, rvec, tvec, v.cam.K, None)
    if len(vlist) == 1:
        return proj.reshape(-1) - v.img.reshape(-1), jac[:, :6]
    rs, js = [proj.reshape(-1) - v.img.reshape(-1)], [jac[:, :6]]
    r_c0, jr = cv2.Rodrigues(rvec)
    jr = jr.reshape(3, 3, 3)  # [i] = d R / d rvec_i
    for v in vlist[1:]:
        rcc = v.T_cam_c0[:3, :3]
        proj, jac = cv2.projectPoints(v.obj, cv2.Rodrigues(rcc @ r_c0)[0], rcc @ tvec + v.T_cam_c0[:3, 3],
                                      v.cam.K, None)
        rs.append(proj.reshape(-1) - v.img.reshape(-1))
        # d uv / d tvec_c is d uv / d p_cam; chain through p_cam = Rcc (R(rvec) P + tvec) + tcc
        duv = jac[:, 3:6].reshape(-1, 2, 3)
        dp = np.transpose(rcc @ (jr @ v.obj.T), (2, 1, 0))  # (M, 3, 3): [k, a, i] = d p_cam[k, a] / d rvec_i
        j = np.empty((len(v.obj), 2, 6))
        j[:, :, :3] = duv @ dp
        j[:, :, 3:] = duv @ rcc
        js.append(j.reshape(-1, 6))
    return np.concatenate(rs), np.concatenate(js)


def in_front(vlist: list[View], t_c0_target: Mat) -> bool:
    """Whether every corner lies in front of every camera."""
    for v in vlist:
        t = t_c0_target if v.T_cam_c0 is EYE4 else v.T_cam_c0 @ t_c0_target
        if not (v.obj @ t[2, :3] + t[2, 3] > 0.0).all():
            return False
    return True


class SixDofSolver:
    """Candidates, refinement, plausibility and covariance of the 6-DOF pose of one target.

    The parameters are :class:`tagswarm.agents.cubepose.CubePoseEstimator`'s (see there):
    ``pixel_sigma_px`` behind the covariance, ``choice_sigma_px`` (>= it) scaling the
    residuals when candidates are scored, ``max_rms_px``, ``z_tol_m``, ``tilt_tol_rad``
    gating the result, the prior sigmas weighing a caller's prior pose.
    """

    def __init__(self, *, pixel_sigma_px: float, choice_sigma_px: float, max_rms_px: float, z_tol_m: float,
                 tilt_tol_rad: float, prior_sigma_xy_m: float, prior_sigma_yaw_rad: float,
                 max_iterations: int) -> None:
        self.pixel_sigma_px = pixel_sigma_px
        self.choice_sigma_px = choice_sigma_px
        self.max_rms_px = max_rms_px
        self.z_tol_m = z_tol_m
        self.tilt_tol_rad = tilt_tol_rad
        self.prior_sigma_xy_m = prior_sigma_xy_m
        self.prior_sigma_yaw_rad = prior_sigma_yaw_rad
        self.max_iterations = max_iterations
        self._cos_tilt_tol = math.cos(tilt_tol_rad)
        # Gauss-Newton has converged once a step would buy less than this (px^2, 0.01 in chi^2: the pose
        # then moves by ~0.1 sigma at most); saves the evaluations that only confirm convergence
        self._tiny_px2 = 1e-2 * pixel_sigma_px**2

    def candidates(self, vlist: list[View], sg: TagGeom, sd: TagDetection, z_exp: float, prior: Prior,
                   starts_only: bool) -> list[Solution]:
        """Scored candidates of one target, best first (steps 1-2 of :mod:`tagswarm.agents.cubepose`).

        ``vlist``: its views, the start camera first; ``sg``/``sd``: the largest tag's geometry
        and detection; ``z_exp``: the expected height of the target's frame (m).  One tag with
        ``starts_only``: IPPE's two poses unrefined (the planar fit refines them).  One tag
        otherwise: the better start refined, the other (or its rebuilt mirror) kept within
        :data:`AMBIGUITY_GAP`.  Several tags: every start not clearly worse refined.  Raises
        :class:`Rejected` when there is none."""
        c0 = vlist[0].cam
        try:
            n, rvecs, tvecs, errs = cv2.solvePnPGeneric(sg.ippe_obj, np.ascontiguousarray(sd.corners[_TO_IPPE]),
                                                        c0.K, None, flags=cv2.SOLVEPNP_IPPE_SQUARE)
        except cv2.error:
            n = 0
        if n == 0:
            raise Rejected("degenerate")
        n_corners = sum(len(v.obj) for v in vlist)
        t_bc = c0.T_base_cam
        t_tags = [rt_to_matrix(rv, tv) for rv, tv in zip(rvecs, tvecs, strict=True)]
        sse_ippe = [e * e * 8.0 for e in errs.ravel().tolist()]  # IPPE's error: RMS of the 8 coordinates
        starts = [self.candidate(t @ sg.T_tag_target, t_bc, sse, z_exp, prior)
                  for t, sse in zip(t_tags, sse_ippe, strict=True)]
        sols: list[Solution] = []
        if n_corners == 4 and starts_only:
            sols = sorted(starts, key=lambda c: c.cost)
        elif n_corners == 4:
            mirror = self.mirror_start(vlist, t_tags, sg, z_exp, prior)
            if mirror is not None:
                starts = [starts[0], mirror]
            # one tag: the better start is refined; the other only matters through the ambiguity
            # term, so it stays as IPPE left it, and is dropped when the gap is large
            starts.sort(key=lambda c: c.cost)
            first = starts[0]
            sol = self.solve(vlist, *first.theta(), z_exp, prior, _SINGLE_TAG_ITERATIONS)
            if sol is not None:
                sols.append(sol)
            sols += [c for c in starts[1:] if c.cost - first.cost < AMBIGUITY_GAP]
        else:
            # several tags: the wrong IPPE start throws the other tags' corners far off; refine the
            # starts whose residuals are not clearly worse than the best one's
            evals = [residuals(vlist, *c.theta()) for c in starts]
            sse0 = [float(r0 @ r0) for r0, _ in evals]
            lim = 3.0 * min(sse0) + AMBIGUITY_GAP * self.choice_sigma_px**2
            for c, sse, ev in zip(starts, sse0, evals, strict=True):
                if sse <= lim:
                    sol = self.solve(vlist, *c.theta(), z_exp, prior, self.max_iterations, ev)
                    if sol is not None:
                        sols.append(sol)
        if not sols:
            raise Rejected("degenerate")
        sols.sort(key=lambda c: c.cost)
        return sols

    def plausible(self, sols: list[Solution], vlist: list[View], n_corners: int,
                  z_exp: float) -> list[tuple[Solution, Mat | None]]:
        """The best two plausible candidates (step 5), with their theta covariance when the gate
        needed it; raises :class:`Rejected` when none is."""
        c0 = vlist[0].cam
        plausible: list[tuple[Solution, Mat | None]] = []
        constrained = False
        for sol in sols:
            cov = None
            if abs(sol.z - z_exp) > self.z_tol_m or sol.r22 < self._cos_tilt_tol:
                cov = self.cov_theta(sol, vlist, n_corners)
                if cov is None or not self.is_plausible(sol, c0, z_exp, cov):
                    constrained = constrained or cov is not None
                    continue
            constrained = True
            plausible.append((sol, cov))
            if len(plausible) == 2:
                break
        if not plausible:
            raise Rejected("implausible" if constrained else "degenerate")
        return plausible

    def answer(self, plausible: list[tuple[Solution, Mat | None]], vlist: list[View],
               n_corners: int) -> SixDofAnswer:
        """The 6-DOF answer (steps 3-4): the best plausible candidate, its covariance propagated to
        (x, y, yaw) with a distinct runner-up folded in; raises :class:`Rejected`."""
        best, cov_theta = plausible[0]
        rms = math.sqrt(best.sse / n_corners)
        if rms > self.max_rms_px:
            raise Rejected("reprojection")
        if cov_theta is None:
            cov_theta = self.cov_theta(best, vlist, n_corners)
            if cov_theta is None:
                raise Rejected("degenerate")
        g3 = se2_jacobian(vlist[0].cam.T_base_cam, best.T_base_target, best.theta()[0])
        cov = g3 @ cov_theta @ g3.T
        ambiguity = 0.0
        if len(plausible) > 1:
            alt = plausible[1][0]
            d = (alt.se2[0] - best.se2[0], alt.se2[1] - best.se2[1], wrap_angle(alt.se2[2] - best.se2[2]))
            # both refined to the same pose (several faces): no ambiguity left
            if abs(d[2]) > 1e-3 or math.hypot(d[0], d[1]) > 1e-3:
                ambiguity = 1.0 / (1.0 + math.exp(min(50.0, 0.5 * (alt.cost - best.cost))))
                cov += ambiguity * np.outer(d, d)
        c00, c11, c22 = cov[0, 0], cov[1, 1], cov[2, 2]
        # G Sigma G^T of finite factors: a finite positive diagonal means a usable covariance
        if not (c00 > 0.0 and c11 > 0.0 and c22 > 0.0 and math.isfinite(c00 + c11 + c22)):
            raise Rejected("degenerate")
        return SixDofAnswer(best.T_base_target, best.se2, cov, rms, ambiguity)

    # ------------------------------------------------------------------ pieces
    def mirror_start(self, vlist: list[View], t_tags: list[Mat], sg: TagGeom, z_exp: float,
                     prior: Prior) -> Solution | None:
        """The other half of a single tag's two-fold ambiguity when IPPE did not return it.

        The two poses of a small square mirror its normal about the line of sight.  On
        small, nearly frontal tags IPPE's second solution sometimes degenerates (e.g.
        upside down) and the real alternative goes missing, leaving a confidently wrong
        yaw; this rebuilds it from the first solution (``t_tags``: IPPE's T_cam_tag) and
        refines it.  None if IPPE's second solution already is that mirror, or the view
        is exactly frontal."""
        t = t_tags[0]
        (_, _, n0, c0), (_, _, n1, c1), (_, _, n2, c2), _ = t.tolist()  # normal n, centre c (camera frame)
        dist = math.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
        v0, v1, v2 = -c0 / dist, -c1 / dist, -c2 / dist  # towards the camera
        cos = n0 * v0 + n1 * v1 + n2 * v2
        if len(t_tags) > 1:
            # the mirrored normal is 2 (n.v) v - n
            (_, _, o0, _), (_, _, o1, _), (_, _, o2, _), _ = t_tags[1].tolist()
            if (2 * cos * v0 - n0) * o0 + (2 * cos * v1 - n1) * o1 + (2 * cos * v2 - n2) * o2 > _MIRROR_COS:
                return None
        axis = np.cross(t[:3, 2], (v0, v1, v2))
        sin = float(np.linalg.norm(axis))
        if sin < 1e-4:
            return None
        r = cv2.Rodrigues(axis * (2.0 * math.atan2(sin, cos) / sin))[0] @ t[:3, :3]
        t_ct = t.copy()
        t_ct[:3, :3] = r
        t_ct = t_ct @ sg.T_tag_target
        return self.solve(vlist, cv2.Rodrigues(t_ct[:3, :3])[0].ravel(), t_ct[:3, 3].copy(), z_exp, prior,
                          _MIRROR_ITERATIONS)

    def prior_terms(self, sol: Solution, z_exp: float, prior: Prior) -> float:
        """Negative log-likelihood (chi^2 units) of a candidate under the ground-robot prior
        (tolerances taken as 3 sigma) and the caller's prior pose."""
        tilt = math.acos(max(-1.0, min(1.0, sol.r22)))
        cost = (3.0 * (sol.z - z_exp) / self.z_tol_m) ** 2 + (3.0 * tilt / self.tilt_tol_rad) ** 2
        if prior is not None:
            x, y, yaw = sol.se2
            cost += ((x - prior[0]) ** 2 + (y - prior[1]) ** 2) / self.prior_sigma_xy_m**2
            cost += (wrap_angle(yaw - prior[2]) / self.prior_sigma_yaw_rad) ** 2
        return cost

    def candidate(self, t_ct: Mat, t_bc: Mat, sse: float, z_exp: float, prior: Prior) -> Solution:
        """A scored candidate from T_c0_target and its residual sum of squares (px^2)."""
        t_bt = t_bc @ t_ct
        (r00, _, _, x), (r10, _, _, y), (_, _, r22, z), _ = t_bt.tolist()
        sol = Solution(t_ct, None, None, None, sse, t_bt, (x, y, math.atan2(r10, r00)), z, r22, 0.0)
        sol.cost = sse / self.choice_sigma_px**2 + self.prior_terms(sol, z_exp, prior)
        return sol

    def solve(self, vlist: list[View], rvec: Arr, tvec: Arr, z_exp: float, prior: Prior, max_iterations: int,
              start: tuple[Arr, Arr] | None = None) -> Solution | None:
        """Gauss-Newton (with step halving) on theta = (rvec, tvec) of T_c0_target over every
        corner of every view, then scored (``start``: residuals and Jacobian at the start,
        if already known); None if a corner ends up behind a camera."""
        r, jac = start if start is not None else residuals(vlist, rvec, tvec)
        sse = float(r @ r)
        for _ in range(max_iterations):
            grad = jac.T @ r
            ok, step = cv2.solve(jac.T @ jac, -grad, flags=cv2.DECOMP_CHOLESKY)
            if not ok:
                break
            step = step.ravel()
            if -float(step @ grad) < self._tiny_px2:
                break
            for _halving in range(4):
                nr, nt = rvec + step[:3], tvec + step[3:]
                r2, jac2 = residuals(vlist, nr, nt)
                sse2 = float(r2 @ r2)
                if sse2 <= sse:
                    rvec, tvec, r, jac, sse = nr, nt, r2, jac2, sse2
                    break
                step *= 0.5
            else:
                break
        t_ct = rt_to_matrix(rvec, tvec)
        # one view: the start faced the camera and Gauss-Newton does not jump through the image plane
        if len(vlist) > 1 and not in_front(vlist, t_ct):
            return None
        sol = self.candidate(t_ct, vlist[0].cam.T_base_cam, sse, z_exp, prior)
        sol.rvec, sol.tvec, sol.jac = rvec, tvec, jac
        return sol

    def cov_theta(self, sol: Solution, vlist: list[View], n_corners: int) -> Mat | None:
        """(6, 6) covariance of theta = (rvec, tvec), or None when the corners do not
        constrain all six degrees of freedom."""
        if sol.jac is None:
            sol.jac = residuals(vlist, *sol.theta())[1]
        dof = 2 * n_corners - 6
        s2 = max(self.pixel_sigma_px**2, sol.sse / dof) if dof > 0 else self.pixel_sigma_px**2
        # the SVD inverse also returns 1/condition number: a near-singular system is degenerate
        rcond, inv = cv2.invert(sol.jac.T @ sol.jac, flags=cv2.DECOMP_SVD)
        if not rcond > 1e-12:
            return None
        return cast(Mat, s2 * inv)

    def is_plausible(self, sol: Solution, c0: CameraModel, z_exp: float, cov_theta: Mat) -> bool:
        """Whether the target stands on the floor like the observer: height within
        ``z_tol_m`` of the expected one (0 for a robot's base, the scenario's height for
        a landmark) and roll/pitch within ``tilt_tol_rad`` -- each widened by 3 sigma of
        the estimate itself, so a far single face whose tilt is barely observable is
        kept while a confident tilted (or fake) solution is not."""
        t_bt = sol.T_base_target
        g = output_jacobian(c0.T_base_cam, *sol.theta())[1]
        dz = float(t_bt[2, 3]) - z_exp
        if abs(dz) > self.z_tol_m + 3.0 * math.sqrt(max(0.0, float(g[3] @ cov_theta @ g[3]))):
            return False
        if t_bt[2, 2] <= 0.0:
            return False
        s = float(np.hypot(t_bt[0, 2], t_bt[1, 2]))
        tilt = math.asin(min(1.0, s))
        if tilt <= self.tilt_tol_rad:
            return True
        gt = (t_bt[0, 2] * g[4] + t_bt[1, 2] * g[5]) / s  # d sin(tilt) / d theta
        return tilt <= self.tilt_tol_rad + 3.0 * math.sqrt(max(0.0, float(gt @ cov_theta @ gt)))
