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
  1 deg of channel angle. Their second order (the sky's curvature precessing, at the even
  harmonics where the channel errors show) is taken by centring the rings on the turn axis
  found from the images (:func:`polins.calibration.rings.on_turn_axis`) and refitting,
  when the tilt terms are kept and the axis is off the optical one. An axis offset from the
  camera (a lever arm) does not matter for a sky at infinity. ``noise_ratio`` well above 1
  says the model does not hold.
* **The sun's motion.** Its azimuth changes by up to about 0.25 deg/min; with a vertical
  turn axis this is a turn of the whole sky, absorbed in the fitted turn angles. Its
  elevation change alters the ring means: a 20-minute sequence in the morning biases the
  channel angles by about 0.9 deg. With the clock (``times_utc`` and ``site``) the
  ephemeris gives the sun at every image, and
  :func:`polins.calibration.rings.sun_motion_factors` the change of
  each ring's mean polarization it causes, from a Rayleigh sky seen through the camera
  about the turn axis ``axis_n``; the fit takes it as known. Without the clock, keep the
  sequence within a few minutes.
* **Exposure changes** between images are absorbed by the per-image scale ``s_j``; the dark
  offsets must be known (calibrate them first with dark frames). With the turns unknown on
  a narrow field, where every ring sees the same normalised polarization, a free scale per
  image lets a turn error uneven over the turn trade against the gains' differential: the
  exposure is then taken as smooth in time (:func:`exposure_basis`), and images whose
  brightness jumps about that are refused.
* **Channel-dependent radial shading.** The channels' gains may change differently with the
  field angle, a camera-fixed polarization growing towards the edge (harmonic 0 of the
  turn, changing ring by ring). The fit models ``g_k (1 + c_k (rho^2 - rho2_ref))`` and
  returns its per-pixel gain map when significant.
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

import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from polins.calibration.images import channel_changes, provenance
from polins.calibration.malus import TurnFit, fit_turning_polarization
from polins.calibration.rings import (
    RingData,
    on_turn_axis,
    polarization_turns,
    ring_data,
    ring_sun_factors,
    turns_modulo_2pi,
)
from polins.errors import UserInputError
from polins.models import CameraModel
from polins.site import Site, TimeLike, to_utc_index

FloatArray = NDArray[np.float64]

ANGLE_STD_MAX_DEG = 0.25  # refuse a fit whose channel angles are this uncertain [deg]
TURN_MISMATCH_MAX_DEG = 5.0  # given turns may differ from the ring-mean AoP by this, RMS [deg]
GAIN_RANGE = (0.8, 1.25)  # physical channel gains relative to their mean [-]
ANGLE_OFFSET_MAX_DEG = 10.0  # physical channel angles: offset from the labels' pattern [deg]
EFFICIENCY_MIN = 0.5  # physical channel efficiencies [-]
JOINT_ITERATIONS = 50  # unknown turns: the joint fit from the ring-mean AoP settles in a few
EXPOSURE_JUMP_MAX = 0.005  # unknown turns: image brightness off a smooth drift, RMS log [-]
TILT_STD_GROWTH_MAX = 3.0  # tilt terms that make the channel angles this much less certain: out
TILT_TURN_MOVE_MAX_DEG = 2.0  # unknown turns: tilt terms that move the turns more fit else
GAIN_STD_MAX = 0.002  # unknown turns: a free exposure leaving the gains this uncertain: smooth it
RESIDUAL_RATIO_WARN = 3.0  # residual RMS over the noise model above which the fit warns [-]
RADIAL_SIGNIFICANT = 3.0  # radial shading coefficients above this many std make a gain map
HARMONICS = 4  # harmonics of the turn in the residual's description


class SkyRotationResidualWarning(UserWarning):
    """A sky-rotation fit whose residual is far above the noise model: the images hold
    something the model lacks; the warning says what the residual looks like."""


