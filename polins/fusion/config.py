"""The one configuration of the fusion: the IMU model, the site and the option parts, with the behaviour they resolve to.

:class:`FuseConfig` is used by ``polins.fuse``, ``build_filter``, the GTSAM graph, the
streaming loop, the manifest's ``[filter]`` table and the CLI's ``--set KEY=VALUE``. Its
options live in parts (:mod:`polins.fusion.parts`: vehicle and aiding, initial state,
noise, gating, sky states, graph solver, output) and are set by their flat names:
``FuseConfig(nhc_std=0.05)``, ``FuseConfig.from_options(...)``, ``--set nhc_std=0.05`` and
``nhc_std = 0.05`` in a manifest's ``[filter]`` table, all parsed by
:func:`polins.fusion.parts.coerce_option`. An option that can be off takes ``"off"``; an
automatic choice is ``"auto"``. Options are SI and radians unless the name carries another
unit. The implementation constants below are not options.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import pandas as pd

from polins.errors import UnknownOptionError, UserInputError
from polins.fusion.parts import (
    AUTO,
    BACKENDS,
    IMU_RATE,
    NHC_STD_GROUND,
    ODOMETER_STD,
    OFF,
    OPTION_FIELDS,
    OUTPUT_RATE_HZ,
    PARTS,
    STANDSTILL_STD,
    VEHICLE_KINDS,
    Aiding,
    Gating,
    GraphSolver,
    Initial,
    Noise,
    Output,
    SkyStates,
    coerce_option,
    option_names,
    option_table,
    split_options,
    unknown_option,
)
from polins.models import ImuModel, load_imu
from polins.site import PAPER_SITE, Site

# Implementation constants (docs/filter.md, "Options"): not options.
TIME_TOL_S = 1e-6  # [s] measurement times this close to an IMU sample use it
COV_STEP_S = 0.1  # [s] longest covariance-propagation step of the ESKF (ESKF(cov_step_s=))
RESET_INTERVAL_S = 20.0  # [s] inject and zero the ESKF error state this long after a reset
RESET_ANGLE_RAD = 0.005  # [rad] ... or as soon as the attitude error estimate exceeds this
NHC_RATE_HZ = 10.0  # [Hz] rate of the non-holonomic constraint and the standstill updates
STANDSTILL_WINDOW_S = 0.5  # [s] window of the standstill detector
ODOMETER_SCALE_STD = 0.02  # [-] initial 1-sigma of the odometer scale factor
SUN_AZIMUTH_RATE_STD = math.radians(24.0) / 3600.0  # [rad/s] no clock: the sun's azimuth rate
MAX_KEYFRAME_DT_S = 1.0  # [s] longest interval between graph keyframes
MAX_ITERATIONS = 20  # Gauss-Newton iterations of the graph's batch solver
INTEGRATION_STD = 1e-2  # [m/sqrt(s)] GTSAM position-integration noise density
MAX_GATE_ROUNDS = 10  # graph batch solver: most re-solves after gating post-fit outliers
_SITE_KEYS = ("lat_deg", "lon_deg", "alt_m")


# ----------------------------------------------------------------------------- FuseConfig
@dataclass(frozen=True, init=False)
class FuseConfig:
    """Configuration of the fusion (both backends): the IMU model, the site and the parts.

    Set options by their flat names, ``FuseConfig(vehicle="ground", nhc_std="off")``, or a
    part whole, ``FuseConfig(aiding=Aiding(...))``; ``lat_deg``, ``lon_deg`` and ``alt_m``
    are a shorthand for ``site``. Read them from their part: ``config.aiding.nhc_std``; the
    resolved behaviour from the properties (``nhc_sigma``, ``mechanize_earth_rate``, ...).
    ``option_table()`` lists every option; options of one backend are refused by the other
    when set away from their defaults. An IMU model with a ``[filter]`` table (a file of
    ``polins tune``, ``ImuModel.filter_options``) sets those options, under the ones given
    explicitly; ``replace(imu_model=...)`` with such a model applies them too.

    ``standstill_model`` is not an option: the IMU model of the standstill detector's test
    when it is held apart from ``imu_model`` (:func:`polins.tuning.tune` holds its start
    model, so that every candidate of a search has the same rest epochs; docs/tuning.md);
    None: ``imu_model``.
    """

    imu_model: ImuModel
    site: Site | None
    aiding: Aiding
    initial: Initial
    noise: Noise
    gating: Gating
    sky: SkyStates
    graph: GraphSolver
    output: Output
    site_is_assumed: bool = field(default=False, repr=False)
    standstill_model: ImuModel | None = field(default=None, repr=False)

    def __init__(
        self,
        imu_model: ImuModel | str | Path = "mems-typical",
        site: Site | None = None,
        *,
        aiding: Aiding | None = None,
        initial: Initial | None = None,
        noise: Noise | None = None,
        gating: Gating | None = None,
        sky: SkyStates | None = None,
        graph: GraphSolver | None = None,
        output: Output | None = None,
        site_is_assumed: bool = False,
        standstill_model: ImuModel | None = None,
        **options: Any,
    ) -> None:
        site = site_from_shorthand(site, options)
        given = {"aiding": aiding, "initial": initial, "noise": noise, "gating": gating,
                 "sky": sky, "graph": graph, "output": output}  # fmt: skip
        model = _imu_model(imu_model)
        flat = split_options(options)
        tuned = model_options(model)
        for name, cls in PARTS.items():
            part = given[name] if given[name] is not None else cls()
            if not isinstance(part, cls):
                raise UserInputError(f"{name} must be a {cls.__name__}, got {part!r}")
            values = flat[name] if given[name] is not None else {**tuned[name], **flat[name]}
            if values:
                part = dataclasses.replace(part, **values)  # type: ignore[type-var]
            object.__setattr__(self, name, part)
        object.__setattr__(self, "imu_model", model)
        object.__setattr__(self, "site", None if site is None else _site(site))
        object.__setattr__(self, "site_is_assumed", bool(site_is_assumed))
        object.__setattr__(self, "standstill_model", standstill_model)

    # ---------------------------------------------------------------- building
    @classmethod
    def from_options(cls, base: FuseConfig | None = None, /, **options: Any) -> FuseConfig:
        """``base`` (default: all defaults) with the options given by their flat names (an
        unknown name is a one-line error with a hint)."""
        return (base or cls()).replace(**options)

    def replace(self, **options: Any) -> FuseConfig:
        """This configuration with the options given by their flat names (or whole parts,
        ``imu_model``, ``site``, the ``lat_deg``/``lon_deg``/``alt_m`` shorthand)."""
        site = site_from_shorthand(options.pop("site", None), options)
        keep: dict[str, Any] = {name: getattr(self, name) for name in PARTS}
        keep["imu_model"] = _imu_model(options.pop("imu_model", self.imu_model))
        if keep["imu_model"].filter_options != self.imu_model.filter_options:
            # another tuned model: its [filter] options, under the ones of this call
            options = {**dict(keep["imu_model"].filter_options), **options}
        keep["site"] = site if site is not None else self.site
        keep["site_is_assumed"] = self.site_is_assumed and site is None
        keep["standstill_model"] = options.pop("standstill_model", self.standstill_model)
        for name in PARTS:
            if name in options:
                keep[name] = options.pop(name)
        return FuseConfig(**keep, **options)

    @classmethod
    def from_log(cls, log: LogLike) -> FuseConfig:
        """The configuration of a log (:class:`polins.io.Log`): its IMU model, its site, its
        manifest's ``[vehicle]`` and ``[filter]`` tables (:func:`config_from_manifest`)."""
        return config_from_manifest(log.manifest, log.imu_model, log.site, log.manifest_path)

    # ---------------------------------------------------------------- resolved behaviour
    @property
    def imu(self) -> ImuModel:
        """The IMU model."""
        return self.imu_model

    @property
    def standstill_imu(self) -> ImuModel:
        """The IMU model of the standstill detector's test (:mod:`polins.fusion.vehicle`):
        ``standstill_model`` when held, else the IMU model."""
        return self.standstill_model if self.standstill_model is not None else self.imu_model

    @property
    def mechanize_earth_rate(self) -> bool:
        """Whether the Earth and transport rates are mechanized: whenever the site is known
        and the heading is absolute (not ``no_clock``), unless ``earth_rate`` says otherwise."""
        if self.sky.earth_rate == AUTO:
            return self.site is not None and not self.site_is_assumed and not self.no_clock
        return bool(self.sky.earth_rate)

    @property
    def uncovered_earth_rate(self) -> bool:
        """True when the world rotates but the Earth rate is not mechanized (no site known,
        or no clock: the heading is relative, so the horizontal Earth rate cannot be
        projected): the process noise then covers it (docs/filter.md, "Without a site")."""
        return self.sky.earth_rate == AUTO and (self.site_is_assumed or self.no_clock)

    @property
    def no_clock(self) -> bool:
        """Whether the no-clock mode is on (``"auto"`` resolves to it when the run's
        measurements ask for it: :meth:`resolve`)."""
        return self.sky.no_clock is True

    @property
    def tilt_coupling(self) -> bool:
        """Whether the yaw updates use the tilt-coupled model (``"auto"``: off until
        :meth:`resolve` sees the prior columns)."""
        return self.gating.tilt_coupling is True

    @property
    def gate_probability(self) -> float | None:
        """The chi-square gate probability, or None: no gate."""
        return _value(self.gating.gate_prob, None)

    @property
    def gap_s(self) -> float | None:
        """The longest IMU gap bridged [s], or None: 5 median sample intervals."""
        return _value(self.gating.max_gap_s, None)

    @property
    def output_rate(self) -> float | None:
        """Output rows per second, or None: every IMU sample (``output_rate_hz="imu"``)."""
        if self.output.output_rate_hz == IMU_RATE:
            return None
        return _value(self.output.output_rate_hz, OUTPUT_RATE_HZ)

    @property
    def nhc_sigma(self) -> float | None:
        """The non-holonomic 1-sigma in use [m/s], or None: off."""
        return _value(
            self.aiding.nhc_std, NHC_STD_GROUND if self.aiding.vehicle == "ground" else None
        )

    @property
    def standstill_sigma(self) -> float | None:
        """The zero-velocity 1-sigma at (detected) standstill [m/s], or None: off."""
        kind = STANDSTILL_STD if self.aiding.vehicle in ("ground", "static") else None
        return _value(self.aiding.standstill_std, kind)

    @property
    def odometer_sigma(self) -> float | None:
        """The wheel-odometer 1-sigma [m/s] (and with it the scale-factor state), or None:
        no odometer (``"auto"`` becomes a value when a run gets odometry: :meth:`resolve`)."""
        return _value(self.aiding.odometer_std, None)

    @property
    def mount_sigma(self) -> float | None:
        """The prior 1-sigma [rad] of the mounting pitch and yaw error states, or None."""
        return _value(self.aiding.mount_std, None)

    @property
    def lever_sigma(self) -> float | None:
        """The prior 1-sigma [m] of the lever-arm error states, or None."""
        return _value(self.aiding.lever_std, None)

    @property
    def site_sigma(self) -> float | None:
        """The 1-sigma [rad] of the site's latitude and longitude states, or None: exact."""
        return _value(self.sky.site_std, None)

    @property
    def heading_bias(self) -> str:
        """The heading-measurement bias state (docs/filter.md §5.7): ``"model"`` (auto: its
        variance from the heading rows' ``yaw_std_model``), ``"fixed"`` (a value: that
        1-sigma [rad], the rows lose ``yaw_std_correlated``) or ``"off"``."""
        std = self.sky.heading_bias_std
        return "model" if std == AUTO else OFF if std == OFF else "fixed"

    @property
    def heading_bias_sigma(self) -> float | None:
        """The initial 1-sigma [rad] of the heading-bias state: the value for ``"fixed"``,
        0 for ``"model"`` (the images' model parts set it,
        :class:`polins.fusion.sky_states.ModelPart`), None when off."""
        mode = self.heading_bias
        if mode == OFF:
            return None
        return 0.0 if mode == "model" else float(self.sky.heading_bias_std)

    @property
    def use_scale_factors(self) -> bool:
        """Whether the scale-factor errors are modelled (``"auto"``: for a MEMS-grade model
        whose scale factors are not both switched off)."""
        if self.noise.scale_factors == AUTO:
            model = self.imu
            return (
                model.grade == "mems" and (model.gyro_scale_factor + model.accel_scale_factor) > 0
            )
        return bool(self.noise.scale_factors)

    def yaw_sigma(self, yaw_std: Any) -> Any:
        """The 1-sigma [rad] a heading row's ``yaw_std`` is fused with: times ``yaw_std_scale``,
        ``yaw_floor_deg`` added in quadrature (:class:`~polins.fusion.parts.Noise`)."""
        noise = self.noise
        return scaled_sigma(yaw_std, noise.yaw_std_scale, noise.yaw_floor_deg)

    def sun_sigma(self, sun_std: Any) -> Any:
        """The 1-sigma [rad] a sun row's ``sun_std`` is fused with (``sun_std_scale``,
        ``sun_floor_deg``)."""
        noise = self.noise
        return scaled_sigma(sun_std, noise.sun_std_scale, noise.sun_floor_deg)

    def resolve(
        self, *, priors: bool = False, sun_azimuth_only: bool = False, odometry: bool = False
    ) -> FuseConfig:
        """The configuration of one run: its ``"auto"`` choices that depend on the inputs
        made (the tilt coupling when the measurements carry the prior columns, the no-clock
        mode when they carry ``sun_azimuth_b`` only, the odometer's sigma when odometry is
        given). An explicit ``no_clock=False`` with such measurements is an error."""
        changes: dict[str, Any] = {}
        if self.gating.tilt_coupling == AUTO:
            changes["tilt_coupling"] = priors
        if sun_azimuth_only:
            if self.sky.no_clock is False:
                raise UserInputError(
                    "no_clock=off but the measurements carry only sun_azimuth_b (no yaw, no sun_n)"
                )
            changes["no_clock"] = True
        if odometry and self.aiding.odometer_std == AUTO:
            changes["odometer_std"] = ODOMETER_STD
        return self.replace(**changes) if changes else self

    # ---------------------------------------------------------------- reporting
    def options(self) -> dict[str, Any]:
        """Every option by its flat name (the parts' fields)."""
        return {f.name: getattr(getattr(self, part), f.name)
                for part, cls in PARTS.items() for f in dataclasses.fields(cls)}  # fmt: skip

    def check_backend(self, backend: str) -> None:
        """Raise ``UserInputError`` if an option set away from its default does not apply
        to ``backend``."""
        if backend not in BACKENDS:
            raise UserInputError(f"backend={backend!r}: expected one of {BACKENDS}")
        for name, value in self.options().items():
            f = OPTION_FIELDS[name]
            if backend not in f.metadata["backends"] and value != f.default:
                only = "/".join(f.metadata["backends"])
                raise UserInputError(f"option {name} applies to the {only} backend only")

    def changes(self) -> dict[str, Any]:
        """The options that differ from their defaults (for run stamps and reports)."""
        out: dict[str, Any] = {"imu_model": self.imu.name}
        if self.site is not None:
            out["site"] = dataclasses.asdict(self.site)
        out.update({k: v for k, v in self.options().items() if v != OPTION_FIELDS[k].default})
        return out


