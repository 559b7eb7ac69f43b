"""Thin clouds: the sky cells whose polarization falls short of, or turns away from, the clear sky's.

A thin cloud depolarizes and turns the E-vector by a few degrees. The field of view is cut
once per camera into a :data:`CLOUD_CELLS` x :data:`CLOUD_CELLS` grid of the rays'
image-plane components (:func:`sky_cells`); three detectors judge the cells
(docs/measurement.md §4): the DoP deficit against the Rayleigh shape with the starting sun
(:func:`cloudy_cells`), the mean AoP residual of a fit (:func:`rotated_cells`) and the DoP
deficit against the fitted Berry sky (:func:`depolarized_cells`, through
:class:`DopTest`). ``MeasureOptions.clouds`` switches them on or off together.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from polins.compass.lens import camera_constants
from polins.compass.prediction import PixelData
from polins.compass.residual import ml_evaluate
from polins.compass.skymodel import SkyModel
from polins.models import CameraModel
from polins.sky.neutral_points import berry_neutral_points_level

__all__ = [
    "CLOUD_AOP_MIN",
    "CLOUD_AOP_Z",
    "CLOUD_CELLS",
    "CLOUD_DOP_RATIO",
    "CLOUD_FIT_RATIO",
    "DopTest",
    "cloudy_cells",
    "depolarized_cells",
    "fitted_sky_depolarized",
    "rotated_cells",
    "sky_cells",
]

CLOUD_DOP_RATIO = 0.95
"""A cell whose polarized intensity is below this fraction of the clear sky's (Rayleigh
shape, starting sun) is cloud (:func:`cloudy_cells`)."""

CLOUD_AOP_Z = 4.0
"""A cell whose mean AoP residual exceeds this many sigmas (and :data:`CLOUD_AOP_MIN`) is
cloud (:func:`rotated_cells`)."""

CLOUD_AOP_MIN = float(np.radians(0.1))
"""Smallest mean E-vector rotation of a cloud cell [rad]."""

CLOUD_FIT_RATIO = 0.97
"""A cell whose polarized intensity is below this fraction of the fitted sky's level (by
more than 3 sigmas) is cloud (:func:`depolarized_cells`)."""

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
        :data:`CLOUD_DOP_RATIO` [-].
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
        :data:`CLOUD_FIT_RATIO` [-].
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
        The estimate and its model (:func:`polins.compass.residual.ml_evaluate`).
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


DOP_TEST_PIXELS = 60_000
"""Pixels of the fitted sky's DoP test (every k-th field-of-view pixel): its cells' sums
need many more than the joint ML's subsample (docs/measurement.md §4)."""


@dataclass(frozen=True)
class DopTest:
    """The pixels of the fitted sky's DoP test (:func:`fitted_sky_depolarized`).

    Attributes
    ----------
    rows : (3, m)
        Stokes rows S0, S1, S2 [DN] of about :data:`DOP_TEST_PIXELS` field-of-view pixels.
    valid : (m,) bool
    rays : (3, m)
        Camera-frame unit rays.
    cells : (m,) int
        Their :func:`sky_cells`.
    mat_cl : (3, 3)
        Level -> camera rotation.
    ratio : float
        Deficit ratio of a flagged cell [-].
    """

    rows: NDArray
    valid: NDArray
    rays: NDArray
    cells: NDArray
    mat_cl: NDArray
    ratio: float


def fitted_sky_depolarized(test: DopTest, azimuth: float, zenith: float, sep: float) -> NDArray:
    """:func:`depolarized_cells` for the fitted level-frame sun (``azimuth``, ``zenith``
    [rad]) and neutral-point separation ``sep`` [rad]: ``(CLOUD_CELLS**2,)`` bool."""
    points = berry_neutral_points_level(azimuth, zenith, sep)
    points_c = (test.mat_cl @ points[0][:, 0], test.mat_cl @ points[1][:, 0])
    return depolarized_cells(test.rows, test.valid, test.rays, test.cells, points_c,
                             test.mat_cl[:, 2], test.ratio)  # fmt: skip
