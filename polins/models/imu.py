"""The IMU model: noise densities and bias models of a gyro/accelerometer triad, read strictly from TOML.

``models/imus/<name>.toml`` (or any path): every key carries its unit in its name
(``arw_deg_per_sqrt_h``); :func:`load_imu` converts to SI and radians, and rejects unknown
keys, missing keys, keys in the wrong unit and values outside the plausible range of the
model's grade (``IMU_PLAUSIBLE_RANGES``, docs/imu-model.md) with a message that names the
file and the key.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from polins.models.schema import (
    ModelFileError,
    Optional,
    Schema,
    boolean,
    choice,
    nonneg,
    positive,
    read_model,
    string,
)

__all__ = ["IMU_PLAUSIBLE_RANGES", "ImuModel", "load_imu"]

_DEG_PER_H = np.pi / 180.0 / 3600.0  # [rad/s] per [deg/h]
_MG = 9.80665e-3  # [m/s^2] per [mg]
_G0 = 9.80665  # [m/s^2] per [g] (standard gravity)

_SENSOR_SCHEMA = {
    "gyro": {
        "arw_deg_per_sqrt_h": nonneg,
        "bias_deg_per_h": nonneg,
        "bias_rw_deg_per_h_per_sqrt_h": nonneg,
        "scale_factor_ppm": nonneg,
        "range_deg_per_s": Optional(positive),
        "misalignment_mrad": Optional(nonneg),
        "misalignment_corr_s": Optional(positive),
    },
    "accel": {
        "vrw_m_per_s_per_sqrt_h": nonneg,
        "bias_mg": nonneg,
        "bias_rw_mg_per_sqrt_h": nonneg,
        "scale_factor_ppm": nonneg,
        "range_g": Optional(positive),
        "misalignment_mrad": Optional(nonneg),
    },
}
# Full scale per grade when the model file has no range keys: (gyro [deg/s], accel [g]),
# typical of the class (docs/imu-model.md); samples beyond it are physically impossible.
IMU_DEFAULT_RANGES: dict[str, tuple[float, float]] = {
    "navigation": (1000.0, 30.0),
    "tactical": (1000.0, 50.0),
    "mems": (2000.0, 16.0),
}
_IMU_SCHEMA: Schema = {
    "name": string,
    "description": string,
    "grade": choice("navigation", "tactical", "mems"),
    "earth_rate": Optional(boolean),  # not a sensor property: load_imu names the filter option
    "sample_rate_hz": positive,
    **_SENSOR_SCHEMA,
    "filter": Optional(lambda v: _filter_table(v)),
}


def _filter_table(table: Any) -> tuple[tuple[str, Any], ...]:
    """A tuned model's ``[filter]`` table as ``(name, value)`` pairs (the values are checked
    as filter options when a configuration is built with the model)."""
    if not isinstance(table, dict):
        raise TypeError("expected a table [filter] of filter options")
    for key, value in table.items():
        if isinstance(value, dict):
            raise TypeError(f"[filter] key {key!r} is a table; expected a value")
    return tuple((str(k), v) for k, v in table.items())


# Plausible ranges per grade, in the TOML's units, [low, high] inclusive; 0 is always
# accepted and means "this error term is absent" (simulations). Each range spans the
# sensors of its class with a margin, and excludes the usual unit mistakes (rad for deg,
# deg/s for deg/h, deg/s/sqrt(Hz) for deg/sqrt(h)). docs/imu-model.md tabulates them.
IMU_PLAUSIBLE_RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "navigation": {
        "gyro.arw_deg_per_sqrt_h": (1e-4, 0.01),
        "gyro.bias_deg_per_h": (1e-4, 0.1),
        "gyro.bias_rw_deg_per_h_per_sqrt_h": (1e-5, 0.05),
        "gyro.scale_factor_ppm": (0.1, 100.0),
        "accel.vrw_m_per_s_per_sqrt_h": (1e-4, 0.05),
        "accel.bias_mg": (1e-3, 0.2),
        "accel.bias_rw_mg_per_sqrt_h": (1e-5, 0.05),
        "accel.scale_factor_ppm": (1.0, 300.0),
    },
    "tactical": {
        "gyro.arw_deg_per_sqrt_h": (0.005, 0.5),
        "gyro.bias_deg_per_h": (0.05, 50.0),
        "gyro.bias_rw_deg_per_h_per_sqrt_h": (1e-3, 5.0),
        "gyro.scale_factor_ppm": (10.0, 3000.0),
        "accel.vrw_m_per_s_per_sqrt_h": (0.005, 0.3),
        "accel.bias_mg": (0.05, 5.0),
        "accel.bias_rw_mg_per_sqrt_h": (1e-3, 1.0),
        "accel.scale_factor_ppm": (10.0, 3000.0),
    },
    "mems": {
        "gyro.arw_deg_per_sqrt_h": (0.05, 10.0),
        "gyro.bias_deg_per_h": (1.0, 1e5),
        "gyro.bias_rw_deg_per_h_per_sqrt_h": (0.01, 1000.0),
        "gyro.scale_factor_ppm": (100.0, 5e4),
        "accel.vrw_m_per_s_per_sqrt_h": (0.01, 2.0),
        "accel.bias_mg": (0.1, 200.0),
        "accel.bias_rw_mg_per_sqrt_h": (1e-3, 50.0),
        "accel.scale_factor_ppm": (100.0, 5e4),
    },
}


def _check_plausible(path: Path, grade: str, d: Mapping[str, Any]) -> None:
    """Raise a one-line ModelFileError for the first value outside its grade's range."""
    for key, (lo, hi) in IMU_PLAUSIBLE_RANGES[grade].items():
        table, name = key.split(".")
        value = d[table][name]
        if value != 0.0 and not lo <= value <= hi:
            raise ModelFileError(
                f"{path}: key '{key}' = {value:g} is implausible for grade '{grade}': "
                f"expected {lo:g} to {hi:g} (or 0 to switch the term off); check the unit "
                "in the key's name or the grade"
            )


