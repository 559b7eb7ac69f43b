"""The parts of the fusion's configuration and the one parser of every option's value.

Each part is a frozen dataclass with one concern (docs/filter.md, "Options"); together they
make :class:`polins.fusion.config.FuseConfig`:

* :class:`Aiding` -- the vehicle and its velocity aiding (NHC, standstill, odometer, mounting),
* :class:`Initial` -- the initial state and its uncertainty, the levelling window,
* :class:`Noise` -- the noise models beyond the IMU model's (scale factors, measurement noise),
* :class:`Gating` -- what a measurement updates and how outliers and IMU gaps are handled,
* :class:`SkyStates` -- the Earth rate and the sky's error states (site, clock, heading bias),
* :class:`GraphSolver` -- the GTSAM backend's solver,
* :class:`Output` -- what the run reports.

Every option has one flat name, unique across the parts. Its value, from Python, a TOML
table or the text of ``--set``, is parsed by :func:`coerce_option` only: an option that can
be off takes ``"off"``; an automatic choice is spelled ``"auto"``; a number may be text.
A name that is not an option fails with one line: what replaces it, or the closest name.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from polins.errors import UnknownOptionError, UserInputError

BACKENDS = ("eskf", "graph")
SOLVERS = ("batch", "isam2", "fixed_lag")
OPTIMIZERS = ("gauss-newton", "levenberg-marquardt")
GRAPH_OUTPUTS = ("samples", "keyframes")
VEHICLE_KINDS = ("free", "ground", "static")
NHC_STD_GROUND = 0.05  # [m/s] non-holonomic 1-sigma of a ground vehicle (docs/filter.md)
STANDSTILL_STD = 0.02  # [m/s] zero-velocity 1-sigma at detected standstill
ODOMETER_STD = 0.05  # [m/s] wheel-odometer speed 1-sigma when odometry is given
OUTPUT_RATE_HZ = 10.0  # [Hz] solution rows per second by default (docs/outputs.md)
AUTO, OFF, IMU_RATE = "auto", "off", "imu"
TABLE_FORMATS = ("csv", "parquet")

_NOT_OPTIONS: dict[str, str] = {
    "zupt_std": "is not an option: give zero-velocity rows at the standstill times (a zupt_std "
    "column of the measurements, polins.fusion.vehicle.with_standstill), or "
    "vehicle='ground' / 'static' (standstill_std)",
    "stationary": "is not an option: give zero-velocity rows at the standstill times (a "
    "zupt_std column of the measurements, polins.fusion.vehicle.with_standstill)",
    "site_assumed": "is set by polins when no site is given (FuseConfig.site)",
    "time_tol_s": "is an implementation constant (polins.fusion.config.TIME_TOL_S)",
    "cov_step_s": "is an implementation constant (polins.fusion.config.COV_STEP_S)",
    "integration_std": "is an implementation constant (polins.fusion.config.INTEGRATION_STD)",
    "max_gate_rounds": "is an implementation constant (polins.fusion.config.MAX_GATE_ROUNDS)",
    "reset_interval_s": "is an implementation constant (polins.fusion.config.RESET_INTERVAL_S)",
    "reset_angle_rad": "is an implementation constant (polins.fusion.config.RESET_ANGLE_RAD)",
    "nhc_rate_hz": "is an implementation constant (polins.fusion.config.NHC_RATE_HZ)",
    "standstill_window_s": "is an implementation constant "
    "(polins.fusion.config.STANDSTILL_WINDOW_S)",
    "odometer_scale_std": "is an implementation constant (polins.fusion.config.ODOMETER_SCALE_STD)",
    "sun_azimuth_rate_std": "is an implementation constant "
    "(polins.fusion.config.SUN_AZIMUTH_RATE_STD)",
    "max_keyframe_dt_s": "is an implementation constant (polins.fusion.config.MAX_KEYFRAME_DT_S)",
    "max_iterations": "is an implementation constant (polins.fusion.config.MAX_ITERATIONS)",
}


def _opt(
    default: Any,
    doc: str,
    kind: str,
    *,
    special: tuple[str, ...] = (),
    backends: tuple[str, ...] = BACKENDS,
    choices: tuple[str, ...] = (),
) -> Any:
    """An option field: its default, its one-line description [unit], how its values are
    parsed (``kind``; ``special``: the words it takes besides values), its backends."""
    meta = {"doc": doc, "kind": kind, "special": special, "backends": backends,
            "choices": choices}  # fmt: skip
    return field(default=default, metadata=meta)


# ----------------------------------------------------------------------------- parts
@dataclass(frozen=True)
class Aiding:
    """The vehicle and its velocity aiding (docs/filter.md, "Ground-vehicle aiding")."""

    vehicle: str = _opt(
        "free",
        f"vehicle kind, one of {VEHICLE_KINDS}: 'ground' turns on the non-holonomic "
        "constraint and zero-velocity updates at detected standstill, 'static' zero-velocity "
        "updates throughout",
        "choice",
        choices=VEHICLE_KINDS,
    )
    nhc_std: float | str = _opt(
        AUTO,
        f"non-holonomic constraint 1-sigma [m/s]; auto: {NHC_STD_GROUND} for a 'ground' "
        "vehicle, else off",
        "positive",
        special=(AUTO, OFF),
    )
    standstill_std: float | str = _opt(
        AUTO,
        f"zero-velocity 1-sigma at (detected) standstill [m/s]; auto: {STANDSTILL_STD} for "
        "'ground' and 'static', else off",
        "positive",
        special=(AUTO, OFF),
    )
    odometer_std: float | str = _opt(
        AUTO,
        f"wheel-odometer speed 1-sigma [m/s], with an odometer scale-factor state; auto: "
        f"{ODOMETER_STD} when odometry is given; off: odometry ignored",
        "positive",
        special=(AUTO, OFF),
    )
    mount_rpy: tuple[float, float, float] = _opt(
        (0.0, 0.0, 0.0), "roll, pitch, yaw of the IMU body in the vehicle frame [rad] (mat_vb)",
        "vector3",
    )  # fmt: skip
    mount_std: float | str = _opt(
        OFF,
        "1-sigma of the errors of mount_rpy's pitch and yaw [rad]: two states (random "
        "constants) the non-holonomic constraint and the odometer observe while the vehicle "
        "moves; off: the mounting is exact",
        "positive",
        special=(OFF,),
    )
    lever_arm_b: tuple[float, float, float] = _opt(
        (0.0, 0.0, 0.0),
        "from the IMU to the vehicle's non-holonomic reference point (e.g. the rear axle's "
        "centre), body axes [m]",
        "vector3",
    )
    lever_std: float | str = _opt(
        OFF,
        "1-sigma of the errors of lever_arm_b per axis [m]: three states (random constants) "
        "the non-holonomic constraint and the odometer observe while the vehicle turns; "
        "off: the lever arm is exact",
        "positive",
        special=(OFF,),
    )

    def __post_init__(self) -> None:
        _coerce_fields(self)


@dataclass(frozen=True)
class Initial:
    """The initial state, its uncertainty and the self-alignment's levelling window."""

    vel_n0: tuple[float, float, float] = _opt(
        (0.0, 0.0, 0.0), "initial ENU velocity [m/s]", "vector3"
    )
    att_std0: tuple[float, float, float] = _opt(
        (math.radians(1.0),) * 3,
        "initial attitude 1-sigma when rot_nb0 is given [rad] (one value or three)",
        "sigma3",
    )
    vel_std0: float = _opt(0.1, "initial velocity 1-sigma [m/s]", "positive")
    pos_std0: float = _opt(1.0, "initial position 1-sigma [m]", "positive")
    align_s: float = _opt(1.0, "static levelling window of the self-alignment [s]", "positive")

    def __post_init__(self) -> None:
        _coerce_fields(self)


