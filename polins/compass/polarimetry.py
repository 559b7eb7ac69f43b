"""Polarimetry: raw DoFP mosaic -> four channels -> calibrated Stokes vectors and quality masks,
and the direct-sunlight compensation (SPEC.md sections 6.2, 7 and 8).

Sensor model (SPEC 6.2), channel k with transmission axis alpha_k, gain g_k (the paper's
beta_k), polarization efficiency eta_k and dark offset o_k::

    I_k = g_k/2 [S0 + eta_k (S1 cos 2alpha_k + S2 sin 2alpha_k)] + o_k + n_k

Channel arrays are ordered by the camera model's nominal labels (0, 45, 90, 135 deg for the
IMX250MZR); the mosaic position of each channel is ``cam.channel_at``. Stokes vectors are
``(..., 3)`` = (S0, S1, S2) in the image-plane reference of CONVENTIONS.md (angles from +x_c
towards +y_c); in the ideal case S1 = I0 - I90 and S2 = I45 - I135 (0 deg *minus* 90 deg:
the paper's Eq. 14 has both signs flipped, which turns the AoP by 90 deg).

Performance note: the functions with a leading underscore work on component-first arrays
(``(3, n)``, one contiguous row per Stokes component) because that is what makes the
per-image pipeline of :mod:`polins.compass.measure` fast; the public functions take and return the
library's usual trailing-component layout and call them through transposed views.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from polins.compass.camera import fov_mask
from polins.models.loader import CameraModel

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
IntArray = NDArray[np.intp]

__all__ = [
    "PixelSet",
    "StokesCalibration",
    "aop",
    "check_raw",
    "dop",
    "mosaic_channels",
    "paper_algorithm1",
    "pixel_set",
    "polarizer_rotation_slope",
    "relative_gradient",
    "stokes_calibration",
    "stokes_compensated",
    "stokes_from_channels",
    "stokes_noise_variance",
    "sunlight_direction",
    "sunlight_stokes",
    "unpolarized_intensity",
    "validity_mask",
]


# ----------------------------------------------------------------------------- raw input
def check_raw(raw: ArrayLike, cam: CameraModel) -> NDArray:
    """Validate a raw mosaic: shape ``cam.shape`` and an unsigned-integer or float dtype.

    Float mosaics (e.g. simulated, or dark-corrected by the user) are accepted; their
    non-finite pixels are masked downstream, never propagated.

    Raises
    ------
    ValueError
        Wrong shape or dtype; the message names the expected shape.
    """
    arr = np.asarray(raw)
    if arr.shape != cam.shape:
        raise ValueError(
            f"raw mosaic has shape {arr.shape}; camera {cam.name!r} expects the full-resolution "
            f"mosaic of shape {cam.shape} (H, W), unsigned integer (e.g. uint16)"
        )
    if not (np.issubdtype(arr.dtype, np.unsignedinteger) or np.issubdtype(arr.dtype, np.floating)):
        raise ValueError(
            f"raw mosaic has dtype {arr.dtype}; expected an unsigned integer (e.g. uint16) or a "
            f"float mosaic of shape {cam.shape}"
        )
    return arr


def mosaic_channels(raw: ArrayLike, cam: CameraModel) -> FloatArray:
    """Split a raw mosaic into its four polarizer channels, ``(Hs, Ws, 4)`` [DN].

    Channel ``k`` (ordered by ``cam.nominal_angle_deg``) of superpixel (i, j) is the raw pixel
    at row ``2i + r``, column ``2j + c`` with ``cam.channel_at[r, c] == k``.
    """
    arr = check_raw(raw, cam)
    hs, ws = cam.superpixel_shape
    out = np.empty((hs, ws, 4))
    for r in range(2):
        for c in range(2):
            out[..., cam.channel_at[r, c]] = arr[r::2, c::2]
    return out


@dataclass(frozen=True, eq=False)
class PixelSet:
    """A fixed set of superpixels of one camera, with the indices the fast pipeline needs.

    Attributes
    ----------
    index : (n,) int
        Flat superpixel index ``i * Ws + j``, increasing.
    pair_index : (2, n) int
        Index of the two horizontally adjacent raw pixels of mosaic row r (0, 1) of every
        superpixel, in the raw image viewed as pixel pairs (one gather fetches two channels).
    channel_at : (2, 2) int
        Channel index at mosaic position (row % 2, col % 2), from the camera model.
    right_step : (n - 1,) float32
        1 where position k + 1 is the right neighbour of position k, else 0.
    horizontal_scale : (n,) float32
        1 / (number of horizontal neighbours in the set; 2 for a central difference), 0 if
        none.
    vertical : (n,) int
        Position of the lower neighbour, else of the upper one, else of the pixel itself.
    vertical_step : (n,) float32
        +1 (lower neighbour), -1 (upper) or 0 (none): the one-sided vertical difference is
        ``(s0[vertical] - s0) * vertical_step``.
    """

    shape: tuple[int, int]
    index: IntArray
    pair_index: IntArray
    channel_at: IntArray
    right_step: NDArray[np.float32]
    horizontal_scale: NDArray[np.float32]
    vertical: IntArray
    vertical_step: NDArray[np.float32]

    @property
    def size(self) -> int:
        """Number of superpixels in the set."""
        return int(self.index.size)

    def to_image(self, values: ArrayLike, fill: float = np.nan) -> FloatArray:
        """Scatter per-pixel ``values`` ``(n, ...)`` into a superpixel image ``(Hs, Ws, ...)``."""
        vals = np.asarray(values)
        out = np.full((self.shape[0] * self.shape[1], *vals.shape[1:]), fill, dtype=float)
        out[self.index] = vals
        return out.reshape(*self.shape, *vals.shape[1:])


def _build_pixel_set(cam: CameraModel, mask: BoolArray) -> PixelSet:
    hs, ws = cam.superpixel_shape
    if mask.shape != (hs, ws):
        raise ValueError(f"pixel mask has shape {mask.shape}, expected {(hs, ws)}")
    index = np.flatnonzero(mask)
    i, j = np.divmod(index, ws)
    pair_index = np.stack([(2 * i + r) * ws + j for r in range(2)]).astype(np.intp)
    channel_at = np.array(cam.channel_at, dtype=np.intp)
    position = np.full(hs * ws, -1, dtype=np.intp)
    position[index] = np.arange(index.size)
    own = np.arange(index.size)

    def neighbour(di: int, dj: int) -> IntArray:
        ni, nj = i + di, j + dj
        inside = (ni >= 0) & (ni < hs) & (nj >= 0) & (nj < ws)
        return np.where(inside, position[np.clip(ni, 0, hs - 1) * ws + np.clip(nj, 0, ws - 1)], -1)

    right, left, down, up = neighbour(0, 1), neighbour(0, -1), neighbour(1, 0), neighbour(-1, 0)
    right_step = (right[:-1] == own[:-1] + 1).astype(np.float32)
    count = (right >= 0).astype(np.float32) + (left >= 0)
    horizontal_scale = np.where(count > 0, 1.0 / np.maximum(count, 1), 0.0).astype(np.float32)
    vertical = np.where(down >= 0, down, np.where(up >= 0, up, own))
    vertical_step = np.where(down >= 0, 1.0, np.where(up >= 0, -1.0, 0.0)).astype(np.float32)
    arrays = (index, pair_index, channel_at, right_step, horizontal_scale, vertical, vertical_step)
    for arr in arrays:
        arr.setflags(write=False)
    return PixelSet((hs, ws), *arrays)


@lru_cache(maxsize=8)
def _fov_pixel_set(cam: CameraModel) -> PixelSet:
    return _build_pixel_set(cam, np.asarray(fov_mask(cam)))


def pixel_set(cam: CameraModel, mask: ArrayLike | None = None) -> PixelSet:
    """The superpixels of ``mask`` (default: the camera's field of view and static occlusion
    mask, :func:`polins.compass.camera.fov_mask`, cached per camera)."""
    if mask is None:
        return _fov_pixel_set(cam)
    return _build_pixel_set(cam, np.asarray(mask, dtype=bool))


def _gather(raw: NDArray, pixels: PixelSet, dtype: type = np.float64) -> NDArray:
    """Channel intensities ``(4, n)`` of the set's superpixels, converted to ``dtype``.

    The raw image is viewed as pairs of horizontally adjacent pixels, so two gathers (one
    per mosaic row) fetch all four channels.
    """
    arr = np.ascontiguousarray(raw)
    pairs = arr.view(np.dtype((np.void, 2 * arr.itemsize))).reshape(-1)
    fetched = pairs.take(pixels.pair_index).view(arr.dtype).reshape(2, -1, 2)
    out: NDArray = np.empty((4, pixels.size), dtype=dtype)
    for r in range(2):
        for c in range(2):
            out[pixels.channel_at[r, c]] = fetched[r, :, c]
    return out


# ----------------------------------------------------------------------------- Stokes
@dataclass(frozen=True)
class StokesCalibration:
    """Least-squares Stokes estimator of one camera (SPEC 7.2-7.4).

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
    """The calibrated least-squares Stokes estimator of ``cam`` (SPEC 7.2).

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


def _stokes_rows(channels: NDArray, cal: StokesCalibration, dtype: type = np.float32) -> NDArray:
    """(S0, S1, S2, nu) as ``(4, n)`` rows from channels ``(4, n)`` (component-first)."""
    matrix: NDArray = np.vstack([cal.estimator, cal.null]).astype(dtype)
    # einsum, not BLAS: a threaded gemm of this thin shape stalls on a busy machine.
    out = np.einsum("ij,jn->in", matrix, channels.astype(dtype, copy=False))
    if np.any(cal.offset):
        out -= (matrix @ cal.offset.astype(dtype))[:, None]
    return out


def stokes_from_channels(
    channels: ArrayLike, cam: CameraModel, *, gain_correction: bool = True
) -> tuple[FloatArray, FloatArray]:
    """Calibrated least-squares Stokes vectors and redundancy residuals (SPEC 7.1-7.3).

    Parameters
    ----------
    channels : array_like, (..., 4)
        Channel intensities [DN] (raw, dark offset included), ordered by channel index.
    gain_correction : bool
        Apply the calibrated gains (SPEC 7.2); False is the paper's uncorrected baseline.

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
    rows = _stokes_rows(ch.reshape(-1, 4).T, cal, np.float64)
    return rows[:3].T.reshape(*ch.shape[:-1], 3), rows[3].reshape(ch.shape[:-1])


