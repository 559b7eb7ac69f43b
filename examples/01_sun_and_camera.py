"""01 - The inputs of every heading: where the sun is, and where each pixel looks.

Prints the sun at the paper's six outdoor sessions (Harbin, 2023-09-05, Table 3) and plots
the solar azimuth/zenith over that day, and the paper camera's per-superpixel ray zenith
angle with the 80 deg field-of-view limit (docs/model.md §5).

    python examples/01_sun_and_camera.py [--quick] [--out out/01_sun_and_camera]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

import polins
from polins.compass.camera import fov_mask, pixel_rays_c

HARBIN = {"lat_deg": 45.6234, "lon_deg": 126.7264, "alt_m": 148.74}
SESSIONS = ["11:33", "12:18", "12:56", "13:29", "15:07", "16:29"]  # paper Table 3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="coarser day sampling, small camera")
    parser.add_argument("--out", type=Path, default=Path("out/01_sun_and_camera"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    times = [pd.Timestamp(f"2023-09-05 {hm}", tz="Asia/Shanghai") for hm in SESSIONS]
    sun = polins.sun_position(times, **HARBIN)
    print("Paper Table 3 sessions, Harbin 2023-09-05 (UTC+8)")
    print(f"{'time':>6} {'azimuth [deg]':>14} {'zenith [deg]':>13}   sun_n (ENU)")
    for t, az, zen in zip(times, sun.azimuth, sun.zenith, strict=True):
        s = polins.sun_vector_n(az, zen)
        print(f"{t:%H:%M} {np.degrees(az):14.3f} {np.degrees(zen):13.3f}   {np.round(s, 4)}")

    day = pd.date_range(
        "2023-09-05 06:00",
        "2023-09-05 18:00",
        freq="30min" if args.quick else "2min",
        tz="Asia/Shanghai",
    )
    sun_day = polins.sun_position(day, **HARBIN)
    fig, ax = plt.subplots(figsize=(8, 4))
    hours = day.hour + day.minute / 60.0
    ax.plot(hours, np.degrees(sun_day.azimuth), label="azimuth (clockwise from North)")
    ax.plot(hours, np.degrees(sun_day.zenith), label="apparent zenith")
    sess_h = [t.hour + t.minute / 60.0 for t in times]
    ax.plot(sess_h, np.degrees(sun.zenith), "ko", label="paper sessions (Table 3)")
    ax.set(
        xlabel="local time (UTC+8) [h]",
        ylabel="angle [deg]",
        title="Sun over Harbin, 2023-09-05 (pvlib NREL SPA)",
    )
    ax.grid(True)
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out / "sun_day.png", dpi=120)

    cam = polins.load_camera("paper-table1")
    if args.quick:
        cam = cam.downscaled(4)
    rays = pixel_rays_c(cam)
    zenith_deg = np.degrees(np.arccos(np.clip(rays[..., 2], -1, 1)))
    fig, ax = plt.subplots(figsize=(7, 5))
    im = ax.imshow(np.where(fov_mask(cam), zenith_deg, np.nan), cmap="viridis")
    ax.set(
        xlabel="u [superpixel]",
        ylabel="v [superpixel]",
        title=f"{cam.name}: ray angle of the used superpixels",
    )
    fig.colorbar(im, ax=ax, label="angle from optical axis [deg]")
    fig.tight_layout()
    fig.savefig(args.out / "camera_rays.png", dpi=120)
    print(
        f"{cam.name}: {int(fov_mask(cam).sum())} of {rays.shape[0] * rays.shape[1]} "
        f"superpixels within {np.degrees(cam.fov_max):.0f} deg; figures in {args.out}/"
    )


if __name__ == "__main__":
    main()