__all__ = [
    "SkyRotationResidualWarning",
    "SkyRotationResult",
    "calibrate_sky_rotation",
    "check_turns",
    "degeneracy",
    "exposure_basis",
    "exposure_jumps",
    "fit_sky_rotation",
    "residual_pattern",
    "turn_span",
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
    notes : tuple of str
        What the images identified and how the fit got there (e.g. a half turn with known
        angles leaves the tilt terms out; a degenerate free fit refitted).
    residual_pattern : str
        With a residual above 3 x the noise model: what it looks like (its share at each
        harmonic of the turn, and by ring radius); "" otherwise.
    radial_gain, radial_gain_std : (4,)
        Channel-dependent radial shading: channel k's gain changes as
        ``g_k (1 + c_k (rho^2 - rho2_ref))`` with the squared normalised radius (the
        coefficients ``c_k`` [-], zero sum, and their standard errors).
    gain_map : (Hs, Ws, 4) or None
        The per-pixel gains of that shading, over the whole image, when it is significant
        (some ``|c_k|`` above 3 standard errors); None otherwise.
    turn_axis_c : (3,)
        The turn axis the rings were centred on, camera frame: found from the images
        (:func:`polins.calibration.rings.turn_axis_c`), or the optical axis when no tilt
        is significant or ``tilt_terms`` is off.
    turn_axis_tilt_std : float
        Standard error of the turn axis's tilt from the optical axis [rad] (inf: not
        identified; 0: not searched).
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
    notes: tuple[str, ...] = ()
    residual_pattern: str = ""
    radial_gain: FloatArray = field(default_factory=lambda: np.zeros(4))
    radial_gain_std: FloatArray = field(default_factory=lambda: np.zeros(4))
    gain_map: FloatArray | None = None
    turn_axis_c: FloatArray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    turn_axis_tilt_std: float = 0.0

    def camera_changes(self) -> dict[str, Any]:
        """The camera-model fields this calibration sets (with the gain map when the
        radial shading is significant; otherwise no gain map, dropping the base camera's)."""
        changes = channel_changes(self.gain, self.gain_std, self.transmission_angle,
                                  self.efficiency, self.transmission_angle_std,
                                  self.efficiency_std)  # fmt: skip
        changes["gain_map"] = self.gain_map
        return changes


def turn_span(turn: ArrayLike) -> float:
    """Span [rad] covered by turns that matter modulo pi: ``pi`` minus the largest gap
    between the sorted turns on the circle of doubled angles, halved."""
    doubled = np.sort(np.mod(2.0 * np.asarray(turn, dtype=float), 2.0 * np.pi))
    gaps = np.diff(np.concatenate([doubled, [doubled[0] + 2.0 * np.pi]]))
    return float(np.pi - 0.5 * gaps.max())


def check_turns(turns: FloatArray, hint: FloatArray) -> None:
    """Refuse given camera turns [rad] that disagree with the images' polarization ``hint``
    (pattern turns modulo pi, :func:`polarization_turns`): a wrong sign, or wrong angles."""

    def rms_deg(theta: FloatArray) -> float:
        d = np.mod(hint - (theta - theta[0]) + 0.5 * np.pi, np.pi) - 0.5 * np.pi
        return float(np.degrees(np.sqrt(np.mean(d**2))))

    right, flipped = rms_deg(-turns), rms_deg(turns)
    if right <= TURN_MISMATCH_MAX_DEG:
        return
    if flipped <= TURN_MISMATCH_MAX_DEG:
        raise UserInputError(
            f"sky-rotation: the turns run against the images' polarization (RMS {right:.1f} deg; "
            f"negated {flipped:.1f} deg): turns count from +u towards +v, counter-clockwise "
            "seen from behind the camera looking up (docs/conventions.md); negate them"
        )
    raise UserInputError(
        f"sky-rotation: the turns disagree with the images' polarization by {right:.1f} deg "
        "RMS: check their order, units (radians) and that the sky stayed clear"
    )


