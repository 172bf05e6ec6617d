"""Copy cubes (``[[decoys]] kind = "cube"``): a second robot carrying copies of a robot's tag
IDs.  Seen in one image with the robot it copies, neither is trusted (two plausible robots of
one identity: ``duplicate``); seen alone it is, in the images, that robot -- the server's gate
keeps it out of the map (tests/e2e/test_copy_cube_run.py)."""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np
import pybullet as pb
import pytest

from tagswarm.agents.cubegeom import CameraModel
from tagswarm.agents.cubepose import CubePoseEstimator, PoseEstimate
from tagswarm.agents.detect import make_detector
from tagswarm.protocol.geometry import se2_matrix
from tagswarm.protocol.scenario import ScenarioError, load_scenario
from tagswarm.protocol.scenario_schema import decoy_cube_ids
from tagswarm.world.decoys import build_decoys
from tagswarm.world.render import CHASSIS_RGBA, Renderer, image_message

BASE = ["robots.count=2", 'robots.placement="explicit"', "robots.start=[{x_m=0.0, y_m=0.0}, {x_m=2.0, y_m=0.4}]"]
COPY = 'decoys=[{kind="cube", tag_id=11, x_m=2.0, y_m=-0.4, yaw_rad=0.0}]'  # robot 1's cube, 0.8 m to its right


def _estimate(preset: str, robot_1_xy: tuple[float, float], robot_1_yaw: float = 0.0,
              expected: dict[tuple[str, int], tuple[float, float, float]] | None = None,
              ) -> tuple[CubePoseEstimator, list[PoseEstimate]]:
    s = load_scenario("paper", [*BASE, COPY, f"camera.preset={preset}"])
    plain = load_scenario("paper", [*BASE, f"camera.preset={preset}"])  # the render scene gets the copy below
    cam = s.robot.cameras[0]
    # an asset folder of our own: the renderer's temporary one is gone once its scene is built
    with tempfile.TemporaryDirectory(prefix="tagswarm-test-assets-") as assets, Renderer(plain, Path(assets)) as r:
        build_decoys(r.cid, s, r.asset_dir, CHASSIS_RGBA)
        r.set_pose(0, (0, 0, 0), (0, 0, 0, 1))
        # both robots face the observer's camera with their back tag (yaw 0: the back is at -x)
        r.set_pose(1, (*robot_1_xy, 0), pb.getQuaternionFromEuler((0, 0, robot_1_yaw)))
        msg = image_message(s, 0, cam, r.render(0, cam, se2_matrix(0, 0, 0)), seq=0, step=0, stamp_ns=0)
    dets = make_detector(s.tags.family).detect(np.frombuffer(msg.data, np.uint8).reshape(msg.height, msg.width))
    est = CubePoseEstimator(s)
    return est, est.estimate([(CameraModel.from_message(msg), [d for d in dets if 10 < d.tag_id < 20])],
                             expected=expected)


def test_copy_cube_ids() -> None:
    s = load_scenario("paper", [COPY])
    assert decoy_cube_ids(s.decoys[0], "tag36h11") == s.tag_ids(1) == (11, 12, 13, 14, 15, 16)
    assert decoy_cube_ids(load_scenario("paper", ['decoys=[{kind="cube", tag_id=585, x_m=0, y_m=0}]']).decoys[0],
                          "tag36h11") == (585, 586, 0, 1, 2, 3)
    with pytest.raises(ScenarioError, match=r"decoys\[0\]"):
        load_scenario("paper", ['decoys=[{kind="box", tag_id=11, x_m=1.0, y_m=0.0}]'])


@pytest.mark.parametrize(("preset", "yaw"), [("ideal", 0.0), ("realistic", 0.0), ("ideal", 0.8)])
def test_a_copy_beside_its_robot_makes_neither_trusted(preset: str, yaw: float) -> None:
    """Yaw 0: both show the back tag alone, both copies fit; 0.8 rad: the robot shows its back and
    a side, which only its own back tag fits, but the copy's back tag alone is a robot too."""
    est, found = _estimate(preset, (2.0, 0.4), yaw)
    assert found == [], found
    assert est.rejects == {"duplicate": 1}, est.rejects


@pytest.mark.parametrize(("preset", "yaw"), [("ideal", 0.0), ("realistic", 0.0), ("ideal", 0.8)])
def test_the_map_tells_a_robot_from_its_copy_beside_it(preset: str, yaw: float) -> None:
    """Once the map has robot 1 (within its reach, 0.5 m here), the copy 0.8 m beside it is told
    apart: robot 1 is estimated where it stands and the copy's tags count as decoys.  A map whose
    reach covers both copies, or one that has robot 1 elsewhere, decides nothing."""
    est, found = _estimate(preset, (2.0, 0.4), yaw, {("robot", 1): (1.95, 0.45, 0.5)})
    assert [e.target_id for e in found] == [1]
    assert math.hypot(found[0].x_m - 2.0, found[0].y_m - 0.4) < 0.05, found[0]
    assert est.resolved_by_map == 1 and est.rejects["decoy"] >= 1 and "duplicate" not in est.rejects
    for wrong in ((2.0, 0.0, 0.9), (-1.0, 2.0, 0.5)):
        est, found = _estimate(preset, (2.0, 0.4), yaw, {("robot", 1): wrong})
        assert found == [] and est.rejects == {"duplicate": 1} and est.resolved_by_map == 0, wrong


def test_a_copy_alone_is_its_robot_in_the_images() -> None:
    """The limit of what one image can tell: the copy alone (robot 1 out of view) is estimated
    where the copy stands, as robot 1 would be.  The map is protected downstream."""
    _, found = _estimate("ideal", (-2.0, 1.5))
    assert [e.target_id for e in found] == [1]
    assert math.hypot(found[0].x_m - 2.0, found[0].y_m + 0.4) < 0.05, found[0]


def test_copy_sites_are_remembered_in_the_map_frame_for_a_while() -> None:
    """A copy seen beside its robot from map pose (1, 0, 90 deg) 2 m ahead is at map (1, 2); a later
    sighting there is at the site, one 0.5 m away is not, and another robot's sightings never are.
    A site not seen again for COPY_SITE_TTL_NS is forgotten (one filed under a wrong map cannot
    hide the robot for good); seeing it again refreshes it."""
    from tagswarm.agents.decoys import COPY_SITE_TTL_NS, MAX_COPY_SITES, CopySites

    sites = CopySites()
    sites.remember((1.0, 0.0, math.pi / 2), [(("robot", 1), 2.0, 0.0), (("landmark", 7), 1.0, 0.0)], 0)
    assert sites.at(1, 1.0, 2.0, 0) and sites.at(1, 1.1, 2.1, 5)
    assert not sites.at(1, 1.0, 2.5, 0) and not sites.at(2, 1.0, 2.0, 0) and not sites.at(7, 1.0, 1.0, 0)
    assert not sites.at(1, 1.0, 2.0, COPY_SITE_TTL_NS + 1)
    sites.remember((1.0, 0.0, math.pi / 2), [(("robot", 1), 2.05, 0.0)], COPY_SITE_TTL_NS)  # the same site again
    assert len(sites.sites[1]) == 1 and sites.at(1, 1.0, 2.0, COPY_SITE_TTL_NS + 1)
    for k in range(20):
        sites.remember((0.0, 0.0, 0.0), [(("robot", 1), 10.0 + k, 0.0)], 0)
    assert len(sites.sites[1]) == MAX_COPY_SITES
