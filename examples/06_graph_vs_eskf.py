"""06 - GTSAM factor graph against the ESKF and the ESKF + RTS smoother on a UGV drive.

A random ground-vehicle drive (``polins.sim``) sensed by a typical MEMS IMU (its error model
in ``models/imus``, scale-factor errors included unless --no-scale: the 15-state estimators
do not model them). Aiding at 5 Hz: the polarization yaw (truth + N(0, 0.2 deg)) with the
vehicle's non-holonomic and zero-velocity constraints (--aiding yaw, default), or the sun
vector in the body frame (sun of the paper's Harbin session, direction noise 0.2 deg) with
zero velocity at the stops (--aiding sun). The initial attitude is the truth with a random
1 deg (1 sigma) error, the prior of every estimator.

The same inputs go through ``polins.fuse``: the ESKF (causal), the ESKF + Rauch-Tung-Striebel
smoother, and the GTSAM graph with its three solvers: batch Gauss-Newton (smoother), ISAM2
(causal, as online) and the fixed-lag smoother (10 s). Prints per estimator the RMSE of
roll, pitch and yaw against the truth, the consistency RMS(error / sigma) (1 is ideal) and
the run time, pooled over --runs drives; then the cost of the Python yaw factor. Writes to
--out: ``attitude_errors.png`` (errors of the first drive with the graph's 3-sigma band)
and ``sigmas.png`` (the reported 1-sigma of each estimator).

    python examples/06_graph_vs_eskf.py [--quick] [--runs 3] [--aiding yaw|sun] [--out ...]

--quick: one 60 s drive (~15 s); default: three 300 s drives (under a minute per drive).
"""

from __future__ import annotations

import argparse
import dataclasses
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
from polins.frames import wrap_angle, yaw_from_rot_nb
from polins.fusion.vehicle import with_standstill
from polins.sim.imu import ideal_imu, imu_errors
from polins.sim.trajectory import ugv_drive
from polins.site import PAPER_SITE

STD = np.radians(0.2)
RATE_HZ = 5.0
SITE = {"lat_deg": PAPER_SITE.lat_deg, "lon_deg": PAPER_SITE.lon_deg, "alt_m": PAPER_SITE.alt_m}
EPOCH = pd.Timestamp("2023-09-05T15:06:00+08:00")  # the paper's simulation (Z = 60 deg)
ANGLES = ("roll", "pitch", "yaw")
ESTIMATORS = {
    "ESKF": {"backend": "eskf"},
    "ESKF+RTS": {"backend": "eskf", "smooth": True},
    "graph batch": {"backend": "graph", "solver": "batch"},
    "graph ISAM2": {"backend": "graph", "solver": "isam2"},
    "graph lag 10 s": {"backend": "graph", "solver": "fixed_lag", "lag_s": 10.0},
}


def simulate(model: polins.ImuModel, duration: float, seed: int, aiding: str, scale: bool):
    """Drive, IMU with the model's errors, measurements, options, initial attitude."""
    traj = ugv_drive(duration_s=duration, rng=np.random.default_rng(seed))
    sim_model = (
        model
        if scale
        else dataclasses.replace(model, gyro_scale_factor=0.0, accel_scale_factor=0.0)
    )
    rng = np.random.default_rng([seed, 1])
    imu, _ = imu_errors(ideal_imu(traj), sim_model, rng)
    idx = np.arange(0, len(traj), round(traj.rate_hz / RATE_HZ))[1:]
    t = traj.t[idx]
    if aiding == "yaw":
        yaw = yaw_from_rot_nb(traj.rot_nb[idx]) + rng.normal(0.0, STD, idx.size)
        meas = pd.DataFrame({"t": t, "yaw": wrap_angle(yaw), "yaw_std": STD})
        extra = {"nhc_std": 0.05}
    else:
        sun = polins.sun_position(EPOCH + pd.to_timedelta(t, unit="s"), **SITE)
        sun_n = polins.sun_vector_n(sun.azimuth, sun.zenith)
        noise = Rotation.from_rotvec(rng.normal(0.0, STD, (idx.size, 3)))
        sun_b = noise.apply(traj.rot_nb[idx].inv().apply(sun_n))
        meas = pd.DataFrame({"t": t, "sun_std": STD})
        for i, c in enumerate("xyz"):
            meas[f"sun_b{c}"], meas[f"sun_n{c}"] = sun_b[:, i], sun_n[:, i]
        extra = {}
    stationary = traj.t[np.linalg.norm(traj.vel_n, axis=1) < 1e-9][:: round(traj.rate_hz / 5)]
    options = {
        "imu_model": model,
        "lat_deg": np.degrees(traj.lat[0]),
        "lon_deg": np.degrees(traj.lon[0]),
        "alt_m": traj.alt_m[0],
        "earth_rate": True,  # the simulated IMU senses the Earth rate
        "output_rate_hz": 10.0,
        **extra,
    }
    meas = with_standstill(meas, stationary, 0.01)  # zero-velocity rows at the stops
    rot0 = Rotation.from_rotvec(rng.normal(0.0, np.radians(1.0), 3)) * traj.rot_nb[0]
    return traj, imu, meas, options, rot0


