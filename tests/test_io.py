"""Log formats: every input format round-trips through its writer; bad input is named."""

from __future__ import annotations

import dataclasses
import sys

import numpy as np
import pandas as pd
import pytest

import polins
from polins.fusion.config import FuseConfig
from polins.io import (
    ImageReadError,
    ManifestError,
    atomic_path,
    load_raw,
    read_image,
    read_image_index,
    read_imu,
    read_log,
    time_from_name,
    write_image,
    write_imu,
    write_log,
)
from polins.io.log import parse_manifest
from polins.io.model_files import camera_model_toml
from polins.io.rosbag import ImageMessage, encoding_dtype, read_bag, write_bag

EPOCH = "2023-09-05T15:06:00+08:00"
SITE = {"lat_deg": 45.6234, "lon_deg": 126.7264, "alt_m": 148.74}


@pytest.fixture(scope="module")
def cam():
    return polins.load_camera("paper-table1").downscaled(8)  # (256, 306)


def _imu(n=60, seed=0):
    rng = np.random.default_rng(seed)
    data = {"t": 0.005 * np.arange(n) + 0.0001}
    for c, scale in zip(
        ("gx", "gy", "gz", "ax", "ay", "az"), (0.5, 0.5, 0.5, 3, 3, 9.8), strict=True
    ):
        data[c] = scale * rng.normal(size=n)
    return pd.DataFrame(data)


def _images(shape, n=3, seed=1, dtype=np.uint16):
    rng = np.random.default_rng(seed)
    hi = np.iinfo(dtype).max
    return [(0.2 * i + 0.013, rng.integers(0, hi, size=shape, dtype=dtype)) for i in range(n)]


# ----------------------------------------------------------------------------- IMU tables
@pytest.mark.parametrize("suffix", ["csv", "parquet"])
def test_imu_si_round_trip_is_exact(tmp_path, suffix):
    imu = _imu()
    back = read_imu(write_imu(tmp_path / f"imu.{suffix}", imu))
    assert list(back.columns) == ["t", "gx", "gy", "gz", "ax", "ay", "az"]
    np.testing.assert_array_equal(back.to_numpy(), imu.to_numpy())


@pytest.mark.parametrize("suffix", ["csv", "parquet"])
def test_imu_units_metadata_converted_to_si(tmp_path, suffix):
    imu = _imu()
    path = write_imu(tmp_path / f"imu.{suffix}", imu, gyro_unit="deg/s", accel_unit="g")
    raw = pd.read_parquet(path) if suffix == "parquet" else pd.read_csv(path, comment="#")
    # on disk: deg/s and g
    np.testing.assert_allclose(raw["gx"], np.degrees(imu["gx"]), rtol=1e-15)
    np.testing.assert_allclose(raw["az"], imu["az"] / 9.80665, rtol=1e-15)
    back = read_imu(path)  # declared units are honoured
    np.testing.assert_allclose(back.to_numpy(), imu.to_numpy(), rtol=1e-14, atol=1e-15)
    same = read_imu(path, gyro_unit="deg/s", accel_unit="g")  # agreeing flags are fine
    np.testing.assert_array_equal(same.to_numpy(), back.to_numpy())
    with pytest.raises(ValueError, match="declares gyro in 'deg/s' but 'rad/s'"):
        read_imu(path, gyro_unit="rad/s")


def test_imu_explicit_flags_for_undeclared_file(tmp_path):
    imu = _imu()
    plain = imu.copy()
    plain[["gx", "gy", "gz"]] = np.degrees(plain[["gx", "gy", "gz"]])
    plain[["ax", "ay", "az"]] /= 9.80665
    plain.to_csv(tmp_path / "imu.csv", index=False)  # no units line: SI unless told
    back = read_imu(tmp_path / "imu.csv", gyro_unit="deg/s", accel_unit="g")
    np.testing.assert_allclose(back.to_numpy(), imu.to_numpy(), rtol=1e-14, atol=1e-15)
    assert read_imu(tmp_path / "imu.csv")["gx"].iloc[0] == pytest.approx(plain["gx"].iloc[0])
    with pytest.raises(ValueError, match="unknown gyro unit 'rpm'"):
        read_imu(tmp_path / "imu.csv", gyro_unit="rpm")


