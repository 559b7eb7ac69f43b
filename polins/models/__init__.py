"""Sensor models: strict loading of the camera and IMU model files (TOML) that polins ships or a user writes.

``schema`` holds the strict TOML checks, ``maps`` the per-pixel map files, ``camera`` the
:class:`CameraModel` and ``imu`` the :class:`ImuModel`.
"""

from polins.models.camera import CALIBRATION_KINDS, MAP_FIELDS, CameraModel, load_camera
from polins.models.imu import IMU_PLAUSIBLE_RANGES, ImuModel, load_imu
from polins.models.maps import load_pixel_map, save_pixel_map
from polins.models.schema import ModelFileError, shipped_folder, shipped_models

__all__ = [
    "CALIBRATION_KINDS",
    "IMU_PLAUSIBLE_RANGES",
    "MAP_FIELDS",
    "CameraModel",
    "ImuModel",
    "ModelFileError",
    "load_camera",
    "load_imu",
    "load_pixel_map",
    "save_pixel_map",
    "shipped_folder",
    "shipped_models",
]
