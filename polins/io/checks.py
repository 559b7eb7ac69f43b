"""Checks of a log around a run: its time base and bit depth before, the verdict after.

The fault policy of docs/faults.md: a run that produced nothing usable (no image measured,
more failed images than allowed, no measurement accepted by the filter) says so in one line
(:func:`run_verdict`), with the likely cause when the time bases of the IMU and the images
do not match (:func:`time_base_hint`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from polins.fusion.faults import nis_verdict
from polins.io.images import ImageReadError, bit_depth_warning, load_raw
from polins.io.log import Log

FloatArray = NDArray[np.float64]


def time_base_hint(t_imu: FloatArray, t_images: FloatArray) -> str | None:
    """A hint when the image times do not fall inside the IMU's time span, else None.

    Names the likely cause: one stream in Unix seconds (or nanoseconds) while the other
    counts seconds from the manifest's ``epoch_utc``.
    """
    ti = np.asarray(t_imu, dtype=float)
    tc = np.asarray(t_images, dtype=float)
    ti, tc = ti[np.isfinite(ti)], tc[np.isfinite(tc)]
    if not ti.size or not tc.size:
        return None
    lo, hi = float(ti.min()), float(ti.max())
    inside = float(np.mean((tc >= lo) & (tc <= hi)))
    if inside > 0.5:
        return None

    def kind(t: FloatArray) -> str | None:
        big = float(np.median(np.abs(t)))
        return "Unix nanoseconds" if big > 1e17 else "Unix seconds" if big > 1e8 else None

    spans = (f"IMU {lo:.10g}..{hi:.10g} s, images {float(tc.min()):.10g}..{float(tc.max()):.10g}"
             f" s; {100 * (1 - inside):.0f}% of the images lie outside the IMU's span")  # fmt: skip
    for name, t, other in (("IMU", ti, tc), ("image", tc, ti)):
        if kind(t) and not kind(other):
            return (f"time base mismatch: the {name} times look like {kind(t)} while the "
                    f"others count seconds from the manifest's epoch_utc ({spans}); subtract "
                    f"the epoch from the {name} times")  # fmt: skip
    return (f"the image times do not fall inside the IMU's time span ({spans}); both must count "
            "seconds from the manifest's epoch_utc")  # fmt: skip


def run_verdict(
    summary: Mapping[str, Any],
    events: pd.DataFrame,
    max_image_failures: float,
    *,
    t_imu: FloatArray | None = None,
    t_images: FloatArray | None = None,
    measurements: pd.DataFrame | None = None,
) -> str | None:
    """One line saying why a run produced nothing usable (docs/faults.md), or None if it did.

    Nothing usable: no image, fewer images measured than ``max_image_failures`` (a share of
    the images, 0..1) allows, or none accepted by the filter. With the measurement table
    (``nis, nis_dof``), a run whose NIS is far outside any plausible band is not a result
    either (:func:`polins.fusion.faults.nis_verdict`). With the IMU and image times, a
    time-base hint is added (:func:`time_base_hint`).
    """
    im = summary["images"]
    outside = int((events["kind"] == "path-outside-log").sum()) if len(events) else 0
    total = int(im["total"]) + outside
    measured = int(im["measured_ok"])
    failed = total - measured
    reasons = {str(k).split(":")[0]: int(v) for k, v in im["rejected_by_measurement"].items()}
    if outside:
        reasons["path-outside-log"] = outside
    top = ", ".join(f"{k} {v}" for k, v in sorted(reasons.items(), key=lambda kv: -kv[1])[:3])
    hint = None
    if t_imu is not None and t_images is not None:
        hint = time_base_hint(t_imu, t_images)
    if total == 0:
        line = "nothing usable: the log has no image"
    elif measured == 0 or failed > max_image_failures * total:
        line = (f"nothing usable: {measured} of {total} images measured, {failed} failed "
                f"(more than the {100 * max_image_failures:g}% allowed by --max-image-failures)"
                + (f": {top}" if top else ""))  # fmt: skip
    elif not im["accepted_by_filter"]:
        line = f"nothing usable: none of the {measured} measured images was accepted by the filter"
    elif measurements is not None and "nis" in measurements and "nis_dof" in measurements:
        nis_line = nis_verdict(measurements["nis"], measurements["nis_dof"])
        if nis_line is None:
            return None
        line = nis_line
    else:
        return None
    return f"{line}; {hint}" if hint else line


def preflight_warnings(log: Log) -> list[str]:
    """Cheap checks of a log before a run: its time base and bit depth (warnings, not errors).

    Returns one line per problem: the image times outside the IMU's span
    (:func:`time_base_hint`), the first readable image's values above the camera's bit
    depth (:func:`polins.io.images.bit_depth_warning`).
    """
    notes = []
    t_imu = log.imu["t"].to_numpy(dtype=float)
    hint = time_base_hint(t_imu, np.asarray(log.images.t, dtype=float))
    if hint:
        notes.append(hint)
    for _, item in log.images:  # the first readable image
        try:
            raw = load_raw(item, shape=log.camera.shape)
        except ImageReadError:
            continue
        note = bit_depth_warning(raw, log.camera.bit_depth, str(item))
        if note:
            notes.append(note)
        break
    return notes


__all__ = ["preflight_warnings", "run_verdict", "time_base_hint"]
