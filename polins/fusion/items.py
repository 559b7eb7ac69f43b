"""Measurement items: the rows of a measurements table turned into filter measurements, their models and gate.

One set of rules turns a table row into items (:func:`items_from_table`: a complete sun
vector, else a yaw, NaN -> an invalid item that is logged, ``zupt_std`` -> a zero-velocity
item); :func:`item_model` linearizes an item with the shared ``(z, H, R)`` models of
:mod:`polins.fusion.measurement`; :func:`gate_limit` is the chi-square gate. The ESKF and
the GTSAM graph both use exactly these.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from polins.frames import euler_from_rot_nb, rot_nb_from_euler
from polins.fusion.measurement import (
    Linearized,
    mount_rotation,
    non_holonomic_kernel,
    odometer_kernel,
    sun_azimuth_kernel,
    sun_direction_cov_b,
    sun_kernel,
    yaw_kernel,
    zero_rate_kernel,
    zero_velocity_kernel,
)

FloatArray = NDArray[np.float64]

_KIND_ORDER = {"gap": -1, "yaw": 0, "sun": 1, "sun_azimuth": 1, "zupt": 2, "zaru": 2, "nhc": 3,
               "odo": 4}  # fmt: skip
HEADING_KINDS = ("yaw", "sun", "sun_azimuth")  # the measurements of the heading
# A heading row's model part counts as correlated from image to image beyond this many
# times its noise part (docs/filter.md §5.7): below it the jackknife may report pixel noise.
NOISE_ALLOWANCE = 2.0
# the name of the no-clock state of the sun's ENU azimuth (docs/filter.md, "No clock")
SUN_AZIMUTH_STATE = "sun_azimuth_n"
# the names of the mounting pitch and yaw error states and of the lever-arm error state
# (docs/filter.md §5.6)
MOUNT_STATES = ("mount_pitch", "mount_yaw")
LEVER_STATE = "lever_b"


@functools.lru_cache(maxsize=64)
def gate_limit(prob: float | None, dof: int) -> float:
    """Chi-square gate: the ``prob`` quantile with ``dof`` degrees of freedom (inf for None)."""
    return math.inf if prob is None else float(chi2.ppf(prob, dof))


@dataclass(frozen=True, eq=False)
class MeasurementItem:
    """One scalar/vector measurement waiting to be applied at time ``t``.

    ``kind`` is ``"yaw"``, ``"sun"``, ``"sun_azimuth"`` (no clock: ``yaw`` holds the sun's
    body azimuth ``sun_azimuth_b``, ``elevation_b`` its body elevation, NaN when unknown),
    ``"zupt"``, ``"zaru"`` (zero angular rate: ``gyro_b`` the mean measured rate over an
    interval at rest, ``rate_n`` the ENU rate a body at rest senses), ``"nhc"``, ``"odo"``
    (a wheel-odometer ``speed`` [m/s]), or ``"gap"`` (not a
    measurement: the IMU resumes after a gap, the filter adds ``inflation`` to the
    covariance of its navigation errors, docs/filter.md); ``valid`` is False for rows with NaN values or a
    non-finite or non-positive sigma, or inside an IMU gap (they are logged as rejected
    with ``reason`` and not used).
    """

    t: float
    kind: str
    std: float
    yaw: float = math.nan
    sun_b: FloatArray | None = None
    sun_n: FloatArray | None = None
    valid: bool = True
    mat_nb_prior: FloatArray | None = None  # the prior polins.measure used (yaw rows)
    reason: str = ""  # why an invalid item is not used
    inflation: FloatArray | None = None  # "gap": variances added to the 9 navigation errors
    cov_b: FloatArray | None = None  # "sun": (3, 3) direction covariance [rad^2], else std^2 I
    elevation_b: float = math.nan  # "sun_azimuth": the sun's elevation in the body frame [rad]
    axis: bool = False  # "sun_azimuth": the 180 deg branch is ambiguous (an axis, not a direction)
    speed: float = math.nan  # "odo": the odometer's forward speed [m/s]
    mat_vb: FloatArray | None = None  # "nhc", "odo": IMU mounting, body -> vehicle frame
    lever_vel_b: FloatArray | None = None  # "nhc", "odo": omega_b x lever_arm_b [m/s]
    gyro_b: FloatArray | None = None  # "nhc", "odo" with a lever-arm state: omega_b [rad/s];
    # "zaru": the mean measured rate at rest [rad/s]
    rate_n: FloatArray | None = None  # "zaru": ENU rate sensed at rest (Earth rate) [rad/s]
    model_std: float = 0.0  # heading kinds: the sigma's part correlated between images [rad]

    @property
    def order(self) -> tuple[float, int]:
        """Processing order: time, then yaw/sun before zero-velocity before NHC."""
        return (self.t, _KIND_ORDER[self.kind])


def item_model(
    item: MeasurementItem,
    mat_nb: FloatArray,
    vel_n: FloatArray | None,
    tilt_coupling: bool,
    states: Mapping[str, FloatArray] | None = None,
) -> Linearized:
    """The 15-state measurement model (:mod:`polins.fusion.measurement`) of ``item`` at a
    nominal attitude ``mat_nb`` and ENU velocity ``vel_n`` [m/s] (only zero-velocity and
    non-holonomic items use it); ``tilt_coupling`` as ``FuseConfig.tilt_coupling``;
    ``states`` the estimates of the sensor-error blocks by name (a ``"sun_azimuth"`` item
    needs :data:`SUN_AZIMUTH_STATE`; a ``"zaru"`` item takes the gyro bias ``"bg"``, zero
    when absent; with :data:`MOUNT_STATES` the non-holonomic and
    odometer items use the mounting turned by their estimate,
    :func:`~polins.fusion.measurement.mount_rotation`, with :data:`LEVER_STATE` the lever
    arm plus its estimate). The ESKF and the GTSAM graph both linearize their items here.
    """
    var = item.std * item.std
    if item.kind == "yaw":
        if tilt_coupling and item.sun_n is not None:
            return yaw_kernel(mat_nb, item.yaw, var, item.sun_n, item.mat_nb_prior)
        return yaw_kernel(mat_nb, item.yaw, var, None)
    if item.kind == "sun":
        return sun_kernel(mat_nb, item.sun_b, item.sun_n, var, None, item.cov_b)  # type: ignore[arg-type]
    if item.kind == "sun_azimuth":
        if states is None or SUN_AZIMUTH_STATE not in states:
            raise ValueError("a sun_azimuth item needs the sun azimuth state (no-clock mode)")
        return sun_azimuth_kernel(
            mat_nb, item.yaw, var, float(states[SUN_AZIMUTH_STATE][0]),
            sun_elevation_n(mat_nb, item.yaw, item.elevation_b), axis=item.axis,
        )  # fmt: skip
    return _vehicle_model(item, mat_nb, vel_n, states)


def _vehicle_model(
    item: MeasurementItem,
    mat_nb: FloatArray,
    vel_n: FloatArray | None,
    states: Mapping[str, FloatArray] | None,
) -> Linearized:
    """:func:`item_model` of the vehicle's kinds (zero rate, zero velocity, NHC, odometer)."""
    var = item.std * item.std
    if item.kind == "zaru":
        assert item.gyro_b is not None  # built by VehicleAiding
        bias = states["bg"] if states is not None and "bg" in states else np.zeros(3)
        return zero_rate_kernel(mat_nb, item.gyro_b, bias, np.full(3, var), item.rate_n)
    if item.kind not in ("zupt", "nhc", "odo"):  # pragma: no cover - built by measurement_items
        raise ValueError(f"unknown measurement kind {item.kind!r}")
    if vel_n is None:
        raise ValueError(f"a {item.kind} item needs the nominal velocity")
    if item.kind == "zupt":
        return zero_velocity_kernel(vel_n, np.full(3, var))
    mat_vb = item.mat_vb
    if states is not None and MOUNT_STATES[0] in states:
        turn = mount_rotation(np.concatenate([states[name] for name in MOUNT_STATES]))
        mat_vb = turn if mat_vb is None else turn @ mat_vb
    lever_vel_b = item.lever_vel_b
    if states is not None and LEVER_STATE in states and item.gyro_b is not None:
        extra = np.cross(item.gyro_b, states[LEVER_STATE])
        lever_vel_b = extra if lever_vel_b is None else lever_vel_b + extra
    if item.kind == "odo":
        return odometer_kernel(mat_nb, vel_n, item.speed, var, mat_vb, lever_vel_b)
    return non_holonomic_kernel(mat_nb, vel_n, np.full(2, var), mat_vb, lever_vel_b)