def degeneracy(
    gain: FloatArray, angle: FloatArray, efficiency: FloatArray, cam: CameraModel
) -> str:
    """Why fitted channels are not a physical polarizer array ("" when they are): gains far
    from their mean, channels whose angles pair up or leave their nominal separation, or
    efficiencies far below 1."""
    rel = gain / gain.mean()
    if np.any((rel < GAIN_RANGE[0]) | (rel > GAIN_RANGE[1])):
        return (f"gains {np.round(rel, 2).tolist()} (relative) outside "
                f"[{GAIN_RANGE[0]:g}, {GAIN_RANGE[1]:g}]")  # fmt: skip
    off = np.degrees(angle - np.radians(cam.nominal_angle_deg))
    off = np.mod(off - off.mean() + 90.0, 180.0) - 90.0
    if np.abs(off).max() > ANGLE_OFFSET_MAX_DEG:
        ang = np.round(np.degrees(angle), 1).tolist()
        return (f"channel angles {ang} deg leave the nominal separation by up to "
                f"{np.abs(off).max():.0f} deg (channels pairing up)")  # fmt: skip
    if np.any(efficiency < EFFICIENCY_MIN):
        return f"efficiencies {np.round(efficiency, 2).tolist()} below {EFFICIENCY_MIN:g}"
    return ""


