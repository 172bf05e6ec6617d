"""Tag detection in camera frames and the map from tag IDs to what carries them (pure code).

Pixel convention: every corner this module returns is in OpenCV's convention (the
centre of pixel (u, v) is at integer coordinates (u, v)), i.e. the AprilTag 3
library's corners minus 0.5 px (docs/architecture.md, section 4).  Corner order is the
contract of :func:`tagswarm.protocol.tags.square_corners`: top-right, top-left,
bottom-left, bottom-right of the upright tag (counter-clockwise in the image).

Two backends:

* :class:`AprilTagDetector` (``pupil_apriltags``, AprilTag 3) -- the default: the
  fastest here with ``quad_decimate=1, nthreads=1`` (~0.9 ms at 320x240, ~2.4 ms at
  640x480 on paper-arena frames, bench/detect.py) and it decodes the smallest tags.
* :class:`ArucoDetector` (``cv2.aruco`` with ``CORNER_REFINE_APRILTAG``) -- a second
  opinion; ~1.5x slower and it loses the smallest tags.  It reports no decision
  margin (treated as passing) and no Hamming distance, so the distance is measured
  here by sampling the decoded cells.  Measured: with AprilTag corner refinement
  its corners carry AprilTag's +0.5 px offset too, and are shifted like them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final, Literal, NamedTuple, Protocol

import cv2
import numpy as np
from numpy.typing import NDArray
from pupil_apriltags import Detector as _PupilDetector

from tagswarm.protocol import tags
from tagswarm.protocol.scenario import Scenario

TargetKind = Literal["robot", "landmark"]

#: AprilTag 3 puts pixel centres at +0.5 relative to OpenCV's convention.
APRILTAG_TO_OPENCV_PX: Final = -0.5

_ARUCO_DICTS: Final[dict[str, int]] = {
    "tag36h11": cv2.aruco.DICT_APRILTAG_36h11,
    "tag16h5": cv2.aruco.DICT_APRILTAG_16h5,
}
# cv2.aruco reports TL, TR, BR, BL (clockwise from the tag's top-left); the contract is TR, TL, BL, BR.
_ARUCO_TO_CONTRACT: Final = np.array([1, 0, 3, 2])


@dataclass(frozen=True, slots=True)
class TagDetection:
    """One decoded tag in one image.

    ``corners``: (4, 2) float64 pixels, OpenCV convention, order TR, TL, BL, BR of
    the upright tag.  ``hamming``: corrected bit errors.  ``margin``: AprilTag's
    decision margin (``inf`` when the backend has none).
    """

    tag_id: int
    corners: NDArray[np.float64]
    hamming: int
    margin: float


class Detector(Protocol):
    """Anything that finds tags in a grayscale frame."""

    family: str

    def detect(self, gray: NDArray[np.uint8]) -> list[TagDetection]:
        """Tags in ``gray`` ((H, W) uint8), filtered by the detector's quality gates."""
        ...


class AprilTagDetector:
    """AprilTag 3 (``pupil_apriltags``); keeps detections with ``hamming <= max_hamming``
    and ``decision_margin >= min_margin``.

    The library corrects up to 2 bit errors; ``max_hamming=0`` (default) keeps only
    exact codes, which makes a false ID practically impossible.
    """

    def __init__(self, family: str = "tag36h11", *, max_hamming: int = 0, min_margin: float = 20.0,
                 quad_decimate: float = 1.0, nthreads: int = 1) -> None:
        if family not in _ARUCO_DICTS:
            raise ValueError(f"unsupported tag family {family!r}")
        self.family = family
        self.max_hamming = max_hamming
        self.min_margin = min_margin
        self._det = _PupilDetector(families=family, quad_decimate=quad_decimate, nthreads=nthreads)

    def close(self) -> None:
        """Free the C detector (also done on garbage collection).

        pupil_apriltags 1.0.4 frees the tag families before the detector, whose
        destructor then writes into the freed families: heap corruption, seen as a
        ``malloc(): mismatching next->prev_size`` abort (reliably with tag16h5 in a
        process that also runs pybullet).  Free them in the right order and disarm
        pupil's own destructor.
        """
        det = getattr(self, "_det", None)
        ptr = getattr(det, "tag_detector_ptr", None)
        if det is None or ptr is None:
            return
        lib = det.libc
        lib.apriltag_detector_destroy.restype = None
        lib.apriltag_detector_destroy(ptr)
        for name, fam in det.tag_families.items():
            destroy = getattr(lib, f"{name}_destroy")
            destroy.restype = None
            destroy(fam)
        det.tag_families = {}
        det.tag_detector_ptr = None

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # at interpreter exit ctypes may already be torn down
            pass

    def detect(self, gray: NDArray[np.uint8]) -> list[TagDetection]:
        """Detections in ``gray`` ((H, W) uint8), corners in OpenCV's pixel convention."""
        if self._det.tag_detector_ptr is None:
            raise RuntimeError("detector is closed")
        out = []
        for d in self._det.detect(gray):
            if d.hamming <= self.max_hamming and d.decision_margin >= self.min_margin:
                out.append(TagDetection(int(d.tag_id), d.corners + APRILTAG_TO_OPENCV_PX, int(d.hamming),
                                        float(d.decision_margin)))
        return out