def sun_elevation_n(mat_nb: FloatArray, azimuth_b: float, elevation_b: float) -> float:
    """The sun's ENU elevation [rad] from its body azimuth and elevation [rad] at the
    attitude ``mat_nb``; 0 when the body elevation is unknown (NaN): the tilt terms of the
    no-clock model then vanish (docs/filter.md, "No clock")."""
    if math.isnan(elevation_b):
        return 0.0
    ce = math.cos(elevation_b)
    s_b = np.array([ce * math.cos(azimuth_b), ce * math.sin(azimuth_b), math.sin(elevation_b)])
    return math.asin(max(-1.0, min(1.0, float(mat_nb[2] @ s_b))))


def no_clock_table(measurements: pd.DataFrame | Mapping[str, ArrayLike]) -> bool:
    """True when a measurements table carries the sun's body azimuth (``sun_azimuth_b``)
    and neither a yaw nor an ENU sun vector: the no-clock mode (docs/filter.md, "No clock")."""
    cols = set(measurements.columns if isinstance(measurements, pd.DataFrame) else measurements)
    return "sun_azimuth_b" in cols and not ({"yaw", "sun_nx"} & cols)


def items_from_table(
    measurements: pd.DataFrame | Mapping[str, ArrayLike],
    *,
    use_sun: bool = True,
    heading_bias: str = "off",
) -> list[MeasurementItem]:
    """The filter's measurement items of a validated measurements table, in row order.

    ``measurements`` is a DataFrame or a mapping of column name to values (one row per
    element). The rules: a sun vector if complete and ``use_sun``, else a yaw; NaN -> an
    invalid item (logged, not used); ``zupt_std`` -> a zero-velocity item; yaw items carry
    the prior attitude of the ``prior_*`` columns; a sun vector carries the direction
    covariance of ``sun_std`` (azimuth) and ``sun_elevation_b_std`` (elevation) when the
    row has the latter; a table without yaw and ``sun_n`` but with ``sun_azimuth_b,
    sun_azimuth_b_std`` gives ``"sun_azimuth"`` items (no clock; docs/filter.md), an axis
    where ``sun_azimuth_b_alt`` is given (the 180 deg branch is ambiguous).

    ``heading_bias`` (``FuseConfig.heading_bias``, docs/filter.md §5.7) says which part of
    a heading row's sigma a heading-bias state carries: ``"fixed"``: its
    ``yaw_std_correlated``, and the yaw, sun-azimuth and sun-vector sigmas keep the rest (for
    a sun vector its azimuth part), ``std sqrt(1 - (part / yaw_std)^2)``, at least a tenth
    of ``std``; ``"model"``: its ``yaw_std_model`` [rad] beyond ``NOISE_ALLOWANCE`` times
    its ``yaw_std_noise`` becomes the item's ``model_std`` (0 without the column; on a sky
    that follows the estimator's model the jackknife's model part is pixel noise, below
    twice the noise part), and the backend takes its share out when it applies the item
    (:func:`polins.fusion.sky_states.without_bias_part`).
    """
    df = measurements
    n = len(df) if isinstance(df, pd.DataFrame) else len(np.atleast_1d(df["t"]))

    def col(name: str) -> FloatArray:
        if name not in df:
            return np.full(n, np.nan)
        return np.atleast_1d(np.asarray(df[name], dtype=float))

    t = col("t")
    has_yaw = "yaw" in df
    has_sun = "sun_std" in df
    has_zupt = "zupt_std" in df
    yaw, yaw_std = col("yaw"), col("yaw_std")
    sun_b = np.column_stack([col(f"sun_b{c}") for c in "xyz"])
    sun_n = np.column_stack([col(f"sun_n{c}") for c in "xyz"])
    sun_std, zupt_std = col("sun_std"), col("zupt_std")
    mat_prior, prior_ok = _prior_matrices(
        np.column_stack([col(c) for c in ("prior_yaw", "prior_pitch", "prior_roll")])
    )
    with np.errstate(invalid="ignore"):
        n_ok = np.all(np.isfinite(sun_n), axis=1)
        sun_ok = has_sun & np.all(np.isfinite(sun_b), axis=1) & n_ok & _sigma_ok(sun_std)
        yaw_ok = np.isfinite(yaw) & _sigma_ok(yaw_std)
        zupt_ok = _sigma_ok(zupt_std)
    # Python scalars (lists) in the row loop: numpy scalar indexing costs more
    heading = "sun_azimuth" if no_clock_table(df) else "yaw"
    if heading == "sun_azimuth":  # the sun's body azimuth takes the place of the yaw
        has_yaw, yaw, yaw_std = True, col("sun_azimuth_b"), col("sun_azimuth_b_std")
        with np.errstate(invalid="ignore"):
            yaw_ok = np.isfinite(yaw) & _sigma_ok(yaw_std)
    model_std = np.zeros(n)
    if heading_bias == "fixed" and "yaw_std_correlated" in df:
        white = _white_share(col("yaw_std_correlated"), yaw_std)
        yaw_std = np.where(yaw_ok, yaw_std * white, yaw_std)
        sun_std = np.where(sun_ok, sun_std * white, sun_std)
    elif heading_bias == "model":
        model_std = correlated_model_std(col("yaw_std_model"), col("yaw_std_noise"))
    elev_b, elev_std = col("sun_elevation_b"), col("sun_elevation_b_std")
    axis = np.isfinite(col("sun_azimuth_b_alt")) & (heading == "sun_azimuth")
    with np.errstate(invalid="ignore"):
        cov_ok = (sun_ok & _sigma_ok(elev_std)).tolist()
    t_l, yaw_l, yaw_std_l, sun_std_l = t.tolist(), yaw.tolist(), yaw_std.tolist(), sun_std.tolist()
    model_l = model_std.tolist()
    zupt_l, sun_ok_l, yaw_ok_l, zupt_ok_l = (
        zupt_std.tolist(), sun_ok.tolist(), yaw_ok.tolist(), zupt_ok.tolist()
    )  # fmt: skip
    # a zero-velocity row (zupt_std, no heading and no sun values) is no heading row
    heading_l = (np.isnan(zupt_std) | ~(np.isnan(yaw) & np.isnan(yaw_std)
                 & np.all(np.isnan(sun_b), axis=1))).tolist()  # fmt: skip
    n_ok_l, prior_ok_l = n_ok.tolist(), prior_ok.tolist()
    items: list[MeasurementItem] = []
    for i in range(n):
        ti = t_l[i]
        if use_sun and sun_ok_l[i]:
            cov_b = None
            if cov_ok[i]:
                cov_b = sun_direction_cov_b(sun_b[i], sun_std_l[i], float(elev_std[i]))
            items.append(
                MeasurementItem(
                    ti,
                    "sun",
                    sun_std_l[i],
                    sun_b=sun_b[i].copy(),
                    sun_n=sun_n[i].copy(),
                    cov_b=cov_b,
                    model_std=model_l[i],
                )
            )
        elif has_yaw and heading_l[i]:
            ok = yaw_ok_l[i]
            items.append(
                MeasurementItem(
                    ti,
                    heading,
                    yaw_std_l[i] if ok else math.nan,
                    yaw=yaw_l[i] if ok else math.nan,
                    sun_n=sun_n[i].copy() if n_ok_l[i] else None,
                    valid=ok,
                    mat_nb_prior=mat_prior[i] if prior_ok_l[i] else None,
                    reason="" if ok else _invalid_reason(heading, yaw_l[i], yaw_std_l[i]),
                    elevation_b=float(elev_b[i]),
                    axis=bool(axis[i]),
                    model_std=model_l[i],
                )
            )
        elif has_sun and heading_l[i]:
            reason = _invalid_reason("sun", math.nan, sun_std_l[i])
            items.append(MeasurementItem(ti, "sun", math.nan, valid=False, reason=reason))
        if has_zupt and not math.isnan(zupt_l[i]):
            ok = zupt_ok_l[i]
            reason = "" if ok else _invalid_reason("zupt", 0.0, zupt_l[i])
            items.append(
                MeasurementItem(ti, "zupt", zupt_l[i] if ok else math.nan, valid=ok, reason=reason)
            )
    return items


