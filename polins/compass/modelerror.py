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

from functools import lru_cache

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from polins.compass.jointml import ml_evaluate
from polins.compass.lens import camera_constants
from polins.compass.measurement import MeasureOptions
from polins.compass.prediction import PixelData, doubled_prediction, image_plane_evector
from polins.compass.skymodel import SkyModel
from polins.models import CameraModel

__all__ = [
    "CLOUD_CELLS",
    "cloudy_cells",
    "depolarized_cells",
    "fitted_sensitivity",
    "instrumental_sensitivity",
    "model_weights",
    "rotated_cells",
    "sky_cells",
]

_SHAPE_FIT = 0.5  # Rayleigh DoP shape above which d_max is fitted
_SHAPE_TEST = 0.3  # ... and above which a pixel is tested (near the sun and the antisun the
# deficit is the neutral points', not a cloud's)


CLOUD_CELLS = 24
"""Cells per side of the thin-cloud mask's grid of image-plane ray components (about 7 deg
at the optical axis of a fisheye)."""
_CELL_MIN_PIXELS = 8  # tested pixels a cell needs to be judged


@lru_cache(maxsize=16)
def sky_cells(cam: CameraModel) -> NDArray:
    """The thin-cloud mask's cell ``(n,)`` of each field-of-view pixel: a
    :data:`CLOUD_CELLS` x :data:`CLOUD_CELLS` grid of the camera-frame ray's ``(x, y)`` in
    ``[-1, 1]``, cached per camera (docs/measurement.md §4)."""
    rays = camera_constants(cam, np.float64).rays
    idx = [np.clip(((c + 1.0) * (0.5 * CLOUD_CELLS)).astype(np.intp), 0, CLOUD_CELLS - 1)
           for c in rays[:2]]  # fmt: skip
    cells = idx[0] * CLOUD_CELLS + idx[1]
    cells.setflags(write=False)
    return cells


def cloudy_cells(
    rows: NDArray, rays: NDArray, sun_c: NDArray, ratio: float, valid: NDArray, cells: NDArray
) -> NDArray:
    """Sky cells flagged as thin cloud ``(CLOUD_CELLS**2,)`` bool (docs/measurement.md §4).

    A thin cloud depolarizes: its polarized intensity falls short of the clear sky's
    ``d_max f S0``, ``f = sin^2 T / (1 + cos^2 T)`` (T the angle to the sun ``sun_c``
    (3,)), ``d_max`` the median of ``p / (f S0)`` over the ``valid`` pixels with
    ``f > 0.5``. A cell is flagged when, over its valid pixels with ``f > 0.3`` (near the
    sun and the antisun the deficit is the neutral points'; at least
    :data:`_CELL_MIN_PIXELS` of them), ``sum p < ratio d_max sum f S0``. The sums average
    the noise of ``p`` out: unlike a per-pixel cut, no pixel is dropped for its noise.

    Parameters
    ----------
    rows : (3, n)
        Stokes rows S0, S1, S2 [DN] (e.g. the chain's subsample).
    rays : (3, n)
        Camera-frame unit rays.
    sun_c : (3,)
        Camera-frame unit sun.
    ratio : float
        ``cloud_dop_ratio`` [-].
    valid : (n,) bool
    cells : (n,) int
        The pixels' :func:`sky_cells`.
    """
    cos_t = rays[0] * sun_c[0] + rays[1] * sun_c[1] + rays[2] * sun_c[2]
    c2 = cos_t * cos_t
    shape = (1.0 - c2) / (1.0 + c2)
    p = np.sqrt(rows[1] * rows[1] + rows[2] * rows[2])
    n_cells = CLOUD_CELLS * CLOUD_CELLS
    fit = valid & (shape > _SHAPE_FIT) & (rows[0] > 0)
    if not np.any(fit):
        return np.zeros(n_cells, dtype=bool)
    d_max = float(np.median(p[fit] / (rows[0][fit] * shape[fit])))
    tested = valid & (shape > _SHAPE_TEST)
    cells_t = cells[tested]
    count = np.bincount(cells_t, minlength=n_cells)
    sum_p = np.bincount(cells_t, weights=p[tested], minlength=n_cells)
    sum_clear = np.bincount(cells_t, weights=(shape * rows[0])[tested], minlength=n_cells)
    return (count >= _CELL_MIN_PIXELS) & (sum_p < (ratio * d_max) * sum_clear)


_FIT_SHAPE_TEST = 0.15  # fitted sky's DoP shape above which a pixel is tested
_FIT_Z = 3.0  # a cell's deficit must exceed this many of its sigmas
_FIT_RINGS = 2  # rings of neighbours dropped with a depolarized cell
_BAND = float(np.radians(7.5))  # elevation band of the clear-sky level [rad]
_BAND_MIN_CELLS = 6  # cells a band needs for its median (else it joins the next)


