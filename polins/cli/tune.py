"""The ``polins tune`` command: the filter's noise fitted to a log by maximum likelihood of its innovations."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from polins.cli.common import ArgumentError, add_method_arg, check, finite
from polins.cli.fuse import filter_changes, filter_options_text
from polins.errors import UserInputError


def cmd_tune(args: argparse.Namespace) -> int:
    from polins.fusion.config import FuseConfig
    from polins.io import read_log, write_text_atomic
    from polins.io.model_files import imu_model_toml
    from polins.loop import LoopOptions, run_log
    from polins.models import load_imu
    from polins.tuning import tune
    from polins.tuning.parameters import check_params, default_params

    out = Path(args.out)
    check(out.suffix == ".toml", f"--out {out}: the tuned IMU model file must end in .toml")
    check(not out.is_dir(), f"--out {out} is a folder; give a .toml file name")
    check(args.workers is None or args.workers >= 1, f"--workers {args.workers}: expected >= 1")
    names = [p.strip() for p in args.params.split(",") if p.strip()]
    try:
        params = None if names == ["auto"] else check_params(names)
    except UserInputError as exc:
        raise ArgumentError(f"--params {args.params}: {exc}") from None
    changes = filter_changes(args)
    imu = None if args.imu is None else load_imu(args.imu)
    log = read_log(args.manifest, gyro_unit=args.gyro_unit, accel_unit=args.accel_unit,
                   imu_model=imu)  # fmt: skip
    config = FuseConfig.from_log(log).replace(**changes)
    config.check_backend("eskf")
    if params is None:
        params = default_params(config, odometry=log.odometry is not None)
    # every image measured with the filter's prior (the loop), then the likelihood
    options = LoopOptions(method=args.method)
    first = run_log(log, options=options, config=config, workers=args.workers,
                    progress=not args.quiet)  # fmt: skip
    assert first.measurements is not None  # the loop's: one row per image
    result = tune(log.imu, first.measurements, options.filter_config(config), params,
                  odometry=log.odometry)  # fmt: skip
    # one file: the tuned IMU terms, and in its [filter] table every option the tuned filter
    # ran with beyond the manifest's (the start file's, --set's, the tuned noise options)
    model = result.tuned_model(changes, name=out.stem,
                               description=f"{log.imu_model.name} tuned on {args.manifest}")  # fmt: skip
    command = f"polins fuse {args.manifest} --imu {out} --out RUN"
    write_text_atomic(out, imu_model_toml(model, comments=[*result.comment_lines(),
                                                           f"fuse with: {command}"]))  # fmt: skip
    print(result.report())
    print(f"wrote {out} (IMU model and [filter] options); fuse with the tuned values:\n  {command}")
    return 0


def add_tune(sub: Any) -> None:
    """Register ``polins tune``."""
    p = sub.add_parser(
        "tune", help="tune the filter's noise on a log (maximum likelihood of the innovations)",
        epilog=filter_options_text(),
    )  # fmt: skip
    p.add_argument("manifest", help="manifest.toml of the log (or its folder)")
    p.add_argument("--params", default="auto",
                   help="comma-separated noise parameters: gyro_arw, gyro_bias_rw, accel_vrw, "
                   "accel_bias_rw, yaw_floor_deg, yaw_std_scale, sun_floor_deg, sun_std_scale, "
                   "nhc_std, standstill_std, odometer_std (docs/tuning.md); auto: gyro_arw, "
                   "yaw_std_scale and the sigma of each aiding the run fuses")  # fmt: skip
    p.add_argument("--out", required=True,
                   help="tuned file to write: the IMU model with a [filter] table of the tuned "
                   "options; polins fuse --imu takes it whole")  # fmt: skip
    p.add_argument("--imu", default=None,
                   help="IMU model name or .toml path to start from (None: the manifest's)")  # fmt: skip
    p.add_argument("--set", action="append", metavar="KEY=VALUE", default=None,
                   help="filter option (polins fuse --list-options); repeatable")  # fmt: skip
    p.add_argument("--scale-factors", action="store_true",
                   help="estimate gyro/accel scale factors (= --set scale_factors=true)")  # fmt: skip
    p.add_argument("--smooth", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--nhc", type=finite, default=None,
                   help="non-holonomic constraint sigma [m/s] (None: off)")  # fmt: skip
    add_method_arg(p)
    p.add_argument("--workers", type=int, default=None, help="image processes (None: all cores)")
    p.add_argument("--gyro-unit", choices=["rad/s", "deg/s"], default=None,
                   help="unit of gx, gy, gz (None: the file's or the manifest's, else rad/s)")  # fmt: skip
    p.add_argument("--accel-unit", choices=["m/s^2", "g"], default=None,
                   help="unit of ax, ay, az (None: the file's or the manifest's, else m/s^2)")  # fmt: skip
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=cmd_tune)
