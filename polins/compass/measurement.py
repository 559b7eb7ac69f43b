"""The measurement: what one image gives (:class:`Measurement`) and the options of the chain.

:class:`MeasureOptions` is the one definition of the options of ``polins.measure``, with
their units and defaults; constructing it (directly or with :func:`measure_options`)
rejects an unknown option in one line, naming what replaces a replaced one. Angles are in radians, like everything inside polins
(docs/conventions.md); intensities in DN, as the ``_dn`` names say.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from numbers import Real
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
    "check_option_names",
    "measure_options",
]


@dataclass(frozen=True)
class MeasureOptions:
    """Options of ``polins.measure`` (pass them as keyword arguments).

    Each has a measured reason in docs/measurement.md; the detectors and thresholds behind
    them are constants of the chain. An option that can be switched off takes ``"off"``;
    ``"auto"`` is the automatic behaviour.

    Attributes
    ----------
    fixed_zenith : bool
        ``method="compensated"``: fix the sun zenith to the ephemeris (needs good roll/pitch).
    sky_model : {"berry", "rayleigh"}
        ``"compensated"``: the sky the joint ML predicts: the Berry four-neutral-point sky
        with its separation fitted per image (docs/model.md §6.3) or the single-scattering
        Rayleigh sky.
    fit_delta : bool
        ``"compensated"``: also estimate the camera-fixed polarization across the sunlight
        direction, ``delta_perp``, per image (a channel-gain residual; docs/measurement.md
        §12): it removes most of a gain residual's error, costs about 10 % of noise sigma on
        clean skies, and leaves the cloud errors to the jackknife.
    loss : {"linear", "huber", "cauchy"}
        Loss of the joint ML (IRLS); robust losses down-weight outlier pixels.
    clouds : {"auto", "off"}
        ``"auto"``: thin-cloud sky cells are found and not used (a DoP deficit against the
        clear sky, a rotated mean AoP and, with the Berry sky, a DoP deficit against the
        fitted sky; docs/measurement.md §4); ``"off"``: every valid pixel is used.
    max_field_angle : float or "off"
        Region of interest: largest ray angle from the optical axis used [rad] (``"off"``:
        the camera file's ``[roi]`` and field of view only).
    sun_exclusion : float
        Pixels closer than this to the sun are not used [rad].
    dop_min : float
        Minimum degree of polarization [-].
    s0_min_dn : float
        Minimum S0 [DN] (dark / occluded pixels).
    min_pixels : int
        Refuse with fewer valid pixels.
    instrumental_dop_std : float or "auto"
        1-sigma per component of the camera-fixed polarization the channel calibration
        leaves [-]; gives :attr:`Measurement.yaw_std_correlated` (docs/measurement.md §12).
        ``"auto"``: the camera file's figure, else 0.002 (gains good to +-0.5 %).
    instrumental_mixing_std : float or "auto"
        1-sigma of the camera-fixed mixing of the linear Stokes components that the
        channel angles and efficiencies leave [-] (e.g. 0.0009 for angles good to 0.05 deg);
        part of :attr:`Measurement.yaw_std_correlated`. ``"auto"``: the camera file's
        figure, else 0 (taken as exact).
    tilt_std : float
        1-sigma roll/pitch error of the prior about the horizontal axis towards the sun
        [rad]; adds ``cot(Z) tilt_std`` to the heading sigma.
    yaw_gate : float or "off"
        Refuse if the heading differs from the prior yaw by more than this [rad].
    residual_rms_max : float or "off"
        Refuse if the RMS normalised residual exceeds this (e.g. a wrong channel
        calibration, clouds); real skies have model errors far above the noise, so a
        threshold must come from field data.
    horizon_fallback : float
        Below this sun elevation [rad] the prior yaw chooses between yaw and yaw + 180 deg
        (without ``sun_n``: the elevation does not choose the branch).
    epsilon0 : float
        Starting epsilon of the joint ML (e.g. the previous image's estimate).
    """

    fixed_zenith: bool = True
    sky_model: str = "berry"
    fit_delta: bool = False
    loss: str = "linear"
    clouds: str = "auto"
    max_field_angle: float | str = "off"
    sun_exclusion: float = float(np.radians(10.0))
    dop_min: float = 0.03
    s0_min_dn: float = 10.0
    min_pixels: int = 500
    instrumental_dop_std: float | str = "auto"
    instrumental_mixing_std: float | str = "auto"
    tilt_std: float = 0.0
    yaw_gate: float | str = "off"
    residual_rms_max: float | str = "off"
    horizon_fallback: float = float(np.radians(5.0))
    epsilon0: float = 0.0

    def __new__(cls, *args: Any, **options: Any) -> MeasureOptions:
        """Refuse an unknown option by name, with what replaces a replaced one."""
        check_option_names(options)
        return super().__new__(cls)

    def __post_init__(self) -> None:
        _check_choices(self)
        _check_ranges(self)

    @property
    def roi(self) -> float | None:
        """``max_field_angle`` [rad], None when off."""
        return None if self.max_field_angle == "off" else float(self.max_field_angle)

    @property
    def gate(self) -> float | None:
        """``yaw_gate`` [rad], None when off."""
        return None if self.yaw_gate == "off" else float(self.yaw_gate)

    @property
    def residual_limit(self) -> float | None:
        """``residual_rms_max``, None when off."""
        return None if self.residual_rms_max == "off" else float(self.residual_rms_max)


def _check_choices(opt: MeasureOptions) -> None:
    """The named choices: loss, sky model, clouds, the booleans, "off" and "auto"."""
    if opt.loss not in LOSSES:
        raise UserInputError(f"loss={opt.loss!r}: expected one of {LOSSES}")
    if opt.sky_model not in SKY_MODELS:
        raise UserInputError(f"sky_model={opt.sky_model!r}: expected one of {SKY_MODELS}")
    if opt.clouds not in ("auto", "off"):
        raise UserInputError(f"clouds={opt.clouds!r}: expected 'auto' or 'off'")
    for name in ("fixed_zenith", "fit_delta"):
        if not isinstance(getattr(opt, name), bool | np.bool_):
            raise UserInputError(f"{name}={getattr(opt, name)!r}: expected True or False")
    for name, word in _WORDS.items():
        value = getattr(opt, name)
        if isinstance(value, bool | np.bool_):
            raise UserInputError(f"{name}={value!r}: expected a number or {word!r}")
        if isinstance(value, str) or value is None:
            if value != word:
                raise UserInputError(f"{name}={value!r}: expected a number or {word!r}")
        elif not value >= 0:
            raise UserInputError(f"{name}={value} must be >= 0 (or {word!r})")


_WORDS = {
    "instrumental_dop_std": "auto",
    "instrumental_mixing_std": "auto",
    "yaw_gate": "off",
    "residual_rms_max": "off",
    "max_field_angle": "off",
}
"""The options that take a number or a word, and the word."""


_NUMBERS = ("sun_exclusion", "dop_min", "s0_min_dn", "min_pixels", "tilt_std",
            "horizon_fallback", "epsilon0")  # fmt: skip
"""The options that take a number only."""


def _check_ranges(opt: MeasureOptions) -> None:
    """The numbers' types and ranges."""
    for name in _NUMBERS:
        value = getattr(opt, name)
        if isinstance(value, bool | np.bool_) or not isinstance(value, Real):
            raise UserInputError(f"{name}={value!r}: expected a number")
    for name in ("sun_exclusion", "tilt_std"):
        if not getattr(opt, name) >= 0:
            raise UserInputError(f"{name}={getattr(opt, name)} must be >= 0")
    if not 0 <= opt.dop_min < 1:
        raise UserInputError(f"dop_min={opt.dop_min} outside [0, 1)")
    angle = opt.max_field_angle
    if angle != "off" and not 0 < float(angle) <= np.pi / 2:
        raise UserInputError(f"max_field_angle={angle} outside (0, pi/2] rad")
    if opt.min_pixels < 3:
        raise UserInputError(f"min_pixels={opt.min_pixels}: at least 3 required")


_OPTION_NAMES = tuple(f.name for f in dataclasses.fields(MeasureOptions))
_CONSTANT = "a constant of the chain (docs/measurement.md)"
_MODEL_PART = (
    "the model part of the sigma is measured in each image (yaw_std_model); a filter's "
    "scale or floor on it is FuseConfig's yaw_std_scale / yaw_floor_deg"
)
_REPLACED = {
    "sun_exclusion_deg": "sun_exclusion [rad]",
    "horizon_fallback_deg": "horizon_fallback [rad]",
    "sigma_floor_deg": _MODEL_PART,
    "zenith_min_deg": _CONSTANT,
    "cloud_dop_ratio": "clouds ('auto' or 'off')",
    "cloud_aop_z": "clouds ('auto' or 'off')",
    "cloud_aop_min": "clouds ('auto' or 'off')",
    "cloud_fit_ratio": "clouds ('auto' or 'off')",
    "kappa": _MODEL_PART,
    "sigma_floor": _MODEL_PART,
    "model_scale": _MODEL_PART,
    "model_aop_std": "max_field_angle (pixel model-error weights are not used)",
    "model_field_angle": "max_field_angle (pixel model-error weights are not used)",
    "model_neutral_angle": "max_field_angle (pixel model-error weights are not used)",
    "neutral_sep": "sky_model ('berry' fits the separation per image)",
    "fit_sep": "sky_model ('berry' fits the separation per image)",
    "gain_correction": "polins.sim.algorithm1.measure_baseline (the paper's baselines)",
    "weighted": "polins.sim.algorithm1.measure_baseline (the paper's baselines)",
}
_CONSTANTS = (
    "snr_min",
    "sep_z_min",
    "gradient_max",
    "redundancy_max_sigma",
    "eigen_gap_min",
    "zenith_min",
    "gn_pixels",
    "max_iterations",
    "epsilon_max",
    "separability_max",
    "branch_z_min",
    "branch_contrast_min",
    "elevation_std_max",
)
_REPLACED.update(dict.fromkeys(_CONSTANTS, _CONSTANT))


def measure_options(**options: Any) -> MeasureOptions:
    """:class:`MeasureOptions` from keyword options, checked before any work.

    Raises
    ------
    UnknownOptionError
        An unknown option, also a ``TypeError``: one line with what replaces it (for a
        replaced option) and the valid options.
    UserInputError
        An impossible value, also a ``ValueError``.
    """
    return MeasureOptions(**options)


def check_option_names(options: Mapping[str, Any]) -> None:
    """Refuse unknown option names before any work (``MeasureOptions(...)`` calls it).

    Raises
    ------
    UnknownOptionError
        One line with what replaces a replaced option and the valid options.
    """
    unknown = sorted(set(options) - set(_OPTION_NAMES))
    if unknown:
        replaced = [f"{k} -> {_REPLACED[k]}" for k in unknown if k in _REPLACED]
        hint = f" ({'; '.join(replaced)})" if replaced else ""
        raise UnknownOptionError(
            f"unknown measure option(s) {unknown}{hint}; valid options: {', '.join(_OPTION_NAMES)}"
        )


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
        Its 1-sigma for a filter [rad], ``sqrt(sigma_meas^2 + yaw_std_model^2)``
        (the body-frame azimuth does not depend on the prior tilt, hence no tilt term).
    sun_elevation_b, sun_elevation_b_std : float
        Sun elevation above the body x-y plane [rad] and its 1-sigma, where the image
        determines it (sigma below 5 deg), else NaN; with ``sun_n`` and
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
        Pixel-noise part of ``yaw_std`` [rad], ``yaw_std_meas`` (uncorrelated from image to
        image).
    yaw_std_model : float
        Model-error part [rad]: ``sqrt((2 sky)^2 + yaw_std_correlated^2)``, ``sky^2`` the
        jackknife variance over sky sectors beyond the pixel noise (the factor 2 calibrated on
        realistic skies, docs/measurement.md §12). Also part of ``sun_azimuth_b_std`` and ``sun_std``; filled with and without
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