class ArucoDetector:
    """OpenCV's aruco detector on the AprilTag dictionaries with AprilTag corner refinement.

    ``max_hamming`` also bounds aruco's own error correction.  The reported
    ``hamming`` is measured by sampling the tag's cells through the detected
    corners; ``margin`` is ``inf`` (aruco has none, so ``min_margin`` never rejects).
    """

    def __init__(self, family: str = "tag36h11", *, max_hamming: int = 0, min_margin: float = 20.0) -> None:
        if family not in _ARUCO_DICTS:
            raise ValueError(f"unsupported tag family {family!r}")
        self.family = family
        self.max_hamming = max_hamming
        self.min_margin = min_margin
        self._dict = cv2.aruco.getPredefinedDictionary(_ARUCO_DICTS[family])
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_APRILTAG
        params.errorCorrectionRate = min(1.0, max_hamming / max(1, self._dict.maxCorrectionBits))
        self._det = cv2.aruco.ArucoDetector(self._dict, params)
        self._cells = tags.black_cells(family)
        self._cell_px = 6
        side = self._cells * self._cell_px
        self._dst = np.array([[side, 0], [0, 0], [0, side], [side, side]], np.float32)  # TR, TL, BL, BR

    def _hamming(self, gray: NDArray[np.uint8], corners: NDArray[np.float64], tag_id: int) -> int:
        """Bit errors of the tag seen at ``corners`` (contract order) against ``tag_id``."""
        side = self._cells * self._cell_px
        # corners are pixel centres; the warp maps the outer edges of the black square to the patch edges
        h = cv2.getPerspectiveTransform(corners.astype(np.float32) + 0.5, self._dst)
        patch = cv2.warpPerspective(gray, h, (side, side), flags=cv2.INTER_LINEAR)
        n, c = self._cells, self._cell_px
        m = c // 4  # sample the middle half of each cell: edges blur into neighbours
        cells = patch.reshape(n, c, n, c)[:, m : c - m, :, m : c - m].mean(axis=(1, 3))
        thr = 0.5 * (float(cells.min()) + float(cells.max()))
        bits = (cells[1:-1, 1:-1] > thr).astype(np.uint8)
        return int(self._dict.getDistanceToId(bits, tag_id, False))

    def detect(self, gray: NDArray[np.uint8]) -> list[TagDetection]:
        """Detections in ``gray`` ((H, W) uint8), corners in OpenCV's pixel convention."""
        corners, ids, _ = self._det.detectMarkers(gray)
        if ids is None:
            return []
        out = []
        for c, i in zip(corners, ids.ravel(), strict=True):
            # measured: with CORNER_REFINE_APRILTAG aruco's corners carry AprilTag's +0.5 px offset too
            cc = np.asarray(c, np.float64).reshape(4, 2)[_ARUCO_TO_CONTRACT] + APRILTAG_TO_OPENCV_PX
            ham = self._hamming(gray, cc, int(i))
            if ham <= self.max_hamming:
                out.append(TagDetection(int(i), cc, ham, float("inf")))
        return out


def make_detector(family: str, backend: Literal["apriltag", "aruco"] = "apriltag", max_hamming: int = 0,
                  min_margin: float = 20.0) -> Detector:
    """A detector for ``family`` ("tag36h11" or "tag16h5") on ``backend``."""
    if backend == "apriltag":
        return AprilTagDetector(family, max_hamming=max_hamming, min_margin=min_margin)
    if backend == "aruco":
        return ArucoDetector(family, max_hamming=max_hamming, min_margin=min_margin)
    raise ValueError(f"unknown detector backend {backend!r}")


class TagOwner(NamedTuple):
    """What carries a tag: ``("robot", robot_id, face)`` or ``("landmark", landmark_id, None)``."""

    kind: TargetKind
    target_id: int
    face: tags.Face | None


class TagMap:
    """Tag ID -> owner for one scenario's robots and landmarks."""

    def __init__(self, owners: dict[int, TagOwner]) -> None:
        self._owners = dict(owners)

    @classmethod
    def from_scenario(cls, scenario: Scenario) -> TagMap:
        """Every robot's six cube tags and every landmark tag of ``scenario``.

        A landmark's ``target_id`` is its tag ID (landmarks are named by their tag).
        """
        owners: dict[int, TagOwner] = {}
        for rid in scenario.robot_ids:
            for face, tid in zip(tags.Face, scenario.tag_ids(rid), strict=True):
                owners[tid] = TagOwner("robot", rid, face)
        for lm in scenario.landmarks:
            owners[lm.id] = TagOwner("landmark", lm.id, None)
        return cls(owners)

    def lookup(self, tag_id: int) -> TagOwner | None:
        """Owner of ``tag_id``, or None for an ID nothing in the scenario carries."""
        return self._owners.get(tag_id)

    def __len__(self) -> int:
        return len(self._owners)
