"""The one configuration of the fusion: every filter and graph option, its unit and default, defined once.

:class:`FuseConfig` is used by ``polins.fuse``, ``build_filter``, the GTSAM graph, the
streaming loop, the manifest's ``[filter]`` table and the CLI's ``--set KEY=VALUE``. Each
option is one dataclass field whose metadata holds its description (with the unit) and the
backends it applies to; :func:`option_table` renders them for docs and ``--help``. Options
are SI and radians unless the name carries another unit.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from polins.errors import UnknownOptionError, UserInputError
from polins.models import ImuModel, load_imu
from polins.site import PAPER_SITE, Site

BACKENDS = ("eskf", "graph")
SOLVERS = ("batch", "isam2", "fixed_lag")
OPTIMIZERS = ("gauss-newton", "levenberg-marquardt")
GRAPH_OUTPUTS = ("samples", "keyframes")
VEHICLE_KINDS = ("free", "ground", "static")
NHC_STD_GROUND = 0.05  # [m/s] non-holonomic 1-sigma of a ground vehicle (docs/filter.md)
STANDSTILL_STD = 0.02  # [m/s] zero-velocity 1-sigma at detected standstill
ODOMETER_STD = 0.05  # [m/s] wheel-odometer speed 1-sigma when none is given


def _opt(default: Any, doc: str, backends: tuple[str, ...] = BACKENDS, **kw: Any) -> Any:
    """A config field: its default, its one-line description [unit], the backends using it."""
    if isinstance(default, list | dict | set):
        raise UserInputError("mutable defaults are not allowed")
    return field(default=default, metadata={"doc": doc, "backends": backends}, **kw)


ESKF = ("eskf",)
GRAPH = ("graph",)


@dataclass(frozen=True)
class FuseConfig:
    """Configuration of the fusion (both backends). Build with :meth:`from_options`.

    Every field is documented in its metadata; ``option_table()`` lists them. Fields that
    apply to one backend only are refused by the other when set to a non-default value.
    """

    imu_model: ImuModel | str = _opt(
        "mems-typical", "IMU error model: shipped name, TOML path or ImuModel"
    )
    site: Site | None = _opt(
        None,
        "start position (polins.Site: lat_deg, lon_deg, alt_m); None: no site known, "
        "reported as a warning",
    )
    vel_n0: tuple[float, float, float] = _opt((0.0, 0.0, 0.0), "initial ENU velocity [m/s]")
    site_assumed: bool = _opt(
        False,
        "the site is a stand-in because none was given (set by the one warning): the Earth "
        "rate is then not mechanized and the process noise covers it (docs/filter.md)",
    )
    earth_rate: bool | None = _opt(
        None,
        "mechanize the Earth and transport rates (None: whenever the site is known; "
        "false: the world does not rotate, e.g. a simulation without Earth rotation)",
    )
    gate_prob: float | None = _opt(
        0.9973, "chi-square gate probability of the innovations (None: no gate)"
    )
    align_s: float = _opt(1.0, "static levelling window of the self-alignment [s]")
    att_std0: tuple[float, float, float] = _opt(
        (math.radians(1.0),) * 3, "initial attitude 1-sigma when rot_nb0 is given [rad]"
    )
    vel_std0: float = _opt(0.1, "initial velocity 1-sigma [m/s]")
    pos_std0: float = _opt(1.0, "initial position 1-sigma [m]")
    use_sun: bool = _opt(True, "use a row's sun vector (2-DOF) instead of its yaw")
    tilt_coupling: bool | None = _opt(
        None,
        "tilt-coupled yaw model (docs/measurement.md); None: on when the table has the "
        "prior_roll/pitch/yaw columns",
    )
    vehicle: str = _opt(
        "free",
        f"vehicle kind, one of {VEHICLE_KINDS}: 'ground' turns on the non-holonomic "
        "constraint and zero-velocity updates at detected standstill, 'static' zero-velocity "
        "updates throughout (docs/filter.md, 'Ground-vehicle aiding')",
    )
    nhc_std: float | None = _opt(
        None,
        f"non-holonomic constraint 1-sigma [m/s]; None: from the vehicle kind "
        f"({NHC_STD_GROUND} for 'ground', else off); inf: off",
    )
    nhc_rate_hz: float = _opt(
        10.0, "rate of the non-holonomic constraint and the standstill updates [Hz]"
    )
    standstill_std: float | None = _opt(
        None,
        f"zero-velocity 1-sigma at detected standstill [m/s]; None: from the vehicle kind "
        f"({STANDSTILL_STD} for 'ground' and 'static', else off); inf: off",
    )
    standstill_window_s: float = _opt(0.5, "window of the standstill detector [s]")
    mount_rpy: tuple[float, float, float] = _opt(
        (0.0, 0.0, 0.0), "roll, pitch, yaw of the IMU body in the vehicle frame [rad] (mat_vb)"
    )
    lever_arm_b: tuple[float, float, float] = _opt(
        (0.0, 0.0, 0.0),
        "from the IMU to the vehicle's non-holonomic reference point (e.g. the rear axle's "
        "centre), body axes [m]",
    )
    mount_std: float | None = _opt(
        None,
        "1-sigma of the errors of mount_rpy's pitch and yaw [rad]: two states (random "
        "constants) the non-holonomic constraint and the odometer observe while the vehicle "
        "moves; None or 0: the mounting is exact (docs/filter.md, 'Ground-vehicle aiding')",
    )
    lever_std: float | None = _opt(
        None,
        "1-sigma of the errors of lever_arm_b per axis [m]: three states (random constants) "
        "the non-holonomic constraint and the odometer observe while the vehicle turns; "
        "None or 0: the lever arm is exact (docs/filter.md, 'Ground-vehicle aiding')",
    )
    odometer_std: float | None = _opt(
        None,
        f"wheel-odometer speed 1-sigma [m/s], with an odometer scale-factor state; "
        f"None: no odometer (polins.fuse(odometry=...) then uses {ODOMETER_STD})",
    )
    odometer_scale_std: float = _opt(0.02, "initial 1-sigma of the odometer scale factor [-]")
    zupt_std: float | None = _opt(None, "zero-velocity 1-sigma at the stationary times [m/s]")
    stationary: tuple[float, ...] = _opt((), "times at which the vehicle stands still [s]")
    output_rate_hz: float | None = _opt(None, "output rows per second (None: every IMU sample)")
    max_gap_s: float | None = _opt(
        None, "longest IMU gap bridged [s] (None: 5 median sample intervals)"
    )
    time_tol_s: float = _opt(1e-6, "measurement times this close to an IMU sample use it [s]")
    # yaw acquisition and recovery (docs/filter.md, "Yaw acquisition and recovery")
    acquire_k: int = _opt(3, "yaw acquisition: this many of the last acquire_n headings must agree")
    acquire_n: int = _opt(5, "yaw acquisition: headings considered for the consensus")
    reacquire_after: int = _opt(
        5, "re-acquire the yaw after this many consecutive gate rejections of headings", ESKF
    )
    # ESKF only
    scale_factors: bool | None = _opt(
        None,
        "gyro/accel scale-factor errors: ESKF states (21 states), graph variables; "
        "None: on for MEMS-grade IMU models",
    )
    reset_interval_s: float = _opt(
        20.0, "inject and zero the error state this long after the last reset [s]", ESKF
    )
    reset_angle_rad: float = _opt(
        0.005, "... or as soon as the attitude error estimate exceeds this [rad]", ESKF
    )
    cov_step_s: float = _opt(0.1, "longest covariance-propagation step [s]", ESKF)
    smooth: bool = _opt(False, "run the Rauch-Tung-Striebel smoother", ESKF)
    # the sky's error states (docs/filter.md, "Approximate site", "No clock",
    # "Heading-measurement bias")
    site_std: float | None = _opt(
        None,
        "1-sigma of the site's latitude and of its longitude [rad] (approximate site): the "
        "site error becomes two states seen by the yaw and sun updates; None: site exact",
    )
    no_clock: bool | None = _opt(
        None,
        "no-clock mode: the sun's ENU azimuth and its rate are states, the heading is "
        "relative; None: when the measurements carry sun_azimuth_b without yaw or sun_n",
    )
    sun_azimuth_rate_std: float = _opt(
        math.radians(24.0) / 3600.0,
        "no clock: 1-sigma of the sun's azimuth rate [rad/s] (24 deg/h: Harbin's largest; "
        "up to hundreds of deg/h near the subsolar point)",
    )
    heading_bias_std: float | None = _opt(
        None,
        "1-sigma of a Gauss-Markov heading-measurement bias [rad] (sky-model errors "
        "correlated from image to image; the rows lose yaw_std_correlated); None: from "
        "the images, the part of each heading row's yaw_std_model beyond twice its "
        "yaw_std_noise (docs/filter.md 5.7); inf: no bias state",
    )
    heading_bias_tau_s: float = _opt(300.0, "correlation time of the heading-measurement bias [s]")
    # graph only
    solver: str = _opt("batch", f"graph solver, one of {SOLVERS}", GRAPH)
    lag_s: float = _opt(10.0, "window of the fixed-lag smoother [s]", GRAPH)
    max_keyframe_dt_s: float = _opt(1.0, "longest interval between keyframes [s]", GRAPH)
    max_iterations: int = _opt(20, "Gauss-Newton iterations of the batch solver", GRAPH)
    integration_std: float = _opt(
        1e-2, "GTSAM position-integration noise density [m/sqrt(s)]", GRAPH
    )
    graph_output: str = _opt(
        "samples", f"report IMU samples or keyframes, one of {GRAPH_OUTPUTS}", GRAPH
    )
    max_gate_rounds: int = _opt(
        10, "batch solver: most re-solves after gating post-fit outliers", GRAPH
    )
    optimizer: str = _opt("gauss-newton", f"batch optimizer, one of {OPTIMIZERS}", GRAPH)

    def __post_init__(self) -> None:
        model = self.imu_model
        if isinstance(model, str | Path):
            object.__setattr__(self, "imu_model", load_imu(model))
        elif not isinstance(model, ImuModel):
            raise UserInputError(
                f"imu_model must be a model name, a TOML path or an ImuModel, got {model!r}"
            )
        if self.site is not None:
            object.__setattr__(self, "site", Site.coerce(self.site))
        object.__setattr__(self, "vel_n0", _floats(self.vel_n0, 3, "vel_n0"))
        att = self.att_std0
        att = (att,) * 3 if isinstance(att, int | float) else att
        object.__setattr__(self, "att_std0", _floats(att, 3, "att_std0"))
        object.__setattr__(
            self, "stationary", _floats(self.stationary, len(self.stationary), "stationary")
        )
        object.__setattr__(self, "mount_rpy", _floats(self.mount_rpy, 3, "mount_rpy"))
        object.__setattr__(self, "lever_arm_b", _floats(self.lever_arm_b, 3, "lever_arm_b"))
        _check(self)

    @property
    def imu(self) -> ImuModel:
        """The resolved IMU model."""
        assert isinstance(self.imu_model, ImuModel)  # resolved in __post_init__
        return self.imu_model

    @property
    def mechanize_earth_rate(self) -> bool:
        """Whether the Earth and transport rates are mechanized: whenever the site is known
        and the heading is absolute (not ``no_clock``), unless ``earth_rate`` says otherwise."""
        if self.earth_rate is None:
            return self.site is not None and not self.site_assumed and not self.no_clock
        return bool(self.earth_rate)

    @property
    def uncovered_earth_rate(self) -> bool:
        """True when the world rotates but the Earth rate is not mechanized (no site known,
        or no clock: the heading is relative, so the horizontal Earth rate cannot be
        projected): the process noise then covers it (docs/filter.md, "Without a site")."""
        return self.earth_rate is None and (self.site_assumed or bool(self.no_clock))

    @property
    def nhc_sigma(self) -> float | None:
        """The non-holonomic 1-sigma in use [m/s] (``nhc_std``, else the vehicle kind's), or
        None: off."""
        return _sigma_in_use(self.nhc_std, NHC_STD_GROUND if self.vehicle == "ground" else None)

    @property
    def mount_sigma(self) -> float | None:
        """The prior 1-sigma [rad] of the mounting pitch and yaw error states, or None: no
        such states (``mount_std`` None or 0)."""
        return float(self.mount_std) if self.mount_std else None

    @property
    def lever_sigma(self) -> float | None:
        """The prior 1-sigma [m] of the lever-arm error states, or None: no such states
        (``lever_std`` None or 0)."""
        return float(self.lever_std) if self.lever_std else None

    @property
    def standstill_sigma(self) -> float | None:
        """The zero-velocity 1-sigma at (detected) standstill [m/s], or None: off."""
        kind_default = STANDSTILL_STD if self.vehicle in ("ground", "static") else None
        return _sigma_in_use(self.standstill_std, kind_default)

    @property
    def heading_bias(self) -> str:
        """The heading-measurement bias state (docs/filter.md §5.7): ``"model"`` (None: its
        variance from the heading rows' ``yaw_std_model``), ``"fixed"`` (a value: that
        1-sigma [rad], the rows lose ``yaw_std_correlated``) or ``"off"`` (inf)."""
        if self.heading_bias_std is None:
            return "model"
        return "off" if math.isinf(self.heading_bias_std) else "fixed"

    @property
    def heading_bias_sigma(self) -> float | None:
        """The initial 1-sigma [rad] of the heading-bias state: the value for ``"fixed"``,
        0 for ``"model"`` (the images' model parts set it,
        :class:`polins.fusion.sky_states.ModelPart`), None when off."""
        mode = self.heading_bias
        if mode == "off":
            return None
        return 0.0 if mode == "model" else float(self.heading_bias_std)  # type: ignore[arg-type]

    @property
    def use_scale_factors(self) -> bool:
        """Whether the scale-factor errors are modelled (``scale_factors``; None: for a
        MEMS-grade model whose scale factors are not both switched off)."""
        if self.scale_factors is None:
            model = self.imu
            return (
                model.grade == "mems" and (model.gyro_scale_factor + model.accel_scale_factor) > 0
            )
        return bool(self.scale_factors)

    @classmethod
    def from_options(cls, base: FuseConfig | None = None, /, **options: Any) -> FuseConfig:
        """A config from keyword options (an unknown name is a ``TypeError`` with a hint).

        ``lat_deg``, ``lon_deg`` and ``alt_m`` are accepted as a shorthand for ``site``.
        Values given replace those of ``base`` (default: all defaults).
        """
        opts = dict(options)
        if {"lat_deg", "lon_deg", "alt_m"} & set(opts):
            if "site" in opts:
                raise UnknownOptionError("give either site or lat_deg/lon_deg/alt_m, not both")
            if "lat_deg" not in opts or "lon_deg" not in opts:
                raise UnknownOptionError(
                    "a site needs both lat_deg and lon_deg (alt_m is optional)"
                )
            opts["site"] = Site(opts.pop("lat_deg"), opts.pop("lon_deg"), opts.pop("alt_m", 0.0))
        names = option_names()
        unknown = [k for k in opts if k not in names]
        if unknown:
            hints = []
            for k in unknown:
                close = difflib.get_close_matches(k, names, n=1)
                hints.append(f"{k!r}" + (f" (did you mean {close[0]!r}?)" if close else ""))
            raise UserInputError(
                f"unknown fuse option(s) {', '.join(hints)}; valid: {', '.join(names)}"
            )
        return dataclasses.replace(base or cls(), **opts)

    def check_backend(self, backend: str) -> None:
        """Raise ``ValueError`` if an option set away from its default does not apply to ``backend``."""
        if backend not in BACKENDS:
            raise UserInputError(f"backend={backend!r}: expected one of {BACKENDS}")
        default = FuseConfig(imu_model=self.imu_model)
        for f in dataclasses.fields(self):
            if backend not in f.metadata["backends"] and getattr(self, f.name) != getattr(
                default, f.name
            ):
                only = "/".join(f.metadata["backends"])
                raise UserInputError(f"option {f.name} applies to the {only} backend only")

    def changes(self) -> dict[str, Any]:
        """The options that differ from their defaults (for run stamps and reports)."""
        default = FuseConfig(imu_model=self.imu_model)
        out: dict[str, Any] = {"imu_model": self.imu.name}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name != "imu_model" and value != getattr(default, f.name):
                out[f.name] = dataclasses.asdict(value) if isinstance(value, Site) else value
        return out


def _floats(value: Any, n: int, name: str) -> tuple[float, ...]:
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise UserInputError(f"{name} must be {n} numbers, got {value!r}") from None
    if len(out) != n or not all(math.isfinite(v) for v in out):
        raise UserInputError(f"{name} must be {n} finite numbers, got {value!r}")
    return out


def _sigma_in_use(value: float | None, default: float | None) -> float | None:
    """An option's sigma: the value given (inf: off), else the default (None: off)."""
    if value is None:
        return default
    return None if math.isinf(value) else float(value)


def _check(c: FuseConfig) -> None:
    """Range checks of every option (one-line ``ValueError`` naming the option)."""
    positive = ("align_s", "vel_std0", "pos_std0", "nhc_rate_hz", "time_tol_s", "cov_step_s",
                "lag_s", "max_keyframe_dt_s", "integration_std", "standstill_window_s",
                "odometer_scale_std", "sun_azimuth_rate_std", "heading_bias_tau_s")  # fmt: skip
    for name in positive:
        value = getattr(c, name)
        if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
            raise UserInputError(f"{name} must be a finite number > 0, got {value!r}")
    for name in ("nhc_std", "standstill_std", "heading_bias_std"):
        value = getattr(c, name)
        if value is not None and not (isinstance(value, int | float) and value > 0):
            unit = "rad" if name == "heading_bias_std" else "m/s"
            raise UserInputError(f"{name} must be > 0 [{unit}], inf (off) or None, got {value!r}")
    if c.vehicle not in VEHICLE_KINDS:
        raise UserInputError(f"vehicle={c.vehicle!r}: expected one of {VEHICLE_KINDS}")
    for name in ("zupt_std", "output_rate_hz", "max_gap_s", "odometer_std", "site_std"):
        value = getattr(c, name)
        if value is not None and not (math.isfinite(value) and value > 0):
            raise UserInputError(f"{name} must be > 0 or None, got {value!r}")
    for name, unit in (("mount_std", "rad"), ("lever_std", "m")):
        value = getattr(c, name)
        if value is not None and not (math.isfinite(value) and value >= 0):
            raise UserInputError(f"{name} must be >= 0 [{unit}] or None, got {value!r}")
    if not all(a > 0 for a in c.att_std0):
        raise UserInputError(f"att_std0 must be 3 positive sigmas [rad], got {c.att_std0}")
    if c.gate_prob is not None and not 0.0 < c.gate_prob < 1.0:
        raise UserInputError(f"gate_prob must be in (0, 1) or None, got {c.gate_prob}")
    if not c.reset_interval_s >= 0.0:
        raise UserInputError(f"reset_interval_s must be >= 0 [s], got {c.reset_interval_s}")
    if not c.reset_angle_rad > 0.0:
        raise UserInputError(f"reset_angle_rad must be > 0 [rad], got {c.reset_angle_rad}")
    for name in ("max_iterations", "max_gate_rounds", "acquire_k", "acquire_n", "reacquire_after"):
        value = getattr(c, name)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise UserInputError(f"{name} must be an integer >= 1, got {value!r}")
    for name, allowed in (("solver", SOLVERS), ("optimizer", OPTIMIZERS),
                          ("graph_output", GRAPH_OUTPUTS)):  # fmt: skip
        if getattr(c, name) not in allowed:
            raise UserInputError(f"{name}={getattr(c, name)!r}: expected one of {allowed}")
    if c.acquire_k > c.acquire_n or c.acquire_n > c.reacquire_after:
        raise UserInputError(
            f"need acquire_k <= acquire_n <= reacquire_after, got {c.acquire_k}, "
            f"{c.acquire_n}, {c.reacquire_after}"
        )
    if c.stationary and c.zupt_std is None:
        raise UserInputError("stationary times need zupt_std [m/s]")


def option_names() -> list[str]:
    """Names of all options (the fields of :class:`FuseConfig`)."""
    return [f.name for f in dataclasses.fields(FuseConfig)]


def option_table(backends: Sequence[str] = BACKENDS) -> list[tuple[str, str, str, str]]:
    """``(name, default, backends, description)`` of every option, for docs and ``--help``."""
    rows = []
    for f in dataclasses.fields(FuseConfig):
        if set(f.metadata["backends"]) & set(backends):
            rows.append((f.name, repr(f.default), "/".join(f.metadata["backends"]),
                         f.metadata["doc"]))  # fmt: skip
    return rows


def parse_option_value(name: str, text: str) -> Any:
    """The value of ``--set name=text`` (CLI) or a manifest entry, typed as the field."""
    fields = {f.name: f for f in dataclasses.fields(FuseConfig)}
    if name not in fields:
        close = difflib.get_close_matches(name, list(fields), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise UnknownOptionError(f"unknown filter option {name!r}{hint}")
    default = fields[name].default
    low = text.strip().lower()
    if low in ("none", "null", "off") and (default is None or "None" in str(fields[name].type)):
        return None
    if isinstance(default, bool) or "bool" in str(fields[name].type):
        if low in ("true", "1", "yes", "on"):
            return True
        if low in ("false", "0", "no", "off"):
            return False
        raise UserInputError(f"{name}={text!r}: expected true or false")
    if isinstance(default, tuple):
        return tuple(float(v) for v in text.split(","))
    if isinstance(default, int):
        return int(text)
    if isinstance(default, float) or default is None:
        try:
            return float(text)
        except ValueError:
            raise UserInputError(f"{name}={text!r}: expected a number") from None
    return text


def config_from_mapping(table: Mapping[str, Any], base: FuseConfig | None = None) -> FuseConfig:
    """A config from a mapping of option names (a manifest ``[filter]`` table)."""
    return FuseConfig.from_options(base, **dict(table))


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
    return FuseConfig.from_options(config, site=PAPER_SITE, site_assumed=True)