def test_imu_bad_tables_name_the_problem(tmp_path):
    imu = _imu(5)
    imu.drop(columns="ay").to_csv(tmp_path / "a.csv", index=False)
    with pytest.raises(ValueError, match=r"lacks column\(s\) \['ay'\]"):
        read_imu(tmp_path / "a.csv")
    bad = imu.astype(object)
    bad.loc[3, "gz"] = "oops"
    bad.to_csv(tmp_path / "b.csv", index=False)
    with pytest.raises(ValueError, match="column 'gz' row 3: not a number"):
        read_imu(tmp_path / "b.csv")
    (tmp_path / "c.txt").write_text("t\n1\n")
    with pytest.raises(ValueError, match=r"expected \.csv or \.parquet"):
        read_imu(tmp_path / "c.txt")
    (tmp_path / "d.csv").write_text("# units: gyro=deg/s, speed=fast\nt\n")
    with pytest.raises(ValueError, match="bad units comment"):
        read_imu(tmp_path / "d.csv")


# ----------------------------------------------------------------------------- images
@pytest.mark.parametrize("suffix", ["png", "tiff", "tif"])
@pytest.mark.parametrize("dtype", [np.uint16, np.uint8])
def test_image_round_trip_is_lossless(tmp_path, cam, suffix, dtype):
    (_, raw), *_ = _images(cam.shape, n=1, dtype=dtype)
    path = write_image(tmp_path / f"x.{suffix}", raw)
    back = read_image(path, shape=cam.shape)
    assert back.dtype == dtype and np.array_equal(back, raw)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp files left


