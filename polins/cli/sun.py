"""Commands ``polins sun`` (the ephemeris at one time and place) and ``polins heading`` (the heading of one raw image).

Both answer for one moment: ``sun`` prints the solar azimuth, zenith and ENU sun vector;
``heading`` measures the heading of one raw mosaic with a camera file, at a time and
place, and exits 1 when the image gives no heading.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from polins.cli.common import add_method_arg, add_site_args, angle, check, finite

__all__ = ["add_heading", "add_sun", "cmd_heading", "cmd_sun", "sun_report"]


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


def cmd_sun(args: argparse.Namespace) -> int:
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


def cmd_heading(args: argparse.Namespace) -> int:
    from polins.compass.measure import measure
    from polins.frames import rot_nb_from_euler
    from polins.io import write_text_atomic
    from polins.io.images import bit_depth_warning, read_image
    from polins.models import load_camera
    from polins.site import Site, to_utc_index
    from polins.sky.ephemeris import sun_position, sun_vector_n

    angle("--roll", args.roll, -180.0, 180.0)
    angle("--pitch", args.pitch, -90.0, 90.0)
    angle("--yaw-prior", args.yaw_prior, -360.0, 360.0)
    path = Path(args.image)
    if not path.is_file():
        raise FileNotFoundError(f"image not found: {path}")
    if args.out:
        check(not Path(args.out).is_dir(), f"--out {args.out}: is a folder, expected a file")
    site = [args.time is not None, args.lat is not None, args.lon is not None]
    check(all(site) or not any(site),
          "--time, --lat and --lon go together (or leave all three out: sun in the body "
          "frame only)")  # fmt: skip
    cam = load_camera(args.camera)
    if all(site):
        Site(args.lat, args.lon, args.alt)
        to_utc_index(args.time)
    raw = read_image(path, shape=cam.shape)  # the reader of `polins fuse`: same image types
    note = bit_depth_warning(raw, cam.bit_depth, str(path))
    if note:
        print(f"polins heading: warning: {note}", file=sys.stderr)
    rot = rot_nb_from_euler(
        np.radians(args.yaw_prior), np.radians(args.pitch), np.radians(args.roll)
    )
    report: dict[str, object] = {"image": str(path), "camera": cam.name}
    prior = None if args.sun_azimuth_prior is None else np.radians(args.sun_azimuth_prior)
    if all(site):
        sun = sun_position(args.time, args.lat, args.lon, args.alt)
        sun_n = sun_vector_n(sun.azimuth, sun.zenith)
        m = measure(raw, cam, sun_n=sun_n, rot_nb_prior=rot, method=args.method)
        report.update(
            time_utc=to_utc_index(args.time)[0].isoformat(),
            sun_azimuth_deg=float(np.degrees(sun.azimuth)),
            sun_zenith_deg=float(np.degrees(sun.zenith)),
            heading_std_deg=float(np.degrees(m.yaw_std)) if m.ok else None,
            yaw_deg=float(np.degrees(m.yaw)) if m.ok else None,
        )
    else:  # no ephemeris: the sun in the body frame (docs/measurement.md §11)
        m = measure(raw, cam, rot_nb_prior=rot, method=args.method, sun_azimuth_b_prior=prior)
    report.update(
        sun_azimuth_b_deg=float(np.degrees(m.sun_azimuth_b)) if m.ok else None,
        sun_azimuth_b_std_deg=float(np.degrees(m.sun_azimuth_b_std)) if m.ok else None,
        **m.as_dict(),
    )
    if args.out:
        write_text_atomic(args.out, json.dumps(report, indent=2) + "\n")
    if args.json:
        print(json.dumps(report, indent=2))
    elif not m.ok:
        print(f"no {'heading' if all(site) else 'sun'} ({args.method}): {m.reason}")
    else:
        sun_b = ", ".join(f"{x:+.6f}" for x in m.sun_b)
        if m.reason:
            print(f"note              {m.reason}")
        if all(site):
            print(f"heading           {m.heading_deg:.4f} deg  (compass, clockwise from North)")
            print(
                f"sigma             {np.degrees(m.yaw_std):.4f} deg  (filter; measurement only "
                f"{np.degrees(m.yaw_std_meas):.5f} deg)"
            )
            print(f"yaw (ENU)         {np.degrees(m.yaw):.4f} deg  (counter-clockwise from East)")
        print(
            f"sun azimuth (body) {np.degrees(m.sun_azimuth_b):.4f} +- "
            f"{np.degrees(m.sun_azimuth_b_std):.4f} deg  (FLU, counter-clockwise from x; "
            f"branch: {m.sun_branch})"
        )
        if np.isfinite(m.sun_azimuth_b_alt):
            print(
                f"  or              {np.degrees(m.sun_azimuth_b_alt):.4f} deg  (180 deg ambiguous)"
            )
        if np.isfinite(m.sun_elevation_b):
            print(f"sun elevation (body) {np.degrees(m.sun_elevation_b):.4f} deg")
        print(f"sun (body)        [{sun_b}]")
        if np.isfinite(m.epsilon_std):
            print(f"epsilon           {m.epsilon:.5f} +- {m.epsilon_std:.5f}")
        print(
            f"pixels            {m.n_pixels}  (eigen-gap {m.eigen_gap:.3f}, "
            f"residual RMS {m.residual_rms:.2f})"
        )
    return 0 if m.ok else 1


def add_sun(sub: Any) -> None:
    """Register ``polins sun``."""
    p = sub.add_parser("sun", help="solar azimuth/zenith (NREL SPA) and the ENU sun vector")
    add_site_args(p)
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(handler=cmd_sun)


def add_heading(sub: Any) -> None:
    """Register ``polins heading``."""
    p = sub.add_parser("heading", help="heading from one raw polarization image (PNG/TIFF)")
    p.add_argument(
        "image",
        help="raw DoFP mosaic, full size: 8-bit, or 12/16-bit in a 16-bit unsigned PNG or TIFF (the camera file's bit_depth)",
    )
    p.add_argument("--camera", default="paper-table1", help="camera model name or .toml path")
    add_site_args(p, required=False)
    p.add_argument("--sun-azimuth-prior", type=finite, default=None,
                   help="without --time/--lat/--lon: prior body-frame sun azimuth [deg, FLU, "
                   "counter-clockwise from x] that chooses the 180 deg branch when the sky "
                   "cannot")  # fmt: skip
    p.add_argument("--roll", type=finite, default=0.0,
                   help="prior roll [deg, -180..180] (FLU, right down +)")  # fmt: skip
    p.add_argument("--pitch", type=finite, default=0.0,
                   help="prior pitch [deg, -90..90] (nose down +)")  # fmt: skip
    p.add_argument("--yaw-prior", type=finite, default=0.0,
                   help="prior ENU yaw [deg, counter-clockwise from East]; used only near the "
                   "horizon")  # fmt: skip
    add_method_arg(p)
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument("--out", default=None, help="also write the JSON report to this file")
    p.set_defaults(handler=cmd_heading)
