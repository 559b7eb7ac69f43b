"""Scenario runner: a tiny simulated log on disk, read back and checked against its truth."""

import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from polins.cli import main
from polins.io import read_log
from polins.io.images import read_image
from polins.sim import render_raw
from polins.sim.imu import ideal_imu
from polins.sim.scenario import image_indices, rot_nb_at, simulate_log

TINY = {"duration_s": 2.0, "image_rate_hz": 5.0, "downscale": 8, "progress": False}


@pytest.fixture(scope="module")
def turntable_log(tmp_path_factory):
    return simulate_log(tmp_path_factory.mktemp("tt"), scenario="turntable", seed=3, **TINY)


def test_files_exist_and_read_back(turntable_log):
    sim = turntable_log
    folder = sim.manifest.parent
    for name in ["manifest.toml", "imu.csv", "images.csv", "truth.csv", "camera.toml"]:
        assert (folder / name).is_file(), name
    assert len(list((folder / "images").glob("*.png"))) == 11
    log = read_log(sim.manifest)
    assert log.epoch_utc.isoformat() == "2023-09-05T07:06:00+00:00"
    assert (log.lat_deg, log.lon_deg, log.alt_m) == (45.6234, 126.7264, 148.74)
    assert log.camera.shape == (256, 306) == sim.camera.shape
    assert log.imu_model.name == "fins-paper"
    assert np.allclose(log.imu.to_numpy(), sim.imu.to_numpy(), rtol=1e-15, atol=0)
    assert log.truth is not None and len(log.truth) == len(log.imu) == 401


def test_timestamps_synchronized(turntable_log):
    log = read_log(turntable_log.manifest)
    t_imu = log.imu["t"].to_numpy()
    assert np.allclose(np.diff(t_imu), 0.005, atol=1e-12)
    assert log.truth is not None and np.array_equal(log.truth["t"].to_numpy(), t_imu)
    t_img = log.images.t
    assert np.allclose(t_img, np.arange(11) * 0.2, atol=1e-12)
    assert np.all(np.isin(t_img, t_imu))  # every image at an IMU sample time
    # the sun of the reader (site, epoch) is the sun the images were rendered with
    assert np.allclose(log.sun_n(t_img), turntable_log.sun_n, atol=1e-12)


def test_truth_consistent_with_imu_and_images(turntable_log):
    sim = turntable_log
    log = read_log(sim.manifest)
    truth = log.truth
    assert truth is not None
    # 7.2 deg/s about the vertical, level
    yaw = np.unwrap(truth["yaw"].to_numpy())
    assert np.degrees(yaw[-1] - yaw[0]) == pytest.approx(14.4, abs=1e-9)
    assert np.allclose(truth[["roll", "pitch", "ve", "vn", "vu"]], 0.0)
    # measured IMU = (1 + s) ideal + b + white noise, with the true errors in truth.csv
    ideal = ideal_imu(sim.trajectory)
    cols = ["gx", "gy", "gz", "ax", "ay", "az"]
    errs = ["bgx", "bgy", "bgz", "bax", "bay", "baz"]
    scale = truth[["sgx", "sgy", "sgz", "sax", "say", "saz"]].to_numpy()
    white = log.imu[cols].to_numpy() - (1 + scale) * ideal[cols].to_numpy() - truth[errs].to_numpy()
    density = np.repeat([sim.imu_model.gyro_arw, sim.imu_model.accel_vrw], 3)
    assert white.std(axis=0) / (density * np.sqrt(200.0)) == pytest.approx(np.ones(6), abs=0.15)
    # each image is the sky seen at the truth attitude of its time stamp: a noise-free
    # re-rendering differs by read noise (1.5 DN) only; the neighbouring pose does not fit
    images = log.images
    for i in [0, 7]:
        raw = read_image(images.files[i]).astype(float)
        assert raw.shape == log.camera.shape
        q = truth.loc[truth["t"] == images.t[i], ["qx", "qy", "qz", "qw"]].to_numpy()[0]
        rot = Rotation.from_quat(q)
        sun_n = log.sun_n(images.t[i : i + 1])[0]
        clean = render_raw(log.camera, sun_n, rot).astype(float)
        ok = (clean > 10) & (clean < log.camera.saturation_dn) & (raw < log.camera.saturation_dn)
        assert np.std(raw[ok] - clean[ok]) == pytest.approx(1.5, rel=0.2)
        wrong = render_raw(log.camera, sun_n, rot * Rotation.from_euler("z", 1.44, degrees=True))
        assert np.std(raw[ok] - wrong.astype(float)[ok]) > 3.0
        assert rot_nb_at(sim.trajectory, images.t[i]).approx_equal(rot)[0]


