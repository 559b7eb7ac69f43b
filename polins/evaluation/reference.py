"""Errors against a reference trajectory: the solution's and the measurements' errors, with their consistency statistics."""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray
from scipy.stats import chi2

from polins.frames import rot_nb_from_euler, wrap_angle
from polins.fusion.inputs import PRIOR_COLUMNS
from polins.fusion.items import item_model, items_from_table
from polins.tuning.innovations import effective_samples

FloatArray = NDArray[np.float64]


def truth_at(truth: pd.DataFrame, t: FloatArray) -> pd.DataFrame:
    """Reference roll, pitch, yaw [rad] at times ``t`` (linear, yaw unwrapped); NaN outside."""
    tt = truth["t"].to_numpy(dtype=float)
    t = np.asarray(t, dtype=float)
    out = {"t": t}
    for name in ("roll", "pitch", "yaw"):
        v = truth[name].to_numpy(dtype=float)
        v = np.unwrap(v) if name == "yaw" else v
        val = np.interp(t, tt, v, left=np.nan, right=np.nan)
        out[name] = wrap_angle(val) if name == "yaw" else val
    return pd.DataFrame(out)


def measurement_residuals(measurements: pd.DataFrame, truth: pd.DataFrame) -> FloatArray:
    """The measured yaws' residuals at the reference attitude [rad], ``z - h(x_true, prior)``.

    With the attitude prior and the ENU sun of each image, the tilt-coupled yaw model
    (docs/measurement.md, tilt coupling) predicts what the image should have measured had
    the attitude been the reference; this residual is what ``yaw_std`` must cover. Rows
    without a yaw are NaN; without the prior or the sun, the residual is the plain error.
    """
    m = measurements
    t = m["t"].to_numpy(dtype=float)
    ref = truth_at(truth, t)
    out = np.full(t.size, np.nan)
    needed = ("yaw", "yaw_std", *PRIOR_COLUMNS, "sun_nx", "sun_ny", "sun_nz")
    rows = m[[c for c in ("t", *needed) if c in m.columns]]
    coupled = all(c in rows.columns for c in needed)
    items = items_from_table(rows, use_sun=False)
    for i, item in enumerate(items):
        if item.kind != "yaw" or not item.valid or not np.isfinite(ref["yaw"].iloc[i]):
            continue
        mat_nb = rot_nb_from_euler(
            ref["yaw"].iloc[i], ref["pitch"].iloc[i], ref["roll"].iloc[i]
        ).as_matrix()
        out[i] = item_model(item, mat_nb, None, coupled).residual[0]
    return out


def error_stats(err: FloatArray, std: FloatArray | None = None) -> dict[str, Any]:
    """RMS / max / final of an error [deg]; with sigmas also RMS(err/sigma) and 3-sigma share."""
    ok = np.isfinite(err)
    if std is not None:
        ok &= np.isfinite(std) & (std > 0)
    e = err[ok]
    if e.size == 0:
        return {"rms_deg": None, "max_abs_deg": None, "final_deg": None, "n": 0}
    out: dict[str, Any] = {
        "rms_deg": float(np.sqrt(np.mean(e**2))),
        "mean_deg": float(np.mean(e)),
        "max_abs_deg": float(np.max(np.abs(e))),
        "final_deg": float(e[-1]),
        "n": int(e.size),
    }
    if std is not None:
        z = e / std[ok]
        out["final_sigma_deg"] = float(std[ok][-1])
        out.update(normalized_error_stats(z))
    return out


def normalized_error_stats(z: FloatArray, prob: float = 0.95) -> dict[str, Any]:
    """RMS of normalized errors ``z = err / sigma`` with its band and verdict.

    The band is that of the RMS of ``n_eff`` independent standard normal samples,
    ``sqrt(chi2.ppf(q, n_eff) / n_eff)``, where ``n_eff`` is the effective number of
    independent ``z^2`` (:func:`polins.tuning.innovations.effective_samples`): a filter's
    errors drift slowly, so a run holds far fewer independent errors than samples.
    Above the band the sigmas are optimistic, below it conservative.
    """
    rms = float(np.sqrt(np.mean(z**2)))
    n_eff = effective_samples(z**2, prob=prob)
    a = 1.0 - prob
    lo, hi = np.sqrt(chi2.ppf([a / 2, 1 - a / 2], n_eff) / n_eff)
    verdict = "consistent"
    if rms > hi:
        verdict = "optimistic: sigma too small"
    elif rms < lo:
        verdict = "conservative: sigma too large"
    return {"rms_normalized": rms, "within_3sigma": float(np.mean(np.abs(z) <= 3.0)),
            "n_eff": n_eff, "rms_normalized_band": [float(lo), float(hi)], "verdict": verdict}  # fmt: skip


def solution_errors(solution: pd.DataFrame, truth: pd.DataFrame) -> pd.DataFrame:
    """Solution minus reference: ``t, roll_err, pitch_err, yaw_err`` [rad] (yaw wrapped)."""
    ref = truth_at(truth, solution["t"].to_numpy(dtype=float))
    return pd.DataFrame(
        {
            "t": ref["t"],
            "roll_err": solution["roll"].to_numpy() - ref["roll"].to_numpy(),
            "pitch_err": solution["pitch"].to_numpy() - ref["pitch"].to_numpy(),
            "yaw_err": wrap_angle(solution["yaw"].to_numpy() - ref["yaw"].to_numpy()),
        }
    )


__all__ = [
    "error_stats",
    "measurement_residuals",
    "normalized_error_stats",
    "solution_errors",
    "truth_at",
]
