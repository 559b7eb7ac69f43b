"""What each image is measured with: the attitude prior from a filter snapshot, and the sun vector.

The prior of an image at ``t_i`` is a filter snapshot (a :class:`polins.ins.state.NavState`)
propagated to ``t_i`` by the strapdown (:func:`polins.ins.strapdown.strapdown`) through the
raw IMU samples in between, corrected by the snapshot's sensor-error estimates as the filter
corrects them; a :class:`PriorJob` carries what it needs to where the image is measured.
The sun vector comes from the NREL SPA ephemeris on a coarse time grid (:class:`SunGrid`).

The prior, exactly (identical in streaming and batch use): the filter keeps *snapshots* of
its estimate at the first IMU sample of every ``snapshot_every_s`` grid cell
(:class:`polins.loop.runner.FilterRunner`). The prior of an image at ``t_i`` is the latest
snapshot taken at ``tau < t_i - prior_lag_s`` (or the first one, if none is that old),
propagated to ``t_i`` by :func:`propagate_nominal` with the snapshot's sensor-error
estimates. A snapshot at ``tau`` contains the updates of all images up to ``tau``, so
images closer than ``prior_lag_s`` to each other do not depend on each other and are
measured in parallel (a sliding window of up to ``max_in_flight`` images in a process pool,
while the filter stays sequential); the prior is propagated where the image is measured
(:class:`PriorJob`). The cost of the lag: the prior misses the last ``prior_lag_s`` of
updates, which typically moves the tilt far less than its sigma (simulated UGV drives:
median 0.001 deg with a MEMS IMU against a 0.16 deg roll sigma).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from polins.frames import euler_from_rot_nb
from polins.ins.state import NavState
from polins.ins.strapdown import Mechanization, strapdown
from polins.loop.samples import Sample
from polins.site import Site
from polins.sky.ephemeris import sun_position, sun_vector_n

FloatArray = NDArray[np.float64]
TIME_TOL_S = 1e-6  # [s] a time this close to a sample is that sample (the filter's tolerance)


def sample_at(t: float, samples: list[Sample]) -> tuple[FloatArray, FloatArray]:
    """IMU rate [rad/s] and specific force [m/s^2] at ``t`` inside ``samples`` (time order),
    linear between the bracketing samples."""
    ts = [s[0] for s in samples]
    k = int(np.searchsorted(ts, t, side="left"))
    for j in (k - 1, k):  # at a sample (to the filter's time tolerance)
        if 0 <= j < len(samples) and abs(samples[j][0] - t) <= TIME_TOL_S:
            return samples[j][1], samples[j][2]
    if k == 0 or k >= len(samples):
        raise ValueError(f"no IMU samples around t={t}")
    a, b = samples[k - 1], samples[k]
    frac = (t - a[0]) / (b[0] - a[0])
    return a[1] + (b[1] - a[1]) * frac, a[2] + (b[2] - a[2]) * frac


def propagate_nominal(
    state: NavState, samples: list[Sample], t_end: float, mech: Mechanization
) -> Rotation:
    """Attitude at ``t_end`` from a single filter estimate and raw IMU samples around it.

    The strapdown runs from ``state.t`` to ``t_end`` through the samples in between, with
    linearly interpolated samples at both ends if they fall between samples (the IMU
    convention), corrected by the estimate's biases (``bg``, ``ba``) and scale factors
    (``sg``, ``sa``, if estimated) as the filter does. ``samples`` must cover
    ``[state.t, t_end]``.
    """
    t0 = float(state.t)
    if t_end <= t0 + 1e-9:
        return state.rot_nb
    w0, f0 = sample_at(t0, samples)
    w1, f1 = sample_at(t_end, samples)
    inner = [s for s in samples if t0 + 1e-9 < s[0] < t_end - 1e-9]
    t = np.array([t0, *[s[0] for s in inner], t_end])
    w = np.array([w0, *[s[1] for s in inner], w1])
    f = np.array([f0, *[s[2] for s in inner], f1])
    err = state.errors
    w = (w - err.get("bg", 0.0)) / (1.0 + err.get("sg", 0.0))
    f = (f - err.get("ba", 0.0)) / (1.0 + err.get("sa", 0.0))
    nav0 = NavState(t0, state.rot_nb, np.asarray(state.vel_n), float(state.lat),
                        float(state.lon), float(state.alt_m))  # fmt: skip
    track = strapdown(nav0, t, w, f, mech)
    return Rotation.from_matrix(track.mat_nb[-1])


@dataclass(frozen=True, eq=False)
class PriorJob:
    """What the prior of an image is computed from, where the image is measured (a worker
    thread or process): a filter snapshot, the raw IMU samples from it to the image, the
    image time [s] and the strapdown's Earth terms (:func:`propagate_nominal`)."""

    snapshot: NavState
    t: FloatArray  # (N,) sample times [s]
    gyro_b: FloatArray  # (N, 3) [rad/s]
    accel_b: FloatArray  # (N, 3) [m/s^2]
    t_image: float
    mech: Mechanization

    @classmethod
    def of(cls, snapshot: NavState, samples: list[Sample], t_image: float,
           mech: Mechanization) -> PriorJob:  # fmt: skip
        """The job of ``samples`` (as arrays: cheap to send to a worker process)."""
        t = np.fromiter((s[0] for s in samples), dtype=float, count=len(samples))
        gyro = np.array([s[1] for s in samples], dtype=float).reshape(-1, 3)
        accel = np.array([s[2] for s in samples], dtype=float).reshape(-1, 3)
        return cls(snapshot, t, gyro, accel, float(t_image), mech)

    def rotation(self) -> Rotation:
        """The prior attitude body -> ENU at the image time."""
        samples = list(zip(self.t.tolist(), self.gyro_b, self.accel_b, strict=True))
        return propagate_nominal(self.snapshot, samples, self.t_image, self.mech)

    def columns(self, rot_prior: Rotation) -> dict[str, float]:
        """The prior's columns of a measurement row: ``prior_t`` [s], ``prior_roll``,
        ``prior_pitch``, ``prior_yaw`` [rad]."""
        yaw, pitch, roll = euler_from_rot_nb(rot_prior)
        return {"prior_t": float(self.snapshot.t), "prior_roll": float(roll),
                "prior_pitch": float(pitch), "prior_yaw": float(yaw)}  # fmt: skip


