"""Validation of the fusion inputs: the IMU table and the measurements table (docs/conventions.md).

A mistake in a table raises ``ValueError`` with a message naming the column, the row and
what was expected; unit mistakes that can be detected (gyro in deg/s, accelerometer in g or
mg, yaw in degrees) are such mistakes. Faults in the data are not errors (docs/faults.md):
impossible IMU samples are dropped and reported, IMU gaps reported to the fusion (which
bridges or skips them), rows with an unusable sigma rejected with a reason.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray

from polins.errors import UserInputError
from polins.fusion.result import FusionEvent
from polins.models import ImuModel, load_imu

FloatArray = NDArray[np.float64]

IMU_COLUMNS = ("t", "gx", "gy", "gz", "ax", "ay", "az")
YAW_COLUMNS = ("yaw", "yaw_std")
SUN_COLUMNS = ("sun_bx", "sun_by", "sun_bz", "sun_nx", "sun_ny", "sun_nz", "sun_std")
ZUPT_COLUMNS = ("zupt_std",)
# the sun in the body frame without an ephemeris (no clock), and its elevation (optional;
# with a sun vector its sigma gives the 2x2 direction covariance); docs/filter.md
SUN_AZIMUTH_COLUMNS = ("sun_azimuth_b", "sun_azimuth_b_std")
SUN_ELEVATION_COLUMNS = ("sun_elevation_b", "sun_elevation_b_std")
PRIOR_COLUMNS = ("prior_roll", "prior_pitch", "prior_yaw")

# Plausibility limit of the unit check of the accelerometer (the gyro's: the IMU model's
# full scale, ImuModel.full_scale).
ACCEL_MEDIAN_RANGE = (6.0, 14.0)  # median |f| [m/s^2] of data near the Earth's surface


@dataclass(frozen=True, eq=False)
class ImuArrays:
    """Validated IMU samples: ``t`` (N,) [s], ``gyro_b`` (N, 3) [rad/s], ``accel_b`` (N, 3)
    [m/s^2], the median sample interval ``dt`` [s], the events of the dropped samples, and
    ``gaps``: the indices ``i`` where ``t[i + 1] - t[i]`` exceeds ``max_gap_s``."""

    t: FloatArray
    gyro_b: FloatArray
    accel_b: FloatArray
    dt: float
    events: tuple[FusionEvent, ...] = ()
    gaps: NDArray[np.int_] = field(default_factory=lambda: np.zeros(0, dtype=int))


def _require_frame(df: object, what: str) -> pd.DataFrame:
    if not isinstance(df, pd.DataFrame):
        raise UserInputError(f"{what} must be a pandas DataFrame, got {type(df).__name__}")
    return df


def _numeric(df: pd.DataFrame, cols: tuple[str, ...], what: str) -> FloatArray:
    try:
        return df[list(cols)].to_numpy(dtype=float)
    except (TypeError, ValueError) as exc:
        raise UserInputError(f"{what} columns {list(cols)} must be numeric: {exc}") from exc


def _check_times(t: FloatArray, what: str) -> None:
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise UserInputError(f"{what}: t is NaN/inf at row {bad[0]} ({bad.size} rows)")
    d = np.diff(t)
    dup = np.flatnonzero(d == 0)
    if dup.size:
        i = int(dup[0])
        raise UserInputError(
            f"{what}: duplicated timestamp t={t[i]!r} at rows {i} and {i + 1} "
            f"({dup.size} duplicates); timestamps must be strictly increasing"
        )
    back = np.flatnonzero(d < 0)
    if back.size:
        i = int(back[0])
        raise UserInputError(
            f"{what}: timestamps are not monotonic: t={t[i + 1]!r} at row {i + 1} follows "
            f"t={t[i]!r} at row {i} ({back.size} backward steps); sort the table by t"
        )


def validate_imu(
    imu: pd.DataFrame, *, max_gap_s: float | None = None, model: ImuModel | None = None
) -> ImuArrays:
    """Check an IMU table and return its arrays, without the faulty samples.

    Mistakes in the table (missing columns, bad times, wrong units) raise; faults in the
    data are handled as docs/faults.md says: a sample with a NaN/inf value or beyond the
    model's full scale (``ImuModel.full_scale``) is dropped and reported as an event, a gap
    longer than ``max_gap_s`` is reported (``gaps``) for the fusion to handle.

    Parameters
    ----------
    imu : DataFrame
        Columns ``t`` [s], ``gx, gy, gz`` [rad/s], ``ax, ay, az`` [m/s^2] (body FLU,
        specific force), one row per sample.
    max_gap_s : float, optional
        Longest interval bridged by interpolation [s]; default 5 times the median interval.
    model : ImuModel, optional
        Its full scale bounds the samples (default: ``mems-typical``'s).

    Returns
    -------
    ImuArrays

    Raises
    ------
    ValueError
        Missing columns, fewer than 2 good rows, NaN/inf times, duplicated or
        non-monotonic timestamps, gyro values that look like deg/s (more than 1 % of the
        samples beyond the gyro's full scale), specific force that looks like g or mg.
    """
    df = _require_frame(imu, "imu")
    missing = [c for c in IMU_COLUMNS if c not in df.columns]
    if missing:
        raise UserInputError(f"imu table lacks columns {missing}; expected {list(IMU_COLUMNS)}")
    if len(df) < 2:
        raise UserInputError(f"imu table needs at least 2 samples, got {len(df)}")
    data = _numeric(df, IMU_COLUMNS, "imu")
    t = data[:, 0]
    _check_times(t, "imu")
    gyro_max, accel_max = (model or load_imu("mems-typical")).full_scale()
    with np.errstate(invalid="ignore", over="ignore"):
        w = np.linalg.norm(data[:, 1:4], axis=1)
        f = np.linalg.norm(data[:, 4:7], axis=1)
    finite = np.isfinite(data[:, 1:]).all(axis=1)
    check_imu_units(w[finite], f[finite], gyro_max)
    events = []
    for i in np.flatnonzero(~finite).tolist():
        events.append(FusionEvent(float(t[i]), "imu-nonfinite", "IMU sample with NaN/inf dropped"))
    beyond = finite & ((w > gyro_max) | (f > accel_max))
    for i in np.flatnonzero(beyond).tolist():
        detail = (
            f"IMU sample beyond the full scale dropped: |w| = {w[i]:.3g} rad/s (limit "
            f"{gyro_max:.3g}), |f| = {f[i]:.3g} m/s^2 (limit {accel_max:.3g})"
        )
        events.append(FusionEvent(float(t[i]), "imu-out-of-range", detail))
    keep = finite & ~beyond
    if keep.sum() < 2:
        raise UserInputError(f"imu: fewer than 2 usable samples ({int(keep.sum())} of {len(t)})")
    t, data = t[keep], data[keep]
    d = np.diff(t)
    dt = float(np.median(d))
    limit = 5.0 * dt if max_gap_s is None else float(max_gap_s)
    gaps = np.flatnonzero(d > limit)
    return ImuArrays(t=t.copy(), gyro_b=data[:, 1:4].copy(), accel_b=data[:, 4:7].copy(),
                     dt=dt, events=tuple(events), gaps=gaps)  # fmt: skip


def check_imu_units(gyro_norm: ArrayLike, accel_norm: ArrayLike, gyro_max: float) -> None:
    """Raise ``UserInputError`` if IMU samples look like the wrong units.

    Parameters
    ----------
    gyro_norm, accel_norm : (N,) array_like
        |gyro| [rad/s] and |specific force| [m/s^2] of finite samples.
    gyro_max : float
        The gyro's full scale [rad/s]: more than 1 % of the samples beyond it is deg/s data.

    Raises
    ------
    UserInputError
        The gyro looks like deg/s, or the median |f| is not ~9.8 m/s^2 (g or mg named).
    """
    w = np.asarray(gyro_norm, dtype=float)
    f = np.asarray(accel_norm, dtype=float)
    if w.size and np.percentile(w, 99) > gyro_max:
        raise UserInputError(
            f"imu: the gyro magnitude exceeds the full scale {gyro_max:.3g} rad/s "
            f"({np.degrees(gyro_max):.4g} deg/s) in more than 1 % of the samples (99th "
            f"percentile {np.percentile(w, 99):.3g}); the gyro looks like deg/s: multiply by "
            "pi/180 (or set range_deg_per_s in the IMU model)"
        )
    f_med = float(np.median(f)) if f.size else math.nan
    lo, hi = ACCEL_MEDIAN_RANGE
    if not lo <= f_med <= hi:
        hint = ""
        if 0.6 <= f_med <= 1.4:
            hint = " It looks like g: multiply by 9.80665."
        elif 600.0 <= f_med <= 1400.0:
            hint = " It looks like mg: multiply by 9.80665e-3."
        raise UserInputError(
            f"imu: median specific force |f| = {f_med:.4g} is not ~9.8 m/s^2 (expected "
            f"{lo}-{hi} m/s^2 near the Earth's surface).{hint}"
        )


DEG_PER_RAD = 180.0 / math.pi


def check_gyro_against_headings(
    imu: pd.DataFrame, measurements: pd.DataFrame, window_s: float = 1.0
) -> None:
    """Raise ``UserInputError`` if the gyro turns ~57x as much as the measured headings.

    An undeclared deg/s gyro below the full scale (slow turns) passes
    :func:`check_imu_units`; while the vehicle turns, the headings show it. Over windows of
    ``window_s`` between yaw measurements, the gyro's rotation about the specific force
    (the vertical at low dynamics), ``int w_b . f_b/|f_b| dt``, is compared with the
    headings' change; windows turning less than 3 deg are not used. At least 5 windows
    with a median ratio within a factor 2 of 180/pi is a deg/s gyro.

    Parameters
    ----------
    imu : DataFrame
        ``t, gx, gy, gz, ax, ay, az`` (checked by :func:`validate_imu`).
    measurements : DataFrame
        Validated measurements; only rows with a finite ``yaw`` are used.
    window_s : float
        Span of the compared heading pairs [s].
    """
    if "yaw" not in measurements.columns:
        return
    yaw = measurements["yaw"].to_numpy(dtype=float)
    ok = np.isfinite(yaw)
    if ok.sum() < 6:
        return
    t_m, yaw = measurements["t"].to_numpy(dtype=float)[ok], np.unwrap(yaw[ok])
    data = imu[list(IMU_COLUMNS)].to_numpy(dtype=float)
    data = data[np.isfinite(data).all(axis=1)]
    # impossible samples (dropped later by the fusion, with an event) may overflow here
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        f_norm = np.linalg.norm(data[:, 4:7], axis=1)
        rate_up = np.einsum("ij,ij->i", data[:, 1:4], data[:, 4:7]) / f_norm
    rate_up = np.where(np.isfinite(rate_up), rate_up, 0.0)
    t = data[:, 0]
    angle = np.concatenate([[0.0], np.cumsum(0.5 * (rate_up[1:] + rate_up[:-1]) * np.diff(t))])
    j = np.searchsorted(t_m, t_m + window_s)
    i = np.flatnonzero((j < t_m.size) & (t_m >= t[0]))
    j = j[i]
    i, j = i[t_m[j] <= t[-1]], j[t_m[j] <= t[-1]]
    turn_m = yaw[j] - yaw[i]
    turn_g = np.interp(t_m[j], t, angle) - np.interp(t_m[i], t, angle)
    used = np.abs(turn_m) > np.radians(3.0)
    if used.sum() < 5:
        return
    ratio = float(np.median(turn_g[used] / turn_m[used]))
    if 0.5 * DEG_PER_RAD <= ratio <= 2.0 * DEG_PER_RAD:
        raise UserInputError(
            f"imu: the gyro turns {ratio:.3g} times as much as the measured headings over "
            f"{int(used.sum())} turning windows: the gyro looks like deg/s; multiply by pi/180"
        )


def validate_measurements(measurements: pd.DataFrame | None) -> pd.DataFrame:
    """Check a measurements table (docs/conventions.md) and return it (an empty table for None).

    Columns: ``t`` [s] and at least one complete group: ``yaw, yaw_std`` [rad]; or
    ``sun_bx, sun_by, sun_bz`` (measured, body), ``sun_nx, sun_ny, sun_nz`` (reference,
    ENU) and ``sun_std`` [rad]; or ``zupt_std`` [m/s] (zero-velocity at that time); or,
    without a clock, ``sun_azimuth_b, sun_azimuth_b_std`` [rad] (the sun's body azimuth).
    Optionally ``sun_elevation_b, sun_elevation_b_std`` [rad] and ``prior_roll, prior_pitch, prior_yaw`` [rad]: the attitude prior
    ``polins.measure`` used for the yaw (the ``measurements.csv`` of ``polins fuse`` has
    them; used by the tilt-coupled yaw model). NaN values mean "no measurement" (e.g. an image that ``polins.measure`` rejected) and
    are logged and skipped; a NaN time is an error.

    Raises
    ------
    ValueError
        Missing ``t`` or incomplete column groups, duplicated or non-monotonic times,
        yaw outside [-2 pi, 2 pi] (degrees?), sigmas > pi, sun vectors that are not unit
        vectors. (A non-finite or non-positive sigma is a data fault, not an error: its
        row is rejected with a reason.)
    """
    if measurements is None:
        return pd.DataFrame({"t": np.zeros(0)})
    df = _require_frame(measurements, "measurements")
    if "t" not in df.columns:
        raise UserInputError("measurements table lacks column 't'")
    groups = {"yaw": YAW_COLUMNS, "sun": SUN_COLUMNS, "zupt": ZUPT_COLUMNS,
              "sun_azimuth": SUN_AZIMUTH_COLUMNS}  # fmt: skip
    present = {g: [c for c in cols if c in df.columns] for g, cols in groups.items()}
    present["prior"] = [c for c in PRIOR_COLUMNS if c in df.columns]  # not a measurement
    for g, cols in {**groups, "prior": PRIOR_COLUMNS}.items():
        if present[g] and len(present[g]) != len(cols):
            missing = [c for c in cols if c not in df.columns]
            raise UserInputError(f"measurements: incomplete {g} columns, missing {missing}")
    if len(df) and not any(present[g] for g in groups):
        raise UserInputError(
            "measurements table has no measurement columns; expected yaw, yaw_std and/or "
            f"{list(SUN_COLUMNS)} and/or zupt_std"
        )
    t = _numeric(df, ("t",), "measurements")[:, 0]
    _check_times(t, "measurements")
    if present["yaw"]:
        yaw, std = _numeric(df, YAW_COLUMNS, "measurements").T
        big = np.flatnonzero(np.abs(yaw) > 2.0 * np.pi)
        if big.size:
            raise UserInputError(
                f"measurements: yaw={yaw[big[0]]:.4g} at row {big[0]} is outside "
                "[-2 pi, 2 pi]; yaw must be in radians (ENU, counter-clockwise from East)"
            )
        _check_std(std, "yaw_std", np.pi)
    if present["sun"]:
        sun = _numeric(df, SUN_COLUMNS, "measurements")
        for name, vec in (("sun_b", sun[:, 0:3]), ("sun_n", sun[:, 3:6])):
            norm = np.linalg.norm(vec, axis=1)
            bad = np.flatnonzero(np.isfinite(norm) & (np.abs(norm - 1.0) > 0.01))
            if bad.size:
                raise UserInputError(
                    f"measurements: {name} at row {bad[0]} has norm {norm[bad[0]]:.4g}; "
                    "sun vectors must be unit vectors"
                )
        _check_std(sun[:, 6], "sun_std", np.pi)
    for name, upper in (("sun_azimuth_b", 2.0 * np.pi), ("sun_elevation_b", np.pi / 2)):
        if name in df.columns:
            angle = _numeric(df, (name,), "measurements")[:, 0]
            big = np.flatnonzero(np.abs(angle) > upper + 1e-9)
            if big.size:
                raise UserInputError(
                    f"measurements: {name}={angle[big[0]]:.4g} at row {big[0]} is outside "
                    f"[-{upper:.4g}, {upper:.4g}]; it must be in radians"
                )
    for name in ("sun_azimuth_b_std", "sun_elevation_b_std"):
        if name in df.columns:
            _check_std(_numeric(df, (name,), "measurements")[:, 0], name, np.pi)
    if present["zupt"]:
        _check_std(_numeric(df, ZUPT_COLUMNS, "measurements")[:, 0], "zupt_std", np.inf)
    if present["prior"]:
        angles = _numeric(df, PRIOR_COLUMNS, "measurements")
        big = np.flatnonzero(np.any(np.abs(angles) > 2.0 * np.pi, axis=1))
        if big.size:
            raise UserInputError(
                f"measurements: prior angles at row {big[0]} are outside [-2 pi, 2 pi]; "
                "prior_roll, prior_pitch, prior_yaw must be in radians"
            )
    return df


def _check_std(std: FloatArray, name: str, upper: float) -> None:
    """A finite sigma above ``upper`` is a unit mistake (degrees for radians): refused. A
    non-finite or non-positive sigma is a data fault: its row is rejected with a reason
    (:func:`polins.fusion.items.items_from_table`, docs/faults.md)."""
    bad = np.flatnonzero(np.isfinite(std) & (std > upper))
    if bad.size:
        raise UserInputError(
            f"measurements: {name}={std[bad[0]]:.4g} at row {bad[0]} must be <= "
            f"{upper:.4g} (radians expected)"
        )


def output_mask(t: FloatArray, rate_hz: float | None) -> NDArray[np.bool_]:
    """IMU samples reported at ``rate_hz`` [Hz]: the first sample at or after each grid time
    ``t[0] + k / rate_hz``, and the last sample (all samples for None)."""
    if rate_hz is None:
        return np.ones(len(t), dtype=bool)
    if not rate_hz > 0:
        raise UserInputError(f"output_rate_hz must be > 0 or None, got {rate_hz}")
    cell = np.floor((t - t[0]) * rate_hz + 1e-9)
    mask = np.concatenate([[True], np.diff(cell) > 0])
    mask[-1] = True
    return mask