@dataclass(frozen=True)
class Noise:
    """Noise models beyond the IMU model's density terms: scale factors and the
    measurement noise (the values ``polins tune`` fits; docs/tuning.md)."""

    scale_factors: bool | str = _opt(
        AUTO,
        "gyro/accel scale-factor errors: ESKF states (21 states), graph variables; auto: on "
        "for MEMS-grade IMU models",
        "flag",
        special=(AUTO,),
    )
    yaw_std_scale: float = _opt(1.0, "factor on every heading row's yaw_std [-]", "positive")
    yaw_floor_deg: float = _opt(
        0.0, "floor added in quadrature to every yaw_std, after the scale [deg]", "nonnegative"
    )
    sun_std_scale: float = _opt(1.0, "factor on every sun row's sun_std [-]", "positive")
    sun_floor_deg: float = _opt(
        0.0, "floor added in quadrature to every sun_std, after the scale [deg]", "nonnegative"
    )

    def __post_init__(self) -> None:
        _coerce_fields(self)


@dataclass(frozen=True)
class Gating:
    """What a measurement row updates, and which innovations and IMU gaps are refused."""

    use_sun: bool = _opt(True, "use a row's sun vector (2-DOF) instead of its yaw", "flag")
    tilt_coupling: bool | str = _opt(
        AUTO,
        "tilt-coupled yaw model (docs/measurement.md); auto: on when the table has the "
        "prior_roll/pitch/yaw columns",
        "flag",
        special=(AUTO,),
    )
    gate_prob: float | str = _opt(
        0.9973, "chi-square gate probability of the innovations; off: no gate", "probability",
        special=(OFF,),
    )  # fmt: skip
    max_gap_s: float | str = _opt(
        AUTO, "longest IMU gap bridged [s]; auto: 5 median sample intervals", "positive",
        special=(AUTO,),
    )  # fmt: skip
    acquire_k: int = _opt(
        3, "yaw acquisition: this many of the last acquire_n headings must agree", "count"
    )
    acquire_n: int = _opt(5, "yaw acquisition: headings considered for the consensus", "count")
    reacquire_after: int = _opt(
        5, "re-acquire the yaw after this many consecutive gate rejections of headings", "count",
        backends=("eskf",),
    )  # fmt: skip

    def __post_init__(self) -> None:
        _coerce_fields(self)
        if not self.acquire_k <= self.acquire_n <= self.reacquire_after:
            raise UserInputError(
                f"need acquire_k <= acquire_n <= reacquire_after, got {self.acquire_k}, "
                f"{self.acquire_n}, {self.reacquire_after}"
            )


