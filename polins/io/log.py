"""A recorded (or simulated) log on disk: ``manifest.toml`` plus IMU table, images and truth.

Folder layout (docs/filter.md), as written by :func:`write_log`::

    manifest.toml       what is where, site, epoch, sensor models, units
    imu.csv             t, gx, gy, gz, ax, ay, az        (or imu.parquet)
    images.csv          t, file                           (index of the raw mosaics)
    images/000000.png   16-bit raw DoFP mosaics           (or .tiff)
    truth.csv           Trajectory.truth_frame() columns  (optional reference trajectory)
    camera.toml         camera model, when given as an object (self-contained log)
    imu_model.toml      IMU model, when given as an object

``manifest.toml``: :mod:`polins.io.manifest` describes and reads it.

Every file is written atomically and the manifest last, so a folder with a manifest is a
complete log; an interrupted :func:`write_log` leaves no manifest.
"""

from __future__ import annotations

import os
import re
import shutil
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from polins.errors import UserInputError
from polins.io.atomic import atomic_path, write_text_atomic
from polins.io.images import IMAGE_SUFFIXES, ImageIndex, read_image_index, write_image
from polins.io.images import write_image_index as _write_index
from polins.io.manifest import MANIFEST_NAME, ManifestError, number_in, parse_manifest
from polins.io.model_files import (
    camera_model_toml,
    imu_model_toml,
    toml_dumps,
    write_camera_file,
)
from polins.io.tables import read_imu, read_table, write_imu, write_table
from polins.models import CameraModel, ImuModel, load_camera, load_imu
from polins.site import Site, utc_timestamp
from polins.sky.ephemeris import sun_position, sun_vector_n


class ImageSource(Protocol):
    """Times and lazily loaded raw images of a log (folder index or ROS bag)."""

    @property
    def t(self) -> NDArray[np.float64]: ...

    def __len__(self) -> int: ...

    def __iter__(self) -> Iterator[tuple[float, Any]]: ...


