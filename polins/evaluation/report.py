"""The report of a fusion run: its tables and summary (written by :mod:`polins.io.report`) and its plots."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pandas as pd

from polins.evaluation.plots import plot_report
from polins.evaluation.reference import truth_at
from polins.frames import wrap_angle
from polins.io.report import write_run_files


def write_report(
    folder: str | Path,
    solution: pd.DataFrame,
    measurements: pd.DataFrame,
    events: pd.DataFrame,
    summary: Mapping[str, Any],
    *,
    truth: pd.DataFrame | None = None,
    plots: bool = True,
    title: str = "",
    table_format: str = "csv",
) -> dict[str, Path]:
    """Write the run's files (:func:`polins.io.report.write_run_files`: the tables as CSV or
    Parquet (``table_format``), ``summary.json``, ``schema.json``) and, optionally, the plots;
    returns name -> path.

    With a reference, ``measurements.csv`` gains ``yaw_error`` [rad] (measured minus reference).
    """
    folder = Path(folder)
    meas = measurements.copy()
    if truth is not None and len(meas):
        ref = truth_at(truth, meas["t"].to_numpy(dtype=float))
        meas["yaw_error"] = wrap_angle(meas["yaw"].to_numpy(dtype=float) - ref["yaw"].to_numpy())
    tables = {"solution.csv": solution, "measurements.csv": meas, "events.csv": events}
    out = write_run_files(folder, tables, summary, table_format=table_format)
    if plots:
        for p in plot_report(folder, solution, measurements, truth=truth, title=title):
            out[p.stem] = p
    return out


__all__ = ["write_report"]
