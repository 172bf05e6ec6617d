"""A relative-pose factor whose measurement goes through a vector variable of the graph (pure
code, GTSAM): the shape the calibrated odometry (:mod:`tagswarm.server.odomcal`) and the views'
range bias (:mod:`tagswarm.server.rangebias`) share.

Between keyframes ``ka`` and ``kb`` (``Pose2``) the error is ``Logmap(meas(x)^-1 * (xa^-1 * xb))``
with ``meas(x)`` the measured relative pose given the value ``x`` of variable ``kx`` (a
``Vector``); at a fixed ``x`` it is GTSAM's between-factor.  The Jacobians in ``xa`` and ``xb``
are analytic; the one in ``x`` is a forward difference of ``meas`` (``step``, in ``x``'s units),
which is cheap: ``meas`` is a few pose compositions.
"""

from __future__ import annotations

from collections.abc import Callable

import gtsam
import numpy as np
from numpy.typing import NDArray


def between_through(ka: int, kb: int, kx: int, meas: Callable[[NDArray[np.float64]], gtsam.Pose2],
                    noise: gtsam.noiseModel.Base, step: float) -> gtsam.CustomFactor:
    """The factor between ``ka`` and ``kb`` measuring ``meas(x)`` (``x`` the value of ``kx``, shape
    (D,)), with ``noise`` in the measurement's tangent space (x_m, y_m, yaw_rad)."""

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jac: list[np.ndarray] | None) -> np.ndarray:
        xa, xb = values.atPose2(ka), values.atPose2(kb)
        x = np.asarray(values.atVector(kx), float)
        ha, hb = np.zeros((3, 3), order="F"), np.zeros((3, 3), order="F")
        pred = xa.between(xb, ha, hb)
        m = meas(x)
        hm, hp = np.zeros((3, 3), order="F"), np.zeros((3, 3), order="F")
        rel = m.between(pred, hm, hp)
        hl = np.zeros((3, 3), order="F")
        e = gtsam.Pose2.Logmap(rel, hl)
        if jac is not None:
            jx = np.empty((3, x.size))
            for i in range(x.size):
                xs = x.copy()
                xs[i] += step
                jx[:, i] = gtsam.Pose2.Logmap(m.between(meas(xs))) / step
            jac[0] = hl @ hp @ ha
            jac[1] = hl @ hp @ hb
            jac[2] = hl @ hm @ jx
        return np.asarray(e)

    return gtsam.CustomFactor(noise, gtsam.KeyVector([ka, kb, kx]), error)
