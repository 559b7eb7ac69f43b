"""Speed of ``polins.fuse`` (15-state ESKF, 10 Hz polarization yaw) beside GTSAM's C++ EKF.

Prints IMU samples per second of, in the same run and over the same IMU samples:

* GTSAM's ``gtsam.NavStateImuEKF.predict`` (9-state navigation EKF in C++, propagation
  only) driven sample by sample from Python;
* ``polins.fuse`` (batch path, vectorised between resets), with one output row per IMU
  sample and with 10 Hz output;
* the straightforward per-sample ESKF (``fast=False``: one ``propagate`` per sample), and
  the largest difference between the two paths (they must agree to 1e-9 rad).

Run: ``python benchmarks/bench_fuse.py [--duration 120] [--imu mems-typical] [--repeat 3]``.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
import pandas as pd

import polins
from polins.attitude import wrap_angle
from polins.sim.imu import ideal_imu, imu_errors
from polins.sim.trajectory import ugv_drive


def simulate(duration: float, model: polins.ImuModel, seed: int = 0):
    rng = np.random.default_rng(seed)
    traj = ugv_drive(duration_s=duration, rate_hz=model.sample_rate_hz, rng=rng)
    imu, _ = imu_errors(ideal_imu(traj, earth_rotation=model.earth_rate), model, rng)
    truth = traj.truth_frame()
    t_meas = np.arange(0.05, duration, 0.1)  # 10 Hz, between IMU samples
    yaw = np.interp(t_meas, truth.t, np.unwrap(truth.yaw))
    std = np.radians(0.3)
    meas = pd.DataFrame(
        {"t": t_meas, "yaw": wrap_angle(yaw + rng.normal(0.0, std, t_meas.size)), "yaw_std": std}
    )
    return traj, imu, meas


def gtsam_rate(imu: pd.DataFrame, model: polins.ImuModel, repeat: int) -> float:
    import gtsam

    g = float(polins.earth.normal_gravity(np.radians(45.6234), 148.74))
    params = gtsam.PreintegrationParams.MakeSharedU(g)
    params.setGyroscopeCovariance(np.eye(3) * model.gyro_arw**2)
    params.setAccelerometerCovariance(np.eye(3) * model.accel_vrw**2)
    params.setIntegrationCovariance(np.eye(3) * 1e-8)
    t = imu["t"].to_numpy()
    w = imu[["gx", "gy", "gz"]].to_numpy()
    f = imu[["ax", "ay", "az"]].to_numpy()
    dt = np.diff(t)
    best = np.inf
    for _ in range(repeat):
        ekf = gtsam.NavStateImuEKF(gtsam.NavState(), np.eye(9) * 1e-4, params)
        t0 = time.perf_counter()
        for k in range(len(dt)):
            ekf.predict(w[k], f[k], dt[k])
        best = min(best, time.perf_counter() - t0)
    return len(dt) / best


def filterpy_floor(n_samples: int, n_updates: int, repeat: int) -> float:
    """Samples/s if the run cost only filterpy's predict + update at each 10 Hz epoch."""
    from filterpy.kalman import predict, update

    rng = np.random.default_rng(0)
    Phi = np.eye(15) + 1e-3 * rng.standard_normal((15, 15))
    Q, P = np.eye(15) * 1e-8, np.eye(15) * 1e-4
    H = np.zeros((1, 15))
    H[0, 2] = 1.0
    R = np.array([[1e-5]])
    best = np.inf
    for _ in range(repeat):
        x, Pk = np.zeros(15), P
        t0 = time.perf_counter()
        for _ in range(n_updates):
            x, Pk = predict(x, Pk, Phi, Q)
            x, Pk = update(x, Pk, np.array([1e-3]), R, H)
        best = min(best, time.perf_counter() - t0)
    return n_samples / best


def fuse_rate(imu, meas, repeat: int, **kw) -> tuple[float, pd.DataFrame]:
    best = np.inf
    sol = None
    for _ in range(repeat):
        t0 = time.perf_counter()
        sol = polins.fuse(imu, meas, **kw)
        best = min(best, time.perf_counter() - t0)
    return len(imu) / best, sol


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=120.0, help="drive length [s]")
    ap.add_argument("--imu", default="mems-typical", help="IMU model name")
    ap.add_argument("--repeat", type=int, default=3, help="timing repeats (best is kept)")
    ap.add_argument(
        "--streaming-s", type=float, default=20.0, help="length for the per-sample path [s]"
    )
    args = ap.parse_args()
    warnings.simplefilter("ignore", UserWarning)
    model = polins.load_imu(args.imu)
    _, imu, meas = simulate(args.duration, model)
    site = dict(lat_deg=45.6234, lon_deg=126.7264, alt_m=148.74, imu_model=model)
    r_gtsam = gtsam_rate(imu, model, args.repeat)
    r_all, _ = fuse_rate(imu, meas, args.repeat, **site)
    r_10, _ = fuse_rate(imu, meas, args.repeat, output_rate_hz=10.0, **site)
    r_floor = filterpy_floor(len(imu), len(meas), args.repeat)
    n_s = int(args.streaming_s * model.sample_rate_hz) + 1
    short_imu, short_meas = imu.iloc[:n_s], meas[meas.t < imu.t.iloc[n_s - 1]]
    r_stream, slow = fuse_rate(short_imu, short_meas, 1, fast=False, **site)
    fast = polins.fuse(short_imu, short_meas, **site)
    diff = max(
        float(np.nanmax(np.abs(wrap_angle(fast[c] - slow[c])))) for c in ("roll", "pitch", "yaw")
    )
    print(f"IMU {model.name}, {len(imu)} samples at {model.sample_rate_hz:g} Hz, "
          f"{len(meas)} yaw updates (10 Hz)")  # fmt: skip
    print(f"{'method':58s} {'samples/s':>12s} {'vs GTSAM':>9s}")
    rows = [
        ("GTSAM NavStateImuEKF.predict (C++, 9 states, no updates)", r_gtsam),
        ("polins.fuse, 15-state ESKF + 10 Hz updates, output every sample", r_all),
        ("polins.fuse, same filter, 10 Hz output", r_10),
        ("per-sample ESKF (fast=False, streaming path)", r_stream),
        ("floor: filterpy predict+update alone per 10 Hz epoch", r_floor),
    ]
    for name, r in rows:
        print(f"{name:58s} {r:12.0f} {r / r_gtsam:9.2f}")
    print(
        f"max |attitude difference| batch vs per-sample over {args.streaming_s:g} s: {diff:.2e} rad"
    )


if __name__ == "__main__":
    main()
