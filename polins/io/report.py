"""Run report of ``polins fuse``: CSV tables, a JSON summary and plots for people.

Outputs (all written atomically into the output folder):

* ``solution.csv``: the fused solution (``polins.fuse`` columns, docs/conventions.md).
* ``measurements.csv``: one row per image: ``t, ok, reason, yaw, yaw_std, heading_deg,
  heading_std_deg, epsilon, n_pixels``, the sun vectors, the prior and the filter's verdict
  (``accepted, innovation, nis, update_reason``); with a reference also ``yaw_error``.
* ``events.csv``: skipped images and IMU samples, gaps (``t, kind, detail``).
* ``schema.json``: unit and meaning of every column of the CSV files (docs/outputs.md).
* ``summary.json``: counts, rejections by reason, timings, throughput, and, with a
  reference trajectory, RMS errors and their consistency with the reported sigmas.
* ``heading.png``, ``heading_error.png``, ``measurements.png``, ``epsilon.png``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray
from scipy.stats import chi2

from polins.frames import rot_nb_from_euler, wrap_angle
from polins.fusion.faults import reason_group
from polins.fusion.inputs import PRIOR_COLUMNS
from polins.fusion.items import item_model, items_from_table
from polins.io.atomic import atomic_path, write_text_atomic
from polins.io.schema import schema_for
from polins.io.tables import write_table

FloatArray = NDArray[np.float64]
CSV_FLOAT_FORMAT = "%.10g"  # 10 significant digits: 1e-10 relative, far below any sigma


def truth_at(truth: pd.DataFrame, t: FloatArray) -> pd.DataFrame:
    """Reference roll, pitch, yaw [rad] at times ``t`` (linear, yaw unwrapped); NaN outside."""
    tt = truth["t"].to_numpy(dtype=float)
    t = np.asarray(t, dtype=float)
    out = {"t": t}
    for name in ("roll", "pitch", "yaw"):
        v = truth[name].to_numpy(dtype=float)
        v = np.unwrap(v) if name == "yaw" else v
        val = np.interp(t, tt, v, left=np.nan, right=np.nan)
        out[name] = wrap_angle(val) if name == "yaw" else val
    return pd.DataFrame(out)


def measurement_residuals(measurements: pd.DataFrame, truth: pd.DataFrame) -> FloatArray:
    """The measured yaws' residuals at the reference attitude [rad], ``z - h(x_true, prior)``.

    With the attitude prior and the ENU sun of each image, the tilt-coupled yaw model
    (docs/measurement.md, tilt coupling) predicts what the image should have measured had
    the attitude been the reference; this residual is what ``yaw_std`` must cover. Rows
    without a yaw are NaN; without the prior or the sun, the residual is the plain error.
    """
    m = measurements
    t = m["t"].to_numpy(dtype=float)
    ref = truth_at(truth, t)
    out = np.full(t.size, np.nan)
    needed = ("yaw", "yaw_std", *PRIOR_COLUMNS, "sun_nx", "sun_ny", "sun_nz")
    rows = m[[c for c in ("t", *needed) if c in m.columns]]
    coupled = all(c in rows.columns for c in needed)
    items = items_from_table(rows, use_sun=False)
    for i, item in enumerate(items):
        if item.kind != "yaw" or not item.valid or not np.isfinite(ref["yaw"].iloc[i]):
            continue
        mat_nb = rot_nb_from_euler(
            ref["yaw"].iloc[i], ref["pitch"].iloc[i], ref["roll"].iloc[i]
        ).as_matrix()
        out[i] = item_model(item, mat_nb, None, coupled).residual[0]
    return out


def _stats(err: FloatArray, std: FloatArray | None = None) -> dict[str, float | None]:
    """RMS / max / final of an error [deg]; with sigmas also RMS(err/sigma) and 3-sigma share."""
    ok = np.isfinite(err)
    if std is not None:
        ok &= np.isfinite(std) & (std > 0)
    e = err[ok]
    if e.size == 0:
        return {"rms_deg": None, "max_abs_deg": None, "final_deg": None, "n": 0}
    out: dict[str, float | None] = {
        "rms_deg": float(np.sqrt(np.mean(e**2))),
        "mean_deg": float(np.mean(e)),
        "max_abs_deg": float(np.max(np.abs(e))),
        "final_deg": float(e[-1]),
        "n": int(e.size),
    }
    if std is not None:
        z = e / std[ok]
        out["final_sigma_deg"] = float(std[ok][-1])
        out["rms_normalized"] = float(np.sqrt(np.mean(z**2)))
        out["within_3sigma"] = float(np.mean(np.abs(z) <= 3.0))
    return out


def solution_errors(solution: pd.DataFrame, truth: pd.DataFrame) -> pd.DataFrame:
    """Solution minus reference: ``t, roll_err, pitch_err, yaw_err`` [rad] (yaw wrapped)."""
    ref = truth_at(truth, solution["t"].to_numpy(dtype=float))
    return pd.DataFrame(
        {
            "t": ref["t"],
            "roll_err": solution["roll"].to_numpy() - ref["roll"].to_numpy(),
            "pitch_err": solution["pitch"].to_numpy() - ref["pitch"].to_numpy(),
            "yaw_err": wrap_angle(solution["yaw"].to_numpy() - ref["yaw"].to_numpy()),
        }
    )


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
            acc[label] = _stats(e[keep], None if s is None else s[keep])
            acc[f"{label}_whole_run"] = _stats(e, s)
        if len(m) and ok.any():
            ref = truth_at(truth, m["t"].to_numpy(dtype=float))
            e = np.degrees(wrap_angle(m["yaw"].to_numpy(dtype=float) - ref["yaw"].to_numpy()))
            std = np.degrees(m["yaw_std"].to_numpy(dtype=float))
            acc["measurement_heading"] = _stats(np.where(ok, e, np.nan), std)
            res = np.degrees(measurement_residuals(m, truth))
            acc["measurement_residual"] = _stats(np.where(ok, res, np.nan), std)
        summary["accuracy_vs_reference"] = acc
    return summary


def heading_plot_series(
    solution: pd.DataFrame, measurements: pd.DataFrame, truth: pd.DataFrame | None = None
) -> dict[str, FloatArray]:
    """Headings [deg] of the heading plot, wrapped consistently with the fused line.

    The fused heading is unwrapped (continuous through 0/360 deg); the reference and the
    measurements are each moved by whole turns to within 180 deg of it, point by point,
    so no line jumps by 360 deg where one series wraps and the other does not.

    Returns
    -------
    dict
        ``fused`` (per solution row), ``ref`` (with a reference), ``mt, mh`` (times and
        headings of the measurements that are ok) and ``mh_fused`` (the fused heading there).
    """
    t = solution["t"].to_numpy(dtype=float)
    fused = np.degrees(np.unwrap(np.radians(solution["heading_deg"].to_numpy(dtype=float))))
    out: dict[str, FloatArray] = {"fused": fused}

    def near_fused(h: FloatArray, f: FloatArray) -> FloatArray:
        return h + 360.0 * np.round((f - h) / 360.0)

    if truth is not None:
        ref = np.mod(90.0 - np.degrees(truth_at(truth, t)["yaw"].to_numpy()), 360.0)
        out["ref"] = near_fused(ref, fused)
    m = measurements
    ok = m["ok"].to_numpy(dtype=bool) if len(m) else np.zeros(0, bool)
    tm = m.loc[ok, "t"].to_numpy(dtype=float)
    if len(t) and tm.size:
        at = np.interp(tm, t, fused)
        out["mt"] = tm
        out["mh"] = near_fused(m.loc[ok, "heading_deg"].to_numpy(dtype=float), at)
        out["mh_fused"] = at
    else:
        out["mt"] = out["mh"] = out["mh_fused"] = np.zeros(0)
    return out


def _legend(ax: Any) -> None:
    """A legend if the axes have labelled artists (an empty run has none)."""
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best", fontsize=8)


def _savefig(fig: Any, path: Path) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight")
    return path


def plot_report(
    folder: str | Path,
    solution: pd.DataFrame,
    measurements: pd.DataFrame,
    *,
    truth: pd.DataFrame | None = None,
    title: str = "",
) -> list[Path]:
    """Write the report's PNG plots; returns their paths."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    suffix = f" ({title})" if title else ""
    # rows before the yaw alignment have no heading
    solution = solution.loc[np.isfinite(solution["heading_deg"].to_numpy(dtype=float))]
    t = solution["t"].to_numpy(dtype=float)
    sigma3 = 3.0 * np.degrees(solution["yaw_std"].to_numpy(dtype=float))
    m = measurements
    ok = m["ok"].to_numpy(dtype=bool) if len(m) else np.zeros(0, bool)
    accepted = m["accepted"].to_numpy(dtype=bool) if "accepted" in m else ok
    paths = []

    # 1. heading vs time; below it, the measurements and the reference against the fused
    #    heading inside its 3-sigma band (a band of 0.1 deg is invisible on a 360 deg axis)
    series = heading_plot_series(solution, measurements, truth)
    fig, (ax, axr) = plt.subplots(2, 1, figsize=(9, 7), sharex=True,
                                  gridspec_kw={"height_ratios": (3, 2)})  # fmt: skip
    if len(series["mt"]):
        ax.plot(series["mt"], series["mh"], "o", ms=2.5, mew=0, alpha=0.6, color="C1",
                zorder=2, label="polarization measurements")  # fmt: skip
        axr.plot(series["mt"], series["mh"] - series["mh_fused"], "o", ms=2.5, mew=0,
                 alpha=0.6, color="C1", zorder=2, label="measurement − fused")  # fmt: skip
    if "ref" in series:
        ax.plot(t, series["ref"], "--", color="k", lw=1.0, zorder=3, label="reference")
        axr.plot(t, series["ref"] - series["fused"], "--", color="k", lw=1.0, zorder=3,
                 label="reference − fused")  # fmt: skip
    ax.fill_between(t, series["fused"] - sigma3, series["fused"] + sigma3, color="C0",
                    alpha=0.25, lw=0, zorder=1, label="fused ±3σ")  # fmt: skip
    ax.plot(t, series["fused"], color="C0", lw=1.6, zorder=4, label="fused heading")
    axr.fill_between(t, -sigma3, sigma3, color="C0", alpha=0.25, lw=0, zorder=1,
                     label="fused ±3σ")  # fmt: skip
    axr.axhline(0.0, color="C0", lw=1.2, zorder=4)
    if len(t):
        after = sigma3[t >= t[0] + 0.2 * (t[-1] - t[0])]
        span = [3.0 * float(np.nanmax(after))] if after.size and np.isfinite(after).any() else []
        resid = series["mh"] - series["mh_fused"]
        if np.isfinite(resid).any():
            span.append(1.2 * float(np.nanpercentile(np.abs(resid), 98)))
        if span and max(span) > 0:
            axr.set_ylim(-max(span), max(span))
    ax.set_ylabel("heading [deg, clockwise from North]")
    ax.set_title(f"Heading vs time{suffix}")
    _legend(ax)
    ax.grid(alpha=0.3)
    axr.set_xlabel("time t [s]")
    axr.set_ylabel("minus the fused heading [deg]")
    axr.set_title("Measurements and reference relative to the fused heading, in its 3σ band")
    _legend(axr)
    axr.grid(alpha=0.3)
    paths.append(_savefig(fig, folder / "heading.png"))
    plt.close(fig)

    # 2. heading error vs the reference
    fig, ax = plt.subplots(figsize=(9, 4.5))
    if truth is not None:
        err = solution_errors(solution, truth)
        e = np.degrees(err["yaw_err"].to_numpy(dtype=float))
        ax.fill_between(t, -sigma3, sigma3, color="C0", alpha=0.25, label="±3σ (reported)")
        ax.plot(t, e, color="C3", lw=1.0, label="fused heading error")
        ax.set_title(f"Heading error vs the reference{suffix}")
    else:
        ax.plot(t, sigma3 / 3.0, color="C0", label="reported 1σ")
        ax.set_title(f"Heading 1σ (no reference trajectory in the log){suffix}")
    ax.set_xlabel("time t [s]")
    ax.set_ylabel("heading error [deg]")
    _legend(ax)
    ax.grid(alpha=0.3)
    paths.append(_savefig(fig, folder / "heading_error.png"))
    plt.close(fig)

    # 3. per-image measurement error and innovations / NIS
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(9, 7), sharex=True)
    if ok.any():
        tm = m.loc[ok, "t"].to_numpy(dtype=float)
        s3 = 3.0 * np.degrees(m.loc[ok, "yaw_std"].to_numpy(dtype=float))
        if truth is not None:
            ref = truth_at(truth, tm)
            e = np.degrees(
                wrap_angle(m.loc[ok, "yaw"].to_numpy(dtype=float) - ref["yaw"].to_numpy())
            )
            ax1.plot(tm, e, ".", ms=3, color="C1", label="measurement − reference")
            ax1.set_title(f"Per-image measurement error{suffix}")
        else:
            e = np.degrees(m.loc[ok, "innovation"].to_numpy(dtype=float))
            ax1.plot(tm, e, ".", ms=3, color="C1", label="innovation (measurement − prediction)")
            ax1.set_title(f"Per-image innovation{suffix}")
        ax1.plot(tm, s3, color="C0", lw=0.8, label="±3σ (measurement)")
        ax1.plot(tm, -s3, color="C0", lw=0.8)
    ax1.set_ylabel("heading error [deg]")
    _legend(ax1)
    ax1.grid(alpha=0.3)
    if "nis" in m and accepted.any():
        ta = m.loc[accepted, "t"].to_numpy(dtype=float)
        nis = m.loc[accepted, "nis"].to_numpy(dtype=float)
        dof = int(np.median(m.loc[accepted, "nis_dof"])) if "nis_dof" in m else 1
        ax2.semilogy(ta, np.maximum(nis, 1e-6), ".", ms=3, color="C2", label="NIS (accepted)")
        rej = ok & ~accepted
        if rej.any():
            tr = m.loc[rej, "t"].to_numpy(dtype=float)
            nr = m.loc[rej, "nis"].to_numpy(dtype=float)
            ax2.semilogy(tr, np.maximum(nr, 1e-6), "x", color="C3", label="NIS (gated out)")
        ax2.axhline(chi2.ppf(0.95, dof), color="k", ls="--", lw=0.8, label=f"χ²({dof}) 95%")
        ax2.axhline(dof, color="k", ls=":", lw=0.8, label=f"expected mean {dof}")
    ax2.set_xlabel("time t [s]")
    ax2.set_ylabel("NIS [-]")
    ax2.set_title("Normalized innovation squared of the filter updates")
    _legend(ax2)
    ax2.grid(alpha=0.3)
    paths.append(_savefig(fig, folder / "measurements.png"))
    plt.close(fig)

    # 4. epsilon over time
    fig, ax = plt.subplots(figsize=(9, 4))
    if ok.any() and "epsilon" in m:
        tm = m.loc[ok, "t"].to_numpy(dtype=float)
        eps = m.loc[ok, "epsilon"].to_numpy(dtype=float)
        ax.plot(tm, eps, ".-", ms=3, lw=0.6, color="C4", label="estimated ε")
        if "epsilon_std" in m:
            es = m.loc[ok, "epsilon_std"].to_numpy(dtype=float)
            if np.isfinite(es).any():
                ax.fill_between(tm, eps - 3 * es, eps + 3 * es, color="C4", alpha=0.2, label="±3σ")
    ax.set_xlabel("time t [s]")
    ax.set_ylabel("direct-sunlight coefficient ε [-]")
    ax.set_title(f"Estimated direct-sunlight coefficient ε per image{suffix}")
    _legend(ax)
    ax.grid(alpha=0.3)
    paths.append(_savefig(fig, folder / "epsilon.png"))
    plt.close(fig)
    return paths


