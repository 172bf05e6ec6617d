"""The scenario's camera sections: each camera's mount and lens (:class:`Camera`, a
``[[robot.cameras]]`` table), the ``[camera]`` section's sensor effects and calibration
error (:class:`CameraSensor`, :class:`CalibrationError`), its presets, and :func:`lens_of`
(docs/camera.md).

Mounts are in the robot's base frame (x forward, y left, z up), metres and degrees.
:mod:`tagswarm.protocol.scenario_schema` re-exports every name of this module.
"""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from tagswarm.protocol.scenario_spec import NonNeg, Pos, Spec

LensName = Literal["auto", "pinhole", "brown_conrady", "fisheye"]
#: "auto" lenses from this horizontal field of view on are fisheyes (a pinhole cannot reach 180 deg)
FISHEYE_MIN_HFOV_DEG = 120.0
#: distortion coefficients each lens model takes (OpenCV's order)
LENS_COEFFICIENTS: dict[str, int] = {"pinhole": 0, "brown_conrady": 5, "fisheye": 4}


class Camera(Spec, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """An onboard pinhole camera.  Mount: optical centre at (x, y, z) in the base
    frame, looking along body yaw ``yaw_deg`` (left positive) tilted up by
    ``pitch_deg``; the image is upright."""

    name: str = "front"
    width: Annotated[int, msgspec.Meta(ge=16, le=4096)] = 320
    height: Annotated[int, msgspec.Meta(ge=16, le=4096)] = 240
    hfov_deg: Annotated[float, msgspec.Meta(gt=1, lt=170)] = 60.0
    rate_hz: Pos = 10.0
    x_m: float = 0.15
    y_m: float = 0.0
    # on a mast above the tag cubes, looking down: from the tags' own height a single
    # tag's two pose solutions differ by a pure yaw flip that no ground prior can
    # resolve; from above, the planar (upright, on the floor) model tells them apart
    z_m: float = 0.6
    yaw_deg: float = 0.0
    pitch_deg: float = -15.0
    near_m: Pos = 0.05
    far_m: Pos = 15.0
    # the lens (docs/camera.md): "auto" takes the [camera] preset's (ideal: pinhole; realistic:
    # Brown-Conrady below FISHEYE_MIN_HFOV_DEG, equidistant fisheye from there on)
    lens: LensName = "auto"
    # brown_conrady: (k1, k2, p1, p2, k3); fisheye: (k1, k2, k3, k4); empty = all zero
    distortion: tuple[float, ...] = ()


class CalibrationError(Spec, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """How wrong the calibration handed to the agent is (1 sigma of a Gaussian each, drawn once
    per robot and camera from the scenario seed; the world renders with the true one).
    ``focal_rel``: relative error of fx and fy (independent); ``center_px``: of cx and cy;
    ``distortion_rel``: relative error of each distortion coefficient; ``extrinsic_deg``
    and ``extrinsic_m``: rotation (about a random axis) and translation of the mount."""

    focal_rel: NonNeg = 0.0
    center_px: NonNeg = 0.0
    distortion_rel: NonNeg = 0.0
    extrinsic_deg: NonNeg = 0.0
    extrinsic_m: NonNeg = 0.0


class CameraSensor(Spec, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """The ``[camera]`` section: sensor effects of every camera and the calibration error
    (docs/camera.md).  ``preset`` fills every field left unset: ``ideal`` (the default) is a
    perfect pinhole with no effects, byte-identical to the renders before lenses existed;
    ``realistic`` a global-shutter machine-vision camera with a wide lens
    (:data:`REALISTIC`).  Effects, applied in this order to the 8-bit image: motion blur
    of the robot's own motion during ``exposure_ms``, the lens, vignetting (relative
    brightness lost in the image corners, cos^4-like), contrast (gain about mid-grey 128) and
    ``brightness_dn`` (offset), shot noise (Poisson in its Gaussian limit, ``electrons_per_dn`` electrons per
    digital number; 0 = none) and Gaussian ``read_noise_dn`` (DN, 1 sigma), then rounding and
    clipping.  Every random draw is seeded from the scenario seed, robot, camera and tick."""

    preset: Literal["ideal", "realistic"] = "ideal"
    exposure_ms: NonNeg | None = None
    read_noise_dn: NonNeg | None = None
    electrons_per_dn: NonNeg | None = None
    brightness_dn: Annotated[float, msgspec.Meta(ge=-255, le=255)] | None = None
    contrast: Annotated[float, msgspec.Meta(gt=0, le=10)] | None = None
    vignetting: Annotated[float, msgspec.Meta(ge=0, lt=1)] | None = None
    calibration_error: CalibrationError = CalibrationError()

    def resolved(self) -> CameraSensor:
        """This section with every unset field taken from its preset."""
        base = IDEAL if self.preset == "ideal" else REALISTIC
        fields = {f: getattr(self, f) for f in self.__struct_fields__}
        return CameraSensor(**{f: (getattr(base, f) if v is None else v) for f, v in fields.items()})

    @property
    def has_effects(self) -> bool:
        """Whether any pixel effect is on (after :meth:`resolved`)."""
        r = self.resolved()
        return bool(r.exposure_ms or r.read_noise_dn or r.electrons_per_dn or r.brightness_dn
                    or r.vignetting or r.contrast != 1.0)


#: the ``ideal`` preset: no effect at all
IDEAL = CameraSensor(preset="ideal", exposure_ms=0.0, read_noise_dn=0.0, electrons_per_dn=0.0, brightness_dn=0.0,
                     contrast=1.0, vignetting=0.0)
#: the ``realistic`` preset: a global-shutter CMOS machine-vision camera (Sony Pregius class) behind a
#: wide M12 lens, indoors with some analogue gain; sources and reasoning in docs/camera.md
REALISTIC = CameraSensor(preset="realistic", exposure_ms=4.0, read_noise_dn=1.0, electrons_per_dn=20.0,
                         brightness_dn=0.0, contrast=0.9, vignetting=0.3)
#: the realistic preset's lenses: Brown-Conrady (k1, k2, p1, p2, k3) of a ~90 deg M12 lens, and the
#: equidistant fisheye (k1..k4) of a ~180 deg class lens (docs/camera.md)
REALISTIC_BROWN_CONRADY = (-0.28, 0.09, 0.0005, -0.0003, -0.012)
REALISTIC_FISHEYE = (-0.02, 0.004, -0.002, 0.0003)


def lens_of(cam: Camera, preset: str) -> tuple[str, tuple[float, ...]]:
    """The lens model of ``cam`` and its full coefficient tuple ("auto" resolved by ``preset``)."""
    name = cam.lens
    if name == "auto":
        if preset == "ideal":
            return "pinhole", ()
        name = "fisheye" if cam.hfov_deg >= FISHEYE_MIN_HFOV_DEG else "brown_conrady"
        if not cam.distortion:
            return name, REALISTIC_FISHEYE if name == "fisheye" else REALISTIC_BROWN_CONRADY
    n = LENS_COEFFICIENTS[name]
    return name, tuple(cam.distortion) if cam.distortion else (0.0,) * n