def correlated_model_std(yaw_std_model: ArrayLike, yaw_std_noise: ArrayLike) -> FloatArray:
    """The part [rad] of heading rows' model part taken as correlated from image to image:
    ``sqrt(max(yaw_std_model^2 - (NOISE_ALLOWANCE yaw_std_noise)^2, 0))``, 0 where unknown
    (docs/filter.md §5.7; NaN noise counts as 0)."""
    model = np.asarray(yaw_std_model, dtype=float)
    noise = np.nan_to_num(np.asarray(yaw_std_noise, dtype=float))
    with np.errstate(invalid="ignore"):
        excess = model**2 - (NOISE_ALLOWANCE * noise) ** 2
    return np.sqrt(np.maximum(np.nan_to_num(excess), 0.0))


def _prior_matrices(prior: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
    """The prior attitude matrices ``mat_nb`` of ``(yaw, pitch, roll)`` rows [rad] (NaN
    where a row is incomplete) and which rows are complete."""
    prior_ok = np.all(np.isfinite(prior), axis=1)
    mat_prior = np.full((prior.shape[0], 3, 3), np.nan)
    if prior_ok.any():
        mat_prior[prior_ok] = rot_nb_from_euler(*prior[prior_ok].T).as_matrix()
    return mat_prior, prior_ok


def _white_share(yaw_std_correlated: FloatArray, yaw_std: FloatArray) -> FloatArray:
    """The factor on heading sigmas that leaves the part a fixed heading-bias state does not
    carry: ``sqrt(1 - (part / yaw_std)^2)``, at least a tenth; 1 where undefined."""
    part = np.nan_to_num(yaw_std_correlated)
    with np.errstate(invalid="ignore", divide="ignore"):  # a share of the heading sigma
        white = np.sqrt(np.maximum(1.0 - (part / yaw_std) ** 2, 0.01))
    return np.where(np.isfinite(white), white, 1.0)


def _sigma_ok(std: FloatArray) -> NDArray[np.bool_]:
    """Usable 1-sigmas: finite and positive (docs/faults.md: others reject their row)."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(std) & (std > 0)


def _invalid_reason(kind: str, value: float, std: float) -> str:
    """The reason an invalid row's item is not used (its update record)."""
    if not math.isnan(std) and not (math.isfinite(std) and std > 0):
        return f"invalid {kind}_std={std:g}: a 1-sigma must be finite and > 0"
    if kind == "sun" or math.isnan(value) or math.isnan(std):
        return f"no {kind} measurement (NaN values)"
    return f"invalid {kind}={value:g}"


def measurement_items(
    t: float,
    *,
    yaw: float | None = None,
    yaw_std: float | None = None,
    sun_b: ArrayLike | None = None,
    sun_n: ArrayLike | None = None,
    sun_std: float | None = None,
    zupt_std: float | None = None,
    use_sun: bool = True,
    rot_nb_prior: Rotation | None = None,
    sky: Mapping[str, float] | None = None,
    heading_bias: str = "off",
) -> list[MeasurementItem]:
    """The measurement items of one row, by the rules of :func:`items_from_table`.

    Parameters are the ``measurements`` table's columns (docs/filter.md); ``rot_nb_prior``
    is the prior ``polins.measure`` used for the yaw (tilt coupling); ``sky`` more columns
    by name: ``sun_azimuth_b, sun_azimuth_b_std`` (without ``yaw`` and ``sun_n``: a no-clock
    row, for ``ESKF.add_items``), ``sun_elevation_b, sun_elevation_b_std``,
    ``yaw_std_model``, ``yaw_std_correlated`` (the parts a heading-bias state carries,
    ``heading_bias`` as in :func:`items_from_table`).
    """
    row: dict[str, list[float]] = {"t": [float(t)]}
    row.update({name: [float(value)] for name, value in (sky or {}).items()})
    if yaw is not None or yaw_std is not None:
        row["yaw"] = [math.nan if yaw is None else float(yaw)]
        row["yaw_std"] = [math.nan if yaw_std is None else float(yaw_std)]
    if sun_b is not None or sun_std is not None or sun_n is not None:
        b = np.full(3, np.nan) if sun_b is None else np.asarray(sun_b, dtype=float)
        n = np.full(3, np.nan) if sun_n is None else np.asarray(sun_n, dtype=float)
        row.update({f"sun_b{c}": [b[i]] for i, c in enumerate("xyz")})
        row.update({f"sun_n{c}": [n[i]] for i, c in enumerate("xyz")})
        if sun_std is not None or sun_b is not None:
            row["sun_std"] = [math.nan if sun_std is None else float(sun_std)]
    if zupt_std is not None:
        row["zupt_std"] = [float(zupt_std)]
    if rot_nb_prior is not None:
        y, p, r = euler_from_rot_nb(rot_nb_prior)
        row.update(prior_yaw=[float(y)], prior_pitch=[float(p)], prior_roll=[float(r)])
    return items_from_table(row, use_sun=use_sun, heading_bias=heading_bias)


@dataclass(frozen=True)
class UpdateRecord:
    """Log entry of one measurement: NIS, acceptance, and the reason for a rejection.

    ``innovation`` (``nu``, ``dim`` values) and ``innovation_var`` (``S``, ``dim x dim``
    row-major) are the gated innovation and its covariance (ESKF updates; empty otherwise),
    for the innovation likelihood of ``polins.tuning``.
    """

    t: float
    name: str
    dim: int
    nis: float
    accepted: bool
    reason: str
    innovation: tuple[float, ...] = ()
    innovation_var: tuple[float, ...] = ()


def records_table(records: Sequence[UpdateRecord]) -> pd.DataFrame:
    """The measurement log as a table: ``t, name, dim, nis, accepted, reason`` and the
    tuples ``innovation, innovation_var`` (:class:`UpdateRecord`)."""
    return pd.DataFrame(
        {
            "t": np.array([r.t for r in records], dtype=float),
            "name": [r.name for r in records],
            "dim": np.array([r.dim for r in records], dtype=int),
            "nis": np.array([r.nis for r in records], dtype=float),
            "accepted": np.array([r.accepted for r in records], dtype=bool),
            "reason": [r.reason for r in records],
            "innovation": [r.innovation for r in records],
            "innovation_var": [r.innovation_var for r in records],
        }
    )
