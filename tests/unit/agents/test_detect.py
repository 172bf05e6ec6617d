"""Tag detection backends and the tag map, on images from the real renderer.

Both backends must decode the right IDs and return corners in OpenCV's pixel
convention, in the contract order TR, TL, BL, BR: the corners of every detection
are compared with the true 3D corners projected through the published
intrinsics (median under 1 px, mean bias under 0.25 px: a forgotten 0.5 px shift
or a rotated corner order fails).
"""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path
from typing import Literal

import numpy as np
import pytest
from numpy.typing import NDArray

from tagswarm.agents.detect import AprilTagDetector, ArucoDetector, TagDetection, TagMap, make_detector
from tagswarm.protocol import tags
from tagswarm.protocol.geometry import se2_matrix, yaw_quat
from tagswarm.protocol.scenario import Scenario, convert, validate
from tagswarm.world import camera
from tagswarm.world.assets import CELL_PX, tag_image
from tagswarm.world.render import Renderer
from tests.geometry_check import project, world_corners

Backend = Literal["apriltag", "aruco"]
BACKENDS: list[Backend] = ["apriltag", "aruco"]


def scenario() -> Scenario:
    table = {
        "robot": {"cameras": [{"name": "front", "width": 640, "height": 480, "hfov_deg": 60.0}]},
        "robots": {"count": 2, "placement": "explicit", "start": [{"x_m": 0.0, "y_m": 0.0}, {"x_m": 1.5, "y_m": 0.0}]},
        "landmarks": [{"id": 100, "x_m": -3.0, "y_m": 0.5, "z_m": 0.3, "yaw_rad": 0.0}],  # behind the observer
    }
    s: Scenario = convert(table, Scenario, "test")
    validate(s)
    return s


@pytest.fixture(scope="module")
def scene():
    s = scenario()
    with Renderer(s) as r:
        r.set_pose(0, (0.0, 0.0, -10.0), (0, 0, 0, 1))  # the observer's own body is out of the way
        yield s, r


# target (x, y, yaw) in the observer's frame: one or two faces, 0.8-2.5 m
CASES = [(0.8, 0.0, math.pi), (1.2, 0.2, math.pi + 0.6), (1.6, -0.3, math.pi - 0.8), (2.0, 0.3, 0.5),
         (2.5, 0.0, math.pi + 0.3), (1.4, -0.1, math.pi / 2 + 0.5)]


def painted(tag_id: int, flip_cell: tuple[int, int] | None = None, black: int = 0, white: int = 255,
            family: str = "tag36h11") -> NDArray[np.uint8]:
    """A tag image as painted on the cubes, optionally with one data cell flipped and
    reduced contrast, on a white quiet zone."""
    n = tags.black_cells(family)
    img = tag_image(family, tag_id, n * CELL_PX).copy()
    if flip_cell is not None:
        r, c = flip_cell
        cell = img[r * CELL_PX:(r + 1) * CELL_PX, c * CELL_PX:(c + 1) * CELL_PX]
        cell[...] = 255 - cell
    img = np.pad(img, 3 * CELL_PX, constant_values=255)
    return np.where(img > 127, white, black).astype(np.uint8)


@pytest.mark.parametrize("backend", BACKENDS)
def test_contract_corner_order_on_a_painted_tag(backend: Backend) -> None:
    (det,) = make_detector("tag36h11", backend).detect(painted(7))
    assert det.tag_id == 7 and det.corners.shape == (4, 2) and det.corners.dtype == np.float64
    (trx, try_), (tlx, tly), (blx, bly), (brx, bry) = det.corners
    # upright tag, image y down: TR right of TL, BL below TL, BR right of BL and below TR
    assert trx > tlx + 50 and abs(try_ - tly) < 1
    assert bly > tly + 50 and abs(blx - tlx) < 1
    assert brx > blx + 50 and bry > try_ + 50
    # the black square spans 8 cells starting after the 3-cell quiet zone; corners are pixel centres
    # on its outer edge: first black pixel centre - 0.5
    lo, hi = 3 * CELL_PX - 0.5, 11 * CELL_PX - 0.5
    np.testing.assert_allclose(det.corners, [[hi, lo], [lo, lo], [lo, hi], [hi, hi]], atol=0.3)


