"""Round trip of the camera-IMU calibration (docs/calibrate.md#camera-imu): time offset and boresight from a 2-minute log with turns."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_calibration_scenes import small_camera

from polins.calibration import apply_to_camera, calibrate_camera_imu
from polins.errors import UserInputError
from polins.sim.render import direction_n

SUN_N = direction_n(140.0, 35.0)


def _log(rng, *, dt_true, rot_bc, turning=True, noise_deg=0.05):
    """Attitudes at 100 Hz over 120 s (turns up to about 45 deg/s, small roll and pitch
    rocking) and camera sun vectors at 5 Hz stamped on a clock late by ``dt_true``."""
    t_att = np.arange(0.0, 120.0, 0.01)
    yaw = (
        np.radians(60.0) * np.sin(2 * np.pi * t_att / 20.0)
        + np.radians(30.0) * np.sin(2 * np.pi * t_att / 7.0)
        if turning
        else np.zeros_like(t_att)
    )
    pitch = np.radians(2.0) * np.sin(2 * np.pi * t_att / 3.0)
    roll = np.radians(2.0) * np.sin(2 * np.pi * t_att / 4.3)
    rot_nb = Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], -1))
    t_cam = np.arange(1.0, 119.0, 0.2)  # camera clock
    t_true = t_cam + dt_true  # when the images were really taken, on the IMU clock
    yaw_c = np.interp(t_true, t_att, yaw)
    rot_true = Rotation.from_euler(
        "ZYX",
        np.stack([yaw_c, np.interp(t_true, t_att, pitch), np.interp(t_true, t_att, roll)], -1),
    )
    sun_c = (rot_true * rot_bc).inv().apply(SUN_N)
    noise = Rotation.from_rotvec(np.radians(noise_deg) * rng.standard_normal((t_cam.size, 3)))
    return t_cam, noise.apply(sun_c), t_att, rot_nb


def test_camera_imu_recovers_a_10ms_offset_and_the_boresight():
    rng = np.random.default_rng(41)
    rot_bc = Rotation.from_euler("xyz", [0.3, -0.5, 1.2], degrees=True)
    t_cam, sun_c, t_att, rot_nb = _log(rng, dt_true=0.010, rot_bc=rot_bc)
    res = calibrate_camera_imu(t_cam, sun_c, t_att, rot_nb, SUN_N)
    assert abs(res.time_offset_s - 0.010) <= 1e-3
    boresight_err = (Rotation.from_matrix(res.mat_bc) * rot_bc.inv()).magnitude()
    assert np.degrees(boresight_err) <= 0.05
    assert res.time_offset_std_s < 5e-4
    assert np.degrees(np.sqrt(np.mean(res.residuals**2))) == pytest.approx(
        0.05 * np.sqrt(2), rel=0.2
    )
    cam = apply_to_camera(small_camera(8), res)
    np.testing.assert_allclose(cam.mat_bc, res.mat_bc)


def test_camera_imu_refuses_a_log_without_turns():
    rng = np.random.default_rng(42)
    t_cam, sun_c, t_att, rot_nb = _log(rng, dt_true=0.0, rot_bc=Rotation.identity(), turning=False)
    with pytest.raises(UserInputError, match="record turns"):
        calibrate_camera_imu(t_cam, sun_c, t_att, rot_nb, SUN_N)