def test_unusable_images_raise_image_read_error(tmp_path, cam):
    (_, raw), *_ = _images(cam.shape, n=1)
    good = write_image(tmp_path / "good.png", raw)
    data = good.read_bytes()
    (tmp_path / "trunc.png").write_bytes(data[: len(data) // 3])
    (tmp_path / "junk.png").write_bytes(b"not an image at all")
    rgb = np.zeros((*cam.shape, 3), np.uint16)
    import cv2

    cv2.imwrite(str(tmp_path / "rgb.png"), rgb)
    for name, pattern in [
        ("trunc.png", "cannot decode"),
        ("junk.png", "cannot decode"),
        ("missing.png", "not found"),
        ("rgb.png", "single-channel"),
    ]:
        with pytest.raises(ImageReadError, match=pattern):
            read_image(tmp_path / name)
    with pytest.raises(ImageReadError, match=r"does not match the camera model \(128, 153\)"):
        read_image(good, shape=(128, 153))
    with pytest.raises(ValueError, match="2-D uint8 or uint16"):
        write_image(tmp_path / "f.png", raw.astype(float))


def test_time_named_image_folder(tmp_path, cam):
    assert time_from_name("000012.250000s.png") == 12.25
    assert time_from_name("cam_12250ms.tiff") == 12.25
    assert time_from_name("img-1693897560123456789ns.png") == pytest.approx(1693897560.1234567)
    assert time_from_name("000001.png") is None  # frame counters are not times
    imgs = _images(cam.shape, n=4)
    names = ["cam_0.013000s.png", "cam_213ms.tiff", "cam_413000us.png", "cam_613000000ns.tif"]
    for (_, raw), name in zip(imgs[::-1], names[::-1], strict=True):  # written out of order
        write_image(tmp_path / name, raw)
    (tmp_path / "notes_000001.png").write_bytes(b"")  # ignored: no unit
    index = read_image_index(tmp_path)
    np.testing.assert_allclose(index.t, [t for t, _ in imgs], rtol=0, atol=1e-15)
    for i, (_, raw) in enumerate(imgs):
        assert np.array_equal(index.read(i), raw)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ValueError, match="no image named with its time"):
        read_image_index(empty)


def test_image_index_csv(tmp_path, cam):
    imgs = _images(cam.shape, n=2)
    for i, (_, raw) in enumerate(imgs):
        write_image(tmp_path / "im" / f"{i}.png", raw)
    pd.DataFrame({"t": [imgs[0][0], imgs[1][0]], "file": ["im/0.png", "im/1.png"]}).to_csv(
        tmp_path / "idx.csv", index=False
    )
    index = read_image_index(tmp_path / "idx.csv")
    assert len(index) == 2 and [t for t, _ in index] == [imgs[0][0], imgs[1][0]]
    assert np.array_equal(load_raw(index.files[1], shape=cam.shape), imgs[1][1])
    pd.DataFrame({"t": [0.0, "x"], "file": ["a", "b"]}).to_csv(tmp_path / "bad.csv", index=False)
    with pytest.raises(ValueError, match="row 1: image time 'x' is not a number"):
        read_image_index(tmp_path / "bad.csv")
    pd.DataFrame({"time": [0.0]}).to_csv(tmp_path / "bad2.csv", index=False)
    with pytest.raises(ValueError, match=r"lacks column\(s\) \['t', 'file'\]"):
        read_image_index(tmp_path / "bad2.csv")


# ----------------------------------------------------------------------------- log folder
def _truth(n=5):
    return pd.DataFrame(
        {"t": np.arange(n) * 0.1, "roll": 0.01, "pitch": -0.02, "yaw": np.linspace(0, 1, n),
         "heading_deg": polins.heading_deg_from_yaw(np.linspace(0, 1, n)), "qw": 1.0,
         "qx": 0.0, "qy": 0.0, "qz": 0.0, "ve": 1.0, "vn": 0.0, "vu": 0.0,
         "lat_deg": SITE["lat_deg"], "lon_deg": SITE["lon_deg"], "alt_m": SITE["alt_m"]}
    )  # fmt: skip


def _assert_same_camera(a, b):
    for f in dataclasses.fields(a):
        if f.name == "path":
            continue
        x, y = getattr(a, f.name), getattr(b, f.name)
        if f.name == "occlusion_polygons":
            assert len(x) == len(y) and all(np.allclose(p, q) for p, q in zip(x, y, strict=True))
        elif isinstance(x, np.ndarray):
            np.testing.assert_allclose(x, y, rtol=1e-14, atol=1e-14, err_msg=f.name)
        else:
            assert x == y, f.name


@pytest.mark.parametrize(
    ("imu_format", "image_format", "gyro_unit", "accel_unit"),
    [("csv", "png", "rad/s", "m/s^2"), ("parquet", "tiff", "deg/s", "g")],
)
def test_log_round_trip(tmp_path, cam, imu_format, image_format, gyro_unit, accel_unit):
    imu, imgs, truth = _imu(), _images(cam.shape), _truth()
    model = polins.load_imu("mems-typical")
    manifest = write_log(
        tmp_path / "log", epoch_utc=EPOCH, camera=cam, imu_model=model, imu=imu,
        images=iter(imgs), truth=truth, imu_format=imu_format, image_format=image_format,
        gyro_unit=gyro_unit, accel_unit=accel_unit, description="round trip", **SITE,
    )  # fmt: skip
    assert manifest.name == "manifest.toml"
    log = read_log(manifest)
    assert log.epoch_utc == pd.Timestamp("2023-09-05T07:06:00Z")
    assert (log.lat_deg, log.lon_deg, log.alt_m) == tuple(SITE.values())
    assert log.description == "round trip"
    _assert_same_camera(cam, log.camera)
    assert dataclasses.replace(log.imu_model, path=model.path) == model
    np.testing.assert_allclose(log.imu.to_numpy(), imu.to_numpy(), rtol=1e-14, atol=1e-15)
    assert len(log.images) == 3
    for (t, item), (t0, raw) in zip(log.images, imgs, strict=True):
        assert t == t0 and np.array_equal(load_raw(item, shape=log.camera.shape), raw)
    pd.testing.assert_frame_equal(log.truth, truth, check_dtype=False)
    # the sun at the image times, through the epoch
    sun = polins.sun_position(log.times_utc(log.images.t), **SITE)
    np.testing.assert_allclose(
        log.sun_n(log.images.t), polins.sun_vector_n(sun.azimuth, sun.zenith)
    )
    assert log.times_utc(np.array([0.0]))[0] == log.epoch_utc
    # a folder is accepted for its manifest
    assert read_log(tmp_path / "log").manifest_path == manifest


def test_log_with_shipped_names_and_model_path(tmp_path, cam):
    cam_file = tmp_path / "mycam.toml"
    cam_file.write_text(camera_model_toml(cam))
    manifest = write_log(
        tmp_path / "log", epoch_utc=pd.Timestamp(EPOCH), camera=cam_file, imu_model="fins-paper",
        imu=_imu(), images=_images(cam.shape, n=1), **SITE,
    )  # fmt: skip
    m = parse_manifest(manifest)
    assert m["log"]["camera"] == "camera.toml" and m["log"]["imu"] == "fins-paper"
    assert "truth" not in m["files"]
    log = read_log(manifest)
    assert log.imu_model.name == "fins-paper" and log.camera.shape == cam.shape
    assert log.truth is None
    with pytest.raises(FileNotFoundError, match="unknown imu model 'no-such-imu'"):
        write_log(tmp_path / "x", epoch_utc=EPOCH, camera=cam, imu_model="no-such-imu",
                  imu=_imu(), images=[], **SITE)  # fmt: skip


def test_rewriting_a_log_removes_stale_images(tmp_path, cam):
    write_log(tmp_path, epoch_utc=EPOCH, camera=cam, imu_model="fins-paper", imu=_imu(),
              images=_images(cam.shape, n=3), **SITE)  # fmt: skip
    write_log(tmp_path, epoch_utc=EPOCH, camera=cam, imu_model="fins-paper", imu=_imu(),
              images=_images(cam.shape, n=1), **SITE)  # fmt: skip
    assert sorted(p.name for p in (tmp_path / "images").iterdir()) == ["000000.png"]
    assert len(read_log(tmp_path).images) == 1


def test_interrupted_write_leaves_no_complete_looking_output(tmp_path, cam):
    target = tmp_path / "table.csv"
    target.write_text("t\n1\n2\n")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("t\n1\n")  # partial content
        raise RuntimeError("killed")
    assert target.read_text() == "t\n1\n2\n"  # old file intact
    assert [p.name for p in tmp_path.iterdir()] == ["table.csv"]  # temp removed

    def images_then_crash():
        yield from _images(cam.shape, n=2)
        raise KeyboardInterrupt

    write_log(tmp_path / "log", epoch_utc=EPOCH, camera=cam, imu_model="fins-paper",
              imu=_imu(), images=_images(cam.shape, n=1), **SITE)  # fmt: skip
    with pytest.raises(KeyboardInterrupt):
        write_log(tmp_path / "log", epoch_utc=EPOCH, camera=cam, imu_model="fins-paper",
                  imu=_imu(), images=images_then_crash(), **SITE)  # fmt: skip
    assert not (tmp_path / "log" / "manifest.toml").exists()  # never mistaken for complete
    assert not [p for p in (tmp_path / "log").rglob(".*")]


def test_naive_epoch_is_an_error(tmp_path, cam):
    with pytest.raises(ValueError, match="naive datetime"):
        write_log(tmp_path, epoch_utc="2023-09-05T07:06:00", camera=cam, imu_model="fins-paper",
                  imu=_imu(), images=[], **SITE)  # fmt: skip


GOOD = """
[log]
epoch_utc = "2023-09-05T07:06:00Z"
camera = "paper-table1"
imu = "fins-paper"
lat_deg = 45.6
lon_deg = 126.7
[files]
imu = "imu.csv"
images = "images.csv"
"""


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ("lat_deg = 45.6", "latitude = 45.6", r"unknown key 'log.latitude'; did you mean 'log.lat_deg'"),
        ("lat_deg = 45.6", "", r"missing key 'log.lat_deg'"),
        ('"2023-09-05T07:06:00Z"', '"2023-09-05T07:06:00"', r"key 'log.epoch_utc' .*naive datetime"),
        ('images = "images.csv"', 'images = "images.csv"\n[units]\ngyro = "rpm"', r"key 'units.gyro' = 'rpm': expected one of 'rad/s', 'deg/s'"),
        ("lat_deg = 45.6", "lat_deg = 145.6", r"key 'log.lat_deg' = 145.6: expected a number in \[-90"),
        ("lon_deg = 126.7", 'lon_deg = "126.7"', r"key 'log.lon_deg' = '126.7': expected a number"),
        ('images = "images.csv"', 'images = "images.csv"\nbag = "x.bag"', r"'files.bag' excludes 'files.imu'"),
        ('images = "images.csv"', "", r"missing key 'files.images'"),
        ("[files]", "[file]", r"unknown key 'file'; did you mean 'files'"),
        ("lat_deg = 45.6", "lat_deg = 45.6 = 3", "not valid TOML"),
        ('epoch_utc = "2023-09-05T07:06:00Z"', "", r"missing key 'log.epoch_utc' .*only a ROS bag"),
    ],
)  # fmt: skip
def test_bad_manifest_names_the_key(tmp_path, old, new, message):
    assert old in GOOD
    path = tmp_path / "manifest.toml"
    path.write_text(GOOD.replace(old, new, 1))
    with pytest.raises(ManifestError, match=message):
        read_log(path)


