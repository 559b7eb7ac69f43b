"""Validation of the fusion inputs: the IMU table and the measurements table (docs/conventions.md).

A mistake in a table raises ``ValueError`` with a message naming the column, the row and
what was expected; unit mistakes that can be detected (gyro in deg/s, accelerometer in g or
mg, yaw in degrees) are such mistakes. Faults in the data are not errors: they follow the
policy of :mod:`polins.fusion.faults` (docs/faults.md). :func:`prepare` turns a run's
inputs into what both backends solve (:class:`Prepared`).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from polins.compass.measurement import Measurement
from polins.errors import UserInputError
from polins.frames import euler_from_rot_nb
from polins.fusion.config import FuseConfig, config_with_site, scaled_measurement_noise
from polins.fusion.faults import (
    FusionEvent,
    GyroHeadingCheck,
    ImuScreen,
    check_imu_units,
    default_max_gap_s,
    gap_item,
    skip_in_gaps,
)
from polins.fusion.items import MeasurementItem, items_from_table, no_clock_table
from polins.fusion.vehicle import odometer_items
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


@dataclass(frozen=True, eq=False)
class ImuArrays:
    """Validated IMU samples: ``t`` (N,) [s], ``gyro_b`` (N, 3) [rad/s], ``accel_b`` (N, 3)
    [m/s^2], the median sample interval ``dt`` [s], the events of the dropped samples and
    of the gaps, and ``gaps``: one ``"gap"`` item per interval longer than ``max_gap_s``
    (:func:`polins.fusion.faults.gap_item`), at the sample after it."""

    t: FloatArray
    gyro_b: FloatArray
    accel_b: FloatArray
    dt: float
    events: tuple[FusionEvent, ...] = ()
    gaps: tuple[MeasurementItem, ...] = ()
    gap_spans: tuple[tuple[float, float], ...] = ()  # (t_a, t_b) [s]: the samples around each


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
    t, gyro, accel = data[:, 0], data[:, 1:4], data[:, 4:7]
    _check_times(t, "imu")
    full_scale = (model or load_imu("mems-typical")).full_scale()
    finite = np.isfinite(data[:, 1:]).all(axis=1)
    with np.errstate(invalid="ignore", over="ignore"):
        check_imu_units(np.linalg.norm(gyro[finite], axis=1),
                        np.linalg.norm(accel[finite], axis=1), full_scale[0])  # fmt: skip
    d = np.diff(t[finite])
    dt = float(np.median(d)) if d.size else math.nan
    screen = ImuScreen(full_scale, default_max_gap_s(max_gap_s, dt))
    keep, events, ends = screen.screen(t, gyro, accel)
    if keep.sum() < 2:
        raise UserInputError(f"imu: fewer than 2 usable samples ({int(keep.sum())} of {len(t)})")
    gaps, spans = [], []
    for k in ends.tolist():
        j = int(np.flatnonzero(keep[:k])[-1])  # the accepted sample before the gap
        item, event = gap_item(float(t[j]), float(t[k]), (gyro[j], gyro[k]), (accel[j], accel[k]))
        gaps.append(item)
        spans.append((float(t[j]), float(t[k])))
        events.append(event)
    return ImuArrays(t=t[keep].copy(), gyro_b=gyro[keep].copy(), accel_b=accel[keep].copy(),
                     dt=float(np.median(np.diff(t[keep]))), events=tuple(events), gaps=tuple(gaps),
                     gap_spans=tuple(spans))  # fmt: skip


def check_gyro_against_headings(arrays: ImuArrays, measurements: pd.DataFrame) -> None:
    """Raise :class:`~polins.fusion.faults.ImuUnitsError` if the gyro turns ~57x as much as
    the measured headings (:class:`~polins.fusion.faults.GyroHeadingCheck`) of validated
    measurements: :func:`heading_proxy` of its rows."""
    check = GyroHeadingCheck(keep_s=math.inf)
    check.add_imu(arrays.t, arrays.gyro_b, arrays.accel_b)
    check.add_headings(measurements["t"].to_numpy(dtype=float), heading_proxy(measurements))


def heading_proxy(rows: pd.DataFrame | Mapping[str, Any]) -> FloatArray:
    """The heading of measurement rows for the gyro check [rad]: ``-sun_azimuth_b`` where
    finite (prior-free), else ``yaw``, else NaN."""
    n = len(rows["t"]) if isinstance(rows, pd.DataFrame) else 1
    out = np.full(n, np.nan)
    for name, sign in (("yaw", 1.0), ("sun_azimuth_b", -1.0)):
        if name in rows:
            value = sign * np.asarray(rows[name], dtype=float).reshape(-1)
            out = np.where(np.isfinite(value), value, out)
    return out


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
    present = _measurement_groups(df)
    t = _numeric(df, ("t",), "measurements")[:, 0]
    _check_times(t, "measurements")
    if present["yaw"]:
        _check_yaw(df)
    if present["sun"]:
        _check_sun_vectors(df)
    _check_sun_angles(df)
    if present["zupt"]:
        _check_std(_numeric(df, ZUPT_COLUMNS, "measurements")[:, 0], "zupt_std", np.inf)
    if present["prior"]:
        _check_prior(df)
    return df


def _measurement_groups(df: pd.DataFrame) -> dict[str, list[str]]:
    """The columns of each group (yaw, sun, zupt, sun_azimuth, prior) present in ``df``;
    refuses an incomplete group and a non-empty table without a measurement group."""
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
    return present


def _check_yaw(df: pd.DataFrame) -> None:
    """Yaw in [-2 pi, 2 pi] (radians) and its sigma."""
    yaw, std = _numeric(df, YAW_COLUMNS, "measurements").T
    big = np.flatnonzero(np.abs(yaw) > 2.0 * np.pi)
    if big.size:
        raise UserInputError(
            f"measurements: yaw={yaw[big[0]]:.4g} at row {big[0]} is outside "
            "[-2 pi, 2 pi]; yaw must be in radians (ENU, counter-clockwise from East)"
        )
    _check_std(std, "yaw_std", np.pi)


def _check_sun_vectors(df: pd.DataFrame) -> None:
    """Unit measured and reference sun vectors (1 % tolerance) and their sigma."""
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


def _check_sun_angles(df: pd.DataFrame) -> None:
    """The sun's body azimuth and elevation, where given, in radians, and their sigmas."""
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


