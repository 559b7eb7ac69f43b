"""Polarimetry: four polarizer channels -> calibrated Stokes vectors, and the pixel quality masks.

Sensor model (docs/model.md §6.2), channel k with transmission axis alpha_k, gain g_k (the
paper's beta_k), polarization efficiency eta_k and dark offset o_k::

    I_k = g_k/2 [S0 + eta_k (S1 cos 2alpha_k + S2 sin 2alpha_k)] + o_k + n_k

Channels come from :mod:`polins.compass.pixels`. Stokes vectors are ``(..., 3)`` =
(S0, S1, S2) in the image-plane reference of docs/conventions.md (angles from +x_c towards
+y_c); in the ideal case S1 = I0 - I90 and S2 = I45 - I135 (0 deg *minus* 90 deg: the
paper's Eq. 14 has both signs flipped, which turns the AoP by 90 deg; docs/errata.md §1).

A camera with per-pixel maps (``CameraModel.gain_map``, ``transmission_angle_map``,
``efficiency_map``) gets a per-pixel response ``a_pk`` and per-pixel least-squares rows
(:class:`PixelStokes`, docs/measurement.md §1) for the pixel set it is measured on; a
camera without maps has one constant calibration matrix for all pixels.

The row kernels :func:`stokes_rows` and :func:`validity_rows` work on component-first
arrays (``(k, n)``, one contiguous row per component), the layout of the per-image chain
(:mod:`polins.compass.chain`); :func:`stokes_image` runs them on a raw image, for an
integer mosaic fused into one compiled pass (:func:`polins.compass.stokes_kernels.stokes_pass`,
bit-identical). The other public functions take and return the library's
trailing-component layout.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from polins.compass.camera import pixel_rays_c
from polins.compass.kernels import compiled
from polins.compass.pixels import PixelSet, check_raw, gather_channels, pixel_set
from polins.models import CameraModel

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

__all__ = [
    "PixelStokes",
    "StokesCalibration",
    "StokesImage",
    "aop",
    "dop",
    "pixel_stokes",
    "polarizer_rotation_slope",
    "relative_gradient",
    "stokes_calibration",
    "stokes_from_channels",
    "stokes_image",
    "stokes_noise_variance",
    "stokes_rows",
    "unpolarized_intensity",
    "validity_mask",
    "validity_rows",
]


# ----------------------------------------------------------------------------- Stokes
@dataclass(frozen=True, eq=False)
class PixelStokes:
    """Per-pixel least-squares Stokes rows of a camera with per-pixel maps, on a pixel set.

    Pixel p responds ``I_pk = a_pk . S_p + o_k`` with
    ``a_pk = g_pk/2 [1, eta_pk cos 2alpha_pk, eta_pk sin 2alpha_pk]`` (the maps, or the
    channel values where a map is absent or NaN); its rows are the least-squares estimator
    ``B_p = (A_p^T A_p)^-1 A_p^T`` (= ``pinv(A_p)``) and the unit null vector of ``A_p^T``
    (docs/measurement.md §1).

    Attributes
    ----------
    matrix : (4, 4, n) float64
        Rows (S0, S1, S2, nu) of every pixel, component-first: ``matrix[i, k, p]``.
    offset_rows : (4, n) float64
        ``matrix_p @ o``: what the dark offsets contribute to each row [DN].
    sigma_l_factor : (n,) float64
        sigma_L / sigma of each pixel.
    """

    matrix: FloatArray
    offset_rows: FloatArray
    sigma_l_factor: FloatArray

    @cached_property
    def _float32(self) -> tuple[NDArray, NDArray]:
        return self.matrix.astype(np.float32), self.offset_rows.astype(np.float32)

    def arrays(self, dtype: type) -> tuple[NDArray, NDArray]:
        """``(matrix, offset_rows)`` in ``dtype`` (the float32 copies are made once)."""
        if np.dtype(dtype) == np.float32:
            return self._float32
        return self.matrix.astype(dtype, copy=False), self.offset_rows.astype(dtype, copy=False)


def pixel_stokes(cam: CameraModel, index: ArrayLike, gain_correction: bool = True) -> PixelStokes:
    """The per-pixel Stokes rows of ``cam`` at flat superpixel indices ``index`` ``(n,)``
    (``i * Ws + j``), from its per-pixel maps (NaN entries and absent maps: the channel
    values). ``gain_correction=False`` sets every gain to 1 (the uncorrected baseline)."""
    idx = np.asarray(index, dtype=np.intp)
    g, alpha, eta = (m.reshape(-1, 4)[idx] for m in cam.pixel_calibration())
    if not gain_correction:
        g = np.ones_like(g)
    two_a = 2.0 * alpha
    a = (
        0.5
        * g[..., None]
        * np.stack([np.ones_like(g), eta * np.cos(two_a), eta * np.sin(two_a)], -1)
    )  # (n, 4, 3)
    cov = np.linalg.inv(np.einsum("nki,nkj->nij", a, a))  # (A^T A)^-1, (n, 3, 3)
    b = np.einsum("nij,nkj->nik", cov, a)  # (n, 3, 4): pinv(A_p) for full column rank
    at = a.transpose(0, 2, 1)  # (n, 3, 4)
    # Null vector of A^T: the signed 3x3 minors (a generalised cross product of its rows).
    null = np.stack([(-1.0) ** j * np.linalg.det(np.delete(at, j, axis=2)) for j in range(4)], -1)
    null /= np.linalg.norm(null, axis=1, keepdims=True)
    null *= np.where(null[:, :1] < 0, -1.0, 1.0)
    matrix = np.ascontiguousarray(np.concatenate([b, null[:, None, :]], axis=1).transpose(1, 2, 0))
    offset_rows = np.einsum("ikn,k->in", matrix, cam.dark_offset_dn)
    sigma_l = np.sqrt(0.5 * (cov[:, 1, 1] + cov[:, 2, 2]))
    return PixelStokes(matrix, offset_rows, sigma_l)


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
    pixel : PixelStokes or None
        Per-pixel rows on the pixel set the calibration was made for, when the camera has
        per-pixel maps (the fields above then hold the channel values' estimator).
    """

    response: FloatArray
    estimator: FloatArray
    null: FloatArray
    covariance: FloatArray
    sigma_l_factor: float
    offset: FloatArray
    pixel: PixelStokes | None = None

    def sigma_l_factors(self) -> FloatArray | float:
        """sigma_L / sigma: per pixel ``(n,)`` with per-pixel maps, else one number."""
        return self.sigma_l_factor if self.pixel is None else self.pixel.sigma_l_factor


