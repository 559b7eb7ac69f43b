"""Allan deviation plot: the per-axis data with error bars against the fitted noise model."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from polins.tuning.allan import ERRORBAR_LEVEL, NoiseTerms
from polins.tuning.imu_model import AllanFit, SensorAllan, model_random_walk

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
    white, flicker, _ = np.sqrt(c.avar_terms(tau)) * scale
    ax.loglog(tau, c.adev(tau) * scale, "k-", lw=2, label="fitted model (axes pooled)")
    model_walk = model_random_walk(c)[0] * np.sqrt(tau / 3.0) * scale  # the model file's value
    for y, style, text in [
        (white, "--", labels["white"]),
        (flicker, ":", labels["flicker"]),
        (model_walk, "-.", labels["walk"]),
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


def _bound_label(terms: NoiseTerms, value: float, text: str) -> str:
    """``text`` with the model file's value, marked as an upper bound when not identified."""
    if terms.identified["random_walk"]:
        return text.format(op="=", value=value, how="fitted")
    return text.format(op="<=", value=value, how="upper bound: not identified")


def legend_labels(fit: AllanFit) -> tuple[dict[str, str], dict[str, str]]:
    """The legend texts of the gyro and accelerometer panels, in the model file's units.

    The white-noise and random-walk entries give the values the IMU model file holds
    (:func:`polins.tuning.model_random_walk`, 4 significant digits as in its comments),
    a random walk the record does not identify as an upper bound (``<=``); the bias
    instability is not a model key and is labelled so.
    """
    g, a = fit.gyro.combined, fit.accel.combined
    deg_h, mg = 1.0 / _DEG_PER_H, 1.0 / 9.80665e-3
    flicker = "bias instability {0:.3g} {1}, fitted (not a model key){2}"
    gyro = {
        "white": f"gyro.arw_deg_per_sqrt_h = {np.degrees(g.white) * 60:.4g} (white noise)",
        "flicker": flicker.format(g.bias_instability * deg_h, "deg/h",
                                  "" if g.identified["bias_instability"] else ", not identified"),
        "walk": _bound_label(g, model_random_walk(g)[0] * deg_h * 60,
                             "gyro.bias_rw_deg_per_h_per_sqrt_h {op} {value:.4g} ({how})"),
    }  # fmt: skip
    accel = {
        "white": f"accel.vrw_m_per_s_per_sqrt_h = {a.white * 60:.4g} (white noise)",
        "flicker": flicker.format(a.bias_instability * mg, "mg",
                                  "" if a.identified["bias_instability"] else ", not identified"),
        "walk": _bound_label(a, model_random_walk(a)[0] * mg * 60,
                             "accel.bias_rw_mg_per_sqrt_h {op} {value:.4g} ({how})"),
    }  # fmt: skip
    return gyro, accel


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
    gyro_labels, accel_labels = legend_labels(fit)
    fig, (ax_g, ax_a) = plt.subplots(1, 2, figsize=(11, 4.6))
    _panel(ax_g, fit.gyro, 1.0 / _DEG_PER_H, "deg/h", gyro_labels)
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


__all__ = ["legend_labels", "plot_allan"]