def _value(value: float | str | bool, auto: float | None) -> float | None:
    """An option's number in use: the value given, ``auto`` for "auto", None for "off"."""
    if value == OFF:
        return None
    if value == AUTO:
        return auto
    return float(value)


def _imu_model(model: Any) -> ImuModel:
    if isinstance(model, str | Path):
        return load_imu(model)
    if not isinstance(model, ImuModel):
        raise UserInputError(
            f"imu_model must be a model name, a TOML path or an ImuModel, got {model!r}"
        )
    return model


def _site(site: Any) -> Site:
    try:
        return Site.coerce(site)
    except TypeError as exc:
        raise UserInputError(str(exc)) from None


def site_from_shorthand(site: Any, options: dict[str, Any]) -> Any:
    """``site``, or the site of the ``lat_deg``/``lon_deg``/``alt_m`` shorthand popped from
    ``options`` [deg, deg, m] (both latitude and longitude needed; not with ``site``)."""
    given = {k: options.pop(k) for k in _SITE_KEYS if options.get(k) is not None}
    for k in _SITE_KEYS:
        options.pop(k, None)
    if not given:
        return site
    if site is not None:
        raise UnknownOptionError("give either site or lat_deg/lon_deg/alt_m, not both")
    if "lat_deg" not in given or "lon_deg" not in given:
        raise UnknownOptionError("a site needs both lat_deg and lon_deg (alt_m is optional)")
    return Site(given["lat_deg"], given["lon_deg"], given.get("alt_m", 0.0))


