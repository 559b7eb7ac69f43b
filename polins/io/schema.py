"""Unit and meaning of every column polins writes: one table behind ``schema.json`` and docs/outputs.md.

:data:`COLUMNS` maps an output file to its columns, each with its unit and meaning.
``polins fuse`` writes the part for the files of a run as ``schema.json``
(:func:`schema_for`); :func:`schema_markdown` renders the same table for docs/outputs.md
(a test checks that the page holds it).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path

import pandas as pd

_ANG = "rad"
_SOLUTION: dict[str, tuple[str, str]] = {
    "t": ("s", "time on the log's clock (seconds after the manifest's epoch_utc)"),
    "roll": (
        _ANG,
        "roll of body (FLU) in ENU, rot_nb = Rotation.from_euler('ZYX', [yaw, pitch, roll])",
    ),
    "pitch": (_ANG, "pitch (nose down positive)"),
    "yaw": (_ANG, "ENU yaw of body x, counter-clockwise from East, wrapped to (-pi, pi]"),
    "heading_deg": ("deg", "compass heading of body x, clockwise from North, in [0, 360)"),
    "roll_std": (_ANG, "1-sigma of roll"),
    "pitch_std": (_ANG, "1-sigma of pitch"),
    "yaw_std": (_ANG, "1-sigma of yaw (and of the heading)"),
    **{f"bg{a}": ("rad/s", f"gyro bias estimate, body {a}") for a in "xyz"},
    **{f"ba{a}": ("m/s^2", f"accelerometer bias estimate, body {a}") for a in "xyz"},
    **{f"bg{a}_std": ("rad/s", f"1-sigma of bg{a}") for a in "xyz"},
    **{f"ba{a}_std": ("m/s^2", f"1-sigma of ba{a}") for a in "xyz"},
    **{
        f"sg{a}": ("-", f"gyro scale-factor error, body {a} (only with scale_factors)")
        for a in "xyz"
    },
    **{
        f"sa{a}": ("-", f"accelerometer scale-factor error, body {a} (only with scale_factors)")
        for a in "xyz"
    },
    **{f"sg{a}_std": ("-", f"1-sigma of sg{a}") for a in "xyz"},
    **{f"sa{a}_std": ("-", f"1-sigma of sa{a}") for a in "xyz"},
    "so": ("-", "wheel-odometer scale-factor error (only with an odometer)"),
    "so_std": ("-", "1-sigma of so"),
    "mount_pitch": (
        _ANG,
        "error of the configured mounting pitch: true mat_vb = exp([(0, mount_pitch, "
        "mount_yaw) x]) configured mat_vb (only with mount_std)",
    ),
    "mount_yaw": (_ANG, "error of the configured mounting yaw (only with mount_std)"),
    "mount_pitch_std": (_ANG, "1-sigma of mount_pitch"),
    "mount_yaw_std": (_ANG, "1-sigma of mount_yaw"),
    **{
        f"lever_b{a}": ("m", f"error of the configured lever_arm_b, IMU {a} (only with lever_std)")
        for a in "xyz"
    },
    **{f"lever_b{a}_std": ("m", f"1-sigma of lever_b{a}") for a in "xyz"},
    **{
        f"site_rot_n{a}": (_ANG, f"ENU frame rotation of the site error, {a} (only with site_std)")
        for a in "xyz"
    },
    **{f"site_rot_n{a}_std": (_ANG, f"1-sigma of site_rot_n{a}") for a in "xyz"},
    "sun_azimuth_n": (_ANG, "the sun's ENU azimuth, counter-clockwise from East (no clock)"),
    "sun_azimuth_n_std": (_ANG, "1-sigma of sun_azimuth_n"),
    "sun_azimuth_rate": ("rad/s", "rate of the sun's ENU azimuth (no clock)"),
    "sun_azimuth_rate_std": ("rad/s", "1-sigma of sun_azimuth_rate"),
    "heading_bias": (
        _ANG,
        "heading-measurement bias: the images' correlated error (not with heading_bias_std "
        "= inf; zero without a correlated model part)",
    ),
    "heading_bias_std": (_ANG, "1-sigma of heading_bias"),
    "ve": ("m/s", "velocity, East"),
    "vn": ("m/s", "velocity, North"),
    "vu": ("m/s", "velocity, Up"),
    "ve_std": ("m/s", "1-sigma of ve"),
    "vn_std": ("m/s", "1-sigma of vn"),
    "vu_std": ("m/s", "1-sigma of vu"),
    "lat_deg": ("deg", "geodetic latitude (WGS-84)"),
    "lon_deg": ("deg", "geodetic longitude (WGS-84)"),
    "alt_m": ("m", "height above the WGS-84 ellipsoid"),
    "pe_std": ("m", "position 1-sigma, local East"),
    "pn_std": ("m", "position 1-sigma, local North"),
    "pu_std": ("m", "position 1-sigma, local Up"),
    "qw": ("-", "attitude quaternion body -> ENU, scalar part"),
    "qx": ("-", "attitude quaternion body -> ENU, x"),
    "qy": ("-", "attitude quaternion body -> ENU, y"),
    "qz": ("-", "attitude quaternion body -> ENU, z"),
}
_MEASUREMENTS: dict[str, tuple[str, str]] = {
    "t": ("s", "image time on the log's clock"),
    "ok": ("bool", "the image gave a heading (False: refused, see reason)"),
    "reason": ("text", "why the measurement refused the image (empty when ok)"),
    "yaw": (_ANG, "measured ENU yaw of body x"),
    "yaw_std": (_ANG, "1-sigma of the measured yaw the filter uses (pixel noise and model error)"),
    "heading_deg": ("deg", "measured compass heading, clockwise from North"),
    "heading_std_deg": ("deg", "1-sigma of heading_deg (= yaw_std)"),
    "epsilon": ("-", "estimated direct-sunlight coefficient of the sky model (docs/model.md)"),
    "epsilon_std": ("-", "1-sigma of epsilon"),
    "n_pixels": ("count", "pixels used by the estimate"),
    "yaw_std_meas": (_ANG, "1-sigma of the yaw from the pixel noise alone (no model error)"),
    "yaw_std_noise": (_ANG, "pixel-noise part of yaw_std (docs/measurement.md §12)"),
    "yaw_std_model": (_ANG, "model-error part of yaw_std (sky-model misfit and camera-fixed part)"),
    "yaw_std_correlated": (
        _ANG,
        "camera-fixed part of yaw_std_model, common to consecutive images",
    ),
    "sun_bx": ("-", "measured unit sun vector, body x"),
    "sun_by": ("-", "measured unit sun vector, body y"),
    "sun_bz": ("-", "measured unit sun vector, body z"),
    "sun_nx": ("-", "ephemeris unit sun vector, East"),
    "sun_ny": ("-", "ephemeris unit sun vector, North"),
    "sun_nz": ("-", "ephemeris unit sun vector, Up"),
    "sun_std": (_ANG, "sun-direction 1-sigma per tangent axis"),
    "sun_azimuth_b": (_ANG, "the sun's azimuth in the body frame, counter-clockwise from body x"),
    "sun_azimuth_b_std": (_ANG, "1-sigma of sun_azimuth_b"),
    "sun_elevation_b": (
        _ANG,
        "the sun's elevation above the body x-y plane where the image determines it, else NaN",
    ),
    "sun_elevation_b_std": (
        _ANG,
        "1-sigma of sun_elevation_b; with it polins.fuse uses the fit's 2x2 sun covariance",
    ),
    "eigen_gap": (
        "-",
        "normalised eigen-gap (lambda_perp - lambda_1) / lambda_perp of the polarization "
        "eigenproblem (docs/model.md 10.1): how clearly the sky fixes the sun's vertical "
        "plane; 1 is a clear sky, below 0.5 the image is refused",
    ),
    "residual_rms": (
        "-",
        "RMS of the fit residuals normalised by the pixel noise; about 1 when the sky model "
        "fits, 25-35 for swapped 45/135 deg channels (docs/measurement.md 8)",
    ),
    "noise_ratio": (
        "-",
        "pixel noise measured in the image / the camera file's noise model; outside "
        "[0.5, 2] the file's noise or gains are wrong (one noise-model event per run)",
    ),
    "prior_t": ("s", "time of the filter state the image prior was taken from"),
    "prior_roll": (_ANG, "attitude prior given to the measurement: roll"),
    "prior_pitch": (_ANG, "attitude prior: pitch"),
    "prior_yaw": (_ANG, "attitude prior: ENU yaw"),
    "accepted": ("bool", "the filter used the measurement (False: gated out or not ok)"),
    "update_reason": ("text", "why the filter did not use it (empty when accepted)"),
    "innovation": (_ANG, "measurement minus the filter's prediction (yaw update)"),
    "nis": ("-", "normalised innovation squared; chi-square with nis_dof degrees of freedom"),
    "nis_dof": ("count", "degrees of freedom of nis (1: yaw, 2: sun vector)"),
    "measure_s": ("s", "wall-clock time the measurement of this image took"),
    "image": ("text", "the image file (or bag message) measured"),
    "yaw_error": (_ANG, "measured yaw minus the reference yaw (logs with truth.csv only)"),
}
_EVENTS: dict[str, tuple[str, str]] = {
    "t": ("s", "time of the sample or image the event is about"),
    "kind": ("text", "event kind (docs/faults.md; polins.fusion.faults.EventKind)"),
    "detail": ("text", "what happened, for a person"),
}
_DEMO_SUMMARY: dict[str, tuple[str, str]] = {
    "key": ("text", "short name of the heading estimator"),
    "estimator": ("text", "heading estimator, as labelled in the plots"),
    "rmse_deg": ("deg", "RMS heading error over the images"),
    "mean_deg": ("deg", "mean heading error"),
    "sd_deg": ("deg", "standard deviation of the heading error"),
    "max_abs_deg": ("deg", "largest absolute heading error"),
    "n_ok": ("count", "images that gave a heading"),
    "n": ("count", "images"),
    "paper_role": ("text", "what the estimator stands for in the paper"),
    "scenario": ("text", "simulated scenario"),
    "crlb_deg": ("deg", "Cramer-Rao lower bound of the heading 1-sigma"),
}
_DEMO_IMAGES: dict[str, tuple[str, str]] = {
    "image": ("count", "image number"),
    "t": ("s", "image time"),
    "estimator": ("text", "short name of the heading estimator"),
    "heading_true_deg": ("deg", "true compass heading, clockwise from North"),
    "heading_prior_deg": ("deg", "heading of the attitude prior given to the estimator"),
    "heading_deg": ("deg", "estimated compass heading, clockwise from North"),
    "error_deg": ("deg", "estimated minus true heading, wrapped to (-180, 180]"),
    "yaw_std_meas_deg": ("deg", "1-sigma of the estimate from the pixel noise"),
    "epsilon": ("-", "estimated direct-sunlight coefficient"),
    "ok": ("bool", "the estimator gave a heading"),
    "reason": ("text", "why it did not (empty when ok)"),
    "scenario": ("text", "simulated scenario"),
}

COLUMNS: dict[str, dict[str, tuple[str, str]]] = {
    "solution.csv": _SOLUTION,
    "measurements.csv": _MEASUREMENTS,
    "events.csv": _EVENTS,
    "summary.csv": _DEMO_SUMMARY,
    "images.csv": _DEMO_IMAGES,
}
FILES: dict[str, str] = {
    "solution.csv": "fused solution, one row per output time (output_rate_hz, default 10 per "
    "second, and the last IMU sample)",
    "measurements.csv": "one row per image: the measurement and the filter's verdict",
    "events.csv": "data faults skipped and reported (docs/faults.md)",
    "summary.json": "counts, rejections, NIS, timings and (with truth) accuracy statistics",
    "schema.json": "this table: unit and meaning of every column of the CSV (or Parquet) files",
    "run.json": "stamp of the run: polins version, command, settings, files, status",
    "heading.png": "heading vs time (fused, reference, measurements) and the residuals in the fused 3-sigma band",
    "heading_error.png": "fused heading minus the reference, with the reported 3-sigma band",
    "measurements.png": "per-image measurement error and the NIS of the filter updates",
    "epsilon.png": "estimated direct-sunlight coefficient per image",
}


def schema_for(tables: Mapping[str, pd.DataFrame]) -> dict[str, dict[str, dict[str, str]]]:
    """``{file: {column: {"unit", "meaning"}}}`` for the columns of the tables written
    (``solution.csv`` or ``solution.parquet``: the same columns).

    A column without an entry in :data:`COLUMNS` gets an empty unit and meaning (a test
    keeps the table complete).
    """
    out = {}
    for name, df in tables.items():  # a Parquet table has the columns of its CSV namesake
        known = COLUMNS.get(name, COLUMNS.get(f"{Path(name).stem}.csv", {}))
        out[name] = {
            str(c): {
                "unit": known.get(str(c), ("", ""))[0],
                "meaning": known.get(str(c), ("", ""))[1],
            }
            for c in df.columns
        }
    return out


def schema_markdown(
    files: Iterable[str] = ("solution.csv", "measurements.csv", "events.csv"),
) -> str:
    """The column tables of ``files`` as Markdown (for docs/outputs.md)."""
    parts = []
    for name in files:
        parts.append(f"### `{name}`\n\n{FILES.get(name, '')}\n")
        parts.append("| column | unit | meaning |\n|---|---|---|")
        parts.extend(f"| `{c}` | {u} | {m} |" for c, (u, m) in COLUMNS[name].items())
        parts.append("")
    return "\n".join(parts)


__all__ = ["COLUMNS", "FILES", "schema_for", "schema_markdown"]