def run_all(traj, imu, meas, options, rot0) -> dict[str, dict]:
    truth = traj.truth_frame().set_index("t")
    out = {}
    for name, kw in ESTIMATORS.items():
        t0 = time.perf_counter()
        opts = {**options, **kw}
        backend = opts.pop("backend")
        config = polins.fusion.FuseConfig.from_options(**opts)
        res = polins.fusion.run_fusion(imu, meas, backend, rot0, config)
        sol = res.solution
        elapsed = time.perf_counter() - t0
        tr = truth.reindex(sol["t"].to_numpy(), method="nearest")
        err = {c: np.asarray(wrap_angle(sol[c].to_numpy() - tr[c].to_numpy())) for c in ANGLES}
        out[name] = {"sol": sol, "err": err, "time": elapsed, "info": res.info}
    return out


def yaw_factor_cost(n: int = 2000) -> tuple[float, float]:
    """Linearization time per factor [us]: Python yaw CustomFactor vs C++ AttitudeFactorPose3."""
    import gtsam
    from gtsam.symbol_shorthand import X

    from polins.fusion.graph import sun_factor, yaw_factor

    rng = np.random.default_rng(0)
    values = gtsam.Values()
    yaw_graph, sun_graph = gtsam.NonlinearFactorGraph(), gtsam.NonlinearFactorGraph()
    for k in range(n):
        rot = Rotation.from_euler("ZYX", rng.uniform(-0.3, 0.3, 3))
        values.insert(X(k), gtsam.Pose3(gtsam.Rot3(rot.as_matrix()), np.zeros(3)))
        yaw_graph.add(yaw_factor(X(k), float(yaw_from_rot_nb(rot)), STD))
        sun_graph.add(
            sun_factor(X(k), [0.5, 0.5, 0.7071], rot.inv().apply([0.5, 0.5, 0.7071]), STD)
        )
    cost = []
    for graph in (yaw_graph, sun_graph):
        t0 = time.perf_counter()
        for _ in range(5):
            graph.linearize(values)
        cost.append((time.perf_counter() - t0) / (5 * n) * 1e6)
    return cost[0], cost[1]


def _style(name: str) -> dict:
    """ESKF curves thick and dashed: the graph's twins (ISAM2, batch) lie on top of them."""
    return {"lw": 2.0, "ls": "--", "alpha": 0.8} if name.startswith("ESKF") else {"lw": 0.9}