def _json_default(v: Any) -> Any:
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    return str(v)


def write_report(
    folder: str | Path,
    solution: pd.DataFrame,
    measurements: pd.DataFrame,
    events: pd.DataFrame,
    summary: Mapping[str, Any],
    *,
    truth: pd.DataFrame | None = None,
    plots: bool = True,
    title: str = "",
) -> dict[str, Path]:
    """Write CSVs (floats ``%.10g``), ``summary.json``, ``schema.json`` (unit and meaning of
    every column, :mod:`polins.io.schema`) and (optionally) the plots; returns name -> path."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    meas = measurements.copy()
    if truth is not None and len(meas):
        ref = truth_at(truth, meas["t"].to_numpy(dtype=float))
        meas["yaw_error"] = wrap_angle(meas["yaw"].to_numpy(dtype=float) - ref["yaw"].to_numpy())
    tables = {"solution.csv": solution, "measurements.csv": meas, "events.csv": events}
    out = {
        name.removesuffix(".csv"): write_table(folder / name, df, float_format=CSV_FLOAT_FORMAT)
        for name, df in tables.items()
    }
    out["summary"] = write_text_atomic(
        folder / "summary.json", json.dumps(summary, indent=2, default=_json_default) + "\n"
    )
    out["schema"] = write_text_atomic(
        folder / "schema.json", json.dumps(schema_for(tables), indent=2) + "\n"
    )
    if plots:
        for p in plot_report(folder, solution, measurements, truth=truth, title=title):
            out[p.stem] = p
    return out


def format_summary(summary: Mapping[str, Any]) -> str:
    """A short human-readable table of a :func:`summarize` result."""
    im = summary["images"]
    lines = [
        f"images            {im['total']} total, {im['measured_ok']} measured, "
        f"{im['accepted_by_filter']} used by the filter",
    ]
    rejected = sorted({**im["rejected_by_measurement"], **im["rejected_by_filter"]}.items(),
                      key=lambda kv: -kv[1])  # fmt: skip
    for k, v in rejected[:8]:
        lines.append(f"  rejected        {v:5d}  {k}")
    if len(rejected) > 8:
        rest = sum(v for _, v in rejected[8:])
        lines.append(f"  rejected        {rest:5d}  for {len(rejected) - 8} other reasons "
                     "(measurements.csv, events.csv)")  # fmt: skip
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


__all__ = [
    "CSV_FLOAT_FORMAT",
    "format_summary",
    "heading_plot_series",
    "measurement_residuals",
    "plot_report",
    "solution_errors",
    "summarize",
    "truth_at",
    "write_report",
]
