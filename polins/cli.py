"""Command line: ``polins sun | demo | simulate | heading | fuse | imu-model``.

The fault policy of docs/faults.md: a user mistake (a bad argument, file, unit, manifest or
naive time: :class:`polins.errors.UserInputError`, or a file that cannot be opened) prints
one readable line and exits with status 2, before any work where the check is cheap; a run
that produced nothing usable exits with status 1 after writing its outputs whole; any other
exception is a bug in polins and keeps its traceback (exit status 1). ``--debug`` shows the
traceback of user mistakes too. Ctrl-C (or SIGTERM) prints one line and exits with status
130 (143), leaving the previous output set; a closed pipe (``| head``) ends quietly (141).
Output folders are written whole (:mod:`polins.io.outputs`, docs/outputs.md).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from polins.errors import UserInputError
from polins.io.outputs import Terminated, check_output_folder, signals_unwind

Handler = Callable[[argparse.Namespace], int]
LOG_FILES = ("manifest.toml", "imu.csv", "imu.parquet", "images.csv", "images", "truth.csv",
             "camera.toml", "imu_model.toml")  # fmt: skip
FUSE_FILES = ("solution.csv", "measurements.csv", "events.csv", "summary.json", "schema.json",
              "heading.png", "heading_error.png", "measurements.png", "epsilon.png")  # fmt: skip
DEMO_FILES = ("summary.csv", "images.csv", "schema.json", "paper_fig6_headings.png",
              "paper_fig7_errors.png", "occluder_fig6_headings.png", "occluder_fig7_errors.png")  # fmt: skip


class ArgumentError(UserInputError):
    """A command-line argument with an impossible value (named in the message)."""


# Exceptions that report a user mistake; anything else is a bug and keeps its traceback.
USER_ERRORS = (UserInputError, FileNotFoundError, IsADirectoryError, NotADirectoryError,
               PermissionError)  # fmt: skip


def _check(ok: bool, message: str) -> None:
    """Raise :class:`ArgumentError` with ``message`` unless ``ok``."""
    if not ok:
        raise ArgumentError(message)


def _finite(text: str) -> float:
    """argparse type: a finite number (``inf`` and ``nan`` are refused)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r}: expected a finite number")
    return value


def _fraction(text: str) -> float:
    """argparse type: ``50%`` or ``0.5``, a share in [0, 1]."""
    percent = text.strip().endswith("%")
    try:
        value = float(text.strip().rstrip("%")) / (100.0 if percent else 1.0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a share like 50% or 0.5") from None
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a share in 0%..100%")
    return value


def _angle(option: str, value: float, lo: float, hi: float) -> None:
    """Check an angle argument [deg] is in ``[lo, hi]`` (finite by its argparse type)."""
    _check(lo <= value <= hi, f"{option} {value:g}: expected an angle in [{lo:g}, {hi:g}] deg")


def _add_site_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--time", required=True, help="timezone-aware ISO time, e.g. 2023-09-05T15:06+08:00"
    )
    p.add_argument("--lat", type=_finite, required=True, help="latitude [deg, North positive]")
    p.add_argument("--lon", type=_finite, required=True, help="longitude [deg, East positive]")
    p.add_argument("--alt", type=_finite, default=0.0, help="height above the ellipsoid [m]")


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
    import pandas as pd

    from polins.io.outputs import output_set, to_json
    from polins.io.report import CSV_FLOAT_FORMAT
    from polins.io.schema import schema_for
    from polins.io.tables import write_table
    from polins.sim.paper import plot_reproduction, run_demo

    downscale = 1 if args.full else args.downscale
    n_images = args.images if args.images is not None else (100 if args.full else 20)
    _check(downscale >= 1, f"--downscale {downscale}: expected an integer >= 1")
    _check(n_images >= 1, f"--images {n_images}: expected an integer >= 1")
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


