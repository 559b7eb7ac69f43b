"""The loop's tables: one measurement row per image, and the bounded buffer of data-fault events.

An event is data, not a log line (docs/faults.md): a time, a kind from :data:`EVENT_KINDS`
and a detail text, so a user can count and filter them. The data faults of the loop
(skipped and reported, the run goes on):

* IMU sample with NaN/inf: dropped (``imu-nonfinite``).
* IMU sample not after the previous accepted one (duplicate or out of order): dropped
  (``imu-out-of-order``).
* IMU sample beyond the IMU model's full scale: dropped (``imu-out-of-range``).
* IMU gap longer than ``max_gap_s`` (FuseConfig; auto: 5 sample intervals): reported (``imu-gap``) and propagated across with
  the rates interpolated linearly (the covariance grows with the gap).
* Image not after the previous image: skipped (``image-out-of-order``).
* Image older than the filter can still take (more than ``max_image_delay_s`` behind the IMU,
  after the filter has moved past it): skipped (``image-late``).
* Image before the first IMU sample or after the last one: skipped (``image-outside-imu``).
* Image inside the levelling window of a self-alignment: skipped (``image-during-alignment``).
* Image that cannot be read or decoded (``image-unreadable``), or on which OpenCV fails
  (``image-error``): skipped. Any other exception of the measurement is a bug and propagates.
* Image index entry outside the log folder (``polins.io.read_log`` without
  ``allow_outside_paths``): skipped (``path-outside-log``).
* Image refused by the measurement (too few pixels, sun near the zenith, ...): kept in the
  measurement table with ``ok=False`` and its reason; no update.
* Update refused by the filter's chi-square gate: kept with ``accepted=False`` and the reason.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np
import pandas as pd

EVENT_KINDS = (
    "imu-nonfinite",
    "imu-out-of-order",
    "imu-gap",
    "imu-out-of-range",
    "image-out-of-order",
    "image-late",
    "image-outside-imu",
    "image-during-alignment",
    "image-unreadable",
    "image-error",
    "path-outside-log",
    "noise-model",
)
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
        self.counts: dict[str, int] = dict.fromkeys(EVENT_KINDS, 0)
        self.dropped = 0

    def add(self, t: float, kind: str, detail: str) -> None:
        """Report one event; ``kind`` must be one of :data:`EVENT_KINDS`."""
        if kind not in self.counts:
            raise ValueError(f"event kind {kind!r} is not one of {EVENT_KINDS}")
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
    "EVENT_KINDS",
    "MEASUREMENT_COLUMNS",
    "EventBuffer",
    "measurement_frame",
]
