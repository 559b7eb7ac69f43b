"""One hour of a MEMS UGV log through both backends: wall and CPU time, peak memory, output size.

Synthesises (once, in this process) a ``--minutes`` long drive of the ``polins simulate
--scenario ugv`` kind: the IMU mounted off the vehicle's axes with road vibration, a MEMS
model (``mems-typical``, 200 Hz), a 10 Hz wheel odometer, and a heading at 1 Hz standing
in for the images (the truth's yaw plus 0.3 deg of noise: the per-image measurement is a
constant cost per image, ``benchmarks/bench_pipeline.py`` gives it). Then, for each
backend and each prefix of the log (``--prefixes``, default 15, 30 and 60 minutes), a
fresh child process reads the inputs, runs ``polins.fusion.run_fusion`` with the
``[vehicle]`` options of a ``polins simulate`` log (ground vehicle: NHC, standstill
updates, odometer, the mounting) and writes the solution as ``polins fuse`` does
(``polins.io.report.write_run_files``, CSV and Parquet). Each child reports its wall
and CPU time, its peak resident memory (``ru_maxrss``) and that before fusing (the inputs),
the solution's rows and file sizes, the heading error against the truth and, for the
graph, the Gauss-Newton iterations of each solve (one solve per post-fit gate round).

Printed: the machine (CPU model, cores, load average before and after) and, per backend,
a row per prefix and the slopes between prefixes (seconds and MB per minute of log): time
and memory grow linearly when the slopes agree.

Run: ``python benchmarks/bench_hour.py [--minutes 60] [--prefixes 15,30,60]
[--graph-prefixes 5,10,20] [--backends eskf,graph]``.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from polins.frames import wrap_angle

SITE = {"lat_deg": 45.6234, "lon_deg": 126.7264, "alt_m": 148.74}
HEADING_STD_DEG = 0.3
IMAGE_RATE_HZ = 1.0


def synthesise(minutes: float, folder: Path, seed: int = 0) -> None:
    """The log's IMU, headings, odometer and truth as Parquet files in ``folder``."""
    from polins.models import load_imu
    from polins.sim.imu import ideal_imu, imu_errors
    from polins.sim.trajectory import ugv_drive
    from polins.sim.vehicle import (
        UGV_LEVER_ARM_B,
        UGV_MOUNT_RPY_DEG,
        UGV_ODOMETER,
        forward_speed,
        mounted_trajectory,
        odometer_speeds,
        road_vibration,
    )

    model = load_imu("mems-typical")
    rng_traj, rng_imu, rng_meas, rng_vib, rng_odo = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(5)
    )
    vehicle = ugv_drive(duration_s=60.0 * minutes, rate_hz=model.sample_rate_hz, rng=rng_traj,
                        yaw0=float(rng_traj.uniform(-np.pi, np.pi)), **SITE)  # fmt: skip
    traj = mounted_trajectory(vehicle, np.radians(UGV_MOUNT_RPY_DEG), UGV_LEVER_ARM_B)
    ideal = ideal_imu(traj)
    gyro_vib, accel_vib = road_vibration(traj.t, forward_speed(vehicle), rng_vib)
    ideal[["gx", "gy", "gz"]] += gyro_vib
    ideal[["ax", "ay", "az"]] += accel_vib
    imu, _ = imu_errors(ideal, model, rng_imu)
    odometry = odometer_speeds(vehicle, rng_odo, **UGV_ODOMETER)
    truth = traj.truth_frame()[["t", "roll", "pitch", "yaw"]]
    every = round(model.sample_rate_hz / IMAGE_RATE_HZ)
    rows = truth.iloc[every::every]
    std = np.radians(HEADING_STD_DEG)
    noisy = wrap_angle(rows["yaw"].to_numpy() + rng_meas.normal(0.0, std, len(rows)))
    meas = pd.DataFrame({"t": rows["t"].to_numpy(), "yaw": noisy, "yaw_std": std})
    imu.to_parquet(folder / "imu.parquet")
    meas.to_parquet(folder / "meas.parquet")
    odometry.to_parquet(folder / "odometry.parquet")
    truth.to_parquet(folder / "truth.parquet")


