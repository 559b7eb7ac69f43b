"""Ground-vehicle aiding: standstill detection, the vehicle's mounting and lever arm, odometer items.

The vehicle kind (``FuseConfig.vehicle``, docs/filter.md "Ground-vehicle aiding") decides
the pseudo-measurements the IMU samples bring with them, at the non-holonomic cadence
(every ``round(1 / (NHC_RATE_HZ dt))``-th sample, sample index >= 1):

* ``"ground"``: the non-holonomic constraint (``nhc_std``, default 0.05 m/s) and a
  zero-velocity update where the standstill detector fires (``standstill_std``, default
  0.02 m/s);
* ``"static"``: a zero-velocity update at every epoch;
* ``"free"``: none (unless ``nhc_std`` / ``standstill_std`` are given).

Known standstill times are zero-velocity rows of the measurements table (a ``zupt_std``
column, :func:`with_standstill`): the one way to ask for zero velocity at given times.

The standstill detector (:func:`standstill_statistic`) tests, over a trailing window of
``n`` samples (``STANDSTILL_WINDOW_S``), the hypothesis "at rest": the gyro measures only
white noise (plus its turn-on bias and the Earth rate) and the specific force is constant
plus white noise. Its statistic ::

    T = sum_k |omega_k|^2 / s_w^2 + sum_k |f_k - mean(f)|^2 / s_f^2

with the per-sample variances of the IMU model, ``s_w^2 = ARW^2 / dt + b_g^2 + Omega_ie^2``
and ``s_f^2 = VRW^2 / dt``, is chi-square with ``6 n - 3`` degrees of freedom at rest; the
window is static when ``T`` is below its ``STANDSTILL_PROB`` quantile. The model of the test
is ``FuseConfig.standstill_imu``: the filter's, unless a tuning holds it apart (the rest
epochs then stay those of the held model while the filter's noise changes). Turning on the spot
fails the gyro term, driving fails the specific-force term through the road's vibration
(a perfectly smooth drive at constant speed is indistinguishable from rest for any IMU).
The window is causal (it ends at the sample), so the ESKF, the stream and the graph detect
the same epochs (:class:`VehicleAiding` keeps the last ``n - 1`` samples between runs).

Mounting and lever arm: the vehicle frame ``v`` (x forward, y left, z up) is the frame of
the non-holonomic constraint and of the odometer; ``mat_vb`` (from ``mount_rpy``, the IMU's
roll, pitch, yaw in the vehicle frame) maps body to vehicle axes, and ``lever_arm_b`` goes
from the IMU to the vehicle's reference point, whose velocity is ``vel_n + mat_nb (omega_b
x lever_arm_b)`` (:func:`polins.fusion.measurement.non_holonomic`).
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Mapping

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from polins.errors import UserInputError
from polins.fusion.config import NHC_RATE_HZ, STANDSTILL_WINDOW_S, FuseConfig
from polins.fusion.items import MeasurementItem
from polins.ins.earth import OMEGA_IE, earth_rate_n
from polins.models import ImuModel

FloatArray = NDArray[np.float64]

STANDSTILL_PROB = 0.999  # chi-square probability of the standstill test at rest
ODOMETER_COLUMNS = ("t", "speed")


def mat_vb_from_mount(mount_rpy: ArrayLike) -> FloatArray:
    """``mat_vb`` (body -> vehicle) of the IMU's roll, pitch, yaw in the vehicle frame [rad]
    (ZYX Euler angles, as ``polins.frames``)."""
    roll, pitch, yaw = (float(v) for v in np.asarray(mount_rpy, dtype=float).reshape(3))
    return Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()


def standstill_variances(model: ImuModel, dt: float) -> tuple[float, float]:
    """Per-sample variances at rest of the gyro [(rad/s)^2] and the specific force
    [(m/s^2)^2] of an IMU model sampled every ``dt`` [s] (module docstring)."""
    gyro_var = model.gyro_arw**2 / dt + model.gyro_bias**2 + OMEGA_IE**2
    accel_var = model.accel_vrw**2 / dt
    return max(gyro_var, 1e-30), max(accel_var, 1e-30)


def standstill_statistic(
    gyro_b: FloatArray, accel_b: FloatArray, n: int, gyro_var: float, accel_var: float
) -> FloatArray:
    """The statistic ``T`` (module docstring) of the window of ``n`` samples ending at each
    sample, ``(N,)``; inf where fewer than ``n`` samples end there.

    Parameters
    ----------
    gyro_b, accel_b : (N, 3) ndarray
        Body rates [rad/s] and specific forces [m/s^2].
    n : int
        Samples per window.
    gyro_var, accel_var : float
        Per-sample variances at rest (:func:`standstill_variances`).
    """
    m = gyro_b.shape[0]
    out = np.full(m, np.inf)
    if m < n:
        return out
    f = accel_b - accel_b.mean(axis=0)  # a common offset keeps the sums small

    def window_sum(x: FloatArray) -> FloatArray:
        c = np.concatenate([np.zeros((1, *x.shape[1:])), np.cumsum(x, axis=0)])
        return c[n:] - c[:-n]

    sum_w2 = window_sum(np.einsum("ij,ij->i", gyro_b, gyro_b))
    sum_f = window_sum(f)
    dev_f = window_sum(np.einsum("ij,ij->i", f, f)) - np.einsum("ij,ij->i", sum_f, sum_f) / n
    out[n - 1 :] = sum_w2 / gyro_var + np.maximum(dev_f, 0.0) / accel_var
    return out


def standstill_threshold(n: int, prob: float = STANDSTILL_PROB) -> float:
    """The ``prob`` quantile of the statistic at rest: chi-square with ``6 n - 3`` dof."""
    return float(chi2.ppf(prob, 6 * n - 3))


def standstill_mask(
    gyro_b: ArrayLike, accel_b: ArrayLike, model: ImuModel, dt: float, window_s: float = 0.5
) -> NDArray[np.bool_]:
    """Which samples end a window of ``window_s`` [s] at rest (module docstring), ``(N,)``."""
    n = window_samples(window_s, dt)
    gv, av = standstill_variances(model, dt)
    w, f = np.asarray(gyro_b, dtype=float), np.asarray(accel_b, dtype=float)
    return standstill_statistic(w, f, n, gv, av) <= standstill_threshold(n)


def zero_rate_std(model: ImuModel, m: int, dt: float) -> float | None:
    """1-sigma [rad/s] of the mean of ``m`` gyro samples at the interval ``dt`` [s] at rest,
    ``ARW / sqrt(m dt)`` (docs/filter.md §12, "Zero angular rate"); None for a model
    without gyro white noise."""
    std = model.gyro_arw / math.sqrt(m * dt)
    return float(std) if std > 0.0 else None


def window_samples(window_s: float, dt: float) -> int:
    """Samples in a window of ``window_s`` [s] at the interval ``dt`` [s] (at least 2)."""
    return max(2, round(window_s / dt))


class VehicleAiding:
    """The pseudo-measurements of the vehicle kind along the IMU samples (module docstring).

    Feed the samples in order (:meth:`items`); the detector keeps the last window between
    calls. ``active`` is False when the configuration asks for none.
    """

    def __init__(self, config: FuseConfig, dt: float) -> None:
        self.nhc_std = config.nhc_sigma
        self.zupt_std = config.standstill_sigma
        self.static = config.aiding.vehicle == "static"
        self.every = max(1, round(1.0 / (NHC_RATE_HZ * dt)))
        self.n = window_samples(STANDSTILL_WINDOW_S, dt)
        # the test's variances: of the detector's model (held apart from the filter's by a
        # tuning, so that the rest epochs do not change with the tuned noise)
        self.gyro_var, self.accel_var = standstill_variances(config.standstill_imu, dt)
        self.threshold = standstill_threshold(self.n)
        # zero angular rate: the mean of the `every` samples up to an epoch at rest
        self.zaru_std = zero_rate_std(config.imu, self.every, dt)
        mech = config.mechanize_earth_rate and config.site is not None
        self.rate_n = earth_rate_n(config.site.lat) if mech else None  # type: ignore[union-attr]
        mount = np.asarray(config.aiding.mount_rpy, dtype=float)
        self.mat_vb = mat_vb_from_mount(mount) if np.any(mount) else None
        lever = np.asarray(config.aiding.lever_arm_b, dtype=float)
        self.lever_arm_b = lever if np.any(lever) else None
        self.lever_state = config.lever_sigma is not None  # the items carry omega_b
        self.detect = not self.static
        self.active = any(s is not None for s in (self.nhc_std, self.zupt_std, self.zaru_std))
        self._keep = max(self.n, self.every) - 1  # samples kept between calls
        self._gyro = np.zeros((0, 3))  # the last `_keep` samples
        self._accel = np.zeros((0, 3))

    def copy(self) -> VehicleAiding:
        """An independent copy (the detector's window)."""
        return copy.copy(self)  # the window arrays are replaced, never changed in place

    def items(
        self, t: FloatArray, gyro_b: FloatArray, accel_b: FloatArray, index0: int
    ) -> list[tuple[int, MeasurementItem]]:
        """The pseudo-measurements at the samples ``t`` [s] (the first has the sample index
        ``index0`` from the filter's start), as ``(i, item)`` with ``i`` the position in
        ``t``; raw ``gyro_b`` [rad/s], ``accel_b`` [m/s^2]."""
        if not self.active:
            return []
        w = np.concatenate([self._gyro, gyro_b])
        f = np.concatenate([self._accel, accel_b])
        old = len(w) - len(t)  # samples before t
        if self.detect:
            stat = standstill_statistic(w, f, self.n, self.gyro_var, self.accel_var)
            still = stat[old:] <= self.threshold
        else:
            still = np.full(len(t), self.static)
        keep = max(0, len(w) - self._keep)
        self._gyro, self._accel = w[keep:], f[keep:]
        g = index0 + np.arange(len(t))
        epochs = np.flatnonzero((g >= 1) & (g % self.every == 0))
        rest = epochs[still[epochs]]
        out: list[tuple[int, MeasurementItem]] = [
            (i, MeasurementItem(float(t[i]), "zupt", self.zupt_std))
            for i in rest.tolist() if self.zupt_std is not None
        ]  # fmt: skip
        out += self._zero_rate(t, w, old, rest)
        if self.nhc_std is not None:
            out += [(i, self.attach(MeasurementItem(float(t[i]), "nhc", self.nhc_std), gyro_b[i]))
                    for i in epochs.tolist()]  # fmt: skip
        out.sort(key=lambda pair: (pair[0], pair[1].order))
        return out

    def _zero_rate(
        self, t: FloatArray, w: FloatArray, old: int, rest: NDArray[np.int_]
    ) -> list[tuple[int, MeasurementItem]]:
        """The zero-angular-rate items at the epochs ``rest`` (positions in ``t``): the mean
        of the ``every`` raw rates ``w`` up to each (``w`` holds ``old`` samples before
        ``t``), where all of them are at hand."""
        if self.zaru_std is None:
            return []
        end = rest + old + 1  # one past the epoch's sample in w
        rest, end = rest[end >= self.every], end[end >= self.every]
        c = np.concatenate([np.zeros((1, 3)), np.cumsum(w, axis=0)])
        mean = (c[end] - c[end - self.every]) / self.every
        return [(i, MeasurementItem(float(t[i]), "zaru", self.zaru_std, gyro_b=m,
                                    rate_n=self.rate_n))
                for i, m in zip(rest.tolist(), mean, strict=True)]  # fmt: skip

    def attach(self, item: MeasurementItem, gyro_b: FloatArray) -> MeasurementItem:
        """``item`` with the mounting and ``omega_b x lever_arm_b`` at the rate ``gyro_b``
        [rad/s], and the rate itself with a lever-arm state (unchanged if it has them
        already)."""
        if (
            (self.lever_arm_b is None and self.mat_vb is None and not self.lever_state)
            or item.mat_vb is not None
            or item.lever_vel_b is not None
            or item.gyro_b is not None
        ):
            return item
        lever_vel_b = None if self.lever_arm_b is None else np.cross(gyro_b, self.lever_arm_b)
        rate = np.array(gyro_b, dtype=float) if self.lever_state else None
        return dataclasses.replace(item, mat_vb=self.mat_vb, lever_vel_b=lever_vel_b,
                                   gyro_b=rate)  # fmt: skip

    def odometer(
        self,
        item: MeasurementItem,
        errors: Mapping[str, FloatArray],
        sample: tuple[float, FloatArray, FloatArray] | None,
    ) -> MeasurementItem:
        """An ``"odo"`` item ready for the update: the mounting and lever arm at the rate of
        ``sample`` (the filter's current ``(t, gyro_b, accel_b)``, if not attached when it
        was scheduled), divided by the scale estimate (:func:`scaled_odometer`)."""
        if sample is not None:
            item = self.attach(item, sample[1])
        return scaled_odometer(item, errors)


def yaw_consider_update(
    x: FloatArray, P: FloatArray, residual: FloatArray, R: FloatArray, H: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """A Kalman update that leaves the yaw error (state 2) alone: the ESKF's update of the
    velocity pseudo-measurements before the yaw is acquired.

    The yaw is then a *consider* state (Schmidt-Kalman filter): its row of the gain is
    zero, the Joseph form keeps the covariance right for that gain. With a yaw sigma of
    1 rad the linear model would otherwise turn small tilt-yaw correlations (the Earth
    rate's gyrocompassing, the NHC's yaw dependence) into large yaw corrections, and the
    headings would no longer agree for the acquisition (docs/filter.md).
    """
    PHt = P @ H.T
    K = np.linalg.solve(H @ PHt + R, PHt.T).T
    K[2] = 0.0
    x = x + K @ (residual - H @ x)
    IKH = np.eye(P.shape[0]) - K @ H
    return x, IKH @ P @ IKH.T + K @ R @ K.T


def vehicle_items(
    config: FuseConfig, t: FloatArray, gyro_b: FloatArray, accel_b: FloatArray
) -> list[MeasurementItem]:
    """The vehicle's pseudo-measurements along a whole IMU log (the graph's; the ESKF
    finds the same with :class:`VehicleAiding` as it goes)."""
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0 / config.imu.sample_rate_hz
    return [item for _, item in VehicleAiding(config, dt).items(t, gyro_b, accel_b, 0)]


def odometer_items(
    odometry: pd.DataFrame | Mapping[str, ArrayLike], std: float
) -> list[MeasurementItem]:
    """``"odo"`` items of an odometer table (``t`` [s], ``speed`` [m/s] forward); rows with
    a non-finite value are invalid items (logged, not used)."""
    missing = [c for c in ODOMETER_COLUMNS if c not in odometry]
    if missing:
        raise UserInputError(f"the odometry table needs the columns t, speed; missing {missing}")
    t = np.atleast_1d(np.asarray(odometry["t"], dtype=float))
    speed = np.atleast_1d(np.asarray(odometry["speed"], dtype=float))
    if not (math.isfinite(std) and std > 0):
        raise UserInputError(f"odometer_std must be > 0 [m/s], got {std!r}")
    out = []
    for ti, si in zip(t.tolist(), speed.tolist(), strict=True):
        ok = math.isfinite(ti) and math.isfinite(si)
        reason = "" if ok else f"invalid odometer row t={ti:g}, speed={si:g}"
        out.append(MeasurementItem(ti, "odo", std if ok else math.nan, speed=si, valid=ok,
                                   reason=reason))  # fmt: skip
    return out


def scaled_odometer(item: MeasurementItem, errors: Mapping[str, FloatArray]) -> MeasurementItem:
    """An ``"odo"`` item divided by ``1 + k`` of the odometer scale estimate ``errors["so"]``
    (docs/filter.md: the model is ``speed = (1 + k) v_x``)."""
    scale = errors.get("so")
    if scale is None:
        return item
    div = 1.0 + float(scale[0])
    return dataclasses.replace(item, speed=item.speed / div, std=item.std / div)


def with_standstill(measurements: pd.DataFrame | None, t: ArrayLike, std: float) -> pd.DataFrame:
    """The measurements table with zero-velocity updates at the known standstill times ``t``
    [s]: column ``zupt_std`` = ``std`` [m/s] on the row of each time (a new row, the other
    columns NaN, where the table has none), in time order; a row's own ``zupt_std`` is kept.
    The way to give zero-velocity updates at known times (docs/filter.md §5.4)."""
    rows = pd.DataFrame({"t": np.asarray(t, dtype=float), "zupt_std": float(std)})
    if measurements is None or len(measurements) == 0:
        return rows
    out = measurements.merge(rows, on="t", how="outer", suffixes=("", "_new"), sort=True)
    if "zupt_std_new" in out:
        out["zupt_std"] = out["zupt_std"].fillna(out.pop("zupt_std_new"))
    return out


__all__ = [
    "STANDSTILL_PROB",
    "VehicleAiding",
    "mat_vb_from_mount",
    "odometer_items",
    "scaled_odometer",
    "standstill_mask",
    "standstill_statistic",
    "standstill_threshold",
    "standstill_variances",
    "vehicle_items",
    "window_samples",
    "with_standstill",
    "yaw_consider_update",
    "zero_rate_std",
]
