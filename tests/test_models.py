"""Strict loading of the shipped camera and IMU model files."""

import pickle
import re

import numpy as np
import pytest

import polins
from polins.io.model_files import camera_model_toml, write_camera_file
from polins.models import ModelFileError, save_pixel_map, shipped_models
from polins.models.camera import calibration_entry

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
    assert polins.load_imu("mems-typical").gyro_misalignment == 0.0
    broad = polins.load_imu("broad-aktos-t")
    assert broad.gyro_misalignment == pytest.approx(6e-3)
    assert broad.gyro_misalignment_corr_time == pytest.approx(0.1)


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


# ----------------------------------------------------------------------------- calibration
SMALL = polins.load_camera("paper-table1").downscaled(8)  # 153 x 128 superpixels
ENTRY = (
    '\n[[calibration]]\nkind = "flat"\ndate = "2026-05-04T10:30:00+00:00"\n'
    'method = "channel means"\nn_images = 20\nresidual_rms = 1.5e-4\nn_superpixels = 9000\n'
    "dsnu_dn = [0.1, 0.2, 0.0, 0.1]\n"
)


def _small_text(**polarizer_keys):
    """SMALL as a camera file, with extra ``[polarizer]`` keys."""
    text = camera_model_toml(SMALL)
    extra = "".join(f'{k} = "{v}"\n' for k, v in polarizer_keys.items())
    return text.replace("[noise]", extra + "\n[noise]")


def _maps(cam, rng):
    shape = (*cam.superpixel_shape, 4)
    gain = 1 + 0.01 * rng.standard_normal(shape)
    gain[0, 0] = np.nan  # NaN: the channel's value
    angle = np.radians(cam.nominal_angle_deg) + np.radians(0.5) * rng.standard_normal(shape)
    return gain, angle, rng.uniform(0.95, 1.0, shape)


def test_calibration_record_and_maps_load(tmp_path):
    rng = np.random.default_rng(0)
    gain, angle, eff = _maps(SMALL, rng)
    (tmp_path / "maps").mkdir()
    for name, values in (("g", gain), ("a", angle), ("e", eff)):
        save_pixel_map(tmp_path / "maps" / name, values)
    text = _small_text(gain_map_npy="maps/g.npy", transmission_angle_map_rad_npy="maps/a.npy",
                       efficiency_map_npy=str(tmp_path / "maps" / "e.npy"))  # fmt: skip
    cam = polins.load_camera(_write(tmp_path, text + ENTRY + ENTRY.replace('"flat"', '"dark"')))
    assert cam.has_pixel_maps and cam.gain_map.shape == (128, 153, 4)
    np.testing.assert_allclose(cam.gain_map, gain, rtol=1e-6)  # float32 on disk
    np.testing.assert_allclose(cam.transmission_angle_map, angle, rtol=1e-6)
    assert np.isnan(cam.gain_map[0, 0]).all()
    g, _, _ = cam.pixel_calibration()
    np.testing.assert_array_equal(g[0, 0], cam.gain)  # NaN -> channel value
    assert [e["kind"] for e in cam.calibration] == ["flat", "dark"]
    first = dict(cam.calibration[0])
    assert first == {"kind": "flat", "date": "2026-05-04T10:30:00+00:00",
                     "method": "channel means", "n_images": 20, "residual_rms": 1.5e-4,
                     "n_superpixels": 9000, "dsnu_dn": [0.1, 0.2, 0.0, 0.1]}  # fmt: skip
    assert not polins.load_camera("paper-table1").has_pixel_maps
    assert polins.load_camera("paper-table1").calibration == ()


@pytest.mark.parametrize(
    ("change", "match"),
    [
        (
            lambda t: t.replace("n_images = 20", "n_image = 20"),
            r"missing key 'calibration\[0\].n_images'",
        ),
        (lambda t: t.replace('"flat"', '"flats"'), r"calibration\[0\].kind.*expected one of"),
        (lambda t: t.replace("+00:00", "+02:00"), r"calibration\[0\].date.*UTC"),
        (lambda t: t.replace('"2026-05-04T10:30:00+00:00"', '"yesterday"'), "ISO-8601"),
        (
            lambda t: t.replace("residual_rms = 1.5e-4", 'residual_rms = "small"'),
            "fit figures must be numbers",
        ),
        (
            lambda t: t.replace("dsnu_dn = [0.1, 0.2, 0.0, 0.1]", 'dsnu_dn = [0.1, "a"]'),
            "fit figures must be numbers or lists of numbers",
        ),
        (
            lambda t: t.replace("[[calibration]]", "[calibration]"),
            r"array of tables \[\[calibration\]\]",
        ),
    ],
)
def test_bad_calibration_entries_are_named(tmp_path, change, match):
    path = _write(tmp_path, change(_small_text() + ENTRY))
    with pytest.raises(ModelFileError, match=match):
        polins.load_camera(path)