def _cmd_simulate(args: argparse.Namespace) -> int:
    import time

    from polins.io.outputs import output_set
    from polins.models import load_imu
    from polins.sim.scenario import simulate_log
    from polins.site import Site, utc_timestamp

    _check(args.downscale in (1, 2, 4, 8), f"--downscale {args.downscale}: expected 1, 2, 4 or 8")
    _check(
        args.duration is None or args.duration > 0, f"--duration {args.duration}: expected > 0 [s]"
    )
    _check(args.image_rate > 0, f"--image-rate {args.image_rate}: expected > 0 [Hz]")
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
                           lon_deg=args.lon, alt_m=args.alt, progress=not args.quiet)  # fmt: skip
    elapsed = time.perf_counter() - start
    traj, cam = sim.trajectory, sim.camera
    elevation = np.degrees(np.arcsin(np.clip(sim.sun_n[:, 2], -1.0, 1.0)))
    print(f"wrote {Path(args.out) / sim.manifest.name}  ({elapsed:.1f} s)")
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

    parts = text.split(",")
    usage = f"--rot0 {text!r}: expected ROLL,PITCH,HEADING, exactly 3 numbers in degrees"
    _check(len(parts) == 3, usage)
    try:
        roll, pitch, heading = (_finite(v) for v in parts)
    except argparse.ArgumentTypeError:
        raise ArgumentError(usage) from None
    _angle("--rot0 roll", roll, -180.0, 180.0)
    _angle("--rot0 pitch", pitch, -90.0, 90.0)
    _angle("--rot0 heading", heading, -360.0, 360.0)
    yaw = float(yaw_from_heading_deg(heading))
    return rot_nb_from_euler(yaw, np.radians(pitch), np.radians(roll))


def _filter_changes(args: argparse.Namespace) -> dict[str, Any]:
    """The filter options of ``--set KEY=VALUE``, ``--scale-factors``, ``--smooth``, ``--nhc``."""
    from polins.fusion.config import parse_option_value

    changes: dict[str, Any] = {}
    for item in args.set or ():
        key, sep, text = item.partition("=")
        key = key.strip()
        _check(bool(sep) and bool(key), f"--set {item!r}: expected KEY=VALUE")
        _check(key not in ("imu_model", "site"),
               f"--set {key}: give the IMU model with --imu, the site in the manifest's [log]")  # fmt: skip
        try:
            changes[key] = parse_option_value(key, text)
        except UserInputError as exc:
            raise ArgumentError(f"--set {item}: {exc}") from None
        except ValueError:  # int()/float() of the text
            raise ArgumentError(f"--set {item}: {text!r} is not a valid value for {key}") from None
    if args.smooth:
        changes["smooth"] = True
    if args.scale_factors:
        changes["scale_factors"] = True
    if args.nhc is not None:
        _check(args.nhc > 0, f"--nhc {args.nhc:g}: expected a sigma > 0 [m/s]")
        changes["nhc_std"] = args.nhc
    return changes


