"""The Stokes stage of one image: calibrated Stokes rows of the field-of-view pixels and their noise.

The second stage of :mod:`polins.compass.chain` (docs/model.md §7, docs/measurement.md §1):
the least-squares Stokes rows and the redundancy of every field-of-view pixel, the
sun-independent quality masks, the channel noise variance and the measured / declared
noise ratio. Integer mosaics are processed in float32 (whose rounding is 4 orders below
the 1 DN quantisation), float mosaics in float64.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtri

from polins.compass.kernels import compiled
from polins.compass.lens import CameraConstants, camera_constants, subsample
from polins.compass.measurement import MeasureOptions
from polins.compass.polarimetry import StokesCalibration, stokes_calibration, stokes_image
from polins.models import CameraModel

__all__ = [
    "GN_PIXELS",
    "GRADIENT_MAX",
    "REDUNDANCY_MAX_SIGMA",
    "ImageStokes",
    "fill_invalid",
    "image_stokes",
]

GRADIENT_MAX = 0.05
"""Largest relative intensity gradient ``|grad S0|/S0`` of a valid pixel [1/superpixel]
(docs/measurement.md §4)."""

REDUNDANCY_MAX_SIGMA = 4.0
"""Largest redundancy residual ``|nu|`` of a valid pixel [channel-noise sigmas]
(docs/model.md §7.3)."""

GN_PIXELS = 15_000
"""Target size of the fixed pixel subsample of the starting sun and the Gauss-Newton
iterations (every k-th field-of-view pixel; docs/measurement.md §5)."""


@dataclass(frozen=True, eq=False)
class ImageStokes:
    """The Stokes stage's result: the field-of-view pixels of one image.

    Attributes
    ----------
    dtype : type
        float32 (integer mosaics) or float64.
    cache : CameraConstants
        Lens constants of all field-of-view pixels.
    sub : CameraConstants
        Those of the fixed subsample (every ``stride``-th pixel).
    stride : int
    cal : StokesCalibration
    rows : (4, n)
        (S0, S1, S2, nu) [DN] of the least-squares estimate.
    estimate : (3, n)
        (S0, S1, S2) [DN] the estimators use (``rows[:3]``, or another per-pixel estimate).
    sigma2 : (n,) or float
        Channel noise variance [DN^2].
    inv_sigma_l2 : (n,) or float
        ``1/sigma_L^2`` of the linear Stokes components [1/DN^2].
    valid : (n,) bool
        The sun-independent quality masks (docs/measurement.md §4).
    noise_ratio : float
        Measured / declared channel noise (NaN without unsaturated pixels).
    channels : (4, n) or None
        The channels [DN], when asked for.
    epsilon_px : (n,) or None
        A per-pixel direct-sunlight coefficient that came with ``estimate``, if any.
    """

    dtype: type
    cache: CameraConstants
    sub: CameraConstants
    stride: int
    cal: StokesCalibration
    rows: NDArray
    estimate: NDArray
    sigma2: NDArray | float
    inv_sigma_l2: NDArray | float
    valid: NDArray
    noise_ratio: float
    channels: NDArray | None = None
    epsilon_px: NDArray | None = None


def _noise_ratio(
    nu: NDArray, sigma2: NDArray | float, unsaturated: NDArray, index: NDArray
) -> float:
    """Robust measured / declared channel noise on the unsaturated pixels among ``index``,
    before the redundancy test (which would truncate ``nu``): from the fraction ``f`` of
    ``|nu| < sigma``, ``1 / Phi^-1((1 + f)/2)`` for Gaussian noise (a quantile, like the
    MAD, but without a sort)."""
    used = unsaturated.take(index)  # False for NaN
    n = int(np.count_nonzero(used))
    if n == 0:
        return float("nan")
    sigma = np.sqrt(sigma2.take(index) if isinstance(sigma2, np.ndarray) else sigma2)
    used &= np.abs(nu.take(index)) < sigma
    q = float(ndtri(0.5 + 0.5 * np.count_nonzero(used) / n))
    return 1.0 / q if q > 0 else float("inf")


def fill_invalid(rows: NDArray, inv_sigma_l2: NDArray | float, valid: NDArray) -> None:
    """Give the invalid pixels harmless finite data (S = (1, 0, 0), no redundancy residual,
    unit weight), in place on arrays the caller owns: the full-set arithmetic then runs over
    all pixels and masks by multiplication, with no compression or NaN handling.

    Parameters
    ----------
    rows : (3, n) or (4, n)
        Stokes rows (S0, S1, S2[, redundancy residual]) [DN].
    inv_sigma_l2 : (n,) or float
        Inverse noise variances [1/DN^2] (a scalar is left alone).
    valid : (n,) bool
    """
    inv = inv_sigma_l2 if isinstance(inv_sigma_l2, np.ndarray) else np.zeros(0, rows.dtype)
    compiled("fill_pass")(rows, inv, valid)  # one pass


def image_stokes(
    arr: NDArray,
    cam: CameraModel,
    opt: MeasureOptions,
    *,
    channels: bool = False,
    gain_correction: bool = True,
) -> ImageStokes:
    """The Stokes stage of a raw mosaic already checked with
    :func:`polins.compass.pixels.check_raw`.

    Parameters
    ----------
    arr : (H, W)
        Raw mosaic.
    cam : CameraModel
    opt : MeasureOptions
    channels : bool
        Also keep the channels ``(4, n)`` [DN] (for another per-pixel estimate).
    gain_correction : bool
        False ignores the channel gains (the paper's uncorrected baseline, for
        :mod:`polins.sim.algorithm1`).
    """
    dtype = np.float64 if np.issubdtype(arr.dtype, np.floating) else np.float32
    cache = camera_constants(cam, dtype)
    cal = stokes_calibration(cam, gain_correction, cache.pixels)  # per-pixel with maps
    image = stokes_image(
        arr,
        cache.pixels,
        cam,
        cal,
        s0_min=opt.s0_min_dn,
        redundancy_max_sigma=REDUNDANCY_MAX_SIGMA,
        gradient_max=GRADIENT_MAX,  # the DoP is cut per selection
        channels=channels,
    )
    sigma_l2 = image.sigma2 * cal.sigma_l_factors() ** 2
    inv_sigma_l2: NDArray | float
    if isinstance(sigma_l2, np.ndarray):
        inv_sigma_l2 = (1.0 / sigma_l2).astype(dtype)
    else:
        inv_sigma_l2 = 1.0 / float(sigma_l2)
    n_fov = cache.pixels.size
    stride = max(1, n_fov // GN_PIXELS)
    sub = subsample(cam, dtype, stride)
    # Every 4th subsample pixel: ~4,000 pixels give the ratio to ~2 %.
    ratio = _noise_ratio(image.rows[3], image.sigma2, image.unsaturated, sub.index[::4])
    fill_invalid(image.rows, inv_sigma_l2, image.valid)
    return ImageStokes(dtype, cache, sub, stride, cal, image.rows, image.rows[:3], image.sigma2,
                       inv_sigma_l2, image.valid, ratio, image.channels)  # fmt: skip
