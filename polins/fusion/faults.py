"""The fault policy of the fusion's inputs: which IMU samples, images and measurements are used, what an IMU gap does, which unit mistakes stop a run.

One policy for every path (``polins.fuse``, ``polins fuse``, ``NavigationStream``),
written down in docs/faults.md:

* :class:`EventKind`: the one vocabulary of the data faults and recoveries (the ``kind`` of
  every event table).
* :class:`ImuScreen`: which IMU samples join the filter (non-finite, not after the previous
  one, beyond the IMU model's full scale: dropped) and where the IMU gaps are.
* :func:`gap_item`, :func:`skip_in_gaps`, :func:`gap_variance`: an IMU gap longer than
  ``max_gap_s`` is propagated across with the covariance grown by the motion that may have
  been missed, and the measurements (images) strictly inside it are skipped.
* :func:`check_imu_units` and :class:`GyroHeadingCheck`: a gyro in deg/s or a specific
  force in g / mg raises :class:`ImuUnitsError`.
* :func:`nis_verdict`: a run whose NIS is far outside any plausible band is not a result.
"""

from __future__ import annotations

import dataclasses
import math
import re
from bisect import bisect_left
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from polins.errors import UserInputError
from polins.fusion.items import MeasurementItem

FloatArray = NDArray[np.float64]


class EventKind(StrEnum):
    """The kinds of data faults and recoveries (docs/faults.md, "Events")."""

    IMU_NONFINITE = "imu-nonfinite"
    IMU_OUT_OF_ORDER = "imu-out-of-order"
    IMU_OUT_OF_RANGE = "imu-out-of-range"
    IMU_GAP = "imu-gap"
    MEASUREMENT_IN_GAP = "measurement-in-gap"
    YAW_REACQUIRED = "yaw-reacquired"
    IMAGE_OUT_OF_ORDER = "image-out-of-order"
    IMAGE_LATE = "image-late"
    IMAGE_OUTSIDE_IMU = "image-outside-imu"
    IMAGE_DURING_ALIGNMENT = "image-during-alignment"
    IMAGE_UNREADABLE = "image-unreadable"
    IMAGE_ERROR = "image-error"
    PATH_OUTSIDE_LOG = "path-outside-log"
    NOISE_MODEL = "noise-model"


@dataclass(frozen=True)
class FusionEvent:
    """One data fault or recovery: time [s], an :class:`EventKind` value, a text."""

    t: float
    kind: str
    detail: str

    def __post_init__(self) -> None:
        object.__setattr__(self, "kind", EventKind(self.kind).value)  # an unknown kind raises


class ImuUnitsError(UserInputError):
    """The IMU data are in other units than declared (a gyro in deg/s, a specific force in
    g or mg); one line naming the fix."""


# Plausibility limit of the accelerometer unit check (the gyro's: the IMU model's full scale)
ACCEL_MEDIAN_RANGE = (6.0, 14.0)  # median |f| [m/s^2] of data near the Earth's surface
DEG_PER_RAD = 180.0 / math.pi
# A run's median NIS per degree of freedom beyond this many times the upper edge of its
# band is not a result (nis_verdict)
IMPLAUSIBLE_FACTOR = 100.0


def default_max_gap_s(max_gap_s: float | None, dt: float) -> float:
    """The gap length [s] of a run: ``max_gap_s``, or 5 nominal sample intervals ``dt``."""
    return 5.0 * dt if max_gap_s is None else float(max_gap_s)


