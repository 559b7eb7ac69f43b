"""Command line: ``polins sun | demo | simulate | heading | fuse``.

User mistakes (bad arguments, files, units, naive times) print one readable line and exit
with status 2; ``--debug`` shows the traceback instead.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence

import numpy as np

Handler = Callable[[argparse.Namespace], int]

# Exceptions that report a user mistake; anything else is a bug and keeps its traceback.
USER_ERRORS = (ValueError, FileNotFoundError, KeyError, IsADirectoryError, PermissionError)


def _add_site_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--time", required=True, help="timezone-aware ISO time, e.g. 2023-09-05T15:06+08:00"
    )
    p.add_argument("--lat", type=float, required=True, help="latitude [deg, North positive]")
    p.add_argument("--lon", type=float, required=True, help="longitude [deg, East positive]")
    p.add_argument("--alt", type=float, default=0.0, help="height above the ellipsoid [m]")


def sun_report(time: str, lat_deg: float, lon_deg: float, alt_m: float) -> dict[str, object]:
    """Solar azimuth/zenith [deg] and the ENU sun vector at one time and place."""
    from polins.ephemeris import sun_position, sun_vector_n, to_utc_index

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
    print("polins demo: the paper reproduction is not yet available in this version.")
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
    p.set_defaults(handler=_cmd_demo)
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
        print(f"polins {args.command}: error: {exc}", file=sys.stderr)
        return 2


__all__ = ["build_parser", "main", "sun_report"]
