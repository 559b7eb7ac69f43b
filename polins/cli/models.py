"""Command ``polins imu-model STATIC [STATIC ...] --out MODEL.toml``: an IMU model file from a static recording (Allan deviation).

The other command that writes a model file, ``polins calibrate`` (camera files), is in
:mod:`polins.cli.calibrate`.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from polins.cli.common import check

__all__ = ["add_imu_model", "cmd_imu_model"]


def cmd_imu_model(args: argparse.Namespace) -> int:
    from polins.io import read_imu, write_text_atomic
    from polins.io.model_files import imu_model_toml
    from polins.tuning import imu_model_from_static, plot_allan

    out = Path(args.out)
    check(out.suffix == ".toml", f"--out {out}: the IMU model file must end in .toml")
    check(not out.is_dir(), f"--out {out} is a folder; give a .toml file name")
    segments = [
        read_imu(path, gyro_unit=args.gyro_unit, accel_unit=args.accel_unit) for path in args.static
    ]
    model, fit = imu_model_from_static(
        segments, name=args.name or out.stem, grade=args.grade, source=args.static[0]
    )
    write_text_atomic(out, imu_model_toml(model, comments=fit.comment_lines()))
    written = [str(out)]
    if args.plot:
        plot_allan(fit, args.plot)
        written.append(str(args.plot))
    print("\n".join(fit.notes))
    print(f"wrote {', '.join(written)}")
    return 0


def add_imu_model(sub: Any) -> None:
    """Register ``polins imu-model``."""
    p = sub.add_parser(
        "imu-model", help="IMU noise model (TOML) from a static recording (Allan deviation)"
    )
    p.add_argument("static", nargs="+",
                   help="CSV/Parquet files of the IMU at rest (t, gx, gy, gz, ax, ay, az), each "
                   "a segment; a file with missing samples is split at its gaps")  # fmt: skip
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
    p.set_defaults(handler=cmd_imu_model)
