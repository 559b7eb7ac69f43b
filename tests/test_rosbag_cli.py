"""ROS 2 bags as a log: ``polins manifest BAG`` writes the manifest, ``polins fuse`` fuses the bag to the CSV log's solution (docs/rosbag.md)."""

import tomllib

import numpy as np
import pandas as pd
import pytest

from polins.cli import main
from polins.io import load_raw, read_log
from polins.io.rosbag import write_bag
from polins.sim.scenario import simulate_log

pytest.importorskip("rosbags")


@pytest.fixture(scope="module")
def csv_log(tmp_path_factory):
    """A 4 s turntable log (FOG IMU, images at 2 Hz, 1/8 resolution) as CSV files."""
    folder = tmp_path_factory.mktemp("rosbag") / "log"
    simulate_log(folder, scenario="turntable", duration_s=4.0, image_rate_hz=2.0,
                 progress=False)  # fmt: skip
    return read_log(folder)


def _bag(log, path, epoch_utc):
    images = ((t, load_raw(item)) for t, item in log.images)
    return write_bag(path, log.imu, images, epoch_utc=epoch_utc, ros_version=2,
                     imu_topic="/vn100/imu", image_topic="/pol/raw",
                     encoding="polarized_mono16")  # fmt: skip


def _manifest_argv(log, bag, out, *extra):
    folder = log.manifest_path.parent
    return ["manifest", str(bag), "--camera", str(folder / "camera.toml"), "--imu",
            log.imu_model.name, "--lat", repr(log.site.lat_deg), "--lon", repr(log.site.lon_deg),
            "--alt", repr(log.site.alt_m), "--out", str(out), *extra]  # fmt: skip


def test_a_bag_fuses_to_the_csv_logs_solution(csv_log, tmp_path, capsys):
    bag = _bag(csv_log, tmp_path / "rec", csv_log.epoch_utc)
    manifest = tmp_path / "bagrun" / "manifest.toml"
    assert main(_manifest_argv(csv_log, bag, manifest)) == 0
    printed = capsys.readouterr().out
    assert "/vn100/imu" in printed and "/pol/raw: 9" in printed and "first stamp" in printed
    tables = tomllib.loads(manifest.read_text())
    assert "epoch_utc" not in tables["log"]  # absolute stamps: none needed
    assert tables["files"]["bag"] == "../rec" and tables["ros"]["image_topic"] == "/pol/raw"
    assert read_log(manifest).epoch_utc == csv_log.epoch_utc

    runs = {}
    for name, source in (("csv", csv_log.manifest_path), ("bag", manifest)):
        out = tmp_path / name
        argv = ["fuse", str(source), "--out", str(out), "--workers", "1", "--quiet", "--no-plots"]
        assert main(argv) == 0
        runs[name] = pd.read_csv(out / "solution.csv")
    assert len(runs["bag"]) == len(runs["csv"]) > 40  # 4 s at the default 10 rows per second
    for col in ("t", "roll", "pitch", "yaw", "yaw_std"):
        np.testing.assert_allclose(runs["bag"][col], runs["csv"][col], rtol=0, atol=1e-9)


def test_relative_stamps_need_the_epoch_in_one_line(csv_log, tmp_path, capsys):
    """Stamps in simulation time (from 0) are refused without the UTC time of stamp 0, and
    with it give the CSV log's times."""
    bag = _bag(csv_log, tmp_path / "sim", "1970-01-01T00:00:00Z")
    manifest = tmp_path / "manifest.toml"
    assert main(_manifest_argv(csv_log, bag, manifest)) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not an absolute UTC time" in err and "--epoch" in err
    epoch = csv_log.epoch_utc.isoformat()
    assert main(_manifest_argv(csv_log, bag, manifest, "--epoch", epoch)) == 0
    log = read_log(manifest)
    assert log.epoch_utc == csv_log.epoch_utc
    np.testing.assert_allclose(log.imu["t"], csv_log.imu["t"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(log.images.t, csv_log.images.t, rtol=0, atol=1e-9)


def test_a_missing_topic_is_one_line(csv_log, tmp_path, capsys):
    bag = _bag(csv_log, tmp_path / "rec", csv_log.epoch_utc)
    argv = _manifest_argv(csv_log, bag, tmp_path / "m.toml", "--image-topic", "/nope")
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no topic '/nope'" in err and "/pol/raw" in err
