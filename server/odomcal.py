"""Per-robot odometry calibration in the pose graph (pure code, GTSAM).

A robot's wheels are not the nominal ones: each wheel's radius and the wheel base are off by
a fixed share (``c = (e_left, e_right, e_base)``).  Its odometry increments then err the same
way every time, an error that grows with the distance travelled and the angle turned and that
white per-increment noise cannot describe.  Here ``c`` is a variable of the graph (a
``Vector3`` per robot) and each odometry factor predicts the increment through it, so views
of the robot estimate ``c`` and the odometry between them is corrected.

An increment ``delta`` (x, y, yaw in the start frame) is read as one circular arc of length
``ds`` and angle ``dth``; the wheels' travels are ``ds -/+ dth b / 2``.  With ``c`` they become
``(1 + e_l)``, ``(1 + e_r)`` times that, on a base ``b (1 + e_b)``; the factor's measurement is
``delta`` moved by the change of that arc, so that at ``c = 0`` it is ``delta`` exactly.
"""

from __future__ import annotations

import math
from typing import Any

import gtsam
import numpy as np
from numpy.typing import NDArray

from tagswarm.protocol.geometry import Pose2
from tagswarm.server.noise import Cov, FusionParams
from tagswarm.server.through import between_through


def arc_of(delta: Pose2) -> tuple[float, float]:
    """(ds, dth): signed length (m) and angle (rad) of the circular arc through ``delta``."""
    dx, dy, dth = delta
    chord = math.hypot(dx, dy)
    if chord < 1e-12:
        return 0.0, dth
    sign = 1.0 if dx >= 0 else -1.0
    half = dth / 2.0
    ds = chord if abs(half) < 1e-9 else chord * half / math.sin(half)
    return sign * ds, dth


def arc_pose(ds: float, dth: float) -> gtsam.Pose2:
    """The end pose of an arc of length ``ds`` and angle ``dth`` from the origin."""
    if abs(dth) < 1e-9:
        return gtsam.Pose2(ds, ds * dth / 2.0, dth)
    r = ds / dth
    return gtsam.Pose2(r * math.sin(dth), r * (1.0 - math.cos(dth)), dth)


def corrected_arc(ds: float, dth: float, c: Any, base_m: float) -> tuple[float, float]:
    """The arc (ds, dth) the wheels really made when the odometry measured (ds, dth) with nominal
    wheels and the calibration error is ``c`` = (e_left, e_right, e_base)."""
    dl = (ds - dth * base_m / 2.0) * (1.0 + float(c[0]))
    dr = (ds + dth * base_m / 2.0) * (1.0 + float(c[1]))
    return (dl + dr) / 2.0, (dr - dl) / (base_m * (1.0 + float(c[2])))


def corrected(delta: Pose2, c: Any, base_m: float) -> gtsam.Pose2:
    """``delta`` corrected by the calibration ``c`` (``delta`` itself at c = 0)."""
    ds, dth = arc_of(delta)
    nominal = arc_pose(ds, dth)
    real = arc_pose(*corrected_arc(ds, dth, c, base_m))
    return gtsam.Pose2(*delta).compose(nominal.between(real))


def factor(ka: int, kb: int, kc: int, delta: Pose2, cov: Cov, base_m: float) -> gtsam.CustomFactor:
    """Odometry factor between keyframes ``ka`` and ``kb`` (increment ``delta``, (3, 3) covariance ``cov`` in
    its tangent space) through robot calibration ``kc``."""
    ds, dth = arc_of(delta)
    d0 = gtsam.Pose2(*delta)
    nominal = arc_pose(ds, dth)

    def meas(c: Any) -> gtsam.Pose2:
        return d0.compose(nominal.between(arc_pose(*corrected_arc(ds, dth, c, base_m))))

    return between_through(ka, kb, kc, meas, gtsam.noiseModel.Gaussian.Covariance(np.asarray(cov, float)), 1e-6)


def prior_cov(p: FusionParams) -> Cov:
    """(3, 3) covariance of a robot's calibration before anything is known: the nominal wheels'
    radii and base are good to ``odom_cal_sigma_radius`` and ``odom_cal_sigma_base`` (shares)."""
    return np.diag([p.odom_cal_sigma_radius**2, p.odom_cal_sigma_radius**2, p.odom_cal_sigma_base**2])


def summary(rid: int, cal: NDArray[np.float64], cov: Cov | None) -> str:
    """One log line: what the graph learnt of robot ``rid``'s wheels (shares in %, with 1-sigma)."""
    sig = np.sqrt(np.maximum(np.diag(cov), 0.0)) if cov is not None else np.full(3, np.nan)
    parts = [f"{name} {100 * float(cal[i]):+.2f} % (sigma {100 * float(sig[i]):.2f} %)"
             for i, name in enumerate(("left wheel radius", "right wheel radius", "wheel base"))]
    return f"robot {rid}'s odometry calibration: " + ", ".join(parts)


#: the odometry sigmas of ``[server]`` left unset, with the calibration: the wheels' own noise (sqrt(m)) and a
#: per-metre share for what the arc model leaves out (docs/benchmarks.md, "Odometry calibration in the graph")
CALIBRATED_WHEEL_SIGMA = 0.01
CALIBRATED_SCALE_SIGMA = 0.01
#: ... and without it: the biases folded into per-increment noise
PLAIN_SCALE_SIGMA = 0.02


def odometry_sigmas(calibration: bool, agent_wheel: float, wheel: float | None,
                    scale: float | None) -> tuple[float, float]:
    """(wheel, scale) sigmas of the fusion's odometry model from ``[server]``'s (None: unset)."""
    if calibration:
        return (CALIBRATED_WHEEL_SIGMA if wheel is None else wheel,
                CALIBRATED_SCALE_SIGMA if scale is None else scale)
    return agent_wheel if wheel is None else wheel, PLAIN_SCALE_SIGMA if scale is None else scale
