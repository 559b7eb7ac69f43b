"""Attitude consistency of the ESKF without velocity aiding, with the simulated effects switched.

A vehicle without a ``[vehicle]`` table (a drone, a hand-held rig, a robot without odometry)
gets no non-holonomic, zero-velocity or odometer updates: the camera's headings, the
zero-rate updates at its stops and the accelerometer's levelling once a second
(docs/filter.md §12). The
drives are those of ``polins simulate --scenario ugv`` (the same random streams for a seed:
trajectory, mounting, road vibration, IMU errors), and the headings are drawn in closed
loop as the camera loop makes them: ``polins.measure`` levels the sun it sees with the
filter's own attitude (the prior), so the yaw it returns is the tilt-coupled model of
docs/filter.md §5.2, ``h(x_true; prior)``, plus white noise (default 0.011 deg at 5 Hz,
the images' sigma on the simulated sky). The filter uses that model (``tilt_coupling``).

Prints, per variant and seed, yaw / pitch / roll RMS(err/sigma) after the first 5 s and,
pooled over the seeds, the RMS of those and the RMS errors [deg]. Variants switch one
simulated effect off in the drive (the filter's model unchanged): ``novib`` (no road
vibration), ``nogyrobias`` (no gyro turn-on bias), ``nogyroarw`` (no gyro white noise),
``noaccel`` (no accelerometer errors).

``--broad`` runs the BROAD trials without zero-velocity rows instead (ESKF, graph and the
``ahrs`` package's EKF when installed; docs/filter.md §12.4). ``--replay graph,smooth`` also fuses each drive's recorded headings (with their priors and
``sun_n``) with the graph backend (batch solver) and the ESKF with the RTS smoother.

Run: ``nice python benchmarks/bench_free_vehicle.py [--seeds 0-7] [--duration 200]
[--variants all,novib,nogyrobias] [--replay graph]`` (about 5 s of CPU per drive of 200 s
for the ESKF, 15 s more for the graph).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time

import numpy as np
import pandas as pd
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from polins.fusion.api import build_filter, run_fusion
from polins.fusion.config import FuseConfig
from polins.fusion.measurement import yaw_kernel
from polins.ins.state import euler_jacobian
from polins.models import ImuModel, load_imu
from polins.sim.imu import ideal_imu, imu_errors
from polins.sim.scenario import DEFAULT_EPOCH, scenario_trajectory
from polins.sim.vehicle import (
    UGV_LEVER_ARM_B,
    UGV_MOUNT_RPY_DEG,
    forward_speed,
    mounted_trajectory,
    road_vibration,
)
from polins.site import PAPER_SITE
from polins.sky.ephemeris import sun_position, sun_vector_n

FloatArray = NDArray[np.float64]
SITE = {"lat_deg": PAPER_SITE.lat_deg, "lon_deg": PAPER_SITE.lon_deg, "alt_m": PAPER_SITE.alt_m}
ANGLES = ("yaw", "pitch", "roll")


def drive(seed: int, duration_s: float, model: ImuModel, vibration: bool = True):
    """The ugv scenario's IMU trajectory and IMU table of ``seed`` (``simulate_log``'s
    streams), the sun vector at mid-drive, the image-noise generator and the true IMU
    errors (``imu_errors``' second table)."""
    rng_traj, rng_imu, rng_img, rng_vib, *_ = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(6)
    )
    vehicle = scenario_trajectory("ugv", duration_s=duration_s, rng=rng_traj)
    traj = mounted_trajectory(vehicle, np.radians(UGV_MOUNT_RPY_DEG), UGV_LEVER_ARM_B)
    ideal = ideal_imu(traj)
    gyro_vib, accel_vib = road_vibration(traj.t, forward_speed(vehicle), rng_vib)
    if vibration:
        ideal[["gx", "gy", "gz"]] += gyro_vib
        ideal[["ax", "ay", "az"]] += accel_vib
    imu, errors = imu_errors(ideal, model, rng_imu)
    when = pd.DatetimeIndex([pd.Timestamp(DEFAULT_EPOCH) + pd.Timedelta(seconds=duration_s / 2)])
    sun = sun_position(when, **SITE)
    return traj, imu, sun_vector_n(sun.azimuth, sun.zenith)[0], rng_img, errors


