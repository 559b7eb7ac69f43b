"""Strict loading of the shipped camera and IMU model files."""

import re

import numpy as np
import pytest

import polins
from polins.models.loader import ModelFileError, shipped_models

CAMERA = polins.load_camera("paper-table1").path.read_text()


def _write(tmp_path, text, name="cam.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_shipped_models_load_and_convert_units():
    assert "paper-table1" in shipped_models("cameras")
    assert {"fins-paper", "mems-typical"} <= set(shipped_models("imus"))
    cam = polins.load_camera("paper-table1")
    assert cam.shape == (2048, 2448) and cam.superpixel_shape == (1024, 1224)
    # Sony IMX250MZR: row 0 = (90, 45), row 1 = (135, 0); channels ordered 0, 45, 90, 135.
    np.testing.assert_array_equal(cam.channel_at, [[2, 1], [3, 0]])
    np.testing.assert_allclose(cam.gain, [1.0269, 1.0, 1.038, 1.005])
    assert cam.fov_max == pytest.approx(np.radians(80.0))
    assert cam.conversion_gain_e_per_dn == np.inf
    imu = polins.load_imu("fins-paper")
    assert imu.gyro_bias == pytest.approx(np.radians(0.02) / 3600.0)
    assert imu.gyro_arw == pytest.approx(np.radians(0.002) / 60.0)
    assert imu.accel_bias == pytest.approx(0.02e-3 * 9.80665)
    assert imu.earth_rate and not polins.load_imu("mems-typical").earth_rate


def test_unknown_name_lists_shipped_models():
    with pytest.raises(FileNotFoundError, match="paper-table1"):
        polins.load_camera("no-such-camera")


def test_wrong_unit_key_is_named_with_file(tmp_path):
    path = _write(tmp_path, CAMERA.replace("fov_max_deg = 80.0", "fov_max_rad = 1.396"))
    with pytest.raises(ModelFileError) as err:
        polins.load_camera(path)
    msg = str(err.value)
    assert str(path) in msg and "lens.fov_max_rad" in msg and "lens.fov_max_deg" in msg


def test_missing_key(tmp_path):
    path = _write(tmp_path, re.sub(r"read_noise_dn = .*\n", "", CAMERA))
    with pytest.raises(ModelFileError, match=r"missing key 'noise.read_noise_dn'"):
        polins.load_camera(path)


@pytest.mark.parametrize(
    ("old", "new", "match"),
    [
        ("[[90, 45], [135, 0]]", "[[90, 45], [45, 0]]", "unknown mosaic layout"),
        # radians in a degree key: 1.4 rad = 80 deg is named (issue: exit 0, yaw NaN all run)
        (
            "fov_max_deg = 80.0",
            "fov_max_deg = 1.4",
            r"degrees expected \(in radians it would be 80.2 deg\)",
        ),
        (
            "fx_superpixel = 259.10",
            "fx_superpixel = 25910.0",
            "focal length must be in superpixels",
        ),
        (
            "transmission_angle_deg = [0.0, 45.0, 90.0, 135.0]",
            "transmission_angle_deg = [0.0, 0.785, 1.571, 2.356]",
            "degrees expected",
        ),
        ("saturation_dn = 4095", "saturation_dn = 65535", "12-bit"),
        ('projection = "kannala-brandt"', 'projection = "fisheye"', "expected one of"),
    ],
)
def test_bad_values(tmp_path, old, new, match):
    assert old in CAMERA
    path = _write(tmp_path, CAMERA.replace(old, new))
    with pytest.raises(ModelFileError, match=match):
        polins.load_camera(path)


def test_imu_wrong_unit(tmp_path):
    text = polins.load_imu("mems-typical").path.read_text()
    path = _write(tmp_path, text.replace("arw_deg_per_sqrt_h", "arw_deg_per_sqrt_s"), "imu.toml")
    with pytest.raises(ModelFileError, match=r"gyro\.arw_deg_per_sqrt_s"):
        polins.load_imu(path)
