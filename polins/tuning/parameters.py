"""The noise parameters a log can tune, their start values, and how each acts on a configuration (docs/tuning.md)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any

import pandas as pd

from polins.errors import UserInputError
from polins.fusion import FuseConfig

PARAMETERS: dict[str, str] = {
    "gyro_arw": "gyro angle random walk [rad/sqrt(s)]",
    "gyro_bias_rw": "gyro bias random walk [rad/s/sqrt(s)]",
    "accel_vrw": "accelerometer velocity random walk [m/s/sqrt(s)]",
    "accel_bias_rw": "accelerometer bias random walk [m/s^2/sqrt(s)]",
    "yaw_floor_deg": "floor added in quadrature to every yaw_std [deg]",
    "sun_floor_deg": "floor added in quadrature to every sun_std [deg]",
    "yaw_std_scale": "factor on every yaw_std [-]",
    "sun_std_scale": "factor on every sun_std [-]",
    "nhc_std": "non-holonomic constraint 1-sigma [m/s] (the vehicle's slip and mounting)",
    "standstill_std": "zero-velocity 1-sigma at standstill [m/s] (vibration, rocking)",
    "odometer_std": "wheel-odometer speed 1-sigma [m/s]",
}
IMU_PARAMS = ("gyro_arw", "gyro_bias_rw", "accel_vrw", "accel_bias_rw")
# the measurement-noise options and the kind of update each acts on
OPTION_KIND = {"yaw_floor_deg": "yaw", "yaw_std_scale": "yaw", "sun_floor_deg": "sun",
                "sun_std_scale": "sun", "nhc_std": "nhc", "standstill_std": "zupt",
                "odometer_std": "odo"}  # fmt: skip
FLOOR_START_DEG = 0.05  # a floor's start when none is given and the log asks for none


def check_params(params: Sequence[str]) -> tuple[str, ...]:
    """``params`` as a tuple, each a key of :data:`PARAMETERS` (else ``UserInputError``)."""
    unknown = [p for p in params if p not in PARAMETERS]
    if unknown or not params:
        raise UserInputError(
            f"unknown noise parameter(s) {unknown or '(none given)'}: expected some of "
            f"{', '.join(PARAMETERS)}"
        )
    if len(set(params)) != len(params):
        raise UserInputError(f"noise parameters given twice: {list(params)}")
    return tuple(params)


def default_params(config: FuseConfig, *, odometry: bool = False) -> tuple[str, ...]:
    """The parameters ``polins tune`` fits by default: the gyro's white noise, the yaw
    scale and the NHC and odometer sigmas when on. Tuning the IMU without the
    pseudo-measurement sigmas lets it absorb their mismatch (docs/tuning.md, "What a log
    can identify"). The zero-velocity sigma is tuned only when asked (``standstill_std``):
    on a log whose rests are exact (a simulation) it runs to its search bound."""
    run = config.resolve(odometry=odometry)
    sigmas = {"nhc_std": run.nhc_sigma, "odometer_std": run.odometer_sigma}
    return ("gyro_arw", "yaw_std_scale", *(p for p, v in sigmas.items() if v is not None))


def with_values(
    config: FuseConfig, measurements: pd.DataFrame, values: Mapping[str, float]
) -> tuple[FuseConfig, pd.DataFrame]:
    """The configuration with the noise ``values`` (:data:`PARAMETERS`); the table unchanged.

    IMU terms replace the model's (``dataclasses.replace`` of the frozen ``ImuModel``); the
    measurement-noise terms are the filter's own options (``yaw_std_scale``,
    ``yaw_floor_deg``, ``sun_std_scale``, ``sun_floor_deg``, :class:`FuseConfig`), so the
    tuned values act in ``polins fuse`` (``--set``, a manifest's ``[filter]``) as in the
    tuning. The measurements are returned as given.
    """
    imu_values: dict[str, Any] = {k: float(v) for k, v in values.items() if k in IMU_PARAMS}
    if imu_values:
        model = dataclasses.replace(config.imu, **imu_values)
        config = config.replace(imu_model=model)
    noise = {k: float(v) for k, v in values.items() if k not in IMU_PARAMS}
    if noise:
        config = config.replace(**noise)
    return config, measurements


def option_start(config: FuseConfig, p: str) -> float:
    """The start of a measurement-noise option: its value in use (a floor of 0 starts at
    0.05 deg); an update kind that is off has nothing to tune."""
    if p in ("nhc_std", "standstill_std", "odometer_std"):
        sigma = {"nhc_std": config.nhc_sigma, "standstill_std": config.standstill_sigma,
                 "odometer_std": config.odometer_sigma}[p]  # fmt: skip
        if sigma is None:
            raise UserInputError(
                f"{p} is off in this configuration (the vehicle kind, the option or no "
                f"odometry): the {OPTION_KIND[p]} updates it would tune are not fused"
            )
        return float(sigma)
    return float(getattr(config.noise, p)) or FLOOR_START_DEG


def start_values(
    config: FuseConfig, params: tuple[str, ...], initial: Mapping[str, float]
) -> dict[str, float]:
    """Start values: ``initial``, else the IMU model's or the configuration's (a floor of 0,
    which the logarithmic search cannot start from, starts at 0.05 deg)."""
    start: dict[str, float] = {}
    for p in params:
        value = initial.get(p)
        if value is None and p in IMU_PARAMS:
            value = float(getattr(config.imu, p))
        elif value is None:
            value = option_start(config, p)
        if not (math.isfinite(value) and value > 0):
            raise UserInputError(
                f"the start value of {p} must be > 0 (the search runs over its logarithm), "
                f"got {value}"
            )
        start[p] = float(value)
    return start


__all__ = [
    "FLOOR_START_DEG",
    "IMU_PARAMS",
    "OPTION_KIND",
    "PARAMETERS",
    "check_params",
    "default_params",
    "option_start",
    "start_values",
    "with_values",
]
