"""Images on their way to the filter: the queue in time order, their measurement by the workers, their rows awaiting the filter's verdict.

:class:`ImageQueue` holds what ``NavigationStream.add_image`` and ``add_measurement`` add
(:class:`~polins.loop.measurer.PendingImage`, in time order) until the stream hands the
measurements over to the filter, submits each image with its prior to the executor, and
keeps the measurement log: one row per image (``polins.loop.tables.MEASUREMENT_COLUMNS``),
completed with the filter's verdict (accepted, NIS, innovation) when the filter applies
the image's update. A skipped image gets its event and a row with its reason
(docs/faults.md).
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from collections.abc import Callable
from concurrent.futures import Executor
from typing import Any

import numpy as np
import pandas as pd

from polins.fusion.config import FuseConfig
from polins.fusion.faults import EventKind, GyroHeadingCheck, ImuScreen, gap_reason
from polins.fusion.inputs import PRIOR_COLUMNS, heading_proxy
from polins.fusion.items import MeasurementItem, UpdateRecord, items_from_table
from polins.loop.measurer import PendingImage, report_noise_model
from polins.loop.prior import PriorJob
from polins.loop.tables import EventBuffer, measurement_frame

# the further columns of a measured row the filter uses: the sun fit's 2x2 covariance and
# the sigma's parts a heading-bias state carries (docs/filter.md §5.7)
SKY_COLUMNS = ("sun_elevation_b", "sun_elevation_b_std", "yaw_std_model", "yaw_std_noise",
               "yaw_std_correlated")  # fmt: skip


def _columns(row: dict[str, float]) -> tuple[str, ...]:
    """The column names of a measurement row, in order."""
    return tuple(row)


def row_items(rows: list[dict[str, float]], config: FuseConfig) -> list[list[MeasurementItem]]:
    """The filter's items of measurement-table rows (:meth:`ImageQueue.filter_row`), in
    order: the rows as one measurement table (``items_from_table``, the rules of
    ``polins.fuse``), rows with the same columns at once; a list per group."""
    out: list[list[MeasurementItem]] = []
    for _, group in itertools.groupby(rows, key=_columns):
        block = list(group)
        out.append(items_from_table({k: [row[k] for row in block] for k in block[0]},
                                    use_sun=config.gating.use_sun,
                                    heading_bias=config.heading_bias))  # fmt: skip
    return out


class ImageQueue:
    """The stream's images between ``add_image`` and the filter, and its measurement log.

    Parameters
    ----------
    executor : Executor
        Where images are measured (``polins.loop.measurer.make_executor``).
    submit_fn : callable
        The function the executor runs: ``(raw, sun_n, prior) -> row``.
    events : EventBuffer
        Where skipped images and the measurement's events are reported.
    max_rows : int
        Bound of the measurement log (rows not drained are dropped, oldest first).
    """

    def __init__(
        self,
        executor: Executor,
        submit_fn: Callable[..., dict[str, Any]],
        events: EventBuffer,
        max_rows: int,
    ) -> None:
        self.executor = executor
        self.pending: deque[PendingImage] = deque()  # added, not yet handed to the filter
        self.awaiting: dict[float, dict[str, Any]] = {}  # handed over, awaiting the verdict
        self.rows: deque[dict[str, Any]] = deque(maxlen=max_rows)  # with their verdict
        self.t_last = -math.inf  # time of the last image admitted
        self._submit_fn = submit_fn
        self._events = events

    def drain(self) -> pd.DataFrame:
        """The rows with their verdict (``MEASUREMENT_COLUMNS``), forgotten here."""
        rows = list(self.rows)
        self.rows.clear()
        return measurement_frame(rows)

    def skip(self, index: int, t: float, kind: str, detail: str) -> None:
        """An image not used: its event and its row."""
        self._events.add(t, kind, detail)
        self.rows.append({"t": t, "image": index, "ok": False, "reason": f"{kind}: {detail}",
                          "accepted": False, "update_reason": "skipped"})  # fmt: skip

    def admit(
        self,
        index: int,
        t: float,
        what: str,
        *,
        gap: tuple[float, float] | None,
        t_first: float | None,
        t_level_end: float,
        align_s: float,
        t_late: float,
        delay: float,
        t_latest: float,
    ) -> bool:
        """Whether image ``index`` (``what``: ``"image"`` or ``"measurement"``) at ``t``
        [s] can be used: after the last one admitted, not inside the IMU gap ``gap``, not
        before the first IMU sample ``t_first`` (None: none yet), after the end
        ``t_level_end`` of the levelling window (``align_s`` long), not before ``t_late`` (the filter's time or
        ``max_image_delay_s = delay`` before the newest sample ``t_latest``); else skipped
        with its reason (docs/faults.md)."""
        if not math.isfinite(t) or t <= self.t_last:
            self.skip(index, t, "image-out-of-order",
                      f"{what} time not after the previous one (t={self.t_last!r})")  # fmt: skip
        elif gap is not None:
            self.skip(index, t, EventKind.MEASUREMENT_IN_GAP, f"{what} skipped: {gap_reason(*gap)}")
        elif t_first is None or t < t_first:
            self.skip(index, t, "image-outside-imu", f"{what} before the first IMU sample")
        elif t <= t_level_end:
            self.skip(index, t, "image-during-alignment",
                      f"{what} inside the levelling window ({align_s} s)")  # fmt: skip
        elif t < t_late:
            self.skip(index, t, "image-late",
                      f"{what} more than max_image_delay_s={delay} s behind the newest IMU "
                      f"sample (t={t_latest:.6f})")  # fmt: skip
        else:
            self.t_last = t
            return True
        return False

    def skip_in_gaps(self, screen: ImuScreen) -> bool:
        """Skip the images (and external measurements) strictly inside an IMU gap of
        ``screen``, as every path does (docs/faults.md); True if one was."""
        if not screen.gaps:
            return False
        inside = [(img, screen.inside_gap(img.t)) for img in self.pending]
        skipped = [(img, gap) for img, gap in inside if gap is not None]
        for img, gap in skipped:
            self.pending.remove(img)
            what = "image" if img.row is None else "measurement"
            self.skip(img.index, img.t, EventKind.MEASUREMENT_IN_GAP,
                      f"{what} skipped: {gap_reason(*gap)}")  # fmt: skip
        return bool(skipped)

    def busy(self) -> int:
        """Images being measured."""
        return sum(1 for img in self.pending if img.future is not None and not img.resolved)

    def wait_oldest(self) -> None:
        """Wait for the oldest image being measured."""
        for img in self.pending:
            if img.future is not None and not img.resolved:
                img.future.result()
                return

    def submit(self, img: PendingImage, prior: PriorJob) -> None:
        """Measure ``img`` with its prior where the executor runs (the prior is propagated
        there, off the caller's thread)."""
        img.future = self.executor.submit(self._submit_fn, img.item, img.sun_n, prior)
        img.item = None  # the raw image is the worker's now

    def filter_row(
        self, img: PendingImage, config: FuseConfig, heading_check: GyroHeadingCheck
    ) -> dict[str, float] | None:
        """The measurement-table row of a measured image for the filter (None when it was
        not measured), with the sigmas ``config`` makes of the measured ones; the headings
        go to ``heading_check`` (``ImuUnitsError``: a gyro in deg/s). The image's row of
        the measurement log waits for the filter's verdict (:meth:`verdict`)."""
        if img.row is None:
            assert img.future is not None
            img.row = dict(img.future.result())
        row = img.row
        row.update(t=img.t, image=img.index)
        for c, v in zip("xyz", img.sun_n, strict=True):
            row[f"sun_n{c}"] = float(v)
        if row.get("event"):
            self._events.add(img.t, row["event"], row["reason"])
        report_noise_model(row, self._events, img.t)
        if not row.get("ok"):
            row.update(accepted=False, update_reason="not measured")
            self.rows.append(row)
            return None
        heading_check.add_headings(img.t, heading_proxy(row))
        cols: dict[str, float] = {"t": img.t}
        if "yaw" in row:
            cols.update(yaw=row["yaw"], yaw_std=float(config.yaw_sigma(row["yaw_std"])))
        if "sun_bx" in row:
            cols.update({f"sun_b{c}": row[f"sun_b{c}"] for c in "xyz"})
            cols["sun_std"] = float(config.sun_sigma(row["sun_std"]))
        else:
            cols.update(sun_bx=math.nan, sun_by=math.nan, sun_bz=math.nan)
        cols.update({f"sun_n{c}": row[f"sun_n{c}"] for c in "xyz"})
        if all(np.isfinite(row.get(c, np.nan)) for c in PRIOR_COLUMNS):
            cols.update({c: row[c] for c in PRIOR_COLUMNS})
        cols.update({c: float(row[c]) for c in SKY_COLUMNS if c in row})
        self.awaiting[img.t] = row
        return cols

    def verdict(self, rec: UpdateRecord) -> None:
        """The filter's verdict on a handed-over image's update (other records: nothing)."""
        row = self.awaiting.pop(rec.t, None) if rec.name in ("yaw", "sun") else None
        if row is None:
            return
        row.update(accepted=bool(rec.accepted), update_reason=rec.reason,
                   nis=rec.nis, nis_dof=rec.dim)  # fmt: skip
        if rec.name == "yaw" and rec.innovation:  # measured minus predicted yaw [rad]
            row["innovation"] = float(rec.innovation[0])
        self.rows.append(row)

    def close(self) -> None:
        """After the last IMU sample: the images still queued skipped, the rows handed
        over and never applied closed."""
        for img in list(self.pending):
            self.skip(img.index, img.t, "image-outside-imu", "image after the last IMU sample")
        self.pending.clear()
        for row in self.awaiting.values():
            row.update(accepted=False, update_reason="after the last IMU sample")
            self.rows.append(row)
        self.awaiting.clear()


__all__ = ["SKY_COLUMNS", "ImageQueue", "row_items"]
