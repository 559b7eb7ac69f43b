"""``polins demo``: the paper's Section 4.1 reproduction as a table, its explanation and figures.

:func:`run_demo` runs the reproduction of :mod:`polins.sim.reproduction` (the paper's
setup, and its world-fixed-occluder variant), prints :func:`format_table` beside the
paper's reported 0.5928 deg ("traditional") and 0.0240 deg ("proposed") and the
Cramer-Rao bound, and :func:`explain` states, with the measured numbers, why the paper's
pattern appears (docs/errata.md §0.3 and §3): the paper's traditional baseline skipped
the beta_k gain calibration, which its Algorithm 1 applies, and the Algorithm-1
compensation itself is inert (the scale-consistent Eq. 22 numerator is identically zero
without noise) or destructive (Eq. 22 as printed). Each verdict of the explanation is
decided by the numbers it quotes.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from polins.sim.reproduction import (
    ESTIMATORS,
    PAPER_PROPOSED_RMSE_DEG,
    PAPER_TRADITIONAL_RMSE_DEG,
    Reproduction,
    gain_pseudo_polarization,
    paper_scenarios,
    run_scenario,
    scenario_camera,
)

__all__ = ["PLOTTED", "explain", "format_table", "plot_reproduction", "run_demo"]


def format_table(repro: Reproduction, *, title: str | None = None) -> str:
    """The summary as a fixed-width text table with the paper's numbers and the CRLB."""
    sc = repro.scenario
    s = repro.summary
    lines = [
        title or f"{sc.name}",
        f"  sun azimuth {repro.sun_azimuth_deg:.2f} deg, zenith {repro.sun_zenith_deg:.2f} deg "
        f"(Harbin {sc.start}); {sc.n_images} images, {sc.turn_deg:.0f} deg in "
        f"{sc.duration_s:.0f} s; camera 1/{sc.downscale} resolution, "
        f"{repro.n_pixels} valid superpixels; d_max {sc.dop_max}, I_in {sc.radiance:g} DN, "
        f"epsilon {sc.epsilon}, sigma {sc.noise_std} DN"
        + (f"; {len(sc.occluders)} world-fixed occluder(s)" if sc.occluders else ""),
        "",
        "  heading error = measured - true compass heading; ms = median time of polins.measure",
        "",
        f"  {'estimator':<47} {'RMSE':>9} {'mean':>9} {'max|e|':>9} {'ok':>7}  {'ms':>6}  role",
        f"  {'':<47} {'[deg]':>9} {'[deg]':>9} {'[deg]':>9} {'':>7}  {'':>6}",
    ]
    for _, r in s.iterrows():
        lines.append(
            f"  {r['estimator']:<47} {_fmt(r['rmse_deg'])} {_fmt(r['mean_deg'], signed=True)} "
            f"{_fmt(r['max_abs_deg'])} {r['n_ok']:>3}/{r['n']:<3}  "
            f"{repro.timings_ms.get(r['key'], np.nan):6.1f}  {r['paper_role']}"
        )
    lines += [
        f"  {'Cramer-Rao bound (this resolution)':<47} {_fmt(repro.crlb_deg)}",
        f"  {'paper, reported: traditional / proposed':<47} "
        f"{PAPER_TRADITIONAL_RMSE_DEG:9.4f} / {PAPER_PROPOSED_RMSE_DEG:.4f}",
        f"  (render {repro.render_ms:.0f} ms per image)",
    ]
    return "\n".join(lines)


def _fmt(x: float, signed: bool = False) -> str:
    if not np.isfinite(x):
        return f"{'nan':>9}"
    if abs(x) >= 1.0:
        return f"{x:+9.2f}" if signed else f"{x:9.2f}"
    return f"{x:+9.4f}" if signed else f"{x:9.4f}"


