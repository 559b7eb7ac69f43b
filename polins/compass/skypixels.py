"""The pixel-selection stage of one image: region of interest, masks, clouds, starting sun.

The third stage of :mod:`polins.compass.chain` (docs/measurement.md §4, §5 step 1): the
region of interest, harmless data for the invalid pixels, the starting sun (the eigen
solution on the fixed subsample, the sun circle taken from the prior or, without an
ephemeris, from a first eigen solution), the thin-cloud cells by their DoP deficit, and the selection rules (:class:`polins.compass.selection.Selection`) of the
subsample and of the full set that the solve stage applies along the predicted AoP.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from polins.compass.clouds import CLOUD_DOP_RATIO, cloudy_cells, sky_cells
from polins.compass.eigen import EigenSolution, eigen_level_rows
from polins.compass.heading import Geometry, resolve_sun_sign
from polins.compass.image import ImageStokes
from polins.compass.kernels import dot_rows
from polins.compass.lens import CameraConstants
from polins.compass.measurement import MeasureOptions, Refusal
from polins.compass.prediction import PixelData, pixel_data
from polins.compass.selection import Selection
from polins.models import CameraModel

__all__ = ["HORIZON_MIN", "SNR_MIN", "SkyPixels", "sky_pixels"]

HORIZON_MIN = float(np.radians(3.0))
"""Lowest elevation [rad] above the prior's level horizon of a used pixel: the ground and
the scenery at the horizon of a tilted wide field are not sky, and the few degrees above
the horizon are depolarized by multiple scattering (docs/measurement.md §4)."""

SNR_MIN = 3.0
"""Smallest polarized intensity of a used pixel in units of its noise sigma_L: rejects
unpolarized scenery (occluders, ground, clouds) whose noise alone would pass ``dop_min``
(docs/measurement.md §4)."""


@dataclass(frozen=True, eq=False)
class SkyPixels:
    """The pixel-selection stage's result.

    Attributes
    ----------
    valid, valid_sub : (n,), (n_sub,) bool
        The sun-independent masks, the region of interest and the cloud cells, of all
        field-of-view pixels and of the subsample (``valid`` is ``select_full.valid``).
    rows_sub : (3, n_sub)
        The subsample's (S0, S1, S2) [DN].
    data_sub, data_full : PixelData
        The subsample and all pixels for the estimators.
    select_sub, select_full : Selection
        The selection rules of the subsample and of the full set.
    eig0 : EigenSolution
        The starting eigen solution (level frame).
    sun_l0 : (3,)
        The starting sun, level frame (its sign resolved with an ephemeris).
    cells, cells_sub : (n,), (n_sub,) int
        The thin-cloud cells (:func:`polins.compass.clouds.sky_cells`) of all
        field-of-view pixels and of the subsample.
    """

    valid: NDArray
    valid_sub: NDArray
    rows_sub: NDArray
    data_sub: PixelData
    data_full: PixelData
    select_sub: Selection
    select_full: Selection
    eig0: EigenSolution
    sun_l0: NDArray
    cells: NDArray
    cells_sub: NDArray


@lru_cache(maxsize=16)
def _cells_every(cam: CameraModel, stride: int) -> NDArray:
    """The thin-cloud cells of every ``stride``-th field-of-view pixel (the subsample's),
    cached per camera (read-only)."""
    cells = np.ascontiguousarray(sky_cells(cam)[::stride])
    cells.setflags(write=False)
    return cells


@lru_cache(maxsize=8)
def _field_angle_max(cache: CameraConstants) -> float:
    """Largest angle of a field-of-view ray from the optical axis [rad]."""
    return float(np.arccos(np.clip(np.min(cache.rays[2]), -1.0, 1.0)))


def _field_above(cache: CameraConstants, cos_tilt: float) -> bool:
    """Every field-of-view ray is at least :data:`HORIZON_MIN` above the level horizon
    (with 1e-5 to spare for the rays' rounding) when the optical axis is ``acos(cos_tilt)``
    from the level zenith: the per-pixel test is then not needed."""
    lowest = np.arccos(cos_tilt) + _field_angle_max(cache)  # from the zenith [rad]
    return bool(lowest < np.pi / 2 and np.cos(lowest) > np.sin(HORIZON_MIN) + 1e-5)


def _excluded_sun(sun_c: NDArray, rays: NDArray, cos_excl: float) -> NDArray:
    return dot_rows(sun_c.astype(rays.dtype), rays) > cos_excl


def _at(w: NDArray | float, idx: NDArray | None) -> NDArray | float:
    """``w`` at the pixels ``idx`` (all with None; a scalar stays a scalar)."""
    if not isinstance(w, np.ndarray):
        return w
    return w if idx is None else w.take(idx)


def _sqrt_at(w: NDArray | float, idx: NDArray | None) -> NDArray | float:
    return (
        np.sqrt(w if idx is None else w.take(idx))
        if isinstance(w, np.ndarray)
        else float(np.sqrt(w))
    )


def _starting_sun(
    img: ImageStokes,
    geo: Geometry,
    opt: MeasureOptions,
    rows_sub: NDArray,
    valid_sub: NDArray,
    weighted: bool,
) -> EigenSolution:
    """The eigen solution on the subsample with the plain DoP and noise cuts, the sun
    circle from the prior (without an ephemeris: around the sun and the antisun of a first
    eigen solution). Refuses with too few pixels."""
    sub, cos_excl = img.sub, float(np.cos(opt.sun_exclusion))
    s0d, s1d, s2d = rows_sub
    inv_sigma2 = _at(img.inv_sigma_l2, sub.index)
    keep = valid_sub.copy()
    p2 = s1d * s1d + s2d * s2d
    keep &= p2 >= opt.dop_min**2 * (s0d * s0d)
    keep &= p2 >= SNR_MIN**2 / inv_sigma2

    def starting_eigen(mask: NDArray) -> EigenSolution:
        eig, _, _ = eigen_level_rows(s1d, s2d, inv_sigma2, sub.basis, img.cache.projection,
                                     geo.mat_lc, weighted, mask=mask)  # fmt: skip
        return eig

    if geo.sun_n is not None:
        keep &= ~_excluded_sun(geo.mat_cn @ geo.sun_n, sub.rays, cos_excl)
    elif np.count_nonzero(keep) >= 3:
        sun_c00 = geo.mat_cl @ starting_eigen(keep).sun
        keep &= ~_excluded_sun(sun_c00, sub.rays, cos_excl)
        keep &= ~_excluded_sun(-sun_c00, sub.rays, cos_excl)
    n_est = int(np.count_nonzero(keep)) * img.stride
    if n_est < opt.min_pixels:
        raise Refusal(f"too few valid pixels ({n_est} < {opt.min_pixels})", n_est)
    return starting_eigen(keep)


def sky_pixels(
    img: ImageStokes, cam: CameraModel, geo: Geometry, opt: MeasureOptions, *, weighted: bool = True
) -> SkyPixels:
    """The pixel-selection stage (module notes); ``weighted=False`` gives the starting eigen
    solution equal weights (the paper's Eq. 31, for :mod:`polins.sim.algorithm1`).

    Raises
    ------
    Refusal
        Too few valid pixels.
    """
    cache, sub = img.cache, img.sub
    valid = img.valid
    if opt.roi is not None:  # the region of interest of this image (a new mask)
        valid = valid & (cache.rays[2] >= img.dtype(np.cos(opt.roi)))
    up_c: NDArray = geo.mat_cl[:, 2].astype(img.dtype)  # the level zenith, camera frame
    if not _field_above(cache, float(np.clip(geo.mat_cl[2, 2], -1.0, 1.0))):
        above = dot_rows(up_c, cache.rays) >= img.dtype(np.sin(HORIZON_MIN))
        if not above.all():
            valid = valid & above
    rows_sub = img.estimate.take(sub.index, axis=1)
    valid_sub = valid[sub.index]
    eig0 = _starting_sun(img, geo, opt, rows_sub, valid_sub, weighted)
    sun_l0 = eig0.sun
    if geo.sun_n is not None:
        sun_l0 = resolve_sun_sign(eig0.sun, geo.sun_n, geo.yaw_prior, opt.horizon_fallback)

    cells, cells_sub = sky_cells(cam), _cells_every(cam, img.stride)
    if opt.clouds == "auto":  # thin clouds: cells with a DoP deficit (§4)
        cloudy = cloudy_cells(rows_sub, sub.rays, geo.mat_cl @ sun_l0, CLOUD_DOP_RATIO,
                              valid_sub, cells_sub)  # fmt: skip
        if cloudy.any():
            valid = valid & ~cloudy.take(cells)
            valid_sub = valid[sub.index]

    # The selection rules: the DoP and noise cuts along the predicted direction.
    cos_excl = float(np.cos(opt.sun_exclusion))
    select_sub = Selection(valid_sub, sub.rays, cos_excl, opt.dop_min,
                           SNR_MIN / _sqrt_at(img.inv_sigma_l2, sub.index))  # fmt: skip
    select_full = Selection(valid, cache.rays, cos_excl, opt.dop_min,
                            SNR_MIN / _sqrt_at(img.inv_sigma_l2, None))  # fmt: skip
    est = img.estimate
    data_sub = pixel_data(rows_sub[0], rows_sub[1], rows_sub[2], sub.forward,
                          _sqrt_at(img.inv_sigma_l2, sub.index), packed=True, rays=sub.lens_rays)  # fmt: skip
    data_full = pixel_data(est[0], est[1], est[2], cache.forward, _sqrt_at(img.inv_sigma_l2, None),
                           packed=True, rays=cache.lens_rays)  # fmt: skip
    return SkyPixels(valid, valid_sub, rows_sub, data_sub, data_full, select_sub, select_full,
                     eig0, sun_l0, cells, cells_sub)  # fmt: skip
