"""Foxglove well-known messages (``foxglove.*`` protobuf schemas, via foxglove-sdk) derived
from tagswarm messages, so a recording opens in Foxglove with poses, frames, the map and the
cameras.  Pure: message in, encoded views out.

Frames (REP-105, see docs/architecture.md, section 4)::

    map ──(static, when the scenario is known)──▶ arena ──▶ (truth poses)
    map ──(Correction: map -> odom_k)──▶ odom_k ──(OdometryEstimate)──▶ base_link_k
    base_link_k ──(CameraImage.mount)──▶ camera_k_<name>   (OpenCV optical frame)

Topics (``<run>`` is the run id of the key)::

    /<run>/tf                              foxglove.FrameTransform (all of the above)
    /<run>/robot/<k>/truth                 foxglove.PoseInFrame  (frame arena)
    /<run>/robot/<k>/fused                 foxglove.PoseInFrame  (frame map, from Correction)
    /<run>/robot/<k>/odometry              foxglove.PoseInFrame  (frame odom_k)
    /<run>/robot/<k>/observation           foxglove.PoseInFrame  (frame base_link_k: the target)
    /<run>/robot/<k>/camera/<name>         foxglove.RawImage     (mono8)
    /<run>/robot/<k>/camera/<name>/calibration  foxglove.CameraCalibration
    /<run>/map                             foxglove.SceneUpdate  (one cube + label per robot, edges)
    /<run>/map/poses                       foxglove.PosesInFrame (frame map)
"""

from __future__ import annotations

import math
from typing import Any

from foxglove import messages as fg

from tagswarm.protocol import messages as m
from tagswarm.protocol.geometry import Pose2
from tagswarm.recording.mcapio import run_of

View = tuple[str, Any, bytes]  # (topic, foxglove.Schema, encoded protobuf)
CUBE_EDGE_M = 0.2  # drawn size of a robot in the map view (the scenario's cube edge when known)


def _stamp(ns: int) -> Any:
    return fg.Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)


def _yaw_quat(yaw_rad: float) -> Any:
    return fg.Quaternion(x=0.0, y=0.0, z=math.sin(yaw_rad / 2), w=math.cos(yaw_rad / 2))


def _planar(x: float, y: float, yaw: float) -> Any:
    return fg.Pose(position=fg.Vector3(x=x, y=y, z=0.0), orientation=_yaw_quat(yaw))


def _pose3(p: m.Pose3) -> Any:
    return fg.Pose(position=fg.Vector3(x=p.x_m, y=p.y_m, z=p.z_m),
                   orientation=fg.Quaternion(x=p.qx, y=p.qy, z=p.qz, w=p.qw))


def _tf(ns: int, parent: str, child: str, x: float, y: float, z: float, q: Any) -> Any:
    return fg.FrameTransform(timestamp=_stamp(ns), parent_frame_id=parent, child_frame_id=child,
                             translation=fg.Vector3(x=x, y=y, z=z), rotation=q)