def parse_option_value(name: str, text: str) -> Any:
    """The value of ``--set name=text`` (:func:`coerce_option`)."""
    return coerce_option(name.strip(), text)


def config_from_mapping(table: Mapping[str, Any], base: FuseConfig | None = None) -> FuseConfig:
    """A config from a mapping of option names (``base`` with them)."""
    return FuseConfig.from_options(base, **dict(table))


class LogLike(Protocol):
    """What :meth:`FuseConfig.from_log` reads of a :class:`polins.io.Log`."""

    @property
    def manifest_path(self) -> Path: ...

    @property
    def manifest(self) -> dict[str, dict[str, Any]]: ...

    @property
    def imu_model(self) -> ImuModel: ...

    @property
    def site(self) -> Site: ...


def _vehicle_options(vehicle: Mapping[str, Any], path: str | Path) -> dict[str, Any]:
    """The :class:`FuseConfig` options of a manifest's ``[vehicle]`` table (degrees
    converted to radians; a sigma of 0 is off)."""
    opts: dict[str, Any] = {}
    if "kind" in vehicle:
        if vehicle["kind"] not in VEHICLE_KINDS:
            raise UserInputError(
                f"{path}: key 'vehicle.kind' = {vehicle['kind']!r}: expected one of "
                f"{', '.join(repr(k) for k in VEHICLE_KINDS)}"
            )
        opts["vehicle"] = vehicle["kind"]
    if "mount_rpy_deg" in vehicle:
        opts["mount_rpy"] = tuple(math.radians(v) for v in vehicle["mount_rpy_deg"])
    if "mount_std_deg" in vehicle:
        opts["mount_std"] = math.radians(vehicle["mount_std_deg"]) or OFF
    if "lever_arm_b" in vehicle:
        opts["lever_arm_b"] = tuple(vehicle["lever_arm_b"])
    if "lever_std" in vehicle:
        opts["lever_std"] = float(vehicle["lever_std"]) or OFF
    if "odometer" in vehicle and "odometer_std" in vehicle:
        opts["odometer_std"] = vehicle["odometer_std"]
    return opts


