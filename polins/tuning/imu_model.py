"""IMU error model from a static recording: per-axis Allan fits mapped to an ``ImuModel``.

What a static recording shows, and how each :class:`polins.models.ImuModel` field is set
(docs/imu-model.md explains the reasoning):

- white noise (ARW, VRW): the white term of the Allan fit pooled over the three axes
  (the root mean square of the axes' densities);
- bias random walk: the fitted random walk if the recording identifies it, else the upper
  end of its confidence interval (the largest one the data cannot exclude); a bias
  instability ``B`` the recording identifies is added in quadrature as the random walk whose
  Allan line touches the flicker floor ``0.664 B`` at the floor's averaging time
  ``tau_floor``, ``K_B = 0.664 B sqrt(3 / tau_floor)`` (conservative beyond ``tau_floor``);
- turn-on bias and scale factor: a static recording of one session cannot show their
  spread; they are given by the caller or taken from ``GRADE_TYPICAL``. The gyro turn-on
  bias is raised to the recording's own mean rates (RMS over segments and axes) when that
  is clearly above the Earth rate.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from polins.errors import UserInputError
from polins.models import IMU_PLAUSIBLE_RANGES, ImuModel, ModelFileError
from polins.tuning.allan import CI_LEVEL, FLICKER_FACTOR, AllanCurve, NoiseTerms, fit_allan

FloatArray = NDArray[np.float64]

GYRO_COLUMNS = ("gx", "gy", "gz")
ACCEL_COLUMNS = ("ax", "ay", "az")
EARTH_RATE = 7.292115e-5  # [rad/s] WGS-84
STANDARD_GRAVITY = 9.80665  # [m/s^2]
_DEG_PER_H = np.pi / 180.0 / 3600.0  # [rad/s] per [deg/h]
GAP_FACTOR = 1.5  # a time step over 1.5 sample periods is a gap: samples are missing
MIN_SEGMENT_SAMPLES = 64  # the shortest series an Allan deviation is computed for

# What a static recording cannot show, typical of each grade (SI): turn-on bias 1-sigma
# (gyro [rad/s], accel [m/s^2]) and scale-factor 1-sigma [-]; the values of the shipped
# fins-paper (navigation) and mems-typical (industrial MEMS) models.
GRADE_TYPICAL: dict[str, dict[str, float]] = {
    "navigation": {
        "gyro_bias": 0.02 * _DEG_PER_H,
        "gyro_scale_factor": 10e-6,
        "accel_bias": 0.02e-3 * STANDARD_GRAVITY,
        "accel_scale_factor": 20e-6,
    },
    "tactical": {
        "gyro_bias": 1.0 * _DEG_PER_H,
        "gyro_scale_factor": 150e-6,
        "accel_bias": 1e-3 * STANDARD_GRAVITY,
        "accel_scale_factor": 300e-6,
    },
    "mems": {
        "gyro_bias": 30.0 * _DEG_PER_H,
        "gyro_scale_factor": 1000e-6,
        "accel_bias": 2e-3 * STANDARD_GRAVITY,
        "accel_scale_factor": 1000e-6,
    },
}


@dataclass(frozen=True)
class SensorAllan:
    """Allan deviations and noise-term fits of one sensor triad (gyro or accelerometer).

    Attributes
    ----------
    sensor : str
        ``"gyro"`` (rate data [rad/s]) or ``"accel"`` (specific force [m/s^2]).
    axes : tuple of str
        The columns, e.g. ``("gx", "gy", "gz")``.
    curves, terms : tuple
        Per axis: :class:`AllanCurve` and its :class:`NoiseTerms`.
    combined_curve, combined : AllanCurve, NoiseTerms
        The three axes pooled (their Allan variances averaged) and its fit.
    mean : ndarray
        Mean of each axis over the recording [rad/s or m/s^2].
    """

    sensor: str
    axes: tuple[str, ...]
    curves: tuple[AllanCurve, ...]
    terms: tuple[NoiseTerms, ...]
    combined_curve: AllanCurve
    combined: NoiseTerms
    mean: FloatArray


@dataclass(frozen=True)
class AllanFit:
    """The Allan analysis of a static recording and how each IMU model number was obtained.

    Attributes
    ----------
    gyro, accel : SensorAllan
        Per-sensor curves and fits.
    sample_rate_hz : float
        Sample rate of the recording [Hz].
    duration_s : float
        Total static time analysed, summed over segments [s].
    n_segments : int
        Number of static segments (each analysed on its own, then pooled).
    notes : tuple of str
        One line per IMU model key: its value and how it was obtained (TOML comments).
    """

    gyro: SensorAllan
    accel: SensorAllan
    sample_rate_hz: float
    duration_s: float
    n_segments: int
    notes: tuple[str, ...]

    def comment_lines(self) -> list[str]:
        """Comment lines (without ``#``) recording the fit, for the head of an IMU TOML."""
        head = [
            f"IMU model from a static recording: {self.duration_s:.1f} s in "
            f"{self.n_segments} segment(s) at {self.sample_rate_hz:.6g} Hz; overlapping Allan",
            "deviation (allantools.oadev), weighted fit of N^2/tau + 0.441 B^2 + K^2 tau/3 "
            f"(IEEE Std 952); intervals {CI_LEVEL:.0%}.",
        ]
        return head + list(self.notes)


def model_random_walk(terms: NoiseTerms) -> tuple[float, str]:
    """The bias random walk an ``ImuModel`` should carry for fitted noise terms.

    Parameters
    ----------
    terms : NoiseTerms
        A fit (:func:`polins.tuning.fit_allan`).

    Returns
    -------
    value : float
        Random-walk density [unit/sqrt(s)]: the fitted ``K`` if identified, else its upper
        bound, combined in quadrature with ``0.664 B sqrt(3 / tau_floor)`` when the bias
        instability ``B`` is identified.
    how : str
        A short description of what was used.
    """
    ident = terms.identified
    k = terms.random_walk if ident["random_walk"] else terms.random_walk_ci[1]
    how = "fitted random walk" if ident["random_walk"] else "upper bound (not identified)"
    k_b = 0.0
    if ident["bias_instability"]:
        k_b = FLICKER_FACTOR * terms.bias_instability * np.sqrt(3.0 / terms.tau_floor)
        how += f" (+) bias instability as a random walk at tau {terms.tau_floor:.3g} s"
    return float(np.hypot(k, k_b)), how


def _segments(imu: pd.DataFrame | Sequence[pd.DataFrame]) -> list[pd.DataFrame]:
    frames = [imu] if isinstance(imu, pd.DataFrame) else list(imu)
    if not frames or not all(isinstance(f, pd.DataFrame) for f in frames):
        raise UserInputError("imu must be a DataFrame or a list of DataFrames (static segments)")
    need = ("t", *GYRO_COLUMNS, *ACCEL_COLUMNS)
    for f in frames:
        missing = [c for c in need if c not in f.columns]
        if missing:
            raise UserInputError(f"static IMU table lacks columns {missing}; expected {need}")
    return frames


def split_at_gaps(frame: pd.DataFrame) -> tuple[list[pd.DataFrame], list[tuple[float, float]]]:
    """Split a static table where samples are missing (a step over ``GAP_FACTOR`` periods).

    Parameters
    ----------
    frame : DataFrame
        A static IMU table with strictly increasing ``t`` [s].

    Returns
    -------
    pieces : list of DataFrame
        The uniformly sampled parts, in order.
    gaps : list of (float, float)
        Each gap's last sample before and first sample after [s].
    """
    t = frame["t"].to_numpy(dtype=float)
    dt = np.diff(t)
    if len(t) < 2 or not np.all(dt > 0):
        first = int(np.argmax(dt <= 0)) if len(t) >= 2 else 0
        raise UserInputError(
            f"static IMU times t must be strictly increasing (t = {t[first]:.6g} s is followed"
            f" by {t[min(first + 1, len(t) - 1)]:.6g} s)"
        )
    period = float(np.median(dt))
    cut = np.flatnonzero(dt > GAP_FACTOR * period)
    pieces = [frame.iloc[idx] for idx in np.split(np.arange(len(t)), cut + 1)]
    return pieces, [(float(t[k]), float(t[k + 1])) for k in cut]


def _rate(frames: list[pd.DataFrame], sample_rate_hz: float | None) -> float:
    if sample_rate_hz is not None:
        if not sample_rate_hz > 0:
            raise UserInputError(f"sample_rate_hz must be positive, got {sample_rate_hz}")
        return float(sample_rate_hz)
    rates = []
    for f in frames:
        t = f["t"].to_numpy(dtype=float)
        dt = np.diff(t)
        period = float(np.median(dt))
        bad = np.flatnonzero(np.abs(dt - period) > 0.01 * period)
        if len(bad):
            k = int(bad[0])
            raise UserInputError(
                f"static IMU samples are not uniformly spaced: the step from t = {t[k]:.6g} s "
                f"to {t[k + 1]:.6g} s is {dt[k]:.3g} s against a sample period of {period:.3g} s"
            )
        rates.append(1.0 / float(np.mean(dt)))
    if max(rates) > 1.001 * min(rates):
        raise UserInputError(f"static segments have different sample rates: {rates}")
    return float(np.mean(rates))


def _usable_segments(
    frames: list[pd.DataFrame],
) -> tuple[list[pd.DataFrame], list[str]]:
    """The segments split at their gaps, those too short for an Allan deviation dropped."""
    pieces, notes = [], []
    for f in frames:
        parts, gaps = split_at_gaps(f)
        if gaps:
            where = ", ".join(f"{a:.6g} -> {b:.6g} s" for a, b in gaps[:5])
            more = f" and {len(gaps) - 5} more" if len(gaps) > 5 else ""
            notes.append(f"split at {len(gaps)} gap(s) in the samples: {where}{more}")
        pieces += parts
    short = [p for p in pieces if len(p) < MIN_SEGMENT_SAMPLES]
    kept = [p for p in pieces if len(p) >= MIN_SEGMENT_SAMPLES]
    if short:
        notes.append(
            f"{len(short)} piece(s) shorter than {MIN_SEGMENT_SAMPLES} samples left out "
            f"({sum(len(p) for p in short)} samples)"
        )
    if not kept:
        raise UserInputError(
            f"no static segment has {MIN_SEGMENT_SAMPLES} samples: the longest holds "
            f"{max(len(p) for p in pieces)}; record longer (record_length_needed says how long)"
        )
    return kept, notes


def grade_random_walk(grade: str, sensor: str) -> float:
    """A mid-range bias random walk of a grade [SI]: the geometric mean of its plausible range.

    Gyro [rad/s/sqrt(s)], accelerometer [m/s^2/sqrt(s)] (``IMU_PLAUSIBLE_RANGES``).
    """
    key, scale = {
        "gyro": ("gyro.bias_rw_deg_per_h_per_sqrt_h", _DEG_PER_H / 60.0),
        "accel": ("accel.bias_rw_mg_per_sqrt_h", 1e-3 * STANDARD_GRAVITY / 60.0),
    }[sensor]
    lo, hi = IMU_PLAUSIBLE_RANGES[grade][key]
    return float(np.sqrt(lo * hi)) * scale


def record_length_needed(white: float, random_walk: float) -> float:
    """Record length that identifies a bias random walk [s]: ten crossover times.

    The white line ``N / sqrt(tau)`` and the random-walk line ``K sqrt(tau / 3)`` of the
    Allan deviation cross at ``tau_c = sqrt(3) N / K``; the Allan deviation reaches a
    quarter of the record and the random walk dominates from a few ``tau_c`` on, so the
    record needs about ``10 tau_c`` (docs/imu-model.md §2).

    Parameters
    ----------
    white : float
        White-noise density ``N`` [unit sqrt(s)].
    random_walk : float
        Random-walk density ``K`` [unit/sqrt(s)].
    """
    return float(10.0 * np.sqrt(3.0) * white / random_walk) if random_walk > 0 else np.inf


def _length_notes(
    gyro: SensorAllan, accel: SensorAllan, grade: str, longest_s: float
) -> tuple[list[str], list[str]]:
    """Per sensor, whether the record identifies its random walk and how long it would need.

    Returns the notes and the problems (a random-walk bound above the grade's range).
    """
    notes, problems = [], []
    keys = {"gyro": ("gyro.bias_rw_deg_per_h_per_sqrt_h", 1.0 / _DEG_PER_H * 60.0, "deg/h/sqrt(h)"),
            "accel": ("accel.bias_rw_mg_per_sqrt_h", 60.0 / (1e-3 * STANDARD_GRAVITY), "mg/sqrt(h)")}  # fmt: skip
    for sensor in (gyro, accel):
        c = sensor.combined
        key, scale, unit = keys[sensor.sensor]
        k_typ = grade_random_walk(grade, sensor.sensor)
        need = record_length_needed(c.white, k_typ)
        if c.identified["random_walk"]:
            notes.append(f"{sensor.sensor} random walk identified by the {longest_s:.0f} s segment")
            continue
        notes.append(
            f"{sensor.sensor} random walk not identified (an upper bound): a mid-range {grade} "
            f"value, {k_typ * scale:.3g} {unit}, shows in a segment of about {need:.0f} s "
            f"({need / 3600:.2g} h, 10 crossover times); the longest here is {longest_s:.1f} s"
        )
        bound, _ = model_random_walk(c)
        hi = IMU_PLAUSIBLE_RANGES[grade][key][1]
        if bound * scale > hi:
            problems.append(
                f"the static record is too short to bound the {sensor.sensor} random walk: its "
                f"longest segment, {longest_s:.1f} s, gives only {key} <= {bound * scale:.4g}, "
                f"above the {grade} range's {hi:g}; record at least {need:.0f} s ({need / 3600:.2g} h) at "
                "rest to identify it"
            )
    return notes, problems


def _white_plausible(gyro: SensorAllan, accel: SensorAllan, grade: str) -> bool:
    """Whether the white-noise densities lie in the grade's plausible ranges."""
    ranges = IMU_PLAUSIBLE_RANGES[grade]
    values = {
        "gyro.arw_deg_per_sqrt_h": float(np.degrees(gyro.combined.white)) * 60.0,
        "accel.vrw_m_per_s_per_sqrt_h": accel.combined.white * 60.0,
    }
    return all(ranges[k][0] <= v <= ranges[k][1] for k, v in values.items())


def _check_units(frames: list[pd.DataFrame]) -> None:
    gyro = np.concatenate([f[list(GYRO_COLUMNS)].to_numpy(dtype=float) for f in frames])
    accel = np.concatenate([f[list(ACCEL_COLUMNS)].to_numpy(dtype=float) for f in frames])
    if np.max(np.abs(gyro.mean(axis=0))) > 1.0:
        raise UserInputError(
            "a gyro axis averages more than 1 rad/s over the static recording: gyro in "
            "deg/s? convert to rad/s (or the IMU was not at rest)"
        )
    g = float(np.linalg.norm(accel.mean(axis=0)))
    if not 8.0 <= g <= 12.0:
        raise UserInputError(
            f"the accelerometer at rest reads {g:.4g}, not about 9.81 m/s^2: accelerometer in"
            " g? convert to m/s^2 (or the IMU was not at rest)"
        )


def _sensor(
    frames: list[pd.DataFrame], sensor: str, cols: tuple[str, ...], rate: float, ppd: int
) -> SensorAllan:
    per_axis = [[f[c].to_numpy(dtype=float) for f in frames] for c in cols]
    fits = [fit_allan(series, rate, points_per_decade=ppd) for series in per_axis]
    pooled = [s for series in per_axis for s in series]
    combined_curve, combined = fit_allan(pooled, rate, points_per_decade=ppd)
    mean = np.concatenate([f[list(cols)].to_numpy(dtype=float) for f in frames]).mean(axis=0)
    return SensorAllan(
        sensor=sensor,
        axes=cols,
        curves=tuple(c for c, _ in fits),
        terms=tuple(t for _, t in fits),
        combined_curve=combined_curve,
        combined=combined,
        mean=mean,
    )


def _noise_notes(gyro: SensorAllan, accel: SensorAllan) -> tuple[float, float, list[str]]:
    """The model's bias random walks [SI] and a note per noise key, in the TOML's units."""
    notes: list[str] = []
    sqrt_h, deg, deg_h = 60.0, float(np.degrees(1.0)), 1.0 / _DEG_PER_H
    mg = 1.0 / (1e-3 * STANDARD_GRAVITY)
    g_rw, g_rw_how = model_random_walk(gyro.combined)
    a_rw, a_rw_how = model_random_walk(accel.combined)
    pooled = "white noise of the three axes pooled"
    rows = [
        ("gyro.arw_deg_per_sqrt_h", gyro, "white", gyro.combined.white, pooled, deg * sqrt_h),
        ("accel.vrw_m_per_s_per_sqrt_h", accel, "white", accel.combined.white, pooled, sqrt_h),
        ("gyro.bias_rw_deg_per_h_per_sqrt_h", gyro, "random_walk", g_rw, g_rw_how, deg_h * sqrt_h),
        ("accel.bias_rw_mg_per_sqrt_h", accel, "random_walk", a_rw, a_rw_how, mg * sqrt_h),
    ]
    for key, sensor, attr, value, how, scale in rows:
        lo, hi = getattr(sensor.combined, f"{attr}_ci")
        axes = ", ".join(f"{getattr(t, attr) * scale:.3g}" for t in sensor.terms)
        notes.append(
            f"{key} = {value * scale:.4g}: {how}; fitted {lo * scale:.3g} to {hi * scale:.3g}"
            f" ({CI_LEVEL:.0%}); per axis x, y, z: {axes}"
        )
    for sensor, unit, scale in [(gyro, "deg/h", deg_h), (accel, "mg", mg)]:
        c = sensor.combined
        notes.append(
            f"{sensor.sensor} bias instability (not a model key) = {c.bias_instability * scale:.3g}"
            f" {unit}, CI {c.bias_instability_ci[0] * scale:.3g} to "
            f"{c.bias_instability_ci[1] * scale:.3g}; Allan floor at tau {c.tau_floor:.3g} s"
        )

    return g_rw, a_rw, notes


def imu_model_from_static(
    imu: pd.DataFrame | Sequence[pd.DataFrame],
    *,
    sample_rate_hz: float | None = None,
    name: str = "static-fit",
    grade: str = "mems",
    description: str | None = None,
    gyro_bias: float | None = None,
    accel_bias: float | None = None,
    gyro_scale_factor: float | None = None,
    accel_scale_factor: float | None = None,
    source: str | Path | None = None,
    points_per_decade: int = 5,
) -> tuple[ImuModel, AllanFit]:
    """Build an IMU error model from a static recording (Allan deviation, IEEE Std 952).

    Parameters
    ----------
    imu : DataFrame or sequence of DataFrame
        Columns ``t`` [s], ``gx, gy, gz`` [rad/s], ``ax, ay, az`` [m/s^2] of an IMU at rest,
        uniformly sampled. Several static segments (e.g. the rests before and after a
        trial, or several files) are analysed one by one and their Allan variances pooled;
        no jump between them enters. A table with missing samples is split at its gaps
        (:func:`split_at_gaps`; the notes say where), pieces under
        ``MIN_SEGMENT_SAMPLES`` are left out. Longer is better: the bias random walk shows
        only in a segment of about ten crossover times (:func:`record_length_needed`).
    sample_rate_hz : float, optional
        Sample rate [Hz]; by default from ``t``.
    name, description : str
        The model's name and description.
    grade : str
        ``"navigation"``, ``"tactical"`` or ``"mems"``: selects ``GRADE_TYPICAL`` and the
        plausible ranges the result is checked against.
    gyro_bias, accel_bias : float, optional
        Turn-on bias 1-sigma [rad/s], [m/s^2] between sessions (a datasheet's or from
        several recordings); default ``GRADE_TYPICAL``, the gyro's raised to the RMS over
        segments and axes of the segments' mean rates if that exceeds 10 Earth rates
        (then it is a sensor bias, not the Earth rate).
    gyro_scale_factor, accel_scale_factor : float, optional
        Scale-factor 1-sigma [-]; default ``GRADE_TYPICAL``.
    source : str or Path, optional
        Where the recording came from (the model's ``path``).
    points_per_decade : int
        Density of the averaging times.

    Returns
    -------
    model : ImuModel
        SI units; ``model.toml_values()`` gives the TOML's.
    fit : AllanFit
        Curves, fits with confidence intervals, and a note per model key.

    Raises
    ------
    UserInputError
        Missing columns, non-uniform or non-finite samples, units that are not rad/s and
        m/s^2, an unknown grade, a record too short to bound a random walk within the
        grade's range (the message says how long a record is needed), or a fitted value
        implausible for the grade.
    """
    if grade not in GRADE_TYPICAL:
        raise UserInputError(f"grade must be one of {sorted(GRADE_TYPICAL)}, got {grade!r}")
    frames, split_notes = _usable_segments(_segments(imu))
    rate = _rate(frames, sample_rate_hz)
    _check_units(frames)
    gyro = _sensor(frames, "gyro", GYRO_COLUMNS, rate, points_per_decade)
    accel = _sensor(frames, "accel", ACCEL_COLUMNS, rate, points_per_decade)
    typical = GRADE_TYPICAL[grade]
    g_rw, a_rw, notes = _noise_notes(gyro, accel)
    longest_s = max(len(f) for f in frames) / rate
    length_notes, too_short = _length_notes(gyro, accel, grade, longest_s)
    if too_short and _white_plausible(gyro, accel, grade):  # else units or grade: below
        raise UserInputError(too_short[0])
    deg_h, mg = 1.0 / _DEG_PER_H, 1.0 / (1e-3 * STANDARD_GRAVITY)

    seg_means = [f[list(GYRO_COLUMNS)].to_numpy(dtype=float).mean(axis=0) for f in frames]
    measured_bias = float(np.sqrt(np.mean(np.square(seg_means))))  # RMS over segments, axes
    if gyro_bias is None:
        gyro_bias = typical["gyro_bias"]
        how = f"grade-typical ({grade}), not measured"
        if measured_bias > 10.0 * EARTH_RATE and measured_bias > gyro_bias:
            gyro_bias, how = measured_bias, "RMS of the segments' mean rates (measured)"
    else:
        how = "given"
    notes.append(f"gyro.bias_deg_per_h = {gyro_bias * deg_h:.4g}: {how}")
    given = {
        "accel_bias": accel_bias,
        "gyro_scale_factor": gyro_scale_factor,
        "accel_scale_factor": accel_scale_factor,
    }
    values = {k: (typical[k] if v is None else float(v)) for k, v in given.items()}
    for k, key, scale in [
        ("accel_bias", "accel.bias_mg", mg),
        ("gyro_scale_factor", "gyro.scale_factor_ppm", 1e6),
        ("accel_scale_factor", "accel.scale_factor_ppm", 1e6),
    ]:
        how = "given" if given[k] is not None else f"grade-typical ({grade}), not measured"
        notes.append(f"{key} = {values[k] * scale:.4g}: {how}")

    n_total = sum(len(f) for f in frames)
    model = ImuModel(
        name=name,
        description=description
        or f"{grade} IMU fitted to a {n_total / rate:.0f} s static recording (Allan deviation)",
        path=Path(source) if source is not None else Path("<static recording>"),
        grade=grade,
        sample_rate_hz=rate,
        gyro_arw=gyro.combined.white,
        gyro_bias=float(gyro_bias),
        gyro_bias_rw=g_rw,
        gyro_scale_factor=values["gyro_scale_factor"],
        accel_vrw=accel.combined.white,
        accel_bias=values["accel_bias"],
        accel_bias_rw=a_rw,
        accel_scale_factor=values["accel_scale_factor"],
    )
    try:
        model.check_plausible()
    except ModelFileError as exc:
        raise UserInputError(
            f"the static fit gives an implausible model: {exc}; is the recording static, in "
            "rad/s and m/s^2, and the grade right?"
        ) from None
    fit = AllanFit(
        gyro=gyro,
        accel=accel,
        sample_rate_hz=rate,
        duration_s=n_total / rate,
        n_segments=len(frames),
        notes=tuple(notes + split_notes + length_notes),
    )
    return model, fit


__all__ = [
    "GAP_FACTOR",
    "GRADE_TYPICAL",
    "AllanFit",
    "SensorAllan",
    "grade_random_walk",
    "imu_model_from_static",
    "model_random_walk",
    "record_length_needed",
    "split_at_gaps",
]
