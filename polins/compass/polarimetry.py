"""Polarimetry: four polarizer channels -> calibrated Stokes vectors, and the pixel quality masks.

Sensor model (docs/model.md §6.2), channel k with transmission axis alpha_k, gain g_k (the
paper's beta_k), polarization efficiency eta_k and dark offset o_k::

    I_k = g_k/2 [S0 + eta_k (S1 cos 2alpha_k + S2 sin 2alpha_k)] + o_k + n_k

Channels come from :mod:`polins.compass.pixels`. Stokes vectors are ``(..., 3)`` =
(S0, S1, S2) in the image-plane reference of docs/conventions.md (angles from +x_c towards
+y_c); in the ideal case S1 = I0 - I90 and S2 = I45 - I135 (0 deg *minus* 90 deg: the
paper's Eq. 14 has both signs flipped, which turns the AoP by 90 deg; docs/errata.md §1).

The row kernels :func:`stokes_rows` and :func:`validity_rows` work on component-first
arrays (``(k, n)``, one contiguous row per component), the layout of the per-image chain
(:mod:`polins.compass.chain`); the other public functions take and return the library's
trailing-component layout.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from polins.compass.camera import pixel_rays_c
from polins.compass.pixels import PixelSet, check_raw, gather_channels, pixel_set
from polins.models.loader import CameraModel

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

__all__ = [
    "StokesCalibration",
    "aop",
    "dop",
    "polarizer_rotation_slope",
    "relative_gradient",
    "stokes_calibration",
    "stokes_from_channels",
    "stokes_noise_variance",
    "stokes_rows",
    "unpolarized_intensity",
    "validity_mask",
    "validity_rows",
]


# ----------------------------------------------------------------------------- Stokes
@dataclass(frozen=True)
class StokesCalibration:
    """Least-squares Stokes estimator of one camera (docs/model.md §7.2-7.4).

    Attributes
    ----------
    response : (4, 3)
        A: rows ``a_k = g_k/2 [1, eta_k cos 2alpha_k, eta_k sin 2alpha_k]``.
    estimator : (3, 4)
        B = (A^T A)^-1 A^T (equal channel variances; exact for per-pixel iid noise).
    null : (4,)
        Unit vector with ``A^T null = 0``: the redundancy ``nu = null . (I - o)`` [DN] has
        standard deviation sigma for iid channel noise and is blind to every Stokes input,
        the sunlight term included (ideal: (+1, -1, +1, -1)/(2 g_k)-like).
    covariance : (3, 3)
        (A^T A)^-1: ``Cov(S) = sigma^2 * covariance``.
    sigma_l_factor : float
        sigma_L / sigma, the per-component noise of (S1, S2) (ideal: sqrt(2)/g).
    offset : (4,)
        Dark offsets o_k [DN].
    """

    response: FloatArray
    estimator: FloatArray
    null: FloatArray
    covariance: FloatArray
    sigma_l_factor: float
    offset: FloatArray


@lru_cache(maxsize=16)
def stokes_calibration(cam: CameraModel, gain_correction: bool = True) -> StokesCalibration:
    """The calibrated least-squares Stokes estimator of ``cam`` (docs/model.md §7.2).

    Parameters
    ----------
    gain_correction : bool
        False ignores the channel gains (g_k = 1): the paper's uncorrected baseline.
    """
    two_alpha = 2.0 * cam.transmission_angle
    gain = cam.gain if gain_correction else np.ones(4)
    a = (
        0.5
        * gain[:, None]
        * np.stack(
            [np.ones(4), cam.efficiency * np.cos(two_alpha), cam.efficiency * np.sin(two_alpha)], -1
        )
    )
    cov = np.linalg.inv(a.T @ a)
    b = cov @ a.T
    _, _, vt = np.linalg.svd(a.T)
    null = vt[-1] * np.sign(vt[-1][0])
    sigma_l_factor = float(np.sqrt(0.5 * (cov[1, 1] + cov[2, 2])))
    return StokesCalibration(
        a, b, null, np.asarray(cov, dtype=np.float64), sigma_l_factor, cam.dark_offset_dn.copy()
    )


def stokes_rows(channels: NDArray, cal: StokesCalibration, dtype: type = np.float32) -> NDArray:
    """Stokes rows (S0, S1, S2, nu) ``(4, n)`` [DN] of component-first channels ``(4, n)``
    (docs/model.md §7.2-7.3): the least-squares estimate and the redundancy residual."""
    matrix: NDArray = np.vstack([cal.estimator, cal.null]).astype(dtype)
    # einsum, not BLAS: a threaded gemm of this thin shape stalls on a busy machine.
    out = np.einsum("ij,jn->in", matrix, channels.astype(dtype, copy=False))
    if np.any(cal.offset):
        out -= (matrix @ cal.offset.astype(dtype))[:, None]
    return out


def stokes_from_channels(
    channels: ArrayLike, cam: CameraModel, *, gain_correction: bool = True
) -> tuple[FloatArray, FloatArray]:
    """Calibrated least-squares Stokes vectors and redundancy residuals (docs/model.md §7.1-7.3).

    Parameters
    ----------
    channels : array_like, (..., 4)
        Channel intensities [DN] (raw, dark offset included), ordered by channel index.
    gain_correction : bool
        Apply the calibrated gains (docs/model.md §7.2); False is the paper's uncorrected baseline.

    Returns
    -------
    stokes : ndarray, (..., 3)
        (S0, S1, S2) [DN].
    redundancy : ndarray, (...)
        nu = null . (I - o) [DN]; zero for any noise-free Malus-law input, standard deviation
        sigma (the per-channel noise) otherwise.
    """
    ch = np.asarray(channels, dtype=float)
    if ch.shape[-1:] != (4,):
        raise ValueError(f"channels must have shape (..., 4), got {ch.shape}")
    cal = stokes_calibration(cam, gain_correction)
    rows = stokes_rows(ch.reshape(-1, 4).T, cal, np.float64)
    return rows[:3].T.reshape(*ch.shape[:-1], 3), rows[3].reshape(ch.shape[:-1])


def stokes_noise_variance(cam: CameraModel, s0: ArrayLike) -> FloatArray | float:
    """Per-channel noise variance sigma^2 [DN^2] at Stokes intensity ``s0`` (docs/model.md §4):
    ``read_noise^2 + I/G_e`` with the mean channel level ``I = mean(g) S0/2``."""
    s = np.asarray(s0, dtype=float)
    shot = 0.0
    if np.isfinite(cam.conversion_gain_e_per_dn):
        shot = np.maximum(s, 0.0) * (0.5 * float(np.mean(cam.gain))) / cam.conversion_gain_e_per_dn
    return cam.read_noise_dn**2 + shot


def dop(stokes: ArrayLike) -> FloatArray:
    """Degree of linear polarization ``|L| / S0`` of Stokes vectors ``(..., 3)``."""
    s = np.asarray(stokes, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.hypot(s[..., 1], s[..., 2]) / s[..., 0]


def aop(stokes: ArrayLike) -> FloatArray:
    """Angle of polarization ``zeta = atan2(S2, S1)/2`` [rad], image-plane convention."""
    s = np.asarray(stokes, dtype=float)
    return 0.5 * np.arctan2(s[..., 2], s[..., 1])


def unpolarized_intensity(stokes: ArrayLike) -> FloatArray:
    """Unpolarized intensity ``u = max(S0 - |L|, 0)`` [DN] (docs/model.md §7.4)."""
    s = np.asarray(stokes, dtype=float)
    return np.maximum(s[..., 0] - np.hypot(s[..., 1], s[..., 2]), 0.0)


# ----------------------------------------------------------------------------- masks
def _relative_gradient_sq(s0: NDArray, pixels: PixelSet) -> NDArray:
    """|grad S0|^2 [DN^2 per superpixel^2]: central horizontal difference (one-sided at the
    edge of the set), one-sided vertical difference; shifts instead of gathers where the
    set's row-major order allows it."""
    forward = np.diff(s0)
    forward *= pixels.right_step
    gx = np.empty_like(s0)
    gx[:-1] = forward
    gx[-1] = 0.0
    gx[1:] += forward
    gx *= pixels.horizontal_scale
    gy = s0.take(pixels.vertical)
    gy -= s0
    gy *= pixels.vertical_step
    gx *= gx
    gy *= gy
    gx += gy
    return gx


