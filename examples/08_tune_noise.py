"""08 - Tune the filter's noise: the Allan plot, a mistuned filter, and the maximum-likelihood fix.

Three steps a user takes with a new IMU and compass (docs/tuning.md):

1. A static recording of the IMU (simulated here with a known MEMS model) gives the IMU
   noise model from its Allan deviation (``polins.tuning.imu_model_from_static``, the same
   as ``polins imu-model``): ``allan.png``.
2. A drive with compass yaw measurements is fused with deliberately wrong noise: the gyro
   noise (Q) 10x too small or too large, the compass sigma (R) as the compass claims it
   (too small: the compass lacks a 0.1 deg floor) or 1 deg (too large). ``mistuned.png``
   shows what each looks like in the innovations, the NIS and the yaw NEES.
3. ``polins.tuning.tune`` (the same as ``polins tune``) fits the gyro ARW and the yaw floor
   by maximum likelihood of the innovations, starting from x3 and x1/3 off, and says which
   parameters the log can identify: ``tuned.png`` (before/after).

    python examples/08_tune_noise.py [--quick] [--out out/08_tune_noise] [--seed 8]

--quick: a 10 min static recording and a 60 s drive at 50 Hz; default: 1 h and 120 s at
100 Hz.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import warnings
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

import polins
from polins.fusion import FuseConfig, run_fusion
from polins.sim.imu import ideal_imu, imu_errors
from polins.sim.trajectory import ugv_drive
from polins.site import PAPER_SITE
from polins.tuning import (
    imu_model_from_static,
    innovation_stats,
    plot_allan,
    stats_table,
    tune,
    with_values,
)
from polins.tuning.innovations import innovation_arrays

YAW_RATE_HZ = 10.0
CLAIMED_STD = math.radians(0.01)  # the yaw_std the compass reports
FLOOR_DEG = 0.1  # what it lacks: the true noise is hypot(CLAIMED_STD, FLOOR)

HOW_TO_READ = """\
How to read the plots (docs/tuning.md)
  Allan plot: the -1/2 slope at short tau is the white noise (ARW, VRW), the +1/2 slope at
    long tau the bias random walk; a term marked 'not identified' needs a longer recording.
  Innovations: about 95 % of the points lie inside +-2 sqrt(S). Points far outside: S is
    too small (R or Q too small); a band much wider than the scatter: S too large.
  NIS (rolling mean): a consistent filter stays in the chi-square band around 1 (the dof).
    Above: S too small; below: too large. Which of Q and R: the lag-1 autocorrelation of
    the innovations (table): positive when Q is too small or R too large (the filter lags
    behind), negative when Q is too large or R too small (it chases the noise).
  Yaw NEES (from the truth, simulation only): the same for the state: above 1 the filter
    is over-confident (sigma too small), below it under-confident.
  The tuned filter: mean NIS inside its band, lag-1 autocorrelation inside +-z/sqrt(n);
    the parameters flagged 'no' are not identified by this log and keep their start values.