class FoxgloveViews:
    """Turns decoded tagswarm messages into Foxglove views.

    ``map_from_arena`` is T_map_arena (x_m, y_m, yaw_rad) from the scenario
    (:func:`tagswarm.protocol.layout.arena_to_map`); without it the truth stays in its own
    ``arena`` frame, unconnected to ``map``.  ``image_scale`` is already applied to the
    images handed in (nothing is resampled here).
    """

    def __init__(self, map_from_arena: Pose2 | None = None, cube_edge_m: float = CUBE_EDGE_M) -> None:
        self.map_from_arena = map_from_arena
        self.cube_edge_m = cube_edge_m
        self._static_sent: set[str] = set()

    def views(self, key: str, msg: m.Msg) -> list[View]:
        """The Foxglove messages for one tagswarm message on ``key`` (may be empty)."""
        run = run_of(key)
        if run is None:
            return []
        p = f"/{run}"
        out: list[View] = []
        if run not in self._static_sent and self.map_from_arena is not None:
            self._static_sent.add(run)
            x, y, yaw = self.map_from_arena
            out.append(self._enc(f"{p}/tf", _tf(msg.stamp_ns, "map", "arena", x, y, 0.0, _yaw_quat(yaw))))
        ns = msg.stamp_ns
        if isinstance(msg, m.GroundTruthPose):
            out.append(self._enc(f"{p}/robot/{msg.robot_id}/truth",
                                 fg.PoseInFrame(timestamp=_stamp(ns), frame_id="arena", pose=_pose3(msg.pose))))
        elif isinstance(msg, m.Correction) and msg.localised:
            out.append(self._enc(f"{p}/robot/{msg.robot_id}/fused", fg.PoseInFrame(
                timestamp=_stamp(msg.pose_time_ns), frame_id="map", pose=_planar(msg.x_m, msg.y_m, msg.yaw_rad))))
            out.append(self._enc(f"{p}/tf", _tf(ns, "map", f"odom_{msg.robot_id}", msg.map_odom_x_m,
                                               msg.map_odom_y_m, 0.0, _yaw_quat(msg.map_odom_yaw_rad))))
        elif isinstance(msg, m.OdometryEstimate):
            rid = msg.robot_id
            out.append(self._enc(f"{p}/robot/{rid}/odometry", fg.PoseInFrame(
                timestamp=_stamp(ns), frame_id=f"odom_{rid}", pose=_planar(msg.x_m, msg.y_m, msg.yaw_rad))))
            out.append(self._enc(f"{p}/tf", _tf(ns, f"odom_{rid}", f"base_link_{rid}", msg.x_m, msg.y_m, 0.0,
                                               _yaw_quat(msg.yaw_rad))))
        elif isinstance(msg, m.RelativeObservation):
            out.append(self._enc(f"{p}/robot/{msg.robot_id}/observation", fg.PoseInFrame(
                timestamp=_stamp(ns), frame_id=f"base_link_{msg.robot_id}",
                pose=_planar(msg.x_m, msg.y_m, msg.yaw_rad))))
        elif isinstance(msg, m.CameraImage):
            out += self._image(p, msg)
        elif isinstance(msg, m.GlobalMap):
            out += self._map(p, msg)
        return out

    @staticmethod
    def _enc(topic: str, message: Any) -> View:
        return topic, message.get_schema(), message.encode()

    def _image(self, p: str, img: m.CameraImage) -> list[View]:
        frame = f"camera_{img.robot_id}_{img.camera}"
        ns, base = img.stamp_ns, f"{p}/robot/{img.robot_id}/camera/{img.camera}"
        mt = img.mount
        k = [img.fx_px, 0.0, img.cx_px, 0.0, img.fy_px, img.cy_px, 0.0, 0.0, 1.0]
        return [
            self._enc(f"{p}/tf", _tf(ns, f"base_link_{img.robot_id}", frame, mt.x_m, mt.y_m, mt.z_m,
                                     fg.Quaternion(x=mt.qx, y=mt.qy, z=mt.qz, w=mt.qw))),
            self._enc(base, fg.RawImage(timestamp=_stamp(ns), frame_id=frame, width=img.width, height=img.height,
                                        encoding="mono8", step=img.width, data=img.data)),
            self._enc(f"{base}/calibration", fg.CameraCalibration(
                timestamp=_stamp(ns), frame_id=frame, width=img.width, height=img.height,
                distortion_model="plumb_bob", D=[0.0] * 5, K=k, R=[1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0],
                P=[img.fx_px, 0.0, img.cx_px, 0.0, 0.0, img.fy_px, img.cy_px, 0.0, 0.0, 0.0, 1.0, 0.0])),
        ]

    def _map(self, p: str, gm: m.GlobalMap) -> list[View]:
        ns, edge = gm.stamp_ns, self.cube_edge_m
        where = {e.robot_id: e for e in gm.robots}
        entities = []
        for e in gm.robots:
            color = fg.Color(r=0.1, g=0.6, b=1.0, a=0.9) if e.alive else fg.Color(r=0.5, g=0.5, b=0.5, a=0.6)
            if e.robot_id == gm.origin_id:
                color = fg.Color(r=1.0, g=0.6, b=0.1, a=0.9)
            heading = fg.Pose(position=fg.Vector3(x=e.x_m, y=e.y_m, z=edge),
                              orientation=_yaw_quat(e.yaw_rad))
            entities.append(fg.SceneEntity(
                timestamp=_stamp(ns), frame_id="map", id=f"robot/{e.robot_id}",
                cubes=[fg.CubePrimitive(pose=fg.Pose(position=fg.Vector3(x=e.x_m, y=e.y_m, z=edge / 2),
                                                     orientation=_yaw_quat(e.yaw_rad)),
                                        size=fg.Vector3(x=edge, y=edge, z=edge), color=color)],
                arrows=[fg.ArrowPrimitive(pose=heading, shaft_length=edge, shaft_diameter=edge / 8,
                                          head_length=edge / 3, head_diameter=edge / 4, color=color)],
                texts=[fg.TextPrimitive(pose=fg.Pose(position=fg.Vector3(x=e.x_m, y=e.y_m, z=edge * 1.8),
                                                     orientation=fg.Quaternion(w=1.0)),
                                        billboard=True, font_size=14.0, scale_invariant=True,
                                        color=fg.Color(r=1.0, g=1.0, b=1.0, a=1.0), text=f"robot {e.robot_id}")]))
        points = []
        for a, b in gm.edges:
            if a in where and b in where:
                points += [fg.Point3(x=where[a].x_m, y=where[a].y_m, z=edge),
                           fg.Point3(x=where[b].x_m, y=where[b].y_m, z=edge)]
        entities.append(fg.SceneEntity(
            timestamp=_stamp(ns), frame_id="map", id="edges",
            lines=[fg.LinePrimitive(type=fg.LinePrimitiveLineType.LineList, thickness=2.0, scale_invariant=True,
                                    points=points, color=fg.Color(r=0.2, g=1.0, b=0.3, a=0.8))] if points else []))
        return [
            self._enc(f"{p}/map", fg.SceneUpdate(entities=entities)),
            self._enc(f"{p}/map/poses", fg.PosesInFrame(
                timestamp=_stamp(ns), frame_id="map", poses=[_planar(e.x_m, e.y_m, e.yaw_rad) for e in gm.robots])),
        ]