def test_ugv_scenario_deterministic_and_streams_independent(tmp_path):
    kw = {**TINY, "duration_s": 12.0, "downscale": 8}
    a = simulate_log(tmp_path / "a", scenario="ugv", imu="mems-typical", seed=1, **kw)
    simulate_log(tmp_path / "b", scenario="ugv", imu="mems-typical", seed=1, **kw)
    c = simulate_log(
        tmp_path / "c", scenario="ugv", imu="mems-typical", seed=1, **{**kw, "image_rate_hz": 2}
    )
    assert (tmp_path / "a" / "imu.csv").read_bytes() == (tmp_path / "b" / "imu.csv").read_bytes()
    assert (tmp_path / "a" / "images" / "000004.png").read_bytes() == (
        tmp_path / "b" / "images" / "000004.png"
    ).read_bytes()
    # another image rate: the same drive and IMU noise, fewer images
    assert np.array_equal(a.imu.to_numpy(), c.imu.to_numpy())
    assert len(c.image_t) == 25 and len(a.image_t) == 61
    log = read_log(a.manifest)
    assert log.imu_model.name == "mems-typical"
    truth = log.truth
    assert truth is not None
    speed = np.linalg.norm(truth[["ve", "vn", "vu"]].to_numpy(), axis=1)
    assert np.all(speed[truth["t"] <= 5.0] == 0.0) and speed.max() > 0.5  # rest, then drive
    moved = np.hypot(
        np.radians(truth["lat_deg"].iloc[-1] - 45.6234) * 6.37e6,
        np.radians(truth["lon_deg"].iloc[-1] - 126.7264) * 6.37e6 * np.cos(np.radians(45.6)),
    )
    assert 1.0 < moved < 12.0 * 10.0


def test_realistic_sky_log_keeps_the_camera_file_honest(tmp_path):
    # sky="realistic": one random realistic sky for the log (the independent renderer), and
    # the camera file keeps its instrumental_dop_std (its gain residual is not the file's)
    kw = {**TINY, "duration_s": 1.0}
    model = simulate_log(tmp_path / "m", scenario="turntable", seed=2, **kw)
    real = simulate_log(tmp_path / "r", scenario="turntable", seed=2, sky="realistic", **kw)
    assert model.real_sky is None and real.real_sky is not None
    assert model.camera.instrumental_dop_std == 0.0
    assert real.camera.instrumental_dop_std is None  # the measurement's default then
    assert np.array_equal(model.imu.to_numpy(), real.imu.to_numpy())  # the same drive, IMU
    img_m = read_image(tmp_path / "m" / "images" / "000001.png").astype(float)
    img_r = read_image(tmp_path / "r" / "images" / "000001.png").astype(float)
    assert np.mean(np.abs(img_r - img_m)) > 5.0  # another sky
    assert np.max(np.abs(real.real_sky.gain_residual)) <= 0.005
    with pytest.raises(ValueError, match="sky='cloudy'"):
        simulate_log(tmp_path / "x", sky="cloudy", **kw)
    with pytest.raises(ValueError, match="render_options apply to sky='model'"):
        simulate_log(tmp_path / "y", sky="realistic", render_options={"epsilon": 0.01}, **kw)


