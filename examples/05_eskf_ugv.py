"""05 - ESKF on a simulated UGV drive: MEMS and FINS IMUs, with and without polarization yaw.

A random ground-vehicle drive (straight runs, turns, slopes, stops; ``polins.sim``) is
sensed by the paper's navigation-grade FINS and by a typical MEMS IMU (their error models
in ``models/imus``, scale factors included). The polarization compass is simulated as the
true yaw plus N(0, 0.3 deg) at 5 Hz. ``polins.fuse`` runs the error-state Kalman filter
with its default options (21 states with scale factors for the MEMS IMU, 15 for the FINS;
the Earth rate mechanized at the given site) with self-alignment (levelling at rest, yaw
from a consensus of the first measurements) when aided, and from the true initial attitude with a 0.1 deg (1 sigma) random
error when not.

Prints a table (yaw error, final sigma, consistency, NIS, speed) and writes to --out:
``yaw_error.png`` (yaw error with its 3-sigma band, per IMU and aiding), ``tilt_error.png``
(roll and pitch errors with 3-sigma bands) and ``gyro_bias.png`` (estimated vs true gyro
z bias).

    python examples/05_eskf_ugv.py [--quick] [--out out/05_eskf_ugv] [--seed 5]

--quick: a 60 s drive (a few seconds); default: 300 s.
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

import polins
import polins.fusion
from polins.frames import wrap_angle
from polins.sim.imu import ideal_imu, imu_errors
from polins.sim.trajectory import ugv_drive
from polins.site import PAPER_SITE

YAW_STD = np.radians(0.3)
RATE_HZ = 5.0
SITE = {"lat_deg": PAPER_SITE.lat_deg, "lon_deg": PAPER_SITE.lon_deg, "alt_m": PAPER_SITE.alt_m}


def simulate(model: polins.ImuModel, duration: float, seed: int):
    """The drive (same for both IMUs), the IMU with the model's errors, yaw measurements."""
    traj = ugv_drive(duration_s=duration, rng=np.random.default_rng(seed))
    rng = np.random.default_rng([seed, len(model.name)])
    imu, errors = imu_errors(ideal_imu(traj), model, rng)
    truth = traj.truth_frame()
    t = np.arange(1.0 / RATE_HZ, duration, 1.0 / RATE_HZ)
    yaw = np.interp(t, truth["t"], np.unwrap(truth["yaw"]))
    meas = pd.DataFrame(
        {"t": t, "yaw": wrap_angle(yaw + rng.normal(0.0, YAW_STD, t.size)), "yaw_std": YAW_STD}
    )
    return traj, imu, errors, truth, meas


def run(model, traj, imu, errors, truth, meas, aided: bool) -> dict:
    """Fuse and compare with the truth at the 10 Hz output rows."""
    t0 = time.perf_counter()
    if aided:
        config = polins.fusion.FuseConfig.from_options(imu_model=model, **SITE, output_rate_hz=10.0)
        res = polins.fusion.run_fusion(imu, meas, config=config)
    else:
        # initial attitude: the truth with an error drawn from the stated 0.1 deg sigma
        att_std0 = np.radians(0.1)
        rng = np.random.default_rng(len(model.name))
        rot_nb0 = Rotation.from_rotvec(rng.normal(0.0, att_std0, 3)) * traj.rot_nb[0]
        config = polins.fusion.FuseConfig.from_options(
            att_std0=att_std0, imu_model=model, **SITE, output_rate_hz=10.0
        )
        res = polins.fusion.run_fusion(imu, None, rot_nb0=rot_nb0, config=config)
    sol = res.solution
    seconds = time.perf_counter() - t0
    k = np.searchsorted(truth["t"].to_numpy(), sol["t"].to_numpy() - 1e-9)
    err = {
        "yaw": wrap_angle(sol["yaw"].to_numpy() - truth["yaw"].to_numpy()[k]),
        "roll": sol["roll"].to_numpy() - truth["roll"].to_numpy()[k],
        "pitch": sol["pitch"].to_numpy() - truth["pitch"].to_numpy()[k],
    }
    upd = res.updates
    nis = upd.loc[(upd["name"] == "yaw") & np.isfinite(upd["nis"]), "nis"]
    ok = np.isfinite(err["yaw"]) & (sol["t"].to_numpy() >= 5.0)
    ratio = err["yaw"][ok] / sol["yaw_std"].to_numpy()[ok]
    return {
        "sol": sol,
        "err": err,
        "true_bgz": errors["bgz"].to_numpy()[k],
        "row": {
            "imu": model.name,
            "aiding": "polarization yaw 5 Hz" if aided else "none",
            "yaw_rms_deg": np.degrees(np.sqrt(np.mean(err["yaw"][ok] ** 2))),
            "yaw_final_err_deg": np.degrees(abs(err["yaw"][-1])),
            "yaw_final_3sigma_deg": np.degrees(3 * sol["yaw_std"].iloc[-1]),
            "rms(err/sigma)": np.sqrt(np.mean(ratio**2)),
            "NIS_mean": nis.mean() if len(nis) else np.nan,
            "rejected": int((~upd["accepted"]).sum()),
            "samples/s": len(imu) / seconds,
        },
    }