class SunGrid:
    """ENU sun vector at log times: the NREL SPA on a grid of ``step_s``, interpolated.

    The interpolation error is below 1e-6 deg (the sun moves < 0.005 deg/s along a smooth
    path); the grid is computed in fixed blocks of ``block`` points, so a value depends on
    ``t`` only, never on the order of the calls. At most five blocks are kept.

    Parameters
    ----------
    site : Site
        Where the sun is seen from.
    epoch_utc : Timestamp
        UTC time of ``t = 0`` (timezone-aware).
    step_s : float
        Grid step [s].
    block : int
        Grid points computed per ephemeris call.
    """

    def __init__(
        self, site: Site, epoch_utc: pd.Timestamp, step_s: float = 10.0, block: int = 32
    ) -> None:
        self.site = site
        self.epoch_utc = epoch_utc
        self.step_s = float(step_s)
        self.block = int(block)
        self._blocks: dict[int, FloatArray] = {}

    def __call__(self, t: float) -> FloatArray:
        """Unit ENU sun vector at log time ``t`` [s]."""
        x = float(t) / self.step_s
        k = math.floor(x)
        a, b = self._point(k), self._point(k + 1)
        v = a + (b - a) * (x - k)
        return np.asarray(v / np.linalg.norm(v), dtype=float)

    def _point(self, k: int) -> FloatArray:
        block, i = divmod(k, self.block)
        if block not in self._blocks:
            steps = self.step_s * (block * self.block + np.arange(self.block))
            times = pd.DatetimeIndex(self.epoch_utc + pd.to_timedelta(steps, "s"))
            site = self.site
            sun = sun_position(times, site.lat_deg, site.lon_deg, site.alt_m)
            self._blocks[block] = sun_vector_n(sun.azimuth, sun.zenith)
            for old in [b for b in self._blocks if abs(b - block) > 2]:
                del self._blocks[old]
        return np.asarray(self._blocks[block][i])


__all__ = ["PriorJob", "Sample", "SunGrid", "propagate_nominal", "sample_at"]
