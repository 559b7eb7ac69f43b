"""Tables on disk: IMU logs (CSV or Parquet) with unit metadata, and atomic table output.

IMU table format
----------------
Columns ``t, gx, gy, gz, ax, ay, az`` (docs/conventions.md): time [s] on the log's clock, body
(FLU) angular rate and specific force. Extra columns are ignored. Units are SI by default;
a file may declare other units, and the reader converts to SI:

* CSV: a comment line before the header, e.g. ``# units: gyro=deg/s, accel=g``.
* Parquet: schema metadata key ``polins.units`` holding JSON ``{"gyro": "deg/s", "accel": "g"}``.
* Or explicit flags (``gyro_unit=``, ``accel_unit=``: the manifest's ``[units]`` table or the
  CLI). A flag that contradicts the file's own declaration is an error, never a silent choice.

Gyro units: ``rad/s``, ``deg/s``; accelerometer units: ``m/s^2``, ``g`` (9.80665 m/s^2).
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from polins.errors import UserInputError
from polins.io.atomic import atomic_path

IMU_COLUMNS = ("t", "gx", "gy", "gz", "ax", "ay", "az")
GYRO_UNITS = {"rad/s": 1.0, "deg/s": np.pi / 180.0}  # unit -> [rad/s] per unit
ACCEL_UNITS = {"m/s^2": 1.0, "g": 9.80665}  # unit -> [m/s^2] per unit
_PARQUET_KEY = b"polins.units"
CHUNK_ROWS = 100_000  # rows formatted (CSV) or grouped (Parquet) at a time by write_table
_UNITS_LINE = re.compile(r"^#\s*units\s*:\s*(?P<body>.*)$", re.IGNORECASE)


def _check_unit(kind: str, unit: str | None) -> str | None:
    table = GYRO_UNITS if kind == "gyro" else ACCEL_UNITS
    if unit is not None and unit not in table:
        raise UserInputError(f"unknown {kind} unit {unit!r}: expected one of {', '.join(table)}")
    return unit


def _table_format(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix == ".csv":
        return "csv"
    if suffix in (".parquet", ".pq"):
        return "parquet"
    raise UserInputError(f"{path}: unknown table format {suffix!r}: expected .csv or .parquet")


def write_table(
    path: str | Path,
    df: pd.DataFrame,
    *,
    metadata: Mapping[str, str] | None = None,
    header_comment: str | None = None,
    float_format: str = "%.17g",
) -> Path:
    """Write a DataFrame as CSV or Parquet (by suffix), atomically, :data:`CHUNK_ROWS` rows
    at a time (a CSV's text and a Parquet row group never hold the whole table).

    CSV floats use ``float_format``: the default is the full round-trip precision (logs);
    reports for people use ``"%.10g"``. ``metadata`` goes to the Parquet schema
    metadata; ``header_comment`` (without ``#``) becomes a first comment line of a CSV.
    """
    path = Path(path)
    fmt = _table_format(path)
    with atomic_path(path) as tmp:
        if fmt == "csv":
            with open(tmp, "w", encoding="utf-8", newline="") as fh:
                if header_comment:
                    fh.write(f"# {header_comment}\n")
                df.to_csv(fh, index=False, float_format=float_format, lineterminator="\n",
                          chunksize=CHUNK_ROWS)  # fmt: skip
        else:
            pa, pq = _pyarrow()
            table = pa.Table.from_pandas(df, preserve_index=False)
            meta = dict(table.schema.metadata or {})
            for key, value in (metadata or {}).items():
                meta[key.encode()] = value.encode()
            pq.write_table(table.replace_schema_metadata(meta), tmp, row_group_size=CHUNK_ROWS)
    return path


def _pyarrow() -> tuple[Any, Any]:
    """The ``pyarrow`` modules for Parquet, or an ImportError naming the extra."""
    try:
        import pyarrow
        import pyarrow.parquet
    except ImportError as exc:
        raise ImportError(
            "Parquet tables need pyarrow: pip install 'polins[parquet]' (or use CSV)"
        ) from exc
    return pyarrow, pyarrow.parquet


def _csv_units(path: Path) -> tuple[dict[str, str], int]:
    """Units declared in leading ``#`` lines of a CSV, and the number of those lines."""
    units: dict[str, str] = {}
    n_comment = 0
    with open(path, encoding="utf-8-sig") as fh:  # a UTF-8 BOM is accepted
        for line in fh:
            if not line.startswith("#"):
                break
            n_comment += 1
            match = _UNITS_LINE.match(line.strip())
            if match:
                for item in re.split(r"[,\s]+", match.group("body").strip()):
                    if not item:
                        continue
                    key, sep, value = item.partition("=")
                    if not sep or key not in ("gyro", "accel"):
                        raise UserInputError(
                            f"{path}: bad units comment {line.strip()!r}: expected "
                            "'# units: gyro=<rad/s|deg/s>, accel=<m/s^2|g>'"
                        )
                    units[key] = value
    return units, n_comment


def read_table(path: str | Path) -> pd.DataFrame:
    """Read a CSV (leading ``#`` comment lines skipped) or Parquet table."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"table not found: {path}")
    if _table_format(path) == "csv":
        _, n_comment = _csv_units(path)
        return pd.read_csv(path, skiprows=n_comment, encoding="utf-8-sig")
    _pyarrow()
    return pd.read_parquet(path)


def imu_file_units(path: str | Path) -> dict[str, str]:
    """Units an IMU file declares about itself (possibly empty): ``{"gyro": .., "accel": ..}``."""
    path = Path(path)
    if _table_format(path) == "csv":
        units, _ = _csv_units(path)
    else:
        _, pq = _pyarrow()
        meta = pq.read_schema(path).metadata or {}
        raw = meta.get(_PARQUET_KEY)
        try:
            units = dict(json.loads(raw)) if raw else {}
        except (ValueError, TypeError):
            raise UserInputError(f"{path}: bad {_PARQUET_KEY.decode()} metadata {raw!r}") from None
    for kind, unit in units.items():
        if kind not in ("gyro", "accel"):
            raise UserInputError(f"{path}: unknown unit key {kind!r} (expected gyro, accel)")
        _check_unit(kind, unit)
    return units


def read_imu(
    path: str | Path, *, gyro_unit: str | None = None, accel_unit: str | None = None
) -> pd.DataFrame:
    """Read an IMU table and convert it to SI.

    Parameters
    ----------
    path : str or Path
        ``.csv`` or ``.parquet`` file with columns ``t, gx, gy, gz, ax, ay, az``.
    gyro_unit, accel_unit : str, optional
        Units of the file's gyro ("rad/s", "deg/s") and accelerometer ("m/s^2", "g") columns.
        Default: what the file declares, else SI. Must agree with the file's declaration.

    Returns
    -------
    DataFrame
        Columns ``t`` [s], ``gx, gy, gz`` [rad/s], ``ax, ay, az`` [m/s^2], float64, in file
        order (sample-order policies are the navigation loop's, see ``polins.loop.stream``).

    Raises
    ------
    ValueError
        Missing or non-numeric columns, unknown or contradicting units.
    """
    path = Path(path)
    declared = imu_file_units(path)
    chosen: dict[str, str] = {}
    for kind, flag in (
        ("gyro", _check_unit("gyro", gyro_unit)),
        ("accel", _check_unit("accel", accel_unit)),
    ):
        own = declared.get(kind)
        if flag is not None and own is not None and flag != own:
            raise UserInputError(
                f"{path}: the file declares {kind} in {own!r} but {flag!r} was requested; "
                "remove one of the two declarations"
            )
        chosen[kind] = flag or own or ("rad/s" if kind == "gyro" else "m/s^2")
    df = read_table(path)
    missing = [c for c in IMU_COLUMNS if c not in df.columns]
    if missing:
        raise UserInputError(
            f"{path}: IMU table lacks column(s) {missing}; expected {list(IMU_COLUMNS)} "
            f"(found {list(df.columns)})"
        )
    out = pd.DataFrame(index=pd.RangeIndex(len(df)))
    for col in IMU_COLUMNS:
        values = pd.to_numeric(df[col], errors="coerce")
        bad = values.isna() & df[col].notna()
        if bad.any():
            row = int(np.flatnonzero(bad.to_numpy())[0])
            raise UserInputError(
                f"{path}: column {col!r} row {row}: not a number: {df[col].iloc[row]!r}"
            )
        out[col] = values.to_numpy(dtype=float)
    out[["gx", "gy", "gz"]] *= GYRO_UNITS[chosen["gyro"]]
    out[["ax", "ay", "az"]] *= ACCEL_UNITS[chosen["accel"]]
    return out


def write_imu(
    path: str | Path, imu: pd.DataFrame, *, gyro_unit: str = "rad/s", accel_unit: str = "m/s^2"
) -> Path:
    """Write an SI IMU DataFrame as CSV or Parquet in the given units, declaring them.

    The inverse of :func:`read_imu`: ``read_imu(write_imu(p, imu, gyro_unit="deg/s"))``
    returns ``imu`` (to rounding). Written atomically.
    """
    _check_unit("gyro", gyro_unit)
    _check_unit("accel", accel_unit)
    missing = [c for c in IMU_COLUMNS if c not in imu.columns]
    if missing:
        raise UserInputError(
            f"IMU DataFrame lacks column(s) {missing}; expected {list(IMU_COLUMNS)}"
        )
    out = imu.loc[:, list(IMU_COLUMNS)].astype(float).reset_index(drop=True)
    out[["gx", "gy", "gz"]] /= GYRO_UNITS[gyro_unit]
    out[["ax", "ay", "az"]] /= ACCEL_UNITS[accel_unit]
    units = {"gyro": gyro_unit, "accel": accel_unit}
    return write_table(
        path,
        out,
        metadata={_PARQUET_KEY.decode(): json.dumps(units)},
        header_comment=f"units: gyro={gyro_unit}, accel={accel_unit}",
    )


__all__ = [
    "ACCEL_UNITS",
    "CHUNK_ROWS",
    "GYRO_UNITS",
    "IMU_COLUMNS",
    "imu_file_units",
    "read_imu",
    "read_table",
    "write_imu",
    "write_table",
]
