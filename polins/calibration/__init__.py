"""Camera calibration from data: dark, flat, polarizer, sky rotation, intrinsics, noise, camera-IMU, and a check.

Each estimator takes raw mosaics and a base camera model and returns a result (fitted values,
their standard errors, residuals and a ``provenance`` record); :func:`apply_to_camera`
turns a result into a new camera model. ``calibrate_sky_rotation`` returns the camera model
directly. The procedures, what to record and what the residuals mean are in
docs/calibrate.md.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any, Protocol

from polins.calibration.camera_imu import CameraImuResult, HeldAxisWarning, calibrate_camera_imu
from polins.calibration.dark import DarkResult, calibrate_dark
from polins.calibration.flat import FlatResult, calibrate_flat
from polins.calibration.intrinsics import IntrinsicsResult, calibrate_intrinsics
from polins.calibration.maps import load_pixel_map, save_pixel_map
from polins.calibration.noise import NoiseResult, calibrate_noise
from polins.calibration.polarizer import PolarizerResult, calibrate_polarizer
from polins.calibration.quality import CheckReport, check
from polins.calibration.sky_rotation import (
    SkyRotationResidualWarning,
    SkyRotationResult,
    calibrate_sky_rotation,
    fit_sky_rotation,
)
from polins.models import CameraModel

__all__ = [
    "KINDS",
    "CameraImuResult",
    "CheckReport",
    "DarkResult",
    "FlatResult",
    "HeldAxisWarning",
    "IntrinsicsResult",
    "NoiseResult",
    "PolarizerResult",
    "SkyRotationResidualWarning",
    "SkyRotationResult",
    "apply_to_camera",
    "calibrate_camera_imu",
    "calibrate_dark",
    "calibrate_flat",
    "calibrate_intrinsics",
    "calibrate_noise",
    "calibrate_polarizer",
    "calibrate_sky_rotation",
    "check",
    "fit_sky_rotation",
    "load_pixel_map",
    "save_pixel_map",
]

KINDS = ("dark", "flat", "polarizer", "sky-rotation", "intrinsics", "noise", "camera-imu")


class CalibrationResult(Protocol):
    """What every estimator's result offers: the camera-model fields it sets."""

    provenance: dict[str, Any]

    def camera_changes(self) -> dict[str, Any]: ...


def apply_to_camera(cam: CameraModel, result: CalibrationResult) -> CameraModel:
    """The camera model ``cam`` with the fields a calibration result sets replaced (the
    result's per-pixel maps and its provenance record are the caller's to add:
    ``CameraModel.gain_map`` etc. and ``CameraModel.calibration``, as
    ``polins calibrate`` does, docs/calibrate.md#the-command-line)."""
    return replace(cam, **result.camera_changes())