@dataclass(frozen=True)
class ImuModel:
    """IMU error model, in SI units, as read from ``models/imus/*.toml``.

    The error model is, per axis: white noise (ARW / VRW) + a constant turn-on bias
    (1-sigma) + a bias random walk + a constant scale-factor error (1-sigma).
    """

    name: str
    description: str
    path: Path
    grade: str
    sample_rate_hz: float
    gyro_arw: float  # [rad/sqrt(s)] (= rad/s/sqrt(Hz))
    gyro_bias: float  # [rad/s] turn-on 1-sigma
    gyro_bias_rw: float  # [rad/s/sqrt(s)]
    gyro_scale_factor: float  # [-] 1-sigma
    accel_vrw: float  # [m/s/sqrt(s)]
    accel_bias: float  # [m/s^2] turn-on 1-sigma
    accel_bias_rw: float  # [m/s^2/sqrt(s)]
    accel_scale_factor: float  # [-] 1-sigma
    gyro_range: float | None = None  # [rad/s] full scale; None: the grade's default
    accel_range: float | None = None  # [m/s^2] full scale; None: the grade's default
    # axis misalignment and cross-axis sensitivity of the gyro, 1-sigma [rad], and the
    # correlation time of the rotation-proportional attitude noise it becomes [s]
    # (docs/filter.md, "Rotation-proportional attitude noise")
    gyro_misalignment: float = 0.0
    gyro_misalignment_corr_time: float = 0.1
    # axis misalignment and cross-axis sensitivity of the accelerometer, 1-sigma [rad]: its
    # error on gravity is a bias (``accel_bias_turn_on``; docs/imu-model.md)
    accel_misalignment: float = 0.0
    # filter options fitted with this IMU on a log (a tuned file's [filter] table, ``polins
    # tune``): every configuration built with this model applies them (docs/tuning.md)
    filter_options: tuple[tuple[str, Any], ...] = ()

    @property
    def accel_bias_turn_on(self) -> float:
        """Turn-on 1-sigma of the accelerometer bias states [m/s^2]: ``accel_bias`` and the
        misalignment's error on gravity ``accel_misalignment * g``, in quadrature (a near-level
        vehicle sees the error ``M g_b`` of a constant matrix ``M`` as a constant bias;
        docs/imu-model.md, "Cross-axis coupling and misalignment")."""
        return float(np.hypot(self.accel_bias, self.accel_misalignment * _G0))

    def full_scale(self) -> tuple[float, float]:
        """``(gyro [rad/s], accel [m/s^2])`` full scale: the model's ranges, else the
        grade's default (``IMU_DEFAULT_RANGES``)."""
        gyro_deg_s, accel_g = IMU_DEFAULT_RANGES.get(self.grade, IMU_DEFAULT_RANGES["mems"])
        return (
            self.gyro_range if self.gyro_range is not None else float(np.radians(gyro_deg_s)),
            self.accel_range if self.accel_range is not None else accel_g * _G0,
        )

    def toml_values(self) -> dict[str, dict[str, float]]:
        """The error terms in the TOML's units: ``{"gyro": {...}, "accel": {...}}``.

        The inverse of the unit conversion :func:`load_imu` applies (docs/imu-model.md).
        """
        sqrt_h = 60.0  # sqrt(3600 s)
        values = {
            "gyro": {
                "arw_deg_per_sqrt_h": float(np.degrees(self.gyro_arw)) * sqrt_h,
                "bias_deg_per_h": self.gyro_bias / _DEG_PER_H,
                "bias_rw_deg_per_h_per_sqrt_h": self.gyro_bias_rw / _DEG_PER_H * sqrt_h,
                "scale_factor_ppm": self.gyro_scale_factor * 1e6,
            },
            "accel": {
                "vrw_m_per_s_per_sqrt_h": self.accel_vrw * sqrt_h,
                "bias_mg": self.accel_bias / _MG,
                "bias_rw_mg_per_sqrt_h": self.accel_bias_rw / _MG * sqrt_h,
                "scale_factor_ppm": self.accel_scale_factor * 1e6,
            },
        }
        if self.gyro_misalignment:
            values["gyro"]["misalignment_mrad"] = self.gyro_misalignment * 1e3
            values["gyro"]["misalignment_corr_s"] = self.gyro_misalignment_corr_time
        if self.accel_misalignment:
            values["accel"]["misalignment_mrad"] = self.accel_misalignment * 1e3
        if self.gyro_range is not None:
            values["gyro"]["range_deg_per_s"] = float(np.degrees(self.gyro_range))
        if self.accel_range is not None:
            values["accel"]["range_g"] = self.accel_range / _G0
        return values

    def check_plausible(self) -> None:
        """Raise :class:`ModelFileError` if a value is outside its grade's plausible range."""
        if self.grade not in IMU_PLAUSIBLE_RANGES:
            raise ModelFileError(
                f"{self.path}: unknown grade {self.grade!r}: expected one of "
                f"{', '.join(repr(g) for g in IMU_PLAUSIBLE_RANGES)}"
            )
        _check_plausible(self.path, self.grade, self.toml_values())


