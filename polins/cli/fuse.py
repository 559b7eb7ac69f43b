"""Command ``polins fuse``: measure every image of a log and fuse the headings with the IMU.

Reads a log (manifest, IMU, images), runs :func:`polins.loop.run_log` with the filter
options of the manifest's ``[filter]`` table and ``--set KEY=VALUE`` overrides, and
writes the whole output set (solution, measurements, events, summary, plots;
docs/outputs.md). Exits 1 when too many images gave no heading.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import Any

import numpy as np

from polins.cli.common import ArgumentError, add_method_arg, angle, check, finite, fraction
from polins.errors import UserInputError
from polins.io.outputs import check_output_folder

__all__ = ["FUSE_FILES", "add_fuse", "cmd_fuse", "filter_options_text"]

FUSE_FILES = ("solution.csv", "measurements.csv", "events.csv", "summary.json", "schema.json",
              "heading.png", "heading_error.png", "measurements.png", "epsilon.png")  # fmt: skip


def _rot0(text: str) -> Any:
    """``--rot0 ROLL,PITCH,HEADING`` [deg] as a Rotation (body -> ENU)."""
    from polins.frames import rot_nb_from_euler, yaw_from_heading_deg

    parts = text.split(",")
    usage = f"--rot0 {text!r}: expected ROLL,PITCH,HEADING, exactly 3 numbers in degrees"
    check(len(parts) == 3, usage)
    try:
        roll, pitch, heading = (finite(v) for v in parts)
    except argparse.ArgumentTypeError:
        raise ArgumentError(usage) from None
    angle("--rot0 roll", roll, -180.0, 180.0)
    angle("--rot0 pitch", pitch, -90.0, 90.0)
    angle("--rot0 heading", heading, -360.0, 360.0)
    yaw = float(yaw_from_heading_deg(heading))
    return rot_nb_from_euler(yaw, np.radians(pitch), np.radians(roll))


def filter_changes(args: argparse.Namespace) -> dict[str, Any]:
    """The filter options of ``--set KEY=VALUE``, ``--scale-factors``, ``--smooth``, ``--nhc``."""
    from polins.fusion.config import parse_option_value

    changes: dict[str, Any] = {}
    for item in args.set or ():
        key, sep, text = item.partition("=")
        key = key.strip()
        check(bool(sep) and bool(key), f"--set {item!r}: expected KEY=VALUE")
        check(key not in ("imu_model", "site"),
               f"--set {key}: give the IMU model with --imu, the site in the manifest's [log]")  # fmt: skip
        try:
            changes[key] = parse_option_value(key, text)
        except UserInputError as exc:
            said = str(exc).startswith(f"{key}=")  # the message quotes the value itself
            raise ArgumentError(f"--set {exc}" if said else f"--set {item}: {exc}") from None
    if args.smooth:
        changes["smooth"] = True
    if args.scale_factors:
        changes["scale_factors"] = True
    if args.nhc is not None:
        try:
            changes["nhc_std"] = parse_option_value("nhc_std", args.nhc)
        except UserInputError as exc:
            raise ArgumentError(f"--nhc {args.nhc}: {exc}") from None
    return changes


def cmd_fuse(args: argparse.Namespace) -> int:
    from polins.evaluation import format_summary, summarize, write_report
    from polins.fusion.config import FuseConfig
    from polins.io import read_log
    from polins.io.checks import preflight_warnings, run_verdict
    from polins.io.outputs import output_set
    from polins.loop import LoopOptions, run_log
    from polins.models import load_imu

    check(args.workers is None or args.workers >= 1, f"--workers {args.workers}: expected >= 1")
    check(args.prior_lag >= 0, f"--prior-lag {args.prior_lag}: expected >= 0 [s]")
    check(args.settle >= 0, f"--settle {args.settle}: expected >= 0 [s]")
    check(not (args.smooth and args.backend != "eskf"), "--smooth needs --backend eskf")
    check_output_folder(args.out, FUSE_FILES)
    rot_nb0 = None if args.rot0 is None else _rot0(args.rot0)
    changes = filter_changes(args)
    imu = None if args.imu is None else load_imu(args.imu)  # named before reading the log
    FuseConfig.from_options(**changes).check_backend(args.backend)
    options = LoopOptions(method=args.method, update=args.update, prior_lag_s=args.prior_lag)
    try:
        log = read_log(args.manifest, gyro_unit=args.gyro_unit, accel_unit=args.accel_unit,
                       imu_model=imu, allow_outside_paths=args.allow_outside_paths)  # fmt: skip
    except ImportError as exc:  # a ROS bag without the optional extra
        raise ArgumentError(str(exc)) from None
    config = FuseConfig.from_log(log).replace(**changes)  # the CLI overrides [filter]
    config.check_backend(args.backend)
    if log.imu_model.filter_options:  # a tuned file: say which options it set
        told = ", ".join(f"{k}={v}" for k, v in log.imu_model.filter_options if k not in changes)
        print(f"filter options of {log.imu_model.path}: {told or 'all overridden by --set'}")
    for note in preflight_warnings(log):
        print(f"polins fuse: warning: {note}", file=sys.stderr)
    with output_set(args.out, command="fuse", known=FUSE_FILES) as out:
        result = run_log(log, options=options, config=config, backend=args.backend,
                         workers=args.workers, rot_nb0=rot_nb0, progress=not args.quiet)  # fmt: skip
        measurements = result.measurements  # the loop's: one row per image
        assert measurements is not None
        # every kind's NIS from the update log; the graph's log has no innovations, there
        # the images' NIS come from the loop's table
        settings = result.info["settings"]
        summary = summarize(result.solution, measurements, result.events, truth=log.truth,
                            timing=result.info["timing"], settings=settings,
                            settle_s=args.settle, gate_prob=config.gate_probability,
                            updates=result.updates if args.backend == "eskf" else None)  # fmt: skip
        verdict = run_verdict(summary, result.events, args.max_image_failures,
                              t_imu=log.imu["t"].to_numpy(dtype=float),
                              t_images=np.asarray(log.images.t, dtype=float),
                              measurements=measurements)  # fmt: skip
        summary["status"] = verdict or "ok"
        write_report(out.path, result.solution, measurements, result.events, summary,
                     truth=log.truth, plots=not args.no_plots,
                     title=log.manifest_path.parent.name,
                     table_format=config.output.table_format)  # fmt: skip
        out.stamp["settings"] = {**settings, "filter": config.changes(),
                                 "argv": sys.argv[1:], "status": summary["status"]}  # fmt: skip
        files = [*out.files(), "run.json"]
    print(format_summary(summary))
    print(f"wrote {', '.join(sorted(files))} to {args.out}")
    if verdict:
        print(f"polins fuse: {verdict}", file=sys.stderr)
        return 1
    return 0


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

    lines = ["filter options by part (--set KEY=VALUE, or KEY = VALUE in the manifest's [filter] "
             "table; 'off' turns an option off, 'auto' is the automatic choice; SI units and "
             "radians unless the name says otherwise):"]  # fmt: skip
    part = ""
    for part_name, name, default, backends, doc in option_table():
        if part_name != part:
            part = part_name
            lines.append(f" {part}:")
        only = "" if backends == "eskf/graph" else f" [{backends} only]"
        lines.append(f"  {name} = {default}{only}\n      {doc}")
    return "\n".join(lines)


def add_fuse(sub: Any) -> None:
    """Register ``polins fuse``."""
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
                   help="IMU model name or .toml path (default: the manifest's log.imu)")  # fmt: skip
    p.add_argument("--set", action="append", metavar="KEY=VALUE", default=None,
                   help="filter option (see --list-options); overrides the manifest's [filter]; "
                   "repeatable")  # fmt: skip
    p.add_argument("--scale-factors", action="store_true",
                   help="estimate gyro/accel scale factors (on by default for MEMS models; = --set "
                   "scale_factors=true)")  # fmt: skip
    p.add_argument("--smooth", action="store_true", help="RTS smoother (ESKF backend)")
    p.add_argument("--workers", type=int, default=None,
                   help="image processes, >= 1 (default: all cores)")  # fmt: skip
    add_method_arg(p)
    p.add_argument("--update", choices=["yaw", "sun"], default="yaw", help="filter update kind")
    p.add_argument("--prior-lag", type=finite, default=1.0, help="age of the image prior [s]")
    p.add_argument("--nhc", default=None, metavar="SIGMA|off|auto",
                   help="non-holonomic constraint 1-sigma [m/s] = --set nhc_std=...; off: none; "
                   "default auto: on (0.05 m/s) for a ground vehicle ([vehicle] kind), else off")  # fmt: skip
    p.add_argument("--rot0", default=None,
                   help="initial ROLL,PITCH,HEADING [deg] (default: self-alignment)")  # fmt: skip
    p.add_argument("--gyro-unit", choices=["rad/s", "deg/s"], default=None,
                   help="unit of gx, gy, gz (default: the file's or the manifest's, else rad/s)")  # fmt: skip
    p.add_argument("--accel-unit", choices=["m/s^2", "g"], default=None,
                   help="unit of ax, ay, az (default: the file's or the manifest's, else m/s^2)")  # fmt: skip
    p.add_argument("--max-image-failures", type=fraction, default=0.5, metavar="SHARE",
                   help="exit 1 if more images than this share (50%% or 0.5) are not measured")  # fmt: skip
    p.add_argument("--allow-outside-paths", action="store_true",
                   help="follow image paths outside the log folder (else skipped, reported)")  # fmt: skip
    p.add_argument("--settle", type=finite, default=5.0, help="skip [s] in the error statistics")
    p.add_argument("--no-plots", action="store_true", help="write tables and JSON only")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=cmd_fuse)
