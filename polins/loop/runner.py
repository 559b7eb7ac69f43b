"""The stream's filter: one ESKF driven over runs of IMU samples, keeping its snapshots and solution.

:class:`FilterRunner` takes the IMU samples the stream releases in runs: the self-alignment
window is levelled at once (``ESKF.level``), a single sample goes through
``ESKF.propagate``, a longer run through the filter's fast path
(:func:`polins.fusion.eskf.propagate.advance`), which gives the estimates
``polins.fusion.run_fusion`` gives. On the way it keeps the *snapshots* the image priors
start from (the first sample of every ``snapshot_every_s`` grid cell) and the solution at
the configuration's output rate (``FuseConfig.output_rate``: the first sample of every
``1 / output_rate_hz`` cell counted from the first sample, as ``polins.fuse`` reports it;
every sample when the rate is None).
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
            self.snaps.append(st)
        if output:
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
        output = np.zeros(len(t), dtype=bool)
        output[len(start) :] = self.output_rows(t[len(start) :])
        mask = output.copy()
        mask[len(start) :] |= self.new_cells(t[len(start) :])
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
            self.snaps.append(states.at(int(i)))


__all__ = ["FilterRunner"]