def test_manifest_missing_files_and_models_are_named(tmp_path):
    path = tmp_path / "manifest.toml"
    path.write_text(GOOD)
    with pytest.raises(FileNotFoundError, match=r"key 'files.imu': .*imu.csv does not exist"):
        read_log(path)
    path.write_text(GOOD.replace('"paper-table1"', '"nocam"'))
    with pytest.raises(FileNotFoundError, match=r"key 'log\.camera': unknown camera model 'nocam'"):
        read_log(path)
    with pytest.raises(FileNotFoundError, match="manifest not found"):
        read_log(tmp_path / "nothing.toml")


# ----------------------------------------------------------------------------- ROS bags
@pytest.mark.parametrize("ros_version", [1, 2])
@pytest.mark.parametrize("encoding", ["mono16", "polarized_mono12", "16UC1"])
def test_rosbag_round_trip(tmp_path, cam, ros_version, encoding):
    imu, imgs = _imu(80), _images(cam.shape, n=2)
    bag = tmp_path / ("run.bag" if ros_version == 1 else "run")
    write_bag(bag, imu, imgs, epoch_utc=EPOCH, ros_version=ros_version, encoding=encoding)
    back, images = read_bag(bag, epoch_utc=EPOCH)
    np.testing.assert_allclose(back.to_numpy(), imu.to_numpy(), rtol=0, atol=1e-9)  # ns stamps
    np.testing.assert_allclose(images.t, [t for t, _ in imgs], rtol=0, atol=1e-9)
    for (_, msg), (_, raw) in zip(images, imgs, strict=True):
        assert msg.encoding == encoding
        assert np.array_equal(load_raw(msg, shape=cam.shape), raw)
    _, default_epoch = read_bag(bag)
    assert default_epoch.epoch_utc == pd.Timestamp("2023-09-05T07:06:00Z")  # first stamp, floored


