"""Plots of a fusion run for people: heading, heading error, measurements and NIS, epsilon."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray
from scipy.stats import chi2

from polins.evaluation.reference import solution_errors, truth_at
from polins.frames import wrap_angle
from polins.io.atomic import atomic_path

FloatArray = NDArray[np.float64]


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


def _compass(heading_deg: FloatArray) -> FloatArray:
    """A continuous heading [deg] shown in 0..360: wrapped, NaN where it crosses North
    (so no line runs across the axis)."""
    wrapped = np.mod(np.asarray(heading_deg, dtype=float), 360.0)
    jump = np.flatnonzero(np.abs(np.diff(wrapped)) > 180.0)
    wrapped[jump] = np.nan
    return wrapped


def _residual_scale(ax: Any, t: FloatArray, sigma3: FloatArray, resid: FloatArray) -> None:
    """The residual panel's y axis: the whole 3-sigma band and the residuals in view.

    Linear within the settled 3-sigma (the median over the last 80 % of the run) and
    logarithmic beyond it (``symlog``), so the wide band after the yaw acquisition and the
    settled band of a tenth of a degree are both readable.
    """
    settled = sigma3[t >= t[0] + 0.2 * (t[-1] - t[0])]
    settled = settled[np.isfinite(settled) & (settled > 0)]
    finite = np.isfinite(sigma3)
    span = [float(np.max(sigma3[finite]))] if finite.any() else []
    if np.isfinite(resid).any():
        span.append(1.2 * float(np.nanmax(np.abs(resid))))
    if not span or max(span) <= 0:
        return
    top = 1.05 * max(span)
    if settled.size and top > 3.0 * float(np.median(settled)):
        ax.set_yscale("symlog", linthresh=float(np.median(settled)))
    ax.set_ylim(-top, top)


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
        ax.plot(series["mt"], _compass(series["mh"]), "o", ms=2.5, mew=0, alpha=0.6,
                color="C1", zorder=2, label="polarization measurements")  # fmt: skip
        axr.plot(series["mt"], series["mh"] - series["mh_fused"], "o", ms=2.5, mew=0,
                 alpha=0.6, color="C1", zorder=2, label="measurement − fused")  # fmt: skip
    if "ref" in series:
        ax.plot(t, _compass(series["ref"]), "--", color="k", lw=1.0, zorder=3,
                label="reference")  # fmt: skip
        axr.plot(t, series["ref"] - series["fused"], "--", color="k", lw=1.0, zorder=3,
                 label="reference − fused")  # fmt: skip
    shown = _compass(series["fused"])
    ax.fill_between(t, shown - sigma3, shown + sigma3, color="C0", alpha=0.25, lw=0, zorder=1,
                    label="fused ±3σ")  # fmt: skip
    ax.plot(t, shown, color="C0", lw=1.6, zorder=4, label="fused heading")
    ax.set_ylim(0.0, 360.0)
    ax.set_yticks(np.arange(0.0, 361.0, 45.0))
    axr.fill_between(t, -sigma3, sigma3, color="C0", alpha=0.25, lw=0, zorder=1,
                     label="fused ±3σ")  # fmt: skip
    axr.axhline(0.0, color="C0", lw=1.2, zorder=4)
    if len(t):
        _residual_scale(axr, t, sigma3, series["mh"] - series["mh_fused"])
    ax.set_ylabel("heading [deg, clockwise from North, 0..360]")
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


__all__ = ["heading_plot_series", "plot_report"]
