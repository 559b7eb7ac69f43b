"""The stream's filter: one ESKF driven over runs of IMU samples, keeping its snapshots, the samples after them and its solution.

:class:`FilterRunner` takes the IMU samples the stream releases in runs: the self-alignment
window is levelled at once (``ESKF.level``), a single sample goes through
``ESKF.propagate``, a longer run through the filter's fast path
(:func:`polins.fusion.eskf.propagate.advance`), which gives the estimates
``polins.fusion.run_fusion`` gives. On the way it keeps the *snapshots* the image priors
start from (the first sample of every ``snapshot_every_s`` grid cell), the filtered samples
a prior may still need (:meth:`FilterRunner.prior_job`, :meth:`FilterRunner.trim`) and the
solution at the configuration's output rate (``FuseConfig.output_rate``: the first sample
of every ``1 / output_rate_hz`` cell counted from the first sample, as ``polins.fuse``
reports it; every sample when the rate is None).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable

import numpy as np
import pandas as pd
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from polins.fusion.config import TIME_TOL_S, FuseConfig
from polins.fusion.eskf.filter import ESKF
from polins.fusion.eskf.propagate import advance, interpolate
from polins.fusion.items import UpdateRecord
from polins.ins.state import NavState, concatenate, solution_table
from polins.loop.prior import PriorJob
from polins.loop.samples import SampleQueue

FloatArray = NDArray[np.float64]


class Snapshot:
    """A filter snapshot: its time [s] and its :class:`NavState`, taken from the run's
    batched states when first asked for (only images' priors need it)."""

    __slots__ = ("_i", "_nav", "_states", "t")

    def __init__(self, nav: NavState | None = None, states: NavState | None = None, i: int = 0):
        self._nav, self._states, self._i = nav, states, i
        src = nav if nav is not None else states
        assert src is not None
        self.t = float(np.asarray(src.t).reshape(-1)[0 if nav is not None else i])

    @property
    def nav(self) -> NavState:
        """The snapshot's state."""
        if self._nav is None:
            assert self._states is not None
            self._nav, self._states = self._states.at(self._i), None
        return self._nav


class FilterRunner:
    """The ESKF of a stream, its snapshots and its solution buffer.

    Parameters
    ----------
    config : FuseConfig
        The filter's configuration (with its site).
    t0 : float
        Time of the first IMU sample [s].
    dt : float
        Nominal IMU interval [s].
    rot_nb0 : Rotation, optional
        Initial attitude; None: self-alignment.
    snapshot_every_s : float
        Grid of the snapshots [s].
    max_rows : int
        Bound of the solution buffer (entries: one state, or the states of one run).
    """

    def __init__(
        self,
        config: FuseConfig,
        t0: float,
        dt: float,
        rot_nb0: Rotation | None,
        *,
        snapshot_every_s: float,
        max_rows: int,
    ) -> None:
        self.filter = ESKF(config, t0, dt, rot_nb0)
        self.t0 = float(t0)
        self.snapshot_every_s = snapshot_every_s
        self.output_rate = config.output_rate
        self._out_cell = -math.inf  # output cell of the last solution row
        self.snaps: deque[Snapshot] = deque()
        self.hist = SampleQueue()  # filtered samples a prior may still need
        self.solution: deque[NavState] = deque(maxlen=max_rows)
        self._levelling: list[FloatArray] = []  # (N, 7) blocks of the self-alignment window
        if self.filter.ready:  # attitude given: the initial state is the first snapshot
            self.snaps.append(Snapshot(self.filter.state()))

    def run(
        self, t: FloatArray, gyro_b: FloatArray, accel_b: FloatArray
    ) -> tuple[list[UpdateRecord], bool]:
        """Filter the samples ``(N,)`` [s], ``(N, 3)`` [rad/s], ``(N, 3)`` [m/s^2] (after
        the filter's last one, in time order).

        Returns
        -------
        records : list of UpdateRecord
            Measurements applied on the way (the filter's own log is cleared).
        changed : bool
            Whether a measurement or a reset changed the estimate.
        """
        f = self.filter
        n_resets = f.n_resets
        n_records = len(f.records)
        self.hist.extend(t, gyro_b, accel_b)
        if not f.ready:  # self-alignment: level on the window, then run from its start
            self._levelling.append(np.column_stack([t, gyro_b, accel_b]))
            block = np.concatenate(self._levelling)
            k_end = int(np.searchsorted(block[:, 0] - self.t0,
                                        f.config.initial.align_s - TIME_TOL_S))  # fmt: skip
            if k_end >= len(block):
                return [], False
            f.level([(float(r[0]), r[1:4], r[4:7]) for r in block[: k_end + 1]])
            t, gyro_b, accel_b = block[:, 0], block[:, 1:4], block[:, 4:7]
            self._levelling = []
        if f.started and len(t) == 1:
            f.propagate(t[0], gyro_b[0], accel_b[0])
            self._keep(f.t, f.state)
        else:
            self._fast_run(t, gyro_b, accel_b)
        records = f.records[n_records:]
        f.records.clear()  # bounded memory: the stream keeps the verdicts
        return records, bool(records) or f.n_resets != n_resets

    def prior_job(self, t_image: float, limit: float, queue: SampleQueue) -> PriorJob:
        """The prior job of an image at ``t_image`` [s] (:mod:`polins.loop.prior`): the
        latest snapshot taken before ``limit`` [s] (or the first), and the samples from the
        one before it to the first at or after the image (the not yet filtered ones from
        ``queue``)."""
        snap = self.snaps[0]
        for s in self.snaps:
            if s.t < limit:
                snap = s
            else:
                break
        hist = self.hist
        k = int(np.searchsorted(hist.t, snap.t - TIME_TOL_S, side="left"))
        k = max((k if k < len(hist) else 0) - 1, 0)
        m = min(int(np.searchsorted(queue.t, t_image, side="left")) + 1, len(queue))
        return PriorJob(snap.nav, np.concatenate([hist.t[k:], queue.t[:m]]),
                        np.concatenate([hist.gyro_b[k:], queue.gyro_b[:m]]),
                        np.concatenate([hist.accel_b[k:], queue.accel_b[:m]]), float(t_image),
                        self.filter.mech)  # fmt: skip

    def trim(self, limit: float) -> None:
        """Forget the snapshots a prior of an image after ``limit + prior_lag_s`` [s] does
        not start from (all but the latest before ``limit``), and the samples before them."""
        while len(self.snaps) > 1 and self.snaps[1].t < limit:
            self.snaps.popleft()
        keep_from = min(self.snaps[0].t if self.snaps else math.inf, self.filter.t)
        hist = self.hist
        k = int(np.searchsorted(hist.t, keep_from, side="right"))  # the last one at or before
        hist.drop(max(0, min(k - 1, len(hist) - 1)))

    def drain_solution(self) -> pd.DataFrame:
        """The solution table of the estimates kept since the last call."""
        states = list(self.solution)
        self.solution.clear()
        if states:
            return solution_table(concatenate(states))
        f = self.filter  # no row yet: the columns of this filter's table
        return solution_table(f.state()).iloc[:0] if f.ready else pd.DataFrame()

    def finish(self) -> None:
        """Keep the filter's last state as the solution's last row (as ``polins.fuse``)."""
        f = self.filter
        last = self.solution[-1].t if self.solution else None
        t_last = None if last is None else float(np.atleast_1d(last)[-1])
        if f.ready and f.started and t_last != f.t:
            self.solution.append(f.state())

    def output_rows(self, t: FloatArray) -> NDArray[np.bool_]:
        """Which of the times ``t`` (increasing) are solution rows (module docstring)."""
        if self.output_rate is None:
            return np.ones(len(t), dtype=bool)
        cell = np.floor((t - self.t0) * self.output_rate + 1e-9)
        new = cell > np.concatenate([[self._out_cell], cell[:-1]])
        if len(cell):
            self._out_cell = float(cell[-1])
        return np.asarray(new, dtype=bool)

    def new_cells(self, t: FloatArray) -> NDArray[np.bool_]:
        """Which of the times ``t`` (increasing) start a new snapshot grid cell."""
        step = self.snapshot_every_s
        cell = np.floor(t / step)
        prev = math.floor(self.snaps[-1].t / step) if self.snaps else -math.inf
        return np.asarray(cell > np.concatenate([[prev], cell[:-1]]), dtype=bool)

    def _keep(self, t: float, state: Callable[[], NavState]) -> None:
        new_cell = bool(self.new_cells(np.array([t]))[0])
        output = bool(self.output_rows(np.array([t]))[0])
        if not (new_cell or output):
            return
        st = state()
        if new_cell:
            self.snaps.append(Snapshot(st))
        if output:
            self.solution.append(st)

    def _fast_run(self, t: FloatArray, gyro_b: FloatArray, accel_b: FloatArray) -> None:
        """A run through the fast path: from the filter's last sample, or from its first
        one (a filter that took none)."""
        f = self.filter
        last = f.last_sample
        f.flush()
        start = 0 if last is None else 1
        if last is not None:
            t = np.concatenate([[last[0]], t])
            gyro_b = np.concatenate([last[1][None], gyro_b])
            accel_b = np.concatenate([last[2][None], accel_b])
        gyro, accel = gyro_b, accel_b
        output = np.zeros(len(t), dtype=bool)
        output[start:] = self.output_rows(t[start:])
        mask = output.copy()
        mask[start:] |= self.new_cells(t[start:])
        if not mask.any():  # a run inside one snapshot cell: nothing to keep
            advance(f, t, gyro, accel)
            return
        run = advance(f, t, gyro, accel, mask)
        assert run is not None
        states = interpolate(*run, f.layout.index)
        rows = output[mask]
        if rows.all():
            self.solution.append(states)
        elif rows.any():
            self.solution.append(states.take(np.flatnonzero(rows)))
        for i in np.flatnonzero(self.new_cells(np.asarray(states.t))):
            self.snaps.append(Snapshot(states=states, i=int(i)))


__all__ = ["FilterRunner", "Snapshot"]