def test_rosbag_through_the_manifest(tmp_path, cam):
    imu, imgs = _imu(40), _images(cam.shape, n=2, dtype=np.uint8)
    write_bag(tmp_path / "rec", imu, imgs, epoch_utc=EPOCH, imu_topic="/vn100/imu",
              image_topic="/pol/raw")  # fmt: skip
    (tmp_path / "camera.toml").write_text(camera_model_toml(cam))
    text = GOOD.replace('imu = "imu.csv"\nimages = "images.csv"', 'bag = "rec/rec.db3"')
    text = text.replace('"paper-table1"', '"camera.toml"')
    (tmp_path / "manifest.toml").write_text(text + '[ros]\nimage_topic = "/pol/raw"\n')
    log = read_log(tmp_path / "manifest.toml")
    # epoch from the manifest: 07:06:00Z; EPOCH is the same instant
    np.testing.assert_allclose(log.imu["t"], imu["t"], atol=1e-9)
    raws = [load_raw(item, shape=log.camera.shape) for _, item in log.images]
    assert all(np.array_equal(a, b) for a, (_, b) in zip(raws, imgs, strict=True))
    (tmp_path / "manifest.toml").write_text(text + '[ros]\nimage_topic = "/nope"\n')
    with pytest.raises(ValueError, match="no topic '/nope'"):
        read_log(tmp_path / "manifest.toml")


