"""The log's manifest: ``manifest.toml``, its tables and keys, read and validated.

``manifest.toml`` (written by :func:`polins.io.log.write_log`)::

    [log]
    epoch_utc = "2023-09-05T07:00:00+00:00"  # timezone-aware; t = 0 of every stream
                                             # (optional with a bag: its first stamp)
    camera = "paper-table1"                  # shipped model name, or a .toml path
    imu = "mems-typical"                     # (paths are relative to the manifest)
    lat_deg = 45.6234
    lon_deg = 126.7264
    alt_m = 148.74                           # optional, default 0
    description = "..."                      # optional

    [files]
    imu = "imu.csv"          # .csv or .parquet
    images = "images.csv"    # index CSV (t, file), or a folder of time-named images
    truth = "truth.csv"      # optional
    # bag = "run.bag"        # instead of imu + images: ROS 1 bag or ROS 2 bag folder/.mcap

    [units]                  # optional; units of the IMU file if it does not declare them
    gyro = "rad/s"           # or "deg/s"
    accel = "m/s^2"          # or "g"

    [ros]                    # optional, with files.bag only
    imu_topic = "/imu/data"
    image_topic = "/camera/image_raw"

    [vehicle]                # optional; the vehicle (docs/filter.md, "Ground-vehicle aiding")
    kind = "ground"          # "ground" | "static" | "free" (FuseConfig.vehicle)
    mount_rpy_deg = [0.5, -1.0, 2.0]  # roll, pitch, yaw of the IMU in the vehicle frame
    mount_std_deg = 2.0               # optional: estimate the mounting's pitch and yaw errors
    lever_arm_b = [-0.6, 0.1, -0.3]   # IMU -> vehicle reference point, IMU axes [m]
    lever_std = 0.3                   # optional: estimate the lever arm's error, 1-sigma [m]
    odometer = "odometer.csv"         # optional wheel-odometer stream: t [s], speed [m/s]
    odometer_std = 0.05               # its 1-sigma [m/s] (default: auto, 0.05)

    [filter]                 # optional; FuseConfig options by their flat names, "off" and
    nhc_std = 0.05           # "auto" as in Python; they override the [vehicle] table's

An unknown or missing key is a :class:`ManifestError` naming it (and the closest key). This
module reads the file only: the filter configuration of a manifest is built by
:func:`polins.fusion.config.config_from_manifest` (``FuseConfig.from_log``), which checks the
``[filter]`` table.
"""

from __future__ import annotations

import datetime as dt
import difflib
import math
import tomllib
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import pandas as pd

from polins.errors import UserInputError
from polins.io.tables import ACCEL_UNITS, GYRO_UNITS
from polins.site import utc_timestamp

MANIFEST_NAME = "manifest.toml"


class ManifestError(UserInputError):
    """A manifest is missing a key, has an unknown key, or a bad value (named in the message)."""


def _str(v: Any) -> str:
    if not isinstance(v, str) or not v:
        raise TypeError("expected a non-empty string")
    return v


def number_in(lo: float, hi: float) -> Callable[[Any], float]:
    """A validator of a number in ``[lo, hi]`` (degrees)."""

    def check(v: Any) -> float:
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise TypeError("expected a number")
        if not lo <= float(v) <= hi:
            raise UserInputError(f"expected a number in [{lo}, {hi}] (degrees)")
        return float(v)

    return check


