"""Allan deviation plot: the per-axis data with error bars against the fitted noise model."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from polins.tuning.allan import ERRORBAR_LEVEL
from polins.tuning.imu_model import AllanFit, SensorAllan

if TYPE_CHECKING:
    from matplotlib.axes import Axes

_DEG_PER_H = np.pi / 180.0 / 3600.0  # [rad/s] per [deg/h]
_AXIS_COLOURS = ("tab:red", "tab:green", "tab:blue")


def _panel(ax: Axes, sensor: SensorAllan, scale: float, unit: str, labels: dict[str, str]) -> None:
    """Draw one sensor's Allan deviations (scaled to ``unit``) and fitted terms on ``ax``."""
    for name, curve, colour in zip(sensor.axes, sensor.curves, _AXIS_COLOURS, strict=True):
        y = curve.adev * scale
        err = np.vstack([y - curve.adev_lo * scale, curve.adev_hi * scale - y])
        ax.errorbar(
            curve.tau,
            y,
            yerr=err,
            fmt="o",
            ms=3,
            lw=0.8,
            color=colour,
            alpha=0.8,
            label=f"{name} data ({ERRORBAR_LEVEL:.0%} bars)",
        )
    c = sensor.combined
    tau = np.geomspace(sensor.combined_curve.tau[0], sensor.combined_curve.tau[-1], 200)
    white, flicker, walk = np.sqrt(c.avar_terms(tau)) * scale
    ax.loglog(tau, c.adev(tau) * scale, "k-", lw=2, label="fitted model (axes pooled)")
    for y, style, text in [
        (white, "--", labels["white"]),
        (flicker, ":", labels["flicker"]),
        (walk, "-.", labels["walk"]),
    ]:
        if np.any(y > 0):
            ax.loglog(tau, y, style, color="0.35", lw=1.2, label=text)
    low = min(float(np.min(cv.adev_lo)) for cv in sensor.curves) * scale
    ax.set_ylim(bottom=0.3 * low)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("averaging time tau [s]")
    ax.set_ylabel(f"Allan deviation [{unit}]")
    ax.grid(True, which="both", lw=0.3, alpha=0.6)
    ax.legend(fontsize=7, loc="best")


def plot_allan(fit: AllanFit, path: str | Path, *, title: str = "") -> Path:
    """Write a log-log Allan deviation plot of a static fit (gyro [deg/h], accel [m/s^2]).

    Parameters
    ----------
    fit : AllanFit
        From :func:`polins.tuning.imu_model_from_static`.
    path : str or Path
        The PNG to write (its folder is created).
    title : str
        Figure title; by default the recording's length and rate.

    Returns
    -------
    Path
        The file written.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    g, a = fit.gyro.combined, fit.accel.combined
    deg_h = 1.0 / _DEG_PER_H
    gyro_labels = {
        "white": f"white: ARW {np.degrees(g.white) * 60:.3g} deg/sqrt(h)",
        "flicker": f"bias instability {g.bias_instability * deg_h:.3g} deg/h",
        "walk": f"rate random walk {g.random_walk * deg_h * 60:.3g} deg/h/sqrt(h)",
    }
    accel_labels = {
        "white": f"white: VRW {a.white * 60:.3g} m/s/sqrt(h)",
        "flicker": f"bias instability {a.bias_instability / 9.80665e-3:.3g} mg",
        "walk": f"accel. random walk {a.random_walk / 9.80665e-3 * 60:.3g} mg/sqrt(h)",
    }
    for sensor, labels in [(fit.gyro, gyro_labels), (fit.accel, accel_labels)]:
        for key, term in [("flicker", "bias_instability"), ("walk", "random_walk")]:
            if not sensor.combined.identified[term]:
                labels[key] += " (not identified)"
    fig, (ax_g, ax_a) = plt.subplots(1, 2, figsize=(11, 4.6))
    _panel(ax_g, fit.gyro, deg_h, "deg/h", gyro_labels)
    ax_g.set_title("gyroscope")
    _panel(ax_a, fit.accel, 1.0, "m/s^2", accel_labels)
    ax_a.set_title("accelerometer")
    fig.suptitle(
        title
        or f"Allan deviation of a static recording: {fit.duration_s:.0f} s in "
        f"{fit.n_segments} segment(s) at {fit.sample_rate_hz:.5g} Hz"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


__all__ = ["plot_allan"]