def closed_loop(traj, imu, sun_n, rng, model, rate_hz=5.0, std_deg=0.011, rows=None, **options):
    """Run the ESKF with tilt-coupled headings drawn with its own attitude as the prior;
    returns the sample indices, estimated attitudes and attitude covariances at the headings,
    and the NIS of the accepted headings. ``rows`` (a list) receives the headings as rows of
    a measurements table (``t, yaw, yaw_std``, ``sun_n*``, ``prior_*``)."""
    cfg = FuseConfig.from_options(imu_model=model, **SITE, tilt_coupling=True, **options)
    t = imu["t"].to_numpy()
    gyro, accel = imu[["gx", "gy", "gz"]].to_numpy(), imu[["ax", "ay", "az"]].to_numpy()
    filt = build_filter(t[0], t[1] - t[0], None, cfg)
    std = math.radians(std_deg)
    k, index, mats, covs = 0, [], [], []
    for t_img in np.arange(1.0, t[-1] + 1e-9, 1.0 / rate_hz):
        stop = int(np.searchsorted(t, t_img + 1e-9))
        filt.propagate_many(t[k:stop], gyro[k:stop], accel[k:stop])
        k, j = stop, stop - 1
        prior = filt.state().rot_nb
        lin = yaw_kernel(traj.rot_nb[j].as_matrix(), 0.0, 1.0, sun_n, prior.as_matrix())
        yaw = -float(lin.residual[0]) + std * rng.standard_normal()
        filt.add_measurement(t[j], yaw=yaw, yaw_std=std, sun_n=sun_n, rot_nb_prior=prior)
        if rows is not None:
            ypr = prior.as_euler("ZYX")
            rows.append({"t": t[j], "yaw": yaw, "yaw_std": std, "sun_nx": sun_n[0],
                         "sun_ny": sun_n[1], "sun_nz": sun_n[2], "prior_yaw": ypr[0],
                         "prior_pitch": ypr[1], "prior_roll": ypr[2], "sun_bx": np.nan,
                         "sun_by": np.nan, "sun_bz": np.nan, "sun_std": np.nan})  # fmt: skip
        state = filt.state()
        if state.yaw_aligned:
            index.append(j)
            mats.append(state.rot_nb.as_matrix())
            covs.append(state.att_cov)
    nis = np.array([r.nis for r in filt.records if r.name == "yaw" and r.accepted])
    nis = nis[np.isfinite(nis)]  # the headings of the yaw acquisition have none
    return np.array(index), np.stack(mats), np.stack(covs), nis


def scores(traj, index, mats, covs, t_min: float = 5.0) -> dict[str, tuple[float, float]]:
    """Per angle: RMS error [deg] and RMS(err/sigma) after ``t_min`` [s]."""
    keep = traj.t[index] > t_min
    est = Rotation.from_matrix(mats[keep]).as_euler("ZYX")
    truth = traj.rot_nb[index[keep]].as_euler("ZYX")
    J = euler_jacobian(est[:, 0], est[:, 1])
    sigma = np.sqrt(np.einsum("nij,njk,nik->ni", J, covs[keep], J))
    err = np.angle(np.exp(1j * (est - truth)))
    return {a: (math.degrees(float(np.sqrt(np.mean(err[:, i] ** 2)))),
                float(np.sqrt(np.mean((err[:, i] / sigma[:, i]) ** 2))))
            for i, a in enumerate(ANGLES)}  # fmt: skip


def replay(traj, imu, rows, model, backend="graph", t_min: float = 5.0, **options):
    """The recorded headings ``rows`` fused by ``run_fusion`` (``backend``, tilt-coupled,
    output at 5 Hz); per angle: RMS error [deg] and RMS(err/sigma) after ``t_min`` [s]."""
    cfg = FuseConfig.from_options(imu_model=model, **SITE, tilt_coupling=True,
                                  output_rate_hz=5.0, **options)  # fmt: skip
    sol = run_fusion(imu, pd.DataFrame(rows), backend, None, cfg).solution
    sol = sol[np.isfinite(sol["yaw"].to_numpy()) & (sol["t"].to_numpy() > t_min)]
    k = np.searchsorted(traj.t, sol["t"].to_numpy() - 1e-9)
    truth = traj.rot_nb[k].as_euler("ZYX")
    out = {}
    for i, a in enumerate(ANGLES):
        err = np.angle(np.exp(1j * (sol[a].to_numpy() - truth[:, i])))
        z = err / sol[f"{a}_std"].to_numpy()
        out[a] = (math.degrees(float(np.sqrt(np.mean(err**2)))), float(np.sqrt(np.mean(z**2))))
    return out


