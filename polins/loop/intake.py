"""The stream's IMU intake: samples collected one by one, screened in blocks by the fault policy, queued for the filter.

:class:`ImuIntake` takes the samples of ``NavigationStream.add_imu``: each is checked at
once against the screen of :mod:`polins.fusion.faults` (time order, NaN, full scale) and
collected as a tuple; once every ``block_s`` of IMU time (or at a fault) the block is due
and :meth:`ImuIntake.screen_block` / :meth:`ImuIntake.queue_block` screen it as
``polins.fuse`` screens a log (the dropped samples and the gaps reported as events), feed
the unit checks (the levelling window, the gyro against the headings) and append the
accepted samples to the queue the filter takes them from
(:class:`~polins.loop.samples.SampleQueue`). The gaps are returned for the stream to
bridge in the filter.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from polins.fusion.faults import GyroHeadingCheck, ImuScreen, UnitsWindow
from polins.loop.samples import Sample, SampleQueue
from polins.loop.tables import EventBuffer

FloatArray = NDArray[np.float64]


class ImuIntake:
    """The IMU samples of a stream from ``add_imu`` to the filter's queue (module docstring).

    Parameters
    ----------
    full_scale : (float, float)
        The IMU's gyro [rad/s] and accelerometer [m/s^2] full scale.
    max_gap_s : float
        The longest interval between samples that is not a gap [s].
    align_s : float
        The levelling window [s] (the units check's window).
    block_s : float
        IMU time [s] collected before a block is due.
    events : EventBuffer
        Where the dropped samples and the gaps are reported.
    """

    def __init__(
        self,
        full_scale: tuple[float, float],
        max_gap_s: float,
        align_s: float,
        block_s: float,
        events: EventBuffer,
    ) -> None:
        self.screen = ImuScreen(full_scale, max_gap_s)
        self.units = UnitsWindow(align_s, full_scale[0])
        self.heading_check = GyroHeadingCheck()
        self.queue = SampleQueue()  # accepted samples not yet filtered
        self.last: Sample | None = None  # the newest accepted sample
        self.t_newest = -math.inf  # time of the newest sample that passed the per-sample check
        self.t_advanced = -math.inf  # newest sample time when the last block was due
        self.block_s = float(block_s)
        self._events = events
        self._pending: list[tuple[float, ...]] = []  # collected samples not yet screened
        self._gyro_max_sq, self._accel_max_sq = full_scale[0] ** 2, full_scale[1] ** 2

    @property
    def n_pending(self) -> int:
        """Samples collected and not yet screened."""
        return len(self._pending)

    def add(
        self, t: float, gyro_b: Sequence[float] | FloatArray, accel_b: Sequence[float] | FloatArray
    ) -> tuple[bool, bool]:
        """Collect one sample; whether it passes the screen, and whether a block is due
        (a fault, a gap or ``block_s`` of IMU time since the last block)."""
        t = float(t)
        wx, wy, wz = gyro_b
        fx, fy, fz = accel_b
        row = (t, float(wx), float(wy), float(wz), float(fx), float(fy), float(fz))
        self._pending.append(row)
        # the screen of polins.fusion.faults on one sample (NaN fails every comparison)
        if not (
            t > self.t_newest
            and row[1] ** 2 + row[2] ** 2 + row[3] ** 2 <= self._gyro_max_sq
            and row[4] ** 2 + row[5] ** 2 + row[6] ** 2 <= self._accel_max_sq
        ):
            return False, True  # dropped by the screen, with its event
        gap = t > self.t_newest + self.screen.max_gap_s  # a gap: known to the next call
        self.t_newest = t
        return True, gap or t >= self.t_advanced + self.block_s

    def pending_block(self) -> FloatArray | None:
        """The collected samples as an ``(N, 7)`` block ``t, gyro_b, accel_b`` (None: no
        sample), forgotten here."""
        if not self._pending:
            return None
        block = np.array(self._pending, dtype=float)
        self._pending.clear()
        return block

    def screen_block(
        self, t: FloatArray, gyro_b: FloatArray, accel_b: FloatArray
    ) -> tuple[NDArray[np.bool_], NDArray[np.int_]]:
        """The IMU sample policy of :mod:`polins.fusion.faults` over a block (N,) [s],
        (N, 3) [rad/s, m/s^2]: the dropped samples and the gaps reported; which samples are
        kept, and the indices of those that close a gap (``ImuScreen.screen``)."""
        keep, events, gap_ends = self.screen.screen(t, gyro_b, accel_b)
        for ev in events:
            self._events.add(ev.t, ev.kind, ev.detail)
        return keep, gap_ends

    def queue_block(
        self,
        t: FloatArray,
        gyro_b: FloatArray,
        accel_b: FloatArray,
        keep: NDArray[np.bool_],
        gap_ends: NDArray[np.int_],
    ) -> list[tuple[Sample, Sample]]:
        """The kept samples of a block :meth:`screen_block` screened: the unit checks fed
        (``ImuUnitsError``), the samples queued; the gaps ``(before, after)`` between
        accepted samples, in time order."""
        self.units.add(t[keep], gyro_b[keep], accel_b[keep])
        self.heading_check.add_imu(t[keep], gyro_b[keep], accel_b[keep])
        kept = np.flatnonzero(keep)
        bounds = [0, *np.searchsorted(kept, gap_ends).tolist(), len(kept)]
        gaps: list[tuple[Sample, Sample]] = []
        for j, (a, b) in enumerate(itertools.pairwise(bounds)):  # the runs between gaps
            run = kept[a:b]
            if not run.size:
                continue
            first, last = int(run[0]), int(run[-1])
            if j > 0 and self.last is not None:  # the run starts after a gap
                gaps.append((self.last, (float(t[first]), gyro_b[first], accel_b[first])))
            self.queue.extend(t[run], gyro_b[run], accel_b[run])
            self.last = (float(t[last]), gyro_b[last].copy(), accel_b[last].copy())
        return gaps


__all__ = ["ImuIntake"]
