"""The result of a fusion run: the solution table with the update log, the data-fault events and the run's facts, in one object."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from polins.fusion.config import FuseConfig
from polins.fusion.faults import FusionEvent


def events_table(events: Sequence[FusionEvent]) -> pd.DataFrame:
    """The events as a table ``t, kind, detail``, in time order."""
    ordered = sorted(events, key=lambda e: e.t)
    return pd.DataFrame(
        {
            "t": np.array([e.t for e in ordered], dtype=float),
            "kind": [e.kind for e in ordered],
            "detail": [e.detail for e in ordered],
        }
    )


@dataclass(frozen=True, eq=False)
class FusionResult:
    """What a fusion run returns: ``polins.fusion.run_fusion`` and ``polins.loop.run_log``.

    Attributes
    ----------
    solution : DataFrame
        The solution table (``polins.ins.state.solution_table``; docs/filter.md lists its
        columns). With smoothing, the smoothed solution.
    updates : DataFrame
        One row per measurement: ``t, name, dim, nis, accepted, reason``
        (``polins.fusion.items.records_table``).
    events : DataFrame
        The data faults met and the recoveries (``t, kind, detail``,
        :func:`events_table`; ``kind`` one of :class:`polins.fusion.faults.EventKind`).
        Empty for a clean run.
    config : FuseConfig
        The resolved configuration of the run (its site, IMU model, tilt coupling, ...).
    backend : str
        "eskf" or "graph".
    filtered : DataFrame or None
        The filtered (causal) solution when ``solution`` is smoothed, else None.
    info : dict
        Facts of the backend: the solver, iterations, keyframes, timings [s], resets. From
        ``run_log`` also ``timing`` (``run_s, loop_s, fuse_s, measure_s_mean`` [s] and the
        counts ``images, imu_samples, workers``), ``settings`` (the run's options, for the
        summary) and ``imu_used`` (the IMU samples the sample policy kept, a DataFrame).
    measurements : DataFrame or None
        The navigation loop's table, one row per image
        (``polins.loop.tables.MEASUREMENT_COLUMNS``); None outside the loop.
    """

    solution: pd.DataFrame
    updates: pd.DataFrame
    events: pd.DataFrame
    config: FuseConfig
    backend: str = "eskf"
    filtered: pd.DataFrame | None = None
    info: dict[str, Any] = field(default_factory=dict)
    measurements: pd.DataFrame | None = None