def _check_filter_key(key: str, path: str | Path) -> None:
    """A key of a manifest's ``[filter]`` table is a flat option name (not the IMU model
    or the site, which are ``[log]``'s)."""
    if key in ("imu_model", "site", *_SITE_KEYS):
        raise UserInputError(
            f"{path}: unknown key 'filter.{key}' (the IMU model and the site are [log]'s)"
        )
    if key not in OPTION_FIELDS:
        error = str(unknown_option(key))
        close = difflib.get_close_matches(key, option_names(), n=1)
        hint = f"; did you mean 'filter.{close[0]}'?" if close else ""
        detail = error if "unknown" not in error else f"unknown key 'filter.{key}'{hint}"
        raise UserInputError(f"{path}: {detail}")


def config_from_manifest(
    manifest: Mapping[str, Mapping[str, Any]],
    imu_model: ImuModel | str | Path,
    site: Site | None,
    path: str | Path = "manifest.toml",
) -> FuseConfig:
    """The configuration of a log's manifest (:func:`polins.io.parse_manifest`'s tables):
    the IMU model and the site, the ``[vehicle]`` table's options (degrees converted; a
    sigma of 0 is off; an odometer file without ``odometer_std`` gets ``"auto"``), then
    the ``[filter]`` table's options by their flat names. A bad key or value is a one-line
    ``UserInputError`` naming the manifest, the table and the key."""
    opts = _vehicle_options(manifest.get("vehicle", {}), path)
    try:
        base = FuseConfig(imu_model, site, **opts)
    except UserInputError as exc:
        raise UserInputError(f"{path}: table [vehicle]: {exc}") from None
    table = manifest.get("filter", {})
    for key in table:
        _check_filter_key(key, path)
    try:
        config = base.replace(**table)
    except UserInputError as exc:
        raise UserInputError(f"{path}: table [filter]: {exc}") from None
    # a tuned IMU model's [filter] table was fitted on top of the manifest's: it wins
    tuned = dict(base.imu.filter_options)
    return config.replace(**tuned) if tuned else config