def residual_pattern(residuals: FloatArray, sigma: FloatArray, theta: FloatArray,
                     radius: FloatArray) -> str:  # fmt: skip
    """What a fit's residual ``(m, R, 4)`` looks like, in one sentence: its share of power at
    each harmonic 0-4 of the pattern turn ``theta`` ``(m,)`` [rad] (per ring and channel,
    over the images; the rest is at higher harmonics or noise), and how it varies with the
    ring radius ``(R,)`` [-]."""
    z = residuals / np.broadcast_to(sigma, residuals.shape)
    n_harm = min(HARMONICS, (theta.size - 1) // 2)
    design = np.column_stack(
        [np.ones_like(theta)]
        + [f(k * theta) for k in range(1, n_harm + 1) for f in (np.cos, np.sin)]
    )
    # Orthonormal in the order of the harmonics (the turns need not cover the circle evenly):
    # each harmonic's share is the power it adds to the lower ones.
    basis, _ = np.linalg.qr(design)
    power = (basis.T @ z.reshape(z.shape[0], -1)) ** 2  # (2K + 1, R * 4)
    total = float(np.sum(z**2))
    shares = [float(power[0].sum()) / total] + [
        float(power[2 * k - 1 : 2 * k + 1].sum()) / total for k in range(1, n_harm + 1)
    ]
    by_ring = np.sqrt(np.mean(z**2, axis=(0, 2)))
    parts = ", ".join(f"{100 * s:.0f} % at harmonic {k}" for k, s in enumerate(shares))
    # The turn-independent part by channel pattern: 0 - 90 and 45 - 135 differences are a
    # camera-fixed polarization (channel gains or shading that differ), the rest is common
    # or redundant (0 + 90 - 45 - 135).
    fixed = z.mean(axis=0)  # (R, 4)
    pol = 0.5 * ((fixed[:, 0] - fixed[:, 2]) ** 2 + (fixed[:, 1] - fixed[:, 3]) ** 2)
    pol_share = float(theta.size * pol.sum()) / total
    return (
        f"residual {np.sqrt(np.mean(z**2)):.1f} x the noise model; {parts} of the turn; "
        f"{100 * pol_share:.0f} % a camera-fixed polarization (harmonic 0, the 0/90 or 45/135 "
        f"channels differing); by ring radius {np.round(radius, 3).tolist()}: "
        f"{np.round(by_ring, 1).tolist()} x"
    )


def exposure_basis(m: int, times_s: FloatArray | None = None) -> FloatArray:
    """Basis ``(m, 2)`` [-] of smoothly changing log exposure scales: a quadratic in the
    images' time (seconds, or their order when None), normalised to [-1/2, 1/2]."""
    t = np.arange(m, dtype=float) if times_s is None else np.asarray(times_s, dtype=float)
    t = (t - t.mean()) / max(float(np.ptp(t)), 1e-300)
    return np.column_stack([t, t**2])


def exposure_jumps(fit: TurnFit, y: FloatArray) -> float:
    """RMS [-] of the per-image brightness the smooth exposure of ``fit`` leaves: each
    image's least-squares scale of the fitted model onto the ring means ``y`` ``(m, R, 4)``,
    in log."""
    model = y - fit.residuals
    ratio = np.sum(y * model, axis=(1, 2)) / np.sum(model**2, axis=(1, 2))
    return float(np.sqrt(np.mean(np.log(ratio) ** 2)))


def _angle_std_deg(fit: TurnFit) -> float:
    return float(np.degrees(fit.angle_std.max()))


def _fit_known_turns(
    data: RingData, cam: CameraModel, turns: FloatArray, tilt_terms: bool,
    factors: NDArray[np.complex128] | None,
) -> tuple[TurnFit, bool, list[str]]:  # fmt: skip
    """Fit with the camera turns known [rad]: the fit, whether it has the tilt terms, notes
    on what the turns identify."""
    theta = -np.asarray(turns, dtype=float)
    plain = fit_turning_polarization(data.y, data.sigma, cam, turn=theta, source_factors=factors,
                                     source_radius2=data.radius2,
                                     source_correlation=data.correlation)  # fmt: skip
    span = np.degrees(np.ptp(np.unwrap(turns)))
    notes = [f"with the turns known ({span:.0f} deg): gains to {np.max(plain.gain_std):.2g}, "
             f"channel angles to {_angle_std_deg(plain):.2g} deg, efficiencies to "
             f"{np.max(plain.efficiency_std):.2g} (their common value and the common angle "
             "offset are conventions: docs/calibrate.md)"]  # fmt: skip
    if not tilt_terms:
        return plain, False, notes
    tilted = fit_turning_polarization(data.y, data.sigma, cam, turn=theta, tilt_terms=True,
                                      source_factors=factors, source_radius2=data.radius2,
                                      source_correlation=data.correlation)  # fmt: skip
    fit, tilt_used = _tilt_or_not(plain, tilted, span, notes)
    return fit, tilt_used, notes


def _tilt_or_not(
    plain: TurnFit, tilted: TurnFit, span: float, notes: list[str]
) -> tuple[TurnFit, bool]:
    """The fit with the tilt terms when they leave the channel angles determined, else the
    one without them, with a note saying so."""
    limit = min(ANGLE_STD_MAX_DEG, TILT_STD_GROWTH_MAX * _angle_std_deg(plain))
    if _angle_std_deg(tilted) <= limit:
        return tilted, True
    notes.append(
        f"turns over {span:.0f} deg cannot tell a tilt of the turn axis from the channel angles "
        f"(their std with the tilt terms: {_angle_std_deg(tilted):.2g} deg, without "
        f"{_angle_std_deg(plain):.2g} deg; efficiencies "
        f"{np.max(tilted.efficiency_std):.2g}): fitted without them, which holds for a turn "
        "axis along the optical axis (a 0.5 deg tilt costs about 1 deg of channel angle); "
        "turn through a full circle to fit the tilt"
    )
    return plain, False


def _joint_fit(
    data: RingData, cam: CameraModel, hint: FloatArray, basis: FloatArray | None,
    factors: NDArray[np.complex128] | None,
) -> tuple[TurnFit, str]:  # fmt: skip
    """The fit with the turns free from ``hint``, and why it is no calibration ("" if it is)."""
    fit = fit_turning_polarization(data.y, data.sigma, cam, turn_start=hint, scale_basis=basis,
                                   source_factors=factors, source_radius2=data.radius2,
                                   source_correlation=data.correlation,
                                   max_iterations=JOINT_ITERATIONS)  # fmt: skip
    why = degeneracy(fit.gain, fit.angle, fit.efficiency, cam)
    if not fit.converged:
        why = why or "it does not settle"
    return fit, why


def _fit_unknown_turns(
    data: RingData, cam: CameraModel, hint: FloatArray, tilt_terms: bool,
    factors: NDArray[np.complex128] | None, times_s: FloatArray | None,
) -> tuple[TurnFit, bool, list[str]]:  # fmt: skip
    """Fit with the turns unknown, from the ring-mean AoP ``hint`` (pattern turns [rad]).

    First with a free exposure per image. Where every ring sees the same normalised
    polarization (a narrow field about the zenith), a free scale per image lets a turn
    error that is uneven over the turn trade against the gains' differential
    (docs/calibrate.md#sky-rotation): when that fit is no physical polarizer array or leaves
    the gains uncertain by more than ``GAIN_STD_MAX`` (or the angles by more than
    ``ANGLE_STD_MAX_DEG``), the exposure is taken as smooth in time (:func:`exposure_basis`),
    which a fixed exposure is; images whose brightness jumps about that by more than
    ``EXPOSURE_JUMP_MAX`` are then refused, and so is a fit that does not settle or is no
    physical polarizer array. A degenerate result is never returned."""
    fit, why = _joint_fit(data, cam, hint, None, factors)
    if not why:
        notes = ["turns fitted with a free exposure per image"]
        final, tilt_used = _with_tilt(data, cam, fit, None, factors, tilt_terms, notes)
        gain_std = float(np.max(final.gain_std / final.gain))
        if gain_std <= GAIN_STD_MAX and _angle_std_deg(final) <= ANGLE_STD_MAX_DEG:
            return final, tilt_used, notes
        why = (f"the gains uncertain by {100 * gain_std:.2g} % and the channel angles by "
               f"{_angle_std_deg(final):.2g} deg")  # fmt: skip
    else:
        why = f"no physical polarizer array ({why})"
    basis = exposure_basis(data.y.shape[0], times_s)
    fit, smooth_why = _joint_fit(data, cam, hint, basis, factors)
    if smooth_why:
        raise UserInputError(
            f"sky-rotation: the turns cannot be fitted from these images: with them free the fit "
            f"is no physical polarizer array ({smooth_why}; with a free exposure per image "
            f"{why}); give the turns (turns=..., polins calibrate sky-rotation --turns-deg)"
        )
    jumps = exposure_jumps(fit, data.y)
    if jumps > EXPOSURE_JUMP_MAX:
        raise UserInputError(
            f"sky-rotation: with the turns free and a free exposure per image the fit leaves "
            f"{why}: turn errors trade against the gains' differential where the sky's "
            "polarization is the same across the field; a fixed exposure tells them apart, but "
            f"the images' brightness jumps by {100 * jumps:.2g} % RMS about a smooth drift. Fix "
            "the exposure, or give the turns (turns=..., polins calibrate sky-rotation "
            "--turns-deg)"
        )
    notes = [f"turns fitted with the exposure smooth in time (jumps about it {100 * jumps:.2g} "
             f"% RMS): with a free exposure per image the fit left {why}"]  # fmt: skip
    final, tilt_used = _with_tilt(data, cam, fit, basis, factors, tilt_terms, notes)
    return final, tilt_used, notes


def _with_tilt(
    data: RingData, cam: CameraModel, fit: TurnFit, basis: FloatArray | None,
    factors: NDArray[np.complex128] | None, tilt_terms: bool, notes: list[str],
) -> tuple[TurnFit, bool]:  # fmt: skip
    """The fit with the tilt terms added from ``fit`` (its turns on the right branch) when
    they are wanted and identified, else ``fit``; ``notes`` say why they were left out."""
    if not tilt_terms:
        return fit, False
    branch = turns_modulo_2pi(data.signal, data.weight, cam)
    turn_start = fit.turn + np.pi * np.round((branch - fit.turn) / np.pi)
    tilted = fit_turning_polarization(
        data.y, data.sigma, cam, tilt_terms=True, turn_start=turn_start,
        turn_prior_std=np.radians(1.0), scale_basis=basis, source_factors=factors,
        source_radius2=data.radius2, source_correlation=data.correlation,
    )  # fmt: skip
    moved = np.degrees(np.abs(np.angle(np.exp(2j * (tilted.turn - fit.turn)))).max() / 2)
    if moved > TILT_TURN_MOVE_MAX_DEG:
        notes.append(f"the tilt terms moved the fitted turns by up to {moved:.2g} deg: they fit "
                     "something other than a tilted turn axis, and are left out")  # fmt: skip
        return fit, False
    return _tilt_or_not(fit, tilted, float(np.degrees(turn_span(-fit.turn))), notes)


def fit_sky_rotation(
    raws: Sequence[ArrayLike] | ArrayLike,
    cam: CameraModel,
    *,
    turns: ArrayLike | None = None,
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
        Raw mosaics [DN] of a clear sky, the camera turned about its optical axis between
        them: 12 or more spread over a full turn (at least 4 over ``min_span_deg`` with
        ``tilt_terms=False`` or with the turns known).
    cam : CameraModel
        Base camera: dark offsets (known), intrinsics (the rings), noise model, and the
        conventions for the unidentifiable common gain, angle offset and efficiency.
    turns : array_like, (m,), optional
        The camera's turns about its optical axis [rad] (a turntable's angles), counted like
        image angles, from +u towards +v (docs/conventions.md): counter-clockwise seen from
        above for a camera looking up with image columns along body x. None: fitted. Turns
        that disagree with the images' polarization (a wrong sign) are refused. With them, a
        half turn fixes the gains and angles; a tilt of the turn axis then needs a full
        turn, and without one the fit says so and leaves the tilt terms out.
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
        taken from the ephemeris (:func:`polins.calibration.rings.sun_motion_factors`).
        Without them the sky is taken as constant: keep the sequence within a few minutes.
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
        With ``notes`` on what the images identify, and ``residual_pattern`` describing the
        residual when it is more than 3 x the noise model (also warned as
        :class:`SkyRotationResidualWarning`).

    Raises
    ------
    UserInputError
        Fewer than 4 images, wrong shapes or turns, turns spanning too little, no usable
        ring, channels that fit only as a degenerate (unphysical) polarizer array, or turns
        that leave the channel angles uncertain by more than 0.25 deg.
    """
    data = ring_data(raws, cam, n_rings, ifov_correction)
    m = data.y.shape[0]
    factors = ring_sun_factors(cam, data.weight, m, times_utc, site, axis_n)
    hint = polarization_turns(data.y, cam)
    known = turns is not None
    if known:
        turns_arr = np.asarray(turns, dtype=float).ravel()
        if turns_arr.shape != (m,) or not np.all(np.isfinite(turns_arr)):
            raise UserInputError(f"sky-rotation: turns needs {m} finite angles [rad], one per "
                                 f"image, got {turns_arr.size}")  # fmt: skip
        check_turns(turns_arr, hint)
        _check_span(np.degrees(turn_span(turns_arr)), min_span_deg)
    else:
        _check_span(np.degrees(turn_span(-hint)), 0.5 * min_span_deg)  # hopeless before a fit
    times_s = None
    if times_utc is not None:
        idx = to_utc_index(times_utc)
        times_s = np.asarray((idx - idx[0]).total_seconds(), dtype=float)

    def run(ring_data: RingData) -> tuple[TurnFit, bool, list[str]]:
        if known:
            return _fit_known_turns(ring_data, cam, turns_arr, tilt_terms, factors)
        return _fit_unknown_turns(ring_data, cam, hint, tilt_terms, factors, times_s)

    fit, tilt_used, notes = run(data)
    if not _shading_significant(fit):  # the nested model without it: no map, uniform gains
        data = replace(data, radius2=None)
        fit, tilt_used, notes = run(data)
    if tilt_used:  # the turns cover the circle: the rings on the turn axis take its 2nd order
        data = on_turn_axis(data, cam)
        if data.axis_c[2] != 1.0:
            fit, tilt_used, notes = run(data)
    axis_note = _axis_note(data)
    span = np.degrees(turn_span(-fit.turn))
    _check_span(span, min_span_deg)
    why = degeneracy(fit.gain, fit.angle, fit.efficiency, cam)
    if why:
        raise UserInputError(f"sky-rotation: the fit is not a physical polarizer array ({why})")
    if _angle_std_deg(fit) > ANGLE_STD_MAX_DEG:
        advice = ", or pass tilt_terms=False if the axis is the optical axis" if tilt_used else ""
        raise UserInputError(
            f"sky-rotation: the images cannot fix the channel angles (std {_angle_std_deg(fit):.2g}"
            f" deg{', a tilt of the turn axis included' if tilt_used else ''}); record more "
            f"images spread over a full turn{advice}"
        )
    return _result(fit, data, cam, m, span, tilt_used, factors is not None, ifov_correction,
                   known, [*notes, axis_note] if axis_note else notes)  # fmt: skip


def _axis_note(data: RingData) -> str:
    """Where the rings were centred, when on a turn axis found off the optical axis."""
    if data.axis_c[2] == 1.0:
        return ""
    return (f"rings centred on the turn axis, found {np.degrees(np.arccos(data.axis_c[2])):.2f} +- "
            f"{np.degrees(data.axis_tilt_std):.2g} deg from the optical axis")  # fmt: skip


def _shading_significant(fit: TurnFit) -> bool:
    """Some radial shading coefficient exceeds ``RADIAL_SIGNIFICANT`` standard errors."""
    return bool(np.any(np.abs(fit.radial_gain) > RADIAL_SIGNIFICANT * fit.radial_gain_std))


def _check_span(span: float, min_span_deg: float) -> None:
    """Refuse turns spanning less than ``min_span_deg`` [deg] (half a degree of slack)."""
    if span + 0.5 < min_span_deg:
        raise UserInputError(
            f"sky-rotation: the turns span only {span:.0f} deg (modulo 180); turn the camera "
            f"through at least {min_span_deg:.0f} deg"
        )


def _result(
    fit: TurnFit, data: RingData, cam: CameraModel, m: int, span: float, tilt_used: bool,
    clock: bool, ifov_correction: bool, known: bool, notes: list[str],
) -> SkyRotationResult:  # fmt: skip
    rms = float(np.sqrt(np.mean(fit.residuals**2)))
    noise_ratio = float(np.sqrt(np.mean((fit.residuals / data.sigma) ** 2)))
    pattern = ""
    if noise_ratio > RESIDUAL_RATIO_WARN:
        pattern = residual_pattern(fit.residuals, data.sigma, fit.turn, data.radius)
        warnings.warn(
            f"sky-rotation: the model does not explain these images ({pattern}); the "
            "standard errors are scaled by it (docs/calibrate.md#sky-rotation)",
            SkyRotationResidualWarning,
            stacklevel=3,
        )
    turn = -fit.turn  # the pattern turns by -phi when the camera turns by +phi
    gain_map = None
    if data.radius2 is not None:
        shading = 1.0 + (data.pixel_radius2 - data.radius2.mean())[..., None] * fit.radial_gain
        gain_map = fit.gain * np.maximum(shading, 0.1)
    return SkyRotationResult(
        gain=fit.gain,
        gain_std=fit.gain_std,
        transmission_angle=fit.angle,
        transmission_angle_std=fit.angle_std,
        efficiency=fit.efficiency,
        efficiency_std=fit.efficiency_std,
        turn=np.mod(turn - turn[0] + 0.5 * np.pi, np.pi) - 0.5 * np.pi,
        scale=fit.scale,
        ring_radius=data.radius,
        residuals=fit.residuals,
        residual_rms_dn=rms,
        noise_ratio=noise_ratio,
        notes=tuple(notes),
        residual_pattern=pattern,
        radial_gain=fit.radial_gain,
        radial_gain_std=fit.radial_gain_std,
        gain_map=gain_map,
        turn_axis_c=data.axis_c,
        turn_axis_tilt_std=data.axis_tilt_std,
        provenance=provenance(
            "sky-rotation",
            "ring means of clear-sky images turning about the optical axis, Malus-law fit"
            + (" with the turns known" if known else "")
            + (" with axis-tilt terms" if tilt_used else "")
            + (", the sun's motion from the ephemeris" if clock else "")
            + (", channels interpolated to the superpixel centres" if ifov_correction else "")
            + " (docs/calibrate.md#sky-rotation)",
            m,
            n_rings=int(data.radius.size),
            turn_span_deg=round(float(span), 1),
            residual_rms_dn=float(f"{rms:.3g}"),
            noise_ratio=float(f"{noise_ratio:.3g}"),
            radial_gain_max=float(f"{np.abs(fit.radial_gain).max():.3g}"),
            turn_axis_tilt_deg=round(float(np.degrees(np.arccos(data.axis_c[2]))), 3),
        ),
    )


def calibrate_sky_rotation(
    raws: Sequence[ArrayLike] | ArrayLike, cam: CameraModel, turns: ArrayLike | None = None
) -> CameraModel:
    """The camera ``cam`` with the channel gains, transmission angles and efficiencies fitted
    to a sky-rotation sequence (:func:`fit_sky_rotation`, whose result holds the residuals,
    uncertainties and provenance); ``turns`` [rad]: the camera's known turns, or None."""
    return replace(cam, **fit_sky_rotation(raws, cam, turns=turns).camera_changes())
