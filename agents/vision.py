"""One robot's vision: camera frames in, relative pose estimates of what it sees out.

Pure code (no bus): :mod:`tagswarm.agents.node` hands it the frames of one instant and
publishes what comes back.  Frames are ``CameraImage`` messages, each (H, W) uint8 grey
in the camera's optical frame with its own camera model; estimates are
:class:`~tagswarm.agents.cubepose.PoseEstimate` of other robots' cubes and of field
landmarks in this robot's base_link (metres, radians).  Its own tags and tags of no
known owner are counted and left out; so is anything farther than ``agent.max_range_m``.
"""

from __future__ import annotations

import time
from collections import Counter

import numpy as np

from tagswarm.agents.cubepose import CameraModel, CubePoseEstimator, PoseEstimate
from tagswarm.agents.detect import TagMap, make_detector
from tagswarm.agents.landmarkfix import fix_estimates
from tagswarm.protocol import messages as m
from tagswarm.protocol.scenario import Scenario

PRIOR_MAX_AGE_NS = 500_000_000  # robots move ~15 cm in 0.5 s: older relative poses mislead more than help


class Vision:
    """Tag detection, cube pose and landmark fixes of one robot (see the module docstring)."""

    def __init__(self, scenario: Scenario, robot_id: int, counters: Counter[str], frame_delay_s: float = 0.0) -> None:
        self.s, self.rid, self.counters = scenario, robot_id, counters
        a = scenario.agent
        self.detector = make_detector(scenario.tags.family, a.detector, max_hamming=a.max_hamming,
                                      min_margin=a.min_margin)
        self.tagmap = TagMap.from_scenario(scenario)
        self.estimator = CubePoseEstimator(scenario, pixel_sigma_px=a.pixel_sigma_px, max_rms_px=a.max_reprojection_px)
        self.frame_delay_s = frame_delay_s
        self._camera_models: dict[str, tuple[tuple[object, ...], CameraModel]] = {}
        # CPU seconds (this thread) in the detector and the pose estimate: bench/speed.py's overhead ratio
        self.detect_pose_cpu_s = 0.0
        self.reset()

    def reset(self) -> None:
        """Forget the relative poses of earlier frames (a new world run)."""
        # last relative pose of each target and when: a prior for single-face ambiguity, only while fresh
        self._priors: dict[tuple[str, int], tuple[int, tuple[float, float, float]]] = {}

    def process(self, frames: list[m.CameraImage], time_ns: int,
                expected: dict[tuple[str, int], tuple[float, float, float]] | None = None) -> list[PoseEstimate]:
        """Estimates from ``frames`` (this robot's, of one instant; ``time_ns`` the agent's clock),
        all stamped with the newest frame's stamp; ``expected`` where the map has the targets
        (see :meth:`~tagswarm.agents.cubepose.CubePoseEstimator.estimate`)."""
        views = []
        for img in frames:
            if self.frame_delay_s > 0:
                time.sleep(self.frame_delay_s)  # injected overload (tests, demos): a slow detector
            # how old the frame is when we get to it (simulated time): stays small if frames are skipped, not queued
            age_ms = max(0, time_ns - img.stamp_ns) // 1_000_000
            self.counters["frame_age_max_ms"] = max(self.counters["frame_age_max_ms"], age_ms)
            gray = np.frombuffer(img.data, np.uint8).reshape(img.height, img.width)
            dets = []
            t0 = time.thread_time()
            found = self.detector.detect(gray)
            self.detect_pose_cpu_s += time.thread_time() - t0
            for d in found:
                owner = self.tagmap.lookup(d.tag_id)
                if owner is None:
                    self.counters["unknown_tags"] += 1
                elif owner[0] == "robot" and owner[1] == self.rid:
                    self.counters["own_tags"] += 1  # a reflection of ourselves cannot happen; count it
                else:
                    dets.append(d)
            views.append((self.camera_model(img), dets))
            self.counters["frames_processed"] += 1
        stamp = max(img.stamp_ns for img in frames)
        fresh = {k: p for k, (t, p) in self._priors.items() if stamp - t <= PRIOR_MAX_AGE_NS}
        # with several field tags in view, one fix from all of them replaces the per-tag ones
        t0 = time.thread_time()
        estimates = fix_estimates(self.estimator, self.s, self.estimator.estimate(views, fresh, expected), views)
        self.detect_pose_cpu_s += time.thread_time() - t0
        kept = []
        for est in estimates:
            if np.hypot(est.x_m, est.y_m) > self.s.agent.max_range_m:
                self.counters["rejected_range"] += 1
                continue
            self._priors[(est.target_kind, est.target_id)] = (stamp, (est.x_m, est.y_m, est.yaw_rad))
            kept.append(est)
        return kept

    def camera_model(self, img: m.CameraImage) -> CameraModel:
        """The camera model of ``img``, made once per camera while its calibration stays the same
        (building one costs ~0.1 ms, a 3x3 and a 4x4 matrix and an inverse, every frame)."""
        key = (img.camera, img.fx_px, img.fy_px, img.cx_px, img.cy_px, img.width, img.height, img.lens,
               tuple(img.distortion), img.mount, img.robot_id)
        cached = self._camera_models.get(img.camera)
        if cached is None or cached[0] != key:
            cached = self._camera_models[img.camera] = (key, CameraModel.from_message(img))
        return cached[1]
