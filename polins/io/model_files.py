"""Model files as polins writes them: camera and IMU models as TOML that the loaders read back.

:func:`camera_model_toml` and :func:`imu_model_toml` give the text of a model file that
:func:`polins.load_camera` / :func:`polins.load_imu` read back to the same model (a log
folder carries its models this way, see :mod:`polins.io.log`);
:func:`write_camera_file` writes a camera file with its per-pixel maps (``.npy``) and its
``[[calibration]]`` record, atomically. :func:`toml_dumps` is the minimal TOML writer behind
them and the log manifest.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from polins.io.atomic import atomic_path, write_text_atomic
from polins.models import MAP_FIELDS, CameraModel, ImuModel, save_pixel_map


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


def _is_table_array(v: Any) -> bool:
    return isinstance(v, list | tuple) and bool(v) and all(isinstance(t, Mapping) for t in v)


def toml_dumps(data: Mapping[str, Any], header: str = "") -> str:
    """Minimal TOML writer for flat keys, one level of tables and arrays of tables
    (``name = [{...}, ...]`` is written as ``[[name]]`` sections; all polins files need)."""
    lines = [f"# {line}" for line in header.splitlines()]
    tables = {k: v for k, v in data.items() if isinstance(v, Mapping)}
    arrays = {k: v for k, v in data.items() if _is_table_array(v)}
    for key, value in data.items():
        if key not in tables and key not in arrays:
            lines.append(f"{key} = {_toml_value(value)}")
    for name, table in tables.items():
        lines.extend(["", f"[{name}]"])
        lines.extend(f"{k} = {_toml_value(v)}" for k, v in table.items())
    for name, entries in arrays.items():
        for entry in entries:
            lines.extend(["", f"[[{name}]]"])
            lines.extend(f"{k} = {_toml_value(v)}" for k, v in entry.items())
    return "\n".join(lines) + "\n"


def camera_model_toml(
    cam: CameraModel,
    comments: Sequence[str] = (),
    *,
    map_paths: Mapping[str, str | Path] | None = None,
) -> str:
    """A camera model as TOML text that :func:`polins.load_camera` reads back to ``cam``.

    Parameters
    ----------
    cam : CameraModel
    comments : sequence of str
        The file's header comment lines (for example the provenance of a calibration);
        default: where the model came from.
    map_paths : mapping, optional
        Per-pixel map field (``"gain_map"``, ``"transmission_angle_map"``,
        ``"efficiency_map"``) -> the ``.npy`` file that holds it, as the TOML should name it
        (relative to the TOML's folder, or absolute). Every map ``cam`` carries needs one:
        :func:`write_camera_file` saves the maps and names them.

    Raises
    ------
    ValueError
        ``cam`` carries a map that ``map_paths`` does not name, or ``map_paths`` names a map
        that ``cam`` does not carry.
    """
    paths = dict(map_paths or {})
    unknown = set(paths) - set(MAP_FIELDS)
    if unknown:
        raise ValueError(
            f"map_paths: unknown map field(s) {sorted(unknown)}; expected {list(MAP_FIELDS)}"
        )
    for field in MAP_FIELDS:
        if (getattr(cam, field) is None) != (field not in paths):
            raise ValueError(
                f"camera {cam.name!r}: {field} is "
                + ("absent but map_paths names a file" if field in paths else "set but has no file")
                + "; save the maps with polins.io.model_files.write_camera_file"
            )
    k = cam.camera_matrix
    data: dict[str, Any] = {
        "name": cam.name,
        "description": cam.description,
        "sensor": {
            "width_px": cam.width_px,
            "height_px": cam.height_px,
            "bit_depth": cam.bit_depth,
            "saturation_dn": cam.saturation_dn,
            "mosaic_layout_deg": cam.nominal_angle_deg[cam.channel_at],
            **({} if cam.pixel_pitch_um is None else {"pixel_pitch_um": cam.pixel_pitch_um}),
        },
        "polarizer": {
            "nominal_angle_deg": cam.nominal_angle_deg,
            "transmission_angle_deg": np.degrees(cam.transmission_angle),
            "gain": cam.gain,
            "efficiency": cam.efficiency,
            "dark_offset_dn": cam.dark_offset_dn,
            **{
                name: getattr(cam, name)
                for name in ("instrumental_dop_std", "instrumental_mixing_std")
                if getattr(cam, name) is not None
            },
            **{MAP_FIELDS[f]: Path(p).as_posix() for f, p in paths.items()},
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
    roi: dict[str, Any] = {}
    if cam.roi_max_field_angle is not None:
        roi["max_field_angle_deg"] = math.degrees(cam.roi_max_field_angle)
    if cam.roi_polygons:  # superpixel [u, v] -> full-resolution pixels (the file's unit)
        roi["polygons_px"] = [(2.0 * p + 0.5).tolist() for p in cam.roi_polygons]
    if roi:
        data["roi"] = roi
    if cam.calibration:  # an empty array of tables has no TOML form: left out
        data["calibration"] = [dict(entry) for entry in cam.calibration]
    header = "\n".join(comments) if comments else f"camera model written by polins from {cam.path}"
    return toml_dumps(data, header=header)


def write_camera_file(
    cam: CameraModel,
    path: str | Path,
    *,
    comments: Sequence[str] = (),
    maps_dir: str | Path | None = None,
) -> list[Path]:
    """Write ``cam`` as a camera file that :func:`polins.load_camera` reads back, with its
    per-pixel maps.

    Each map ``cam`` carries is saved as ``<maps_dir>/<stem>.<field>.npy`` (float32, no
    pickle; :func:`polins.models.save_pixel_map`), and the TOML names it relative to its own
    folder (absolute when that is impossible). Every file is written atomically, maps first.

    Parameters
    ----------
    cam : CameraModel
    path : str or Path
        The ``.toml`` file to write.
    comments : sequence of str
        Header comment lines (:func:`camera_model_toml`).
    maps_dir : str or Path, optional
        Folder of the map files (created if needed); default: the TOML's folder.

    Returns
    -------
    list of Path
        The files written, maps first, the TOML last.
    """
    path = Path(path)
    folder = path.parent if maps_dir is None else Path(maps_dir)
    written: list[Path] = []
    map_paths: dict[str, str] = {}
    for field in MAP_FIELDS:
        values = getattr(cam, field)
        if values is None:
            continue
        target = folder / f"{path.stem}.{field}.npy"
        target.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(target) as tmp:
            save_pixel_map(tmp, values)
        written.append(target)
        try:
            map_paths[field] = os.path.relpath(target.resolve(), path.parent.resolve())
        except ValueError:  # another drive (Windows)
            map_paths[field] = str(target.resolve())
    written.append(write_text_atomic(path, camera_model_toml(cam, comments, map_paths=map_paths)))
    return written


def imu_model_toml(model: ImuModel, comments: Sequence[str] = ()) -> str:
    """An IMU model as TOML text that :func:`polins.load_imu` reads back to ``model``.

    ``comments`` become the file's header comment lines (for example the Allan fit that
    produced the model, ``polins.tuning.AllanFit.comment_lines()``); the model's
    ``filter_options`` become its ``[filter]`` table.
    """
    data: dict[str, Any] = {
        "name": model.name,
        "description": model.description,
        "grade": model.grade,
        "sample_rate_hz": model.sample_rate_hz,
        **model.toml_values(),
    }
    if model.filter_options:
        data["filter"] = dict(model.filter_options)
    header = "\n".join(comments) if comments else f"IMU model written by polins from {model.path}"
    return toml_dumps(data, header=header)


__all__ = ["camera_model_toml", "imu_model_toml", "toml_dumps", "write_camera_file"]
