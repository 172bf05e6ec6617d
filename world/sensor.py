"""Sensor effects on a rendered frame: vignetting, contrast/brightness, shot and read noise
(pure numpy/OpenCV; docs/camera.md; motion blur is :mod:`tagswarm.world.blur`).

Intensities are 8-bit digital numbers (DN): the lens image is 8-bit, a motion blur's
average is float32, and :func:`develop` works in float32 until it rounds and clips.
Randomness comes only from (scenario seed, robot, camera, tick): :func:`frame_key` picks a
frame's place in its camera's :class:`NoiseBank`, so a lockstep run repeats its images byte
for byte whatever else draws random numbers.  Images are (H, W) in the camera's output pixels.
"""

from __future__ import annotations

import functools
import math
import operator
import zlib
from typing import Any, Final

import cv2
import numpy as np
from numpy.typing import NDArray

from tagswarm.protocol.geometry import Mat
from tagswarm.protocol.scenario import CameraSensor

#: a camera's noise bank holds this many frames' worth of normal samples (see NoiseBank)
BANK_FRAMES: Final = 8
_BANK_STREAM: Final = 0xBA4C
F32 = NDArray[np.float32]


_MASK64: Final = (1 << 64) - 1


def _mix64(x: int) -> int:
    """SplitMix64's finaliser: a bijection of 64-bit integers whose output bits each depend on every input bit."""
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & _MASK64
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & _MASK64
    return x ^ (x >> 31)


def frame_key(seed: int, robot_id: int, camera: str, step: int) -> int:
    """A uniform 64-bit key of one frame: a function of (seed, robot, camera, tick) only.  It picks
    the frame's noise in its :class:`NoiseBank`; a numpy generator per frame did the same at ~0.1 ms
    a frame right after a render (measured: 15 % of a fisheye's camera model)."""
    x = 0
    for v in (seed, robot_id, zlib.crc32(camera.encode()), step):
        x = _mix64(((x ^ (operator.index(v) & _MASK64)) + 0x9E3779B97F4A7C15) & _MASK64)
    return x


def vignetting_gain(width: int, height: int, K: Mat, strength: float) -> F32:
    """Relative brightness (H, W): 1 at the principal point, ``1 - strength`` in the farthest image
    corner, quadratic in the radius between (the cos^4 fall-off's leading term)."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32))
    cx, cy = float(K[0, 2]), float(K[1, 2])
    r2 = (u - cx) ** 2 + (v - cy) ** 2
    corner2 = max((x - cx) ** 2 + (y - cy) ** 2 for x in (0, width - 1) for y in (0, height - 1))
    return np.asarray(1.0 - strength * r2 / corner2, np.float32)


def tone(cfg: CameraSensor, gain: F32 | None, shape: tuple[int, int]) -> tuple[F32, float]:
    """(scale (H, W), offset) with ``scale * light + offset`` the frame before noise: vignetting
    ``gain``, contrast about mid-grey 128 and brightness, in one multiply-add."""
    contrast = 1.0 if cfg.contrast is None else cfg.contrast
    scale = np.full(shape, contrast, np.float32) if gain is None else np.asarray(gain * np.float32(contrast),
                                                                                  np.float32)
    return scale, 128.0 * (1.0 - contrast) + (cfg.brightness_dn or 0.0)


class NoiseBank:
    """Standard normal samples for one camera's frames, :data:`BANK_FRAMES` frames' worth drawn once
    (seeded): a frame takes one frame's worth at an offset given by its :func:`frame_key`, because
    drawing a frame's ~10^5 fresh normals costs about as much as rendering it.  Each pixel's
    noise is still N(0, 1) and independent of its neighbours; two frames' noise fields are the
    same sequence at offsets a random distance apart, which no detector can exploit."""

    def __init__(self, seed: int, camera: str, size: int) -> None:
        self.samples = np.random.default_rng([seed, zlib.crc32(camera.encode()), _BANK_STREAM]).standard_normal(
            size * BANK_FRAMES, dtype=np.float32)

    def draw(self, key: int, shape: tuple[int, ...]) -> F32:
        """A frame's noise (``shape``) at the offset chosen by its 64-bit ``key`` (:func:`frame_key`)."""
        n = math.prod(shape)
        off = (int(key) & _MASK64) * (len(self.samples) - n + 1) >> 64
        return self.samples[off:off + n].reshape(shape)