def plot_errors(res: dict, path: Path) -> None:
    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    band = res["graph batch"]["sol"]
    for ax, c in zip(axes, ANGLES, strict=True):
        t = band["t"].to_numpy()
        s3 = 3.0 * np.degrees(band[f"{c}_std"].to_numpy())
        ax.fill_between(t, -s3, s3, color="0.85", label="graph batch +-3 sigma")
        for name, r in res.items():
            ax.plot(r["sol"]["t"], np.degrees(r["err"][c]), label=name, **_style(name))
        ax.set_ylabel(f"{c} error [deg]")
        ax.grid(True)
    axes[0].legend(ncol=3, fontsize=8)
    axes[-1].set_xlabel("t [s]")
    fig.suptitle("Attitude error against the simulated truth (first drive)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_sigmas(res: dict, path: Path) -> None:
    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    for ax, c in zip(axes, ANGLES, strict=True):
        for name, r in res.items():
            ax.plot(r["sol"]["t"], np.degrees(r["sol"][f"{c}_std"]), label=name, **_style(name))
        ax.set_ylabel(f"{c} 1-sigma [deg]")
        ax.set_yscale("log")
        ax.grid(True, which="both")
    axes[0].legend(ncol=3, fontsize=8)
    axes[-1].set_xlabel("t [s]")
    fig.suptitle("Reported attitude sigmas (first drive)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one 60 s drive")
    parser.add_argument("--runs", type=int, default=None, help="drives (default 3, quick 1)")
    parser.add_argument("--duration", type=float, default=None, help="drive length [s]")
    parser.add_argument("--aiding", choices=("yaw", "sun"), default="yaw")
    parser.add_argument("--no-scale", action="store_true", help="IMU without scale errors")
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--out", type=Path, default=Path("out/06_graph_vs_eskf"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    runs = args.runs or (1 if args.quick else 3)
    duration = args.duration or (60.0 if args.quick else 300.0)
    warnings.simplefilter("ignore", UserWarning)
    model = polins.load_imu("mems-typical")

    pooled: dict[str, dict] = {
        n: {"e": {c: [] for c in ANGLES}, "z": {c: [] for c in ANGLES}, "time": 0.0}
        for n in ESTIMATORS
    }
    first = None
    for run in range(runs):
        data = simulate(model, duration, args.seed + run, args.aiding, not args.no_scale)
        res = run_all(*data)
        first = first or res
        for name, r in res.items():
            for c in ANGLES:
                pooled[name]["e"][c].append(r["err"][c])
                pooled[name]["z"][c].append(r["err"][c] / r["sol"][f"{c}_std"].to_numpy())
            pooled[name]["time"] += r["time"]
        print(f"drive {run + 1}/{runs} done", flush=True)

    print(
        f"\nMEMS IMU ({'with' if not args.no_scale else 'without'} scale-factor errors), "
        f"{runs} x {duration:.0f} s UGV drive(s), {args.aiding} aiding at {RATE_HZ:g} Hz"
    )
    head = "".join(f"{c + ' [deg]':>12}" for c in ANGLES)
    cons = "".join(f"{c + ' e/s':>10}" for c in ANGLES)
    print(f"{'estimator':<16}{'RMSE: ':>6}{head}  RMS{cons}  {'time/drive [s]':>15}")
    for name, p in pooled.items():
        rmse = [np.degrees(np.sqrt(np.mean(np.concatenate(p["e"][c]) ** 2))) for c in ANGLES]
        nees = [np.sqrt(np.mean(np.concatenate(p["z"][c]) ** 2)) for c in ANGLES]
        print(
            f"{name:<16}{'':>6}"
            + "".join(f"{v:12.4f}" for v in rmse)
            + "     "
            + "".join(f"{v:10.2f}" for v in nees)
            + f"  {p['time'] / runs:15.2f}"
        )
    info = first["graph batch"]["info"]
    print(
        f"\ngraph batch (first drive): {info['n_keyframes']} keyframes, "
        f"{info['n_measurement_factors']} measurement factors, Gauss-Newton iterations "
        f"{info['iterations']}, gated {len(info['rejected'])}; build {info['time_build_s']:.2f} s, "
        f"solve + marginals {info['time_solve_s']:.2f} s, output {info['time_output_s']:.2f} s"
    )
    py_us, cpp_us = yaw_factor_cost()
    print(
        f"linearization per factor: yaw CustomFactor (Python) {py_us:.1f} us, "
        f"AttitudeFactorPose3 (C++) {cpp_us:.1f} us"
    )
    plot_errors(first, args.out / "attitude_errors.png")  # type: ignore[arg-type]
    plot_sigmas(first, args.out / "sigmas.png")  # type: ignore[arg-type]
    print(f"figures written to {args.out}/")


if __name__ == "__main__":
    main()