def _height(v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise TypeError("expected a number [m]")
    return float(v)


def _epoch(v: Any) -> pd.Timestamp:
    if not isinstance(v, str | dt.datetime):
        raise TypeError("expected an ISO time string with a timezone")
    return utc_timestamp(v, None)


def _unit(table: Mapping[str, float]) -> Callable[[Any], str]:
    def check(v: Any) -> str:
        if v not in table:
            raise UserInputError(f"expected one of {', '.join(repr(u) for u in table)}")
        return str(v)

    return check


def _triple(v: Any) -> tuple[float, float, float]:
    if not isinstance(v, list | tuple) or len(v) != 3:
        raise TypeError("expected 3 numbers")
    x, y, z = (_height(e) for e in v)
    return (x, y, z)


def _sigma(v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or not (0 < v < math.inf):
        raise UserInputError("expected a number > 0")
    return float(v)


def _sigma_or_zero(v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or not (0 <= v < math.inf):
        raise UserInputError("expected a number >= 0 (0: off)")
    return float(v)


# section -> key -> (required, validator)
_MANIFEST_SCHEMA: dict[str, dict[str, tuple[bool, Callable[[Any], Any]]]] = {
    "log": {
        "epoch_utc": (False, _epoch),  # required unless a ROS bag's stamps give it
        "camera": (True, _str),
        "imu": (True, _str),
        "lat_deg": (True, number_in(-90.0, 90.0)),
        "lon_deg": (True, number_in(-180.0, 360.0)),
        "alt_m": (False, _height),
        "description": (False, lambda v: v if isinstance(v, str) else _str(v)),
    },
    "files": {
        "imu": (False, _str),
        "images": (False, _str),
        "truth": (False, _str),
        "bag": (False, _str),
    },
    "units": {"gyro": (False, _unit(GYRO_UNITS)), "accel": (False, _unit(ACCEL_UNITS))},
    "ros": {"imu_topic": (False, _str), "image_topic": (False, _str)},
    "vehicle": {
        "kind": (False, _str),  # checked with the configuration (FuseConfig's vehicle)
        "mount_rpy_deg": (False, _triple),
        "mount_std_deg": (False, number_in(0.0, 90.0)),
        "lever_arm_b": (False, _triple),
        "lever_std": (False, _sigma_or_zero),
        "odometer": (False, _str),
        "odometer_std": (False, _sigma),
    },
}
_REQUIRED_SECTIONS = ("log", "files")


def _unknown(path: Path, key: str, allowed: Iterable[str]) -> ManifestError:
    allowed = list(allowed)
    name = key.rsplit(".", 1)[-1]
    guess = difflib.get_close_matches(name, allowed, n=1, cutoff=0.5)
    prefix = key[: -len(name)]
    hint = f"; did you mean '{prefix}{guess[0]}'?" if guess else ""
    return ManifestError(
        f"{path}: unknown key '{key}'{hint} (allowed: {', '.join(prefix + a for a in allowed)})"
    )


def _read_toml(path: Path) -> dict[str, Any]:
    """The TOML tables of the manifest file ``path``."""
    if not path.is_file():
        raise FileNotFoundError(f"manifest not found: {path}")
    try:
        return tomllib.loads(path.read_text(encoding="utf-8-sig"))  # a BOM is accepted
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ManifestError(f"{path}: not valid TOML: {exc}") from None


def _check_section_names(path: Path, data: dict[str, Any]) -> None:
    """Every top-level entry is a known section and a table."""
    for section, content in data.items():
        if section not in _MANIFEST_SCHEMA and section != "filter":
            raise _unknown(path, section, [*_MANIFEST_SCHEMA, "filter"])
        if not isinstance(content, dict):
            raise ManifestError(f"{path}: '{section}' must be a table [{section}]")


def _section_values(
    path: Path,
    section: str,
    schema: dict[str, tuple[bool, Callable[[Any], Any]]],
    content: dict[str, Any],
) -> dict[str, Any]:
    """The checked values of one section: unknown keys, missing keys and bad values raise."""
    for key in content:
        if key not in schema:
            raise _unknown(path, f"{section}.{key}", schema)
    values: dict[str, Any] = {}
    for key, (required, check) in schema.items():
        if key not in content:
            if required:
                raise ManifestError(f"{path}: missing key '{section}.{key}'")
            continue
        try:
            values[key] = check(content[key])
        except (TypeError, ValueError) as exc:
            raise ManifestError(
                f"{path}: key '{section}.{key}' = {content[key]!r}: {exc}"
            ) from None
    return values


def _check_sources(path: Path, out: dict[str, dict[str, Any]]) -> None:
    """The data sources: either a ROS bag (with optional [ros]) or IMU log + images."""
    files = out["files"]
    if "bag" not in files and "epoch_utc" not in out["log"]:
        raise ManifestError(
            f"{path}: missing key 'log.epoch_utc' (t = 0 of the IMU and image files; only a "
            "ROS bag's absolute stamps give it)"
        )
    if "bag" in files:
        clash = [k for k in ("imu", "images") if k in files]
        if clash:
            raise ManifestError(
                f"{path}: key 'files.bag' excludes 'files.{clash[0]}': give either a bag or "
                "imu + images"
            )
    else:
        for key in ("imu", "images"):
            if key not in files:
                raise ManifestError(
                    f"{path}: missing key 'files.{key}' (or give 'files.bag' for a ROS bag)"
                )
    if out["ros"] and "bag" not in files:
        raise ManifestError(f"{path}: table [ros] is only used with 'files.bag'")


def parse_manifest(path: str | Path) -> dict[str, dict[str, Any]]:
    """Read and validate a manifest; returns ``{section: {key: value}}`` (defaults filled).

    Raises
    ------
    FileNotFoundError
        No such file.
    ManifestError
        Not TOML, unknown/missing key, wrong type or unit; the message names the key.
    """
    path = Path(path)
    if path.is_dir():
        path = path / MANIFEST_NAME
    data = _read_toml(path)
    _check_section_names(path, data)
    out: dict[str, dict[str, Any]] = {}
    for section, schema in _MANIFEST_SCHEMA.items():
        content = data.get(section)
        if content is None:
            if section in _REQUIRED_SECTIONS:
                raise ManifestError(f"{path}: missing table [{section}]")
            content = {}
        out[section] = _section_values(path, section, schema, content)
    out["log"].setdefault("alt_m", 0.0)
    out["log"].setdefault("description", "")
    _check_sources(path, out)
    out["filter"] = dict(data.get("filter", {}))  # FuseConfig options: polins.fusion.config
    return out


__all__ = ["MANIFEST_NAME", "ManifestError", "number_in", "parse_manifest"]
