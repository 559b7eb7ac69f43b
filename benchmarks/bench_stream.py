"""Costs of ``polins.NavigationStream`` on the caller's thread (docs/streaming.md, "Costs").

Prints, in one run and beside GTSAM's C++ EKF driven sample by sample from Python (the
reference of benchmarks/bench_fuse.py, on the same samples):

* the per-sample cost of the stream: the wall time of feeding a 200 Hz MEMS IMU one
  ``add_imu`` call per sample, with 10 Hz yaw measurements (``add_measurement``), through
  ``close()``, divided by the samples; for the default configuration (a free vehicle,
  22 states) and a ground vehicle with 10 Hz odometry (NHC, zero-velocity and odometer
  updates), each with the solution kept at 10 Hz (the default) and at every sample; the
  constructor (its ephemeris) is a one-time cost, timed on its own;
* on a simulated UGV log (images at 5 Hz, 1/8 resolution, each delivered 40 ms after its
  exposure, the log's manifest through ``from_manifest``): the wall time of each
  ``add_imu``, ``add_image`` and ``state()`` call (10 Hz) on the caller's thread, median,
  99th percentile and maximum, with a thread and a process executor;
* the one-time costs in a fresh process: importing polins, the first constructor, the
  first ``add_imu`` that runs the filter and the first ``add_image``.

Run: ``python benchmarks/bench_stream.py [--duration 60] [--repeat 3]``. The machine may be
shared: the per-sample figures are the best of ``--repeat`` runs, interleaved; the ratio to
the reference says what they would be on an idle machine.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
from bench_fuse import best_times, gtsam_run, simulate

import polins
from polins.fusion.config import FuseConfig
from polins.io import load_raw, read_log
from polins.loop import NavigationStream
from polins.sim.scenario import simulate_log

SITE = polins.Site(45.6234, 126.7264, 148.74)
EPOCH = "2023-09-05T07:06:00+00:00"
CAMERA = polins.load_camera("paper-table1").downscaled(8)


def per_sample(imu: pd.DataFrame, meas: pd.DataFrame, config: FuseConfig, odo: np.ndarray):
    """A function feeding a new stream sample by sample (10 Hz yaw, ``odo`` speeds); it
    returns the wall times [s] of the constructor and of the feeding through ``close()``."""
    data = imu[["t", "gx", "gy", "gz", "ax", "ay", "az"]].to_numpy()
    t_meas, yaw, yaw_std = (meas[c].to_numpy() for c in ("t", "yaw", "yaw_std"))

    def run() -> tuple[float, float]:
        c0 = time.perf_counter()
        nav = NavigationStream(CAMERA, config.imu_model, site=SITE, epoch_utc=EPOCH,
                               config=config)  # fmt: skip
        c1 = time.perf_counter()
        j = i = 0
        for t, gx, gy, gz, ax, ay, az in data:
            nav.add_imu(t, (gx, gy, gz), (ax, ay, az))
            while i < len(odo) and odo[i, 0] <= t:
                nav.add_odometry(odo[i, 0], odo[i, 1])
                i += 1
            while j < len(t_meas) and t_meas[j] <= t:
                nav.add_measurement(t_meas[j], yaw=yaw[j], yaw_std=yaw_std[j])
                j += 1
        nav.close()
        return c1 - c0, time.perf_counter() - c1

    return run


def per_sample_table(duration: float, repeat: int) -> None:
    model = polins.load_imu("mems-typical")
    traj, imu, meas = simulate(duration, model)
    t_odo = np.arange(0.05, duration, 0.1)
    speed = np.linalg.norm(traj.truth_frame()[["ve", "vn"]].to_numpy(), axis=1)
    odo = np.column_stack([t_odo, np.interp(t_odo, traj.t, speed)])
    free = FuseConfig(model, SITE)
    ground = FuseConfig(model, SITE, vehicle="ground", odometer_std=0.05)
    none = np.zeros((0, 2))
    gtsam = gtsam_run(imu, model)
    fns = {
        "free": per_sample(imu, meas, free, none),
        "free_all": per_sample(imu, meas, free.replace(output_rate_hz="imu"), none),
        "ground": per_sample(imu, meas, ground, odo),
        "ground_all": per_sample(imu, meas, ground.replace(output_rate_hz="imu"), odo),
    }
    times = dict.fromkeys(["gtsam", *fns], np.inf)
    built = []
    for _ in range(repeat):  # interleaved round by round (bench_fuse.best_times)
        times["gtsam"] = min(times["gtsam"], best_times({"gtsam": gtsam}, 1)["gtsam"])
        for key, fn in fns.items():
            construct, feed = fn()
            built.append(construct)
            times[key] = min(times[key], feed)
    n = len(imu)
    print(f"per-sample cost: {n} samples at 200 Hz ({duration:g} s), 10 Hz yaw, best of {repeat}")
    print(f"{'':58s} {'us/sample':>10s} {'x GTSAM':>8s}")
    rows = [
        ("GTSAM NavStateImuEKF.predict per sample (reference)", "gtsam"),
        ("stream, free vehicle, solution at 10 Hz (the default)", "free"),
        ("stream, free vehicle, solution at every sample", "free_all"),
        ("stream, ground vehicle + 10 Hz odometer, 10 Hz", "ground"),
        ("stream, ground vehicle + 10 Hz odometer, every sample", "ground_all"),
    ]
    for name, key in rows:
        us = 1e6 * times[key] / n
        print(f"{name:58s} {us:10.1f} {times[key] / times['gtsam']:8.1f}")
    print(
        f"the constructor (once per stream, its ephemeris): median {1e3 * np.median(built):.0f} ms"
    )


def latency(manifest: Path, executor: str) -> dict[str, np.ndarray]:
    """Wall time of each call on the caller's thread [s]; images 40 ms late, state() 10 Hz."""
    log = read_log(manifest)
    imu = log.imu[["t", "gx", "gy", "gz", "ax", "ay", "az"]].to_numpy()
    odo = log.odometry[["t", "speed"]].to_numpy()
    images = [(t, load_raw(item)) for t, item in log.images]
    cost: dict[str, list[float]] = {"add_imu": [], "add_image": [], "state": []}
    nav = NavigationStream.from_manifest(manifest, executor=executor)
    i = j = 0
    clock = time.perf_counter
    for k, (t, *sample) in enumerate(imu):
        c0 = clock()
        nav.add_imu(t, sample[:3], sample[3:])
        cost["add_imu"].append(clock() - c0)
        while i < len(odo) and odo[i, 0] <= t:
            nav.add_odometry(odo[i, 0], odo[i, 1])
            i += 1
        while j < len(images) and images[j][0] + 0.04 <= t:
            c0 = clock()
            nav.add_image(*images[j])
            cost["add_image"].append(clock() - c0)
            j += 1
        if k % 20 == 0:
            c0 = clock()
            nav.state()
            cost["state"].append(clock() - c0)
    nav.close()
    return {key: 1e3 * np.asarray(v) for key, v in cost.items()}