# ----------------------------------------------------------------------------- Log
@dataclass(frozen=True, eq=False)
class Log:
    """A log loaded from its manifest; images are read lazily.

    Attributes
    ----------
    manifest_path : Path
    epoch_utc : Timestamp
        UTC time of ``t = 0``.
    camera : CameraModel
    imu_model : ImuModel
    site : Site
        Where the log was recorded (``[log]`` lat_deg, lon_deg, alt_m).
    imu : DataFrame
        ``t, gx, gy, gz`` [rad/s], ``ax, ay, az`` [m/s^2], as recorded (not yet cleaned).
    images : ImageSource
        ``.t`` image times [s] and iteration over ``(t, item)``; load an item with
        :func:`polins.io.load_raw`.
    truth : DataFrame or None
        Reference trajectory (``Trajectory.truth_frame()`` columns), if the log has one.
    description : str
    manifest : dict
        The validated manifest (``parse_manifest``); its filter configuration is
        ``polins.FuseConfig.from_log(log)``.
    events : tuple of (t, kind, detail)
        Data faults found while loading (``path-outside-log``: an image index entry outside
        the log folder, skipped); the navigation loop reports them with its own.
    odometry : DataFrame or None
        The wheel odometer of ``[vehicle] odometer`` (``t`` [s], ``speed`` [m/s]), if any.
    """

    manifest_path: Path
    epoch_utc: pd.Timestamp
    camera: CameraModel
    imu_model: ImuModel
    site: Site
    imu: pd.DataFrame
    images: ImageSource
    truth: pd.DataFrame | None = None
    description: str = ""
    manifest: dict[str, dict[str, Any]] = field(default_factory=dict)
    events: tuple[tuple[float, str, str], ...] = ()
    odometry: pd.DataFrame | None = None

    @property
    def lat_deg(self) -> float:
        """Latitude of the site [deg]."""
        return self.site.lat_deg

    @property
    def lon_deg(self) -> float:
        """Longitude of the site [deg]."""
        return self.site.lon_deg

    @property
    def alt_m(self) -> float:
        """Height of the site above the WGS-84 ellipsoid [m]."""
        return self.site.alt_m

    @property
    def folder(self) -> Path:
        """Folder holding the manifest."""
        return self.manifest_path.parent

    def times_utc(self, t: NDArray[np.float64]) -> pd.DatetimeIndex:
        """Absolute UTC times of log times ``t`` [s]."""
        return pd.DatetimeIndex(self.epoch_utc + pd.to_timedelta(np.asarray(t, float), unit="s"))

    def sun_n(self, t: NDArray[np.float64]) -> NDArray[np.float64]:
        """``(N, 3)`` ENU sun vectors (NREL SPA, apparent) at log times ``t`` [s]."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        if t.size == 0:
            return np.zeros((0, 3))
        sun = sun_position(self.times_utc(t), self.lat_deg, self.lon_deg, self.alt_m)
        return sun_vector_n(sun.azimuth, sun.zenith)


def model_ref(folder: Path, ref: str) -> str | Path:
    """Manifest model reference -> shipped name or path (relative to the manifest)."""
    if ref.endswith(".toml") or "/" in ref or "\\" in ref:
        p = Path(ref)
        return p if p.is_absolute() else folder / p
    return ref


def _inside(path: Path, roots: Iterable[Path]) -> bool:
    """Whether ``path`` lies in one of ``roots`` (lexically: ``..`` resolved, symlinks kept)."""
    p = Path(os.path.normpath(path.absolute()))
    return any(p.is_relative_to(os.path.normpath(r.absolute())) for r in roots)


def _images_inside(
    images: ImageIndex, roots: Iterable[Path]
) -> tuple[ImageIndex, list[tuple[float, str, str]]]:
    """The index without its entries outside ``roots``, and one event per entry dropped."""
    roots = list(roots)
    keep = [_inside(f, roots) for f in images.files]
    events = [
        (float(t), "path-outside-log",
         f"{f}: outside the log folder, skipped (--allow-outside-paths to follow it)")
        for t, f, k in zip(images.t.tolist(), images.files, keep, strict=True) if not k
    ]  # fmt: skip
    if not events:
        return images, []
    mask = np.array(keep, dtype=bool)
    files = tuple(f for f, k in zip(images.files, keep, strict=True) if k)
    return ImageIndex(t=images.t[mask], files=files), events


def read_log(
    manifest_path: str | Path,
    *,
    gyro_unit: str | None = None,
    accel_unit: str | None = None,
    imu_model: str | Path | ImuModel | None = None,
    allow_outside_paths: bool = False,
) -> Log:
    """Load a log from its manifest (a folder is taken to mean its ``manifest.toml``).

    ``gyro_unit`` / ``accel_unit`` override the manifest's ``[units]`` (not the IMU file's
    own declaration, which must agree). ``imu_model`` (a shipped name, a TOML path relative
    to the working folder, or a model) overrides the manifest's ``log.imu``. Image index
    entries outside the log folder (``../..``, absolute paths) are skipped and reported as
    ``path-outside-log`` events (:attr:`Log.events`) unless ``allow_outside_paths``.

    Raises
    ------
    FileNotFoundError, ManifestError, ValueError
        Missing files, bad manifest keys (named), bad tables.
    """
    path = Path(manifest_path)
    if path.is_dir():
        path = path / MANIFEST_NAME
    m = parse_manifest(path)
    folder = path.parent
    log, files, units = m["log"], m["files"], m["units"]

    def load(key: str, loader: Callable[[Any], Any]) -> Any:
        try:
            return loader(model_ref(folder, log[key]))
        except (FileNotFoundError, ValueError) as exc:
            raise type(exc)(f"{path}: key 'log.{key}': {exc}") from None

    camera = load("camera", load_camera)
    model: ImuModel
    if imu_model is None:
        model = load("imu", load_imu)
    else:
        model = imu_model if isinstance(imu_model, ImuModel) else load_imu(imu_model)

    def file(key: str) -> Path:
        p = Path(files[key])
        p = p if p.is_absolute() else folder / p
        if not p.exists():
            raise FileNotFoundError(f"{path}: key 'files.{key}': {p} does not exist")
        return p

    images: ImageSource
    if "bag" in files:
        from polins.io.rosbag import read_bag

        imu, images = read_bag(file("bag"), epoch_utc=log.get("epoch_utc"), **m["ros"])
        log = {**log, "epoch_utc": images.epoch_utc}  # the manifest's, else the first stamp
    else:
        imu = read_imu(
            file("imu"),
            gyro_unit=gyro_unit or units.get("gyro"),
            accel_unit=accel_unit or units.get("accel"),
        )
        images = read_image_index(file("images"))
    events: list[tuple[float, str, str]] = []
    if isinstance(images, ImageIndex) and not allow_outside_paths:
        images, events = _images_inside(images, {folder, file("images").parent})
    truth = read_table(file("truth")) if "truth" in files else None
    site = Site(log["lat_deg"], log["lon_deg"], log["alt_m"])
    vehicle = m["vehicle"]
    odometry = None
    if "odometer" in vehicle:
        p = Path(vehicle["odometer"])
        p = p if p.is_absolute() else folder / p
        if not p.exists():
            raise FileNotFoundError(f"{path}: key 'vehicle.odometer': {p} does not exist")
        odometry = read_table(p)
        if not {"t", "speed"} <= set(odometry.columns):
            raise ManifestError(f"{path}: key 'vehicle.odometer': {p} needs columns t, speed")
    return Log(
        manifest_path=path,
        epoch_utc=log["epoch_utc"],
        camera=camera,
        imu_model=model,
        site=site,
        imu=imu,
        images=images,
        truth=truth,
        description=log["description"],
        manifest=m,
        events=tuple(events),
        odometry=odometry,
    )


def _model_entry(
    folder: Path, model: Any, file_name: str, kind: str, to_toml: Callable[[Any], str]
) -> str:
    if isinstance(model, CameraModel) and model.has_pixel_maps:
        write_camera_file(model, folder / file_name)  # its per-pixel maps go beside it
        return file_name
    if isinstance(model, CameraModel | ImuModel):
        write_text_atomic(folder / file_name, to_toml(model))
        return file_name
    if not isinstance(model, str | Path):
        raise TypeError(f"{kind} must be a model object, a shipped model name or a .toml path")
    p = Path(model)
    if p.suffix == ".toml" or p.exists():
        if not p.is_file():
            raise FileNotFoundError(f"{kind} model file not found: {p}")
        if kind == "camera" and "_npy" in p.read_text(encoding="utf-8"):
            # A camera file that names per-pixel maps: a plain copy would lose them (their
            # paths are relative to the original); write it with its maps instead.
            write_camera_file(load_camera(p), folder / file_name)
            return file_name
        with atomic_path(folder / file_name) as tmp:
            shutil.copyfile(p, tmp)
        return file_name
    (load_camera if kind == "camera" else load_imu)(str(model))  # unknown name -> clear error
    return str(model)


_NUMBERED = re.compile(r"^(?P<i>[0-9]{6,})\.(png|tif|tiff)$")


def write_log(
    folder: str | Path,
    *,
    epoch_utc: Any,
    camera: CameraModel | str | Path,
    imu_model: ImuModel | str | Path,
    lat_deg: float,
    lon_deg: float,
    alt_m: float,
    imu: pd.DataFrame,
    images: Iterable[tuple[float, NDArray[np.unsignedinteger]]],
    truth: pd.DataFrame | None = None,
    image_format: str = "png",
    imu_format: str = "csv",
    gyro_unit: str = "rad/s",
    accel_unit: str = "m/s^2",
    description: str = "",
    vehicle: Mapping[str, Any] | None = None,
    odometry: pd.DataFrame | None = None,
) -> Path:
    """Write a log folder (layout in the module docstring); returns the manifest path.

    Parameters
    ----------
    folder : str or Path
        Output folder (created). An existing log there is replaced: its manifest is
        removed first, so an interrupted rewrite is never mistaken for a complete log.
    epoch_utc : str, datetime or Timestamp
        Timezone-aware UTC epoch of ``t = 0``; a naive time raises ``ValueError``.
    camera, imu_model : model object, shipped name, or .toml path
        Objects (e.g. ``cam.downscaled(4)``) and paths are written into the folder
        (``camera.toml``, ``imu_model.toml``), so the log is self-contained.
    lat_deg, lon_deg, alt_m : float
        Site [deg, deg, m].
    imu : DataFrame
        SI IMU samples ``t, gx, gy, gz, ax, ay, az``.
    images : iterable of (t, raw)
        Image times [s] and ``(H, W)`` uint16 mosaics; consumed once, one at a time.
    truth : DataFrame, optional
        Reference trajectory (``Trajectory.truth_frame()``), written as ``truth.csv``.
    image_format : {"png", "tiff"}
    imu_format : {"csv", "parquet"}
    gyro_unit, accel_unit : str
        Units to store the IMU in (declared in the file; read back as SI).
    description : str
        Free text stored in the manifest.
    vehicle : mapping, optional
        The manifest's ``[vehicle]`` table (module docstring).
    odometry : DataFrame, optional
        Wheel-odometer ``t, speed``, written as ``odometer.csv`` (named in ``[vehicle]``).
    """
    folder = Path(folder)
    epoch = utc_timestamp(epoch_utc)
    if image_format not in ("png", "tiff", "tif"):
        raise UserInputError(f"image_format {image_format!r}: expected 'png' or 'tiff'")
    if imu_format not in ("csv", "parquet"):
        raise UserInputError(f"imu_format {imu_format!r}: expected 'csv' or 'parquet'")
    number_in(-90.0, 90.0)(lat_deg)
    number_in(-180.0, 360.0)(lon_deg)
    folder.mkdir(parents=True, exist_ok=True)
    manifest = folder / MANIFEST_NAME
    manifest.unlink(missing_ok=True)

    camera_ref = _model_entry(folder, camera, "camera.toml", "camera", camera_model_toml)
    imu_ref = _model_entry(folder, imu_model, "imu_model.toml", "imu", imu_model_toml)
    imu_name = f"imu.{imu_format}"
    write_imu(folder / imu_name, imu, gyro_unit=gyro_unit, accel_unit=accel_unit)

    image_dir = folder / "images"
    image_dir.mkdir(exist_ok=True)
    times: list[float] = []
    names: list[str] = []
    for i, (t, raw) in enumerate(images):
        name = f"images/{i:06d}.{image_format}"
        write_image(folder / name, raw)
        times.append(float(t))
        names.append(name)
    for stale in image_dir.iterdir():  # numbered images of an earlier, longer log
        match = _NUMBERED.match(stale.name)
        if match and int(match.group("i")) >= len(names) and stale.suffix in IMAGE_SUFFIXES:
            stale.unlink()
    _write_index(folder / "images.csv", np.asarray(times), names)

    files = {"imu": imu_name, "images": "images.csv"}
    if truth is not None:
        write_table(folder / "truth.csv", truth)
        files["truth"] = "truth.csv"
    tables: dict[str, Any] = {}
    if vehicle is not None or odometry is not None:
        tables["vehicle"] = dict(vehicle or {})
    if odometry is not None:
        write_table(folder / "odometer.csv", odometry[["t", "speed"]])
        tables["vehicle"]["odometer"] = "odometer.csv"
    text = toml_dumps(
        {
            "log": {
                "epoch_utc": epoch.isoformat(),
                "camera": camera_ref,
                "imu": imu_ref,
                "lat_deg": float(lat_deg),
                "lon_deg": float(lon_deg),
                "alt_m": float(alt_m),
                "description": description,
            },
            "files": files,
            "units": {"gyro": gyro_unit, "accel": accel_unit},
            **tables,
        },
        header="polins log manifest (see polins.io.log); t [s] counts from log.epoch_utc",
    )
    return write_text_atomic(manifest, text)


__all__ = [
    "MANIFEST_NAME",
    "ImageSource",
    "Log",
    "ManifestError",
    "model_ref",
    "parse_manifest",
    "read_log",
    "write_log",
]
