"""The stream's filter: one ESKF driven over runs of IMU samples, keeping its snapshots and solution.

:class:`FilterRunner` takes the IMU samples the stream releases in runs: the self-alignment
window is levelled at once (``ESKF.level``), a single sample goes through
``ESKF.propagate``, a longer run through the filter's fast path
(:func:`polins.fusion.eskf.propagate.advance`), which gives the estimates
``polins.fusion.run_fusion`` gives. On the way it keeps the *snapshots* the image priors
start from (the first sample of every ``snapshot_every_s`` grid cell) and, if asked, the
estimate at the configured output rate (the solution).
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
from polins.loop.prior import Sample

FloatArray = NDArray[np.float64]


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
    record_solution : bool
        Keep the estimate at the output rate of ``config`` (``output_rate_hz``; every sample
        for ``"imu"``) for :meth:`drain_solution`.
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
        record_solution: bool,
        max_rows: int,
    ) -> None:
        self.filter = ESKF(config, t0, dt, rot_nb0)
        self.t0 = float(t0)
        self.snapshot_every_s = snapshot_every_s
        self.record_solution = record_solution
        self.output_rate = config.output_rate  # None: every sample
        self._output_cell = -math.inf  # the output grid cell of the last row kept
        self.snaps: deque[NavState] = deque()
        self.solution: deque[NavState] = deque(maxlen=max_rows)
        self._levelling: list[Sample] = []  # samples of the self-alignment window so far
        if self.filter.ready:  # attitude given: the initial state is the first snapshot
            self.snaps.append(self.filter.state())

    def run(self, samples: list[Sample]) -> tuple[list[UpdateRecord], bool]:
        """Filter the samples (after the filter's last one, in time order).

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
        if not f.ready:  # self-alignment: level on the window, then run from its start
            self._levelling.extend(samples)
            t_lev = np.array([s[0] for s in self._levelling]) - self.t0
            k_end = int(np.searchsorted(t_lev, f.config.initial.align_s - TIME_TOL_S))
            if k_end >= len(t_lev):
                return [], False
            f.level(self._levelling[: k_end + 1])
            samples, self._levelling = self._levelling, []
        if f.started and len(samples) == 1:
            f.propagate(*samples[0])
            self._keep(f.t, f.state)
        else:
            self._fast_run(samples)
        records = f.records[n_records:]
        f.records.clear()  # bounded memory: the stream keeps the verdicts
        return records, bool(records) or f.n_resets != n_resets

    def drain_solution(self) -> pd.DataFrame:
        """The solution table of the estimates kept since the last call."""
        states = list(self.solution)
        self.solution.clear()
        return solution_table(concatenate(states)) if states else pd.DataFrame()

    def new_cells(self, t: FloatArray) -> NDArray[np.bool_]:
        """Which of the times ``t`` (increasing) start a new snapshot grid cell."""
        step = self.snapshot_every_s
        cell = np.floor(t / step)
        prev = math.floor(self.snaps[-1].t / step) if self.snaps else -math.inf
        return np.asarray(cell > np.concatenate([[prev], cell[:-1]]), dtype=bool)

    def output_rows(self, t: FloatArray) -> NDArray[np.bool_]:
        """Which of the times ``t`` (increasing) are solution rows: every one without an
        output rate, else the first sample of each ``1 / output_rate_hz`` cell after ``t0``
        (``polins.fusion.output_mask``); updates the last cell kept."""
        if not self.record_solution:
            return np.zeros(len(t), dtype=bool)
        if self.output_rate is None:
            return np.ones(len(t), dtype=bool)
        cell = np.floor((t - self.t0) * self.output_rate + 1e-9)
        rows = np.asarray(cell > np.concatenate([[self._output_cell], cell[:-1]]), dtype=bool)
        if len(t):
            self._output_cell = float(cell[-1])
        return rows

    def _keep(self, t: float, state: Callable[[], NavState]) -> None:
        new_cell = bool(self.new_cells(np.array([t]))[0])
        row = bool(self.output_rows(np.array([t]))[0])
        if not (new_cell or row):
            return
        st = state()
        if new_cell:
            self.snaps.append(st)
        if row:
            self.solution.append(st)

    def _fast_run(self, samples: list[Sample]) -> None:
        """A run through the fast path: from the filter's last sample, or from its first
        one (a filter that took none)."""
        f = self.filter
        start = [] if f.last_sample is None else [f.last_sample]
        f.flush()
        t = np.array([s[0] for s in start + samples])
        gyro = np.array([s[1] for s in start + samples])
        accel = np.array([s[2] for s in start + samples])
        mask = np.zeros(len(t), dtype=bool)
        rows = self.output_rows(t[len(start) :])
        mask[len(start) :] = self.new_cells(t[len(start) :]) | rows
        if not mask.any():  # a run inside one snapshot and output cell: nothing to keep
            advance(f, t, gyro, accel)
            return
        run = advance(f, t, gyro, accel, mask)
        assert run is not None
        states = interpolate(*run, f.layout.index)
        if rows.all():
            self.solution.append(states)
        elif rows.any():
            kept = np.flatnonzero(rows[mask[len(start) :]])
            self.solution.append(concatenate([states.at(int(i)) for i in kept]))
        for i in np.flatnonzero(self.new_cells(np.asarray(states.t))):
            self.snaps.append(states.at(int(i)))


__all__ = ["FilterRunner"]