def relative_gradient(s0: ArrayLike, pixels: PixelSet) -> FloatArray:
    """Relative intensity gradient ``|grad S0| / S0`` [1/superpixel] (docs/model.md §7.5): central
    difference along rows, one-sided difference along columns.

    Parameters
    ----------
    s0 : array_like, (n,)
        S0 of the superpixels of ``pixels`` (same order).
    """
    s = np.asarray(s0, dtype=float)
    if s.shape != (pixels.size,):
        raise ValueError(f"s0 must have shape ({pixels.size},), got {s.shape}")
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(_relative_gradient_sq(s, pixels)) / s


def validity_rows(
    channels: NDArray,
    rows: NDArray,
    pixels: PixelSet,
    cam: CameraModel,
    sigma2: NDArray | float,
    *,
    dop_min: float,
    s0_min: float,
    redundancy_max_sigma: float,
    gradient_max: float | None,
    finite_check: bool = True,
) -> BoolArray:
    """Validity ``(n,)`` of every pixel of the set, all criteria of docs/model.md §7.5
    except the sun, from component-first channels ``(4, n)`` (float) and their
    :func:`stokes_rows`; ``sigma2`` is the channel noise variance [DN^2].
    ``finite_check=False`` when the input was an integer image."""
    s0, s1, s2, nu = rows
    with np.errstate(invalid="ignore"):
        ok = channels.max(axis=0) < cam.saturation_dn  # False for NaN channels
    if finite_check:
        ok &= np.isfinite(rows).all(axis=0)
    with np.errstate(invalid="ignore"):
        ok &= s0 >= s0_min
        if dop_min > 0:
            ok &= s1 * s1 + s2 * s2 >= (dop_min * dop_min) * (s0 * s0)
        ok &= nu * nu <= (redundancy_max_sigma**2) * sigma2
        if gradient_max is not None:
            s0_finite = np.where(np.isfinite(s0), s0, 0.0).astype(s0.dtype) if finite_check else s0
            ok &= _relative_gradient_sq(s0_finite, pixels) < (gradient_max * gradient_max) * (
                s0 * s0
            )
    return ok