def test_image_indices_snap_to_samples():
    t = np.arange(2001) / 200.0
    idx = image_indices(t, 22.0)
    assert np.max(np.abs(t[idx] - np.arange(len(idx)) / 22.0)) <= 0.0025 + 1e-12
    assert len(idx) == 221 and np.all(np.diff(idx) > 0)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"scenario": "boat"}, "unknown scenario"),
        ({"image_rate_hz": 500.0}, "above the IMU rate"),
        ({"downscale": 7}, "factor 7"),
        ({"imu": "no-such-imu"}, "unknown imu model"),
        ({"epoch_utc": "2023-09-05T15:06"}, "naive"),
    ],
)
def test_bad_input(tmp_path, kwargs, match):
    with pytest.raises((ValueError, FileNotFoundError), match=match):
        simulate_log(tmp_path, **{**TINY, **kwargs})


def test_cli_simulate_writes_a_log(tmp_path, capsys):
    out = tmp_path / "log"
    args = ["simulate", "--scenario", "ugv", "--out", str(out), "--duration", "3"]
    assert main([*args, "--downscale", "8", "--imu", "mems-typical", "--seed", "2", "--quiet"]) == 0
    text = capsys.readouterr().out
    assert f"wrote {out / 'manifest.toml'}" in text and "16 at 5 Hz" in text
    log = read_log(out / "manifest.toml")
    assert len(log.imu) == 601 and len(log.images) == 16 and log.imu_model.name == "mems-typical"


@pytest.mark.parametrize(
    ("extra", "match"),
    [
        (["--downscale", "3"], r"downscale[= ]3"),
        (["--imu", "no-such-imu"], "unknown imu model"),
        (["--image-rate", "0"], r"image[-_]rate"),
        (["--epoch", "2023-09-05T12:00"], "naive datetime"),
    ],
)
def test_cli_simulate_errors_are_one_line(tmp_path, capsys, extra, match):
    args = ["simulate", "--scenario", "turntable", "--out", str(tmp_path), "--duration", "1"]
    assert main([*args, "--quiet", *extra]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and re.search(match, err) and "Traceback" not in err


def test_output_that_is_a_file_is_refused(tmp_path):
    target = tmp_path / "taken"
    target.write_text("not a folder")
    with pytest.raises(ValueError, match="not a folder"):
        simulate_log(target, **TINY)


def test_static_scenario_is_a_record_for_imu_model(tmp_path, capsys):
    """``polins simulate --scenario static`` then ``polins imu-model`` on its IMU file."""
    import polins

    out = tmp_path / "static"
    args = ["simulate", "--scenario", "static", "--out", str(out), "--duration", "120"]
    assert main([*args, "--imu", "mems-typical", "--seed", "4", "--quiet"]) == 0
    assert "3 at 0.0167 Hz" in capsys.readouterr().out  # one image a minute: t = 0, 60, 120 s
    log = read_log(out / "manifest.toml")
    truth = log.truth
    assert np.ptp(truth["yaw"]) == 0.0 and np.ptp(truth["roll"]) == 0.0  # at rest, level
    assert np.abs(truth[["vn", "ve", "vu"]].to_numpy()).max() == 0.0
    model_path = tmp_path / "sim-imu.toml"
    assert main(["imu-model", str(out / "imu.csv"), "--out", str(model_path)]) == 0
    fitted, true = polins.load_imu(model_path), polins.load_imu("mems-typical")
    assert fitted.gyro_arw / true.gyro_arw == pytest.approx(1.0, abs=0.05)
    assert fitted.accel_vrw / true.accel_vrw == pytest.approx(1.0, abs=0.05)
    # 120 s cannot show a random walk: the file holds an upper bound above the truth
    assert fitted.gyro_bias_rw > true.gyro_bias_rw
    assert "random walk not identified" in capsys.readouterr().out