def model_options(model: ImuModel) -> dict[str, dict[str, Any]]:
    """A tuned IMU model's ``[filter]`` options by part (:func:`split_options`, values
    parsed by :func:`coerce_option`); a bad key or value is a one-line ``UserInputError``
    naming the model file."""
    if not model.filter_options:
        return split_options({})
    for key, _ in model.filter_options:
        _check_filter_key(key, model.path)
    try:
        return split_options({k: coerce_option(k, v) for k, v in model.filter_options})
    except UserInputError as exc:
        raise UserInputError(f"{model.path}: table [filter]: {exc}") from None


def config_with_site(config: FuseConfig | None, *, stacklevel: int = 3) -> FuseConfig:
    """``config`` (default: all defaults) with a site: when none is given, the one
    ``UserWarning`` that says which site is assumed (:data:`polins.site.PAPER_SITE`)."""
    config = config or FuseConfig()
    if config.site is not None:
        return config
    warnings.warn(
        f"no site given (FuseConfig.site or lat_deg/lon_deg/alt_m); assuming the paper's "
        f"site {PAPER_SITE} for gravity; the Earth rate is not mechanized and the process "
        "noise covers it",
        UserWarning,
        stacklevel=stacklevel,
    )
    return dataclasses.replace(config, site=PAPER_SITE, site_is_assumed=True)


