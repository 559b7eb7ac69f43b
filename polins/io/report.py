"""Files of a fusion run: its tables (CSV or Parquet), ``summary.json`` and ``schema.json``.

Outputs (all written atomically into the output folder; with ``table_format="parquet"``
the three tables are ``.parquet`` files of the same columns):

* ``solution.csv``: the fused solution (``polins.fuse`` columns, docs/conventions.md).
* ``measurements.csv``: one row per image: ``t, ok, reason, yaw, yaw_std, heading_deg,
  heading_std_deg, epsilon, n_pixels``, the sun vectors, the prior and the filter's verdict
  (``accepted, innovation, nis, update_reason``); with a reference also ``yaw_error``.
* ``events.csv``: skipped images and IMU samples, gaps (``t, kind, detail``).
* ``schema.json``: unit and meaning of every column of the CSV files (docs/outputs.md).
* ``summary.json``: counts, rejections by reason, timings, throughput, and, with a
  reference trajectory, RMS errors and their consistency with the reported sigmas.

The summary and the plots are computed by :mod:`polins.evaluation`.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from polins.fusion.parts import TABLE_FORMATS
from polins.io.atomic import write_text_atomic
from polins.io.schema import schema_for
from polins.io.tables import write_table

CSV_FLOAT_FORMAT = "%.10g"  # 10 significant digits: 1e-10 relative, far below any sigma


def _json_default(v: Any) -> Any:
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    return str(v)


def write_run_files(
    folder: str | Path,
    tables: Mapping[str, pd.DataFrame],
    summary: Mapping[str, Any],
    *,
    table_format: str = "csv",
) -> dict[str, Path]:
    """Write the tables as CSV (floats ``%.10g``) or Parquet, ``summary.json`` and
    ``schema.json`` (keyed by the file names written).

    Parameters
    ----------
    folder
        The output folder (created if missing).
    tables
        File name (``solution.csv``, ...) -> table.
    summary
        The run's summary (:func:`polins.evaluation.summarize`).
    table_format : {"csv", "parquet"}
        The tables' format (``FuseConfig`` option ``table_format``): the suffix of their
        files.

    Returns
    -------
    dict
        File stem -> path, with ``summary`` and ``schema``.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if table_format not in TABLE_FORMATS:
        raise ValueError(f"table_format={table_format!r}: expected one of {TABLE_FORMATS}")
    named = {f"{Path(name).stem}.{table_format}": df for name, df in tables.items()}
    out = {
        Path(name).stem: write_table(folder / name, df, float_format=CSV_FLOAT_FORMAT)
        for name, df in named.items()
    }
    out["summary"] = write_text_atomic(
        folder / "summary.json", json.dumps(summary, indent=2, default=_json_default) + "\n"
    )
    out["schema"] = write_text_atomic(
        folder / "schema.json", json.dumps(schema_for(named), indent=2) + "\n"
    )
    return out


__all__ = ["CSV_FLOAT_FORMAT", "write_run_files"]