def explain(paper: Reproduction, occluder: Reproduction | None = None) -> str:
    """Why the paper reports 0.5928 vs 0.0240 deg, stated with the measured numbers.

    Every number quoted is read from the reproductions, and every verdict is decided by
    them: which traditional row the paper's baseline matches, whether Algorithm 1's
    compensation adds noise or removes error, and whether the joint estimate alone removes
    the occluder's sunlight bias.
    """
    cam = scenario_camera(paper.scenario)
    f = paper.scenario.downscale
    rmse = paper.rmse_deg
    nogain, trad, alg1 = rmse("trad_nogain"), rmse("trad"), rmse("paper")
    nogain_matches = abs(nogain - PAPER_TRADITIONAL_RMSE_DEG) < abs(
        trad - PAPER_TRADITIONAL_RMSE_DEG
    )
    if nogain_matches:
        first = (
            f"  1. The paper's 'traditional' baseline matches traditional WITHOUT the beta_k "
            f"gain calibration: {nogain:.3f} deg here (paper 0.5928; 0.57 at d_max = 0.4)."
        )
    else:
        first = (
            f"  1. The paper's 'traditional' baseline does not match traditional without the "
            f"beta_k gain calibration: {nogain:.3f} deg here (paper 0.5928)."
        )
    ratio = alg1 / max(trad, 1e-12)
    if ratio > 1.0:
        compensation = (
            "its compensation is inert: the scale-consistent Eq. 22 numerator is identically "
            "zero without noise, so k_m is pure noise and only adds noise"
        )
    else:
        compensation = "its compensation reduces the error"
    if nogain_matches and trad <= alg1:
        verdict = "measures the gain calibration, not the sunlight compensation."
    else:
        verdict = "is not explained by the gain calibration alone."
    lines = [
        "What the table shows (docs/errata.md §0 and §3):",
        f"{first} Uncorrected gains add a camera-fixed pseudo-polarization of "
        f"{100 * gain_pseudo_polarization(cam):.2f}% of S0; its heading error changes with the "
        "turntable angle and does not average out. It is independent of resolution and of "
        "the direct sunlight.",
        f"  2. With the gains corrected, the same traditional estimator reaches "
        f"{trad:.4f} deg (p^2-weighted {rmse('trad_weighted'):.4f}): in "
        "this level geometry, symmetric about the solar meridian, the sunlight term can only "
        "bias the sun elevation, not the heading.",
        f"  3. The paper's 'proposed' Algorithm 1 divides by beta_k (step 2); {compensation}: "
        f"{alg1:.4f} deg (paper 0.0240; {ratio:.1f}x the gain-corrected traditional). "
        "Applied to the raw intensities as Eq. 23 literally says, beta never reaches the AoP: "
        f"{rmse('paper_raw'):.3f} deg. Eq. 22 as printed gives k_m ~ 150 and "
        f"{rmse('paper_printed'):.0f} deg.",
        f"  4. So 0.5928 -> 0.0240 deg {verdict} The joint ML estimate ('compensated') "
        f"reaches {rmse('compensated'):.4f} deg against a Cramer-Rao bound of "
        f"{paper.crlb_deg:.4f} deg.",
    ]
    if f > 1:
        lines.append(
            f"     (1/{f} resolution: noise-limited rows and the bound are about {f}x the "
            "full-resolution values, docs/errata.md §3: 0.0041 / 0.026 / 0.0015 / CRLB "
            "0.0014 deg; `polins demo --full` for full resolution.)"
        )
    if occluder is not None:
        bias = occluder.mean_deg
        others = [abs(bias(k)) for k in ("trad", "paper") if np.isfinite(bias(k))]
        handled = bool(others) and abs(bias("compensated")) < 0.25 * min(others)
        ending = (
            "this is the case the paper's compensation was meant for, and only the joint "
            "estimate of sun and epsilon handles it."
            if handled
            else "here the joint estimate does not remove the sunlight bias either."
        )
        lines.append(
            f"  5. A world-fixed occluder (azimuth 260-350 deg, elevation < 40 deg) breaks "
            f"the symmetry: now the sunlight term biases the gain-corrected traditional "
            f"heading by {bias('trad'):+.3f} deg (RMSE "
            f"{occluder.rmse_deg('trad'):.3f}; docs/model.md §12.6: about 0.11 deg "
            f"noise-free), the paper's Algorithm 1 by {bias('paper'):+.3f} deg, while "
            f"'compensated' {'stays at' if handled else 'is at'} {bias('compensated'):+.4f} deg "
            f"(RMSE {occluder.rmse_deg('compensated'):.4f}, bound {occluder.crlb_deg:.4f} deg): "
            + ending
        )
    return "\n".join(lines)


# ----------------------------------------------------------------------------- figures
PLOTTED = ("trad_nogain", "trad", "paper", "compensated")
_COLORS = {"trad_nogain": "C0", "trad": "C1", "paper": "C2", "compensated": "C3"}
_MARKERS = {"trad_nogain": "o", "trad": "^", "paper": "s", "compensated": "d"}


