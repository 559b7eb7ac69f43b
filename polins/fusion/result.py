"""The result of a fusion run: the solution table with the update log, the data-fault events and the run's facts, in one object."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

# The data faults and recoveries of the fusion (docs/faults.md, docs/filter.md): an IMU
# sample that is not finite or beyond the model's full scale (dropped), an IMU gap longer
# than max_gap_s (propagated across, covariance inflated; the measurements inside it
# skipped), a measurement skipped inside such a gap, and the yaw re-acquired.
FUSION_EVENT_KINDS = (
    "imu-nonfinite",
    "imu-out-of-range",
    "imu-gap",
    "measurement-in-gap",
    "yaw-reacquired",
)


@dataclass(frozen=True)
class FusionEvent:
    """One data fault or recovery: time [s], a kind of :data:`FUSION_EVENT_KINDS`, a text."""

    t: float
    kind: str
    detail: str


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
    """What ``polins.fusion.run_fusion`` returns (``polins.fuse`` returns its ``solution``).

    Attributes
    ----------
    solution : DataFrame
        The solution table (``polins.ins.state.solution_table``; docs/filter.md lists its
        columns). With smoothing, the smoothed solution.
    updates : DataFrame
        One row per measurement: ``t, name, dim, nis, accepted, reason``
        (``polins.fusion.items.records_table``).
    filtered : DataFrame or None
        The filtered (causal) solution when ``solution`` is smoothed, else None.
    backend : str
        "eskf" or "graph".
    info : dict
        Facts of the run: the IMU model's name, the solver, iterations, timings [s], ...
    events : DataFrame
        The data faults met and the recoveries (``t, kind, detail``,
        :func:`events_table`): dropped IMU samples, IMU gaps, skipped measurements, yaw
        re-acquisitions. Empty for a clean run.
    """

    solution: pd.DataFrame
    updates: pd.DataFrame
    filtered: pd.DataFrame | None = None
    backend: str = "eskf"
    info: dict[str, Any] = field(default_factory=dict)
    events: pd.DataFrame = field(default_factory=lambda: events_table([]))