@pytest.mark.parametrize("backend", BACKENDS)
def test_rendered_ids_and_corners_match_projected_truth(scene, backend: Backend) -> None:
    s, r = scene
    cam = s.robot.cameras[0]
    det = make_detector(s.tags.family, backend)
    tmap = TagMap.from_scenario(s)
    t_wc = camera.mount_transform(cam)
    errors, found = [], 0
    for x, y, yaw in CASES:
        r.set_pose(1, (x, y, 0.0), yaw_quat(yaw))
        dets = det.detect(r.render(0, cam, se2_matrix(0, 0, 0)))
        for d in dets:
            owner = tmap.lookup(d.tag_id)
            assert owner is not None and owner.kind == "robot" and owner.target_id == 1, d.tag_id
            assert owner.face is not None
            uv = project(camera.intrinsics(cam), t_wc, world_corners(s, se2_matrix(x, y, yaw), owner.face))
            errors.append(d.corners - uv)
        found += len(dets)
    assert found >= len(CASES)
    err = np.concatenate(errors)
    assert float(np.median(np.linalg.norm(err, axis=1))) < 1.0
    assert np.all(np.abs(err.mean(axis=0)) < 0.25), f"corner bias {err.mean(axis=0)} px"
    assert float(np.max(np.linalg.norm(err, axis=1))) < 2.5


def test_backends_agree_on_a_landmark(scene) -> None:
    s, r = scene
    cam = s.robot.cameras[0]
    r.set_pose(1, (0.0, 0.0, -10.0), (0, 0, 0, 1))
    img = r.render(0, cam, se2_matrix(-1.5, 0.2, math.pi - 0.2))
    a = {d.tag_id: d for d in AprilTagDetector().detect(img)}
    b = {d.tag_id: d for d in ArucoDetector().detect(img)}
    assert set(a) == set(b) == {100}
    np.testing.assert_allclose(a[100].corners, b[100].corners, atol=0.6)


def test_tag_map_owners() -> None:
    s = scenario()
    tmap = TagMap.from_scenario(s)
    assert len(tmap) == 2 * 6 + 1
    for rid in s.robot_ids:
        for face, tid in zip(tags.Face, s.tag_ids(rid), strict=True):
            assert tmap.lookup(tid) == ("robot", rid, face)
    assert tmap.lookup(100) == ("landmark", 100, None)
    for unknown in (0, 21, 99, 586, 10_000):
        assert tmap.lookup(unknown) is None


@pytest.mark.parametrize("backend", BACKENDS)
def test_hamming_filter(backend: Backend) -> None:
    img = painted(7, flip_cell=(3, 4))  # one data bit wrong
    assert make_detector("tag36h11", backend, max_hamming=0).detect(img) == []
    (d,) = make_detector("tag36h11", backend, max_hamming=1).detect(img)
    assert (d.tag_id, d.hamming) == (7, 1)
    (clean,) = make_detector("tag36h11", backend, max_hamming=1).detect(painted(7))
    assert clean.hamming == 0


def test_margin_filter() -> None:
    low = painted(7, black=100, white=130)  # low contrast: a small decision margin
    (d,) = make_detector("tag36h11", "apriltag", min_margin=0.0).detect(low)
    assert d.tag_id == 7 and 0.0 < d.margin < 20.0
    assert make_detector("tag36h11", "apriltag", min_margin=20.0).detect(low) == []
    (hi,) = make_detector("tag36h11", "apriltag", min_margin=20.0).detect(painted(7))
    assert hi.margin > 20.0
    # aruco has no margin: it never fails that gate
    (a,) = make_detector("tag36h11", "aruco", min_margin=1e9).detect(painted(7))
    assert a.margin == math.inf


@pytest.mark.parametrize("backend", BACKENDS)
def test_tag16h5(backend: Backend) -> None:
    (d,) = make_detector("tag16h5", backend).detect(painted(3, family="tag16h5"))
    assert d.tag_id == 3 and isinstance(d, TagDetection)


def test_bad_arguments() -> None:
    with pytest.raises(ValueError, match="backend"):
        make_detector("tag36h11", "nope")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="family"):
        make_detector("tag25h9")


def test_closing_a_tag16h5_detector_does_not_corrupt_the_heap() -> None:
    """pupil_apriltags frees families before the detector; in a process that also runs
    pybullet that aborts with a corrupted heap.  AprilTagDetector frees them in order."""
    code = (
        "import gc, numpy as np\n"
        "from tagswarm.agents.detect import AprilTagDetector\n"
        "from tagswarm.protocol.scenario import Scenario\n"
        "from tagswarm.world.render import Renderer\n"
        "r = Renderer(Scenario())\n"
        "for _ in range(3):\n"
        "    d = AprilTagDetector('tag16h5')\n"
        "    d.detect(np.full((60, 80), 255, np.uint8))\n"
        "    del d\n"
        "    gc.collect()\n"
        "r.close()\n"
        "print('clean')\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                         cwd=Path(__file__).resolve().parents[3])
    assert res.returncode == 0 and "clean" in res.stdout, res.stderr[-2000:]
    d = AprilTagDetector("tag16h5")
    d.close()
    d.close()  # idempotent
    with pytest.raises(RuntimeError, match="closed"):
        d.detect(painted(3, family="tag16h5"))