_IN_RANGE: dict[int, tuple[F32, float, bool]] = {}


def _stays_in_range(scale: F32, offset: float) -> bool:
    """Whether ``light * scale + offset`` stays within 0..255 for every light in 0..255 (a blur's
    average of 8-bit samples included), so clipping it is a no-op (cached per scale image)."""
    hit = _IN_RANGE.get(id(scale))
    if hit is not None and hit[0] is scale and hit[1] == offset:
        return hit[2]
    lo, hi = float(scale.min()), float(scale.max())
    # float32 rounding of the product and the sum stays far inside the half-DN margin asked for
    ok = lo >= 0.0 and offset >= 0.0 and 255.0 * hi + offset <= 254.5
    if len(_IN_RANGE) > 64:
        _IN_RANGE.clear()
    _IN_RANGE[id(scale)] = (scale, offset, ok)  # the image is kept: its id cannot be reused meanwhile
    return ok


@functools.lru_cache(maxsize=16)
def _noise_sigma(electrons_per_dn: float, read2: float) -> F32:
    """The noise sigma (DN) of each whole DN of signal (256,): shot noise and read noise (variance ``read2``)."""
    e = electrons_per_dn
    return np.sqrt(np.arange(256, dtype=np.float32) * np.float32(1.0 / e if e else 0.0) + np.float32(read2))


def develop(img: NDArray[Any], cfg: CameraSensor, gain: F32 | None = None, toned: tuple[F32, float] | None = None,
            bank: NoiseBank | None = None, key: int | None = None) -> NDArray[np.uint8]:
    """The 8-bit frame of a light image ``img`` (H, W, DN; float or 8-bit): vignetting ``gain``, contrast about
    mid-grey and brightness (or their precomputed :func:`tone`), shot noise (variance signal /
    ``electrons_per_dn``, DN^2) and read noise (Gaussian, DN), rounded and clipped.  ``cfg`` is
    a resolved ``[camera]`` section.  The noise is ``bank``'s at ``key`` (:func:`frame_key`)."""
    scale, offset = toned if toned is not None else tone(cfg, gain, img.shape)  # type: ignore[arg-type]
    out = np.asarray(cv2.multiply(img, scale, dtype=cv2.CV_32F), np.float32)  # type: ignore[call-overload]
    out += np.float32(offset)
    if not _stays_in_range(scale, offset):
        np.clip(out, 0.0, 255.0, out=out)
    read2 = float(cfg.read_noise_dn or 0.0) ** 2
    if cfg.electrons_per_dn or read2:
        # shot noise as its Gaussian limit (>= 20 electrons per DN is far beyond where Poisson differs),
        # one draw with read noise; sigma looked up per whole DN of the signal (cv2.LUT: ~3x numpy's gather)
        noise: F32 = np.asarray(cv2.LUT(out.astype(np.uint8), _noise_sigma(float(cfg.electrons_per_dn or 0.0), read2)),
                                np.float32)
        if bank is None or key is None:  # offset 0 for every frame would repeat one noise field
            raise ValueError("develop: noise needs the camera's noise bank and the frame's key (frame_key)")
        noise *= bank.draw(key, out.shape)
        out += noise
    # rounding to nearest (ties to even, as numpy's rint) and saturation to 0..255 in one pass
    return np.asarray(cv2.add(out, 0.0, dtype=cv2.CV_8U), np.uint8)  # type: ignore[call-overload]