def latency_table(duration: float) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        sim = simulate_log(Path(tmp) / "log", scenario="ugv", duration_s=duration,
                           image_rate_hz=5.0, downscale=8, imu="mems-typical", seed=0,
                           progress=False)  # fmt: skip
        print(f"\ncalls on the caller's thread [ms]: simulated UGV log, {duration:g} s, images "
              "at 5 Hz (1/8 resolution) 40 ms late, state() at 10 Hz")  # fmt: skip
        print(
            f"{'executor':10s} {'call':10s} {'median':>8s} {'99 %':>8s} {'max':>8s} {'calls':>6s}"
        )
        for executor in ("thread", "process"):
            for call, ms in latency(sim.manifest, executor).items():
                print(f"{executor:10s} {call:10s} {np.median(ms):8.3f} "
                      f"{np.percentile(ms, 99):8.3f} {ms.max():8.2f} {ms.size:6d}")  # fmt: skip
        first_calls(sim.manifest)


FIRST = """
import time
c0 = time.perf_counter()
from polins.io import load_raw, read_log
from polins.loop import NavigationStream
c1 = time.perf_counter()
log = read_log({manifest!r})
imu = log.imu[["t", "gx", "gy", "gz", "ax", "ay", "az"]].to_numpy()
images = [(t, load_raw(item)) for t, item in log.images]
c2 = time.perf_counter()
nav = NavigationStream.from_manifest({manifest!r}, executor="process")
c3 = time.perf_counter()
first_run = first_image = None
j = 0
for t, *s in imu[:800]:
    n = 0 if nav.filter is None else nav.filter.count
    a = time.perf_counter()
    nav.add_imu(t, s[:3], s[3:])
    b = time.perf_counter()
    if first_run is None and nav.filter is not None and nav.filter.count > n:
        first_run = b - a
    if images[j][0] + 0.04 <= t:
        a = time.perf_counter()
        nav.add_image(*images[j])
        if j == 6:  # the first image after the levelling
            first_image = time.perf_counter() - a
        j += 1
nav.close()
print(f"import polins.loop {{1e3 * (c1 - c0):.0f}} ms; first constructor {{1e3 * (c3 - c2):.0f}}"
      f" ms; first add_imu that runs the filter {{1e3 * first_run:.1f}} ms; first add_image "
      f"after the levelling {{1e3 * first_image:.2f}} ms")
"""


def first_calls(manifest: Path) -> None:
    """The one-time costs, in a fresh interpreter."""
    code = FIRST.format(manifest=str(manifest))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=False, env=os.environ)  # fmt: skip
    if out.returncode:
        raise RuntimeError(out.stderr)
    print(f"\none-time costs (a fresh process): {out.stdout.strip()}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0, help="IMU record length [s]")
    ap.add_argument("--repeat", type=int, default=3, help="timing repeats (best is kept)")
    args = ap.parse_args()
    warnings.simplefilter("ignore", UserWarning)
    load = os.getloadavg()[0]
    print(f"{os.cpu_count()} cores, load average {load:.1f} at the start\n")
    per_sample_table(args.duration, args.repeat)
    latency_table(min(args.duration, 30.0))
    print(f"\nload average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main()
