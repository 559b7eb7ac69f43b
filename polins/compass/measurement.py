"""The measurement: what one image gives (:class:`Measurement`) and the options of the chain.

:class:`MeasureOptions` is the one definition of the options of ``polins.measure``, with
their units and defaults; :func:`measure_options` builds it from keyword options and
rejects unknown ones. Angles are in radians, like everything inside polins
(docs/conventions.md); intensities in DN, as the ``_dn`` names say.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from polins.compass.losses import LOSSES
from polins.compass.skymodel import SKY_MODELS
from polins.errors import UnknownOptionError, UserInputError

FloatArray = NDArray[np.float64]

METHODS = ("compensated", "traditional")
"""The methods of ``polins.measure`` (the paper's Algorithm 1 is reproduced in
:mod:`polins.sim.algorithm1`, not offered as a method)."""


def check_method(method: str) -> None:
    """Raise a one-line :class:`UserInputError` for a method not in :data:`METHODS`."""
    if method in METHODS:
        return
    hint = ""
    if method == "paper":
        hint = " (the paper's Algorithm 1 is polins.sim.algorithm1.measure_algorithm1)"
    raise UserInputError(f"method={method!r}: expected one of {METHODS}{hint}")


class Refusal(Exception):
    """A stage of the chain refuses the image: the reason and the valid pixels it had
    (the chain turns it into :meth:`Measurement.refused`)."""

    def __init__(self, reason: str, n_pixels: int = 0) -> None:
        super().__init__(reason)
        self.reason = reason
        self.n_pixels = n_pixels


class NoiseModelWarning(UserWarning):
    """The noise measured in an image (redundancy residual) is far from the camera file's
    noise model: its read noise, gains or dark offsets do not describe this camera."""


NOISE_RATIO_BAND = (0.5, 2.0)
"""Range of :attr:`Measurement.noise_ratio` (measured / declared noise) outside which
``polins.measure`` warns that the camera file's noise model or calibration is off."""

__all__ = [
    "METHODS",
    "NOISE_RATIO_BAND",
    "MeasureOptions",
    "Measurement",
    "MeasurementMaps",
    "NoiseModelWarning",
    "Refusal",
    "check_method",
    "measure_options",
]