def stokes_calibration(
    cam: CameraModel, gain_correction: bool = True, pixels: PixelSet | None = None
) -> StokesCalibration:
    """The calibrated least-squares Stokes estimator of ``cam`` (docs/model.md §7.2).

    Parameters
    ----------
    gain_correction : bool
        False ignores the channel gains (g_k = 1): the paper's uncorrected baseline.
    pixels : PixelSet, optional
        The pixel set the rows will be applied to. With it, a camera with per-pixel maps
        gets per-pixel rows (``pixel``, cached per camera and set); without it, or without
        maps, the channel values' one matrix.
    """
    channel = _channel_calibration(cam, gain_correction)
    if pixels is None or not cam.has_pixel_maps:
        return channel
    return _pixel_calibration(cam, gain_correction, pixels)


@lru_cache(maxsize=8)
def _pixel_calibration(
    cam: CameraModel, gain_correction: bool, pixels: PixelSet
) -> StokesCalibration:
    channel = _channel_calibration(cam, gain_correction)
    return dataclasses.replace(channel, pixel=pixel_stokes(cam, pixels.index, gain_correction))


@lru_cache(maxsize=4)
def _image_calibration(cam: CameraModel, gain_correction: bool) -> StokesCalibration:
    """Per-pixel rows of every superpixel of the image (row-major)."""
    channel = _channel_calibration(cam, gain_correction)
    every = np.arange(cam.superpixel_shape[0] * cam.superpixel_shape[1])
    return dataclasses.replace(channel, pixel=pixel_stokes(cam, every, gain_correction))


