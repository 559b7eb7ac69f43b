"""The summary of a fusion run: counts, rejections, NIS and, with a reference, accuracy and consistency."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd
from scipy.stats import chi2

from polins.evaluation.reference import (
    error_stats,
    measurement_residuals,
    solution_errors,
    truth_at,
)
from polins.frames import wrap_angle


def summarize(
    solution: pd.DataFrame,
    measurements: pd.DataFrame,
    events: pd.DataFrame,
    *,
    truth: pd.DataFrame | None = None,
    timing: Mapping[str, float] | None = None,
    settings: Mapping[str, Any] | None = None,
    settle_s: float = 0.0,
) -> dict[str, Any]:
    """The JSON summary (module docstring). Errors are in degrees.

    ``settle_s``: error statistics skip the first ``settle_s`` seconds of the solution
    (alignment transient); the whole run is reported too.
    """
    m = measurements
    ok = m["ok"].to_numpy(dtype=bool) if len(m) else np.zeros(0, bool)
    accepted = m["accepted"].to_numpy(dtype=bool) if "accepted" in m else ok
    reasons = m.loc[~ok, "reason"].value_counts().to_dict() if len(m) else {}
    gate = m.loc[ok & ~accepted, "update_reason"].value_counts().to_dict() if len(m) else {}
    summary: dict[str, Any] = {
        "images": {
            "total": len(m),
            "measured_ok": int(ok.sum()),
            "accepted_by_filter": int(accepted.sum()),
            "rejected_by_measurement": {str(k): int(v) for k, v in reasons.items()},
            "rejected_by_filter": {str(k): int(v) for k, v in gate.items()},
        },
        "imu_samples": len(solution),
        "events": {str(k): int(v) for k, v in events["kind"].value_counts().items()}
        if len(events)
        else {},
    }
    nis_ok = accepted & np.isfinite(m["nis"].to_numpy(dtype=float)) if "nis" in m else accepted
    if "nis" in m and nis_ok.any():  # the yaw alignment itself has no NIS
        nis = m.loc[nis_ok, "nis"].to_numpy(dtype=float)
        dof = (
            m.loc[nis_ok, "nis_dof"].to_numpy(dtype=float) if "nis_dof" in m else np.ones_like(nis)
        )
        n = nis.size
        summary["nis"] = {
            "mean": float(np.mean(nis)),
            "expected": float(np.mean(dof)),
            "band95_of_mean": [
                float(chi2.ppf(0.025, dof.sum()) / n),
                float(chi2.ppf(0.975, dof.sum()) / n),
            ],
            "n": int(n),
        }
    if timing:
        summary["timing"] = {k: float(v) for k, v in timing.items()}
        run = float(timing.get("run_s", 0.0))
        if run > 0:
            summary["timing"]["images_per_s"] = len(m) / run
            summary["timing"]["imu_samples_per_s"] = len(solution) / run
    if settings:
        summary["settings"] = dict(settings)
    if truth is not None and len(solution):
        err = solution_errors(solution, truth)
        keep = err["t"].to_numpy() >= err["t"].iloc[0] + settle_s
        acc: dict[str, Any] = {"settle_s": settle_s}
        for name in ("yaw", "roll", "pitch"):
            e = np.degrees(err[f"{name}_err"].to_numpy(dtype=float))
            s = (
                np.degrees(solution[f"{name}_std"].to_numpy(dtype=float))
                if f"{name}_std" in solution
                else None
            )
            label = "heading" if name == "yaw" else name
            acc[label] = error_stats(e[keep], None if s is None else s[keep])
            acc[f"{label}_whole_run"] = error_stats(e, s)
        if len(m) and ok.any():
            ref = truth_at(truth, m["t"].to_numpy(dtype=float))
            e = np.degrees(wrap_angle(m["yaw"].to_numpy(dtype=float) - ref["yaw"].to_numpy()))
            std = np.degrees(m["yaw_std"].to_numpy(dtype=float))
            acc["measurement_heading"] = error_stats(np.where(ok, e, np.nan), std)
            res = np.degrees(measurement_residuals(m, truth))
            acc["measurement_residual"] = error_stats(np.where(ok, res, np.nan), std)
        summary["accuracy_vs_reference"] = acc
    return summary


def format_summary(summary: Mapping[str, Any]) -> str:
    """A short human-readable table of a :func:`summarize` result."""
    im = summary["images"]
    lines = [
        f"images            {im['total']} total, {im['measured_ok']} measured, "
        f"{im['accepted_by_filter']} used by the filter",
    ]
    for k, v in {**im["rejected_by_measurement"], **im["rejected_by_filter"]}.items():
        lines.append(f"  rejected        {v:5d}  {k}")
    if summary.get("events"):
        ev = ", ".join(f"{k} {v}" for k, v in summary["events"].items())
        lines.append(f"events            {ev}")
    if "nis" in summary:
        n = summary["nis"]
        lo, hi = n["band95_of_mean"]
        lines.append(f"NIS mean          {n['mean']:.3f} (expected {n['expected']:.0f}, "
                     f"95% band of the mean {lo:.2f}..{hi:.2f})")  # fmt: skip
    acc = summary.get("accuracy_vs_reference")
    if acc:
        lines.append(f"vs reference      after the first {acc['settle_s']:g} s "
                     "[deg]: RMS / max / final (final 1-sigma), RMS(err/sigma), within 3 sigma")  # fmt: skip
        for name in ("heading", "roll", "pitch", "measurement_heading", "measurement_residual"):
            st = acc.get(name)
            if not st or st.get("rms_deg") is None:
                continue
            line = (
                f"  {name:<16}{st['rms_deg']:8.4f} {st['max_abs_deg']:8.4f} {st['final_deg']:+8.4f}"
            )
            if "rms_normalized" in st:
                line += (f" ({st['final_sigma_deg']:.4f})   {st['rms_normalized']:.2f}"
                         f"   {100 * st['within_3sigma']:.1f}%")  # fmt: skip
            lines.append(line)
    tm = summary.get("timing")
    if tm:
        lines.append(
            f"run time          {tm['run_s']:.2f} s ({tm.get('images_per_s', 0):.1f} images/s, "
            f"{tm.get('imu_samples_per_s', 0):.0f} IMU samples/s, {tm['workers']:.0f} workers)"
        )
    return "\n".join(lines)


__all__ = ["format_summary", "summarize"]
