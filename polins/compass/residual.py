"""The joint ML's residual: the AoP-orthogonal residual of a trial sun, its Jacobian and sums.

Per pixel, the measured linear Stokes vector minus the sunlight term, ``L_i - eps u_i w``,
is polarized along the Rayleigh AoP the sun predicts; the residual is its component
orthogonal to that direction (docs/model.md §9.2, docs/measurement.md §3)::

    r_i = n_i . (L_i - eps u_i w) / sigma_L,i,   n_i = (-sin 2zeta_R, cos 2zeta_R)

with ``u_i`` the exact unpolarized intensity of
:func:`polins.compass.sunlight.sunlight_unpolarized`. :func:`ml_evaluate` (rows) and
:func:`ml_pass_sums` (the normal equations' sums in one compiled pass) are the
component-first kernels of :mod:`polins.compass.jointml`'s Gauss-Newton;
:func:`ml_residuals` takes the library's trailing-component layout.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from polins.compass.normal import pass_sums
from polins.compass.prediction import (
    PixelData,
    doubled_prediction,
    image_plane_evector,
    pixel_data,
)
from polins.compass.sectors import SectorRuns
from polins.compass.selection import Selection, select_pixels
from polins.compass.skymodel import SkyModel, sky_evector
from polins.compass.sunlight import sunlight_direction, sunlight_unpolarized

FloatArray = NDArray[np.float64]

__all__ = [
    "ml_evaluate",
    "ml_pass_sums",
    "ml_residuals",
    "stokes_pixel_data",
    "sun_derivatives",
]


def stokes_pixel_data(stokes: NDArray, forward: ArrayLike, sigma_l: ArrayLike | float) -> PixelData:
    """:func:`polins.compass.prediction.pixel_data` from the public functions' arguments:
    Stokes ``(n, 3)``, forward rows ``(n, 2, 3)`` and a per-pixel or common ``sigma_L``."""
    inv_sigma = 1.0 / np.asarray(sigma_l, dtype=float)
    return pixel_data(
        stokes[:, 0],
        stokes[:, 1],
        stokes[:, 2],
        np.moveaxis(np.asarray(forward, dtype=float), 0, -1),
        float(inv_sigma) if inv_sigma.ndim == 0 else inv_sigma,
    )


def sun_derivatives(theta: NDArray, zenith: float | None) -> tuple[NDArray, list[NDArray]]:
    """Level-frame sun and its derivatives w.r.t. the sun parameters (A[, Z])."""
    a = theta[0]
    z = zenith if zenith is not None else theta[1]
    sa, ca, sz, cz = np.sin(a), np.cos(a), np.sin(z), np.cos(z)
    sun = np.array([sz * ca, sz * sa, cz])
    derivs = [np.array([-sz * sa, sz * ca, 0.0])]
    if zenith is None:
        derivs.append(np.array([cz * ca, cz * sa, -sz]))
    return sun, derivs


def ml_evaluate(
    data: PixelData,
    theta: NDArray,
    zenith: float | None,
    mat_cl: NDArray,
    jacobian: bool,
    select: Selection | None = None,
    sky: SkyModel | None = None,
) -> tuple[NDArray, NDArray | None, NDArray, NDArray | None]:
    """Residuals ``r`` (n,), Jacobian ``(k, n)``, exact unpolarized intensities ``u`` and the
    mask in force, at ``theta = (A[, Z], eps)`` (docs/model.md §9.2).

    ``r_i = n_i . (L_i - eps u_i w)`` with ``n_i = (-sin 2zeta_R, cos 2zeta_R)``, NOT yet
    divided by sigma_L when sigma_L is one number (the caller scales the normal equations);
    per-pixel sigma_L is applied here. Masked pixels get ``r = 0`` and a zero Jacobian.
    """
    n = data.s0.size
    dt = data.s0.dtype
    eps = float(theta[-1])
    cols, xy, delta = _predicted(data, theta, zenith, mat_cl, jacobian, sky)
    assert xy is not None
    sun_c = cols[:, 0]
    w = sunlight_direction(sun_c)
    x, y = xy[0, :n], xy[0, n:]
    n1, n2, e2 = doubled_prediction(x, y)
    mask = data.mask
    if select is not None:
        mask = select_pixels(data, select, sun_c, n1, n2, e2)
    inv_e = np.divide(1.0, e2, out=e2)
    if mask is not None:
        inv_e *= mask  # zeroes (cos, sin 2zeta_R), hence r and the Jacobian, of masked pixels
    u = sunlight_unpolarized(
        data.s0, data.s1, data.s2, data.c, dt.type(eps), w.astype(dt), finite=mask is None
    )
    c2 = np.multiply(n1, inv_e, out=n1)  # (cos 2zeta_R, sin 2zeta_R)
    s2 = np.multiply(n2, inv_e, out=n2)
    # r = n . (L - eps u w) = (c2 S2 - s2 S1) - eps u (n . w),  n . w = c2 w1 - s2 w0
    n_dot_w = c2 * dt.type(w[1])
    n_dot_w -= s2 * dt.type(w[0])
    u_nw = u * n_dot_w if delta != 0.0 else np.multiply(u, n_dot_w, out=n_dot_w)
    r = c2 * data.s2
    r -= s2 * data.s1
    r -= dt.type(eps) * u_nw
    fit_delta = sky is not None and sky.fit_delta
    k_par = cols.shape[1] - 1 + fit_delta if jacobian else 0
    delta_col = k_par - 1 if fit_delta else None
    if delta != 0.0:  # - delta S0 (n . w_perp), n . w_perp = r_hat . w
        r_w0 = c2 * dt.type(w[0])
        r_w0 += s2 * dt.type(w[1])
        r_w0 *= data.s0
        r -= dt.type(delta) * r_w0
    weight = data.inv_sigma if isinstance(data.inv_sigma, np.ndarray) else None
    if weight is not None:
        r *= weight
    if not jacobian:
        return r, None, u, mask
    rows = (c2, s2, inv_e, u, u_nw, n_dot_w)
    jac = _jacobian(data, cols, xy, w, rows, eps, delta, k_par, delta_col is not None)
    return r, jac, u, mask


def _jacobian(
    data: PixelData,
    cols: NDArray,
    xy: NDArray,
    w: NDArray,
    rows: tuple[NDArray, NDArray, NDArray, NDArray, NDArray, NDArray],
    eps: float,
    delta: float,
    k_par: int,
    fit_delta: bool,
) -> NDArray:
    """The residuals' Jacobian ``(k_par + 1, n)`` (docs/measurement.md §3) from the parameter
    columns ``cols``, the image-plane E-vector rows ``xy`` and the residual's per-pixel rows
    ``(cos 2zeta_R, sin 2zeta_R, 1/e2, u, u (n . w), n . w)`` (the last is only read with a
    ``delta``). d r / d theta_sun = -d(2 zeta) r_hat . (L - eps u w) - eps u n . dw/dtheta,
    with n . dw/dtheta = 2 alpha_s' (r_hat . w) (alpha_s the sun's image-plane azimuth); only
    the O(eps^2) term through u is left out. dr/deps = -u (n . w)."""
    c2, s2, inv_e, u, u_nw, n_dot_w = rows
    n = data.s0.size
    dt = data.s0.dtype
    x, y = xy[0, :n], xy[0, n:]
    sun_c = cols[:, 0]
    proj = c2 * data.s1
    proj += s2 * data.s2
    t_w = c2 * dt.type(w[0])  # eps u (r_hat . w) [- delta S0 (n . w)]
    t_w += s2 * dt.type(w[1])
    r_w = t_w.copy() if fit_delta else None
    t_w *= u
    t_w *= dt.type(eps)
    if delta != 0.0:
        t_w -= dt.type(delta) * n_dot_w * data.s0
    proj -= t_w
    proj *= inv_e
    proj *= -2.0
    jac = np.empty((k_par + 1, n), dtype=dt)
    rho2 = sun_c[0] ** 2 + sun_c[1] ** 2
    for j in range(1, cols.shape[1]):
        xj, yj = xy[j, :n], xy[j, n:]
        d2zeta = np.multiply(x, yj, out=jac[j - 1])
        d2zeta -= y * xj
        d2zeta *= proj
        alpha_j = (sun_c[0] * cols[1, j] - sun_c[1] * cols[0, j]) / rho2
        if alpha_j != 0.0:
            d2zeta -= dt.type(2.0 * alpha_j) * t_w
    if r_w is not None:
        np.multiply(r_w, data.s0, out=jac[-2])
        jac[-2] *= -1.0
    np.negative(u_nw, out=jac[-1])
    if isinstance(data.inv_sigma, np.ndarray):
        jac *= data.inv_sigma
    return jac


def _predicted(
    data: PixelData,
    theta: NDArray,
    zenith: float | None,
    mat_cl: NDArray,
    jacobian: bool,
    sky: SkyModel | None,
    rows: bool = True,
) -> tuple[NDArray, NDArray | None, float]:
    """Camera-frame columns ``(3, 1 + k)`` (the sun, its derivatives by the sun and sky
    parameters), their image-plane E-vector rows (None without ``rows`` for the Rayleigh
    sky: the compiled pass makes them from the rays) and ``delta_perp``, at ``theta``."""
    if sky is not None:  # the Berry sky and/or the camera-fixed polarization
        return sky_evector(data, sky, theta, zenith, mat_cl, jacobian)
    sun_l, dsun_l = sun_derivatives(theta, zenith)
    cols = mat_cl @ np.column_stack([sun_l, *dsun_l])  # camera frame, (3, 1 + k_sun)
    if not rows:
        return cols, None, 0.0
    return cols, image_plane_evector(data, cols if jacobian else cols[:, :1]), 0.0


def ml_pass_sums(
    data: PixelData,
    theta: NDArray,
    zenith: float | None,
    mat_cl: NDArray,
    select: Selection | None,
    sky: SkyModel | None,
    sectors: SectorRuns | None,
) -> tuple[FloatArray, NDArray]:
    """:func:`ml_evaluate` with the linear loss as per-group sums ``(G, ML_SUMS)`` of the
    normal equations over the jackknife groups of ``sectors`` (or one), and the mask in
    force (:func:`polins.compass.normal.pass_sums`; their ``J^T J``, ``J^T r``, ``r^T r``:
    :func:`polins.compass.normal.sums_normal_equations`)."""
    cols, xy, _ = _predicted(data, theta, zenith, mat_cl, True, sky, rows=data.rays is None)
    sun_c = cols[:, 0]
    rho2 = sun_c[0] ** 2 + sun_c[1] ** 2
    alphas = [
        (sun_c[0] * cols[1, j] - sun_c[1] * cols[0, j]) / rho2 for j in range(1, cols.shape[1])
    ]
    return pass_sums(data, cols, xy, float(theta[-1]), sunlight_direction(sun_c), alphas,
                     select, sectors)  # fmt: skip


def ml_residuals(
    stokes: ArrayLike,
    forward: ArrayLike,
    mat_cl: ArrayLike,
    sun_l: ArrayLike,
    epsilon: float,
    sigma_l: ArrayLike | float = 1.0,
) -> FloatArray:
    """Normalised AoP-orthogonal residuals ``(n,)`` of docs/model.md §9.2 at a given sun and
    epsilon.

    ``r_i = n_i . (L_i - eps u_i w) / sigma_L,i`` = ``p_i sin(2 (zeta_corr - zeta_R))/sigma_L``.

    Parameters
    ----------
    stokes : (n, 3) measured Stokes [DN]. forward : (n, 2, 3) :func:`lens_forward` rows.
    mat_cl : (3, 3) level -> camera rotation matrix. sun_l : (3,) unit level-frame sun.
    sigma_l : per-pixel or common sigma_L [DN].
    """
    s = np.asarray(stokes, dtype=float)
    sl = np.asarray(sun_l, dtype=float)
    sl = sl / np.linalg.norm(sl)
    theta = np.array([np.arctan2(sl[1], sl[0]), np.arccos(np.clip(sl[2], -1, 1)), epsilon])
    data = stokes_pixel_data(s, forward, sigma_l)
    r, _, _, _ = ml_evaluate(data, theta, None, np.asarray(mat_cl, dtype=float), False)
    return r if isinstance(data.inv_sigma, np.ndarray) else r * data.inv_sigma