@dataclass
class ImuScreen:
    """Which IMU samples join the filter, block by block (a table is one block).

    A sample is dropped with an event when a value is NaN/inf (``imu-nonfinite``), when it
    is not after the previous accepted sample (``imu-out-of-order``), or when its rate or
    specific force is beyond the full scale (``imu-out-of-range``). An accepted sample more
    than ``max_gap_s`` after the previous one closes an IMU gap (``imu-gap``: see
    :func:`gap_item`).

    Parameters
    ----------
    full_scale : (float, float)
        Gyro [rad/s] and accelerometer [m/s^2] full scale (``ImuModel.full_scale()``).
    max_gap_s : float
        Longer intervals between accepted samples are gaps [s].
    """

    full_scale: tuple[float, float]
    max_gap_s: float
    t_latest: float = -math.inf  # newest accepted time [s]
    n: int = 0  # accepted samples
    gaps: list[tuple[float, float]] = field(default_factory=list)  # (t_a, t_b) of each gap

    def screen(
        self, t: FloatArray, gyro_b: FloatArray, accel_b: FloatArray
    ) -> tuple[NDArray[np.bool_], list[FusionEvent], NDArray[np.int_]]:
        """The samples ``t`` (N,) [s], ``gyro_b``, ``accel_b`` (N, 3) screened in order.

        Returns
        -------
        keep : (N,) bool ndarray
        events : list of FusionEvent
            The dropped samples (the gaps: :func:`gap_item`).
        gap_ends : int ndarray
            Indices of the accepted samples that close a gap (their predecessor: the
            previous accepted sample).
        """
        gyro_max, accel_max = self.full_scale
        with np.errstate(invalid="ignore", over="ignore"):
            w = np.linalg.norm(gyro_b, axis=1)
            f = np.linalg.norm(accel_b, axis=1)
        finite = np.isfinite(t) & np.isfinite(gyro_b).all(axis=1) & np.isfinite(accel_b).all(axis=1)
        in_range = finite & (w <= gyro_max) & (f <= accel_max)
        prev = np.maximum.accumulate(
            np.concatenate([[self.t_latest], np.where(finite, t, -np.inf)])
        )
        ordered = finite & (t > prev[:-1])
        keep = ordered & in_range
        events = []
        for i in np.flatnonzero(~keep).tolist():
            events.append(self._drop_event(float(t[i]), bool(finite[i]), bool(ordered[i]),
                                           prev[i], float(w[i]), float(f[i])))  # fmt: skip
        t_kept = np.concatenate([[self.t_latest], t[keep]])
        closes = np.flatnonzero(np.diff(t_kept) > self.max_gap_s)
        if self.n == 0:
            closes = closes[closes > 0]
        gap_ends = np.flatnonzero(keep)[closes]
        self.gaps += [(float(t_kept[i]), float(t_kept[i + 1])) for i in closes.tolist()]
        if keep.any():
            self.t_latest = float(t_kept[-1])
            self.n += int(keep.sum())
        return keep, events, gap_ends

    def _drop_event(
        self, t: float, finite: bool, ordered: bool, t_prev: float, w: float, f: float
    ) -> FusionEvent:
        if not finite:
            return FusionEvent(t, EventKind.IMU_NONFINITE, "IMU sample with NaN/inf dropped")
        if not ordered:
            what = "duplicated" if t == t_prev else "out-of-order"
            return FusionEvent(t, EventKind.IMU_OUT_OF_ORDER,
                               f"{what} IMU sample dropped (previous t={t_prev!r})")  # fmt: skip
        gyro_max, accel_max = self.full_scale
        return FusionEvent(t, EventKind.IMU_OUT_OF_RANGE,
                           f"IMU sample beyond the full scale dropped: |w| = {w:.3g} rad/s "
                           f"(limit {gyro_max:.3g}), |f| = {f:.3g} m/s^2 (limit {accel_max:.3g})")  # fmt: skip

    def inside_gap(self, t: float) -> tuple[float, float] | None:
        """The gap ``(t_a, t_b)`` with ``t_a < t < t_b``, if any."""
        for t_a, t_b in self.gaps:
            if t_a < t < t_b:
                return t_a, t_b
        return None


def gap_variance(
    gap_s: float,
    gyro_b: tuple[FloatArray, FloatArray],
    accel_b: tuple[FloatArray, FloatArray],
) -> FloatArray:
    """Variances added to the navigation error state over an IMU gap (9: attitude [rad^2],
    velocity [m^2/s^2], position [m^2]).

    The rates inside the gap are interpolated linearly between its end samples; the
    motion that misses is taken of the size of the motion seen at the ends: a rotation of
    ``gap_s * max |w|`` about each axis, a velocity change of ``gap_s * |f_b - f_a|`` and
    half of that times ``gap_s`` in position (1-sigma each).
    """
    rate = max(float(np.linalg.norm(gyro_b[0])), float(np.linalg.norm(gyro_b[1])))
    force = float(np.linalg.norm(accel_b[1] - accel_b[0]))
    att, vel = gap_s * rate, gap_s * force
    return np.repeat(np.array([att, vel, 0.5 * vel * gap_s]) ** 2, 3)


