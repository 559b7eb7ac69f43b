"""Tuning tools: IMU noise models from static recordings (docs/imu-model.md), filter noise from a log (docs/tuning.md)."""

from polins.tuning.allan import AllanCurve, NoiseTerms, allan_deviation, fit_allan, fit_noise_terms
from polins.tuning.imu_model import (
    GRADE_TYPICAL,
    AllanFit,
    SensorAllan,
    imu_model_from_static,
    model_random_walk,
)
from polins.tuning.innovations import InnovationStats, innovation_stats, stats_table
from polins.tuning.likelihood import negative_log_likelihood, tune
from polins.tuning.parameters import PARAMETERS, with_values
from polins.tuning.plot import plot_allan
from polins.tuning.result import TuneResult

__all__ = [
    "GRADE_TYPICAL",
    "PARAMETERS",
    "AllanCurve",
    "AllanFit",
    "InnovationStats",
    "NoiseTerms",
    "SensorAllan",
    "TuneResult",
    "allan_deviation",
    "fit_allan",
    "fit_noise_terms",
    "imu_model_from_static",
    "innovation_stats",
    "model_random_walk",
    "negative_log_likelihood",
    "plot_allan",
    "stats_table",
    "tune",
    "with_values",
]
