"""Evaluation of a fusion run: errors against a reference, the summary with its verdicts, the report's plots.

Above :mod:`polins.fusion` (it replays the measurement model to score the measurements) and
:mod:`polins.io` (it writes through the file formats there); ``polins fuse`` and the examples
use it, the filters do not.
"""

from polins.evaluation.plots import heading_plot_series, plot_report
from polins.evaluation.reference import (
    error_stats,
    measurement_residuals,
    solution_errors,
    truth_at,
)
from polins.evaluation.report import write_report
from polins.evaluation.summary import format_summary, summarize

__all__ = [
    "error_stats",
    "format_summary",
    "heading_plot_series",
    "measurement_residuals",
    "plot_report",
    "solution_errors",
    "summarize",
    "truth_at",
    "write_report",
]