def gap_item(
    t_a: float,
    t_b: float,
    gyro_b: tuple[FloatArray, FloatArray],
    accel_b: tuple[FloatArray, FloatArray],
) -> tuple[MeasurementItem, FusionEvent]:
    """The ``"gap"`` item at ``t_b`` (the ESKF adds its :func:`gap_variance` to the
    covariance; the graph the same variance to the gap's preintegration noise) and the
    ``imu-gap`` event of a gap from the sample at ``t_a`` to the one at ``t_b``."""
    inflation = gap_variance(t_b - t_a, gyro_b, accel_b)
    detail = (
        f"IMU gap of {t_b - t_a:.3g} s until t={t_b:.6g}: propagated across, uncertainty "
        "grown by the motion it may hide"
    )
    item = MeasurementItem(t_b, "gap", t_b - t_a, inflation=inflation)
    return item, FusionEvent(t_a, EventKind.IMU_GAP, detail)


def gap_reason(t_a: float, t_b: float) -> str:
    """The reason of a measurement skipped inside the gap ``t_a .. t_b`` [s]."""
    return f"inside an IMU gap ({t_a:.6g} to {t_b:.6g} s)"


def skip_in_gaps(
    gaps: Sequence[tuple[float, float]], items: list[MeasurementItem]
) -> tuple[list[MeasurementItem], list[FusionEvent]]:
    """The items with those strictly inside an IMU gap made invalid, an event for each.

    Parameters
    ----------
    gaps : sequence of (t_a, t_b)
        The gaps [s] (:attr:`ImuScreen.gaps`).
    items : list of MeasurementItem

    Returns
    -------
    items : list of MeasurementItem
        In the input order; those inside a gap invalid with the reason :func:`gap_reason`.
    events : list of FusionEvent
        A ``measurement-in-gap`` event for each item made invalid.
    """
    out = list(items)
    events: list[FusionEvent] = []
    if not gaps or not out:
        return out, events
    starts = np.array([g[0] for g in gaps])
    for k, it in enumerate(out):
        j = int(np.searchsorted(starts, it.t, side="left")) - 1
        if j < 0 or not it.t < gaps[j][1] or not it.valid:
            continue
        reason = gap_reason(*gaps[j])
        out[k] = dataclasses.replace(it, valid=False, reason=reason)
        events.append(
            FusionEvent(it.t, EventKind.MEASUREMENT_IN_GAP, f"{it.kind} skipped: {reason}")
        )
    return out, events


