"""docs/streaming.md, statement by statement: lifecycle, units, exceptions, events, threading, memory."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

import polins
from polins.compass.measure import NoiseModelWarning
from polins.errors import UserInputError
from polins.loop import LoopOptions, NavigationStream
from polins.sim import render_raw
from polins.sim.reproduction import PAPER_EPOCH
from polins.site import PAPER_SITE

RATE_HZ = 200.0
CAMERA = polins.load_camera("paper-table1").downscaled(8)
MODEL = polins.load_imu("mems-typical")


def static_imu(seconds: float, seed: int = 0) -> np.ndarray:
    """A level IMU at rest facing East (yaw 0): rows ``t, gx, gy, gz, ax, ay, az``."""
    n = int(seconds * RATE_HZ) + 1
    rng = np.random.default_rng(seed)
    data = np.zeros((n, 7))
    data[:, 0] = np.arange(n) / RATE_HZ
    data[:, 6] = 9.80665
    data[:, 1:] += rng.normal(0.0, 1e-4, (n, 6))
    return data


def stream(**kwargs) -> NavigationStream:
    return NavigationStream(CAMERA, MODEL, site=PAPER_SITE, epoch_utc=PAPER_EPOCH, **kwargs)


def feed(nav: NavigationStream, imu: np.ndarray, t_end: float) -> None:
    for row in imu[(imu[:, 0] <= t_end + 1e-9) & (imu[:, 0] > nav.t_latest)]:
        nav.add_imu(row[0], row[1:4], row[4:7])


def sky_image(t: float, seed: int = 0) -> np.ndarray:
    stamp = pd.DatetimeIndex([pd.Timestamp(PAPER_EPOCH) + pd.to_timedelta(t, unit="s")])
    sun = polins.sun_position(stamp, PAPER_SITE.lat_deg, PAPER_SITE.lon_deg, PAPER_SITE.alt_m)
    sun_n = polins.sun_vector_n(sun.azimuth, sun.zenith)[0]
    return render_raw(CAMERA, sun_n, Rotation.identity(), rng=np.random.default_rng(seed))


def test_lifecycle_levelling_no_heading_then_steady_state():
    imu = static_imu(4.0)
    nav = stream()
    st = nav.state()  # before the first IMU sample
    assert st.aligning and st.nav is None and not st.heading_known
    assert not nav.add_image(-0.5, np.zeros(CAMERA.shape))
    feed(nav, imu, 0.5)  # levelling: no exception, no state
    st = nav.state()
    assert st.aligning and st.nav is None
    assert not nav.add_image(0.6, np.zeros(CAMERA.shape))
    assert set(nav.drain_events()["kind"]) == {"image-outside-imu", "image-during-alignment"}
    feed(nav, imu, 1.5)  # levelled: roll and pitch, no heading
    st = nav.state()
    assert not st.aligning and not st.heading_known and not st.nav.yaw_aligned
    row = st.nav.row()
    assert abs(row["roll"]) < math.radians(0.1) and abs(row["pitch"]) < math.radians(0.1)
    assert math.isnan(row["heading_deg"])
    for k in range(3):  # the first fix: acquire_k (3) headings that agree
        assert nav.add_measurement(1.6 + 0.1 * k, yaw=0.0, yaw_std=math.radians(0.5))
        feed(nav, imu, 1.65 + 0.1 * k)
        assert nav.state().heading_known == (k == 2)
    feed(nav, imu, 2.5)
    st = nav.state()
    assert st.heading_known and st.nav.yaw_aligned
    assert abs(st.nav.row()["heading_deg"] - 90.0) < 1.0  # yaw 0 = East = heading 90 deg
    nav.close()


def test_known_initial_attitude_has_a_heading_at_once():
    nav = stream(rot_nb0=Rotation.identity())
    imu = static_imu(0.1)
    nav.add_imu(imu[0, 0], imu[0, 1:4], imu[0, 4:7])
    st = nav.state()
    assert not st.aligning and st.heading_known
    nav.close()


def test_units_lat_lon_radians_row_degrees():
    nav = stream()
    feed(nav, static_imu(1.5), 1.5)
    st = nav.state()
    assert st.nav.lat == pytest.approx(math.radians(PAPER_SITE.lat_deg), abs=1e-7)
    assert st.nav.lon == pytest.approx(math.radians(PAPER_SITE.lon_deg), abs=1e-7)
    row = st.nav.row()
    assert row["lat_deg"] == pytest.approx(PAPER_SITE.lat_deg, abs=1e-5)
    assert row["lon_deg"] == pytest.approx(PAPER_SITE.lon_deg, abs=1e-5)
    nav.close()


@pytest.mark.parametrize(
    "kwargs",
    [
        {"epoch_utc": "2023-09-05T07:06:00"},  # naive
        {"lat_deg": 45.0, "lon_deg": 126.0},  # both site and lat_deg/lon_deg
        {"executor": "gpu"},
        {"workers": 0},
    ],
)
def test_call_mistakes_raise_user_input_error(kwargs):
    args = {"site": PAPER_SITE, "epoch_utc": PAPER_EPOCH, **kwargs}
    with pytest.raises(UserInputError) as info:
        NavigationStream(CAMERA, MODEL, **args)
    assert isinstance(info.value, ValueError)


def test_add_imu_many_length_mismatch_and_no_site_warning():
    nav = stream()
    with pytest.raises(UserInputError, match="add_imu_many"):
        nav.add_imu_many(np.arange(3) / RATE_HZ, np.zeros((2, 3)), np.zeros((3, 3)))
    nav.close()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        NavigationStream(CAMERA, MODEL, epoch_utc=PAPER_EPOCH).close()
    assert [w.category for w in caught] == [UserWarning]


def test_data_faults_return_false_and_report_events_never_raise():
    imu = static_imu(3.0)
    nav = stream()
    feed(nav, imu, 1.5)
    t = nav.t_latest
    assert not nav.add_imu(t + 0.005, [np.nan, 0, 0], [0, 0, 9.8])  # imu-nonfinite
    assert not nav.add_imu(t, imu[0, 1:4], imu[0, 4:7])  # imu-out-of-order
    assert nav.add_imu(t + 0.5, imu[0, 1:4], imu[0, 4:7])  # imu-gap, propagated across
    assert not nav.add_measurement(t + 0.4, yaw=0.0, yaw_std=0.01)  # measurement-in-gap
    assert nav.add_measurement(t + 0.55, yaw=0.0, yaw_std=0.01)
    assert not nav.add_measurement(t + 0.52, yaw=0.0, yaw_std=0.01)  # image-out-of-order
    kinds = list(nav.drain_events()["kind"])
    assert kinds == ["imu-nonfinite", "imu-out-of-order", "imu-gap", "measurement-in-gap",
                     "image-out-of-order"]  # fmt: skip
    assert nav.drain_events().empty  # drained
    assert nav.counts["imu-gap"] == 1  # the totals stay
    for k in range(1, 200):  # the IMU runs on, > max_image_delay_s
        nav.add_imu(t + 0.5 + k / RATE_HZ, imu[0, 1:4], imu[0, 4:7])
    assert not nav.add_image(t + 0.6, np.zeros(CAMERA.shape))  # image-late
    assert nav.add_image(t + 1.2, "does-not-exist.png")  # unreadable: found when measured
    nav.close()
    assert list(nav.drain_events()["kind"]) == ["image-late", "image-unreadable"]


def test_result_does_not_depend_on_the_executor():
    imu = static_imu(3.0)
    headings = []
    for executor in ("inline", "thread", "process"):
        nav = stream(executor=executor)
        feed(nav, imu, 1.1)
        for t_img in (1.2, 1.4, 1.6, 1.8):
            feed(nav, imu, t_img + 0.05)
            nav.add_image(t_img, sky_image(t_img))
        feed(nav, imu, 3.0)
        nav.close()
        st = nav.state()
        assert st.heading_known
        headings.append(st.nav.row()["heading_deg"])
    # the thread executor replays from a snapshot: the same updates, other rounding and
    # covariance steps (the yaw_std differs by 5e-4 relative); the acquired yaw's
    # correlation with the tilt (docs/filter.md §7.1) carries that into the heading:
    # measured 1.7e-8 deg apart (2e-9 without the correlation)
    assert headings[0] == pytest.approx(headings[1], abs=1e-7)
    assert headings[2] == headings[1]  # the same schedule as the thread's, other workers


def test_buffers_are_bounded_and_count_what_they_drop():
    nav = stream(options=LoopOptions(max_table_rows=5))
    imu = static_imu(1.5)
    feed(nav, imu, 1.5)
    t = nav.t_latest
    for _ in range(8):
        nav.add_imu(t, imu[0, 1:4], imu[0, 4:7])  # 8 out-of-order events
    assert nav.events_dropped == 3 and len(nav.drain_events()) == 5
    nav.close()


def test_a_run_inside_one_snapshot_cell_is_filtered():
    """A run of several samples that starts no snapshot cell (an image handed over 10 ms
    after the previous run) is filtered, not a crash (polins.loop.runner)."""
    from polins.fusion.config import FuseConfig, config_with_site
    from polins.loop.runner import FilterRunner

    imu = static_imu(2.0)
    # a solution row a second: the short run below has neither a snapshot nor a row
    config = config_with_site(FuseConfig(imu_model=MODEL, site=PAPER_SITE, output_rate_hz=1.0))
    runner = FilterRunner(config, 0.0, 1.0 / RATE_HZ, Rotation.identity(),
                          snapshot_every_s=0.1, max_rows=100)  # fmt: skip
    runner.run(imu[:101, 0], imu[:101, 1:4], imu[:101, 4:7])  # up to t = 0.5 s
    runner.run(imu[101:104, 0], imu[101:104, 1:4], imu[101:104, 4:7])  # 0.505 .. 0.515 s:
    # inside the 0.5 s cell
    assert runner.filter.t == pytest.approx(0.515)
    runner.finish()  # the last state is the solution's last row, as polins.fuse
    assert list(runner.drain_solution()["t"]) == pytest.approx([0.0, 0.515])


def test_add_imu_checks_units_like_the_cli_and_drops_out_of_range_samples():
    """Specific force in g is a user mistake once the levelling window is full (one line,
    before any heading); a sample beyond the full scale is dropped with an event."""
    from polins.errors import UserInputError

    imu = static_imu(3.0)
    nav = stream()
    gyro_max, _ = MODEL.full_scale()
    assert nav.add_imu(imu[0, 0], imu[0, 1:4], imu[0, 4:7])
    assert not nav.add_imu(imu[1, 0], [2.0 * gyro_max, 0.0, 0.0], imu[1, 4:7])
    assert nav.counts["imu-out-of-range"] == 1
    feed(nav, imu, 2.5)  # the window closes: SI data pass the check
    assert nav.t_latest == pytest.approx(2.5)
    in_g = stream()
    with pytest.raises(UserInputError, match="looks like g"):
        for row in imu:
            in_g.add_imu(row[0], row[1:4], row[4:7] / 9.80665)


def test_a_wrong_noise_model_is_reported_once():
    # images of 1.5 DN read noise measured with a camera file that says 0.3 DN: every image's
    # noise_ratio shows it, one noise-model event and one warning say so
    quiet = CAMERA.with_changes(read_noise_dn=0.3)
    nav = NavigationStream(quiet, MODEL, site=PAPER_SITE, epoch_utc=PAPER_EPOCH)
    imu = static_imu(2.5)
    feed(nav, imu, 1.1)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for t_img in (1.2, 1.4, 1.6, 1.8):
            feed(nav, imu, t_img + 0.05)
            nav.add_image(t_img, sky_image(t_img))
        feed(nav, imu, 2.5)
        nav.close()
    noise = [w for w in caught if issubclass(w.category, NoiseModelWarning)]
    assert len(noise) == 1 and "reported once" in str(noise[0].message)
    events = nav.drain_events()
    assert list(events["kind"]).count("noise-model") == 1
    rows = nav.drain_measurements()
    assert len(rows) == 4 and np.all(rows["noise_ratio"] > 3.0)


def test_from_manifest_configures_the_stream_as_the_log(tmp_path):
    """The manifest's camera, IMU model, site, epoch, [vehicle] and [filter]; its data files
    are not read (they need not exist); an odometer without odometer_std gets 0.05 m/s."""
    (tmp_path / "manifest.toml").write_text(
        '[log]\nepoch_utc = "2023-09-05T07:06:00+00:00"\ncamera = "paper-table1"\n'
        'imu = "mems-typical"\nlat_deg = 45.6\nlon_deg = 126.7\nalt_m = 150.0\n\n'
        '[files]\nimu = "imu.csv"\nimages = "images.csv"\n\n'
        '[vehicle]\nkind = "ground"\nmount_rpy_deg = [0.0, 1.0, 2.0]\nodometer = "odo.csv"\n\n'
        "[filter]\nnhc_std = 0.1\n"
    )
    nav = NavigationStream.from_manifest(tmp_path)  # a folder: its manifest.toml
    config = nav.config
    assert nav.camera.name == "paper-table1" and nav.imu_model.name == "mems-typical"
    assert (nav.site.lat_deg, nav.site.lon_deg, nav.site.alt_m) == (45.6, 126.7, 150.0)
    assert nav.epoch_utc == pd.Timestamp("2023-09-05T07:06:00Z")
    assert config.aiding.vehicle == "ground" and config.nhc_sigma == 0.1
    assert config.odometer_sigma == 0.05 and config.standstill_sigma is not None
    assert config.aiding.mount_rpy[2] == pytest.approx(math.radians(2.0))
    assert config.tilt_coupling  # the loop's yaw update: as run_log's stream
    nav.close()
    (tmp_path / "manifest.toml").write_text(
        (tmp_path / "manifest.toml").read_text().replace("nhc_std", "nhc_sd")
    )
    with pytest.raises(UserInputError, match=r"manifest.toml: unknown key 'filter.nhc_sd'"):
        NavigationStream.from_manifest(tmp_path / "manifest.toml")