def scaled_sigma(std: Any, scale: float, floor_deg: float) -> Any:
    """``hypot(scale * std, radians(floor_deg))``: a measurement 1-sigma [rad] with a noise
    scale [-] and a floor [deg] (scalar or array; exactly ``std`` for 1 and 0)."""
    if scale == 1.0 and floor_deg == 0.0:
        return std
    return np.hypot(np.asarray(std, dtype=float) * scale, math.radians(floor_deg))


def scaled_measurement_noise(measurements: pd.DataFrame, config: FuseConfig) -> pd.DataFrame:
    """The measurements with the configured measurement noise (:class:`Noise`): each
    ``yaw_std`` / ``sun_std`` multiplied by its scale, then its floor added in quadrature.
    Returns ``measurements`` itself when the noise is the rows' own."""
    noise = config.noise
    terms = {"yaw_std": (noise.yaw_std_scale, noise.yaw_floor_deg),
             "sun_std": (noise.sun_std_scale, noise.sun_floor_deg)}  # fmt: skip
    todo = {c: t for c, t in terms.items() if c in measurements.columns and t != (1.0, 0.0)}
    if not todo:
        return measurements
    out = measurements.copy()
    for col, (scale, floor_deg) in todo.items():
        out[col] = scaled_sigma(out[col].to_numpy(dtype=float), scale, floor_deg)
    return out


__all__ = [
    "AUTO",
    "BACKENDS",
    "OFF",
    "PARTS",
    "Aiding",
    "FuseConfig",
    "Gating",
    "GraphSolver",
    "Initial",
    "LogLike",
    "Noise",
    "Output",
    "SkyStates",
    "coerce_option",
    "config_from_manifest",
    "config_from_mapping",
    "config_with_site",
    "model_options",
    "option_names",
    "option_table",
    "parse_option_value",
    "scaled_measurement_noise",
    "scaled_sigma",
    "site_from_shorthand",
]