def test_a_misspelt_map_key_gets_a_hint_and_bad_maps_are_named(tmp_path):
    save_pixel_map(tmp_path / "g", np.ones((128, 153, 4)))
    save_pixel_map(tmp_path / "small", np.ones((64, 76, 4)))
    with pytest.raises(ModelFileError, match=r"did you mean 'polarizer.gain_map_npy'"):
        polins.load_camera(_write(tmp_path, _small_text(gain_map_np="g.npy")))
    with pytest.raises(
        ModelFileError, match=r"did you mean 'polarizer.transmission_angle_map_rad_npy'"
    ):
        polins.load_camera(_write(tmp_path, _small_text(transmission_angle_map_deg_npy="g.npy")))
    with pytest.raises(ModelFileError, match=r"shape \(64, 76, 4\).*\(128, 153, 4\)"):
        polins.load_camera(_write(tmp_path, _small_text(gain_map_npy="small.npy")))
    with pytest.raises(ModelFileError, match="map file not found"):
        polins.load_camera(_write(tmp_path, _small_text(efficiency_map_npy="none.npy")))
    save_pixel_map(tmp_path / "deg", np.full((128, 153, 4), 45.0))
    with pytest.raises(ModelFileError, match="radians expected"):
        polins.load_camera(_write(tmp_path, _small_text(transmission_angle_map_rad_npy="deg.npy")))
    save_pixel_map(tmp_path / "zero", np.zeros((128, 153, 4)))
    with pytest.raises(ModelFileError, match=r"efficiencies must be in \(0, 1.1\]"):
        polins.load_camera(_write(tmp_path, _small_text(efficiency_map_npy="zero.npy")))
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(ModelFileError, match=r"not a plain \.npy"):
        polins.load_camera(_write(tmp_path, _small_text(gain_map_npy="obj.npy")))


def test_camera_file_round_trip_with_maps_and_record(tmp_path):
    """load_camera(write_camera_file(cam)) gives the same model: every field, the maps and
    the [[calibration]] record."""
    rng = np.random.default_rng(1)
    gain, angle, eff = _maps(SMALL, rng)
    record = calibration_entry({"kind": "polarizer", "date": "2026-05-04T10:30:00+00:00",
                                "method": "Malus fit", "n_images": 12, "chi2_dof": 1.02})  # fmt: skip
    cam = SMALL.with_changes(
        name="mine", gain=np.array([1.01, 0.99, 1.02, 0.98]), gain_map=gain,
        transmission_angle_map=angle, efficiency_map=eff, calibration=(record,),
        occlusion_polygons=(np.array([[0.0, 0.0], [10.0, 0.0], [5.0, 8.0]]),),
    )  # fmt: skip
    cam = polins.load_camera(
        write_camera_file(cam, tmp_path / "a.toml", maps_dir=tmp_path / "m")[-1]
    )
    again = polins.load_camera(
        write_camera_file(cam, tmp_path / "sub" / "b.toml", comments=["line one", "line two"])[-1]
    )
    assert again.path.read_text().startswith("# line one\n# line two\n")
    for name in cam.__dataclass_fields__:
        if name in ("path", "occlusion_polygons", "calibration"):
            continue
        a, b = getattr(cam, name), getattr(again, name)
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b, err_msg=name)
        else:
            assert a == b, name
    assert [dict(e) for e in again.calibration] == [dict(record)]
    clone = pickle.loads(pickle.dumps(again))  # worker processes get the camera by pickle
    assert clone.calibration == again.calibration
    np.testing.assert_array_equal(clone.gain_map, again.gain_map)
    np.testing.assert_array_equal(again.occlusion_polygons[0], cam.occlusion_polygons[0])
    assert sorted(p.name for p in (tmp_path / "sub").iterdir()) == [
        "b.efficiency_map.npy", "b.gain_map.npy", "b.toml", "b.transmission_angle_map.npy"
    ]  # fmt: skip
    # The text alone cannot name maps it does not have.
    with pytest.raises(ValueError, match="gain_map is set but has no file"):
        camera_model_toml(cam)
    assert camera_model_toml(SMALL).count("[[calibration]]") == 0


def test_calibration_kinds_match_the_estimators():
    from polins.calibration import KINDS
    from polins.models import CALIBRATION_KINDS

    assert set(KINDS) == set(CALIBRATION_KINDS)


def test_pixel_pitch_is_optional(tmp_path):
    """A camera file without pixel_pitch_um loads, and writes back without it."""
    from polins.io.model_files import camera_model_toml

    text = re.sub(r"pixel_pitch_um = .*\n", "", CAMERA)
    cam = polins.load_camera(_write(tmp_path, text))
    assert cam.pixel_pitch_um is None
    assert "pixel_pitch_um" not in camera_model_toml(cam)
    assert polins.load_camera("paper-table1").pixel_pitch_um > 0


def test_an_earth_rate_key_is_refused_with_the_option_to_use(tmp_path):
    text = (polins.models.shipped_folder("imus") / "mems-typical.toml").read_text()
    path = tmp_path / "with-earth-rate.toml"
    path.write_text(text.replace('grade = "mems"\n', 'grade = "mems"\nearth_rate = false\n'))
    with pytest.raises(ModelFileError, match="'earth_rate' is not an IMU property") as info:
        polins.load_imu(path)
    assert "filter option earth_rate" in str(info.value) and "\n" not in str(info.value)
