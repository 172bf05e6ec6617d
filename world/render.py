"""Camera rendering on a visual-only replica of the scene.

A :class:`Renderer` owns its own pybullet client (DIRECT, TinyRenderer) holding
only visual shapes: no physics is ever stepped on it, robots are moved with
``resetBasePositionAndOrientation`` (cheap for massless, collision-free bodies).
The world process holds one when it renders in-process; each render worker
holds one and renders a subset of the cameras.  Cheap choices are the default
(docs/architecture.md, section 5): no floor, no shadows, no segmentation mask, one body per
robot.
"""

from __future__ import annotations

import functools
import itertools
import math
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from tagswarm.protocol.geometry import Mat, matrix_to_pose3, quat_to_rot, transform
from tagswarm.protocol.layout import wall_boxes
from tagswarm.protocol.messages import CameraImage, Pose3
from tagswarm.protocol.scenario import Camera, Scenario
from tagswarm.world import assets
from tagswarm.world._pybullet import pb
from tagswarm.world.blur import Exposures, camera_twist, expose, exposure_maps
from tagswarm.world.camera import mount_transform, vfov_deg
from tagswarm.world.decoys import build_decoys, robot_visual
from tagswarm.world.lens import Fovea, Lens, RenderPlan, lens_for, plan
from tagswarm.world.sensor import NoiseBank, develop, frame_key, tone, vignetting_gain

WALL_RGBA = (0.55, 0.55, 0.6, 1.0)
OBSTACLE_RGBA = (0.45, 0.35, 0.3, 1.0)
CHASSIS_RGBA = (0.15, 0.3, 0.6, 1.0)
FLOOR_RGBA = (0.7, 0.7, 0.7, 1.0)
SEGMENT_M = 1.0  # longest side of the pieces static boxes are drawn in (see Renderer._box)
MAX_SHAPES_PER_BODY = 16  # pybullet's limit for createVisualShapeArray
Shot = tuple[NDArray[np.uint8], NDArray[Any] | None]  # a pinhole render (H, W) and its depth buffer, if asked


