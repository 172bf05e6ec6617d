"""Tag families, the robot tag-ID scheme and the geometry of a tag cube.

This is part of the contract: the world paints the tags exactly where these
functions say they are, and agents use the same functions to estimate poses.

Frames (REP-103): the cube frame has its origin at the cube centre and its axes
aligned with the robot body (x forward, y left, z up).  Each face carries one
tag, upright when seen from outside (for the side faces "up" is +z; for the top
and bottom faces "up" is +x, i.e. towards the robot's front).
"""

from __future__ import annotations

from enum import IntEnum
from typing import Final

import numpy as np
from numpy.typing import NDArray


class Face(IntEnum):
    """Cube faces in the paper's order; ``robot k`` carries ``base + stride*k + face``."""

    FRONT = 0
    BACK = 1
    LEFT = 2
    RIGHT = 3
    TOP = 4
    BOTTOM = 5


#: Number of IDs in each supported family and the width in cells of the black
#: square (data bits plus the one-cell black border).
FAMILIES: Final[dict[str, tuple[int, int]]] = {
    "tag36h11": (587, 8),
    "tag16h5": (30, 6),
}

# normal, up, right (viewer's right when facing the face from outside), cube frame
_FACE_AXES: Final[dict[Face, tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]]] = {
    Face.FRONT: ((1, 0, 0), (0, 0, 1), (0, 1, 0)),
    Face.BACK: ((-1, 0, 0), (0, 0, 1), (0, -1, 0)),
    Face.LEFT: ((0, 1, 0), (0, 0, 1), (-1, 0, 0)),
    Face.RIGHT: ((0, -1, 0), (0, 0, 1), (1, 0, 0)),
    Face.TOP: ((0, 0, 1), (1, 0, 0), (0, -1, 0)),
    Face.BOTTOM: ((0, 0, -1), (1, 0, 0), (0, 1, 0)),
}


def family_size(family: str) -> int:
    """Number of valid IDs in ``family``; raises ``KeyError`` for unknown families."""
    return FAMILIES[family][0]


def black_cells(family: str) -> int:
    """Width of the tag's black square in cells (data + black border)."""
    return FAMILIES[family][1]


def min_face_for_tag(family: str, tag_size_m: float) -> float:
    """Smallest square (m) that holds a tag of black-square size ``tag_size_m`` plus
    the one-cell white quiet zone the detector needs around it."""
    n = black_cells(family)
    return tag_size_m * (n + 2) / n


def robot_tag_ids(robot_id: int, id_base: int, id_stride: int) -> tuple[int, ...]:
    """The six tag IDs of robot ``robot_id`` in :class:`Face` order."""
    first = id_base + id_stride * robot_id
    return tuple(first + f for f in range(6))


def face_axes(face: Face) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Unit vectors (normal, up, right) of ``face`` in the cube frame, each shape (3,)."""
    n, u, r = _FACE_AXES[face]
    return np.array(n, float), np.array(u, float), np.array(r, float)


def square_corners(
    center: NDArray[np.float64],
    up: NDArray[np.float64],
    right: NDArray[np.float64],
    size_m: float,
) -> NDArray[np.float64]:
    """Corners of an upright square, shape (4, 3), in the detector's corner order.

    For the tags we paint (``cv2.aruco.generateImageMarker`` images, upright),
    AprilTag 3 reports the corners top-right, top-left, bottom-left,
    bottom-right as seen from the front of the tag (counter-clockwise in the
    image); tests/unit/agents/test_detect.py pins this.
    """
    h = size_m / 2.0
    return np.stack(
        [
            center + right * h + up * h,
            center - right * h + up * h,
            center - right * h - up * h,
            center + right * h - up * h,
        ]
    )


def cube_tag_corners(face: Face, edge_m: float, tag_size_m: float) -> NDArray[np.float64]:
    """3D corners (4, 3) in metres, cube frame, of the tag's black square on ``face``,
    in the detector's corner order (see :func:`square_corners`)."""
    n, u, r = face_axes(face)
    return square_corners(n * (edge_m / 2.0), u, r, tag_size_m)


def cube_face_corners(face: Face, edge_m: float) -> NDArray[np.float64]:
    """3D corners (4, 3), cube frame, of the whole face, in the same order."""
    n, u, r = face_axes(face)
    return square_corners(n * (edge_m / 2.0), u, r, edge_m)