def validity_mask(
    raw: ArrayLike,
    cam: CameraModel,
    *,
    sun_c: ArrayLike | None = None,
    sun_exclusion: float = np.radians(10.0),
    dop_min: float = 0.03,
    s0_min_dn: float = 10.0,
    redundancy_max_sigma: float = 4.0,
    gradient_max: float | None = 0.05,
    gain_correction: bool = True,
) -> BoolArray:
    """Valid-pixel mask ``(Hs, Ws)`` of a raw mosaic (docs/model.md §7.5).

    A superpixel is valid when it is inside the field of view and outside the static
    occlusion polygons; no channel is saturated (``>= cam.saturation_dn``) or non-finite;
    S0 >= ``s0_min_dn``; DoP >= ``dop_min``; the redundancy residual is within
    ``redundancy_max_sigma`` noise sigmas; ``|grad S0|/S0 < gradient_max`` [1/superpixel]
    (None: no gradient test); and, if ``sun_c`` (camera frame) is given, it is at least
    ``sun_exclusion`` [rad] from the sun.
    """
    arr = check_raw(raw, cam)
    pixels = pixel_set(cam)
    channels = gather_channels(arr, pixels)
    cal = stokes_calibration(cam, gain_correction)
    rows = stokes_rows(channels, cal, np.float64)
    ok = validity_rows(
        channels,
        rows,
        pixels,
        cam,
        stokes_noise_variance(cam, rows[0]),
        dop_min=dop_min,
        s0_min=s0_min_dn,
        redundancy_max_sigma=redundancy_max_sigma,
        gradient_max=gradient_max,
    )
    if sun_c is not None:
        rays = pixel_rays_c(cam).reshape(-1, 3)[pixels.index]
        s = np.asarray(sun_c, dtype=float)
        ok &= rays @ (s / np.linalg.norm(s)) <= np.cos(sun_exclusion)
    return pixels.to_image(ok, fill=0.0).astype(bool)


# ----------------------------------------------------------------------------- calibration
def polarizer_rotation_slope(
    raws: Iterable[ArrayLike], polarizer_angles: ArrayLike, cam: CameraModel
) -> float:
    """The rotating-polarizer test of docs/model.md §3.4: d(AoP)/d(polarizer angle) [-].

    Image a linear polarizer in front of the lens at increasing angles (turning, as imaged,
    from +u towards +v). With correct channel labels the median AoP follows the polarizer:
    slope +1. A slope of -1 means the 45 and 135 deg channels are swapped (alpha_k -> -alpha_k).

    Parameters
    ----------
    raws : array_like, (m, H, W)
        Raw mosaics, one per polarizer angle (m >= 2).
    polarizer_angles : array_like, (m,)
        Polarizer angles [rad], increasing, steps below 90 deg.
    """
    angles = np.asarray(polarizer_angles, dtype=float)
    images = [check_raw(r, cam) for r in raws]
    if len(images) != angles.size or angles.size < 2:
        raise ValueError("need one raw image per polarizer angle, at least two")
    pixels = pixel_set(cam)
    cal = stokes_calibration(cam)
    doubled = []
    for img in images:
        rows = stokes_rows(gather_channels(img, pixels), cal, np.float64)
        c = np.nanmedian(rows[1] / np.hypot(rows[1], rows[2]))
        s = np.nanmedian(rows[2] / np.hypot(rows[1], rows[2]))
        doubled.append(np.arctan2(s, c))
    zeta = 0.5 * np.unwrap(np.asarray(doubled))
    return float(np.polyfit(angles, zeta, 1)[0])
