"""Pose of an observed tag cube (or landmark tag) from one camera or a rig (pure code).

This is the seed-003 bundle adjustment (docs/architecture.md, section 6): every visible corner
of one target, over every camera that sees it, in one least-squares problem with
the target's geometry known.

Frames: the result is ``T_base_target``, the pose of the observed robot's BASE
frame (on the floor, x forward, y left, z up) -- or of a landmark tag's frame
(origin at the plate centre, +x the tag's outward normal, z up; see
``tagswarm.world.assets.landmark_mesh``) -- in the OBSERVER's base frame.  Cameras are
OpenCV pinholes (pixel centres at integer coordinates) mounted at ``T_base_cam``; a
distorted lens's corners are first undistorted onto its pinhole, with the calibration
the agent believes (:mod:`tagswarm.agents.lens`).  Metres, radians, pixels.

Algorithm per target (``c0``: the camera that sees the target's largest tag):

1. Start: ``cv2.solvePnPGeneric(SOLVEPNP_IPPE_SQUARE)`` on the largest tag gives the
   two poses a small square cannot tell apart (normal mirrored about the line of
   sight).  When IPPE's second pose is not that mirror (it degenerates on small,
   nearly frontal tags) the mirror is rebuilt, so the ambiguity is never lost.
2. Refine: Gauss-Newton on theta = (rvec, tvec) of ``T_c0_target`` over every corner
   of the target in every view, with ``cv2.projectPoints`` Jacobians (other cameras
   chained through their fixed ``T_cam_c0``).  One tag: the better start is refined,
   the other kept as IPPE left it.  Several tags: the start that throws the other
   tags' corners off is dropped unrefined.
3. Choose: candidates are scored by a negative log-likelihood -- reprojection
   residuals over ``choice_sigma_px``, the ground-robot prior (both robots stand on
   the floor: the target's base near z = 0 -- a landmark near its known height --
   with little roll/pitch) and the caller's prior pose if any.  The best plausible
   one wins.
4. Covariance: ``s^2 (J^T J)^-1`` with ``s = max(pixel_sigma_px, residual-based
   estimate)``, propagated to (x, y, yaw) of ``T_base_target``; when the other
   candidate of the two-fold ambiguity is still plausible its spread is added with
   its weight (moment-matched two-component mixture), so a possibly flipped yaw
   says so in its covariance instead of being confidently wrong.
5. Reject (counted in :attr:`CubePoseEstimator.rejects`): reprojection RMS above
   ``max_rms_px`` ("reprojection"); height or roll/pitch out of tolerance beyond
   the estimate's own 3-sigma, or a tag seen from behind ("implausible"); too few
   or collapsed corners, a singular Jacobian ("degenerate"); one tag ID twice in
   one image ("duplicate") unless exactly one choice of its copies gives a plausible
   pose, then the other copies count as "decoy" (a poster with the ID); a set of tags
   that fits no plausible pose is retried leaving each tag out, and if exactly one such
   set fits, the tag left out counts as "decoy".
6. Planar (the default for robots, ``planar=True``): both robots stand upright on
   one floor, so once the 6-DOF stage has found a plausible pose (step 5 still
   rejects a target its 6-DOF fit puts off the floor or tilted), (x, y, yaw) of
   ``T_base_target`` is re-solved with z = 0 and roll = pitch = 0
   (:mod:`tagswarm.agents.planar`: Gauss-Newton over every corner of every camera, each at
   its ``T_base_cam``) from the plausible 6-DOF pose(s) -- one tag: from the better
   IPPE pose and from the pose with the tag's normal mirrored about the horizontal
   line of sight, the two-fold ambiguity in the plane.  The lowest score wins (a
   distinct runner-up is folded into the covariance as in step 4), its reprojection
   RMS must stay under ``max_rms_px``, and its covariance is the planar
   ``s^2 (J^T J)^-1``.  What it buys depends on the camera's height above the tag centres:
   a camera at their height (the default mount, z = 0.22 m = the cube centre) sees
   the two-fold ambiguity as a pure yaw mirror the planar model cannot remove, and
   the range comes from the tag's size alone, so yaw and position stay as the
   6-DOF ones; a camera above (or below) them gets the range from the elevation
   angle and loses the mirror (0.68 m above: position ~5x, p90 yaw ~2x better at
   2.5-4 m; tests/unit/agents/test_cubepose.py).  Landmarks stay 6-DOF unless
   ``planar_landmarks`` (z fixed at the scenario's height).

Modules: :mod:`tagswarm.agents.cubegeom` (cameras, targets, results, frame Jacobians),
:mod:`tagswarm.agents.sixdof` (steps 1-5), :mod:`tagswarm.agents.planar` (the planar model of step 6);
this module groups the detections per target and runs the steps.

Cost: the single-camera path is a handful of OpenCV calls per target (IPPE,
Rodrigues, projectPoints, solve, invert) plus two or three evaluations of the
3-parameter planar model (a dozen numpy operations each); bench/detect.py measures
it against a bare AprilTag detect call.
"""