def plot_reproduction(repro: Reproduction, out_dir: Any, *, prefix: str = "") -> list[Any]:
    """Figures like the paper's Figures 6 and 7: headings and heading errors over time per
    estimator (Agg backend, PNG). Returns the written paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    labels = {e.key: e.label for e in ESTIMATORS}
    img = repro.images
    paths = []

    fig, ax = plt.subplots(figsize=(8, 4.5))
    sc = repro.scenario
    t_dense = np.linspace(0.0, sc.duration_s, 4001)
    heading = np.mod(90.0 - sc.turn_deg * t_dense / sc.duration_s, 360.0)
    heading[1:][np.abs(np.diff(heading)) > 180.0] = np.nan  # break the line where it wraps
    ax.plot(t_dense, heading, "k-", lw=2.5, label="true heading")
    for key in PLOTTED:
        marker = _MARKERS[key]
        sel = img[img["estimator"] == key]
        if len(sel):
            ax.plot(
                sel["t"],
                sel["heading_deg"],
                marker,
                ms=4,
                mfc="none",
                color=_COLORS[key],
                label=labels[key],
            )
    ax.set(
        xlabel="time [s]",
        ylabel="heading [deg, clockwise from North]",
        title=f"Heading results ({sc.name}), cf. paper Fig. 6",
        ylim=(0, 360),
    )
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2)
    fig.tight_layout()
    paths.append(out / f"{prefix}fig6_headings.png")
    fig.savefig(paths[-1], dpi=120, bbox_inches="tight")
    plt.close(fig)

    fig, axes = plt.subplots(2, 1, figsize=(11, 6), sharex=True)
    for key in PLOTTED:
        sel = img[img["estimator"] == key]
        if not len(sel):
            continue
        rmse = float(np.sqrt(np.nanmean(sel["error_deg"] ** 2)))
        for ax in axes if key in ("paper", "compensated", "trad") else axes[:1]:
            ax.plot(
                sel["t"],
                sel["error_deg"],
                _MARKERS[key] + "-",
                ms=3,
                lw=0.8,
                color=_COLORS[key],  # one colour per method in every panel and figure
                label=f"{labels[key]} (RMSE {rmse:.4f} deg)",
            )
    axes[0].set(
        ylabel="heading error [deg]",
        title=f"Heading errors ({repro.scenario.name}), cf. paper Fig. 7",
    )
    axes[1].set(
        xlabel="time [s]", ylabel="heading error [deg]", title="zoom: gain-corrected estimators"
    )
    for ax in axes:
        ax.axhline(0.0, color="k", lw=0.5)
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    paths.append(out / f"{prefix}fig7_errors.png")
    fig.savefig(paths[-1], dpi=120, bbox_inches="tight")
    plt.close(fig)
    return paths


# ----------------------------------------------------------------------------- demo
def run_demo(
    *,
    downscale: int = 4,
    n_images: int = 20,
    seed: int = 0,
    out: Any = None,
    progress: bool = True,
    occluder: bool = True,
) -> tuple[str, list[Reproduction]]:
    """The ``polins demo`` job: the Section 4.1 reproduction and the occluder case.

    Returns the printed report and the reproductions; with ``out`` (a folder) also writes
    ``summary.csv``, ``images.csv`` and the Figure 6/7-like plots there.
    """
    if downscale < 1 or n_images < 1:
        raise ValueError(f"downscale ({downscale}) and images ({n_images}) must be >= 1")
    tic = time.perf_counter()
    paper_sc, occ_sc = paper_scenarios(downscale=downscale, n_images=n_images, seed=seed)
    runs = [run_scenario(paper_sc, progress=progress)]
    if occluder:
        runs.append(run_scenario(occ_sc, progress=progress))
    elapsed = time.perf_counter() - tic
    parts = [format_table(r) for r in runs]
    parts.append(explain(runs[0], runs[1] if occluder else None))
    parts.append(f"({elapsed:.1f} s in total)")
    if out is not None:
        folder = Path(out)
        folder.mkdir(parents=True, exist_ok=True)
        tables, images = [], []
        written = []
        for r, prefix in zip(runs, ("paper_", "occluder_"), strict=False):
            tables.append(r.summary.assign(scenario=r.scenario.name, crlb_deg=r.crlb_deg))
            images.append(r.images.assign(scenario=r.scenario.name))
            written += plot_reproduction(r, folder, prefix=prefix)
        pd.concat(tables).to_csv(folder / "summary.csv", index=False)
        pd.concat(images).to_csv(folder / "images.csv", index=False)
        written += [folder / "summary.csv", folder / "images.csv"]
        parts.append("wrote " + ", ".join(str(p) for p in written))
    return "\n\n".join(parts), runs