def check_imu_units(gyro_norm: ArrayLike, accel_norm: ArrayLike, gyro_max: float) -> None:
    """Raise :class:`ImuUnitsError` if IMU samples look like the wrong units.

    Parameters
    ----------
    gyro_norm, accel_norm : (N,) array_like
        |gyro| [rad/s] and |specific force| [m/s^2] of finite samples.
    gyro_max : float
        The gyro's full scale [rad/s]: more than 1 % of the samples beyond it is deg/s data.
    """
    w = np.asarray(gyro_norm, dtype=float)
    f = np.asarray(accel_norm, dtype=float)
    if w.size and np.percentile(w, 99) > gyro_max:
        raise ImuUnitsError(
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
        raise ImuUnitsError(
            f"imu: median specific force |f| = {f_med:.4g} is not ~9.8 m/s^2 (expected "
            f"{lo}-{hi} m/s^2 near the Earth's surface).{hint}"
        )


class UnitsWindow:
    """The unit check of a live IMU stream: :func:`check_imu_units` once, over the samples of
    its first ``window_s`` (the levelling window; a table is checked whole)."""

    def __init__(self, window_s: float, gyro_max: float) -> None:
        self.window_s = window_s
        self.gyro_max = gyro_max
        self.t_first = math.nan
        self._norms: list[FloatArray] | None = []  # (n, 2): |w|, |f| of the window so far

    def add(self, t: FloatArray, gyro_b: FloatArray, accel_b: FloatArray) -> None:
        """Accepted samples [s, rad/s, m/s^2]; raises :class:`ImuUnitsError` at the end of
        the window if they look like other units."""
        if self._norms is None or len(t) == 0:
            return
        if math.isnan(self.t_first):
            self.t_first = float(t[0])
        inside = t <= self.t_first + self.window_s
        norms = np.column_stack([np.linalg.norm(gyro_b[inside], axis=1),
                                 np.linalg.norm(accel_b[inside], axis=1)])  # fmt: skip
        self._norms.append(norms)
        if not inside.all():
            window = np.concatenate(self._norms)
            self._norms = None
            check_imu_units(window[:, 0], window[:, 1], self.gyro_max)


class GyroHeadingCheck:
    """Whether the gyro turns ~57x as much as the measured headings (a deg/s gyro).

    An undeclared deg/s gyro below the full scale (slow turns) passes
    :func:`check_imu_units`; while the vehicle turns, the headings show it. A heading is a
    yaw [rad], or better the negated azimuth of the sun in the body frame
    (``-sun_azimuth_b``: measured from the image alone, while a measured yaw depends on the
    attitude prior, which a deg/s gyro ruins in the camera loop). Each heading at ``t_i`` is
    paired with the first heading at or after ``t_i + window_s``; the gyro's rotation about
    the specific force (the vertical at low dynamics), ``int w_b . f_b/|f_b| dt``, over the
    pair is compared with the headings' change, taken modulo pi (a 180 deg branch flip of
    the sun's azimuth is no turn). Pairs turning less than 3 deg are not used. Once ``n_windows`` pairs turn, the check
    decides: a median ratio within a factor 2 of 180/pi raises :class:`ImuUnitsError`;
    any other ratio ends the check (:attr:`decided`). IMU samples and headings may come
    in blocks (a table) or one by one (a stream), the IMU ahead of the headings.
    """

    def __init__(self, window_s: float = 1.0, n_windows: int = 5, keep_s: float = 60.0) -> None:
        """``keep_s`` [s]: the IMU history kept while no heading waits for a partner (inf
        for a table, whose headings come after all its samples)."""
        self.window_s = window_s
        self.n_windows = n_windows
        self.keep_s = keep_s
        self.decided = False
        self._t: list[float] = []  # IMU times [s]
        self._angle: list[float] = []  # gyro rotation about the vertical since the start [rad]
        self._heads: list[tuple[float, float]] = []  # unpaired headings (t, heading)
        self._ratios: list[float] = []
        self._rate_last = 0.0

    def add_imu(self, t: FloatArray, gyro_b: FloatArray, accel_b: FloatArray) -> None:
        """IMU samples (accepted by :class:`ImuScreen`, in time order) [s, rad/s, m/s^2]."""
        if self.decided or len(t) == 0:
            return
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            rate_up = np.einsum("ij,ij->i", gyro_b, accel_b) / np.linalg.norm(accel_b, axis=1)
        rate_up = np.where(np.isfinite(rate_up), rate_up, 0.0)
        if self._t:  # continue from the last sample
            t_all = np.concatenate([[self._t[-1]], t])
            r_all = np.concatenate([[self._rate_last], rate_up])
            angle = self._angle[-1] + np.cumsum(0.5 * (r_all[1:] + r_all[:-1]) * np.diff(t_all))
        else:
            steps = 0.5 * (rate_up[1:] + rate_up[:-1]) * np.diff(t)
            angle = np.concatenate([[0.0], np.cumsum(steps)])
        self._t += np.asarray(t, dtype=float).tolist()
        self._angle += angle.tolist()
        self._rate_last = float(rate_up[-1])
        self._trim()

    def add_headings(self, t: ArrayLike, yaw: ArrayLike) -> None:
        """Measured headings [rad] at ``t`` [s] (class docstring), in time order; non-finite
        ones are ignored. Raises :class:`ImuUnitsError` when the check decides deg/s."""
        for t_i, y_i in zip(np.atleast_1d(t).tolist(), np.atleast_1d(yaw).tolist(), strict=True):
            if self.decided:
                return
            if not (math.isfinite(t_i) and math.isfinite(y_i)):
                continue
            while self._heads and t_i >= self._heads[0][0] + self.window_s:
                self._pair(self._heads.pop(0), (t_i, y_i))
            self._heads.append((t_i, y_i))
        self._decide()

    def _pair(self, a: tuple[float, float], b: tuple[float, float]) -> None:
        turn_m = math.remainder(b[1] - a[1], math.pi)
        if abs(turn_m) <= math.radians(3.0) or not self._t:
            return
        if a[0] < self._t[0] or b[0] > self._t[-1]:
            return
        turn_g = self._angle_at(b[0]) - self._angle_at(a[0])
        self._ratios.append(turn_g / turn_m)

    def _angle_at(self, t: float) -> float:
        """The gyro's turn at ``t`` [rad], interpolated between the two samples around it
        (the lists are not converted whole: a log's headings would cost its length each)."""
        if len(self._t) < 2:
            return float(self._angle[0])
        k = min(max(bisect_left(self._t, t), 1), len(self._t) - 1)
        return float(np.interp(t, self._t[k - 1 : k + 1], self._angle[k - 1 : k + 1]))

    def _decide(self) -> None:
        if len(self._ratios) < self.n_windows:
            return
        ratio = float(np.median(self._ratios))
        self.decided = True
        self._t, self._angle, self._heads = [], [], []
        if 0.5 * DEG_PER_RAD <= ratio <= 2.0 * DEG_PER_RAD:
            raise ImuUnitsError(
                f"imu: the gyro turns {ratio:.3g} times as much as the measured headings over "
                f"{len(self._ratios)} turning windows: the gyro looks like deg/s; multiply by "
                'pi/180 (or declare it: [units] gyro = "deg/s")'
            )

    def _trim(self) -> None:
        t_keep = (self._heads[0][0] if self._heads else self._t[-1] - self.keep_s) - 1.0
        k = bisect_left(self._t, t_keep)
        if k > 1000:
            del self._t[:k], self._angle[:k]


def nis_verdict(nis: ArrayLike, dof: ArrayLike) -> str | None:
    """One line when the normalized innovations are far outside any plausible band, else None.

    The median of ``NIS / dof`` over the measurements with a finite NIS (accepted or gated)
    is compared with ``IMPLAUSIBLE_FACTOR`` = 100 times the upper edge of the 95 % band of the mean NIS
    per degree of freedom, ``1 + 1.96 sqrt(2 / sum(dof))`` (a consistent filter's median is
    below 1: 0.45 for one degree of freedom). The median ignores a few outliers. A filter
    whose model does not fit the data is far above (a gyro in deg/s: 4408); a mis-tuned
    one is not (headings whose sigma is 4 times too small: 17), and tuning it needs the
    run (docs/faults.md, "Implausible runs").
    """
    nis_a = np.asarray(nis, dtype=float)
    dof_a = np.asarray(dof, dtype=float)
    ok = np.isfinite(nis_a) & np.isfinite(dof_a) & (dof_a > 0)
    if ok.sum() < 10:
        return None
    upper = 1.0 + 1.96 * math.sqrt(2.0 / float(dof_a[ok].sum()))
    median = float(np.median(nis_a[ok] / dof_a[ok]))
    if median <= IMPLAUSIBLE_FACTOR * upper:
        return None
    return (
        f"implausible run: the median NIS per degree of freedom is {median:.4g} over "
        f"{int(ok.sum())} measurements, more than {IMPLAUSIBLE_FACTOR:g} times the band's upper edge "
        f"{upper:.3g}; likely causes: IMU units (a gyro in deg/s?), the time base of the "
        "images against the IMU, the IMU model (noise far too small), the camera file"
    )


def reason_group(reason: str) -> str:
    """The group of a rejection reason, for counting: the text before its first colon
    (``"unreadable image: <path> ..."`` -> ``"unreadable image"``, ``"NIS above the gate:
    ..."``), with the numbers of what is left replaced by ``#`` (``"too few valid pixels (#
    < #)"``). The full reason stays in the tables."""
    head = reason.split(":", 1)[0].strip()
    return re.sub(r"\d+(\.\d+)?(e[-+]?\d+)?", "#", head) or reason


class ImplausibleRunError(RuntimeError):
    """A run whose NIS is far outside any plausible band (:func:`nis_verdict`); ``result``
    holds what the run produced, for diagnosis."""

    def __init__(self, message: str, result: Any = None) -> None:
        super().__init__(message)
        self.result = result


__all__ = [
    "ACCEL_MEDIAN_RANGE",
    "EventKind",
    "FusionEvent",
    "GyroHeadingCheck",
    "ImplausibleRunError",
    "ImuScreen",
    "ImuUnitsError",
    "UnitsWindow",
    "check_imu_units",
    "default_max_gap_s",
    "gap_item",
    "gap_reason",
    "gap_variance",
    "nis_verdict",
    "reason_group",
    "skip_in_gaps",
]