@dataclass(frozen=True)
class SkyStates:
    """The Earth rate and the sky's error states (docs/filter.md, "Approximate site",
    "No clock", "Heading-measurement bias")."""

    earth_rate: bool | str = _opt(
        AUTO,
        "mechanize the Earth and transport rates; auto: whenever the site is known and the "
        "heading absolute; off: the world does not rotate (a simulation without it)",
        "flag",
        special=(AUTO,),
    )
    site_std: float | str = _opt(
        OFF,
        "1-sigma of the site's latitude and of its longitude [rad] (approximate site): the "
        "site error becomes two states seen by the yaw and sun updates; off: site exact",
        "positive",
        special=(OFF,),
    )
    no_clock: bool | str = _opt(
        AUTO,
        "no-clock mode: the sun's ENU azimuth and its rate are states, the heading is "
        "relative; auto: when the measurements carry sun_azimuth_b without yaw or sun_n",
        "flag",
        special=(AUTO,),
    )
    heading_bias_std: float | str = _opt(
        AUTO,
        "1-sigma of a Gauss-Markov heading-measurement bias [rad] (sky-model errors "
        "correlated from image to image; the rows lose yaw_std_correlated); auto: from the "
        "images, the part of each heading row's yaw_std_model beyond twice its "
        "yaw_std_noise (docs/filter.md 5.7); off: no bias state",
        "positive",
        special=(AUTO, OFF),
    )
    heading_bias_tau_s: float = _opt(
        300.0, "correlation time of the heading-measurement bias [s]", "positive"
    )

    def __post_init__(self) -> None:
        _coerce_fields(self)


@dataclass(frozen=True)
class GraphSolver:
    """The GTSAM backend's solver (docs/filter.md, "Factor graph")."""

    solver: str = _opt(
        "batch", f"graph solver, one of {SOLVERS}", "choice", backends=("graph",),
        choices=SOLVERS,
    )  # fmt: skip
    lag_s: float = _opt(10.0, "window of the fixed-lag smoother [s]", "positive",
                        backends=("graph",))  # fmt: skip
    optimizer: str = _opt(
        "gauss-newton", f"batch optimizer, one of {OPTIMIZERS}", "choice", backends=("graph",),
        choices=OPTIMIZERS,
    )  # fmt: skip
    graph_output: str = _opt(
        "samples", f"report IMU samples or keyframes, one of {GRAPH_OUTPUTS}", "choice",
        backends=("graph",), choices=GRAPH_OUTPUTS,
    )  # fmt: skip

    def __post_init__(self) -> None:
        _coerce_fields(self)