def _grow(flagged: NDArray, rings: int) -> NDArray:
    """Flagged cells ``(CLOUD_CELLS**2,)`` and ``rings`` rings of their 4-neighbours."""
    if rings < 1:  # binary_dilation would repeat until nothing changes
        return flagged.copy()
    grid = flagged.reshape(CLOUD_CELLS, CLOUD_CELLS)
    return ndimage.binary_dilation(grid, iterations=rings).ravel()  # cross: 4-neighbours


def _band_level(ratio: NDArray, elevation: NDArray) -> NDArray:
    """Median of the cells' ``ratio`` ``(m,)`` over bands of :data:`_BAND` in their
    ``elevation`` [rad], a band of fewer than :data:`_BAND_MIN_CELLS` cells joined to the
    next (the last to the previous): ``(m,)``."""
    order = np.argsort(elevation)
    band = np.floor(elevation[order] / _BAND)
    level = np.empty_like(ratio)
    start, m = 0, order.size
    while start < m:
        stop = max(int(np.searchsorted(band, band[start], side="right")), start + _BAND_MIN_CELLS)
        stop = m if m - stop < _BAND_MIN_CELLS else stop
        level[order[start:stop]] = np.median(ratio[order[start:stop]])
        start = stop
    return level


def depolarized_cells(
    rows: NDArray,
    valid: NDArray,
    rays: NDArray,
    cells: NDArray,
    points_c: tuple[NDArray, NDArray],
    up_c: NDArray,
    ratio: float,
) -> NDArray:
    """Sky cells ``(CLOUD_CELLS**2,)`` bool whose DoP falls short of the fitted clear sky's
    (docs/measurement.md §4).

    The fitted sky's DoP shape is ``f = |w| / (2 - |w|)``, ``|w| = sin T_1 sin T_2`` (T_k
    the angles to its Babinet and Brewster points, docs/model.md §6.3). Per cell, over the
    valid pixels with ``f >`` :data:`_FIT_SHAPE_TEST`, ``q_c = sum p / sum f S0`` and its
    sigma from the pixels' scatter about ``q_c f S0``; the clear-sky level is the median
    ``q`` of the cells at the same elevation (:func:`_band_level`: a horizon
    depolarization is a function of the elevation, a cloud is local). A cell with
    ``q_c < ratio level_c`` and ``level_c - q_c >`` :data:`_FIT_Z` sigmas is flagged, with
    :data:`_FIT_RINGS` rings of neighbours (a cloud's rim turns the E-vector too).

    Parameters
    ----------
    rows : (3, n)
        Stokes rows S0, S1, S2 [DN]. valid : (n,) bool.
    rays : (3, n)
        Camera-frame unit rays.
    cells : (n,) int
        The pixels' :func:`sky_cells`.
    points_c : ((3,), (3,))
        Camera-frame unit Babinet and Brewster points of the fit (both the sun for the
        Rayleigh sky).
    up_c : (3,)
        Camera-frame unit vertical (a cell's elevation: that of its tested pixels' mean ray).
    ratio : float
        ``cloud_fit_ratio`` [-].
    """
    n_cells = CLOUD_CELLS * CLOUD_CELLS
    cos2 = np.asarray(points_c, dtype=rays.dtype) @ rays  # (2, n)
    np.multiply(cos2, cos2, out=cos2)
    w = np.sqrt(np.clip((1.0 - cos2[0]) * (1.0 - cos2[1]), 0.0, 1.0))
    shape = w / (2.0 - w)
    at = np.flatnonzero(valid & (shape > _FIT_SHAPE_TEST) & (rows[0] > 0))
    ct = cells.take(at)
    s0, s1, s2 = rows[:, at]
    p = np.hypot(s1, s2)
    clear = shape.take(at) * s0
    count = np.bincount(ct, minlength=n_cells)
    used = count >= _CELL_MIN_PIXELS
    if np.count_nonzero(used) < 2 * _BAND_MIN_CELLS:
        return np.zeros(n_cells, dtype=bool)
    sin_el = np.asarray(up_c, dtype=rays.dtype) @ rays[:, at]
    sum_p, sum_clear, sum_pp, sum_pc, sum_cc, sum_up = (
        np.bincount(ct, weights=x, minlength=n_cells)
        for x in (p, clear, p * p, p * clear, clear * clear, sin_el)
    )
    safe = np.where(used, sum_clear, 1.0)
    q = np.where(used, sum_p / safe, 0.0)
    # the pixels' scatter about q f S0: sum (p - q f S0)^2
    scatter = np.maximum(sum_pp - 2.0 * q * sum_pc + q * q * sum_cc, 0.0)
    sigma = np.sqrt(scatter) / safe
    idx = np.flatnonzero(used)
    elevation = np.arcsin(np.clip(sum_up[idx] / count[idx], -1.0, 1.0))
    level = _band_level(q[idx], elevation)
    deficit = level - q[idx]
    flagged = np.zeros(n_cells, dtype=bool)
    flagged[idx] = (q[idx] < ratio * level) & (deficit > _FIT_Z * sigma[idx])
    return _grow(flagged, _FIT_RINGS)


