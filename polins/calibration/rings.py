"""Ring means of a sky seen while turning: windows about the turn axis, turns, the sun's motion.

The data side of the sky-rotation calibration (:mod:`polins.calibration.sky_rotation`,
docs/calibrate.md#sky-rotation): within a ring of pixels centred on the turn axis the
camera sees the same directions of the sky in every image, only turned, so each ring's
mean channels are a polarized source turning in front of the channels.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from polins.calibration.images import centred_channels, channel_stack
from polins.calibration.malus import base_stokes
from polins.compass.camera import doubled_aop_from_evector, fov_mask, pixel_rays_c
from polins.errors import UserInputError
from polins.models import CameraModel
from polins.site import Site, TimeLike, to_utc_index
from polins.sky.ephemeris import sun_position, sun_vector_n
from polins.sky.scattering import rayleigh_dop, rayleigh_evector

FloatArray = NDArray[np.float64]

__all__ = [
    "RingData",
    "normalised_radius2",
    "polarization_turns",
    "ring_data",
    "ring_sun_factors",
    "ring_windows",
    "sun_motion_factors",
    "turns_modulo_2pi",
]


def ring_windows(cam: CameraModel, n_rings: int) -> tuple[FloatArray, FloatArray]:
    """Smooth ring windows ``(R, Hs, Ws)`` [-] about the principal point and their centres ``(R,)``.

    Window r is ``cos^2(pi/2 (rho - r D)/D)`` for ``|rho - r D| < D``, in the normalised radius
    ``rho = hypot((u - cx)/fx, (v - cy)/fy)`` (a turn about the optical axis turns normalised
    coordinates rigidly); neighbouring windows sum to one. Smooth windows make the
    pixel-grid sum of a smooth sky nearly independent of the turn, where sharp ring edges
    would not. The last window ends at the field-of-view limit or at the largest circle
    inside the image, whichever is smaller.
    """
    hs, ws = cam.superpixel_shape
    fx, fy = cam.camera_matrix[0, 0], cam.camera_matrix[1, 1]
    cx, cy = cam.camera_matrix[0, 2], cam.camera_matrix[1, 2]
    v, u = np.mgrid[0:hs, 0:ws].astype(float)
    rho = np.hypot((u - cx) / fx, (v - cy) / fy)
    outside = rho[~fov_mask(cam)]
    rho_max = min(
        float(outside.min()) if outside.size else np.inf,
        (cx + 0.5) / fx,
        (ws - 0.5 - cx) / fx,
        (cy + 0.5) / fy,
        (hs - 0.5 - cy) / fy,
    )
    step = rho_max / n_rings
    centres = step * np.arange(n_rings)
    x = (rho[None] - centres[:, None, None]) / step
    windows = np.where(np.abs(x) < 1.0, np.cos(0.5 * np.pi * x) ** 2, 0.0)
    return windows, centres


def normalised_radius2(cam: CameraModel) -> FloatArray:
    """Squared normalised radius ``((u - cx)/fx)^2 + ((v - cy)/fy)^2`` [-] of every superpixel
    ``(Hs, Ws)``."""
    hs, ws = cam.superpixel_shape
    v, u = np.mgrid[0:hs, 0:ws].astype(float)
    k = cam.camera_matrix
    return np.asarray(((u - k[0, 2]) / k[0, 0]) ** 2 + ((v - k[1, 2]) / k[1, 1]) ** 2)


def turns_modulo_2pi(signal: FloatArray, weight: FloatArray, cam: CameraModel) -> FloatArray:
    """Pattern turns ``theta_j = -phi_j`` [rad] modulo 2 pi, relative to the first image.

    The polarization gives the turns modulo pi only. The first azimuthal harmonic of the
    DoP within each ring tells the sun's side of the sky from the antisun's: pixel azimuth
    ``psi`` in image j sees the world azimuth ``psi + phi_j``, so the harmonic turns by
    ``exp(i phi_j)``.

    Parameters
    ----------
    signal : (m, n, 4)
        Dark-subtracted channels of the superpixels [DN].
    weight : (R, n)
        Ring windows [-].
    cam : CameraModel
        Base camera (channel model and principal point).
    """
    stokes = base_stokes(signal, cam)  # (m, n, 3)
    with np.errstate(invalid="ignore", divide="ignore"):
        dop = np.nan_to_num(np.hypot(stokes[..., 1], stokes[..., 2]) / stokes[..., 0])
    hs, ws = cam.superpixel_shape
    v, u = np.mgrid[0:hs, 0:ws].astype(float)
    azimuth = np.arctan2(
        (v - cam.camera_matrix[1, 2]) / cam.camera_matrix[1, 1],
        (u - cam.camera_matrix[0, 2]) / cam.camera_matrix[0, 0],
    ).ravel()
    first = np.einsum("rn,mn->mr", weight, dop * np.exp(-1j * azimuth))  # (m, R)
    return np.asarray(-np.angle((first * np.conj(first[:1])).sum(axis=1)), dtype=float)


def sun_motion_factors(
    cam: CameraModel, weight: FloatArray, sun_n: ArrayLike, axis_n: ArrayLike = (0.0, 0.0, 1.0)
) -> NDArray[np.complex128]:
    """Change of each ring's mean linear polarization as the sun moves, ``(m, R)`` complex.

    A Rayleigh sky (``polins.sky.scattering``) seen through ``cam`` with its optical axis
    on the turn axis ``axis_n``: the ring means ``L_jr = sum_n w_rn d_jn exp(2i zeta_jn)``
    [-] of the degree and angle of polarization for the sun of image j (normalised by
    ``sum_n w_rn``), relative to the first image's (``f_jr = L_jr / L_0r``; 1 where that is
    below 1% DoP).
    The turn of the sky about the axis (the sun's azimuth) makes a common phase, which
    the fitted turns take; the change that matters is the sun's angle from the axis. (The
    direct-sunlight term of docs/model.md §6.2 is not modelled: it leaves a residual.)

    Parameters
    ----------
    cam : CameraModel
        Camera (lens projection and polarization model).
    weight : (R, n)
        Ring windows over the superpixels (:func:`ring_windows`, flattened).
    sun_n : array_like, (m, 3)
        Unit sun vector of each image, ENU.
    axis_n : array_like, (3,)
        The turn axis (the optical axis) in ENU; default the zenith.
    """
    axis = np.asarray(axis_n, dtype=float)
    axis = axis / np.linalg.norm(axis)
    ref = np.array([0.0, 1.0, 0.0]) if abs(axis[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(ref, axis)
    x /= np.linalg.norm(x)
    mat_an = np.stack([x, np.cross(axis, x), axis])  # rows: the axis frame's axes in ENU
    sun_a = np.asarray(sun_n, dtype=float) @ mat_an.T  # (m, 3)
    rays = np.nan_to_num(pixel_rays_c(cam).reshape(-1, 3))  # the camera at turn 0
    with np.errstate(invalid="ignore", divide="ignore"):
        evec = rayleigh_evector(sun_a[:, None, :], rays[None])  # (m, n, 3)
        aop2 = np.nan_to_num(doubled_aop_from_evector(evec, rays[None], cam.polarization_model))
    dop = np.nan_to_num(rayleigh_dop(sun_a[:, None, :], rays[None], 1.0))
    ring = (dop * (aop2[..., 0] + 1j * aop2[..., 1])) @ weight.T / weight.sum(axis=1)  # (m, R)
    usable = np.abs(ring[0]) > 0.01  # a ring mean of 1% DoP or more
    return np.where(usable[None, :], ring / np.where(usable, ring[0], 1.0)[None, :], 1.0)


def polarization_turns(y: FloatArray, cam: CameraModel) -> FloatArray:
    """Pattern turns ``theta_j`` [rad] modulo pi, relative to the first image, from the ring
    means' angle of polarization under the base camera ``(m, R, 4)`` -> ``(m,)``.

    Model-free (no channel fit): channel gain and angle errors bias each turn by up to
    about 1-2 deg at the second harmonic of the turn, which makes it the start of the fit
    and the measure of the span the images cover.
    """
    stokes = base_stokes(y, cam)
    lin = stokes[..., 1] + 1j * stokes[..., 2]
    return np.asarray(0.5 * np.angle((lin * np.conj(lin[:1])).sum(axis=1)), dtype=float)


@dataclass(frozen=True)
class RingData:
    """Ring means of a sequence and what the fits need of them."""

    y: FloatArray  # (m, R, 4) [DN]
    sigma: FloatArray  # (m, R, 4) [DN]
    weight: FloatArray  # (R, n)
    radius: FloatArray  # (R,)
    signal: FloatArray  # (m, n, 4) [DN]
    radius2: FloatArray | None  # (R,) the windows' mean squared normalised radius [-]; None:
    # no radial shading fitted
    pixel_radius2: FloatArray  # (Hs, Ws) squared normalised radius of each superpixel [-]


def ring_data(
    raws: Sequence[ArrayLike] | ArrayLike, cam: CameraModel, n_rings: int, ifov_correction: bool
) -> RingData:
    """The ring means of the raw images ``raws`` under ``cam`` over ``n_rings`` windows
    (:func:`ring_windows`), rings holding a saturated superpixel in any image dropped, with
    their noise model (read and shot noise over the window's effective pixel count);
    ``ifov_correction`` interpolates the channels to the superpixel centres first."""
    stack = channel_stack(raws, cam, min_images=4, what="sky-rotation")
    windows, centres = ring_windows(cam, n_rings)
    channels = centred_channels(stack.channels, cam) if ifov_correction else stack.channels
    m = stack.n_images
    signal = (channels - cam.dark_offset_dn).reshape(m, -1, 4)
    weight = windows.reshape(n_rings, -1)  # (R, n)
    saturated = stack.saturated.any(axis=0).ravel()
    keep = np.flatnonzero(~np.any((weight > 0) & saturated, axis=1) & (weight.sum(axis=1) >= 8))
    if keep.size < 2:
        raise UserInputError(
            "sky-rotation: fewer than two rings free of saturation in the field of view"
        )
    weight = weight[keep]
    norm = weight.sum(axis=1)  # (R,)
    y = np.einsum("rn,mnk->mrk", weight, signal) / norm[None, :, None]
    n_eff = norm**2 / (weight**2).sum(axis=1)  # effective number of pixels of a window
    var_pix = cam.read_noise_dn**2 + (
        np.maximum(y, 0.0) / cam.conversion_gain_e_per_dn
        if np.isfinite(cam.conversion_gain_e_per_dn)
        else 0.0
    )
    sigma = np.broadcast_to(np.sqrt(var_pix / n_eff[None, :, None]), y.shape)
    rho2 = normalised_radius2(cam)
    radius2 = weight @ rho2.ravel() / norm
    return RingData(y, np.array(sigma), weight, centres[keep], signal, radius2, rho2)


def ring_sun_factors(
    cam: CameraModel, weight: FloatArray, m: int, times_utc: TimeLike | None,
    site: Site | None, axis_n: ArrayLike,
) -> NDArray[np.complex128] | None:  # fmt: skip
    """:func:`sun_motion_factors` for ``m`` images taken at ``times_utc`` at ``site`` (both or
    neither: None without the clock)."""
    if (times_utc is None) != (site is None):
        raise UserInputError("sky-rotation: the sun's motion needs both times_utc and site")
    if times_utc is None or site is None:
        return None
    times = to_utc_index(times_utc)
    if times.size != m:
        raise UserInputError(
            f"sky-rotation: times_utc needs {m} timezone-aware times (one per image), got "
            f"{times.size}"
        )
    sun = sun_position(times, site.lat_deg, site.lon_deg, site.alt_m)
    return sun_motion_factors(cam, weight, sun_vector_n(sun.azimuth, sun.zenith), axis_n)