class Renderer:
    """Visual replica of a scenario's scene and the cameras of its robots."""

    def __init__(self, scenario: Scenario, asset_dir: Path | None = None) -> None:
        self.scenario = scenario
        tmp = None
        if asset_dir is None:
            tmp = tempfile.TemporaryDirectory(prefix="tagswarm-assets-")
            asset_dir = Path(tmp.name)
        self.asset_dir = asset_dir  # read only while the scene is built (a temporary one is gone after)
        self.cid = pb.connect(pb.DIRECT)
        self.bodies: dict[int, int] = {}
        self._proj: dict[str, list[float]] = {}
        self._mount: dict[str, Mat] = {c.name: mount_transform(c) for c in scenario.robot.cameras}
        self.frames_rendered = 0
        self._sensor = scenario.camera.resolved()
        self._effects = scenario.camera.has_effects
        self._plans: dict[str, RenderPlan] = {}
        self._tone: dict[str, tuple[NDArray[np.float32], float]] = {}
        self._banks: dict[str, NoiseBank] = {}
        self._poses: dict[int, Mat] = {}
        # per robot: (stamp, T_world_base) of the two newest instants this renderer developed a frame at
        self._track: dict[int, tuple[tuple[int, Mat], tuple[int, Mat] | None]] = {}
        self._track_stamp = -1  # the newest instant the tracks advanced to
        try:
            self._build()
        finally:
            # pybullet reads meshes and textures when a body is made: the files are not needed
            # after the build, and a process SIGKILLed later (render workers at a run's end)
            # would leave them in /tmp for good
            if tmp is not None:
                tmp.cleanup()

    # ------------------------------------------------------------------ scene
    def _box(self, half: tuple[float, float, float], pos: tuple[float, float, float], yaw: float,
             rgba: tuple[float, ...]) -> None:
        """A static box, drawn as pieces of at most ``SEGMENT_M`` a side.  TinyRenderer tests
        every pixel of each triangle's screen bounding box, and a wall's triangles reach far
        past the image: a 7 m wall in view cost 25 ms of a 320x240 frame, 1 m pieces 9 ms,
        with the same pixels out (tests/unit/world/test_render_geometry.py)."""
        counts = [max(1, math.ceil(2 * h / SEGMENT_M - 1e-9)) for h in half]
        piece = [h / n for h, n in zip(half, counts, strict=True)]
        frames = [[-h + (2 * i + 1) * q for h, q, i in zip(half, piece, idx, strict=True)]
                  for idx in itertools.product(*(range(n) for n in counts))]
        orn = pb.getQuaternionFromEuler((0, 0, yaw))
        for k in range(0, len(frames), MAX_SHAPES_PER_BODY):  # more per body crashes pybullet
            chunk = frames[k:k + MAX_SHAPES_PER_BODY]
            vis = pb.createVisualShapeArray(shapeTypes=[pb.GEOM_BOX] * len(chunk), halfExtents=[piece] * len(chunk),
                                            rgbaColors=[list(rgba)] * len(chunk), visualFramePositions=chunk,
                                            physicsClientId=self.cid)
            pb.createMultiBody(baseMass=0, baseVisualShapeIndex=vis, basePosition=pos, baseOrientation=orn,
                               physicsClientId=self.cid)

    def _build(self) -> None:
        s = self.scenario
        a = s.arena
        if s.render.floor:
            self._box((a.size_x_m / 2, a.size_y_m / 2, 0.005), (0, 0, -0.005), 0.0, FLOOR_RGBA)
        for pos, half in wall_boxes(a):
            self._box(half, pos, 0.0, WALL_RGBA)
        for ob in a.obstacles:
            self._box((ob.size_x_m / 2, ob.size_y_m / 2, ob.size_z_m / 2), (ob.x_m, ob.y_m, ob.size_z_m / 2),
                      ob.yaw_rad, OBSTACLE_RGBA)
        for lm in s.landmarks:
            obj = assets.landmark_mesh(self.asset_dir, s.tags.family, lm.id, lm.size_m)
            vis = pb.createVisualShape(pb.GEOM_MESH, fileName=str(obj), physicsClientId=self.cid)
            pb.createMultiBody(baseMass=0, baseVisualShapeIndex=vis, basePosition=(lm.x_m, lm.y_m, lm.z_m),
                               baseOrientation=pb.getQuaternionFromEuler((0, 0, lm.yaw_rad)),
                               physicsClientId=self.cid)
        build_decoys(self.cid, s, self.asset_dir, CHASSIS_RGBA)  # posters and copy cubes
        for rid in s.robot_ids:
            # one body per robot (every body costs ~0.2 ms per image): chassis box + cube mesh
            vis = robot_visual(self.cid, s, s.tags.family, s.tag_ids(rid), self.asset_dir, CHASSIS_RGBA)
            self.bodies[rid] = pb.createMultiBody(baseMass=0, baseVisualShapeIndex=vis, basePosition=(0, 0, -10),
                                                  physicsClientId=self.cid)

    # ------------------------------------------------------------------ poses
    def set_pose(self, robot_id: int, position: tuple[float, float, float],
                 orientation: tuple[float, float, float, float]) -> None:
        """Place robot ``robot_id``'s base frame (floor level, body axes) in the arena."""
        pb.resetBasePositionAndOrientation(self.bodies[robot_id], position, orientation, physicsClientId=self.cid)
        if self._effects:
            self._poses[robot_id] = pose_matrix(position, orientation)

    # ------------------------------------------------------------------ cameras
    def _projection(self, cam: Camera) -> list[float]:
        proj = self._proj.get(cam.name)
        if proj is None:
            proj = self._proj[cam.name] = list(pb.computeProjectionMatrixFOV(
                fov=vfov_deg(cam), aspect=cam.width / cam.height, nearVal=cam.near_m, farVal=cam.far_m,
                physicsClientId=self.cid))
        return proj

    def plan(self, cam: Camera) -> RenderPlan:
        """The render plan of ``cam`` (its lens's pinhole render and remap maps), made once."""
        p = self._plans.get(cam.name)
        if p is None:
            p = self._plans[cam.name] = plan(cam, self.scenario.camera.preset)
        return p

    def _shoot(self, cam: Camera, t_wc: Mat, depth: bool, count: bool = True,
               out: NDArray[np.uint8] | None = None) -> tuple[NDArray[np.uint8], NDArray[Any] | None]:
        """Grayscale pinhole render (H, W) of ``cam`` at T_world_cam ``t_wc`` (written into ``out`` if
        given), and its depth buffer if asked (``count``: a camera frame in :attr:`frames_rendered`,
        not a lens's fovea)."""
        eye = t_wc[:3, 3]
        fwd, down = t_wc[:3, 2], t_wc[:3, 1]
        view = pb.computeViewMatrix(eye.tolist(), (eye + fwd).tolist(), (-down).tolist(), physicsClientId=self.cid)
        _, _, rgba, zbuf, _ = pb.getCameraImage(
            cam.width, cam.height, viewMatrix=view, projectionMatrix=self._projection(cam),
            shadow=int(self.scenario.render.shadows), renderer=pb.ER_TINY_RENDERER,
            flags=pb.ER_NO_SEGMENTATION_MASK, physicsClientId=self.cid)
        img = np.asarray(rgba, dtype=np.uint8).reshape(cam.height, cam.width, 4)
        self.frames_rendered += count
        gray = np.asarray(cv2.cvtColor(img, cv2.COLOR_RGBA2GRAY, dst=out), np.uint8)  # ITU-R 601 luma
        return gray, (np.asarray(zbuf, np.float32).reshape(cam.height, cam.width) if depth else None)

    def render(self, robot_id: int, cam: Camera, base_pose: Mat) -> NDArray[np.uint8]:
        """Grayscale image (H, W) uint8 of camera ``cam`` on robot ``robot_id`` whose
        base is at ``base_pose`` (T_world_base, (4, 4)), through its lens.  With sensor
        effects on (``[camera]``) it is an :class:`Exposure`: the noise-free image, which
        :func:`image_message` develops with the frame's tick (seed, motion blur)."""
        t_wc = base_pose @ self._mount[cam.name]
        p = self.plan(cam)
        if p.maps is None and not self._effects:
            return self._shoot(cam, t_wc, False)[0]
        need_depth = self._effects and bool(self._sensor.exposure_ms)
        fovea = None
        if p.fovea is None:
            gray, zbuf = self._shoot(p.render_cam, t_wc, need_depth)
            lensed = np.asarray(p.apply(gray), np.uint8)
        else:  # both renders into one atlas, resampled at once
            atlas = p.fovea.atlas()
            gray, zbuf = self._shoot(p.render_cam, t_wc, need_depth, out=p.fovea.wide_part(atlas))
            fovea = self._shoot(p.fovea.render_cam, t_wc, need_depth, count=False, out=p.fovea.part(atlas))
            lensed = np.asarray(p.apply(atlas), np.uint8)
        if not self._effects:
            return lensed
        # the 8-bit lens image is developed as it is unless a blur resamples the render: its rounding
        # (0.29 DN rms) is a tenth of the realistic preset's noise and spares a float copy of the render
        frame = lensed.view(Exposure)
        frame.develop_fn = functools.partial(self._develop, robot_id, cam, (gray, zbuf), lensed, fovea,
                                             base_pose.copy())
        return frame

    def _twist(self, robot_id: int, cam: Camera, base_pose: Mat, stamp_ns: int) -> NDArray[np.float64] | None:
        """The camera's twist (optical frame) from its robot's motion since the previous instant this
        renderer developed a frame at; every robot's track advances to ``stamp_ns``."""
        if stamp_ns < self._track_stamp:  # a new world run (a restart): its clock starts again
            self._track.clear()
            self._track_stamp = -1
        if stamp_ns > self._track_stamp:  # a new instant: every robot's track advances, once
            self._track_stamp = stamp_ns
            for rid, pose in self._poses.items():
                if rid != robot_id:  # its pose is the one it is rendered at
                    self._advance(rid, pose, stamp_ns)
        self._advance(robot_id, base_pose, stamp_ns)
        (_, now), prev = self._track[robot_id]
        if prev is None:
            return None
        mount = self._mount[cam.name]
        return camera_twist(prev[1] @ mount, now @ mount, (stamp_ns - prev[0]) * 1e-9)

    def _advance(self, robot_id: int, pose: Mat, stamp_ns: int) -> None:
        cur = self._track.get(robot_id)
        if cur is None or cur[0][0] < stamp_ns:
            self._track[robot_id] = ((stamp_ns, pose), None if cur is None else cur[0])

    def _develop(self, robot_id: int, cam: Camera, shot: Shot, lensed: NDArray[np.uint8], fovea: Shot | None,
                 base_pose: Mat, step: int, stamp_ns: int) -> NDArray[np.uint8]:
        """The finished frame: motion blur on the pinhole render ``shot`` (image, depth buffer) and the
        lens's ``fovea`` render, or their noise-free ``lensed`` image when there is none, then
        vignetting, contrast/brightness and noise seeded by (scenario seed, robot, camera, tick)."""
        p = self.plan(cam)
        twist = self._twist(robot_id, cam, base_pose, stamp_ns)
        gray, zbuf = shot
        exposure_s = float(self._sensor.exposure_ms or 0.0) * 1e-3
        maps = None if zbuf is None or twist is None else exposure_maps(
            *p.sample_maps(), zbuf, p.K_render, twist, exposure_s, near_far=(cam.near_m, cam.far_m))
        # the blur's sub-exposures sample the render through the lens directly: one resampling in all
        img: NDArray[Any] = lensed
        if maps is not None:
            img = blurred = expose(gray, maps, lensed)
            if p.fovea is not None and fovea is not None and twist is not None:
                img = self._blur_fovea(p.fovea, maps, blurred, lensed, fovea, twist, exposure_s, cam)
        toned = self._tone.get(cam.name)
        if toned is None:
            v = self._sensor.vignetting or 0.0
            gain = vignetting_gain(cam.width, cam.height, p.lens.K, v) if v > 0 else None
            toned = self._tone[cam.name] = tone(self._sensor, gain, (cam.height, cam.width))
        bank = self._banks.get(cam.name)
        if bank is None:
            bank = self._banks[cam.name] = NoiseBank(self.scenario.seed, cam.name, cam.width * cam.height)
        key = frame_key(self.scenario.seed, robot_id, cam.name, step)
        return develop(img, self._sensor, toned=toned, bank=bank, key=key)

    @staticmethod
    def _blur_fovea(fv: Fovea, maps: Exposures, img: NDArray[np.float32], lensed: NDArray[np.uint8], fovea: Shot,
                    twist: NDArray[np.float64], exposure_s: float, cam: Camera) -> NDArray[np.float32]:
        """``img``, the blurred frame, with its fovea's pixels that the wide render's sub-exposures
        made (a filter over ``lensed`` is right as it is) made again from the fovea's own render."""
        where = fv.mask
        if maps.kernel is not None or (maps.tiles is not None and all(k is not None for _, _, k in maps.tiles)):
            return img
        if maps.tiles is not None:  # only the tiles the sub-exposures made
            made = np.zeros_like(where)
            r0, c0 = fv.rows.start, fv.cols.start
            for rows, cols, k in maps.tiles:
                if k is None:
                    made[max(rows.start - r0, 0):max(rows.stop - r0, 0),
                         max(cols.start - c0, 0):max(cols.stop - c0, 0)] = True
            where = where & made
        gray_f, zbuf_f = fovea
        fmaps = None if zbuf_f is None else exposure_maps(*fv.float_maps, zbuf_f, fv.K_render, twist, exposure_s,
                                                           near_far=(cam.near_m, cam.far_m), resample=True)
        centre = lensed[fv.rows, fv.cols] if fmaps is None else expose(gray_f, fmaps)
        np.copyto(img[fv.rows, fv.cols], centre, where=where)
        return img

    def close(self) -> None:
        """Disconnect the pybullet client."""
        if self.cid >= 0:
            pb.disconnect(physicsClientId=self.cid)
            self.cid = -1

    def __enter__(self) -> Renderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def pose_matrix(position: tuple[float, float, float], orientation: tuple[float, float, float, float]) -> Mat:
    """T_world_base (4, 4) from a position and an (x, y, z, w) quaternion."""
    return transform(quat_to_rot(orientation), position)