def _cmd_fuse(args: argparse.Namespace) -> int:
    from polins.fusion.config import FuseConfig
    from polins.io import read_log
    from polins.io.checks import preflight_warnings, run_verdict
    from polins.io.outputs import output_set
    from polins.io.report import format_summary, summarize, write_report
    from polins.loop import LoopOptions, run_log
    from polins.models import load_imu

    _check(args.workers is None or args.workers >= 1, f"--workers {args.workers}: expected >= 1")
    _check(args.prior_lag >= 0, f"--prior-lag {args.prior_lag}: expected >= 0 [s]")
    _check(args.settle >= 0, f"--settle {args.settle}: expected >= 0 [s]")
    _check(not (args.smooth and args.backend != "eskf"), "--smooth needs --backend eskf")
    check_output_folder(args.out, FUSE_FILES)
    rot_nb0 = None if args.rot0 is None else _rot0(args.rot0)
    changes = _filter_changes(args)
    imu = None if args.imu is None else load_imu(args.imu)  # named before reading the log
    FuseConfig.from_options(**changes).check_backend(args.backend)
    options = LoopOptions(method=args.method, update=args.update, prior_lag_s=args.prior_lag)
    try:
        log = read_log(args.manifest, gyro_unit=args.gyro_unit, accel_unit=args.accel_unit,
                       imu_model=imu, allow_outside_paths=args.allow_outside_paths)  # fmt: skip
    except ImportError as exc:  # a ROS bag without the optional extra
        raise ArgumentError(str(exc)) from None
    config = FuseConfig.from_options(log.config, **changes)  # the CLI overrides [filter]
    config.check_backend(args.backend)
    for note in preflight_warnings(log):
        print(f"polins fuse: warning: {note}", file=sys.stderr)
    with output_set(args.out, command="fuse", known=FUSE_FILES) as out:
        result = run_log(log, options=options, config=config, backend=args.backend,
                         workers=args.workers, rot_nb0=rot_nb0, progress=not args.quiet)  # fmt: skip
        summary = summarize(result.solution, result.measurements, result.events,
                            truth=log.truth, timing=result.timing, settings=result.settings,
                            settle_s=args.settle)  # fmt: skip
        verdict = run_verdict(summary, result.events, args.max_image_failures,
                              t_imu=log.imu["t"].to_numpy(dtype=float),
                              t_images=np.asarray(log.images.t, dtype=float))  # fmt: skip
        summary["status"] = verdict or "ok"
        write_report(out.path, result.solution, result.measurements, result.events, summary,
                     truth=log.truth, plots=not args.no_plots,
                     title=log.manifest_path.parent.name)  # fmt: skip
        out.stamp["settings"] = {**result.settings, "filter": config.changes(),
                                 "argv": sys.argv[1:], "status": summary["status"]}  # fmt: skip
        files = [*out.files(), "run.json"]
    print(format_summary(summary))
    print(f"wrote {', '.join(sorted(files))} to {args.out}")
    if verdict:
        print(f"polins fuse: {verdict}", file=sys.stderr)
        return 1
    return 0


def _cmd_heading(args: argparse.Namespace) -> int:
    from polins.compass.measure import measure
    from polins.frames import rot_nb_from_euler
    from polins.io import write_text_atomic
    from polins.io.images import bit_depth_warning, read_image
    from polins.models.loader import load_camera
    from polins.site import Site, to_utc_index
    from polins.sky.ephemeris import sun_position, sun_vector_n

    _angle("--roll", args.roll, -180.0, 180.0)
    _angle("--pitch", args.pitch, -90.0, 90.0)
    _angle("--yaw-prior", args.yaw_prior, -360.0, 360.0)
    path = Path(args.image)
    if not path.is_file():
        raise FileNotFoundError(f"image not found: {path}")
    if args.out:
        _check(not Path(args.out).is_dir(), f"--out {args.out}: is a folder, expected a file")
    cam = load_camera(args.camera)
    Site(args.lat, args.lon, args.alt)
    to_utc_index(args.time)
    raw = read_image(path, shape=cam.shape)  # the reader of `polins fuse`: same image types
    note = bit_depth_warning(raw, cam.bit_depth, str(path))
    if note:
        print(f"polins heading: warning: {note}", file=sys.stderr)
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
        write_text_atomic(args.out, json.dumps(report, indent=2) + "\n")
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


class _Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line (docs/faults.md) and whose help shows
    every default."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", _HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> Any:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """``--help`` with each option's default and the epilog's line breaks kept."""


class _ListOptions(argparse.Action):
    """``polins fuse --list-options``: print the filter options and exit."""

    def __init__(self, option_strings: Sequence[str], dest: str, **kwargs: Any) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser: argparse.ArgumentParser, *args: Any, **kwargs: Any) -> None:
        print(filter_options_text())
        parser.exit(0)