def stokes_noise_variance(cam: CameraModel, s0: ArrayLike) -> FloatArray | float:
    """Per-channel noise variance sigma^2 [DN^2] at Stokes intensity ``s0`` (SPEC 4):
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
    """Unpolarized intensity ``u = max(S0 - |L|, 0)`` [DN] (SPEC 7.4)."""
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
    """Relative intensity gradient ``|grad S0| / S0`` [1/superpixel] (SPEC 7.5): central
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


def _valid_rows(
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
    """Validity of every pixel of the set, all criteria of SPEC 7.5 except the sun;
    ``channels`` (4, n) float. ``finite_check=False`` when the input was an integer image."""
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
    sun_exclusion_deg: float = 10.0,
    dop_min: float = 0.03,
    s0_min_dn: float = 10.0,
    redundancy_max_sigma: float = 4.0,
    gradient_max: float | None = 0.05,
    gain_correction: bool = True,
) -> BoolArray:
    """Valid-pixel mask ``(Hs, Ws)`` of a raw mosaic (SPEC 7.5).

    A superpixel is valid when it is inside the field of view and outside the static
    occlusion polygons; no channel is saturated (``>= cam.saturation_dn``) or non-finite;
    S0 >= ``s0_min_dn``; DoP >= ``dop_min``; the redundancy residual is within
    ``redundancy_max_sigma`` noise sigmas; ``|grad S0|/S0 < gradient_max`` [1/superpixel]
    (None: no gradient test); and, if ``sun_c`` (camera frame) is given, it is at least
    ``sun_exclusion_deg`` from the sun.
    """
    arr = check_raw(raw, cam)
    pixels = pixel_set(cam)
    channels = _gather(arr, pixels)
    cal = stokes_calibration(cam, gain_correction)
    rows = _stokes_rows(channels, cal, np.float64)
    ok = _valid_rows(
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
        from polins.compass.camera import pixel_rays_c

        rays = pixel_rays_c(cam).reshape(-1, 3)[pixels.index]
        s = np.asarray(sun_c, dtype=float)
        ok &= rays @ (s / np.linalg.norm(s)) <= np.cos(np.radians(sun_exclusion_deg))
    return pixels.to_image(ok, fill=0.0).astype(bool)


# ----------------------------------------------------------------------------- sunlight
def sunlight_direction(sun_c: ArrayLike) -> FloatArray:
    """Doubled-angle direction ``w = -(cos 2alpha_s, sin 2alpha_s)`` ``(..., 2)`` of the
    direct-sunlight pseudo-polarization (SPEC 6.2), ``alpha_s = atan2(s_y, s_x)`` the sun's
    azimuth in the image plane; computed without trigonometry."""
    s = np.asarray(sun_c, dtype=float)
    sx, sy = s[..., 0], s[..., 1]
    rho2 = sx * sx + sy * sy
    if np.any(rho2 <= 0.0):
        raise ValueError("the sun is on the optical axis: its image-plane azimuth is undefined")
    return -np.stack([(sx * sx - sy * sy) / rho2, 2.0 * sx * sy / rho2], axis=-1)


def _sunlight_unpolarized(
    s0: NDArray, s1: NDArray, s2: NDArray, c: NDArray, eps, w, finite: bool = True
) -> NDArray:
    """Exact sky unpolarized intensity u from measured Stokes (SPEC 8.1), any dtype/shape;
    ``c = S0^2 - |L|^2``.

    The discriminant ``B^2 - (1 - 2 eps) C`` is a sum of squares for eps < 1/2 (it equals
    ``(eps S0 - (1 - eps) L.w)^2 + (1 - 2 eps)(|L|^2 - (L.w)^2)``), so its absolute value
    only removes rounding. ``finite=False`` is the fast path for callers that mask
    non-physical pixels themselves: no clean-up of ``S0 <= 0`` pixels and no ``u >= 0``
    clamp (a noisy pixel with DoP > 1 keeps its slightly negative, unbiased u).
    """
    b = s0 * (1.0 - eps)
    b -= eps * (s1 * w[0] + s2 * w[1])
    disc = b * b
    disc -= (1.0 - 2.0 * eps) * c
    np.abs(disc, out=disc)
    np.sqrt(disc, out=disc)
    disc += b
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.divide(c, disc, out=disc)
    if not finite:
        return u
    u = np.nan_to_num(u, nan=0.0, posinf=0.0, neginf=0.0, copy=False)
    return np.maximum(u, 0.0, out=u)


def sunlight_stokes(stokes_sky: ArrayLike, epsilon: float, w: ArrayLike) -> FloatArray:
    """Measured Stokes vectors with the direct-sunlight term added (SPEC 6.2).

    ``S0 - eps u``, ``L + eps u w`` with ``u = S0_sky - |L_sky|`` (the forward model; the
    inverse is :func:`stokes_compensated`).
    """
    s = np.asarray(stokes_sky, dtype=float)
    wv = np.asarray(w, dtype=float)
    u = unpolarized_intensity(s)
    out = s.copy()
    out[..., 0] -= epsilon * u
    out[..., 1] += epsilon * u * wv[..., 0]
    out[..., 2] += epsilon * u * wv[..., 1]
    return out


def stokes_compensated(stokes: ArrayLike, epsilon: float, w: ArrayLike) -> FloatArray:
    """Exact direct-sunlight compensation of measured Stokes vectors (SPEC 8.1).

    Solves ``S0 = p + (1 - eps) u`` and ``|L - eps u w| = p`` for the sky's unpolarized
    intensity ``u`` (physical, numerically stable root), then returns
    ``(S0 + eps u, L - eps u w)``.

    Parameters
    ----------
    stokes : array_like, (..., 3)
        Measured Stokes vectors [DN].
    epsilon : float
        Direct-sunlight coefficient (SPEC 6.2), >= 0 and < 0.5.
    w : array_like, (2,)
        Doubled-angle sunlight direction, :func:`sunlight_direction` of the sun vector.
    """
    if not 0.0 <= epsilon < 0.5:
        raise ValueError(f"epsilon={epsilon} outside [0, 0.5)")
    s = np.asarray(stokes, dtype=float)
    wv = np.asarray(w, dtype=float)
    s0, s1, s2 = s[..., 0], s[..., 1], s[..., 2]
    u = _sunlight_unpolarized(s0, s1, s2, s0 * s0 - s1 * s1 - s2 * s2, epsilon, wv)
    return np.stack([s0 + epsilon * u, s1 - epsilon * u * wv[0], s2 - epsilon * u * wv[1]], -1)


# ----------------------------------------------------------------------------- paper mode
def _paper_rows(
    channels: NDArray,
    cam: CameraModel,
    sun_c_prior: NDArray,
    *,
    eq22: str,
    kc: float,
    gain_final: bool,
    eq14: str,
) -> tuple[NDArray, NDArray]:
    """SPEC 8.2 on component-first channels ``(4, n)``: rows (I_in, s1_hat, s2_hat), k_m."""
    if eq22 not in ("printed", "scale-consistent"):
        raise ValueError(f"paper_eq22={eq22!r}: expected 'printed' or 'scale-consistent'")
    if eq14 not in ("fixed", "printed"):
        raise ValueError(f"paper_eq14={eq14!r}: expected 'fixed' or 'printed'")
    dt = channels.dtype if np.issubdtype(channels.dtype, np.floating) else np.float32
    dark = (channels.astype(dt) - cam.dark_offset_dn.astype(dt)[:, None]).astype(dt)
    beta = cam.gain.astype(dt)[:, None]
    i_hat = dark / beta  # Algorithm 1 step 2
    sign = 1.0 if eq14 == "fixed" else -1.0
    i_in = i_hat[0] + i_hat[2]
    s1 = sign * (i_hat[0] - i_hat[2])
    s2 = sign * (i_hat[1] - i_hat[3])
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.sqrt(s1 * s1 + s2 * s2) / i_in
    sun_azimuth_c = float(np.arctan2(sun_c_prior[1], sun_c_prior[0]))
    p_k = 0.5 * np.cos(sun_azimuth_c - np.pi / 2 - cam.transmission_angle) ** 2  # Eq. 10-11
    p_hat = 0.5 * (1.0 - cam.efficiency[:, None].astype(dt) * d) * (p_k[:, None] - 0.5).astype(dt)
    m = 4.0 if eq22 == "printed" else 2.0
    # Dark pixels (I_in = 0) give non-finite d and k_m; they stay NaN and the masks drop them.
    with np.errstate(invalid="ignore", divide="ignore"):
        k_m = kc * (i_hat.sum(axis=0) - m * i_in) / (i_in * p_hat.sum(axis=0))  # Eq. 22
        corrected = dark - p_hat * (i_in * k_m)  # Eq. 23 (subtracted from the raw intensities)
    if gain_final:
        corrected = corrected / beta
    s1_hat = sign * (corrected[0] - corrected[2])  # Eq. 24
    s2_hat = sign * (corrected[1] - corrected[3])
    return np.stack([i_in, s1_hat, s2_hat]), k_m


def paper_algorithm1(
    channels: ArrayLike,
    cam: CameraModel,
    sun_c_prior: ArrayLike,
    *,
    eq22: str = "scale-consistent",
    kc: float = 20.0,
    gain_final: bool = True,
    eq14: str = "fixed",
) -> tuple[FloatArray, FloatArray]:
    """The paper's Algorithm 1 (Eqs. 14, 10-11, 22-24), reproduction mode of SPEC 8.2.

    **Not for operational use**: the scale-consistent Eq. 22 numerator is identically zero
    for noise-free data (k_m is pure noise, amplified by k_c), and the printed one gives
    k_m ~ 80/(1 - d) and heading errors of about 90 deg (AUDIT 1, Eq. 22).

    Parameters
    ----------
    channels : array_like, (..., 4)
        Raw channel intensities [DN], ordered by channel index (0, 45, 90, 135 deg).
    sun_c_prior : array_like, (3,)
        Sun vector in the camera frame from the *prior* attitude (the paper's Eq. 13,
        evaluated in the image-plane convention of SPEC 3).
    eq22 : {"scale-consistent", "printed"}
        ``m = 2`` or the printed ``m = 4`` in ``k_m = k_c (sum I_k - m I_in)/(I_in sum P_k)``.
    kc : float
        The paper's empirical constant k_c (20).
    gain_final : bool
        Divide the compensated intensities by beta_k (Algorithm 1 as printed: False).
    eq14 : {"fixed", "printed"}
        Stokes sign: fixed (``I0 - I90``) or the paper's printed ``I90 - I0`` (turns the AoP
        by 90 deg).

    Returns
    -------
    stokes : ndarray, (..., 3)
        (I_in, s1_hat, s2_hat) with I_in = I0/beta + I90/beta.
    k_m : ndarray, (...)
        The per-pixel k_m of Eq. 22.
    """
    ch = np.asarray(channels, dtype=float)
    if ch.shape[-1:] != (4,):
        raise ValueError(f"channels must have shape (..., 4), got {ch.shape}")
    rows, k_m = _paper_rows(
        ch.reshape(-1, 4).T,
        cam,
        np.asarray(sun_c_prior, dtype=float),
        eq22=eq22,
        kc=kc,
        gain_final=gain_final,
        eq14=eq14,
    )
    return rows.T.reshape(*ch.shape[:-1], 3), k_m.reshape(ch.shape[:-1])


# ----------------------------------------------------------------------------- calibration
def polarizer_rotation_slope(
    raws: Iterable[ArrayLike], polarizer_angles: ArrayLike, cam: CameraModel
) -> float:
    """The rotating-polarizer test of SPEC 3.4: d(AoP)/d(polarizer angle) [-].

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
        rows = _stokes_rows(_gather(img, pixels), cal, np.float64)
        c = np.nanmedian(rows[1] / np.hypot(rows[1], rows[2]))
        s = np.nanmedian(rows[2] / np.hypot(rows[1], rows[2]))
        doubled.append(np.arctan2(s, c))
    zeta = 0.5 * np.unwrap(np.asarray(doubled))
    return float(np.polyfit(angles, zeta, 1)[0])