def test_rosbag_bad_messages(cam):
    good = np.arange(12, dtype=np.uint16).reshape(3, 4)
    data = good.astype("<u2").tobytes()
    msg = ImageMessage("mono16", 3, 4, 8, 0, data, "m")
    assert np.array_equal(msg.to_array(), good)
    big = ImageMessage("mono16", 3, 4, 8, 1, good.astype(">u2").tobytes(), "m")
    assert np.array_equal(big.to_array(), good)  # big-endian payloads are swapped
    padded = ImageMessage("mono16", 3, 4, 10, 0, np.pad(good, ((0, 0), (0, 1))).tobytes(), "m")
    assert np.array_equal(padded.to_array(), good)  # row padding (step > width) is dropped
    with pytest.raises(ImageReadError, match="truncated message"):
        ImageMessage("mono16", 3, 4, 8, 0, data[:-2], "m").to_array()
    with pytest.raises(ImageReadError, match="packed formats must be unpacked"):
        encoding_dtype("mono12p")
    with pytest.raises(ImageReadError, match="unsupported image encoding 'rgb8'"):
        encoding_dtype("rgb8")
    assert encoding_dtype("Polarized_Mono8") == np.uint8
    assert encoding_dtype("polarization_mono16_90_45_135_0") == np.uint16


def test_missing_rosbags_names_the_extra(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "rosbags", None)
    with pytest.raises(ImportError, match=r"optional extra 'ros': pip install 'polins\[ros\]'"):
        read_bag(tmp_path / "x.bag")


def test_parquet_without_pyarrow_names_the_extra(tmp_path, monkeypatch):
    import sys

    from polins.io.tables import read_table

    path = tmp_path / "imu.parquet"
    path.write_bytes(b"PAR1")
    monkeypatch.setitem(sys.modules, "pyarrow", None)
    monkeypatch.setitem(sys.modules, "pyarrow.parquet", None)
    with pytest.raises(ImportError, match=r"polins\[parquet\]"):
        read_table(path)


def test_manifest_filter_table_and_site(tmp_path, cam):
    from polins.errors import UserInputError
    from polins.site import Site

    manifest = write_log(tmp_path / "log", epoch_utc=EPOCH, camera=cam, imu_model="fins-paper",
                         imu=_imu(), images=_images(cam.shape, n=1), **SITE)  # fmt: skip
    text = manifest.read_text()
    log = read_log(manifest)
    c = FuseConfig.from_log(log)  # the configuration of a manifest is fusion's, not io's
    assert log.site == Site(**SITE) and c.site == log.site
    assert c.imu.name == "fins-paper" and c.aiding.nhc_std == "auto"  # defaults
    manifest.write_text(text + "\n[filter]\nnhc_std = 0.05\ngate_prob = 0.99\nsmooth = true\n")
    c = FuseConfig.from_log(read_log(manifest))
    assert (c.aiding.nhc_std, c.gating.gate_prob, c.output.smooth) == (0.05, 0.99, True)
    assert c.site == Site(**SITE) and c.imu.name == "fins-paper"
    for table, message in [
        ("nhc_sdt = 0.05", r"unknown key 'filter.nhc_sdt'; did you mean 'filter.nhc_std'"),
        ("lat_deg = 10.0", r"unknown key 'filter.lat_deg'"),  # the site is [log]'s
        ("gate_prob = 2.0", r"table \[filter\]: gate_prob=2.0: expected a probability in \(0, 1\)"),
        ('att_std0 = "big"', r"table \[filter\]: att_std0='big': expected 1 or 3 sigmas"),
    ]:
        manifest.write_text(text + f"\n[filter]\n{table}\n")
        log = read_log(manifest)  # io reads the file; the [filter] values are the config's
        with pytest.raises(UserInputError, match=message) as info:
            FuseConfig.from_log(log)
        assert isinstance(info.value, UserInputError) and "\n" not in str(info.value)