def filter_options_text() -> str:
    """The filter options of ``--set KEY=VALUE`` and the manifest's ``[filter]`` table."""
    from polins.fusion.config import option_table

    lines = ["filter options (--set KEY=VALUE, or the manifest's [filter] table; SI units and "
             "radians unless the name says otherwise):"]  # fmt: skip
    for name, default, backends, doc in option_table():
        if name not in ("imu_model", "site"):
            only = "" if backends == "eskf/graph" else f" [{backends} only]"
            lines.append(f"  {name} = {default}{only}\n      {doc}")
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    """The ``polins`` argument parser with all subcommands."""
    parser = _Parser(
        prog="polins",
        description="Bio-inspired polarization navigation: sky images -> heading -> INS fusion.",
    )
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True,
                                parser_class=_Parser)  # fmt: skip

    p = sub.add_parser("sun", help="solar azimuth/zenith (NREL SPA) and the ENU sun vector")
    _add_site_args(p)
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(handler=_cmd_sun)

    p = sub.add_parser("demo", help="reproduce the paper's Section 4.1 simulation (table+plots)")
    p.add_argument("--full", action="store_true", help="full resolution, 100 images (minutes)")
    p.add_argument("--downscale", type=int, default=4, help="render at 1/K resolution")
    p.add_argument("--images", type=int, default=None, help="images (None: 20; 100 with --full)")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument("--out", default="out/demo", help="folder for plots and CSV tables")
    p.add_argument("--no-plots", action="store_true", help="print the table only, write nothing")
    p.add_argument("--no-occluder", action="store_true", help="skip the occluder case")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=_cmd_demo)

    p = sub.add_parser("simulate", help="simulate a scenario log (IMU, raw sky images, truth)")
    p.add_argument("--scenario", choices=["turntable", "ugv"], required=True)
    p.add_argument("--out", required=True, help="output folder of the log")
    p.add_argument("--duration", type=_finite, default=None,
                   help="[s] (None: 100 turntable, 300 ugv)")  # fmt: skip
    p.add_argument("--image-rate", type=_finite, default=5.0, help="camera rate [Hz]")
    p.add_argument("--imu", default="fins-paper",
                   help="IMU model: fins-paper (navigation-grade FOG), mems-typical or a .toml "
                   "path")  # fmt: skip
    p.add_argument("--downscale", type=int, default=8,
                   help="render at 1/K resolution (1, 2, 4, 8); 8 writes about 1/64 of the "
                   "full-resolution images' size")  # fmt: skip
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument("--epoch", default="2023-09-05T15:06+08:00", help="timezone-aware time of t = 0")
    p.add_argument("--lat", type=_finite, default=45.6234, help="site latitude [deg]")
    p.add_argument("--lon", type=_finite, default=126.7264, help="site longitude [deg]")
    p.add_argument("--alt", type=_finite, default=148.74, help="site height [m]")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=_cmd_simulate)

    p = sub.add_parser("heading", help="heading from one raw polarization image (PNG/TIFF)")
    p.add_argument("image", help="raw DoFP mosaic, 8/16-bit unsigned PNG or TIFF, full size")
    p.add_argument("--camera", default="paper-table1", help="camera model name or .toml path")
    _add_site_args(p)
    p.add_argument("--roll", type=_finite, default=0.0,
                   help="prior roll [deg, -180..180] (FLU, right down +)")  # fmt: skip
    p.add_argument("--pitch", type=_finite, default=0.0,
                   help="prior pitch [deg, -90..90] (nose down +)")  # fmt: skip
    p.add_argument("--yaw-prior", type=_finite, default=0.0,
                   help="prior ENU yaw [deg, counter-clockwise from East]; used only near the "
                   "horizon")  # fmt: skip
    p.add_argument(
        "--method", choices=["compensated", "traditional", "paper"], default="compensated",
        help="heading estimator",
    )  # fmt: skip
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument("--out", default=None, help="also write the JSON report to this file")
    p.set_defaults(handler=_cmd_heading)

    p = sub.add_parser(
        "fuse", help="measure every image of a log and fuse with the IMU (solution, report)",
        epilog=filter_options_text(),
    )  # fmt: skip
    p.add_argument("manifest", help="manifest.toml of the log (or its folder)")
    p.add_argument("--out", required=True,
                   help="output folder (CSV, JSON, PNG; replaced whole, docs/outputs.md)")  # fmt: skip
    p.add_argument("--list-options", action=_ListOptions,
                   help="list the filter options of --set and exit")  # fmt: skip
    p.add_argument("--backend", choices=["eskf", "graph"], default="eskf", help="estimator")
    p.add_argument("--imu", default=None,
                   help="IMU model name or .toml path (None: the manifest's log.imu)")  # fmt: skip
    p.add_argument("--set", action="append", metavar="KEY=VALUE", default=None,
                   help="filter option (see --list-options); overrides the manifest's [filter]; "
                   "repeatable")  # fmt: skip
    p.add_argument("--scale-factors", action="store_true",
                   help="estimate gyro/accel scale factors (ESKF; = --set scale_factors=true)")  # fmt: skip
    p.add_argument("--smooth", action="store_true", help="RTS smoother (ESKF backend)")
    p.add_argument("--workers", type=int, default=None,
                   help="image processes, >= 1 (None: all cores)")  # fmt: skip
    p.add_argument(
        "--method", choices=["compensated", "traditional", "paper"], default="compensated",
        help="heading estimator",
    )  # fmt: skip
    p.add_argument("--update", choices=["yaw", "sun"], default="yaw", help="filter update kind")
    p.add_argument("--prior-lag", type=_finite, default=1.0, help="age of the image prior [s]")
    p.add_argument("--nhc", type=_finite, default=None,
                   help="non-holonomic constraint sigma [m/s] (None: off)")  # fmt: skip
    p.add_argument("--rot0", default=None,
                   help="initial ROLL,PITCH,HEADING [deg] (None: self-alignment)")  # fmt: skip
    p.add_argument("--gyro-unit", choices=["rad/s", "deg/s"], default=None,
                   help="unit of gx, gy, gz (None: the file's or the manifest's, else rad/s)")  # fmt: skip
    p.add_argument("--accel-unit", choices=["m/s^2", "g"], default=None,
                   help="unit of ax, ay, az (None: the file's or the manifest's, else m/s^2)")  # fmt: skip
    p.add_argument("--max-image-failures", type=_fraction, default=0.5, metavar="SHARE",
                   help="exit 1 if more images than this share (50%% or 0.5) are not measured")  # fmt: skip
    p.add_argument("--allow-outside-paths", action="store_true",
                   help="follow image paths outside the log folder (else skipped, reported)")  # fmt: skip
    p.add_argument("--settle", type=_finite, default=5.0, help="skip [s] in the error statistics")
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


def _quiet_stdout() -> None:
    """After a closed pipe: point stdout at /dev/null so that the exit flush stays silent."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``polins`` console script (exit status: docs/faults.md)."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --list-options (0) or a one-line argparse error (2)
        return exc.code if isinstance(exc.code, int) else 2
    handler: Handler = args.handler
    name = f"polins {args.command}"
    try:
        with signals_unwind():
            return handler(args)
    except USER_ERRORS as exc:
        if args.debug:
            raise
        message = "; ".join(line.strip() for line in str(exc).splitlines() if line.strip())
        print(f"{name}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{name}: interrupted; outputs unchanged", file=sys.stderr)
        return 130
    except Terminated:
        print(f"{name}: terminated; outputs unchanged", file=sys.stderr)
        return 143
    except BrokenPipeError:  # stdout closed early (| head): not an error of the run
        _quiet_stdout()
        return 141


__all__ = ["USER_ERRORS", "ArgumentError", "Terminated", "build_parser", "filter_options_text",
           "main", "sun_report"]  # fmt: skip
