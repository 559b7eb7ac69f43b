"""Command line: ``polins sun | demo | simulate | heading | fuse``.

The fault policy of docs/faults.md: a user mistake (a bad argument, file, unit, manifest or
naive time: :class:`polins.errors.UserInputError`, or a file that cannot be opened) prints
one readable line and exits with status 2, before any work where the check is cheap; a run
that produced nothing usable exits with status 1; any other exception is a bug in polins and
keeps its traceback (exit status 1). ``--debug`` shows the traceback of user mistakes too.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from polins.errors import UserInputError

Handler = Callable[[argparse.Namespace], int]


class ArgumentError(UserInputError):
    """A command-line argument with an impossible value (named in the message)."""


# Exceptions that report a user mistake; anything else is a bug and keeps its traceback.
USER_ERRORS = (UserInputError, FileNotFoundError, IsADirectoryError, NotADirectoryError,
               PermissionError)  # fmt: skip


def _check(ok: bool, message: str) -> None:
    """Raise :class:`ArgumentError` with ``message`` unless ``ok``."""
    if not ok:
        raise ArgumentError(message)


def _check_out_folder(out: str) -> None:
    from pathlib import Path

    _check(not Path(out).is_file(), f"--out {out}: is a file, expected a folder")


def _add_site_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--time", required=True, help="timezone-aware ISO time, e.g. 2023-09-05T15:06+08:00"
    )
    p.add_argument("--lat", type=float, required=True, help="latitude [deg, North positive]")
    p.add_argument("--lon", type=float, required=True, help="longitude [deg, East positive]")
    p.add_argument("--alt", type=float, default=0.0, help="height above the ellipsoid [m]")


def sun_report(time: str, lat_deg: float, lon_deg: float, alt_m: float) -> dict[str, object]:
    """Solar azimuth/zenith [deg] and the ENU sun vector at one time and place."""
    from polins.site import to_utc_index
    from polins.sky.ephemeris import sun_position, sun_vector_n

    sun = sun_position(time, lat_deg, lon_deg, alt_m)
    return {
        "time_utc": to_utc_index(time)[0].isoformat(),
        "lat_deg": lat_deg,
        "lon_deg": lon_deg,
        "alt_m": alt_m,
        "sun_azimuth_deg": float(np.degrees(sun.azimuth)),
        "sun_zenith_deg": float(np.degrees(sun.zenith)),
        "sun_n": [float(x) for x in sun_vector_n(sun.azimuth, sun.zenith)],
    }


def _cmd_sun(args: argparse.Namespace) -> int:
    from polins.site import Site

    Site(args.lat, args.lon, args.alt)  # a site out of range is named before any work
    report = sun_report(args.time, args.lat, args.lon, args.alt)
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    sun_n = np.asarray(report["sun_n"])
    print(f"time (UTC)        {report['time_utc']}")
    print(f"sun azimuth       {report['sun_azimuth_deg']:.4f} deg (clockwise from North)")
    print(f"sun zenith        {report['sun_zenith_deg']:.4f} deg (apparent)")
    print(f"sun vector (ENU)  [{sun_n[0]:+.6f}, {sun_n[1]:+.6f}, {sun_n[2]:+.6f}]")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from polins.sim.paper import run_demo

    downscale = 1 if args.full else args.downscale
    n_images = args.images if args.images is not None else (100 if args.full else 20)
    _check(downscale >= 1, f"--downscale {downscale}: expected an integer >= 1")
    _check(n_images >= 1, f"--images {n_images}: expected an integer >= 1")
    if not args.no_plots:
        _check_out_folder(args.out)
    print(
        f"polins demo: the paper's Section 4.1 simulation (docs/model.md §11), {n_images} images at "
        f"1/{downscale} resolution{' (use --full for full resolution)' if downscale > 1 else ''}",
        flush=True,
    )
    report, _ = run_demo(
        downscale=downscale,
        n_images=n_images,
        seed=args.seed,
        out=None if args.no_plots else args.out,
        progress=not args.quiet,
        occluder=not args.no_occluder,
    )
    print(report)
    return 0


def _cmd_simulate(args: argparse.Namespace) -> int:
    import time
    from pathlib import Path

    from polins.sim.scenario import simulate_log
    from polins.site import Site, utc_timestamp

    _check(args.downscale in (1, 2, 4, 8), f"--downscale {args.downscale}: expected 1, 2, 4 or 8")
    _check(
        args.duration is None or args.duration > 0, f"--duration {args.duration}: expected > 0 [s]"
    )
    _check(args.image_rate > 0, f"--image-rate {args.image_rate}: expected > 0 [Hz]")
    Site(args.lat, args.lon, args.alt)
    utc_timestamp(args.epoch, "--epoch")
    _check_out_folder(args.out)
    start = time.perf_counter()
    sim = simulate_log(
        Path(args.out),
        scenario=args.scenario,
        duration_s=args.duration,
        image_rate_hz=args.image_rate,
        downscale=args.downscale,
        imu=args.imu,
        seed=args.seed,
        epoch_utc=args.epoch,
        lat_deg=args.lat,
        lon_deg=args.lon,
        alt_m=args.alt,
        progress=not args.quiet,
    )
    elapsed = time.perf_counter() - start
    traj, cam = sim.trajectory, sim.camera
    elevation = np.degrees(np.arcsin(np.clip(sim.sun_n[:, 2], -1.0, 1.0)))
    print(f"wrote {sim.manifest}  ({elapsed:.1f} s)")
    print(f"scenario          {sim.scenario}, {traj.t[-1]:g} s, seed {args.seed}")
    print(f"imu               {len(sim.imu)} samples at {traj.rate_hz:g} Hz, {sim.imu_model.name}")
    print(f"images            {len(sim.image_t)} at {args.image_rate:g} Hz, {cam.name}")
    print(f"image size        {cam.shape[1]} x {cam.shape[0]} px (downscale {args.downscale})")
    print(f"truth             {len(traj)} rows (attitude, velocity, position, IMU errors)")
    print(f"epoch (UTC)       {sim.epoch_utc.isoformat()}")
    print(f"sun elevation     {elevation.min():.2f} .. {elevation.max():.2f} deg")
    if elevation.min() <= 0.0:
        print("note: the sun is below the horizon in part of the log", file=sys.stderr)
    return 0


def _rot0(text: str) -> Any:
    """``--rot0 ROLL,PITCH,HEADING`` [deg] as a Rotation (body -> ENU)."""
    from polins.frames import rot_nb_from_euler, yaw_from_heading_deg

    try:
        roll, pitch, heading = (float(v) for v in text.split(","))
    except ValueError:
        raise ArgumentError(f"--rot0 {text!r}: expected ROLL,PITCH,HEADING in degrees") from None
    yaw = float(yaw_from_heading_deg(heading))
    return rot_nb_from_euler(yaw, np.radians(pitch), np.radians(roll))


def _cmd_fuse(args: argparse.Namespace) -> int:
    from pathlib import Path

    from polins.fusion.config import FuseConfig
    from polins.io import read_log
    from polins.io.report import format_summary, summarize, write_report
    from polins.loop import LoopOptions, run_log

    _check(args.workers is None or args.workers >= 1, f"--workers {args.workers}: expected >= 1")
    _check(args.prior_lag >= 0, f"--prior-lag {args.prior_lag}: expected >= 0 [s]")
    _check(args.settle >= 0, f"--settle {args.settle}: expected >= 0 [s]")
    _check(not (args.smooth and args.backend != "eskf"), "--smooth needs --backend eskf")
    _check_out_folder(args.out)
    rot_nb0 = None if args.rot0 is None else _rot0(args.rot0)
    options = LoopOptions(method=args.method, update=args.update, prior_lag_s=args.prior_lag)
    try:
        log = read_log(args.manifest, gyro_unit=args.gyro_unit, accel_unit=args.accel_unit)
    except ImportError as exc:  # a ROS bag without the optional extra
        raise ArgumentError(str(exc)) from None
    changes: dict[str, Any] = {"smooth": True} if args.smooth else {}
    if args.nhc is not None:
        changes["nhc_std"] = args.nhc
    config = FuseConfig.from_options(log.config, **changes)
    config.check_backend(args.backend)
    result = run_log(
        log,
        options=options,
        config=config,
        backend=args.backend,
        workers=args.workers,
        rot_nb0=rot_nb0,
        progress=not args.quiet,
    )
    summary = summarize(
        result.solution,
        result.measurements,
        result.events,
        truth=log.truth,
        timing=result.timing,
        settings=result.settings,
        settle_s=args.settle,
    )
    files = write_report(
        Path(args.out),
        result.solution,
        result.measurements,
        result.events,
        summary,
        truth=log.truth,
        plots=not args.no_plots,
        title=log.manifest_path.parent.name,
    )
    print(format_summary(summary))
    print(f"wrote {', '.join(sorted(p.name for p in files.values()))} to {args.out}")
    if not summary["images"]["accepted_by_filter"]:
        print("polins fuse: no measurement was accepted by the filter", file=sys.stderr)
        return 1
    return 0


def _cmd_heading(args: argparse.Namespace) -> int:
    from pathlib import Path

    from polins.compass.measure import measure
    from polins.frames import rot_nb_from_euler
    from polins.io.images import read_image
    from polins.models.loader import load_camera
    from polins.site import Site, to_utc_index
    from polins.sky.ephemeris import sun_position, sun_vector_n

    path = Path(args.image)
    if not path.is_file():
        raise FileNotFoundError(f"image not found: {path}")
    cam = load_camera(args.camera)
    Site(args.lat, args.lon, args.alt)
    to_utc_index(args.time)
    raw = read_image(path, shape=cam.shape)
    sun = sun_position(args.time, args.lat, args.lon, args.alt)
    sun_n = sun_vector_n(sun.azimuth, sun.zenith)
    rot = rot_nb_from_euler(
        np.radians(args.yaw_prior), np.radians(args.pitch), np.radians(args.roll)
    )
    m = measure(raw, cam, sun_n=sun_n, rot_nb_prior=rot, method=args.method)
    report: dict[str, object] = {
        "image": str(path),
        "camera": cam.name,
        "time_utc": to_utc_index(args.time)[0].isoformat(),
        "sun_azimuth_deg": float(np.degrees(sun.azimuth)),
        "sun_zenith_deg": float(np.degrees(sun.zenith)),
        "heading_std_deg": float(np.degrees(m.yaw_std)) if m.ok else None,
        "yaw_deg": float(np.degrees(m.yaw)) if m.ok else None,
        **m.as_dict(),
    }
    if args.out:
        Path(args.out).write_text(json.dumps(report, indent=2) + "\n")
    if args.json:
        print(json.dumps(report, indent=2))
    elif not m.ok:
        print(f"no heading ({args.method}): {m.reason}")
    else:
        sun_b = ", ".join(f"{x:+.6f}" for x in m.sun_b)
        print(f"heading           {m.heading_deg:.4f} deg  (compass, clockwise from North)")
        print(
            f"sigma             {np.degrees(m.yaw_std):.4f} deg  (filter; measurement only "
            f"{np.degrees(m.yaw_std_meas):.5f} deg)"
        )
        print(f"yaw (ENU)         {np.degrees(m.yaw):.4f} deg  (counter-clockwise from East)")
        print(f"sun (body)        [{sun_b}]")
        if np.isfinite(m.epsilon_std):
            print(f"epsilon           {m.epsilon:.5f} +- {m.epsilon_std:.5f}")
        print(
            f"pixels            {m.n_pixels}  (eigen-gap {m.eigen_gap:.3f}, "
            f"residual RMS {m.residual_rms:.2f})"
        )
    return 0 if m.ok else 1


def _cmd_imu_model(args: argparse.Namespace) -> int:
    from pathlib import Path

    from polins.io import read_imu, write_text_atomic
    from polins.io.model_files import imu_model_toml
    from polins.tuning import imu_model_from_static, plot_allan

    out = Path(args.out)
    _check(out.suffix == ".toml", f"--out {out}: the IMU model file must end in .toml")
    _check(not out.is_dir(), f"--out {out} is a folder; give a .toml file name")
    imu = read_imu(args.static, gyro_unit=args.gyro_unit, accel_unit=args.accel_unit)
    model, fit = imu_model_from_static(
        imu, name=args.name or out.stem, grade=args.grade, source=args.static
    )
    write_text_atomic(out, imu_model_toml(model, comments=fit.comment_lines()))
    written = [str(out)]
    if args.plot:
        plot_allan(fit, args.plot)
        written.append(str(args.plot))
    print("\n".join(fit.notes))
    print(f"wrote {', '.join(written)}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The ``polins`` argument parser with all subcommands."""
    parser = argparse.ArgumentParser(
        prog="polins",
        description="Bio-inspired polarization navigation: sky images -> heading -> INS fusion.",
    )
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    p = sub.add_parser("sun", help="solar azimuth/zenith (NREL SPA) and the ENU sun vector")
    _add_site_args(p)
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(handler=_cmd_sun)

    p = sub.add_parser("demo", help="reproduce the paper's Section 4.1 simulation (table+plots)")
    p.add_argument("--full", action="store_true", help="full resolution, 100 images (minutes)")
    p.add_argument("--downscale", type=int, default=4, help="render at 1/K resolution (default 4)")
    p.add_argument("--images", type=int, default=None, help="images (default 20; 100 with --full)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument(
        "--out", default="out/demo", help="folder for plots and CSV tables (default out/demo)"
    )
    p.add_argument("--no-plots", action="store_true", help="print the table only, write nothing")
    p.add_argument("--no-occluder", action="store_true", help="skip the occluder case")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=_cmd_demo)

    p = sub.add_parser("simulate", help="simulate a scenario log (IMU, raw sky images, truth)")
    p.add_argument("--scenario", choices=["turntable", "ugv"], required=True)
    p.add_argument("--out", required=True, help="output folder of the log")
    p.add_argument(
        "--duration", type=float, default=None, help="[s] (default 100 turntable, 300 ugv)"
    )
    p.add_argument("--image-rate", type=float, default=5.0, help="camera rate [Hz] (default 5)")
    p.add_argument(
        "--imu", default="fins-paper", help="IMU model: fins-paper, mems-typical or a .toml path"
    )
    p.add_argument(
        "--downscale", type=int, default=4, help="render at 1/K resolution (1, 2, 4, 8; default 4)"
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--epoch", default="2023-09-05T15:06+08:00", help="timezone-aware time of t = 0")
    p.add_argument("--lat", type=float, default=45.6234, help="site latitude [deg]")
    p.add_argument("--lon", type=float, default=126.7264, help="site longitude [deg]")
    p.add_argument("--alt", type=float, default=148.74, help="site height [m]")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=_cmd_simulate)

    p = sub.add_parser("heading", help="heading from one raw polarization image (PNG/TIFF)")
    p.add_argument("image", help="raw DoFP mosaic, 16-bit PNG or TIFF, full resolution")
    p.add_argument("--camera", default="paper-table1", help="camera model name or .toml path")
    _add_site_args(p)
    p.add_argument("--roll", type=float, default=0.0, help="prior roll [deg] (FLU, right down +)")
    p.add_argument("--pitch", type=float, default=0.0, help="prior pitch [deg] (nose down +)")
    p.add_argument(
        "--yaw-prior",
        type=float,
        default=0.0,
        help="prior ENU yaw [deg, counter-clockwise from East]; used only near the horizon",
    )
    p.add_argument(
        "--method", choices=["compensated", "traditional", "paper"], default="compensated"
    )
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument("--out", default=None, help="also write the JSON report to this file")
    p.set_defaults(handler=_cmd_heading)

    p = sub.add_parser(
        "fuse", help="measure every image of a log and fuse with the IMU (solution, report)"
    )
    p.add_argument("manifest", help="manifest.toml of the log (or its folder)")
    p.add_argument("--out", required=True, help="output folder (CSV, JSON summary, PNG plots)")
    p.add_argument("--backend", choices=["eskf", "graph"], default="eskf")
    p.add_argument("--smooth", action="store_true", help="RTS smoother (ESKF backend)")
    p.add_argument("--workers", type=int, default=None, help="image processes (default all cores)")
    p.add_argument(
        "--method", choices=["compensated", "traditional", "paper"], default="compensated"
    )
    p.add_argument("--update", choices=["yaw", "sun"], default="yaw", help="filter update kind")
    p.add_argument("--prior-lag", type=float, default=1.0, help="age of the image prior [s]")
    p.add_argument("--nhc", type=float, default=None, help="non-holonomic constraint sigma [m/s]")
    p.add_argument(
        "--rot0", default=None, help="initial ROLL,PITCH,HEADING [deg] (default self-alignment)"
    )
    p.add_argument("--gyro-unit", choices=["rad/s", "deg/s"], default=None)
    p.add_argument("--accel-unit", choices=["m/s^2", "g"], default=None)
    p.add_argument("--settle", type=float, default=5.0, help="skip [s] in the error statistics")
    p.add_argument("--no-plots", action="store_true", help="write tables and JSON only")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=_cmd_fuse)
    p = sub.add_parser(
        "imu-model", help="IMU noise model (TOML) from a static recording (Allan deviation)"
    )
    p.add_argument("static", help="CSV/Parquet of the IMU at rest: t, gx, gy, gz, ax, ay, az")
    p.add_argument("--out", required=True, help="IMU model TOML to write")
    p.add_argument("--plot", default=None, help="Allan deviation plot (PNG) to write")
    p.add_argument("--grade", choices=["navigation", "tactical", "mems"], default="mems",
                   help="IMU grade: sets the plausible ranges and the terms a static "
                   "recording cannot show (default: %(default)s)")  # fmt: skip
    p.add_argument("--name", default=None, help="model name (default: the --out file's stem)")
    p.add_argument("--gyro-unit", choices=["rad/s", "deg/s"], default=None,
                   help="unit of gx, gy, gz if the file does not declare it")  # fmt: skip
    p.add_argument("--accel-unit", choices=["m/s^2", "g"], default=None,
                   help="unit of ax, ay, az if the file does not declare it")  # fmt: skip
    p.set_defaults(handler=_cmd_imu_model)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``polins`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    handler: Handler = args.handler
    try:
        return handler(args)
    except USER_ERRORS as exc:
        if args.debug:
            raise
        message = "; ".join(line.strip() for line in str(exc).splitlines() if line.strip())
        print(f"polins {args.command}: error: {message}", file=sys.stderr)
        return 2


__all__ = ["USER_ERRORS", "ArgumentError", "build_parser", "main", "sun_report"]
