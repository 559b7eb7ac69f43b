"""Tuning tools: IMU noise models from static recordings (Allan deviation, docs/imu-model.md)."""

from polins.tuning.allan import AllanCurve, NoiseTerms, allan_deviation, fit_allan, fit_noise_terms
from polins.tuning.imu_model import (
    GRADE_TYPICAL,
    AllanFit,
    SensorAllan,
    imu_model_from_static,
    model_random_walk,
)
from polins.tuning.plot import plot_allan

__all__ = [
    "GRADE_TYPICAL",
    "AllanCurve",
    "AllanFit",
    "NoiseTerms",
    "SensorAllan",
    "allan_deviation",
    "fit_allan",
    "fit_noise_terms",
    "imu_model_from_static",
    "model_random_walk",
    "plot_allan",
]
