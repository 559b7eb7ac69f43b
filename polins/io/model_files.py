"""Model files as polins writes them: camera and IMU models as TOML that the loaders read back.

:func:`camera_model_toml` and :func:`imu_model_toml` give the text of a model file that
:func:`polins.load_camera` / :func:`polins.load_imu` read back to the same model (a log
folder carries its models this way, see :mod:`polins.io.log`); :func:`toml_dumps` is the
minimal TOML writer behind them and the log manifest.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from polins.models.loader import CameraModel, ImuModel


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | np.integer):
        return str(int(v))
    if isinstance(v, float | np.floating):
        x = float(v)
        if math.isnan(x):
            return "nan"
        if math.isinf(x):
            return "inf" if x > 0 else "-inf"
        return repr(x)
    if isinstance(v, str):
        return json.dumps(v)  # a JSON string is a valid TOML basic string
    if isinstance(v, np.ndarray):
        return _toml_value(v.tolist())
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def toml_dumps(data: Mapping[str, Any], header: str = "") -> str:
    """Minimal TOML writer for flat keys and one level of tables (all polins files need)."""
    lines = [f"# {line}" for line in header.splitlines()]
    tables = {k: v for k, v in data.items() if isinstance(v, Mapping)}
    for key, value in data.items():
        if key not in tables:
            lines.append(f"{key} = {_toml_value(value)}")
    for name, table in tables.items():
        lines.extend(["", f"[{name}]"])
        lines.extend(f"{k} = {_toml_value(v)}" for k, v in table.items())
    return "\n".join(lines) + "\n"


def camera_model_toml(cam: CameraModel) -> str:
    """A camera model as TOML text that :func:`polins.load_camera` reads back to ``cam``."""
    k = cam.camera_matrix
    data = {
        "name": cam.name,
        "description": cam.description,
        "sensor": {
            "width_px": cam.width_px,
            "height_px": cam.height_px,
            "pixel_pitch_um": cam.pixel_pitch_um,
            "bit_depth": cam.bit_depth,
            "saturation_dn": cam.saturation_dn,
            "mosaic_layout_deg": cam.nominal_angle_deg[cam.channel_at],
        },
        "polarizer": {
            "nominal_angle_deg": cam.nominal_angle_deg,
            "transmission_angle_deg": np.degrees(cam.transmission_angle),
            "gain": cam.gain,
            "efficiency": cam.efficiency,
            "dark_offset_dn": cam.dark_offset_dn,
        },
        "noise": {
            "read_noise_dn": cam.read_noise_dn,
            "conversion_gain_e_per_dn": cam.conversion_gain_e_per_dn,
        },
        "lens": {
            "projection": cam.projection,
            "polarization_model": cam.polarization_model,
            "fx_superpixel": k[0, 0],
            "fy_superpixel": k[1, 1],
            "cx_superpixel": k[0, 2],
            "cy_superpixel": k[1, 2],
            "distortion": cam.distortion,
            "fov_max_deg": math.degrees(cam.fov_max),
        },
        "mount": {"mat_bc": cam.mat_bc},
        "occlusion": {"polygons_superpixel": [p.tolist() for p in cam.occlusion_polygons]},
    }
    return toml_dumps(data, header=f"camera model written by polins from {cam.path}")


def imu_model_toml(model: ImuModel, comments: Sequence[str] = ()) -> str:
    """An IMU model as TOML text that :func:`polins.load_imu` reads back to ``model``.

    ``comments`` become the file's header comment lines (for example the Allan fit that
    produced the model, ``polins.tuning.AllanFit.comment_lines()``).
    """
    data: dict[str, Any] = {
        "name": model.name,
        "description": model.description,
        "grade": model.grade,
        "earth_rate": model.earth_rate,
        "sample_rate_hz": model.sample_rate_hz,
        **model.toml_values(),
    }
    header = "\n".join(comments) if comments else f"IMU model written by polins from {model.path}"
    return toml_dumps(data, header=header)


__all__ = ["camera_model_toml", "imu_model_toml", "toml_dumps"]