def _check_prior(df: pd.DataFrame) -> None:
    """The attitude prior's angles in [-2 pi, 2 pi] (radians)."""
    angles = _numeric(df, PRIOR_COLUMNS, "measurements")
    big = np.flatnonzero(np.any(np.abs(angles) > 2.0 * np.pi, axis=1))
    if big.size:
        raise UserInputError(
            f"measurements: prior angles at row {big[0]} are outside [-2 pi, 2 pi]; "
            "prior_roll, prior_pitch, prior_yaw must be in radians"
        )


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


@dataclass(frozen=True, eq=False)
class Prepared:
    """A fusion run's inputs, validated and resolved: what both backends solve.

    Attributes
    ----------
    config : FuseConfig
        The resolved configuration (``FuseConfig.resolve``): a site, ``tilt_coupling`` and
        ``no_clock`` decided, ``odometer_std`` set when odometry is given.
    imu : ImuArrays
        The accepted IMU samples and the ``"gap"`` items of the IMU gaps.
    items : list of MeasurementItem
        The measurement rows (zero-velocity rows among them) and odometer speeds; those
        with an unusable value or inside an IMU gap invalid, with their reason.
    events : list of FusionEvent
        Dropped IMU samples, IMU gaps and the measurements skipped inside them.
    rot_nb0 : Rotation or None
        The initial attitude (None: self-alignment).
    """

    config: FuseConfig
    imu: ImuArrays
    items: list[MeasurementItem]
    events: list[FusionEvent]
    rot_nb0: Rotation | None


def prepare(
    imu: pd.DataFrame,
    measurements: pd.DataFrame | None,
    backend: str,
    rot_nb0: Rotation | None,
    config: FuseConfig | None,
    odometry: pd.DataFrame | None = None,
) -> Prepared:
    """Validate a run's inputs and resolve its configuration, for either backend.

    The arguments are those of :func:`polins.fusion.run_fusion`. Raises on a mistake
    (``UserInputError``; :class:`~polins.fusion.faults.ImuUnitsError` for IMU units, also
    those the headings reveal); applies the fault policy of :mod:`polins.fusion.faults`
    to the data; warns once when no site is given (the site assumed) and once in the
    no-clock mode.
    """
    cfg = config or FuseConfig()
    cfg.check_backend(backend)
    if rot_nb0 is not None and (not isinstance(rot_nb0, Rotation) or not rot_nb0.single):
        raise UserInputError("rot_nb0 must be a single scipy Rotation (body FLU -> ENU) or None")
    meas = scaled_measurement_noise(validate_measurements(measurements), cfg)
    arrays = validate_imu(imu, max_gap_s=cfg.gap_s, model=cfg.imu)
    check_gyro_against_headings(arrays, meas)
    cfg = config_with_site(cfg, stacklevel=5)
    if no_clock_table(meas):
        cfg = announce_no_clock(cfg)
    cfg = cfg.resolve(priors=all(c in meas.columns for c in PRIOR_COLUMNS),
                      odometry=odometry is not None)  # fmt: skip
    items = items_from_table(meas, use_sun=cfg.gating.use_sun, heading_bias=cfg.heading_bias)
    if odometry is not None and cfg.odometer_sigma is not None:  # "off": ignored
        items += odometer_items(odometry, cfg.odometer_sigma)
    items, in_gaps = skip_in_gaps(arrays.gap_spans, items)
    return Prepared(cfg, arrays, items, [*arrays.events, *in_gaps], rot_nb0)


