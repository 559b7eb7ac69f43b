"""The loop's tables: one measurement row per image, and the bounded buffer of data-fault events.

An event is data, not a log line (docs/faults.md): a time, a kind of
:class:`polins.fusion.faults.EventKind` (the one vocabulary of every path) and a detail
text, so a user can count and filter them. docs/faults.md says which data faults the loop
meets and what it does with each; beyond the IMU policy of :mod:`polins.fusion.faults`
(shared with ``polins.fuse``) the loop skips images out of order (``image-out-of-order``),
too late for the filter (``image-late``), outside the IMU span (``image-outside-imu``),
inside the levelling window (``image-during-alignment``), unreadable (``image-unreadable``)
or failing in OpenCV (``image-error``), and index entries outside the log folder
(``path-outside-log``). An image refused by the measurement stays in the measurement table
with ``ok=False`` and its reason; an update refused by the gate with ``accepted=False``.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np
import pandas as pd

from polins.fusion.faults import EventKind

EVENT_COLUMNS = ("t", "kind", "detail")
MEASUREMENT_COLUMNS = (
    "t", "ok", "reason", "yaw", "yaw_std", "heading_deg", "heading_std_deg", "epsilon",
    "epsilon_std", "n_pixels", "yaw_std_meas", "yaw_std_noise", "yaw_std_model",
    "yaw_std_correlated", "sun_bx", "sun_by", "sun_bz", "sun_nx",
    "sun_ny", "sun_nz", "sun_std", "sun_azimuth_b", "sun_azimuth_b_std", "sun_elevation_b",
    "sun_elevation_b_std", "eigen_gap", "residual_rms", "noise_ratio", "prior_t", "prior_roll",
    "prior_pitch", "prior_yaw", "accepted", "update_reason", "innovation", "nis", "nis_dof",
    "measure_s", "image",
)  # fmt: skip


class EventBuffer:
    """Bounded buffer of events (``t, kind, detail``): beyond ``maxlen`` the oldest is dropped.

    Parameters
    ----------
    maxlen : int
        Events kept until the next :meth:`drain`.

    Attributes
    ----------
    counts : dict of str to int
        Events reported per kind since the start (drained or not).
    dropped : int
        Events pushed out of the buffer before they were drained.
    """

    def __init__(self, maxlen: int) -> None:
        if maxlen < 1:
            raise ValueError(f"maxlen={maxlen} must be >= 1")
        self._rows: deque[dict[str, Any]] = deque(maxlen=maxlen)
        self.counts: dict[str, int] = {kind.value: 0 for kind in EventKind}
        self.dropped = 0

    def add(self, t: float, kind: str, detail: str) -> None:
        """Report one event; ``kind`` must be an :class:`~polins.fusion.faults.EventKind`."""
        kind = EventKind(kind).value  # an unknown kind raises ValueError
        if len(self._rows) == self._rows.maxlen:
            self.dropped += 1
        self.counts[kind] += 1
        self._rows.append({"t": float(t), "kind": kind, "detail": detail})

    def __len__(self) -> int:
        return len(self._rows)

    def drain(self) -> pd.DataFrame:
        """The buffered events (``t, kind, detail``, oldest first), and forget them."""
        rows = list(self._rows)
        self._rows.clear()
        return pd.DataFrame(rows, columns=pd.Index(EVENT_COLUMNS))


def measurement_frame(rows: list[dict[str, Any]]) -> pd.DataFrame:
    """Image rows as a table with ``MEASUREMENT_COLUMNS`` (sorted by time)."""
    df = pd.DataFrame(rows)
    for col in MEASUREMENT_COLUMNS:
        if col not in df.columns:
            df[col] = np.nan
    df = df.loc[:, list(MEASUREMENT_COLUMNS)]
    if len(df):
        df = df.sort_values("t", kind="stable").reset_index(drop=True)
    for col in ("ok", "accepted"):
        df[col] = df[col].astype(object).fillna(False).astype(bool)
    for col in ("reason", "update_reason", "image"):
        df[col] = df[col].astype(object).fillna("").astype(str)
    return df


__all__ = [
    "EVENT_COLUMNS",
    "MEASUREMENT_COLUMNS",
    "EventBuffer",
    "measurement_frame",
]
