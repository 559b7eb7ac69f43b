"""The stream's set-up from a log's manifest: camera, IMU model, site, epoch and the filter's configuration.

:func:`manifest_setup` reads what ``NavigationStream.from_manifest`` needs of a log's
manifest, configured as ``polins fuse`` configures that log (docs/streaming.md);
:func:`with_odometer` completes a configuration for a run with a wheel odometer.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from polins.fusion.config import FuseConfig, config_from_manifest
from polins.fusion.parts import AUTO, ODOMETER_STD
from polins.io.log import model_ref
from polins.io.manifest import MANIFEST_NAME, parse_manifest
from polins.models import load_camera, load_imu
from polins.site import Site


def with_odometer(config: FuseConfig) -> FuseConfig:
    """``config`` for a run with a wheel odometer: an ``"auto"`` ``odometer_std`` becomes
    its value, as :meth:`FuseConfig.resolve` makes it (without resolving the other
    ``"auto"`` choices, which the loop makes itself)."""
    if config.aiding.odometer_std == AUTO:
        return config.replace(odometer_std=ODOMETER_STD)
    return config


def manifest_setup(manifest_path: str | Path) -> dict[str, Any]:
    """The stream's ``camera``, ``imu_model``, ``site``, ``epoch_utc`` and ``config`` of the
    vehicle a log's manifest describes (a folder means its ``manifest.toml``).

    The camera and IMU model files and the site and ``epoch_utc`` of ``[log]``; the filter
    configuration of ``[vehicle]`` and ``[filter]`` (:meth:`polins.FuseConfig.from_log`'s
    :func:`~polins.fusion.config.config_from_manifest`; a ``[vehicle] odometer`` gives the
    odometer scale-factor state). The log's data files are not read.
    """
    path = Path(manifest_path)
    path = path / MANIFEST_NAME if path.is_dir() else path
    tables = parse_manifest(path)
    log, vehicle = tables["log"], tables["vehicle"]
    imu_model = load_imu(model_ref(path.parent, log["imu"]))
    site = Site(log["lat_deg"], log["lon_deg"], log["alt_m"])
    config = config_from_manifest(tables, imu_model, site, path)
    if "odometer" in vehicle:
        config = with_odometer(config)
    camera = load_camera(model_ref(path.parent, log["camera"]))
    return {"camera": camera, "imu_model": imu_model, "site": site,
            "epoch_utc": log["epoch_utc"], "config": config}  # fmt: skip


__all__ = ["manifest_setup", "with_odometer"]