@dataclass(frozen=True)
class Output:
    """What the run reports."""

    output_rate_hz: float | str = _opt(
        AUTO,
        f"solution rows per second [Hz]; auto: {OUTPUT_RATE_HZ:g} (every sample of a slower "
        f"IMU); {IMU_RATE}: every IMU sample",
        "positive",
        special=(AUTO, IMU_RATE),
    )
    table_format: str = _opt(
        "csv",
        f"format of the command line's tables, one of {TABLE_FORMATS} (solution.parquet, ...)",
        "choice",
        choices=TABLE_FORMATS,
    )
    smooth: bool = _opt(False, "run the Rauch-Tung-Striebel smoother", "flag",
                        backends=("eskf",))  # fmt: skip

    def __post_init__(self) -> None:
        _coerce_fields(self)


PARTS: dict[str, type] = {
    "aiding": Aiding,
    "initial": Initial,
    "noise": Noise,
    "gating": Gating,
    "sky": SkyStates,
    "graph": GraphSolver,
    "output": Output,
}
"""The parts of :class:`FuseConfig`: attribute name -> part type."""

PART_OF: dict[str, str] = {
    f.name: part for part, cls in PARTS.items() for f in dataclasses.fields(cls)
}
OPTION_FIELDS: dict[str, dataclasses.Field[Any]] = {
    f.name: f for cls in PARTS.values() for f in dataclasses.fields(cls)
}


# ----------------------------------------------------------------------------- parsing
def coerce_option(name: str, value: Any) -> Any:
    """The value of option ``name`` from Python, TOML or the text of ``--set``: the one
    parser of every option (one-line ``UserInputError`` naming the option)."""
    f = OPTION_FIELDS.get(name)
    if f is None:
        raise unknown_option(name)
    meta = f.metadata
    if isinstance(value, str):
        low = value.strip().lower()
        if low in meta["special"]:
            return low
    if value is None or (isinstance(value, float) and math.isinf(value) and OFF in meta["special"]):
        words = " or ".join(repr(w) for w in meta["special"]) or "a value"
        raise UserInputError(f"{name}={value!r}: give {words} ({meta['doc'].split(';')[0]})")
    return _PARSERS[meta["kind"]](name, value, meta)


def _flag(name: str, value: Any, meta: Mapping[str, Any]) -> bool:
    if isinstance(value, bool | np.bool_):
        return bool(value)
    low = str(value).strip().lower() if isinstance(value, str) else None
    if low in ("true", "on", "yes", "1"):
        return True
    if low in ("false", "off", "no", "0"):
        return False
    words = "".join(f", {w}" for w in meta["special"])
    raise UserInputError(f"{name}={value!r}: expected on or off (true/false){words}")


def _number(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float | str | np.number):
        raise UserInputError(f"{name}={value!r}: expected a number")
    try:
        out = float(value)
    except ValueError:
        raise UserInputError(f"{name}={value!r}: expected a number") from None
    if not math.isfinite(out):
        raise UserInputError(f"{name}={value!r}: expected a finite number")
    return out


def _positive(name: str, value: Any, meta: Mapping[str, Any]) -> float:
    out = _number(name, value)
    if not out > 0.0:
        words = "".join(f", {w!r}" for w in meta["special"])
        raise UserInputError(f"{name}={value!r}: expected a number > 0{words}")
    return out


def _nonnegative(name: str, value: Any, meta: Mapping[str, Any]) -> float:
    out = _number(name, value)
    if not out >= 0.0:
        raise UserInputError(f"{name}={value!r}: expected a number >= 0")
    return out


def _probability(name: str, value: Any, meta: Mapping[str, Any]) -> float:
    out = _number(name, value)
    if not 0.0 < out < 1.0:
        raise UserInputError(f"{name}={value!r}: expected a probability in (0, 1) or 'off'")
    return out


def _choice(name: str, value: Any, meta: Mapping[str, Any]) -> str:
    if value not in meta["choices"]:
        raise UserInputError(f"{name}={value!r}: expected one of {meta['choices']}")
    return str(value)


