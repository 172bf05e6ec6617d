"""Decoys in the render scene: posters and copy cubes (``[[decoys]]``; docs/camera.md, Decoys).

Only the renderer knows them: visual bodies, no physics (a robot drives through a
copy cube as through air), and no agent is told.  A ``poster`` is a landmark's plate
carrying the decoy's tag; a ``cube`` is a copy of a robot -- its chassis and tag cube at
the scenario's sizes -- standing still on the floor, carrying
:func:`tagswarm.protocol.scenario_schema.decoy_cube_ids`.  Frames: the arena frame; metres, radians.
"""

from __future__ import annotations

from pathlib import Path

from tagswarm.protocol.scenario import Scenario
from tagswarm.protocol.scenario_schema import Decoy, decoy_cube_ids
from tagswarm.world import assets
from tagswarm.world._pybullet import pb

Rgba = tuple[float, float, float, float]


def robot_visual(cid: int, scenario: Scenario, family: str, ids: tuple[int, ...], asset_dir: Path,
                 chassis_rgba: Rgba) -> int:
    """A visual shape of a robot (chassis box and tag cube carrying ``ids`` of ``family``) in its base frame."""
    r = scenario.robot
    obj = assets.cube_mesh(asset_dir, family, ids, r.cube_edge_m, scenario.tags.size_m)
    return int(pb.createVisualShapeArray(
        shapeTypes=[pb.GEOM_BOX, pb.GEOM_MESH],
        halfExtents=[[r.chassis_length_m / 2, r.chassis_width_m / 2, r.chassis_height_m / 2], [0, 0, 0]],
        fileNames=["", str(obj)],
        meshScales=[[1, 1, 1], [1, 1, 1]],
        rgbaColors=[list(chassis_rgba), [1, 1, 1, 1]],
        visualFramePositions=[[0, 0, r.ground_clearance_m + r.chassis_height_m / 2], [0, 0, r.cube_center_z_m]],
        physicsClientId=cid,
    ))


def build_decoy(cid: int, scenario: Scenario, d: Decoy, asset_dir: Path, chassis_rgba: Rgba) -> int:
    """Add decoy ``d`` to the render scene of client ``cid``; returns its body id."""
    family = d.family or scenario.tags.family
    orn = pb.getQuaternionFromEuler((0, 0, d.yaw_rad))
    if d.kind == "cube":
        vis = robot_visual(cid, scenario, family, decoy_cube_ids(d, family), asset_dir, chassis_rgba)
        pos = (d.x_m, d.y_m, 0.0)
    else:
        obj = assets.landmark_mesh(asset_dir, family, d.tag_id, d.size_m)
        vis = pb.createVisualShape(pb.GEOM_MESH, fileName=str(obj), physicsClientId=cid)
        pos = (d.x_m, d.y_m, d.z_m)
    return int(pb.createMultiBody(baseMass=0, baseVisualShapeIndex=vis, basePosition=pos, baseOrientation=orn,
                                  physicsClientId=cid))


def build_decoys(cid: int, scenario: Scenario, asset_dir: Path, chassis_rgba: Rgba) -> list[int]:
    """Every decoy of ``scenario`` in the render scene of client ``cid`` (body ids)."""
    return [build_decoy(cid, scenario, d, asset_dir, chassis_rgba) for d in scenario.decoys]
