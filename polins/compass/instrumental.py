"""The camera-fixed (instrumental) polarization: its part of the heading's sigma.

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

from polins.compass.prediction import PixelData, doubled_prediction, image_plane_evector
from polins.compass.residual import ml_evaluate
from polins.compass.skymodel import SkyModel

__all__ = ["fitted_sensitivity", "instrumental_sensitivity"]


def fitted_sensitivity(
    data: PixelData, theta: NDArray, zenith: float | None, mat_cl: NDArray, sky: SkyModel
) -> tuple[float, float]:
    """Yaw change per unit camera-fixed polarization ``sqrt(g_1^2 + g_2^2)`` [rad] of a
    joint ML that estimates ``delta_perp`` (``theta = (A_l[, Z_l], delta_perp, eps)``,
    ``sky`` with ``fit_delta``): that component is absorbed, what is left is the part
    along the sunlight direction that epsilon does not absorb (docs/measurement.md §12);
    and per unit camera-fixed mixing. Same arguments as :func:`instrumental_sensitivity`."""
    _, jac, _, _ = ml_evaluate(data, theta, zenith, mat_cl, True, None, sky)
    assert jac is not None
    return _yaw_per_delta(data, jac.astype(np.float64), theta, zenith, mat_cl)


def instrumental_sensitivity(
    data: PixelData, theta: NDArray, zenith: float | None, mat_cl: NDArray, with_epsilon: bool
) -> tuple[float, float]:
    """Yaw change per unit camera-fixed polarization, ``sqrt(g_1^2 + g_2^2)`` [rad], and per
    unit camera-fixed mixing of the linear Stokes components (``sqrt(g_a^2 + g_b^2)``).

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
    data = _every(data, max(1, data.s0.size // _SENSITIVITY_PIXELS))
    _, jac, _, _ = ml_evaluate(data, theta, zenith, mat_cl, True)
    assert jac is not None
    j = (jac if with_epsilon else jac[:-1]).astype(np.float64)
    return _yaw_per_delta(data, j, theta, zenith, mat_cl)


def _yaw_per_delta(
    data: PixelData, j: NDArray, theta: NDArray, zenith: float | None, mat_cl: NDArray
) -> tuple[float, float]:
    """``sqrt(g_1^2 + g_2^2)`` [rad] of the linear response ``d theta = -(J J^T)^-1 J dr``
    of the estimate (Jacobian rows ``j``, float64) to a camera-fixed polarization ``delta``,
    and the same for a camera-fixed mixing ``dL = [[a, b], [b, -a]] L`` of the linear
    Stokes components (docs/measurement.md §12); NaN when ``J J^T`` is singular."""
    sun_l = _sun_level(theta, zenith)
    xy = image_plane_evector(data, (mat_cl @ sun_l)[:, None])
    n = data.s0.size
    n1, n2, e2 = doubled_prediction(xy[0, :n], xy[0, n:])
    scale = 1.0 / e2.astype(np.float64)
    if data.mask is not None:
        scale = scale * data.mask
    if isinstance(data.inv_sigma, np.ndarray):
        scale = scale * data.inv_sigma
    s0, s1, s2 = (x.astype(np.float64) * scale for x in (data.s0, data.s1, data.s2))
    # dr = n . dL with n = (-sin 2zeta, cos 2zeta): delta = (1, 0) and (0, 1) give dL = (S0, 0)
    # and (0, S0); the mixing a and b give dL = (S1, -S2) and (S2, S1).
    dr = np.stack([-n2 * s0, n1 * s0, -n2 * s1 - n1 * s2, n1 * s1 - n2 * s2])
    try:
        dtheta = -np.linalg.solve(j @ j.T, j @ dr.T)  # (k, 4)
    except np.linalg.LinAlgError:
        return float("nan"), float("nan")
    return float(np.hypot(dtheta[0, 0], dtheta[0, 1])), float(np.hypot(dtheta[0, 2], dtheta[0, 3]))


_SENSITIVITY_PIXELS = 4000  # a ratio of sums: a few thousand pixels give it to ~1 %


def _every(data: PixelData, k: int) -> PixelData:
    """Every ``k``-th pixel of ``data``."""
    if k == 1:
        return data
    n = data.s0.size
    fwd = data.forward
    if fwd is not None:
        fwd = np.ascontiguousarray(np.concatenate([fwd[:, :n:k], fwd[:, n::k]], axis=1))
    return PixelData(
        data.s0[::k],
        data.s1[::k],
        data.s2[::k],
        fwd,
        None if data.rays is None else np.ascontiguousarray(data.rays[:, ::k]),
        data.inv_sigma[::k] if isinstance(data.inv_sigma, np.ndarray) else data.inv_sigma,
        None if data.mask is None else data.mask[::k],
    )


def _sun_level(theta: NDArray, zenith: float | None) -> NDArray:
    """Level-frame unit sun of ``theta = (A[, Z], eps)``."""
    a = float(theta[0])
    z = float(zenith if zenith is not None else theta[1])
    return np.array([np.sin(z) * np.cos(a), np.sin(z) * np.sin(a), np.cos(z)])