def broad(trial: str) -> None:
    """A BROAD trial (tests/test_broad.py's set-up: 1 Hz headings of 0.5 deg, the truth as
    the first attitude) without zero-velocity rows: the ESKF, the graph and, if installed,
    the ``ahrs`` package's EKF (gyro and accelerometer; it takes no heading without a
    magnetometer, so only its tilt compares). Prints RMS(err/sigma) and RMS errors [deg]."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from test_broad import SITE as BERLIN
    from test_broad import broad_trial, score

    imu, meas, truth, rot0 = broad_trial(trial)
    heading = meas[meas["yaw"].notna()][["t", "yaw", "yaw_std"]]
    cfg = FuseConfig.from_options(imu_model="broad-aktos-t", output_rate_hz=2.0, **BERLIN)
    for backend in ("eskf", "graph"):
        s = score(run_fusion(imu, heading, backend, rot0, cfg).solution, truth)
        print(f"trial {trial} {backend:5s} RMS(err/sigma) "
              + " / ".join(f"{s[a][0]:.2f}" for a in ANGLES) + "  RMS error [deg] "
              + " / ".join(f"{s[a][2]:.3f}" for a in ANGLES), flush=True)  # fmt: skip
    try:
        from ahrs.filters import EKF  # optional: not a polins dependency
    except ImportError:
        print("ahrs is not installed: no attitude-filter comparison")
        return
    t = imu["t"].to_numpy()
    gyro, accel = imu[["gx", "gy", "gz"]].to_numpy(), imu[["ax", "ay", "az"]].to_numpy()
    # ahrs' ENU frame takes the accelerometer with the opposite sign (checked at rest)
    q = EKF(gyr=gyro, acc=-accel, frequency=1.0 / float(np.median(np.diff(t))), frame="ENU",
            q0=rot0.as_quat()[[3, 0, 1, 2]]).Q  # fmt: skip
    ypr = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_euler("ZYX")
    sol = pd.DataFrame({"t": t, **{a: ypr[:, i] for i, a in enumerate(ANGLES)},
                        **{f"{a}_std": 1.0 for a in ANGLES}}).iloc[::143]  # fmt: skip
    s = score(sol, truth)
    print(f"trial {trial} ahrs EKF  RMS error [deg] pitch / roll "
          + " / ".join(f"{s[a][2]:.3f}" for a in ANGLES[1:]), flush=True)  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="0-7", help="first-last or a comma list")
    parser.add_argument("--duration", type=float, default=200.0, help="[s]")
    parser.add_argument("--variants", default="all,novib,nogyrobias")
    parser.add_argument("--replay", default="", help="also replay the headings: graph,smooth")
    parser.add_argument("--broad", action="store_true", help="the BROAD trials instead")
    args = parser.parse_args()
    args.replay = [b for b in args.replay.split(",") if b]
    if args.broad:
        for trial in ("02", "15"):
            broad(trial)
        return
    if "-" in args.seeds:
        first, last = (int(s) for s in args.seeds.split("-"))
        seeds = list(range(first, last + 1))
    else:
        seeds = [int(s) for s in args.seeds.split(",")]
    model = load_imu("mems-typical")
    variants = {
        "all": (model, True),
        "novib": (model, False),
        "nogyrobias": (dataclasses.replace(model, gyro_bias=0.0), True),
        "nogyroarw": (dataclasses.replace(model, gyro_arw=0.0), True),
        "noaccel": (dataclasses.replace(model, accel_vrw=0.0, accel_bias=0.0, accel_bias_rw=0.0,
                                        accel_scale_factor=0.0), True),
    }  # fmt: skip
    for name in args.variants.split(","):
        sim_model, vibration = variants[name]
        runs: dict[str, tuple[list, list]] = {b: ([], []) for b in ["eskf", *args.replay]}
        start = time.process_time()
        for seed in seeds:
            traj, imu, sun_n, rng, _ = drive(seed, args.duration, sim_model, vibration)
            rows: list[dict[str, float]] = []
            out = closed_loop(traj, imu, sun_n, rng, model, rows=rows)
            found = {"eskf": scores(traj, *out[:3])}
            for backend in args.replay:  # the same headings, replayed
                opts = {"smooth": True} if backend == "smooth" else {}
                found[backend] = replay(
                    traj, imu, rows, model, "eskf" if backend == "smooth" else backend, **opts
                )
            for backend, s in found.items():
                ratios, errors = runs[backend]
                ratios.append([s[a][1] for a in ANGLES])
                errors.append([s[a][0] for a in ANGLES])
                print(f"{name:11s} {backend:6s} seed {seed:3d}  RMS(err/sigma) "
                      + " / ".join(f"{r:.2f}" for r in ratios[-1])
                      + "  RMS error [deg] " + " / ".join(f"{e:.3f}" for e in errors[-1])
                      + (f"  heading NIS mean {np.mean(out[3]):.2f}" if backend == "eskf" else ""),
                      flush=True)  # fmt: skip
        for backend, (ratios, errors) in runs.items():
            pooled = np.sqrt(np.mean(np.square(ratios), axis=0))
            err = np.sqrt(np.mean(np.square(errors), axis=0))
            print(f"{name:11s} {backend:6s} pooled over {len(seeds)} drives: RMS(err/sigma) "
                  + "yaw / pitch / roll " + " / ".join(f"{r:.2f}" for r in pooled)
                  + ", RMS error [deg] " + " / ".join(f"{e:.3f}" for e in err)
                  + f" ({time.process_time() - start:.0f} s CPU)", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