def plot_bands(results, key: str, path: Path, title: str) -> None:
    """Error with its +-3 sigma band, one panel per IMU and aiding."""
    fig, axes = plt.subplots(2, 2, figsize=(12, 7), sharex=True)
    for ax, res in zip(axes.ravel(), results, strict=True):
        sol, t = res["sol"], res["sol"]["t"].to_numpy()
        for name, color in ((key, "C0"),) if key == "yaw" else (("roll", "C0"), ("pitch", "C1")):
            band = 3 * np.degrees(sol[f"{name}_std"].to_numpy())
            ax.fill_between(t, -band, band, color=color, alpha=0.2, label=f"±3σ {name}")
            ax.plot(t, np.degrees(res["err"][name]), color=color, lw=0.8, label=f"{name} error")
        ax.set_title(f"{res['row']['imu']}, aiding: {res['row']['aiding']}", fontsize=10)
        ax.set_ylabel("error [deg]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper left")
    for ax in axes[-1]:
        ax.set_xlabel("time [s]")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_bias(results, path: Path) -> None:
    """Estimated gyro z bias (with 3 sigma) against the simulated truth."""
    fig, axes = plt.subplots(2, 2, figsize=(12, 7), sharex=True)
    deg_h = 180.0 / np.pi * 3600.0
    for ax, res in zip(axes.ravel(), results, strict=True):
        sol, t = res["sol"], res["sol"]["t"].to_numpy()
        est, std = sol["bgz"].to_numpy() * deg_h, sol["bgz_std"].to_numpy() * deg_h
        ax.fill_between(
            t, est - 3 * std, est + 3 * std, color="C0", alpha=0.2, label="estimate ±3σ"
        )
        ax.plot(t, est, color="C0", lw=1.0, label="estimated bgz")
        ax.plot(t, res["true_bgz"] * deg_h, color="k", lw=1.0, ls="--", label="true bgz")
        ax.set_title(f"{res['row']['imu']}, aiding: {res['row']['aiding']}", fontsize=10)
        ax.set_ylabel("gyro z bias [deg/h]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    for ax in axes[-1]:
        ax.set_xlabel("time [s]")
    fig.suptitle("Gyro z bias: estimate vs simulated truth")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="60 s drive instead of 300 s")
    ap.add_argument("--out", type=Path, default=Path("out/05_eskf_ugv"), help="figure folder")
    ap.add_argument("--seed", type=int, default=5, help="random seed of the drive and noises")
    args = ap.parse_args()
    warnings.simplefilter("ignore", UserWarning)
    args.out.mkdir(parents=True, exist_ok=True)
    duration = 60.0 if args.quick else 300.0
    results = []
    for name in ("fins-paper", "mems-typical"):
        model = polins.load_imu(name)
        data = simulate(model, duration, args.seed)
        for aided in (True, False):
            results.append(run(model, *data, aided=aided))
    table = pd.DataFrame([r["row"] for r in results])
    with pd.option_context("display.width", 160, "display.float_format", "{:.4g}".format):
        print(f"UGV drive, {duration:g} s, polarization yaw sigma {np.degrees(YAW_STD):g} deg")
        print(table.to_string(index=False))
    plot_bands(results, "yaw", args.out / "yaw_error.png", "Yaw error and 3σ band")
    plot_bands(results, "tilt", args.out / "tilt_error.png", "Roll / pitch error and 3σ bands")
    plot_bias(results, args.out / "gyro_bias.png")
    table.to_csv(args.out / "summary.csv", index=False)
    print(f"figures and summary.csv in {args.out}")


if __name__ == "__main__":
    main()
