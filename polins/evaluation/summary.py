"""The summary of a fusion run: counts, rejections, NIS and, with a reference, accuracy and consistency."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from polins.evaluation.reference import (
    error_stats,
    measurement_residuals,
    solution_errors,
    truth_at,
)
from polins.frames import wrap_angle
from polins.fusion.config import FuseConfig
from polins.fusion.faults import reason_group
from polins.tuning.innovations import (
    effective_samples,
    innovation_stats,
    likely_cause,
    nis_mean_band,
    nis_verdict,
)

GATE_PROB = FuseConfig().gate_probability  # the default gate of the filters
_IMAGE_KINDS = {1: "yaw", 2: "sun"}  # nis_dof of an image's update


def nis_summary(
    measurements: pd.DataFrame,
    accepted: NDArray[np.bool_],
    *,
    gate_prob: float | None = GATE_PROB,
    updates: pd.DataFrame | None = None,
    prob: float = 0.95,
) -> dict[str, dict[str, Any]]:
    """Mean NIS per measurement kind with its band and verdict (docs/outputs.md).

    Each kind's band is that of its effective number of independent updates
    (:func:`polins.tuning.innovations.effective_samples`) and of the gate's truncation
    (:func:`polins.tuning.innovations.nis_mean_band`); the verdict is consistent,
    conservative or optimistic, with the likely cause.
    """
    out: dict[str, dict[str, Any]] = {}
    if updates is not None and "innovation" in updates.columns:
        for kind, st in innovation_stats(updates, prob=prob, gate_prob=gate_prob).items():
            out[kind] = _nis_entry(st.nis_mean, st.nis_expected, st.nis_band, st.n, st.n_eff,
                                   st.verdict, st.cause)  # fmt: skip
        return out
    if "nis" not in measurements:
        return out
    m = measurements
    ok = accepted & np.isfinite(m["nis"].to_numpy(dtype=float))  # the acquisition has none
    dof = m["nis_dof"].to_numpy(dtype=float) if "nis_dof" in m else np.ones(len(m))
    for d, kind in _IMAGE_KINDS.items():
        rows = ok & (dof == d)
        if not rows.any():
            continue
        nis = m.loc[rows, "nis"].to_numpy(dtype=float)
        n_eff = effective_samples(nis, prob=prob)
        expected, band = nis_mean_band(d, n_eff, prob=prob, gate_prob=gate_prob)
        verdict = nis_verdict(float(np.mean(nis)), band)
        out[kind] = _nis_entry(float(np.mean(nis)), expected, band, nis.size, n_eff, verdict,
                               likely_cause(kind, verdict))  # fmt: skip
    return out


def _nis_entry(
    mean: float,
    expected: float,
    band: tuple[float, float],
    n: int,
    n_eff: float,
    verdict: str,
    cause: str,
) -> dict[str, Any]:
    return {"mean": mean, "expected": expected, "band95_of_mean": list(band), "n": int(n),
            "n_eff": n_eff, "verdict": verdict, "likely_cause": cause}  # fmt: skip


def summarize(
    solution: pd.DataFrame,
    measurements: pd.DataFrame,
    events: pd.DataFrame,
    *,
    truth: pd.DataFrame | None = None,
    timing: Mapping[str, float] | None = None,
    settings: Mapping[str, Any] | None = None,
    settle_s: float = 0.0,
    gate_prob: float | None = GATE_PROB,
    updates: pd.DataFrame | None = None,
) -> dict[str, Any]:
    """The JSON summary (module docstring). Errors are in degrees.

    ``settle_s``: error statistics skip the first ``settle_s`` seconds of the solution
    (alignment transient); the whole run is reported too. ``gate_prob``: the run's
    chi-square gate (None: none), which lowers the accepted updates' expected NIS.
    ``updates``: the filter's update log (``FusionResult.updates``), for the NIS of every
    measurement kind; without it, the images' NIS from ``measurements``.
    """
    m = measurements
    ok = m["ok"].to_numpy(dtype=bool) if len(m) else np.zeros(0, bool)
    accepted = m["accepted"].to_numpy(dtype=bool) if "accepted" in m else ok
    # grouped by reason (polins.fusion.faults.reason_group); each row's in measurements.csv
    reasons = m.loc[~ok, "reason"].map(reason_group).value_counts().to_dict() if len(m) else {}
    gate = (m.loc[ok & ~accepted, "update_reason"].map(reason_group).value_counts().to_dict()
            if len(m) else {})  # fmt: skip
    summary: dict[str, Any] = {
        "images": {
            "total": len(m),
            "measured_ok": int(ok.sum()),
            "accepted_by_filter": int(accepted.sum()),
            "rejected_by_measurement": {str(k): int(v) for k, v in reasons.items()},
            "rejected_by_filter": {str(k): int(v) for k, v in gate.items()},
        },
        # the IMU samples filtered (the timing's count), else the solution rows
        "imu_samples": int(timing["imu_samples"])
        if timing and "imu_samples" in timing
        else len(solution),
        "events": {str(k): int(v) for k, v in events["kind"].value_counts().items()}
        if len(events)
        else {},
    }
    nis = nis_summary(m, accepted, gate_prob=gate_prob, updates=updates)
    if nis:
        summary["nis"] = nis
    if timing:
        summary["timing"] = {k: float(v) for k, v in timing.items()}
        run = float(timing.get("run_s", 0.0))
        if run > 0:
            summary["timing"]["images_per_s"] = len(m) / run
            summary["timing"]["imu_samples_per_s"] = summary["imu_samples"] / run
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
            raw = error_stats(np.where(ok, e, np.nan), std)
            for key in ("verdict", "rms_normalized_band", "n_eff"):  # yaw_std covers the
                raw.pop(key, None)  # residual below, not the raw tilt-coupled error
            acc["measurement_heading"] = raw
            res = np.degrees(measurement_residuals(m, truth))
            acc["measurement_residual"] = error_stats(np.where(ok, res, np.nan), std)
        summary["accuracy_vs_reference"] = acc
    return summary


def rejection_lines(images: Mapping[str, Any], most: int = 8) -> list[str]:
    """The rejected images by reason group, largest first: at most ``most`` lines and one
    for the other reasons (every row is in measurements.csv and events.csv)."""
    rejected = sorted({**images["rejected_by_measurement"], **images["rejected_by_filter"]}.items(),
                      key=lambda kv: -kv[1])  # fmt: skip
    lines = [f"  rejected        {v:5d}  {k}" for k, v in rejected[:most]]
    if len(rejected) > most:
        rest = sum(v for _, v in rejected[most:])
        lines.append(f"  rejected        {rest:5d}  for {len(rejected) - most} other reasons "
                     "(measurements.csv, events.csv)")  # fmt: skip
    return lines


def format_summary(summary: Mapping[str, Any]) -> str:
    """A short human-readable table of a :func:`summarize` result."""
    im = summary["images"]
    lines = [
        f"images            {im['total']} total, {im['measured_ok']} measured, "
        f"{im['accepted_by_filter']} used by the filter",
    ]
    lines += rejection_lines(im)
    if summary.get("events"):
        ev = ", ".join(f"{k} {v}" for k, v in summary["events"].items())
        lines.append(f"events            {ev}")
    backend = summary.get("settings", {}).get("backend", "eskf")
    if backend == "graph" and summary.get("nis"):
        lines.append("from the navigation loop's ESKF (it gave the images their priors and "
                     "verdicts): the NIS below; from the graph: the solution vs the reference")  # fmt: skip
    for kind, n in summary.get("nis", {}).items():
        lo, hi = n["band95_of_mean"]
        lines.append(f"NIS {kind:<13} {n['mean']:.3g} (expected {n['expected']:.3g}, 95% band "
                     f"{lo:.3g}..{hi:.3g} from {n['n_eff']:.0f} independent of {n['n']}): "
                     f"{n['verdict']}")  # fmt: skip
        if n.get("likely_cause"):
            lines.append(f"  likely cause    {n['likely_cause']}")
    acc = summary.get("accuracy_vs_reference")
    if acc:
        solver = summary.get("settings", {}).get("solver")
        source = f"{backend} {solver}" if backend == "graph" and solver else backend
        lines.append(f"vs reference      {source} solution, after the first {acc['settle_s']:g} s "
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
                if "verdict" in st:
                    lo, hi = st["rms_normalized_band"]
                    line += f"   {_word(st['verdict'])} (band {lo:.2f}..{hi:.2f})"
                else:
                    line += "   (tilt-coupled: yaw_std covers the residual below)"
            lines.append(line)
            cause = sigma_cause(name, st.get("verdict", ""))
            if cause:
                lines.append(f"    likely cause  {cause}")
    tm = summary.get("timing")
    if tm:
        lines.append(
            f"run time          {tm['run_s']:.2f} s ({tm.get('images_per_s', 0):.1f} images/s, "
            f"{tm.get('imu_samples_per_s', 0):.0f} IMU samples/s, {tm['workers']:.0f} workers)"
        )
    return "\n".join(lines)


def _word(verdict: str) -> str:
    return verdict.split(":")[0]


def sigma_cause(name: str, verdict: str) -> str:
    """The likely cause of an RMS(err/sigma) outside its band, for a row of the summary."""
    side = _word(verdict)
    if side not in ("optimistic", "conservative"):
        return ""
    if name.startswith("measurement"):
        return ("yaw_std is smaller than the images' errors (a sky or camera the sigma model "
                "lacks)" if side == "optimistic" else "yaw_std is larger than the images' "
                "errors")  # fmt: skip
    if side == "optimistic":
        return (
            "the filter's sigma is too small: the IMU model's noise is below this "
            "vehicle's (vibration, no velocity aiding) or the images' sigma is too small"
        )
    return "the filter's sigma is larger than its errors: IMU or image noise set too high"


__all__ = ["format_summary", "nis_summary", "sigma_cause", "summarize"]