@dataclass(frozen=True)
class MeasureOptions:
    """Options of ``polins.measure`` (pass them as keyword arguments).

    Attributes
    ----------
    gain_correction : bool
        Apply the calibrated channel gains in the Stokes estimate (False: the paper's
        uncorrected "traditional" baseline).
    weighted : bool
        Eigen weights ``p^2/sigma_L^2`` (docs/model.md §9.1); False = the paper's equal
        weights.
    fixed_zenith : bool
        ``method="compensated"``: fix the sun zenith to the ephemeris (needs good roll/pitch).
    loss : {"linear", "huber", "cauchy"}
        Loss of the joint ML (IRLS); robust losses down-weight outlier pixels.
    sun_exclusion : float
        Pixels closer than this to the sun are not used [rad].
    dop_min : float
        Minimum degree of polarization [-].
    snr_min : float
        Minimum polarized intensity in units of its noise sigma_L: rejects unpolarized
        scenery (occluders, ground, clouds) whose noise alone would pass ``dop_min``.
    kappa : float
        Correlated-error inflation factor, ``kappa^2 = N/N_eff`` (docs/model.md §10.2).
    sigma_floor : float
        An extra model-error floor of the heading [rad], added in quadrature to the model
        part (default 0: the model part comes from the data, docs/measurement.md §12).
    model_scale : float
        Calibration factor of the sky-model part: the jackknife's variance beyond the pixel
        noise times ``model_scale^2`` (2, calibrated on realistic skies, with and without
        ``sun_n``; §12).
    instrumental_dop_std : float
        1-sigma per component of the camera-fixed polarization the channel calibration
        leaves [-] (0.002 for gains good to +-0.5 %; 0 for a perfect calibration); gives
        :attr:`Measurement.yaw_std_correlated` (§12).
    instrumental_mixing_std : float
        1-sigma of the camera-fixed mixing of the linear Stokes components that the
        channel angles and efficiencies leave [-] (0: taken as exact; a calibration's
        figure, e.g. 0.0009 for angles good to 0.05 deg); part of
        :attr:`Measurement.yaw_std_correlated` (§12).
    max_field_angle : float or None
        Region of interest: largest ray angle from the optical axis used [rad] (None: the
        camera file's ``[roi]`` and field of view only).
    model_aop_std : float
        Model error of the AoP on the optical axis [rad] in the pixel weights (0: weights
        from the pixel noise only); it grows as ``1 + (theta / model_field_angle)^2 +
        (model_neutral_angle / gamma)^2`` with the field angle theta and towards the sun
        and the antisun (gamma the angle to the nearer; docs/measurement.md §4).
    model_field_angle : float
        Field angle [rad] at which the AoP model error has doubled.
    model_neutral_angle : float
        Angle [rad] to the sun or the antisun at which the AoP model error has doubled
        (the neutral points).
    cloud_dop_ratio : float or None
        Thin-cloud mask: sky cells (about 7 deg) whose summed polarized intensity is below
        this fraction of the clear sky's ``d_max sin^2 T / (1 + cos^2 T) S0`` (d_max fitted
        per image) are not used, away from the sun and the antisun (docs/measurement.md
        §4); None: no cloud mask.
    sky_model : {"berry", "rayleigh"}
        ``"compensated"``: the sky the joint ML predicts: the Berry four-neutral-point sky
        (docs/model.md §6.3) or the single-scattering Rayleigh sky.
    neutral_sep : float
        Berry sky: separation of the Babinet and Brewster points [rad], the start of its fit
        (or its value with ``fit_sep=False``).
    fit_sep : bool
        Berry sky: fit the separation per image (a nuisance parameter of the joint ML).
    sep_z_min : float
        Berry sky: a fitted separation below this many of its sigmas is not identified
        (its effect grows as its square: near zero the linearised sigma is optimistic), and
        the image is solved with the Rayleigh sky.
    fit_delta : bool
        ``"compensated"``: also estimate the camera-fixed polarization across the sunlight
        direction, ``delta_perp``, per image (a channel-gain residual; docs/measurement.md
        §12): it removes most of a gain residual's error, costs about 10 % of noise sigma on
        clean skies, and leaves the cloud errors to the jackknife.
    cloud_aop_z : float or None
        Thin-cloud cells by their AoP residual: sky cells (and their neighbours) whose mean
        E-vector rotation exceeds this many sigmas and ``cloud_aop_min`` are dropped and the
        joint ML solved again (docs/measurement.md §4); None: no such test.
    cloud_aop_min : float
        Smallest mean rotation of a cell that counts as cloud [rad].
    cloud_fit_ratio : float or None
        ``"compensated"``: thin-cloud cells after the fit: sky cells whose summed polarized
        intensity (on about 60,000 pixels) falls below this fraction of the fitted sky's
        (its neutral-point DoP shape, the level of the cells at the same elevation) by more
        than 3 sigmas are dropped with two rings of neighbours and the joint ML solved again
        (docs/measurement.md §4); None: no such test.
    tilt_std : float
        1-sigma roll/pitch error about the horizontal axis towards the sun [rad]; adds
        ``cot(Z) tilt_std`` to the heading sigma.
    yaw_gate : float or None
        Refuse if the heading differs from the prior yaw by more than this [rad].
    gradient_max : float or None
        Maximum relative intensity gradient ``|grad S0|/S0`` [1/superpixel]; None: no test.
    redundancy_max_sigma : float
        Maximum redundancy residual ``|nu|`` in channel-noise sigmas (docs/model.md §7.3).
    s0_min_dn : float
        Minimum S0 [DN] (dark / occluded pixels).
    min_pixels : int
        Refuse with fewer valid pixels.
    eigen_gap_min : float
        Refuse if the normalised eigen-gap is below this (docs/model.md §10.1).
    residual_rms_max : float or None
        Refuse if the RMS normalised residual exceeds this (e.g. a wrong channel
        calibration, clouds); None: no test (real skies have model errors far above the
        noise, so a threshold must come from field data).
    zenith_min : float
        Refuse if the sun is closer than this to the zenith [rad].
    horizon_fallback : float
        Below this sun elevation [rad] the prior yaw chooses between yaw and yaw + 180 deg.
    gn_pixels : int
        Target number of pixels of the Gauss-Newton subsample (0: all pixels every
        iteration); the last step always uses all valid pixels.
    max_iterations : int
        Gauss-Newton iterations on the subsample.
    epsilon0 : float
        Starting epsilon (e.g. the previous image's estimate).
    epsilon_max : float
        ``"compensated"``: largest accepted ``|epsilon|`` (the physical range is about 0 to
        0.05); the Gauss-Newton iteration is bounded to it and a solution on the bound falls
        back to weighted ``"traditional"`` (docs/measurement.md §11).
    separability_max : float
        ``"compensated"``: largest accepted correlation of epsilon with the sun parameters
        (:func:`polins.compass.jointml.epsilon_correlation`, from the Fisher information);
        above it epsilon and the sun (mostly the zenith) are not separable and the chain
        falls back to weighted ``"traditional"``.
    branch_z_min : float
        Sun-free measurement: significance [sigmas] an elevation or a brightness difference
        needs to choose the 180 deg branch (docs/measurement.md §11).
    branch_contrast_min : float
        Sun-free measurement: minimum relative brightness difference between the sun side
        and the antisun side of the image for the brightness to choose the branch [-].
    elevation_std_max : float
        Sun-free measurement: ``sun_elevation_b`` is reported (not NaN) when its sigma is
        below this [rad].
    """

    gain_correction: bool = True
    weighted: bool = True
    fixed_zenith: bool = True
    loss: str = "linear"
    sun_exclusion: float = float(np.radians(10.0))
    dop_min: float = 0.03
    snr_min: float = 3.0
    kappa: float = 1.0
    sigma_floor: float = 0.0
    model_scale: float = 2.0
    instrumental_dop_std: float = 0.002
    instrumental_mixing_std: float = 0.0
    max_field_angle: float | None = None
    model_aop_std: float = 0.0
    model_field_angle: float = float(np.radians(60.0))
    model_neutral_angle: float = float(np.radians(10.0))
    cloud_dop_ratio: float | None = 0.95
    sky_model: str = "berry"
    neutral_sep: float = float(np.radians(32.0))
    fit_sep: bool = True
    sep_z_min: float = 10.0
    fit_delta: bool = False
    cloud_aop_z: float | None = 4.0
    cloud_aop_min: float = float(np.radians(0.1))
    cloud_fit_ratio: float | None = 0.97
    tilt_std: float = 0.0
    yaw_gate: float | None = None
    gradient_max: float | None = 0.05
    redundancy_max_sigma: float = 4.0
    s0_min_dn: float = 10.0
    min_pixels: int = 500
    eigen_gap_min: float = 0.5
    residual_rms_max: float | None = None
    zenith_min: float = float(np.radians(5.0))
    horizon_fallback: float = float(np.radians(5.0))
    gn_pixels: int = 15_000
    max_iterations: int = 10
    epsilon0: float = 0.0
    epsilon_max: float = 0.1
    separability_max: float = 0.98
    branch_z_min: float = 5.0
    branch_contrast_min: float = 0.02
    elevation_std_max: float = float(np.radians(5.0))

    def __post_init__(self) -> None:
        if self.loss not in LOSSES:
            raise UserInputError(f"loss={self.loss!r}: expected one of {LOSSES}")
        for name in (
            "kappa",
            "sun_exclusion",
            "sigma_floor",
            "model_scale",
            "instrumental_dop_std",
            "instrumental_mixing_std",
            "model_aop_std",
            "model_neutral_angle",
            "tilt_std",
            "epsilon_max",
            "branch_z_min",
            "branch_contrast_min",
            "elevation_std_max",
        ):
            if not getattr(self, name) >= 0:
                raise UserInputError(f"{name}={getattr(self, name)} must be >= 0")
        if not 0 <= self.dop_min < 1:
            raise UserInputError(f"dop_min={self.dop_min} outside [0, 1)")
        if self.max_field_angle is not None and not 0 < self.max_field_angle <= np.pi / 2:
            raise UserInputError(f"max_field_angle={self.max_field_angle} outside (0, pi/2] rad")
        for name in ("cloud_dop_ratio", "cloud_fit_ratio"):
            if getattr(self, name) is not None and not 0 < getattr(self, name) < 1:
                raise UserInputError(f"{name}={getattr(self, name)} outside (0, 1)")
        if not self.model_field_angle > 0:
            raise UserInputError(f"model_field_angle={self.model_field_angle} must be > 0 [rad]")
        if self.sky_model not in SKY_MODELS:
            raise UserInputError(f"sky_model={self.sky_model!r}: expected one of {SKY_MODELS}")
        if not 0 <= self.neutral_sep < np.pi / 2 or not self.sep_z_min >= 0:
            raise UserInputError("neutral_sep in [0, pi/2) rad and sep_z_min >= 0 required")
        if self.cloud_aop_z is not None and not self.cloud_aop_z > 0:
            raise UserInputError(f"cloud_aop_z={self.cloud_aop_z} must be > 0 (or None)")
        if not self.cloud_aop_min >= 0:
            raise UserInputError(f"cloud_aop_min={self.cloud_aop_min} must be >= 0 [rad]")
        if not 0 < self.separability_max <= 1:
            raise UserInputError(f"separability_max={self.separability_max} outside (0, 1]")
        if self.min_pixels < 3 or self.max_iterations < 1 or self.gn_pixels < 0:
            raise UserInputError("min_pixels >= 3, max_iterations >= 1 and gn_pixels >= 0 required")


