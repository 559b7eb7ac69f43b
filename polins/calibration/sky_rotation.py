"""Sky-rotation calibration: channel gains, efficiencies and angles from a clear sky seen while turning.

Record a clear sky with the camera turning about its optical axis by unknown angles (a
turntable, or a vehicle turning on the spot; docs/calibrate.md#sky-rotation). The sky's
polarization is fixed in the world while the sensor turns, so within any ring of pixels
centred on the turn axis the camera sees the same directions of the sky in every image,
only turned: the ring's mean Stokes vector keeps its S0 and its linear part turns by
``-2 phi_j`` when the camera turns by ``phi_j`` about its axis (docs/conventions.md: image
angles run from +u towards +v). Each ring is thus a polarized source turning in front of the
channels, and :func:`polins.calibration.malus.fit_turning_polarization` fits the channel
gains, efficiencies and transmission angles to the ring means of all images, with the turn
angles, a per-image exposure scale and the ring Stokes vectors as nuisance unknowns. No
truth angles are needed.

Fixed by convention (the data cannot tell): the common gain (the base camera's mean gain is
kept), the common angle offset (the base camera's mean offset from the nominal labels is
kept; it is the same unknown as the turn angles, and the camera-to-body boresight needs an
external reference) and the common efficiency times the sky's DoP (the base camera's
largest efficiency is kept).

Pitfalls, and how they are handled:

* **Turn axis.** The rings are centred on the principal point. A turn axis tilted from the
  optical axis makes the camera's view precess, and the ring means change with the turn
  at the first and third harmonics; ``tilt_terms`` (default) fits these terms per ring,
  which needs turns spread over the circle (the fit is refused when the channel angles
  come out uncertain by more than 0.25 deg). Without them a 0.5 deg tilt costs about
  1 deg of channel angle. An axis offset from the camera (a lever arm) does not matter
  for a sky at infinity. ``noise_ratio`` well above 1 says the model does not hold.
* **The sun's motion.** Its azimuth changes by up to about 0.25 deg/min; with a vertical
  turn axis this is a turn of the whole sky, absorbed in the fitted turn angles. Its
  elevation change alters the ring means: a 20-minute sequence in the morning biases the
  channel angles by about 0.9 deg. With the clock (``times_utc`` and ``site``) the
  ephemeris gives the sun at every image, and :func:`sun_motion_factors` the change of
  each ring's mean polarization it causes, from a Rayleigh sky seen through the camera
  about the turn axis ``axis_n``; the fit takes it as known. Without the clock, keep the
  sequence within a few minutes.
* **Exposure changes** between images are absorbed by the per-image scale ``s_j``; the dark
  offsets must be known (calibrate them first with dark frames).
* **Turns spanning less than about 90 deg** leave the gains and the efficiencies
  degenerate: refused.
* **The sun disc and saturation.** A ring that holds a saturated superpixel in any image
  is dropped, so the sun's ring never enters the fit.
* **The DoFP IFOV error.** The four pixels of a superpixel look a quarter superpixel
  off its centre, each in its own direction, which fakes polarization wherever the sky
  changes across the image; a ring mean does not cancel it (its gradient along the ring
  turns with the pattern). On the test camera (153 x 128 superpixels) it biases the
  channel angles by 0.2-0.4 deg and the efficiencies by up to 1.7% (noise ratio about 4).
  ``ifov_correction`` (default) first interpolates each channel to the superpixel centres
  (bilinear, the same smoothing for all four channels):
  the errors drop to those of IFOV-free images (0.03-0.08 deg, noise ratio 0.9).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from polins.calibration.images import (
    centred_channels,
    channel_changes,
    channel_stack,
    provenance,
)
from polins.calibration.malus import base_stokes, fit_turning_polarization
from polins.compass.camera import doubled_aop_from_evector, fov_mask, pixel_rays_c
from polins.errors import UserInputError
from polins.models import CameraModel
from polins.site import Site, TimeLike, to_utc_index
from polins.sky.ephemeris import sun_position, sun_vector_n
from polins.sky.scattering import rayleigh_dop, rayleigh_evector

FloatArray = NDArray[np.float64]

ANGLE_STD_MAX_DEG = 0.25  # refuse a fit whose channel angles are this uncertain [deg]

__all__ = [
    "SkyRotationResult",
    "calibrate_sky_rotation",
    "fit_sky_rotation",
    "ring_windows",
    "sun_motion_factors",
    "turn_span",
    "turns_modulo_2pi",
]


@dataclass(frozen=True)
class SkyRotationResult:
    """Channel calibration fitted to a sky-rotation sequence.

    Attributes
    ----------
    gain, gain_std : (4,)
        Channel gains g_k [-] (mean: the base camera's) and standard errors.
    transmission_angle, transmission_angle_std : (4,)
        Transmission angles alpha_k [rad] (mean offset from the labels: the base camera's).
    efficiency, efficiency_std : (4,)
        Efficiencies eta_k [-] (largest: the base camera's).
    turn : (m,)
        Fitted camera turn about the optical axis, relative to the first image [rad],
        counted like image angles (+u towards +v), modulo pi.
    scale : (m,)
        Exposure scale of each image relative to the first [-] (with ``tilt_terms``, up to
        a first-harmonic wobble in the turn, which the data cannot tell from a tilt).
    ring_radius : (R,)
        Centre radius of each ring window used, in normalised image coordinates [-].
    residuals : (m, R, 4)
        Ring-mean data minus model [DN].
    residual_rms_dn : float
        RMS of ``residuals`` [DN].
    noise_ratio : float
        RMS of the residuals over the declared noise of a ring mean (about 1 when the
        model holds; far above: tilted or offset turn axis, changing sky, wrong dark).
    provenance : dict
    """

    gain: FloatArray
    gain_std: FloatArray
    transmission_angle: FloatArray
    transmission_angle_std: FloatArray
    efficiency: FloatArray
    efficiency_std: FloatArray
    turn: FloatArray
    scale: FloatArray
    ring_radius: FloatArray
    residuals: FloatArray
    residual_rms_dn: float
    noise_ratio: float
    provenance: dict[str, Any] = field(default_factory=dict)

    def camera_changes(self) -> dict[str, Any]:
        """The camera-model fields this calibration sets."""
        return channel_changes(self.gain, self.gain_std, self.transmission_angle, self.efficiency,
                               self.transmission_angle_std, self.efficiency_std)  # fmt: skip


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


def turn_span(turn: ArrayLike) -> float:
    """Span [rad] covered by turns that matter modulo pi: ``pi`` minus the largest gap
    between the sorted turns on the circle of doubled angles, halved."""
    doubled = np.sort(np.mod(2.0 * np.asarray(turn, dtype=float), 2.0 * np.pi))
    gaps = np.diff(np.concatenate([doubled, [doubled[0] + 2.0 * np.pi]]))
    return float(np.pi - 0.5 * gaps.max())


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


def fit_sky_rotation(
    raws: Sequence[ArrayLike] | ArrayLike,
    cam: CameraModel,
    *,
    n_rings: int = 12,
    min_span_deg: float = 90.0,
    tilt_terms: bool = True,
    times_utc: TimeLike | None = None,
    site: Site | None = None,
    axis_n: ArrayLike = (0.0, 0.0, 1.0),
    ifov_correction: bool = True,
) -> SkyRotationResult:
    """Fit channel gains, angles and efficiencies to clear-sky images of a turning camera.

    Parameters
    ----------
    raws : array_like, (m, H, W)
        Raw mosaics [DN] of a clear sky, the camera turned about its optical axis by
        unknown angles between them: 12 or more spread over a full turn (at least 4 over
        ``min_span_deg`` with ``tilt_terms=False``).
    cam : CameraModel
        Base camera: dark offsets (known), intrinsics (the rings), noise model, and the
        conventions for the unidentifiable common gain, angle offset and efficiency.
    n_rings : int
        Number of rings [-].
    min_span_deg : float
        Refuse turns spanning less than this [deg] (modulo 180 deg).
    tilt_terms : bool
        Model the first-order effect of a turn axis tilted from the optical axis
        (:func:`polins.calibration.malus.fit_turning_polarization`); needs about 8 images or
        more spread over a full turn. ``False`` when the axis is known to be the optical
        axis (then 4 images over 90 deg suffice).
    times_utc : array_like, (m,), optional
        UTC time of each image (timezone-aware datetimes, ISO strings or a
        ``pandas.DatetimeIndex``): with ``site``, the sun's motion during the sequence is
        taken from the ephemeris (:func:`sun_motion_factors`). Without them the sky is
        taken as constant: keep the sequence within a few minutes.
    site : polins.Site, optional
        Where the images were taken.
    axis_n : array_like, (3,)
        The turn axis (the optical axis) in ENU, used with the clock; default the zenith.
    ifov_correction : bool
        Interpolate the four channels to their superpixel centres first
        (:func:`polins.calibration.images.centred_channels`; module docstring). Real DoFP
        images need it; ``False`` only for images free of the IFOV error.

    Returns
    -------
    SkyRotationResult

    Raises
    ------
    UserInputError
        Fewer than 4 images, wrong shapes, turns spanning too little, no usable ring, or
        turns that leave the channel angles uncertain by more than 0.25 deg.
    """
    stack = channel_stack(raws, cam, min_images=4, what="sky-rotation")
    windows, centres = ring_windows(cam, n_rings)
    channels = centred_channels(stack.channels, cam) if ifov_correction else stack.channels
    signal = channels - cam.dark_offset_dn  # (m, Hs, Ws, 4)
    weight = windows.reshape(n_rings, -1)  # (R, n)
    saturated = stack.saturated.any(axis=0).ravel()
    keep = np.flatnonzero(~np.any((weight > 0) & saturated, axis=1) & (weight.sum(axis=1) >= 8))
    if keep.size < 2:
        raise UserInputError(
            "sky-rotation: fewer than two rings free of saturation in the field of view"
        )
    m = stack.n_images
    weight = weight[keep]
    norm = weight.sum(axis=1)  # (R,)
    y = np.einsum("rn,mnk->mrk", weight, signal.reshape(m, -1, 4)) / norm[None, :, None]
    n_eff = norm**2 / (weight**2).sum(axis=1)  # effective number of pixels of a window
    var_pix = cam.read_noise_dn**2 + (
        np.maximum(y, 0.0) / cam.conversion_gain_e_per_dn
        if np.isfinite(cam.conversion_gain_e_per_dn)
        else 0.0
    )
    sigma = np.sqrt(var_pix / n_eff[None, :, None])

    factors = None
    if (times_utc is None) != (site is None):
        raise UserInputError("sky-rotation: the sun's motion needs both times_utc and site")
    if times_utc is not None and site is not None:
        times = to_utc_index(times_utc)
        if times.size != m:
            raise UserInputError(
                f"sky-rotation: times_utc needs {m} timezone-aware times (one per image), got "
                f"{times.size}"
            )
        sun = sun_position(times, site.lat_deg, site.lon_deg, site.alt_m)
        sun_n = sun_vector_n(sun.azimuth, sun.zenith)
        factors = sun_motion_factors(cam, weight, sun_n, axis_n)
    fit = fit_turning_polarization(y, sigma, cam, source_factors=factors)
    if tilt_terms:  # start from the fit without them, its turns on the right branch
        hint = turns_modulo_2pi(signal.reshape(m, -1, 4), weight, cam)
        turn_start = fit.turn + np.pi * np.round((hint - fit.turn) / np.pi)
        fit = fit_turning_polarization(
            y, sigma, cam, tilt_terms=True, turn_start=turn_start, turn_prior_std=np.radians(1.0),
            source_factors=factors,
        )  # fmt: skip
    turn = -fit.turn  # the pattern turns by -phi when the camera turns by +phi
    span = np.degrees(turn_span(turn))
    if span + 0.5 < min_span_deg:  # half a degree of slack for the fitted turns
        raise UserInputError(
            f"sky-rotation: the turns span only {span:.0f} deg (modulo 180); turn the camera "
            f"through at least {min_span_deg:.0f} deg"
        )
    angle_std = float(np.degrees(fit.angle_std.max()))
    if angle_std > ANGLE_STD_MAX_DEG:
        advice = ", or pass tilt_terms=False if the axis is the optical axis" if tilt_terms else ""
        raise UserInputError(
            f"sky-rotation: the images cannot fix the channel angles (std {angle_std:.2g} deg"
            f"{', a tilt of the turn axis included' if tilt_terms else ''}); record more "
            f"images spread over a full turn{advice}"
        )
    rms = float(np.sqrt(np.mean(fit.residuals**2)))
    noise_ratio = float(np.sqrt(np.mean((fit.residuals / sigma) ** 2)))
    return SkyRotationResult(
        gain=fit.gain,
        gain_std=fit.gain_std,
        transmission_angle=fit.angle,
        transmission_angle_std=fit.angle_std,
        efficiency=fit.efficiency,
        efficiency_std=fit.efficiency_std,
        turn=np.mod(turn - turn[0] + 0.5 * np.pi, np.pi) - 0.5 * np.pi,
        scale=fit.scale,
        ring_radius=centres[keep],
        residuals=fit.residuals,
        residual_rms_dn=rms,
        noise_ratio=noise_ratio,
        provenance=provenance(
            "sky-rotation",
            "ring means of clear-sky images turning about the optical axis, Malus-law fit"
            + (" with axis-tilt terms" if tilt_terms else "")
            + (", the sun's motion from the ephemeris" if factors is not None else "")
            + (", channels interpolated to the superpixel centres" if ifov_correction else "")
            + " (docs/calibrate.md#sky-rotation)",
            m,
            n_rings=int(keep.size),
            turn_span_deg=round(float(span), 1),
            residual_rms_dn=float(f"{rms:.3g}"),
            noise_ratio=float(f"{noise_ratio:.3g}"),
        ),
    )


def calibrate_sky_rotation(raws: Sequence[ArrayLike] | ArrayLike, cam: CameraModel) -> CameraModel:
    """The camera ``cam`` with the channel gains, transmission angles and efficiencies fitted
    to a sky-rotation sequence (:func:`fit_sky_rotation`, whose result holds the residuals,
    uncertainties and provenance)."""
    return replace(cam, **fit_sky_rotation(raws, cam).camera_changes())
