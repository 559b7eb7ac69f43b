"""Model error of the heading: the camera-fixed (instrumental) polarization part of its sigma.

A channel-gain or polarizer-angle residual of the calibration leaves a spurious
polarization fixed to the camera, ``dL_i = S0_i delta`` with ``delta = (delta_1, delta_2)``
a small constant (e.g. ``delta ~ 0.002`` for gains good to +-0.5 %). It is common to every
sky sector, so the jackknife of :mod:`polins.compass.sectors` does not see it, and it is
the same from image to image. Its effect on the estimate is linear: with the estimator's
Jacobian ``J`` (the joint ML's, epsilon included for ``"compensated"``; the sun angles only
for the eigen methods, whose first-order sensitivity is that of the same weighted
AoP fit) and the residual change ``dr_i = n_i . dL_i``::

    d theta = -(J^T J)^-1 J^T dr,     sigma_instr^2 = sigma_delta^2 (g_1^2 + g_2^2)

with ``g_j`` the yaw's change per unit ``delta_j`` (docs/measurement.md §12).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from polins.compass.jointml import ml_evaluate
from polins.compass.prediction import PixelData, doubled_prediction, image_plane_evector

__all__ = ["instrumental_sensitivity"]


def instrumental_sensitivity(
    data: PixelData, theta: NDArray, zenith: float | None, mat_cl: NDArray, with_epsilon: bool
) -> float:
    """Yaw change per unit camera-fixed polarization, ``sqrt(g_1^2 + g_2^2)`` [rad].

    Parameters
    ----------
    data : PixelData
        The pixels (with their mask) the estimate used, or a subsample of them.
    theta : (k,)
        The estimate ``(A_l[, Z_l], eps)``.
    zenith : float or None
        Fixed zenith [rad], or None when ``theta`` holds it.
    mat_cl : (3, 3)
        Level -> camera rotation.
    with_epsilon : bool
        Epsilon was estimated (it absorbs part of a camera-fixed polarization).
    """
    _, jac, _, _ = ml_evaluate(data, theta, zenith, mat_cl, True)
    assert jac is not None
    j = (jac if with_epsilon else jac[:-1]).astype(np.float64)
    sun_l = _sun_level(theta, zenith)
    xy = image_plane_evector(data, (mat_cl @ sun_l)[:, None])
    n = data.s0.size
    n1, n2, e2 = doubled_prediction(xy[0, :n], xy[0, n:])
    scale = data.s0.astype(np.float64) / e2
    if data.mask is not None:
        scale = scale * data.mask
    if isinstance(data.inv_sigma, np.ndarray):
        scale = scale * data.inv_sigma
    # dr for delta = (1, 0) and (0, 1): n . (S0, 0) = -sin 2zeta S0, n . (0, S0) = cos 2zeta S0.
    dr = np.stack([-n2 * scale, n1 * scale])
    info = j @ j.T
    try:
        dtheta = -np.linalg.solve(info, j @ dr.T)  # (k, 2)
    except np.linalg.LinAlgError:
        return float("nan")
    return float(np.hypot(dtheta[0, 0], dtheta[0, 1]))


def _sun_level(theta: NDArray, zenith: float | None) -> NDArray:
    """Level-frame unit sun of ``theta = (A[, Z], eps)``."""
    a = float(theta[0])
    z = float(zenith if zenith is not None else theta[1])
    return np.array([np.sin(z) * np.cos(a), np.sin(z) * np.sin(a), np.cos(z)])