def child(backend: str, minutes: float, folder: Path) -> dict[str, float]:
    """One fusion run over the first ``minutes`` of the log (in a fresh process)."""
    from polins.evaluation.reference import solution_errors
    from polins.fusion import FuseConfig, run_fusion
    from polins.io.report import write_run_files
    from polins.sim.vehicle import UGV_LEVER_ARM_B, UGV_MOUNT_RPY_DEG, UGV_ODOMETER

    def first(name: str) -> pd.DataFrame:  # read the prefix only
        end = 60.0 * minutes + 1e-9
        return pd.read_parquet(folder / f"{name}.parquet", filters=[("t", "<=", end)])

    imu, meas, odo, truth = (first(n) for n in ("imu", "meas", "odometry", "truth"))
    config = FuseConfig.from_options(
        imu_model="mems-typical", vehicle="ground",
        mount_rpy=tuple(np.radians(UGV_MOUNT_RPY_DEG)), lever_arm_b=tuple(UGV_LEVER_ARM_B),
        odometer_std=UGV_ODOMETER["noise_std"], **SITE,
    )  # fmt: skip
    rss_inputs = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    wall, cpu = time.perf_counter(), time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = run_fusion(imu, meas, backend, config=config, odometry=odo)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    sizes = {}
    with tempfile.TemporaryDirectory() as tmp:
        for fmt in ("csv", "parquet"):
            out = Path(tmp) / fmt
            write_run_files(out, {"solution.csv": result.solution}, {}, table_format=fmt)
            sizes[fmt] = (out / f"solution.{fmt}").stat().st_size / 1e6
    err = solution_errors(result.solution, truth)
    keep = err["t"].to_numpy() > 30.0  # after the yaw acquisition and its transient
    e = np.degrees(err["yaw_err"].to_numpy()[keep])
    s = np.degrees(result.solution["yaw_std"].to_numpy()[keep])
    return {
        "minutes": minutes,
        "wall_s": wall,
        "cpu_s": cpu,
        "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "inputs_mb": rss_inputs,
        "rows": float(len(result.solution)),
        "csv_mb": sizes["csv"],
        "parquet_mb": sizes["parquet"],
        "heading_rms_deg": float(np.sqrt(np.nanmean(e**2))),
        "heading_rms_norm": float(np.sqrt(np.nanmean((e / s) ** 2))),
        "iterations": result.info.get("iterations", []),  # the graph's, one per solve
    }


def machine() -> str:
    """CPU model, cores and load average."""
    model = platform.processor() or platform.machine()
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    load = " ".join(f"{v:.2f}" for v in os.getloadavg())
    return f"{model}, {os.cpu_count()} cores, load average (1/5/15 min) {load}"


def slopes(rows: list[dict[str, float]], key: str) -> str:
    """``key`` per minute of log between successive prefixes."""
    pairs = itertools.pairwise(rows)
    return " / ".join(f"{(b[key] - a[key]) / (b['minutes'] - a['minutes']):.3g}" for a, b in pairs)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--minutes", type=float, default=60.0)
    parser.add_argument("--prefixes", default="15,30,60", help="prefixes of the log [min]")
    parser.add_argument("--graph-prefixes", default=None,
                        help="prefixes for the graph [min] (default: --prefixes)")  # fmt: skip
    parser.add_argument("--backends", default="eskf,graph")
    parser.add_argument("--child", nargs=3, metavar=("BACKEND", "MINUTES", "FOLDER"),
                        help=argparse.SUPPRESS)  # fmt: skip
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(args.child[0], float(args.child[1]), Path(args.child[2]))))
        return
    prefixes = {
        backend: [float(p) for p in text.split(",") if float(p) <= args.minutes]
        for backend, text in (("eskf", args.prefixes),
                              ("graph", args.graph_prefixes or args.prefixes))
    }  # fmt: skip
    print(f"machine: {machine()}")
    start_cpu = resource.getrusage(resource.RUSAGE_SELF).ru_utime
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        synthesise(args.minutes, Path(tmp))
        print(f"synthesised {args.minutes:g} min of a MEMS UGV log (200 Hz IMU, 10 Hz "
              f"odometer, headings at {IMAGE_RATE_HZ:g} Hz) in {time.perf_counter() - t0:.1f} s")  # fmt: skip
        for backend in args.backends.split(","):
            rows = []
            for minutes in prefixes[backend]:
                run = subprocess.run([sys.executable, __file__, "--child", backend, str(minutes), tmp],
                                     capture_output=True, text=True, check=True)  # fmt: skip
                rows.append(json.loads(run.stdout.strip().splitlines()[-1]))
                r = rows[-1]
                print(f"{backend:5} {minutes:5g} min: wall {r['wall_s']:7.1f} s, CPU "
                      f"{r['cpu_s']:7.1f} s, peak {r['peak_mb']:6.0f} MB (inputs "
                      f"{r['inputs_mb']:4.0f} MB), {r['rows']:.0f} rows: CSV "
                      f"{r['csv_mb']:.1f} MB, Parquet {r['parquet_mb']:.1f} MB; heading RMS "
                      f"{r['heading_rms_deg']:.4f} deg, RMS(err/sigma) "
                      f"{r['heading_rms_norm']:.2f}"
                      + (f"; Gauss-Newton iterations per solve {r['iterations']}"
                         if r["iterations"] else ""), flush=True)  # fmt: skip
            if len(rows) > 1:
                print(f"{backend:5} slopes per minute of log between the prefixes: CPU "
                      f"{slopes(rows, 'cpu_s')} s, wall {slopes(rows, 'wall_s')} s, peak "
                      f"memory {slopes(rows, 'peak_mb')} MB, CSV {slopes(rows, 'csv_mb')} MB")  # fmt: skip
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    own = resource.getrusage(resource.RUSAGE_SELF).ru_utime - start_cpu
    print(f"benchmark CPU time: {own + children.ru_utime + children.ru_stime:.0f} s; "
          f"machine after: {machine()}")  # fmt: skip


if __name__ == "__main__":
    main()
