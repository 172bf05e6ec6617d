"""Mesh and texture files for tag cubes and landmark tags.

pybullet textures a mesh only through the OBJ's own ``mtllib``/``map_Kd`` (the
EGL plugin ignores ``changeVisualShape(textureUniqueId=...)``) and a textured
``GEOM_BOX`` does not put one image per face, so each cube is an OBJ with 24
vertices whose faces map into a 3 x 2 texture atlas (docs/architecture.md, section 5).
OBJ texture v = 0 is the image's bottom row; pybullet does not flip.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from tagswarm.protocol import tags

_ARUCO_DICT = {
    "tag36h11": cv2.aruco.DICT_APRILTAG_36h11,
    "tag16h5": cv2.aruco.DICT_APRILTAG_16h5,
}
#: Pixels per tag cell in the textures: enough that texture sampling never
#: blurs a bit at the distances a camera can still decode.
CELL_PX = 12


def tag_image(family: str, tag_id: int, black_px: int) -> NDArray[np.uint8]:
    """The tag's black square (data bits + black border), (black_px, black_px) uint8,
    upright as the AprilTag library expects it."""
    dictionary = cv2.aruco.getPredefinedDictionary(_ARUCO_DICT[family])
    return np.asarray(cv2.aruco.generateImageMarker(dictionary, tag_id, black_px, borderBits=1), np.uint8)


def face_image(family: str, tag_id: int | None, face_m: float, tag_m: float) -> NDArray[np.uint8]:
    """One square face texture, white with the tag centred; the black square covers
    ``tag_m / face_m`` of the face width.  ``tag_id=None`` gives a blank face."""
    n = tags.black_cells(family)
    black_px = n * CELL_PX
    face_px = round(black_px * face_m / tag_m)
    img = np.full((face_px, face_px), 255, np.uint8)
    if tag_id is not None:
        off = (face_px - black_px) // 2
        img[off : off + black_px, off : off + black_px] = tag_image(family, tag_id, black_px)
    return img


def _atlas(faces: list[NDArray[np.uint8]]) -> NDArray[np.uint8]:
    """Six equal square images into a 3 x 2 atlas, row-major from the top-left."""
    s = faces[0].shape[0]
    atlas = np.full((2 * s, 3 * s), 255, np.uint8)
    for i, img in enumerate(faces):
        r, c = divmod(i, 3)
        atlas[r * s : (r + 1) * s, c * s : (c + 1) * s] = img
    return atlas


def _write_obj(
    folder: Path,
    stem: str,
    face_quads: list[NDArray[np.float64]],
    atlas: NDArray[np.uint8],
) -> Path:
    """Write ``stem.obj/.mtl/.png``: quad i (corners TR, TL, BL, BR as seen from
    outside, see :func:`tagswarm.protocol.tags.square_corners`) gets atlas cell i."""
    folder.mkdir(parents=True, exist_ok=True)
    png, mtl, obj = folder / f"{stem}.png", folder / f"{stem}.mtl", folder / f"{stem}.obj"
    cv2.imwrite(str(png), atlas)
    mtl.write_text(f"newmtl tag\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nmap_Kd {png.name}\n")
    lines = [f"mtllib {mtl.name}", "o tagmesh"]
    vts: list[str] = []
    fs: list[str] = []
    for i, quad in enumerate(face_quads):
        r, c = divmod(i, 3)
        u0, u1 = c / 3.0, (c + 1) / 3.0
        v1, v0 = 1.0 - r / 2.0, 1.0 - (r + 1) / 2.0  # v=0 is the image bottom
        for p in quad:
            lines.append(f"v {p[0]:.6f} {p[1]:.6f} {p[2]:.6f}")
        vts += [f"vt {u1:.6f} {v1:.6f}", f"vt {u0:.6f} {v1:.6f}", f"vt {u0:.6f} {v0:.6f}", f"vt {u1:.6f} {v0:.6f}"]
        b = 4 * i + 1
        # TR, TL, BL, BR is counter-clockwise seen from outside: two triangles
        fs += [f"f {b}/{b} {b + 1}/{b + 1} {b + 2}/{b + 2}", f"f {b}/{b} {b + 2}/{b + 2} {b + 3}/{b + 3}"]
    lines += [*vts, "usemtl tag", "s off", *fs]
    obj.write_text("\n".join(lines) + "\n")
    return obj


def cube_mesh(folder: Path, family: str, ids: tuple[int, ...], edge_m: float, tag_m: float) -> Path:
    """OBJ of a tag cube (cube frame, see :mod:`tagswarm.protocol.tags`) carrying ``ids`` in
    :class:`~tagswarm.protocol.tags.Face` order; returns the OBJ path."""
    faces = [face_image(family, tid, edge_m, tag_m) for tid in ids]
    quads = [tags.cube_face_corners(f, edge_m) for f in tags.Face]
    return _write_obj(folder, f"cube_{family}_{'_'.join(map(str, ids))}_{edge_m:g}_{tag_m:g}", quads, _atlas(faces))


def landmark_mesh(folder: Path, family: str, tag_id: int, tag_m: float, thickness_m: float = 0.01) -> Path:
    """OBJ of a thin plate in a frame whose +x is the tag's outward normal and +z up:
    the tag is on the +x face, the other faces are white."""
    face_m = tags.min_face_for_tag(family, tag_m)
    blank = face_image(family, None, face_m, tag_m)
    faces = [face_image(family, tag_id, face_m, tag_m)] + [blank] * 5
    quads = []
    half = np.array([thickness_m / 2, face_m / 2, face_m / 2])
    for f in tags.Face:
        n, u, r = tags.face_axes(f)
        size_u, size_r = abs(u @ half) * 2, abs(r @ half) * 2
        c = n * abs(n @ half)
        quads.append(np.stack([c + r * size_r / 2 + u * size_u / 2, c - r * size_r / 2 + u * size_u / 2,
                               c - r * size_r / 2 - u * size_u / 2, c + r * size_r / 2 - u * size_u / 2]))
    return _write_obj(folder, f"landmark_{family}_{tag_id}_{tag_m:g}", quads, _atlas(faces))