def announce_no_clock(config: FuseConfig) -> FuseConfig:
    """The config of a measurements table in the no-clock mode (sun_azimuth_b without yaw
    or sun_n), with the one warning that says so (both backends)."""
    config = config.resolve(sun_azimuth_only=True)  # no_clock=off: a one-line error
    warnings.warn(
        "no-clock mode: the measurements carry sun_azimuth_b without yaw or sun_n; the sun's "
        "ENU azimuth is a filter state and the heading is relative to the initial yaw "
        "(absolute heading is not observable without a clock; docs/filter.md, 'No clock')",
        UserWarning,
        stacklevel=5,
    )
    return config


def measurement_row(measurement: Measurement) -> dict[str, Any]:
    """One :class:`polins.Measurement` as a row of the measurements table ``polins.fuse``
    takes: its fields (``Measurement.as_dict``), the body sun vector as ``sun_bx, sun_by,
    sun_bz`` (``sun_l``, ``sun_c`` left out), NaN for a missing value. A refused
    measurement's row is all NaN: ``polins.fuse`` skips it with its reason logged."""
    fields = measurement.as_dict()
    sun_b = fields.pop("sun_b")
    del fields["sun_l"], fields["sun_c"]
    row = {k: math.nan if v is None else v for k, v in fields.items()}
    for c, v in zip("xyz", sun_b, strict=True):
        row[f"sun_b{c}"] = math.nan if v is None else float(v)
    return row


def measurement_table(
    measurements: Measurement | Sequence[Measurement],
    t: ArrayLike,
    *,
    sun_n: ArrayLike | None = None,
    rot_nb_prior: Rotation | None = None,
) -> pd.DataFrame:
    """Measurements (one or a list) as the measurements table ``polins.fuse`` takes.

    Parameters
    ----------
    measurements : Measurement or sequence of Measurement
        What ``polins.measure`` returned, one per image.
    t : float or (N,) array_like
        The image times [s] (the IMU's clock).
    sun_n : (3,) or (N, 3) array_like, optional
        The ENU sun vector each image was measured with: adds ``sun_nx, sun_ny, sun_nz``,
        and with them the 2-DOF sun-vector rows (``use_sun``); without it the sun-vector
        columns are left out and the rows are yaw measurements.
    rot_nb_prior : Rotation, optional
        The attitude prior of each image (single or N): adds ``prior_roll, prior_pitch,
        prior_yaw`` [rad], which the tilt-coupled yaw model uses.

    Returns
    -------
    DataFrame
        One row per measurement: ``t`` and the :func:`measurement_row` columns.
    """
    ms = [measurements] if isinstance(measurements, Measurement) else list(measurements)
    times = np.atleast_1d(np.asarray(t, dtype=float))
    if len(times) != len(ms):
        raise UserInputError(f"{len(ms)} measurements but {len(times)} times")
    table = pd.DataFrame([measurement_row(m) for m in ms])
    table.insert(0, "t", times)
    if sun_n is None:
        table = table.drop(columns=["sun_bx", "sun_by", "sun_bz", "sun_std"])
    else:
        s_n = np.broadcast_to(np.asarray(sun_n, dtype=float), (len(ms), 3))
        for i, c in enumerate("xyz"):
            table[f"sun_n{c}"] = s_n[:, i]
    if rot_nb_prior is not None:
        mats = np.broadcast_to(rot_nb_prior.as_matrix(), (len(ms), 3, 3))
        yaw, pitch, roll = euler_from_rot_nb(Rotation.from_matrix(mats))
        table["prior_roll"], table["prior_pitch"], table["prior_yaw"] = roll, pitch, yaw
    return table
