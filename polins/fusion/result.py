"""The result of a fusion run: the solution table with the update log and the run's facts, in one object."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import pandas as pd


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
    """

    solution: pd.DataFrame
    updates: pd.DataFrame
    filtered: pd.DataFrame | None = None
    backend: str = "eskf"
    info: dict[str, Any] = field(default_factory=dict)