from __future__ import annotations

import math
from collections import Counter
from typing import Final

import numpy as np
from numpy.typing import NDArray

from tagswarm.agents import planar
from tagswarm.agents.cubegeom import (
    EYE4,
    LANDMARK_PLATE_THICKNESS_M,
    CameraModel,
    PoseEstimate,
    Rejected,
    TagGeom,
    View,
    output_jacobian,
    quad_area,
)
from tagswarm.agents.decoys import DecoyResolver
from tagswarm.agents.detect import TagDetection, TagMap
from tagswarm.agents.lens import LensCorrector, corner_sigma_px
from tagswarm.agents.planar import PlanarProblem
from tagswarm.agents.sixdof import AMBIGUITY_GAP, Prior, SixDofSolver
from tagswarm.protocol import tags
from tagswarm.protocol.geometry import wrap_angle
from tagswarm.protocol.scenario import Scenario

__all__ = ["LANDMARK_PLATE_THICKNESS_M", "CameraModel", "CubePoseEstimator", "PoseEstimate", "output_jacobian"]

# one-camera planar problems kept per (tags, camera): the part that does not depend on the pixels
_PLANAR_CACHE_SIZE: Final = 1024
# the planar covariance's pixel sigma over pixel_sigma_px: see CubePoseEstimator
_PLANAR_NOISE: Final = 1.35