def _vector3(name: str, value: Any, meta: Mapping[str, Any]) -> tuple[float, ...]:
    parts = value.split(",") if isinstance(value, str) else value
    try:
        out = tuple(_number(name, v) for v in parts)
    except (TypeError, UserInputError):
        raise UserInputError(f"{name}={value!r}: expected 3 numbers") from None
    if len(out) != 3:
        raise UserInputError(f"{name}={value!r}: expected 3 numbers")
    return out


def _sigma3(name: str, value: Any, meta: Mapping[str, Any]) -> tuple[float, ...]:
    one = isinstance(value, int | float | np.number) or (
        isinstance(value, str) and "," not in value
    )
    try:
        out = (_number(name, value),) * 3 if one else _vector3(name, value, meta)
    except UserInputError:
        out = (math.nan,)
    if len(out) != 3 or not all(v > 0 for v in out):
        raise UserInputError(f"{name}={value!r}: expected 1 or 3 sigmas > 0")
    return out


def _count(name: str, value: Any, meta: Mapping[str, Any]) -> int:
    if isinstance(value, str):
        value = value.strip()
        if not value.isdigit():
            raise UserInputError(f"{name} must be an integer >= 1, got {value!r}")
        value = int(value)
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
        raise UserInputError(f"{name} must be an integer >= 1, got {value!r}")
    return int(value)


def _times(name: str, value: Any, meta: Mapping[str, Any]) -> tuple[float, ...]:
    parts = value.split(",") if isinstance(value, str) else value
    try:
        return tuple(_number(name, v) for v in parts if not (isinstance(v, str) and not v.strip()))
    except TypeError:
        raise UserInputError(f"{name}={value!r}: expected times [s]") from None


_PARSERS = {"count": _count, "times": _times, "flag": _flag, "positive": _positive, "nonnegative": _nonnegative,
            "probability": _probability, "choice": _choice, "vector3": _vector3,
            "sigma3": _sigma3}  # fmt: skip


def _coerce_fields(part: Any) -> None:
    """Parse every field of a part in place (frozen: ``object.__setattr__``)."""
    for f in dataclasses.fields(part):
        object.__setattr__(part, f.name, coerce_option(f.name, getattr(part, f.name)))


def unknown_option(name: str) -> UnknownOptionError:
    """The one-line error of an option name that is not one: what replaces a retired name,
    else the closest option."""
    if name in _NOT_OPTIONS:
        return UnknownOptionError(f"filter option {name!r} {_NOT_OPTIONS[name]}")
    close = difflib.get_close_matches(name, option_names(), n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return UnknownOptionError(f"unknown filter option {name!r}{hint}; see option_names()")


def split_options(options: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """Flat options -> ``{part: {name: value}}``; an unknown name is a one-line error."""
    out: dict[str, dict[str, Any]] = {part: {} for part in PARTS}
    for name, value in options.items():
        part = PART_OF.get(name)
        if part is None:
            raise unknown_option(name)
        out[part][name] = value
    return out


def option_names() -> list[str]:
    """The flat names of all options, part by part."""
    return list(OPTION_FIELDS)


def option_table(backends: Sequence[str] = BACKENDS) -> list[tuple[str, str, str, str, str]]:
    """``(part, name, default, backends, description)`` of every option, for docs and
    ``--help``."""
    rows = []
    for name, f in OPTION_FIELDS.items():
        if set(f.metadata["backends"]) & set(backends):
            default = f.default if isinstance(f.default, str) else repr(f.default)
            rows.append((PART_OF[name], name, default, "/".join(f.metadata["backends"]),
                         f.metadata["doc"]))  # fmt: skip
    return rows


__all__ = [
    "AUTO",
    "BACKENDS",
    "GRAPH_OUTPUTS",
    "IMU_RATE",
    "NHC_STD_GROUND",
    "ODOMETER_STD",
    "OFF",
    "OPTIMIZERS",
    "OPTION_FIELDS",
    "OUTPUT_RATE_HZ",
    "PARTS",
    "PART_OF",
    "SOLVERS",
    "STANDSTILL_STD",
    "TABLE_FORMATS",
    "VEHICLE_KINDS",
    "Aiding",
    "Gating",
    "GraphSolver",
    "Initial",
    "Noise",
    "Output",
    "SkyStates",
    "coerce_option",
    "option_names",
    "option_table",
    "split_options",
    "unknown_option",
]
