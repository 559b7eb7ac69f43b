"""The ``polins manifest`` command: the manifest of a ROS bag, so that ``polins fuse`` and ``polins tune`` take the bag as a log (docs/rosbag.md).

Reads the bag once (its topics, IMU samples and image stamps, as ``polins fuse`` will), checks
the camera and IMU models, and writes ``manifest.toml`` with the bag's path relative to it,
the topics found or named, and no ``epoch_utc`` when the stamps are absolute UTC times.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import Any

import numpy as np

from polins.cli.common import ArgumentError, angle, check, finite


def _reference(value: str, folder: Path) -> str:
    """A model's name as given, or its file's path relative to the manifest's folder."""
    path = Path(value)
    if path.suffix != ".toml" and not path.exists():
        return value  # a shipped model's name
    try:
        return os.path.relpath(path.resolve(), folder.resolve())
    except ValueError:  # another drive (Windows)
        return str(path.resolve())


def manifest_tables(args: argparse.Namespace, imu_topic: str, image_topic: str) -> dict[str, Any]:
    """The manifest's tables for the bag and the models of ``args``."""
    folder = Path(args.out).parent
    log: dict[str, Any] = {}
    if args.epoch is not None:
        log["epoch_utc"] = args.epoch
    log |= {"camera": _reference(args.camera, folder), "imu": _reference(args.imu, folder),
            "lat_deg": args.lat, "lon_deg": args.lon, "alt_m": args.alt,
            "description": f"ROS bag {Path(args.bag).name}"}  # fmt: skip
    tables: dict[str, Any] = {"log": log, "files": {"bag": _reference(args.bag, folder)},
                              "ros": {"imu_topic": imu_topic, "image_topic": image_topic}}  # fmt: skip
    if args.vehicle is not None:
        tables["vehicle"] = {"kind": args.vehicle}
    return tables


def cmd_manifest(args: argparse.Namespace) -> int:
    from polins.io import write_text_atomic
    from polins.io.model_files import toml_dumps
    from polins.io.rosbag import bag_topics, read_bag
    from polins.models import load_camera, load_imu
    from polins.site import utc_timestamp

    out = Path(args.out)
    check(out.suffix == ".toml", f"--out {out}: the manifest file must end in .toml")
    angle("--lat", args.lat, -90.0, 90.0)
    angle("--lon", args.lon, -180.0, 360.0)
    if args.epoch is not None:
        utc_timestamp(args.epoch, None)  # a naive time is one line
    load_camera(args.camera)
    load_imu(args.imu)
    try:
        imu_topic, image_topic = bag_topics(args.bag, args.imu_topic, args.image_topic)
        imu, images = read_bag(args.bag, epoch_utc=args.epoch, imu_topic=imu_topic,
                               image_topic=image_topic)  # fmt: skip
    except ImportError as exc:  # without the optional extra
        raise ArgumentError(str(exc)) from None
    out.parent.mkdir(parents=True, exist_ok=True)
    tables = manifest_tables(args, imu_topic, image_topic)
    write_text_atomic(out, toml_dumps(tables, header="polins log manifest of a ROS bag "
                                      "(polins manifest; keys: polins.io.manifest)"))  # fmt: skip
    t = imu["t"].to_numpy(dtype=float)
    rate = (len(t) - 1) / (t[-1] - t[0]) if len(t) > 1 else float("nan")
    epoch = "manifest" if args.epoch is not None else "first stamp, floored to a second"
    print(f"IMU     {imu_topic}: {len(t)} samples, {rate:.1f} Hz, t = {t[0]:.3f} .. {t[-1]:.3f} s")
    t_img = np.asarray(images.t, dtype=float)
    span = f"t = {t_img[0]:.3f} .. {t_img[-1]:.3f} s" if t_img.size else "none"
    print(f"images  {image_topic}: {t_img.size}, {span}")
    print(f"t = 0   {images.epoch_utc.isoformat()} ({epoch})")
    print(f"wrote {out}; fuse with:\n  polins fuse {out} --out RUN")
    return 0


def add_manifest(sub: Any) -> None:
    """Register ``polins manifest``."""
    p = sub.add_parser("manifest", help="write the manifest of a ROS bag (then polins fuse it)",
                       description=__doc__)  # fmt: skip
    p.add_argument("bag", help="ROS 1 .bag file, or ROS 2 bag folder (or its .mcap / .db3)")
    p.add_argument("--camera", required=True, help="camera model name or .toml path")
    p.add_argument("--imu", required=True, help="IMU model name or .toml path")
    p.add_argument("--lat", type=finite, required=True, help="latitude [deg, North positive]")
    p.add_argument("--lon", type=finite, required=True, help="longitude [deg, East positive]")
    p.add_argument("--alt", type=finite, default=0.0, help="height above the ellipsoid [m]")
    p.add_argument("--out", required=True, help="manifest .toml to write")
    p.add_argument("--imu-topic", default=None,
                   help="sensor_msgs/Imu topic (default: the bag's only one)")  # fmt: skip
    p.add_argument("--image-topic", default=None,
                   help="sensor_msgs/Image topic of the raw DoFP mosaics (default: the bag's "
                   "only one)")  # fmt: skip
    p.add_argument("--epoch", default=None,
                   help="timezone-aware UTC time of stamp 0, for stamps that are not absolute "
                   "(simulation or boot time; default: none needed, t = 0 is the first "
                   "absolute stamp)")  # fmt: skip
    p.add_argument("--vehicle", choices=["ground", "static", "free"], default=None,
                   help="the [vehicle] table's kind (docs/filter.md; default: none, a free "
                   "vehicle)")  # fmt: skip
    p.set_defaults(handler=cmd_manifest)
