"""The ESKF's measurement update: the innovation and its chi-square gate, filterpy's Joseph-form update.

:func:`innovation` gives the normalised innovation squared (NIS) the gate tests
(:func:`~polins.fusion.items.gate_limit`) and the innovation and its covariance the update
log keeps; :func:`kalman_update` applies a measurement through filterpy: a scalar one with
``KalmanFilter.update_sequential`` (the gain without a matrix inverse), a vector one with
``filterpy.kalman.update``. Both are filterpy's Joseph form
``P = (I - K H) P (I - K H)^T + K R K^T``; their cost for the 22-state filter is stated in
docs/filter.md ("Cost").
"""

from __future__ import annotations

import numpy as np
from filterpy.kalman import KalmanFilter
from filterpy.kalman import update as kf_update
from numpy.typing import NDArray

from polins.fusion.measurement import Linearized

FloatArray = NDArray[np.float64]


def innovation(
    lin: Linearized, x: FloatArray, P: FloatArray
) -> tuple[float, tuple[float, ...], tuple[float, ...]]:
    """The NIS of ``lin`` at the error state ``x`` and covariance ``P``, the innovation
    ``nu = residual - H x`` and its covariance ``S = H P H^T + R`` (row-major)."""
    H = lin.H
    if lin.residual.shape[0] == 1:  # scalar innovation: dot products
        h = H[0]
        y1 = float(lin.residual[0]) - float(h @ x)
        s1 = float(h @ (P @ h)) + float(lin.R[0, 0])
        return y1 * y1 / s1, (y1,), (s1,)
    y = lin.residual - H @ x
    Sm = H @ (P @ H.T) + lin.R
    nis = float(y @ np.linalg.solve(Sm, y))
    return nis, tuple(y.tolist()), tuple(Sm.ravel().tolist())


def kalman_update(
    kf: KalmanFilter, x: FloatArray, P: FloatArray, lin: Linearized
) -> tuple[FloatArray, FloatArray]:
    """The Kalman update of ``(x, P)`` by ``lin`` in filterpy's Joseph form: a scalar
    measurement through ``KalmanFilter.update_sequential`` (``kf`` of the state's size
    lends its arrays), a vector one through ``filterpy.kalman.update``. Both give the same
    numbers for a scalar; ``x`` and ``P`` are not changed in place."""
    if lin.residual.shape[0] != 1:
        return kf_update(x, P, lin.residual, lin.R, lin.H)
    kf.x, kf.P = x[:, None].copy(), P  # filterpy's column state; updated in place
    kf.update_sequential(0, lin.residual, lin.R, lin.H)
    return kf.x[:, 0], kf.P


__all__ = ["innovation", "kalman_update"]