class Exposure(np.ndarray):  # type: ignore[type-arg]
    """A rendered frame not yet developed: the noise-free lens image, and ``develop_fn(step,
    stamp_ns)`` giving the finished one (motion blur needs the frame's time, the noise its
    tick).  :func:`image_message` develops it; as an array it is the noise-free image."""

    develop_fn: Callable[[int, int], NDArray[np.uint8]] | None = None

    def __array_finalize__(self, obj: Any) -> None:
        self.develop_fn = getattr(obj, "develop_fn", None)


@functools.lru_cache(maxsize=64)
def published_lens(cam: Camera, preset: str) -> Lens:
    """The lens a camera's images are published with (cached: one per camera)."""
    return lens_for(cam, preset)


@functools.lru_cache(maxsize=64)
def published_mount(cam: Camera) -> Pose3:
    """The mount pose a camera's images carry (cached: building it cost ~3 % of the world's time)."""
    return matrix_to_pose3(mount_transform(cam))


def image_message(scenario: Scenario, robot_id: int, cam: Camera, img: NDArray[np.uint8], *, seq: int, step: int,
                  stamp_ns: int) -> CameraImage:
    """Wrap a rendered (H, W) uint8 frame with its intrinsics, lens and mount pose (an
    :class:`Exposure` is developed first, with tick ``step`` at ``stamp_ns``)."""
    fn = getattr(img, "develop_fn", None)
    if fn is not None:
        img = fn(step, stamp_ns)
    lens = published_lens(cam, scenario.camera.preset)
    k = lens.K
    return CameraImage(seq=seq, stamp_ns=stamp_ns, robot_id=robot_id, camera=cam.name, step=step,
                       width=cam.width, height=cam.height, fx_px=float(k[0, 0]), fy_px=float(k[1, 1]),
                       cx_px=float(k[0, 2]), cy_px=float(k[1, 2]), mount=published_mount(cam),
                       data=np.ascontiguousarray(img, np.uint8).tobytes(), lens=lens.model,
                       distortion=lens.coeffs, version=2)
