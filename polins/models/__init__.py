"""Sensor models: strict loading of the camera and IMU model files (TOML) that polins ships or a user writes."""

from polins.models.loader import (
    CameraModel,
    ImuModel,
    ModelFileError,
    load_camera,
    load_imu,
    shipped_models,
)

__all__ = ["CameraModel", "ImuModel", "ModelFileError", "load_camera", "load_imu", "shipped_models"]