def rotated_cells(
    data: PixelData,
    theta: NDArray,
    zenith: float | None,
    mat_cl: NDArray,
    sky: SkyModel | None,
    cells: NDArray,
    z_min: float,
    angle_min: float,
) -> NDArray:
    """Sky cells ``(CLOUD_CELLS**2,)`` bool whose mean AoP residual is significant: a thin
    cloud turns the E-vector by a few degrees (docs/measurement.md §4).

    A rotation ``dzeta`` of the sky's E-vector changes the residual by ``2 p dzeta``; per
    cell its weighted estimate is ``dzeta_c = sum r p / (2 sum p^2)`` (residuals and
    polarized intensities in units of sigma_L) with the noise sigma ``1 / (2 sqrt(sum
    p^2))``; the ratios ``z_c = |dzeta_c| / sigma_c`` are divided by their robust spread
    ``1.4826 median(z_c)`` when it exceeds 1. A cell is flagged, with its four neighbours
    (a cloud's rim is turned too), when ``z_c > z_min`` and ``|dzeta_c| > angle_min`` [rad].

    Parameters
    ----------
    data : PixelData
        The pixels with the mask the estimate used.
    theta, zenith, mat_cl, sky
        The estimate and its model (:func:`polins.compass.jointml.ml_evaluate`).
    cells : (n,) int
        The pixels' :func:`sky_cells`.
    """
    r, _, _, mask = ml_evaluate(data, theta, zenith, mat_cl, False, None, sky)
    r = data.sigma_scaled(r).astype(np.float64)
    p = np.hypot(data.s1, data.s2).astype(np.float64)
    p = p * data.inv_sigma if isinstance(data.inv_sigma, np.ndarray) else p * float(data.inv_sigma)
    if mask is not None:
        p = p * mask
    n_cells = CLOUD_CELLS * CLOUD_CELLS
    num = np.bincount(cells, weights=r * p, minlength=n_cells)
    den = np.bincount(cells, weights=p * p, minlength=n_cells)
    with np.errstate(invalid="ignore", divide="ignore"):
        rot = 0.5 * num / den
        z = np.abs(rot) * 2.0 * np.sqrt(den)
    used = den > 0
    if np.any(used):  # in units of the cells' own spread (the residuals are not all noise)
        z = z / max(1.0, 1.4826 * float(np.median(z[used])))
    flagged = used & (z > z_min) & (np.abs(rot) > angle_min)
    return _grow(flagged, 1) & (den > 0)  # and their neighbours: a cloud's rim is turned too


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


def model_weights(
    inv_sigma_l2: NDArray | float,
    rows: NDArray,
    rays: NDArray,
    sun_c: NDArray,
    opt: MeasureOptions,
) -> NDArray:
    """Per-pixel ``1/var(r_i)`` ``(n,)`` with a model error of the AoP (docs/measurement.md
    §4): ``var(r_i) = sigma_L,i^2 + (2 p_i sigma_zeta,i)^2``,
    ``sigma_zeta = model_aop_std (1 + (theta / model_field_angle)^2 +
    (model_neutral_angle / gamma)^2)``, theta the field angle, gamma the angle to the
    nearer of the sun ``sun_c`` (3,) and the antisun (the neutral points lie within
    about 20 deg of them).

    Parameters
    ----------
    inv_sigma_l2 : (n,) or float
        ``1/sigma_L^2`` [1/DN^2]. rows : (3, n) Stokes rows [DN]. rays : (3, n) camera rays.
    opt : MeasureOptions
    """
    dt = rows.dtype
    field = np.arccos(np.clip(rays[2], -1.0, 1.0)) * (1.0 / opt.model_field_angle)
    cos_t = np.abs(rays[0] * sun_c[0] + rays[1] * sun_c[1] + rays[2] * sun_c[2])
    gamma = np.arccos(np.clip(cos_t, 0.0, 1.0)) + dt.type(1e-3)
    near = opt.model_neutral_angle / gamma
    sigma_aop = opt.model_aop_std * (1.0 + field * field + near * near)
    p2 = rows[1] * rows[1] + rows[2] * rows[2]
    return np.asarray(1.0 / (1.0 / inv_sigma_l2 + 4.0 * p2 * sigma_aop**2), dtype=dt)


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
        data.c[::k],
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