@lru_cache(maxsize=16)
def _channel_calibration(cam: CameraModel, gain_correction: bool) -> StokesCalibration:
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
    (docs/model.md §7.2-7.3): the least-squares estimate and the redundancy residual.
    With per-pixel rows (``cal.pixel``) the channels must be those of its pixel set."""
    if cal.pixel is not None:
        pix_matrix, pix_offset = cal.pixel.arrays(dtype)
        if channels.shape[1:] != pix_offset.shape[1:]:
            raise ValueError(
                f"channels of {channels.shape[1]} pixels for per-pixel rows of "
                f"{pix_offset.shape[1]}: use the pixel set the calibration was made for"
            )
        pix_out = np.einsum("ikn,kn->in", pix_matrix, channels.astype(dtype, copy=False))
        pix_out -= pix_offset
        return pix_out
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
    if not cam.has_pixel_maps:
        cal = _channel_calibration(cam, gain_correction)
        rows = stokes_rows(ch.reshape(-1, 4).T, cal, np.float64)
        return rows[:3].T.reshape(*ch.shape[:-1], 3), rows[3].reshape(ch.shape[:-1])
    image = (*cam.superpixel_shape, 4)
    if ch.shape[-3:] != image:
        raise ValueError(
            f"camera {cam.name!r} has per-pixel maps: channels must be whole superpixel images "
            f"(..., {image[0]}, {image[1]}, 4), got {ch.shape}; or use cam.without_pixel_maps()"
        )
    cal = _image_calibration(cam, gain_correction)
    per_image = ch.reshape(-1, image[0] * image[1], 4)
    rows = np.stack([stokes_rows(c.T, cal, np.float64) for c in per_image])  # (m, 4, n)
    stokes = rows[:, :3].transpose(0, 2, 1).reshape(*ch.shape[:-1], 3)
    return stokes, rows[:, 3].reshape(ch.shape[:-1])


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


@dataclass(frozen=True, eq=False)
class StokesImage:
    """Stokes rows and the sun-independent validity of a raw image's pixel set.

    Attributes
    ----------
    rows : (4, n)
        (S0, S1, S2, nu) [DN] (:func:`stokes_rows`).
    sigma2 : (n,) or float
        Channel noise variance [DN^2] (:func:`stokes_noise_variance`).
    valid : (n,) bool
        :func:`validity_rows`.
    unsaturated : (n,) bool
        No channel at or above the saturation level (False for a non-finite channel).
    channels : (4, n) or None
        The channels [DN], when asked for.
    """

    rows: NDArray
    sigma2: NDArray | float
    valid: BoolArray
    unsaturated: BoolArray
    channels: NDArray | None


def stokes_image(
    raw: NDArray,
    pixels: PixelSet,
    cam: CameraModel,
    cal: StokesCalibration,
    *,
    s0_min: float,
    redundancy_max_sigma: float,
    gradient_max: float | None,
    dop_min: float = 0.0,
    channels: bool = False,
) -> StokesImage:
    """:func:`gather_channels`, :func:`stokes_rows`, :func:`stokes_noise_variance` and
    :func:`validity_rows` (``finite_check`` for float mosaics) of a raw mosaic, already
    checked with :func:`polins.compass.pixels.check_raw`, on ``pixels`` (docs/model.md §7).

    An unsigned-integer mosaic is processed in float32 by one compiled pass
    (:func:`polins.compass.stokes_kernels.stokes_pass`: the same numbers), which reads the mosaic
    once instead of writing and re-reading the channels and the rows (docs/measurement.md
    §10); a float mosaic in float64 by the numpy row kernels. ``channels`` also returns
    the channels ``(4, n)`` [DN].
    """
    integer = not np.issubdtype(raw.dtype, np.floating)
    dtype = np.float32 if integer else np.float64
    if integer:
        if cal.pixel is not None:
            matrix, offset = cal.pixel.arrays(np.float32)  # (4, 4, n), (4, n)
            if offset.shape[1] != pixels.size:
                raise ValueError("per-pixel Stokes rows of another pixel set")
        else:
            constant = np.vstack([cal.estimator, cal.null]).astype(np.float32)
            offset = np.zeros((4, 1), np.float32)
            if np.any(cal.offset):
                offset = (constant @ cal.offset.astype(np.float32))[:, None]
            matrix = constant[:, :, None]
        shot = np.isfinite(cam.conversion_gain_e_per_dn)
        noise = np.array([cam.read_noise_dn**2, 0.5 * float(np.mean(cam.gain)),
                          cam.conversion_gain_e_per_dn, float(shot)])  # fmt: skip
        grad2 = -1.0 if gradient_max is None else gradient_max * gradient_max
        limits = np.array([cam.saturation_dn, s0_min, redundancy_max_sigma**2,
                           dop_min * dop_min, grad2])  # fmt: skip
        n = pixels.size
        rows = np.empty((4, n), np.float32)
        sigma2_px = np.empty(n if shot else 0)
        valid = np.empty(n, bool)
        unsaturated = np.empty(n, bool)
        chan = np.empty((4, n if channels else 0), np.float32)
        position = np.argsort(np.asarray(pixels.channel_at).ravel())  # channel -> 2 r + c
        native = np.ascontiguousarray(raw, dtype=raw.dtype.newbyteorder("="))
        compiled("stokes_pass")(native, pixels.runs, position, matrix,
                                offset, limits, noise, pixels.vertical, rows, sigma2_px, valid,
                                unsaturated, chan)  # fmt: skip
        sigma2: NDArray | float = sigma2_px
        if not shot:  # one number (read noise only), as stokes_noise_variance gives it
            sigma2 = float(stokes_noise_variance(cam, 0.0))
        return StokesImage(rows, sigma2, valid, unsaturated, chan if channels else None)
    chan = gather_channels(raw, pixels, dtype)
    rows = stokes_rows(chan, cal, dtype)
    sigma2 = stokes_noise_variance(cam, rows[0])
    valid = validity_rows(chan, rows, pixels, cam, sigma2, dop_min=dop_min, s0_min=s0_min,
                          redundancy_max_sigma=redundancy_max_sigma, gradient_max=gradient_max,
                          finite_check=not integer)  # fmt: skip
    with np.errstate(invalid="ignore"):
        unsaturated = chan.max(axis=0) < cam.saturation_dn
    return StokesImage(rows, sigma2, valid, unsaturated, chan if channels else None)


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
    cal = stokes_calibration(cam, gain_correction, pixels)
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
    cal = stokes_calibration(cam, True, pixels)
    doubled = []
    for img in images:
        rows = stokes_rows(gather_channels(img, pixels), cal, np.float64)
        c = np.nanmedian(rows[1] / np.hypot(rows[1], rows[2]))
        s = np.nanmedian(rows[2] / np.hypot(rows[1], rows[2]))
        doubled.append(np.arctan2(s, c))
    zeta = 0.5 * np.unwrap(np.asarray(doubled))
    return float(np.polyfit(angles, zeta, 1)[0])
