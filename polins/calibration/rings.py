"""Ring means of a sky seen while turning: windows about the turn axis, turns, the sun's motion.

The data side of the sky-rotation calibration (:mod:`polins.calibration.sky_rotation`,
docs/calibrate.md#sky-rotation): within a ring of pixels centred on the turn axis the
camera sees the same directions of the sky in every image, only turned, so each ring's
mean channels are a polarized source turning in front of the channels.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

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

OPTICAL_AXIS_C = (0.0, 0.0, 1.0)
AXIS_PIXELS = 300_000  # the turn axis is found on about this many superpixels [-]
AXIS_ITERATIONS = 3  # Gauss-Newton steps of the turn axis from the optical axis
AXIS_STEP = 1e-3  # finite-difference step of the axis tilt [rad]
AXIS_SIGNIFICANT = 3.0  # a tilt of the turn axis below this many standard errors: none
AXIS_STEP_MAX = float(np.radians(1.0))  # largest Gauss-Newton step of the axis tilt [rad]
AXIS_TILT_MAX = float(np.radians(5.0))  # a turn axis found further from the optical axis
# than this [rad] is no turn axis: the rings stay on the optical axis

__all__ = [
    "RingData",
    "normalised_radius2",
    "on_turn_axis",
    "polarization_turns",
    "radius_about",
    "ring_data",
    "ring_sun_factors",
    "ring_windows",
    "sun_motion_factors",
    "turn_axis_c",
    "turns_modulo_2pi",
]


def ring_windows(
    cam: CameraModel, n_rings: int, axis_c: ArrayLike = OPTICAL_AXIS_C
) -> tuple[FloatArray, FloatArray]:
    """Smooth ring windows ``(R, Hs, Ws)`` [-] about the turn axis and their centres ``(R,)``.

    Window r is ``cos^2(pi/2 (rho - r D)/D)`` for ``|rho - r D| < D``, in the radius ``rho``
    about the turn axis ``axis_c`` (:func:`radius_about`: on the optical axis, the normalised
    radius ``hypot((u - cx)/fx, (v - cy)/fy)``, which a turn about the optical axis turns
    rigidly); neighbouring windows sum to one. Smooth windows make the pixel-grid sum of a
    smooth sky nearly independent of the turn, where sharp ring edges would not. The last
    window ends at the field-of-view limit or at the largest circle inside the image,
    whichever is smaller.
    """
    rho, rho_max = radius_about(cam, axis_c)
    return _windows(rho, rho_max, n_rings)


def _windows(rho: FloatArray, rho_max: float, n_rings: int) -> tuple[FloatArray, FloatArray]:
    """The windows of :func:`ring_windows` over the radii ``rho`` (any shape) [-]."""
    step = rho_max / n_rings
    centres = np.asarray(step * np.arange(n_rings), dtype=float)
    x = np.minimum(np.abs(rho[None] - centres.reshape((-1,) + (1,) * rho.ndim)) / step, 1.0)
    return np.asarray(np.cos(0.5 * np.pi * x) ** 2 * (x < 1.0), dtype=float), centres


def radius_about(cam: CameraModel, axis_c: ArrayLike = OPTICAL_AXIS_C) -> tuple[FloatArray, float]:
    """Radius ``(Hs, Ws)`` [-] of every superpixel about the turn axis ``axis_c`` (camera
    frame), and the largest radius whose circle stays in the image and the field of view.

    The radius is the angle ``beta`` between the superpixel's ray and the axis, expressed in
    the lens's own radial scale: the normalised radius ``rho(theta)`` a ray at field angle
    ``theta = beta`` has. About the optical axis it is the normalised radius itself; about a
    tilted axis its circles are the cones about that axis, which a turn about it keeps
    (docs/calibrate.md#sky-rotation). Rays the lens model cannot invert are at infinity.
    """
    hs, ws = cam.superpixel_shape
    k = cam.camera_matrix
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    v, u = np.mgrid[0:hs, 0:ws].astype(float)
    rho = np.hypot((u - cx) / fx, (v - cy) / fy)
    axis = np.asarray(axis_c, dtype=float)
    axis = axis / np.linalg.norm(axis)
    offset = 0.0
    if not np.allclose(axis, OPTICAL_AXIS_C, rtol=0.0, atol=1e-12):
        rays = pixel_rays_c(cam)
        valid = np.isfinite(rays[..., 2])
        theta = np.arccos(np.clip(rays[..., 2][valid], -1.0, 1.0))
        order = np.argsort(theta)
        profile_theta, profile_rho = theta[order], rho[valid][order]
        beta = np.arccos(np.clip(np.nan_to_num(rays @ axis, nan=-1.0), -1.0, 1.0))
        rho = np.where(valid, np.interp(beta, profile_theta, profile_rho, right=np.inf), np.inf)
        offset = float(np.interp(np.arccos(axis[2]), profile_theta, profile_rho))
    outside = rho[~fov_mask(cam)]
    rho_max = min(
        float(outside.min()) if outside.size else np.inf,
        (cx + 0.5) / fx - offset,
        (ws - 0.5 - cx) / fx - offset,
        (cy + 0.5) / fy - offset,
        (hs - 0.5 - cy) / fy - offset,
    )
    return np.asarray(rho, dtype=float), float(rho_max)


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
    saturated: NDArray[np.bool_]  # (n,) superpixels saturated in any image
    n_rings: int  # windows laid out, before those with saturation were dropped
    correlation: FloatArray  # (R, R) of the ring means' noise (overlapping windows)
    axis_c: FloatArray = field(default_factory=lambda: np.array(OPTICAL_AXIS_C))  # (3,) the
    # turn axis the rings are centred on, camera frame
    axis_tilt_std: float = 0.0  # standard error of its tilt from the optical axis [rad]


def ring_data(
    raws: Sequence[ArrayLike] | ArrayLike, cam: CameraModel, n_rings: int, ifov_correction: bool
) -> RingData:
    """The ring means of the raw images ``raws`` under ``cam`` over ``n_rings`` windows about
    the optical axis (:func:`ring_windows`), rings holding a saturated superpixel in any image
    dropped, with their noise model (read and shot noise over the window's effective pixel
    count); ``ifov_correction`` interpolates the channels to the superpixel centres first."""
    stack = channel_stack(raws, cam, min_images=4, what="sky-rotation")
    channels = centred_channels(stack.channels, cam) if ifov_correction else stack.channels
    signal = (channels - cam.dark_offset_dn).reshape(stack.n_images, -1, 4)
    saturated = stack.saturated.any(axis=0).ravel()
    return _ring_means(signal, saturated, cam, n_rings, np.array(OPTICAL_AXIS_C), 0.0)


def on_turn_axis(data: RingData, cam: CameraModel) -> RingData:
    """``data`` with its rings centred on the turn axis found from the images
    (:func:`turn_axis_c`; unchanged when none is found off the optical axis)."""
    n_rings = data.n_rings
    axis_c, tilt_std = turn_axis_c(data.signal, cam, n_rings, data.saturated)
    if axis_c[2] == 1.0:
        return replace(data, axis_tilt_std=tilt_std)
    out = _ring_means(data.signal, data.saturated, cam, n_rings, axis_c, tilt_std)
    return out if data.radius2 is not None else replace(out, radius2=None)


def _ring_means(
    signal: FloatArray, saturated: NDArray[np.bool_], cam: CameraModel, n_rings: int,
    axis_c: FloatArray, tilt_std: float,
) -> RingData:  # fmt: skip
    """The :class:`RingData` of dark-subtracted channels ``signal`` (m, n, 4) [DN] over
    ``n_rings`` windows about ``axis_c``."""
    windows, centres = ring_windows(cam, n_rings, axis_c)
    weight = windows.reshape(n_rings, -1)  # (R, n)
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
    overlap = weight @ weight.T
    correlation = overlap / np.sqrt(np.outer(np.diag(overlap), np.diag(overlap)))
    return RingData(y, np.array(sigma), weight, centres[keep], signal, radius2, rho2, saturated,
                    n_rings, correlation, axis_c, tilt_std)  # fmt: skip


def turn_axis_c(
    signal: FloatArray, cam: CameraModel, n_rings: int, saturated: NDArray[np.bool_]
) -> tuple[FloatArray, float]:
    """The turn axis ``(3,)`` in the camera frame, found from the images, and the standard
    error [rad] of its tilt from the optical axis.

    About the turn axis every ring of directions sees the same sky in every image, only
    turned, so each ring's mean degree of polarization is the same in all images (the DoP
    is free of the exposure, the vignetting and the frame of the angles). Rings about a
    point off the axis see the sky's DoP gradient precess with the turn. Gauss-Newton on
    the axis's tilt (two components, finite differences of the ring-mean DoP) minimises
    the ring means' spread over the images, on at most about ``AXIS_PIXELS`` superpixels
    (the DoP under the base camera; pixels saturated in any image left out). The optical
    axis is kept unless the tilt found exceeds ``AXIS_SIGNIFICANT`` standard errors: the
    rings about an axis tilted from the optical one differ from those about it at the
    second order of the tilt, which the first-order tilt terms of the Malus fit cannot
    take (a 0.5 deg tilt biases the channel angles by up to 0.04 deg near a high sun;
    docs/calibrate.md#sky-rotation).
    """
    hs, ws = cam.superpixel_shape
    stride = max(1, int(np.sqrt(hs * ws / AXIS_PIXELS)))
    sub = np.zeros((hs, ws), dtype=bool)
    sub[::stride, ::stride] = True
    use = np.flatnonzero(sub.ravel() & ~saturated & fov_mask(cam).ravel())
    stokes = base_stokes(signal[:, use], cam)  # (m, p, 3)
    s0 = stokes[..., 0]
    good = np.all(s0 > 0.0, axis=0)
    use, stokes = use[good], stokes[:, good]
    dop = np.hypot(stokes[..., 1], stokes[..., 2]) / stokes[..., 0]  # (m, p)

    sat = np.flatnonzero(saturated)
    rho, rho_max = radius_about(cam, OPTICAL_AXIS_C)
    w0, centres = _windows(rho.ravel()[use], rho_max, n_rings)
    # Rings near a saturated superpixel (the sun) are left out, with a margin for the tilt.
    near_sun = np.abs(rho.ravel()[sat][None] - centres[:, None]) < 1.25 * rho_max / n_rings
    rings = np.flatnonzero((w0.sum(axis=1) >= 8) & ~near_sun.any(axis=1))
    if rings.size < 2:
        return np.array(OPTICAL_AXIS_C), np.inf

    def ring_means(tilt: FloatArray) -> tuple[FloatArray, FloatArray]:
        rho, rho_max = radius_about(cam, _axis_of(tilt))
        w = _windows(rho.ravel()[use], rho_max, n_rings)[0][rings]
        return dop @ w.T / w.sum(axis=1), w.sum(axis=1) ** 2 / (w**2).sum(axis=1)

    # Channel gain and angle errors change the DoP with the turn at its even harmonics
    # (pattern turns modulo pi from the ring means' polarization): harmonics 0, 2 and 4 are
    # projected out per ring. The tilt shows at the first harmonic, which turns that do not
    # cover the circle cannot tell from them: its standard error then grows.
    lin = np.einsum("rp,mp->mr", w0[rings], stokes[..., 1] + 1j * stokes[..., 2])
    theta = 0.5 * np.angle((lin * np.conj(lin[:1])).sum(axis=1))
    nuisance = np.column_stack([np.ones_like(theta)] + [f(k * theta) for k in (2, 4)
                                                          for f in (np.cos, np.sin)])  # fmt: skip
    project = np.eye(theta.size) - nuisance @ np.linalg.pinv(nuisance)
    tilt = np.zeros(2)
    for _ in range(AXIS_ITERATIONS):
        d0, n_eff = ring_means(tilt)
        jac = np.stack([(ring_means(tilt + AXIS_STEP * e)[0] - d0) / AXIS_STEP
                        for e in np.eye(2)], -1)  # fmt: skip
        w = np.sqrt(n_eff / n_eff.max())[None, :, None]
        a = (np.einsum("ij,jrk->irk", project, jac) * w).reshape(-1, 2)
        b = -((project @ d0)[..., None] * w).ravel()
        step, *_ = np.linalg.lstsq(a, b, rcond=None)
        step *= min(1.0, AXIS_STEP_MAX / max(float(np.hypot(*step)), 1e-300))
        tilt = tilt + step
        if not np.hypot(*tilt) <= AXIS_TILT_MAX:
            return np.array(OPTICAL_AXIS_C), np.inf
    dof = max(b.size - nuisance.shape[1] * rings.size - 2, 1)
    cov = np.linalg.pinv(a.T @ a) * float(np.sum((b - a @ step) ** 2)) / dof
    size = float(np.sqrt(tilt @ np.linalg.pinv(cov) @ tilt))
    tilt_std = float(np.sqrt(np.trace(cov) / 2))
    if size <= AXIS_SIGNIFICANT:
        return np.array(OPTICAL_AXIS_C), tilt_std
    return _axis_of(tilt), tilt_std


def _axis_of(tilt: FloatArray) -> FloatArray:
    """Unit camera-frame axis ``(3,)`` tilted by ``tilt`` (2,) [rad] towards +u and +v."""
    axis = np.array([np.tan(tilt[0]), np.tan(tilt[1]), 1.0])
    return axis / np.linalg.norm(axis)


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