_OPTION_NAMES = tuple(f.name for f in dataclasses.fields(MeasureOptions))
_RENAMED = {
    "sun_exclusion_deg": "sun_exclusion",
    "sigma_floor_deg": "sigma_floor",
    "zenith_min_deg": "zenith_min",
    "horizon_fallback_deg": "horizon_fallback",
}


def measure_options(**options: Any) -> MeasureOptions:
    """:class:`MeasureOptions` from keyword options, checked before any work.

    Raises
    ------
    UnknownOptionError
        An unknown option, also a ``TypeError`` (the message lists the valid ones, and the new name of an option
        that was renamed to radians).
    UserInputError
        An impossible value, also a ``ValueError``.
    """
    unknown = sorted(set(options) - set(_OPTION_NAMES))
    if unknown:
        renamed = [f"{k} -> {_RENAMED[k]} [rad]" for k in unknown if k in _RENAMED]
        hint = f" (renamed: {', '.join(renamed)})" if renamed else ""
        raise UnknownOptionError(
            f"unknown measure option(s) {unknown}{hint}; valid options: {', '.join(_OPTION_NAMES)}"
        )
    return MeasureOptions(**options)


@dataclass(frozen=True)
class Measurement:
    """One polarization heading measurement (docs/conventions.md).

    Attributes
    ----------
    ok : bool
        False when the image was refused; then every number is NaN.
    reason : str
        Why it was refused ("" when ok).
    method : str
        The method that produced it.
    yaw : float
        ENU yaw of body x [rad], counter-clockwise from East, in (-pi, pi].
    yaw_std : float
        1-sigma for a filter [rad]: ``sqrt(yaw_std_noise^2 + yaw_std_model^2 + cot^2 Z
        tilt_std^2)`` (docs/measurement.md §12).
    yaw_std_meas : float
        Un-inflated pixel-noise sigma [rad] (Gauss-Newton or eigen-gap sandwich).
    heading_deg : float
        Compass heading of body x [deg], clockwise from North, in [0, 360).
    sun_b, sun_l, sun_c : (3,)
        Unit sun vector in the body, level and camera frames.
    sun_std : float
        1-sigma of the sun direction along the azimuth [rad], inflated like yaw_std (without
        the tilt term, which belongs in the filter's Jacobian for a vector measurement):
        ``sin Z sqrt(yaw_std_noise^2 + yaw_std_model^2)``. With ``fixed_zenith`` the
        elevation of sun_b comes from the ephemeris and the prior tilt, not from the image.
    epsilon, epsilon_std : float
        Direct-sunlight coefficient and its sigma ("compensated"; "traditional": NaN).
    n_pixels : int
        Valid pixels used.
    eigen_gap : float
        Normalised eigen-gap of the eigen solution (docs/model.md §10.1).
    residual_rms : float
        RMS of the normalised AoP-orthogonal residual ``n_i . L_i / sigma_L`` (about 1 when
        the sky model and the camera noise model hold; much larger for a wrong calibration).
    noise_std_est : float
        Per-channel noise [DN] estimated from the redundancy residual (docs/model.md §7.3).
    sun_azimuth_b : float
        Sun azimuth in the body frame [rad], FLU, counter-clockwise from body +x towards +y:
        ``atan2(sun_b[1], sun_b[0])``; filled with and without ``sun_n``.
    sun_azimuth_b_std : float
        Its 1-sigma for a filter [rad], ``sqrt((kappa sigma_meas)^2 + yaw_std_model^2)``
        (the body-frame azimuth does not depend on the prior tilt, hence no tilt term).
    sun_elevation_b, sun_elevation_b_std : float
        Sun elevation above the body x-y plane [rad] and its 1-sigma, where the image
        determines it (sigma below ``elevation_std_max``), else NaN; with ``sun_n`` and
        ``fixed_zenith`` the elevation comes from the ephemeris and the prior tilt (sigma NaN).
    sun_azimuth_b_alt : float
        The other 180 deg candidate [rad] when the branch is ambiguous
        (``sun_branch == "ambiguous"``), else NaN.
    sun_branch : str
        What chose between the sun and the antisun (docs/measurement.md §11):
        ``"elevation"`` (the sun is above the horizon), ``"prior yaw"`` (with ``sun_n``, near
        the horizon), ``"brightness"`` (the sky is brighter towards the sun), ``"prior"``
        (``sun_azimuth_b_prior``) or ``"ambiguous"`` (then ``reason`` says so and ``ok`` is
        True); "" when refused.
    noise_ratio : float
        Channel noise measured by the redundancy residual over the camera file's noise model
        (robust: MAD over the field of view); a warning is issued outside
        :data:`NOISE_RATIO_BAND`.
    yaw_std_noise : float
        Pixel-noise part of ``yaw_std`` [rad], ``kappa yaw_std_meas`` (uncorrelated from
        image to image).
    yaw_std_model : float
        Model-error part [rad]: ``sqrt((model_scale sky)^2 + yaw_std_correlated^2 +
        sigma_floor^2)``, ``sky^2`` the jackknife variance over sky sectors beyond the pixel
        noise. Also part of ``sun_azimuth_b_std`` and ``sun_std``; filled with and without
        ``sun_n``.
    yaw_std_correlated : float
        The camera-fixed part of ``yaw_std_model`` [rad] (``instrumental_dop_std`` times the
        heading's sensitivity to a camera-fixed polarization): the same error in every
        image of the same sun-camera geometry, for a filter's measurement-bias state. The
        rest of the model part follows the sky (clouds, neutral points) and decorrelates as
        the sky and the attitude change.
    yaw_std_jackknife : float
        Jackknife sigma of the azimuth over the 16 mirror-pair sky sectors [rad]
        (pixel noise and sky-model error; a diagnostic).
    """

    ok: bool
    reason: str
    method: str
    yaw: float
    yaw_std: float
    yaw_std_meas: float
    heading_deg: float
    sun_b: FloatArray
    sun_l: FloatArray
    sun_c: FloatArray
    sun_std: float
    epsilon: float
    epsilon_std: float
    n_pixels: int
    eigen_gap: float
    residual_rms: float
    noise_std_est: float = float("nan")
    sun_azimuth_b: float = float("nan")
    sun_azimuth_b_std: float = float("nan")
    sun_elevation_b: float = float("nan")
    sun_elevation_b_std: float = float("nan")
    sun_azimuth_b_alt: float = float("nan")
    sun_branch: str = ""
    noise_ratio: float = float("nan")
    yaw_std_noise: float = float("nan")
    yaw_std_model: float = float("nan")
    yaw_std_correlated: float = float("nan")
    yaw_std_jackknife: float = float("nan")

    @classmethod
    def refused(cls, method: str, reason: str, n_pixels: int = 0) -> Measurement:
        """A refused measurement: ``ok=False``, the reason, every number NaN."""
        nan3 = np.full(3, np.nan)
        return cls(
            ok=False,
            reason=reason,
            method=method,
            yaw=np.nan,
            yaw_std=np.nan,
            yaw_std_meas=np.nan,
            heading_deg=np.nan,
            sun_b=nan3,
            sun_l=nan3.copy(),
            sun_c=nan3.copy(),
            sun_std=np.nan,
            epsilon=np.nan,
            epsilon_std=np.nan,
            n_pixels=n_pixels,
            eigen_gap=np.nan,
            residual_rms=np.nan,
        )

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready dict (vectors as lists, NaN as None)."""

        def clean(v: Any) -> Any:
            if isinstance(v, np.ndarray):
                return [clean(x) for x in v.tolist()]
            if isinstance(v, float | np.floating):
                return None if not np.isfinite(v) else float(v)
            if isinstance(v, np.integer | np.bool_):
                return v.item()
            return v

        return {f.name: clean(getattr(self, f.name)) for f in dataclasses.fields(self)}


@dataclass(frozen=True)
class MeasurementMaps:
    """Per-superpixel images of one measurement, ``(Hs, Ws)`` (NaN outside the field of view).

    Attributes
    ----------
    aop : (Hs, Ws)
        Angle of polarization [rad].
    dop : (Hs, Ws)
        Degree of polarization [-].
    valid : (Hs, Ws) bool
        Pixels used.
    residual : (Hs, Ws)
        Normalised residual at the estimate, NaN where not used.
    """

    aop: FloatArray
    dop: FloatArray
    valid: NDArray[np.bool_]
    residual: FloatArray