def test_atomic_files_get_the_umask_without_touching_it(tmp_path, monkeypatch):
    import os
    import stat

    old = os.umask(0o027)
    try:
        calls = []
        monkeypatch.setattr(os, "umask", lambda mask: calls.append(mask) or 0)
        path = tmp_path / "out" / "a.txt"
        from polins.io import write_text_atomic

        write_text_atomic(path, "x")
        write_text_atomic(path, "y")  # replacing keeps the umask's mode
    finally:
        monkeypatch.undo()
        os.umask(old)
    assert calls == [] and path.read_text() == "y"
    assert stat.S_IMODE(path.stat().st_mode) == 0o640
    assert [p.name for p in path.parent.iterdir()] == ["a.txt"]


def test_input_errors_are_user_errors():
    from polins.errors import UserInputError

    assert issubclass(ManifestError, UserInputError) and issubclass(ImageReadError, UserInputError)


def test_bad_imu_unit_is_a_user_error(tmp_path):
    from polins.errors import UserInputError

    path = write_imu(tmp_path / "imu.csv", _imu())
    with pytest.raises(UserInputError, match="unknown gyro unit 'rpm'"):
        read_imu(path, gyro_unit="rpm")


def test_utf8_bom_is_accepted_in_the_imu_csv_and_the_manifest(tmp_path, cam):
    """Found: a BOM gave "lacks column(s)" (IMU CSV) and "Invalid statement" (manifest)."""
    imu = _imu()
    manifest = write_log(tmp_path / "log", epoch_utc=EPOCH, camera=cam, imu_model="mems-typical",
                         imu=imu, images=iter(_images(cam.shape, n=2)), **SITE)  # fmt: skip
    for path in (manifest, tmp_path / "log" / "imu.csv"):
        path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    log = read_log(manifest)
    np.testing.assert_allclose(log.imu.to_numpy(), imu.to_numpy(), rtol=1e-14, atol=1e-15)
    bare = tmp_path / "bare.csv"  # no units comment: the BOM sits before the header "t"
    bare.write_bytes(b"\xef\xbb\xbf" + imu.to_csv(index=False).encode())
    assert list(read_imu(bare).columns) == list(imu.columns)


def test_bit_depth_warning_names_the_shift():
    from polins.io.images import bit_depth_warning

    raw = np.random.default_rng(0).integers(0, 4096, size=(8, 8), dtype=np.uint16)
    assert bit_depth_warning(raw, 12, "a.png") is None
    note = bit_depth_warning(raw << 4, 12, "a.png")
    assert "values up to" in note and "shifted left by 4 bits (x16)" in note
    assert "shifted" not in bit_depth_warning(raw | 0x8001, 12, "a.png")  # odd values: no shift


def test_report_tables_are_short_logs_exact(tmp_path):
    from polins.io.tables import read_table, write_table

    df = pd.DataFrame({"t": [0.2, 1 / 3]})
    write_table(tmp_path / "log.csv", df)
    write_table(tmp_path / "report.csv", df, float_format="%.10g")
    assert read_table(tmp_path / "log.csv")["t"].tolist() == df["t"].tolist()  # round trip
    assert (tmp_path / "report.csv").read_text() == "t\n0.2\n0.3333333333\n"