class CubePoseEstimator(DecoyResolver):
    """Bundle adjustment of observed tag cubes and landmark tags, one camera or a rig.

    ``pixel_sigma_px`` is the render's corner noise (1 sigma per axis) behind the covariance;
    a camera with noise or motion blur (``[camera]``) widens it (:func:`corner_sigma_px`).
    Measured on our renders (AprilTag 3, 0.5-5 m, 320x240 and 640x480, 60 deg HFOV):
    corners scatter 0.25-0.33 px RMS per axis about the projected truth, whatever
    the tag's size; with 0.3 px the NEES of (x, y, yaw) averages 2.5-3.4 over
    several hundred random views (expected: 3; tests/unit/agents/test_cubepose.py asserts
    it).  ``choice_sigma_px`` (>= ``pixel_sigma_px``) scales the residuals when the
    two-fold ambiguity is weighed: render errors are correlated within a tag, so a
    wrong flip can fit a small tag slightly better than the truth, and judging
    that with 0.3 px made some flips look certain (NEES ~400); 0.8 px keeps
    them flagged.  ``max_rms_px``, ``z_tol_m`` and ``tilt_tol_rad`` gate the result
    (see :meth:`tagswarm.agents.sixdof.SixDofSolver.is_plausible`); ``prior_sigma_xy_m``/``prior_sigma_yaw_rad`` weigh a
    caller's prior pose when choosing between the two-fold solutions.

    ``planar`` (default) answers with the planar fit of step 6 of the module
    docstring, ``planar=False`` with the 6-DOF one; ``planar_landmarks`` extends it
    to landmarks.  The planar covariance uses ``1.35 * pixel_sigma_px``: render
    errors are correlated within a tag (a near-vertical edge shifts as a whole,
    corr ~0.9, so its width and horizontal position scatter ~1.4x what independent
    corners imply), which the 6-DOF fit partly absorbs into z/roll/pitch and the
    planar fit cannot.  Measured on the views of tests/unit/agents/test_cubepose.py: NEES
    of (x, y, yaw) 2.1-3.5 for a camera at the tag's height, 0.4-0.8 (conservative)
    for one 0.68 m above it, whose corner errors are smaller along the elevation
    that then fixes the range.  The hard case for the yaw, a single face seen almost
    square-on 2-3.5 m away at 320x240 from 0.6 m up (~10-20 px), stays on the safe
    side too: yaw NEES ~0.15, none beyond 3 sigma, the mirrored pose (~20 deg of yaw
    away) folded in with weight ~0.25 (tests/unit/agents/test_cubepose_frontal.py).
    """

    def __init__(self, scenario: Scenario, pixel_sigma_px: float = 0.3, max_rms_px: float = 2.0,
                 z_tol_m: float = 0.08, tilt_tol_rad: float = 0.15, *, choice_sigma_px: float = 0.8,
                 prior_sigma_xy_m: float = 0.25, prior_sigma_yaw_rad: float = 0.35, max_iterations: int = 10,
                 planar: bool = True, planar_landmarks: bool = False) -> None:
        if pixel_sigma_px <= 0:
            raise ValueError("pixel_sigma_px must be positive")
        # the render's corner noise, widened by the camera's noise and blur (ideal camera: unchanged)
        pixel_sigma_px = corner_sigma_px(scenario, pixel_sigma_px)
        self.scenario = scenario
        self.planar = planar
        # the ablation of a per-tag PnP: keep only the largest face of each target
        self.single_tag = scenario.agent.pose_method == "single_tag"
        self.planar_landmarks = planar_landmarks
        self._planar_cache: dict[tuple[tuple[int, ...], bytes, bytes], PlanarProblem] = {}
        self.pixel_sigma_px = pixel_sigma_px
        self.choice_sigma_px = max(choice_sigma_px, pixel_sigma_px)
        self.max_rms_px = max_rms_px
        self.prior_sigma_xy_m = prior_sigma_xy_m
        self.prior_sigma_yaw_rad = prior_sigma_yaw_rad
        self.max_iterations = max_iterations
        self.rejects: Counter[str] = Counter()
        self.expected = {}
        self.copies_seen = []
        self.resolved_by_map = 0
        self.tag_map = TagMap.from_scenario(scenario)
        self.lens = LensCorrector(scenario.camera.calibration_error, scenario.seed)
        self._six = SixDofSolver(pixel_sigma_px=pixel_sigma_px, choice_sigma_px=self.choice_sigma_px,
                                 max_rms_px=max_rms_px, z_tol_m=z_tol_m, tilt_tol_rad=tilt_tol_rad,
                                 prior_sigma_xy_m=prior_sigma_xy_m, prior_sigma_yaw_rad=prior_sigma_yaw_rad,
                                 max_iterations=max_iterations)
        # the planar fit's last step, below 0.1 in chi^2 (~0.3 sigma), is taken blind (tagswarm.agents.planar.solve)
        self._planar_tiny_px2 = 1e-1 * pixel_sigma_px**2
        self._geom: dict[int, TagGeom] = {}
        self._expected_z: dict[tuple[str, int], float] = {}
        r = scenario.robot
        for rid in scenario.robot_ids:
            self._expected_z[("robot", rid)] = 0.0
            for face, tid in zip(tags.Face, scenario.tag_ids(rid), strict=True):
                n, u, rr = tags.face_axes(face)
                centre = n * (r.cube_edge_m / 2.0) + np.array([0.0, 0.0, r.cube_center_z_m])
                self._geom[tid] = TagGeom.make("robot", rid, centre, n, u, rr, scenario.tags.size_m)
        for lm in scenario.landmarks:
            self._expected_z[("landmark", lm.id)] = lm.z_m
            n, u, rr = tags.face_axes(tags.Face.FRONT)
            self._geom[lm.id] = TagGeom.make("landmark", lm.id, n * (LANDMARK_PLATE_THICKNESS_M / 2.0), n, u, rr,
                                             lm.size_m)

    def object_points(self, tag_id: int) -> NDArray[np.float64] | None:
        """(4, 3) corners of ``tag_id`` in its target's frame (metres, contract order), or None."""
        g = self._geom.get(tag_id)
        return None if g is None else g.obj.copy()

    # ------------------------------------------------------------------ public
    def estimate(self, views: list[tuple[CameraModel, list[TagDetection]]],
                 priors: dict[tuple[str, int], tuple[float, float, float]] | None = None,
                 expected: dict[tuple[str, int], tuple[float, float, float]] | None = None) -> list[PoseEstimate]:
        """Poses of every target seen in ``views`` (one synchronised frame per camera).

        Detections of tags that belong to nothing in the scenario are ignored (the
        caller counts them with :class:`~tagswarm.agents.detect.TagMap`).  ``priors`` maps
        ``(kind, target_id)`` to a predicted (x_m, y_m, yaw_rad) of the target in the
        observer's base frame; it only helps choose between the two-fold solutions.
        ``expected`` maps ``(kind, target_id)`` to where the map has the target, (x_m, y_m,
        radius_m) in the observer's base frame: it only decides between two plausible copies
        of one target in one instant (see :meth:`DecoyResolver.resolve`).
        Rejected targets are counted in :attr:`rejects` by reason.
        """
        self.expected = expected or {}
        self.copies_seen = []
        # distorted lenses and the believed calibration: from here on every camera is a pinhole
        views = [self.lens.prepare(cam, dets) for cam, dets in views]
        groups: dict[tuple[str, int], list[tuple[int, TagGeom, TagDetection]]] = {}
        for vi, (_, dets) in enumerate(views):
            for d in dets:
                g = self._geom.get(d.tag_id)
                if g is not None:
                    groups.setdefault((g.kind, g.target_id), []).append((vi, g, d))
        out = []
        for key, members in groups.items():
            if self.single_tag and len(members) > 1:
                members = [max(members, key=lambda m: quad_area(m[2].corners))]
            est = self.resolve(key, members, views, None if priors is None else priors.get(key))
            if est is not None:
                out.append(est)
        return out

    # ------------------------------------------------------------------ internals
    def _reject(self, reason: str) -> None:
        self.rejects[reason] += 1

    def _views(self, members: list[tuple[int, TagGeom, TagDetection]],
               views: list[tuple[CameraModel, list[TagDetection]]]) -> tuple[list[View], TagGeom, TagDetection]:
        """The target's corners per camera, the start camera (largest tag) first, and the
        largest tag's geometry and detection; raises :class:`Rejected` on a bad set."""
        if len(members) == 1:
            vi, g, d = members[0]
            c = d.corners
            if c.shape != (4, 2) or not np.isfinite(c).all():
                raise Rejected("degenerate")
            area = quad_area(c)
            if area < 4.0:
                # a tag is only decodable from its front: clockwise corners mean a fake or garbled set
                raise Rejected("implausible" if area < -4.0 else "degenerate")
            return [View(views[vi][0], g.obj, c, EYE4, (d.tag_id,))], g, d
        per_cam: dict[int, list[tuple[TagGeom, TagDetection]]] = {}
        best_area, start = -1.0, members[0]
        for m in members:
            vi, g, d = m
            items = per_cam.setdefault(vi, [])
            if any(other.tag_id == d.tag_id for _, other in items):  # one tag twice in one image: a false decode
                raise Rejected("duplicate")
            items.append((g, d))
            c = d.corners
            if c.shape != (4, 2) or not np.isfinite(c).all():
                raise Rejected("degenerate")
            area = quad_area(c)
            if area < -4.0:
                raise Rejected("implausible")
            if area > best_area:
                best_area, start = area, m
        if not best_area >= 4.0:
            raise Rejected("degenerate")
        c0 = views[start[0]][0]
        out: list[View] = []
        for vi, items in per_cam.items():
            img = np.ascontiguousarray(np.concatenate([d.corners for _, d in items]), np.float64)
            obj = np.concatenate([g.obj for g, _ in items])
            cam = views[vi][0]
            ids = tuple(d.tag_id for _, d in items)
            if vi == start[0]:
                out.insert(0, View(cam, obj, img, EYE4, ids))
            else:
                out.append(View(cam, obj, img, cam.T_cam_base @ c0.T_base_cam, ids))
        return out, start[1], start[2]

    def _estimate_target(self, key: tuple[str, int], members: list[tuple[int, TagGeom, TagDetection]],
                         views: list[tuple[CameraModel, list[TagDetection]]], prior: Prior) -> PoseEstimate | None:
        try:
            vlist, sg, sd = self._views(members, views)
            n_corners = sum(len(v.obj) for v in vlist)
            z_exp = self._expected_z.get(key, 0.0)
            planar_fit = self.planar and (sg.kind == "robot" or self.planar_landmarks)
            # one tag, planar answer: IPPE's poses only gate plausibility and seed the planar fit,
            # which weighs the tag's mirror itself (see _planar)
            sols = self._six.candidates(vlist, sg, sd, z_exp, prior, planar_fit)
            plausible = self._six.plausible(sols, vlist, n_corners, z_exp)
            tag_ids = (sd.tag_id,) if len(members) == 1 else tuple(sorted({d.tag_id for _, _, d in members}))
            cameras = (vlist[0].cam.name,) if len(vlist) == 1 else tuple(v.cam.name for v in vlist)
            if planar_fit:
                # one tag: the best plausible pose (the mirror comes later); several: the 6-DOF stage has
                # already dropped or refined the start that throws the other tags off
                seeds = [sol.se2 for sol, _ in plausible[:1 if n_corners == 4 else 2]]
                return self._planar(vlist, seeds, z_exp, prior, sg, tag_ids, cameras, n_corners)
            ans = self._six.answer(plausible, vlist, n_corners)
        except Rejected as exc:
            self._reject(str(exc))
            return None
        return PoseEstimate(
            target_kind=sg.kind, target_id=sg.target_id, T_base_target=ans.T_base_target, x_m=ans.se2[0],
            y_m=ans.se2[1], yaw_rad=ans.se2[2], cov=ans.cov, reprojection_rms_px=ans.rms_px, tag_ids=tag_ids,
            cameras=cameras, n_corners=n_corners, ambiguity=ans.ambiguity)

    def _planar(self, vlist: list[View], seeds: list[tuple[float, float, float]], z_exp: float,
                prior: Prior, sg: TagGeom, tag_ids: tuple[int, ...],
                cameras: tuple[str, ...], n_corners: int) -> PoseEstimate:
        """The planar answer (step 6 of the module docstring): Gauss-Newton on (x, y, yaw) at the
        known height from each distinct seed (plausible 6-DOF poses projected onto the floor); one
        tag: also from its mirror (:func:`tagswarm.agents.planar.mirror`).  The lowest score wins; a distinct
        runner-up within the ambiguity gap is folded into the covariance as in the 6-DOF path.  Raises
        :class:`Rejected`."""
        pr = self._planar_problem(vlist, z_exp)
        tiny = self._planar_tiny_px2
        fits: list[tuple[float, planar.PlanarFit]] = []
        for seed in seeds:
            fit = planar.solve(pr, seed, self.max_iterations, tiny)
            if fit is not None and not any(self._same(fit, f) for _, f in fits):
                fits.append((self._planar_cost(fit, prior), fit))
        if not fits:
            raise Rejected("degenerate")
        fits.sort(key=lambda cf: cf[0])
        if n_corners == 4:
            # one tag: the pose with its normal mirrored about the line of sight may explain the corners
            # about as well (at the tag's height exactly so) -- weigh it where the cost stands there (yaw
            # held: from there Gauss-Newton may roll back over the shallow ridge), and where it fits
            # better than the seed's minimum, that basin is the better one
            first = fits[0][1]
            mirrored = planar.mirror(first.p, sg.centre, sg.normal, vlist[0].cam.T_base_cam[:2, 3])
            # one Gauss-Newton step on (x, y), its SSE as predicted
            alt = None if mirrored is None else planar.solve(pr, mirrored, 1, math.inf, yaw_fixed=True)
            if alt is not None:
                alt_cost = self._planar_cost(alt, prior)
                if alt_cost < fits[0][0]:
                    full = planar.solve(pr, (alt.p[0], alt.p[1], alt.p[2]), self.max_iterations, tiny)
                    if full is not None:
                        alt, alt_cost = full, self._planar_cost(full, prior)
                if not self._same(alt, first):
                    fits = sorted([fits[0], (alt_cost, alt)], key=lambda cf: cf[0])
        cost, best = fits[0]
        rms = math.sqrt(best.sse / n_corners)
        if rms > self.max_rms_px:
            raise Rejected("reprojection")
        cov = planar.covariance(best, self.pixel_sigma_px * _PLANAR_NOISE)
        if cov is None:
            raise Rejected("degenerate")
        x, y, yaw = best.p.tolist()
        ambiguity = 0.0
        if len(fits) > 1 and fits[1][0] - cost < AMBIGUITY_GAP:
            other = fits[1][1].p
            d = (other[0] - x, other[1] - y, wrap_angle(other[2] - yaw))
            ambiguity = 1.0 / (1.0 + math.exp(0.5 * (fits[1][0] - cost)))
            cov = cov + ambiguity * np.outer(d, d)
        return PoseEstimate(
            target_kind=sg.kind, target_id=sg.target_id, T_base_target=planar.matrix(x, y, yaw, z_exp), x_m=x,
            y_m=y, yaw_rad=yaw, cov=cov, reprojection_rms_px=rms, tag_ids=tag_ids, cameras=cameras,
            n_corners=n_corners, ambiguity=ambiguity)

    @staticmethod
    def _same(a: planar.PlanarFit, b: planar.PlanarFit) -> bool:
        """Whether two planar fits found the same minimum (1 mm, 1 mrad)."""
        return abs(wrap_angle(a.p[2] - b.p[2])) < 1e-3 and math.hypot(a.p[0] - b.p[0], a.p[1] - b.p[1]) < 1e-3

    def _planar_problem(self, vlist: list[View], z_exp: float) -> PlanarProblem:
        """The planar problem of a target's views; in one camera (the common case) the part that
        only depends on the tags and the camera is reused."""
        if len(vlist) > 1:
            return PlanarProblem.make([(v.cam.K, v.cam.T_cam_base, v.obj, v.img) for v in vlist], z_exp)
        v = vlist[0]
        key = (v.tag_ids, v.cam.K.tobytes(), v.cam.T_base_cam.tobytes())
        pr = self._planar_cache.get(key)
        if pr is None:
            if len(self._planar_cache) >= _PLANAR_CACHE_SIZE:
                self._planar_cache.clear()
            pr = self._planar_cache[key] = PlanarProblem.make([(v.cam.K, v.cam.T_cam_base, v.obj, v.img)],
                                                                      z_exp)
        return PlanarProblem(pr.basis, pr.q_z, v.img, pr.dq)

    def _planar_cost(self, fit: planar.PlanarFit, prior: Prior) -> float:
        """Negative log-likelihood (chi^2 units) of a planar fit: residuals over ``choice_sigma_px``
        and the caller's prior pose."""
        cost = fit.sse / self.choice_sigma_px**2
        if prior is not None:
            x, y, yaw = fit.p[:3].tolist()
            cost += ((x - prior[0]) ** 2 + (y - prior[1]) ** 2) / self.prior_sigma_xy_m**2
            cost += (wrap_angle(yaw - prior[2]) / self.prior_sigma_yaw_rad) ** 2
        return cost