"""


def static_recording(
    model: polins.ImuModel, seconds: float, rate_hz: float, seed: int
) -> pd.DataFrame:
    """A level IMU at rest for ``seconds`` at ``rate_hz`` with the model's errors (no Earth
    rate)."""
    n = int(seconds * rate_hz)
    ideal = pd.DataFrame(np.zeros((n, 7)), columns=["t", "gx", "gy", "gz", "ax", "ay", "az"])
    ideal["t"] = np.arange(n) / rate_hz
    ideal["az"] = 9.80665
    return imu_errors(ideal, model, np.random.default_rng(seed))[0]


def drive(model: polins.ImuModel, seconds: float, rate_hz: float, seed: int):
    """A UGV drive, its IMU, the truth and 10 Hz yaw measurements with a hidden floor."""
    traj = ugv_drive(duration_s=seconds, rate_hz=rate_hz, rng=np.random.default_rng(seed))
    rng = np.random.default_rng(seed + 1)
    imu, _ = imu_errors(ideal_imu(traj, earth_rotation=False), model, rng)
    truth = traj.truth_frame()
    t = np.arange(1.0 / YAW_RATE_HZ, seconds, 1.0 / YAW_RATE_HZ)
    yaw = np.interp(t, truth["t"], np.unwrap(truth["yaw"]))
    noise = rng.normal(0.0, math.hypot(CLAIMED_STD, math.radians(FLOOR_DEG)), t.size)
    meas = pd.DataFrame({"t": t, "yaw": polins.wrap_angle(yaw + noise), "yaw_std": CLAIMED_STD})
    return imu, meas, truth


def yaw_nees(solution: pd.DataFrame, truth: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """Times [s] and the yaw NEES ``(error / sigma)^2`` of the solution rows."""
    t = solution["t"].to_numpy()
    k = np.clip(np.searchsorted(truth["t"].to_numpy(), t - 1e-9), 0, len(truth) - 1)
    err = polins.wrap_angle(solution["yaw"].to_numpy() - truth["yaw"].to_numpy()[k])
    ok = np.isfinite(err) & (t > 2.0)
    return t[ok], (err[ok] / solution["yaw_std"].to_numpy()[ok]) ** 2


def rolling(x: np.ndarray, n: int = 50) -> np.ndarray:
    """Centred rolling mean over ``n`` points."""
    return pd.Series(x).rolling(n, center=True, min_periods=n // 2).mean().to_numpy()


def draw_case(axes, result, truth, label: str, colour: str) -> None:
    """Innovations with +-2 sqrt(S), rolling NIS with its band, rolling yaw NEES."""
    upd = result.updates
    t, nu, S = innovation_arrays(upd, "yaw")
    two_sigma = 2 * np.degrees(np.sqrt(S[:, 0, 0]))
    two_sigma[1:][np.diff(t) > 1.5 / YAW_RATE_HZ] = np.nan  # no line across gated updates
    axes[0].plot(t, np.degrees(nu[:, 0]), ".", ms=2, color=colour, label=f"{label}: innovation")
    axes[0].plot(t, two_sigma, "-", color=colour, lw=1, label=f"{label}: ±2√S")
    axes[0].plot(t, -two_sigma, "-", color=colour, lw=1)
    stats = innovation_stats(upd)["yaw"]
    axes[1].semilogy(t, rolling(nu[:, 0] ** 2 / S[:, 0, 0]), color=colour,
                     label=f"{label}: mean {stats.nis_mean:.3g}")  # fmt: skip
    tn, nees = yaw_nees(result.solution, truth)
    axes[2].semilogy(tn, rolling(nees), color=colour, label=f"{label}: mean {nees.mean():.3g}")


def finish_row(axes, title: str, band: tuple[float, float]) -> None:
    """Labels, the NIS band and the NEES reference of one row of panels."""
    axes[0].set_ylabel("yaw innovation [deg]")
    axes[1].axhspan(*band, color="0.8", label="95 % band of the mean NIS")
    axes[1].set_ylabel("NIS, 5 s rolling mean [-]")
    axes[2].axhline(1.0, color="k", lw=0.8, ls="--", label="consistent: 1")
    axes[2].set_ylabel("yaw NEES, rolling mean [-]")
    axes[0].set_title(title, fontsize=10, loc="left")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper right")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="10 min static, 60 s drive, 50 Hz")
    ap.add_argument("--out", type=Path, default=Path("out/08_tune_noise"), help="figure folder")
    ap.add_argument("--seed", type=int, default=8, help="random seed")
    args = ap.parse_args()
    warnings.simplefilter("ignore", UserWarning)
    args.out.mkdir(parents=True, exist_ok=True)
    static_s, drive_s, rate_hz = (600.0, 60.0, 50.0) if args.quick else (3600.0, 120.0, 100.0)
    base = polins.load_imu("mems-typical")
    true_model = dataclasses.replace(base, gyro_arw=base.gyro_arw * 10.0)  # a noisy gyro

    # 1. the IMU model from a static recording
    fitted, fit = imu_model_from_static(static_recording(true_model, static_s, rate_hz, args.seed),
                                        name="fitted", grade="mems")  # fmt: skip
    plot_allan(fit, args.out / "allan.png")
    arw = lambda m: math.degrees(m.gyro_arw) * 60  # noqa: E731 [deg/sqrt(h)]
    print(f"1. Allan fit of a {static_s / 60:g} min static recording: gyro ARW "
          f"{arw(fitted):.3g} deg/sqrt(h) (true {arw(true_model):.3g}), VRW "
          f"{fitted.accel_vrw * 60:.3g} m/s/sqrt(h) (true {true_model.accel_vrw * 60:.3g})")  # fmt: skip

    # 2. mistuned filters
    imu, meas, truth = drive(true_model, drive_s, rate_hz, args.seed)
    # no gate: a gate hides a too-small S by dropping the largest innovations (docs/tuning.md)
    config = FuseConfig(imu_model=true_model, site=PAPER_SITE, output_rate_hz=10.0, gate_prob="off")
    right = with_values(config, meas, {"yaw_floor_deg": FLOOR_DEG})[0]  # the filter's R option
    cases = [
        ("Q too small (ARW / 10)", right.replace(imu_model=dataclasses.replace(
            true_model, gyro_arw=base.gyro_arw)), "Q"),
        ("Q too large (ARW x 10)", right.replace(imu_model=dataclasses.replace(
            true_model, gyro_arw=true_model.gyro_arw * 10)), "Q"),
        ("R too small (the compass's claimed sigma)", config, "R"),
        ("R too large (1 deg)", with_values(config, meas, {"yaw_floor_deg": 1.0})[0], "R"),
    ]  # fmt: skip
    reference = run_fusion(imu, meas, config=right)
    fig, axes = plt.subplots(2, 3, figsize=(15, 7.5), sharex=True)
    rows = []
    for label, case, row in cases:
        res = run_fusion(imu, meas, config=case)
        colour = "C3" if "small" in label else "C0"
        draw_case(axes[0 if row == "Q" else 1], res, truth, label, colour)
        row = stats_table(innovation_stats(res.updates)).iloc[0].to_dict()
        row["sigma floor"] = np.degrees(row["sigma floor"])  # [rad] -> [deg] for the yaw
        rows.append({"case": label, **row})
    for r in (0, 1):
        draw_case(axes[r], reference, truth, "right Q and R", "k")
        band = innovation_stats(reference.updates)["yaw"].nis_band
        finish_row(axes[r], "process noise Q wrong" if r == 0 else "measurement noise R wrong",
                   band)  # fmt: skip
        axes[r, 0].set_ylim(-0.6, 0.6)
    for ax in axes[-1]:
        ax.set_xlabel("time [s]")
    fig.suptitle("A mistuned filter: yaw innovations, NIS and NEES (10 Hz compass, MEMS gyro)")
    fig.tight_layout()
    fig.savefig(args.out / "mistuned.png", dpi=100)
    plt.close(fig)
    with pd.option_context("display.width", 200, "display.float_format", "{:.3g}".format):
        print("2. mistuned filters (yaw updates):")
        print(
            pd.DataFrame(rows)
            .drop(columns="kind")
            .rename(columns={"sigma floor": "floor [deg]"})
            .to_string(index=False)
        )

    # 3. maximum-likelihood tuning from x3 / x1/3 off
    start_model = dataclasses.replace(true_model, gyro_arw=true_model.gyro_arw * 3,
                                      accel_vrw=true_model.accel_vrw * 3)  # fmt: skip
    res = tune(imu, meas, dataclasses.replace(config, imu_model=start_model),
               params=("gyro_arw", "yaw_floor_deg", "accel_vrw"),
               initial={"yaw_floor_deg": FLOOR_DEG / 3})  # fmt: skip
    print(f"3. maximum-likelihood tuning ({res.n_evaluations} filter runs); true gyro_arw "
          f"{true_model.gyro_arw:.4g}, yaw floor {FLOOR_DEG} deg, accel_vrw {true_model.accel_vrw:.4g}")  # fmt: skip
    print(res.report())
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2), sharex=True)
    draw_case(axes, res.before, truth, "start (x3, x1/3)", "C3")
    draw_case(axes, res.after, truth, "tuned", "C2")
    finish_row(axes, "before and after tuning", res.stats_after["yaw"].nis_band)
    axes[0].set_ylim(-0.6, 0.6)
    for ax in axes:
        ax.set_xlabel("time [s]")
    fig.tight_layout()
    fig.savefig(args.out / "tuned.png", dpi=100)
    plt.close(fig)
    print(HOW_TO_READ)
    print(f"figures allan.png, mistuned.png, tuned.png in {args.out}")


if __name__ == "__main__":
    main()
