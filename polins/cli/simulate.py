"""Commands ``polins demo`` (the paper's simulation, tables and plots) and ``polins simulate`` (a scenario log).

Both render raw sky images with :mod:`polins.sim`: ``demo`` reproduces the paper's
Section 4.1 and writes an output set of tables and plots; ``simulate`` writes a log
folder (manifest, IMU, images, truth) that ``polins fuse`` reads.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

from polins.cli.common import check, finite
from polins.io.outputs import check_output_folder

__all__ = ["DEMO_FILES", "LOG_FILES", "add_demo", "add_simulate", "cmd_demo", "cmd_simulate"]

LOG_FILES = ("manifest.toml", "imu.csv", "imu.parquet", "images.csv", "images", "truth.csv",
             "camera.toml", "imu_model.toml", "odometer.csv")  # fmt: skip
DEMO_FILES = ("summary.csv", "images.csv", "schema.json", "paper_fig6_headings.png",
              "paper_fig7_errors.png", "occluder_fig6_headings.png", "occluder_fig7_errors.png")  # fmt: skip


def cmd_demo(args: argparse.Namespace) -> int:
    import pandas as pd

    from polins.io.outputs import output_set, to_json
    from polins.io.report import CSV_FLOAT_FORMAT
    from polins.io.schema import schema_for
    from polins.io.tables import write_table
    from polins.sim.paper import plot_reproduction, run_demo

    downscale = 1 if args.full else args.downscale
    n_images = args.images if args.images is not None else (100 if args.full else 20)
    check(downscale >= 1, f"--downscale {downscale}: expected an integer >= 1")
    check(n_images >= 1, f"--images {n_images}: expected an integer >= 1")
    if not args.no_plots:
        check_output_folder(args.out, DEMO_FILES)
    print(
        f"polins demo: the paper's Section 4.1 simulation (docs/model.md §11), {n_images} images at "
        f"1/{downscale} resolution{' (use --full for full resolution)' if downscale > 1 else ''}",
        flush=True,
    )
    report, runs = run_demo(downscale=downscale, n_images=n_images, seed=args.seed, out=None,
                            progress=not args.quiet, occluder=not args.no_occluder)  # fmt: skip
    if args.no_plots:
        print(report)
        return 0
    with output_set(args.out, command="demo", known=DEMO_FILES) as out:
        out.stamp["settings"] = {"downscale": downscale, "images": n_images, "seed": args.seed,
                                 "occluder": not args.no_occluder}  # fmt: skip
        for r, prefix in zip(runs, ("paper_", "occluder_"), strict=False):
            plot_reproduction(r, out.path, prefix=prefix)
        tables = {
            "summary.csv": pd.concat([r.summary.assign(scenario=r.scenario.name,
                                                       crlb_deg=r.crlb_deg) for r in runs]),
            "images.csv": pd.concat([r.images.assign(scenario=r.scenario.name) for r in runs]),
        }  # fmt: skip
        for name, df in tables.items():
            write_table(out.path / name, df, float_format=CSV_FLOAT_FORMAT)
        (out.path / "schema.json").write_text(to_json(schema_for(tables)), encoding="utf-8")
        files = [*out.files(), "run.json"]
    print(report)
    print(f"wrote {', '.join(sorted(files))} to {args.out}")
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    import time

    from polins.io.outputs import output_set
    from polins.models import load_imu
    from polins.sim.scenario import DEFAULT_IMAGE_RATE_HZ, simulate_log
    from polins.site import Site, utc_timestamp

    check(args.downscale in (1, 2, 4, 8), f"--downscale {args.downscale}: expected 1, 2, 4 or 8")
    check(
        args.duration is None or args.duration > 0, f"--duration {args.duration}: expected > 0 [s]"
    )
    check(
        args.image_rate is None or args.image_rate > 0,
        f"--image-rate {args.image_rate}: expected > 0 [Hz]",
    )
    Site(args.lat, args.lon, args.alt)
    utc_timestamp(args.epoch, "--epoch")
    load_imu(args.imu)  # an unknown model is named before any work
    check_output_folder(args.out, LOG_FILES)
    start = time.perf_counter()
    with output_set(args.out, command="simulate", known=LOG_FILES) as out:
        out.stamp["settings"] = {k: v for k, v in vars(args).items() if k != "handler"}
        sim = simulate_log(out.path, scenario=args.scenario, duration_s=args.duration,
                           image_rate_hz=args.image_rate, downscale=args.downscale,
                           imu=args.imu, seed=args.seed, epoch_utc=args.epoch, lat_deg=args.lat,
                           lon_deg=args.lon, alt_m=args.alt, sky=args.sky,
                           progress=not args.quiet)  # fmt: skip
    elapsed = time.perf_counter() - start
    traj, cam = sim.trajectory, sim.camera
    elevation = np.degrees(np.arcsin(np.clip(sim.sun_n[:, 2], -1.0, 1.0)))
    print(f"wrote {Path(args.out) / sim.manifest.name}  ({elapsed:.1f} s)")
    print(f"scenario          {sim.scenario}, {traj.t[-1]:g} s, seed {args.seed}")
    print(f"imu               {len(sim.imu)} samples at {traj.rate_hz:g} Hz, {sim.imu_model.name}")
    rate = DEFAULT_IMAGE_RATE_HZ[args.scenario] if args.image_rate is None else args.image_rate
    print(f"images            {len(sim.image_t)} at {rate:.3g} Hz, {cam.name}")
    print(f"image size        {cam.shape[1]} x {cam.shape[0]} px (downscale {args.downscale})")
    print(f"truth             {len(traj)} rows (attitude, velocity, position, IMU errors)")
    if sim.vehicle is not None and sim.odometry is not None:
        v = sim.vehicle
        print(f"vehicle           {v['kind']}: IMU mounted at roll/pitch/yaw "
              f"{'/'.join(f'{a:g}' for a in v['mount_rpy_deg'])} deg, lever arm "
              f"{'/'.join(f'{a:g}' for a in v['lever_arm_b'])} m")  # fmt: skip
        print(f"odometer          {len(sim.odometry)} speeds in {v['odometer']} "
              f"(sigma {v['odometer_std']:g} m/s, scale error +1 %)")  # fmt: skip
    if sim.real_sky is not None:
        rs = sim.real_sky
        print(f"sky               realistic: CIE type {rs.sky_type}, neutral points "
              f"{np.degrees(rs.neutral_sep):.0f} deg apart, {len(rs.clouds)} thin clouds, "
              f"vignetting {rs.vignetting:.2f}, channel-gain residual "
              f"{'/'.join(f'{100 * g:+.2f}' for g in rs.gain_residual)} %")  # fmt: skip
    print(f"epoch (UTC)       {sim.epoch_utc.isoformat()}")
    print(f"sun elevation     {elevation.min():.2f} .. {elevation.max():.2f} deg")
    if elevation.min() <= 0.0:
        print("note: the sun is below the horizon in part of the log", file=sys.stderr)
    return 0


def add_demo(sub: Any) -> None:
    """Register ``polins demo``."""
    p = sub.add_parser("demo", help="reproduce the paper's Section 4.1 simulation (table+plots)")
    p.add_argument("--full", action="store_true", help="full resolution, 100 images (minutes)")
    p.add_argument("--downscale", type=int, default=4, help="render at 1/K resolution")
    p.add_argument("--images", type=int, default=None, help="images (None: 20; 100 with --full)")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument("--out", default="out/demo", help="folder for plots and CSV tables")
    p.add_argument("--no-plots", action="store_true", help="print the table only, write nothing")
    p.add_argument("--no-occluder", action="store_true", help="skip the occluder case")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=cmd_demo)


def add_simulate(sub: Any) -> None:
    """Register ``polins simulate``."""
    p = sub.add_parser("simulate", help="simulate a scenario log (IMU, raw sky images, truth)")
    p.add_argument("--scenario", choices=["turntable", "ugv", "static"], required=True,
                   help="turntable: the paper's level turntable, 7.2 deg/s; ugv: a ground "
                   "vehicle's drive with odometer, IMU mounting and road vibration; static: "
                   "the IMU at rest, a record for polins imu-model")  # fmt: skip
    p.add_argument("--out", required=True, help="output folder of the log")
    p.add_argument("--duration", type=finite, default=None,
                   help="length [s] (default: 100 turntable, 300 ugv, 7200 static)")  # fmt: skip
    p.add_argument("--image-rate", type=finite, default=None,
                   help="camera rate [Hz] (default: 5; static: one image a minute)")  # fmt: skip
    p.add_argument("--imu", default="fins-paper",
                   help="IMU model: fins-paper (navigation-grade FOG), mems-typical or a .toml "
                   "path")  # fmt: skip
    p.add_argument("--downscale", type=int, default=8,
                   help="render at 1/K resolution (1, 2, 4, 8); 8 writes about 1/64 of the "
                   "full-resolution images' size")  # fmt: skip
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument("--sky", choices=["model", "realistic"], default="model",
                   help="model: the estimator's own sky, exact camera calibration; realistic: "
                   "CIE radiance, neutral points, thin clouds, vignetting and a channel-gain "
                   "residual, rendered independently of the estimator")  # fmt: skip
    p.add_argument("--epoch", default="2023-09-05T15:06+08:00", help="timezone-aware time of t = 0")
    p.add_argument("--lat", type=finite, default=45.6234, help="site latitude [deg]")
    p.add_argument("--lon", type=finite, default=126.7264, help="site longitude [deg]")
    p.add_argument("--alt", type=finite, default=148.74, help="site height [m]")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=cmd_simulate)
