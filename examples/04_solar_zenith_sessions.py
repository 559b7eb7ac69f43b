"""04 - The paper's six outdoor sessions (Table 3) in simulation: heading error vs solar zenith.

Each session (Harbin, 2023-09-05 at 11:33, 12:18, 12:56, 13:29, 15:07, 16:29 +08:00, solar
zenith 38.7 to 74.1 deg) is simulated like the paper's Section 4.1 (Table 1 camera,
epsilon = 0.0125, sigma = 1.5 DN, 720 deg in 100 s) and measured with the traditional
estimator with and without gain correction, the paper's Algorithm 1 (scale-consistent Eq. 22,
beta applied) and the joint ML "compensated". Plots like the paper's Figure 10 (heading
errors over time per session) and the RMSE against the solar zenith with the Cramer-Rao
bound and the paper's outdoor Table 3 values, which are 10-100x above every simulated
noise figure: outdoors, model error (multiple scattering, calibration, IFOV, clouds), not
noise, limits the accuracy.

    python examples/04_solar_zenith_sessions.py [--quick | --full] [--sky berry] [--ifov]
        [--out out/04_solar_zenith_sessions]

--quick: 1/8 resolution, 12 images per session (seconds); default 1/4 resolution, 40
images; --full: full resolution, 100 images. --sky berry renders the Berry four-neutral-point
sky (model error for the Rayleigh-based estimators), --ifov the DoFP mosaic's per-channel
sampling offsets.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from polins.sim.reproduction import ESTIMATORS, TABLE3_SESSIONS, run_scenario, session_scenarios

KEYS = ("trad_nogain", "trad", "paper", "compensated")
COLORS = {"trad_nogain": "C0", "trad": "C1", "paper": "C2", "compensated": "C3"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--quick", action="store_true", help="1/8 resolution, 12 images/session")
    group.add_argument("--full", action="store_true", help="full resolution, 100 images/session")
    parser.add_argument("--sky", choices=["rayleigh", "berry"], default="rayleigh")
    parser.add_argument("--neutral-sep-deg", type=float, default=35.0, help="Berry sky [deg]")
    parser.add_argument("--ifov", action="store_true", help="per-channel mosaic sampling")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("out/04_solar_zenith_sessions"))
    args = parser.parse_args()
    downscale, n_images = (8, 12) if args.quick else (1, 100) if args.full else (4, 40)
    render = (
        ("sky", args.sky),
        ("neutral_sep", np.radians(args.neutral_sep_deg)),
        ("ifov", args.ifov),
    )
    estimators = [e for e in ESTIMATORS if e.key in KEYS]
    labels = {e.key: e.label for e in estimators}

    tic = time.perf_counter()
    runs = [
        run_scenario(sc, estimators, progress=True)
        for sc in session_scenarios(
            downscale=downscale, n_images=n_images, seed=args.seed, render_options=render
        )
    ]
    rows = []
    for r, (hhmm, paper_trad, paper_prop) in zip(runs, TABLE3_SESSIONS, strict=True):
        s = r.summary.set_index("key")
        rows.append(
            {
                "time": hhmm,
                "zenith_deg": r.sun_zenith_deg,
                "azimuth_deg": r.sun_azimuth_deg,
                **{f"{k}_rmse_deg": s.loc[k, "rmse_deg"] for k in KEYS},
                "crlb_deg": r.crlb_deg,
                "paper_traditional_deg": paper_trad,
                "paper_proposed_deg": paper_prop,
            }
        )
    table = pd.DataFrame(rows)
    print(
        f"Table 3 sessions in simulation: {n_images} images each at 1/{downscale} resolution, "
        f"{args.sky} sky{', IFOV mosaic sampling' if args.ifov else ''}; heading RMSE [deg]"
    )
    head = (
        f"{'time':>6} {'zenith':>7} {'azimuth':>8} {'trad,no gain':>13} {'trad':>8} "
        f"{'Alg. 1':>8} {'compens.':>9} {'CRLB':>8} | {'paper: trad':>11} {'proposed':>9}"
    )
    print(head)
    for _, row in table.iterrows():
        print(
            f"{row['time']:>6} {row['zenith_deg']:7.2f} {row['azimuth_deg']:8.2f} "
            f"{row['trad_nogain_rmse_deg']:13.4f} {row['trad_rmse_deg']:8.4f} "
            f"{row['paper_rmse_deg']:8.4f} {row['compensated_rmse_deg']:9.4f} "
            f"{row['crlb_deg']:8.4f} | {row['paper_traditional_deg']:11.4f} "
            f"{row['paper_proposed_deg']:9.4f}"
        )
    ratio = table["paper_proposed_deg"] / table["crlb_deg"]
    print(
        "\nIn simulation the gain-corrected estimators sit near the noise floor (CRLB, which"
        "\nfollows the sun's zenith and the visible sky), and the uncorrected gains cost a few"
        "\ntenths of a degree at any zenith. The paper's outdoor 'proposed' errors are"
        f"\n{ratio.min():.0f}-{ratio.max():.0f}x this bound (at full resolution ~{ratio.min() * downscale:.0f}x or"
        " more) and grow towards noon:\nmodel error (multiple scattering, calibration, IFOV,"
        " clouds) and the cot(Z) tilt\ncoupling, not noise, limit real skies (docs/errata.md"
        " §1 and §5)."
    )

    args.out.mkdir(parents=True, exist_ok=True)
    table.to_csv(args.out / "sessions.csv", index=False)

    # Figure 10-like: heading errors over time per session.
    fig, axes = plt.subplots(2, 3, figsize=(13, 6.5), sharex=True)
    for ax, r, (hhmm, _, _) in zip(axes.ravel(), runs, TABLE3_SESSIONS, strict=True):
        for key in KEYS:
            sel = r.images[r.images["estimator"] == key]
            ax.plot(
                sel["t"], sel["error_deg"], ".-", ms=2, lw=0.7, color=COLORS[key], label=labels[key]
            )
        ax.axhline(0.0, color="k", lw=0.5)
        ax.set_title(f"{hhmm}, zenith {r.sun_zenith_deg:.1f} deg", fontsize=9)
    for ax in axes[:, 0]:
        ax.set_ylabel("heading error [deg]")
    for ax in axes[-1]:
        ax.set_xlabel("time [s]")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle("Heading errors per session (simulation), cf. paper Fig. 10")
    fig.tight_layout()
    fig.savefig(args.out / "fig10_errors_per_session.png", dpi=120)
    plt.close(fig)

    # RMSE against the solar zenith.
    fig, ax = plt.subplots(figsize=(8, 5))
    z = table["zenith_deg"]
    for key in KEYS:
        ax.plot(z, table[f"{key}_rmse_deg"], "o-", color=COLORS[key], label=f"{labels[key]} (sim.)")
    ax.plot(z, table["crlb_deg"], "k:", label="Cramer-Rao bound (sim.)")
    ax.plot(
        z,
        table["paper_traditional_deg"],
        "s--",
        color="0.4",
        label="paper Table 3: traditional (outdoor)",
    )
    ax.plot(
        z,
        table["paper_proposed_deg"],
        "D--",
        color="0.7",
        label="paper Table 3: proposed (outdoor)",
    )
    ax.set_yscale("log")
    ax.set(
        xlabel="solar zenith angle [deg]",
        ylabel="heading RMSE [deg]",
        title=f"Heading RMSE vs solar zenith ({args.sky} sky, 1/{downscale} resolution)",
    )
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    fig.savefig(args.out / "rmse_vs_zenith.png", dpi=120, bbox_inches="tight")
    plt.close(fig)
    print(f"\nwrote {args.out}/fig10_errors_per_session.png, rmse_vs_zenith.png, sessions.csv")
    print(f"({time.perf_counter() - tic:.1f} s)")


if __name__ == "__main__":
    main()
