"""The stream's IMU sample gate: which samples join the filter, and an event for each that does not.

The policy of docs/faults.md for a live IMU stream (``NavigationStream.add_imu``):

* a sample with NaN/inf is dropped (``imu-nonfinite``);
* a sample not after the previous accepted one is dropped (``imu-out-of-order``);
* a sample beyond the IMU model's full scale (``ImuModel.full_scale``) is dropped
  (``imu-out-of-range``);
* a gap longer than ``max_gap_s`` is reported (``imu-gap``) and the sample accepted;
* over the static levelling window the units are checked as ``polins fuse`` checks a file
  (:func:`polins.fusion.inputs.check_imu_units`): specific force in g or mg, or a gyro in
  deg/s, is a user mistake and raises ``UserInputError`` once, before any heading.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from polins.fusion.inputs import check_imu_units
from polins.loop.tables import EventBuffer

FloatArray = NDArray[np.float64]


class ImuGate:
    """Accepts or drops IMU samples one by one (module docstring).

    Parameters
    ----------
    events : EventBuffer
        Where the dropped samples and gaps are reported.
    full_scale : (float, float)
        Gyro [rad/s] and accelerometer [m/s^2] full scale (``ImuModel.full_scale()``).
    window_s : float
        Length of the levelling window whose samples are unit-checked [s].
    max_gap_s : float
        Longer intervals without a sample are reported as gaps [s].
    """

    def __init__(
        self, events: EventBuffer, full_scale: tuple[float, float], window_s: float,
        max_gap_s: float,
    ) -> None:  # fmt: skip
        self.events = events
        self.gyro_max, self.accel_max = full_scale
        self.window_s = window_s
        self.max_gap_s = max_gap_s
        self.n = 0  # accepted samples
        self.t_first = math.nan  # first accepted time [s]
        self.t_latest = -math.inf  # newest accepted time [s]
        self._norms: list[tuple[float, float]] | None = []  # |w|, |f| of the window

    def accept(self, t: float, w: FloatArray, f: FloatArray) -> bool:
        """True if the sample ``(t, w [rad/s], f [m/s^2])`` joins the filter."""
        if not (math.isfinite(t) and np.all(np.isfinite(w)) and np.all(np.isfinite(f))):
            self.events.add(t, "imu-nonfinite", "IMU sample with NaN/inf dropped")
            return False
        if t <= self.t_latest:
            what = "duplicated" if t == self.t_latest else "out-of-order"
            self.events.add(t, "imu-out-of-order",
                            f"{what} IMU sample dropped (previous t={self.t_latest!r})")  # fmt: skip
            return False
        w_norm, f_norm = math.hypot(*w), math.hypot(*f)
        if w_norm > self.gyro_max or f_norm > self.accel_max:
            self.events.add(t, "imu-out-of-range",
                            f"IMU sample beyond the full scale dropped: |w| = {w_norm:.3g} rad/s "
                            f"(limit {self.gyro_max:.3g}), |f| = {f_norm:.3g} m/s^2 "
                            f"(limit {self.accel_max:.3g})")  # fmt: skip
            return False
        if self.n and t - self.t_latest > self.max_gap_s:
            self.events.add(t, "imu-gap",
                            f"{t - self.t_latest:.4g} s without IMU data after "
                            f"t={self.t_latest:.6f}; propagated across")  # fmt: skip
        if self.n == 0:
            self.t_first = t
        if self._norms is not None:
            if t > self.t_first + self.window_s:
                norms = np.array(self._norms).reshape(-1, 2)
                self._norms = None
                check_imu_units(norms[:, 0], norms[:, 1], self.gyro_max)
            else:
                self._norms.append((w_norm, f_norm))
        self.t_latest = t
        self.n += 1
        return True
