"""02 - One raw polarization image -> heading, with the two methods of polins.measure.

Renders one raw DoFP mosaic of a clear Rayleigh sky (paper Table 1 camera and sun, a tilted
vehicle, direct-sunlight coefficient eps = 0.0125, a world-fixed occluder at compass azimuth
260-350 deg below 40 deg, 1.5 DN noise), measures the heading with the "traditional" and
"compensated" methods, prints a table, and plots the angle of polarization, the valid-pixel
mask and the per-pixel normalised residual.

    python examples/02_heading_from_image.py [--quick] [--out out/02_heading_from_image]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

import polins
from polins.compass.crlb import yaw_crlb
from polins.compass.measure import measure_with_maps
from polins.sim import azimuth_band, render_raw

HARBIN = {"lat_deg": 45.6234, "lon_deg": 126.7264, "alt_m": 148.74}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1/4 resolution image")
    parser.add_argument("--out", type=Path, default=Path("out/02_heading_from_image"))
    parser.add_argument("--seed", type=int, default=2)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    cam = polins.load_camera("paper-table1")
    if args.quick:
        cam = cam.downscaled(4)
    sun = polins.sun_position("2023-09-05T15:06+08:00", **HARBIN)
    sun_n = polins.sun_vector_n(sun.azimuth, sun.zenith)
    heading_true, pitch, roll = 40.0, np.radians(4.0), np.radians(-6.0)
    rot_true = polins.rot_nb_from_euler(polins.yaw_from_heading_deg(heading_true), pitch, roll)
    occluder = azimuth_band(260.0, 350.0, 40.0)
    raw = render_raw(
        cam,
        sun_n,
        rot_true,
        epsilon=0.0125,
        noise_std=1.5,
        occluders=[occluder],
        rng=np.random.default_rng(args.seed),
    )
    # The INS prior: good roll/pitch, a yaw 2 deg off (used only near the horizon).
    rot_prior = polins.rot_nb_from_euler(
        polins.yaw_from_heading_deg(heading_true + 2.0), pitch, roll
    )
    crlb = yaw_crlb(
        cam, sun_n, rot_true, dop_max=0.75, radiance=220.0, noise_std=1.5, epsilon=0.0125
    )
    print(
        f"camera {cam.name}: raw {raw.shape} {raw.dtype}; sun azimuth "
        f"{np.degrees(sun.azimuth):.2f} deg, zenith {np.degrees(sun.zenith):.2f} deg"
    )
    print(f"true heading {heading_true:.3f} deg; CRLB (no occluder) {np.degrees(crlb):.5f} deg\n")
    header = (
        f"{'method':12s} {'heading':>10s} {'error':>9s} {'sigma_meas':>10s} {'sigma_KF':>9s}"
        f" {'epsilon':>9s} {'pixels':>7s} {'resid':>6s} {'ms':>6s}"
    )
    print(header)
    print(f"{'':12s} {'[deg]':>10s} {'[deg]':>9s} {'[deg]':>10s} {'[deg]':>9s}")
    maps = {}
    for method in ("traditional", "compensated"):
        t0 = time.perf_counter()
        m, maps[method] = measure_with_maps(
            raw, cam, sun_n=sun_n, rot_nb_prior=rot_prior, method=method
        )
        ms = 1e3 * (time.perf_counter() - t0)
        if not m.ok:
            print(f"{method:12s} refused: {m.reason}")
            continue
        err = (m.heading_deg - heading_true + 180.0) % 360.0 - 180.0
        print(
            f"{method:12s} {m.heading_deg:10.4f} {err:+9.4f} {np.degrees(m.yaw_std_meas):10.5f}"
            f" {np.degrees(m.yaw_std):9.4f} {m.epsilon:9.5f} {m.n_pixels:7d}"
            f" {m.residual_rms:6.2f} {ms:6.0f}"
        )
    print(
        "\nsigma_KF = the sigma for a filter (pixel noise and the model error measured in the"
        " image); ms includes the per-pixel maps."
    )

    comp = maps["compensated"]
    assert comp is not None
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6), constrained_layout=True)
    im = axes[0].imshow(np.degrees(comp.aop), cmap="twilight", vmin=-90, vmax=90)
    fig.colorbar(im, ax=axes[0], label="AoP [deg] (from +u towards +v)")
    axes[0].set(title="Angle of polarization", xlabel="u [superpixel]", ylabel="v [superpixel]")
    axes[1].imshow(comp.valid, cmap="gray", interpolation="nearest")
    axes[1].set(
        title=f"Valid pixels ({int(comp.valid.sum())}): FOV, sun, DoP, occluder",
        xlabel="u [superpixel]",
        ylabel="v [superpixel]",
    )
    vmax = 4.0
    for i, (method, label) in enumerate([("compensated", "compensated")]):
        res = maps[method]
        assert res is not None
        im = axes[2 + i].imshow(res.residual, cmap="coolwarm", vmin=-vmax, vmax=vmax)
        fig.colorbar(im, ax=axes[2 + i], label="normalised residual [sigma]")
        axes[2 + i].set(
            title=f"Residual n.(L - eps u w)/sigma_L, {label}",
            xlabel="u [superpixel]",
            ylabel="v [superpixel]",
        )
    fig.suptitle("One raw DoFP image (paper Table 1 camera), tilted, eps = 0.0125, occluder")
    path = args.out / "aop_mask_residual.png"
    fig.savefig(path, dpi=110)

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for method, color in [("traditional", "C0"), ("compensated", "C2")]:
        res = maps[method]
        assert res is not None
        r = res.residual[np.isfinite(res.residual)]
        ax.hist(
            r,
            bins=np.linspace(-5, 5, 101),
            histtype="step",
            color=color,
            label=method,
            density=True,
        )
    x = np.linspace(-5, 5, 200)
    ax.plot(x, np.exp(-0.5 * x**2) / np.sqrt(2 * np.pi), "k--", label="N(0, 1)")
    ax.set(
        xlabel="normalised residual [sigma]",
        ylabel="density",
        title="Per-pixel residuals: the sunlight term shows up without compensation",
    )
    ax.legend()
    fig.savefig(args.out / "residual_histogram.png", dpi=110)
    print(f"wrote {path} and residual_histogram.png to {args.out}")


if __name__ == "__main__":
    main()