def load_imu(name_or_path: str | Path) -> ImuModel:
    """Load an IMU model: a shipped name (``"fins-paper"``, ``"mems-typical"``) or a TOML path.

    The keys and their units are documented in docs/imu-model.md.

    Raises
    ------
    FileNotFoundError
        Unknown name or missing file.
    ModelFileError
        Unknown, missing or malformed keys, or a value outside the plausible range of the
        model's grade (``IMU_PLAUSIBLE_RANGES``), named with the file and the key.
    """
    path, d = read_model(name_or_path, "imus", _IMU_SCHEMA)
    if "earth_rate" in d:
        raise ModelFileError(
            f"{path}: key 'earth_rate' is not an IMU property: delete it (the filters mechanize "
            "the Earth rate whenever the site is known; the filter option earth_rate turns it off)"
        )
    _check_plausible(path, d["grade"], d)
    g, a = d["gyro"], d["accel"]
    sqrt_h = 60.0  # sqrt(3600 s)
    return ImuModel(
        name=d["name"],
        description=d["description"],
        path=path,
        grade=d["grade"],
        sample_rate_hz=d["sample_rate_hz"],
        gyro_arw=np.radians(g["arw_deg_per_sqrt_h"]) / sqrt_h,
        gyro_bias=g["bias_deg_per_h"] * _DEG_PER_H,
        gyro_bias_rw=g["bias_rw_deg_per_h_per_sqrt_h"] * _DEG_PER_H / sqrt_h,
        gyro_scale_factor=g["scale_factor_ppm"] * 1e-6,
        accel_vrw=a["vrw_m_per_s_per_sqrt_h"] / sqrt_h,
        accel_bias=a["bias_mg"] * _MG,
        accel_bias_rw=a["bias_rw_mg_per_sqrt_h"] * _MG / sqrt_h,
        accel_scale_factor=a["scale_factor_ppm"] * 1e-6,
        gyro_range=float(np.radians(g["range_deg_per_s"])) if "range_deg_per_s" in g else None,
        accel_range=a["range_g"] * _G0 if "range_g" in a else None,
        gyro_misalignment=g.get("misalignment_mrad", 0.0) * 1e-3,
        gyro_misalignment_corr_time=g.get("misalignment_corr_s", 0.1),
        accel_misalignment=a.get("misalignment_mrad", 0.0) * 1e-3,
        filter_options=d.get("filter", ()),
    )
