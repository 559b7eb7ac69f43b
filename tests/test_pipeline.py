"""The Eq. 13 loop: batch vs streaming, bad-data policies, bounded memory, CLI end to end."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pandas as pd
import pytest

from polins.cli import main
from polins.evaluation import summarize, truth_at
from polins.frames import euler_from_rot_nb, wrap_angle
from polins.fusion.config import FuseConfig
from polins.io import load_raw, read_log
from polins.loop import LoopOptions, NavigationStream, run_log
from polins.loop.stream import BLOCK_S, RUN_S

DURATION_S = 12.0


@pytest.fixture(scope="module")
def sim_log(tmp_path_factory):
    """A small simulated UGV log: 12 s, 200 Hz MEMS IMU, 5 Hz images at 1/8 resolution."""
    from polins.sim.scenario import simulate_log

    out = tmp_path_factory.mktemp("sim") / "ugv"
    simulate_log(out, scenario="ugv", duration_s=DURATION_S, image_rate_hz=5.0, downscale=8,
                 imu="mems-typical", seed=3, progress=False)  # fmt: skip
    return out / "manifest.toml"


@pytest.fixture(scope="module")
def batch(sim_log):
    return run_log(read_log(sim_log), workers=2, progress=False)


def _stream(log, *, options=None, delay_s=0.05, state_every=25, **kwargs):
    """Feed a log to a NavigationStream the way a vehicle would: IMU samples as they come,
    each image ``delay_s`` after it was taken; ``state()`` every ``state_every`` samples."""
    kwargs.setdefault("config", FuseConfig.from_log(log))  # [filter], [vehicle]: as run_log
    nav = NavigationStream(log.camera, log.imu_model, site=log.site, epoch_utc=log.epoch_utc,
                           options=options, **kwargs)  # fmt: skip
    imu = log.imu.to_numpy()
    k = 0
    estimates = []
    if log.odometry is not None:  # the odometer queued after the first sample, as run_log
        nav.add_imu(imu[0, 0], imu[0, 1:4], imu[0, 4:7])
        nav.add_odometry(log.odometry["t"], log.odometry["speed"])
        k = 1
    for t, item in log.images:
        while k < len(imu) and imu[k, 0] <= t + delay_s:
            nav.add_imu(imu[k, 0], imu[k, 1:4], imu[k, 4:7])
            k += 1
            if k % state_every == 0 and imu[k - 1, 0] > 1.5:
                estimates.append(nav.state())
        nav.add_image(t, load_raw(item))
    while k < len(imu):
        nav.add_imu(imu[k, 0], imu[k, 1:4], imu[k, 4:7])
        k += 1
    nav.close()
    return nav, estimates


def acquiring(m: pd.DataFrame) -> pd.Series:
    """The rows held for the yaw acquisition (docs/filter.md 7.1). The acquisition amends
    the verdicts of the first headings it used once it finds their consensus; a row shows
    the verdict the filter had when its run ended (held, or used when the same run of
    IMU samples also completed the acquisition)."""
    return m["update_reason"].fillna("").str.startswith("held for the yaw acquisition")


def test_streaming_matches_batch(sim_log, batch):
    log = read_log(sim_log)
    nav, estimates = _stream(log)
    sol = nav.drain_solution()
    ref = batch.solution.set_index("t").loc[sol["t"]].reset_index()
    assert len(sol) > 0.9 * len(batch.solution)
    # the runs split elsewhere (the stream's IMU blocks, the log's blocks per image); a
    # covariance step ends where a run ends: measured 3e-10 rad, sigmas 3e-6 relative
    for col in ("roll", "pitch", "yaw", "bgx", "bgz", "lat_deg"):
        np.testing.assert_allclose(sol[col], ref[col], rtol=0, atol=1e-9, err_msg=col)
    for col in ("yaw_std", "roll_std"):
        np.testing.assert_allclose(sol[col], ref[col], rtol=1e-5, atol=0, err_msg=col)
    np.testing.assert_allclose(sol["ve"], ref["ve"], rtol=0, atol=1e-5)
    # the image stage: the priors start from snapshots of the filter, which the run splits
    # above move by 1e-10 rad (measured 1.2e-10 rad in the measured yaw)
    m, mb = nav.drain_measurements(), batch.measurements
    pd.testing.assert_series_equal(m["ok"], mb["ok"])
    # (the verdicts of the yaw acquisition's first headings: see the next test)
    pd.testing.assert_series_equal(m["accepted"] | acquiring(m), mb["accepted"] | acquiring(mb))
    for col in ("yaw", "yaw_std", "prior_yaw", "prior_roll", "epsilon"):
        np.testing.assert_allclose(m[col], mb[col], rtol=0, atol=1e-9, err_msg=col)
    np.testing.assert_allclose(m["nis"], mb["nis"], rtol=1e-5, atol=1e-7)  # the sigmas above
    # the live estimate (IMU ahead of the images) ends on the batch solution
    last = nav.state()
    assert not last.aligning and last.heading_known and last.images_pending == 0
    row = last.nav.row()
    assert row["t"] == batch.solution["t"].iloc[-1]
    assert abs(wrap_angle(row["yaw"] - batch.solution["yaw"].iloc[-1])) < 1e-9
    assert row["yaw_std"] == pytest.approx(batch.solution["yaw_std"].iloc[-1], rel=1e-5)
    assert len(estimates) > 50 and all(e.heading_known for e in estimates[-10:])
    assert all(np.isfinite(e.nav.euler_std()[0]) for e in estimates[-10:])


def test_batch_heading_agrees_with_truth_within_sigma(sim_log, batch):
    log = read_log(sim_log)
    m = batch.measurements
    # the first headings are held until 3 agree (docs/filter.md 7.1): the stream reports
    # the verdict it had when it applied them
    held = acquiring(m)
    assert m["ok"].sum() >= 0.85 * len(m) and (m["accepted"] | held).sum() == m["ok"].sum()
    assert held.sum() <= 2 and not m.loc[held, "accepted"].any()
    # priors come from a snapshot at least prior_lag_s old (or the first one)
    used = m[m["ok"]]
    assert np.all(
        (used["prior_t"] <= used["t"] - 1.0 + 1e-9) | (used["prior_t"] == used["prior_t"].min())
    )
    s = summarize(
        batch.solution, m, batch.events, truth=log.truth, timing=batch.info["timing"], settle_s=3
    )
    heading = s["accuracy_vs_reference"]["heading"]
    assert heading["within_3sigma"] >= 0.95
    assert abs(heading["final_deg"]) < 3 * heading["final_sigma_deg"]
    assert heading["rms_deg"] < 0.5
    assert s["accuracy_vs_reference"]["measurement_heading"]["rms_deg"] < 0.5
    # the images' residual at the reference attitude, z - h(x_true, prior), is what their
    # sigma must cover (the raw heading error also holds the prior's tilt error)
    res = s["accuracy_vs_reference"]["measurement_residual"]
    assert 0.6 < res["rms_normalized"] < 1.4 and res["within_3sigma"] > 0.95, res


def test_measurements_do_not_depend_on_workers(sim_log, batch):
    one = run_log(read_log(sim_log), workers=1, progress=False)
    verdicts = ["measure_s", "accepted", "update_reason"]  # (the acquisition's: acquiring)
    pd.testing.assert_frame_equal(
        one.measurements.drop(columns=verdicts), batch.measurements.drop(columns=verdicts)
    )
    m, mb = one.measurements, batch.measurements
    pd.testing.assert_series_equal(m["accepted"] | acquiring(m), mb["accepted"] | acquiring(mb))
    # the filter's runs may split differently (timing of the pool), and a covariance step
    # ends where a run ends: measured 1.5e-10 rad, sigmas 3e-6 relative
    np.testing.assert_allclose(one.solution["yaw"], batch.solution["yaw"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(one.solution["yaw_std"], batch.solution["yaw_std"], rtol=1e-5,
                               atol=0)  # fmt: skip


def test_corrupt_and_missing_images_are_skipped(sim_log, batch, tmp_path):
    folder = tmp_path / "log"
    shutil.copytree(sim_log.parent, folder)
    index = pd.read_csv(folder / "images.csv")
    bad = [20, 31, 40]
    data = (folder / index["file"][bad[0]]).read_bytes()
    (folder / index["file"][bad[0]]).write_bytes(data[: len(data) // 2])  # truncated
    (folder / index["file"][bad[1]]).unlink()  # missing
    (folder / index["file"][bad[2]]).write_bytes(b"\x89PNG garbage")  # not an image
    result = run_log(read_log(folder), workers=2, progress=False)
    m = result.measurements
    assert len(m) == len(index)
    assert not m.loc[bad, "ok"].any()
    assert m.loc[bad, "reason"].str.startswith("unreadable image").all()
    assert (result.events["kind"] == "image-unreadable").sum() == 3
    good = m.index.difference(bad)
    np.testing.assert_array_equal(m.loc[good, "ok"], batch.measurements.loc[good, "ok"])
    assert np.all(np.isfinite(result.solution["yaw"].iloc[-100:]))


def test_bad_imu_samples_are_dropped_and_reported(sim_log, batch, tmp_path):
    log = read_log(sim_log)
    imu = log.imu.copy()
    extra = pd.DataFrame(
        {"t": [imu["t"][500], imu["t"][800] + 0.001, imu["t"][900] - 1.0],
         "gx": [0.0, np.nan, 0.0], "gy": 0.0, "gz": 0.0, "ax": 0.0, "ay": 0.0, "az": 9.8}
    )  # fmt: skip
    # a duplicate, a NaN sample and an old (out-of-order) sample, inserted in file order
    noisy = pd.concat([imu.iloc[:501], extra.iloc[[0]], imu.iloc[501:801], extra.iloc[[1]],
                       imu.iloc[801:901], extra.iloc[[2]], imu.iloc[901:]], ignore_index=True)  # fmt: skip
    dirty = log.__class__(**{**log.__dict__, "imu": noisy})
    result = run_log(dirty, workers=1, progress=False)
    kinds = result.events["kind"].value_counts()
    assert kinds["imu-out-of-order"] == 2 and kinds["imu-nonfinite"] == 1
    assert len(result.info["imu_used"]) == len(imu)
    np.testing.assert_allclose(result.solution["yaw"], batch.solution["yaw"], atol=1e-12)

    gap = pd.concat([imu.iloc[:1000], imu.iloc[1040:]], ignore_index=True)  # 0.2 s missing
    gapped = run_log(log.__class__(**{**log.__dict__, "imu": gap}), workers=1, progress=False)
    events = gapped.events[gapped.events["kind"] == "imu-gap"]
    assert len(events) == 1 and events["t"].iloc[0] == pytest.approx(imu["t"][999])  # its start
    s = summarize(gapped.solution, gapped.measurements, gapped.events, truth=log.truth, settle_s=3)
    assert s["accuracy_vs_reference"]["heading"]["within_3sigma"] >= 0.95


def test_image_order_policies_and_external_measurements(sim_log):
    log = read_log(sim_log)
    truth = log.truth
    opts = LoopOptions(max_image_delay_s=0.0)
    nav = NavigationStream(log.camera, log.imu_model, site=log.site, epoch_utc=log.epoch_utc,
                           options=opts)  # fmt: skip
    imu = log.imu.to_numpy()
    rng = np.random.default_rng(0)
    yaw_std = np.radians(0.2)
    t_meas = np.arange(2.0, DURATION_S, 0.25)
    ref = truth_at(truth, t_meas)["yaw"].to_numpy()
    j = 0
    for k in range(len(imu)):
        nav.add_imu(imu[k, 0], imu[k, 1:4], imu[k, 4:7])
        while j < len(t_meas) and t_meas[j] <= imu[k, 0]:
            nav.add_measurement(t_meas[j], yaw=ref[j] + yaw_std * rng.normal(), yaw_std=yaw_std)
            j += 1
        if k == 600:
            assert not nav.add_measurement(1.0, yaw=0.0, yaw_std=yaw_std)  # older: out of order
    assert not nav.add_image(5.0, np.zeros(log.camera.shape, np.uint16))  # before the last one
    late = NavigationStream(log.camera, log.imu_model, lat_deg=log.lat_deg, lon_deg=log.lon_deg,
                            alt_m=log.alt_m, epoch_utc=log.epoch_utc, options=opts)  # fmt: skip
    assert late.site == log.site  # the lat_deg/lon_deg/alt_m shorthand builds the Site
    for k in range(700):
        late.add_imu(imu[k, 0], imu[k, 1:4], imu[k, 4:7])
    assert not late.add_image(imu[500, 0], np.zeros(log.camera.shape, np.uint16))
    assert late.counts["image-late"] == 1
    nav.close()
    est = nav.state().nav
    assert nav.counts["image-out-of-order"] == 2
    yaw, yaw_std = euler_from_rot_nb(est.rot_nb)[0], est.euler_std()[0]
    err = float(wrap_angle(yaw - truth_at(truth, np.array([est.t]))["yaw"].iloc[0]))
    assert abs(err) < 3 * yaw_std and yaw_std < np.radians(0.2)
    m = nav.drain_measurements()
    assert (m["accepted"] | acquiring(m)).sum() == len(t_meas) and (
        m["reason"].str.contains("out-of-order")
    ).sum() == 2


def test_stream_memory_is_bounded(sim_log):
    log = read_log(sim_log)
    nav = NavigationStream(log.camera, log.imu_model, site=log.site, epoch_utc=log.epoch_utc,
                           executor="thread")  # fmt: skip
    imu = log.imu.to_numpy()
    images = iter(log.images)
    nxt = next(images)
    sizes = []
    for k in range(len(imu)):
        nav.add_imu(imu[k, 0], imu[k, 1:4], imu[k, 4:7])
        if nxt is not None and imu[k, 0] >= nxt[0] + 0.05:
            nav.add_image(nxt[0], load_raw(nxt[1]))
            nxt = next(images, None)
        if nav.filter is not None:
            sizes.append((len(nav._buf) + nav._intake.n_pending, len(nav._runner.hist), len(nav._snaps),
                          len(nav._images)))  # fmt: skip
    nav.close()
    buf, hist, snaps, pending = np.max(np.array(sizes[400:]), axis=0)
    rate = 200.0
    opts = nav.options
    # the filter runs at the end of a block of IMU time, on runs of at least RUN_S
    held = opts.max_image_delay_s + RUN_S + BLOCK_S
    assert hist <= (opts.prior_lag_s + held + 0.5) * rate
    assert buf <= (held + 0.5) * rate
    assert snaps <= (opts.prior_lag_s + opts.max_image_delay_s) / opts.snapshot_every_s + 3
    assert pending <= nav.max_in_flight + 3
    assert nav.drain_measurements()["ok"].sum() >= 50


def test_cli_simulate_then_fuse(tmp_path, capsys):
    sim, run = tmp_path / "sim", tmp_path / "run"
    code = main(["simulate", "--scenario", "ugv", "--out", str(sim), "--duration", "10",
                 "--downscale", "8", "--imu", "mems-typical", "--seed", "5", "--quiet"])  # fmt: skip
    assert code == 0
    code = main(["fuse", str(sim / "manifest.toml"), "--out", str(run), "--workers", "2",
                 "--quiet", "--settle", "3"])  # fmt: skip
    out = capsys.readouterr().out
    assert code == 0 and "heading" in out and "IMU samples/s" in out
    names = {p.name for p in run.iterdir()}
    assert {"solution.csv", "measurements.csv", "events.csv", "summary.json", "heading.png",
            "heading_error.png", "measurements.png", "epsilon.png"} <= names  # fmt: skip
    assert not [n for n in names if n.startswith(".")]  # no temporary files left
    summary = json.loads((run / "summary.json").read_text())
    heading = summary["accuracy_vs_reference"]["heading"]
    assert heading["within_3sigma"] >= 0.95
    assert abs(heading["final_deg"]) < 3 * heading["final_sigma_deg"]
    assert summary["images"]["accepted_by_filter"] >= 40
    assert summary["timing"]["images_per_s"] > 0 and summary["timing"]["imu_samples_per_s"] > 0
    # every kind's NIS with its verdict, printed and in the summary
    assert set(summary["nis"]) == {"yaw", "odo", "nhc", "zupt", "zaru"}, summary["nis"]
    assert all(f"NIS {kind}" in out for kind in summary["nis"])
    assert all(n["verdict"] and n["n"] > 0 for n in summary["nis"].values())
    meas = pd.read_csv(run / "measurements.csv")
    for col in ("t", "yaw", "heading_deg", "yaw_std", "heading_std_deg", "epsilon", "n_pixels",
                "ok", "reason", "yaw_error"):  # fmt: skip
        assert col in meas.columns
    sol = pd.read_csv(run / "solution.csv")
    assert len(sol) == 101 and {"heading_deg", "yaw_std"} <= set(sol.columns)  # 10 s at 10 Hz


def test_cli_fuse_user_errors(tmp_path, capsys):
    (tmp_path / "manifest.toml").write_text('[log]\nepoch_utc = "2023-09-05T07:06:00"\n')
    code = main(["fuse", str(tmp_path / "manifest.toml"), "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert code == 2 and "naive datetime" in err and "Traceback" not in err
    code = main(["fuse", str(tmp_path / "nope.toml"), "--out", str(tmp_path / "run")])
    assert code == 2 and "manifest not found" in capsys.readouterr().err


def test_ros_bag_log_gives_the_same_result(sim_log, batch, tmp_path):
    from polins.io.rosbag import write_bag

    log = read_log(sim_log)
    images = ((t, load_raw(item)) for t, item in log.images)
    write_bag(tmp_path / "rec", log.imu, images, epoch_utc=log.epoch_utc, ros_version=2,
              encoding="polarized_mono16")  # fmt: skip
    for name in ("camera.toml", "imu_model.toml"):
        if (sim_log.parent / name).exists():
            shutil.copy(sim_log.parent / name, tmp_path / name)
    m = log.manifest
    text = (
        f'[log]\nepoch_utc = "{log.epoch_utc.isoformat()}"\ncamera = "{m["log"]["camera"]}"\n'
        f'imu = "{m["log"]["imu"]}"\nlat_deg = {log.lat_deg!r}\nlon_deg = {log.lon_deg!r}\n'
        f'alt_m = {log.alt_m!r}\n[files]\nbag = "rec"\n'
    )
    if "vehicle" in m:  # the same vehicle, mounting and odometer
        shutil.copy(sim_log.parent / "odometer.csv", tmp_path / "odometer.csv")
        v = m["vehicle"]
        text += (f'[vehicle]\nkind = "{v["kind"]}"\nmount_rpy_deg = {list(v["mount_rpy_deg"])}\n'
                 f'lever_arm_b = {list(v["lever_arm_b"])}\nodometer = "odometer.csv"\n'
                 f'odometer_std = {v["odometer_std"]}\n')  # fmt: skip
    (tmp_path / "manifest.toml").write_text(text)
    result = run_log(read_log(tmp_path / "manifest.toml"), workers=1, progress=False)
    mb = batch.measurements
    pd.testing.assert_series_equal(result.measurements["ok"], mb["ok"])
    np.testing.assert_allclose(result.measurements["t"], mb["t"], atol=1e-9)
    np.testing.assert_allclose(result.measurements["yaw"], mb["yaw"], atol=1e-9)
    np.testing.assert_allclose(result.solution["yaw"], batch.solution["yaw"], atol=1e-9)


@pytest.mark.slow
def test_default_ugv_simulate_then_fuse(tmp_path, capsys):
    """The README's two commands with their defaults (300 s drive, 1501 images)."""
    sim, run = tmp_path / "sim", tmp_path / "run"
    assert main(["simulate", "--scenario", "ugv", "--out", str(sim), "--quiet"]) == 0
    assert main(["fuse", str(sim / "manifest.toml"), "--out", str(run), "--quiet"]) == 0
    summary = json.loads((run / "summary.json").read_text())
    heading = summary["accuracy_vs_reference"]["heading"]
    assert heading["within_3sigma"] >= 0.95 and heading["rms_normalized"] < 2.0
    assert abs(heading["final_deg"]) < 3 * heading["final_sigma_deg"]
    assert heading["rms_deg"] < 0.05
    assert summary["images"]["accepted_by_filter"] >= 0.95 * summary["images"]["total"]


def test_a_bug_in_the_measurer_propagates_and_opencv_failures_are_events(sim_log, monkeypatch):
    import cv2
    from scipy.spatial.transform import Rotation

    import polins.loop.measurer as measurer_module
    from polins.ins.state import NavState
    from polins.ins.strapdown import Mechanization
    from polins.loop.measurer import ImageMeasurer
    from polins.loop.prior import PriorJob

    log = read_log(sim_log)
    measurer = ImageMeasurer(log.camera, "compensated", {"fixed_zenith": False})
    raw = np.zeros(log.camera.shape, np.uint16)
    level = NavState(0.0, Rotation.identity(), np.zeros(3), 0.8, 2.2, 0.0)
    prior = PriorJob.of(level, [], 0.0, Mechanization())  # the prior: the state itself
    sun_n = np.array([0.0, 0.6, 0.8])

    def bug(*args, **kwargs):
        raise TypeError("a bug inside polins.measure")

    monkeypatch.setattr(measurer_module, "measure", bug)
    with pytest.raises(TypeError, match="a bug inside"):
        measurer(raw, sun_n, prior)
    with pytest.raises(TypeError, match="a bug inside"):  # not an "image-error" row
        run_log(log, workers=1, progress=False)

    def opencv_fails(*args, **kwargs):
        raise cv2.error("OpenCV failed on these pixels")

    monkeypatch.setattr(measurer_module, "measure", opencv_fails)
    row = measurer(raw, sun_n, prior)
    assert not row["ok"] and row["event"] == "image-error" and "OpenCV" in row["reason"]
    row = measurer(np.zeros((3, 3), np.uint16), sun_n, prior)  # wrong size: a data fault
    assert not row["ok"] and row["event"] == "image-unreadable"


def test_run_log_runs_the_filter_once(sim_log, batch, monkeypatch):
    """One ESKF for the whole run, and its estimates are what run_fusion gives on the
    stream's own measurement table (no second pass over the log)."""

    from polins.fusion.eskf import ESKF
    from polins.loop.offline import fuse_measurements

    built = []
    init = ESKF.__init__

    def counting_init(self, *args, **kwargs):
        built.append(args)
        init(self, *args, **kwargs)

    monkeypatch.setattr(ESKF, "__init__", counting_init)
    log = read_log(sim_log)
    result = run_log(log, workers=1, progress=False)
    assert len(built) == 1
    assert len(result.solution) == 121 and result.info["timing"]["fuse_s"] < 1.0  # 12 s, 10 Hz
    config = LoopOptions().filter_config(FuseConfig.from_log(log))
    fused = fuse_measurements(result.info["imu_used"], result.measurements, config,
                              odometry=log.odometry)  # fmt: skip
    ref = fused.solution
    assert len(built) == 2  # (the reference itself)
    # the stream's update log holds every kind's updates, as the batch filter's
    kinds = result.updates["name"].value_counts().to_dict()
    assert kinds == fused.updates["name"].value_counts().to_dict()
    assert set(kinds) == {"yaw", "nhc", "odo", "zupt", "zaru"}, kinds
    nis = summarize(result.solution, result.measurements, result.events,
                    updates=result.updates)["nis"]  # fmt: skip
    u = result.updates
    used = u[u["accepted"] & (u["innovation"].map(len) > 0)]  # (the yaw alignment has none)
    assert {k: v["n"] for k, v in nis.items()} == used["name"].value_counts().to_dict()
    # (a ground vehicle's 10 Hz NHC and standstill updates make the covariance steps, cut
    # where the stream's runs end, move bgz by ~1e-10 rad/s, ve and alt_m by ~3e-6)
    for col, atol in (("roll", 1e-9), ("pitch", 1e-9), ("yaw", 1e-9), ("yaw_std", 1e-7),
                      ("bgz", 1e-10), ("ve", 1e-5), ("alt_m", 1e-5)):  # fmt: skip
        np.testing.assert_allclose(result.solution[col], ref[col], rtol=0, atol=atol, err_msg=col)
    # one worker or a pool: the runs split where the images resolve (the same cut steps)
    np.testing.assert_allclose(result.solution["yaw"], batch.solution["yaw"], rtol=0, atol=1e-9)


def test_events_are_bounded_and_the_site_is_never_silent(sim_log):
    from polins.fusion.faults import EventKind
    from polins.loop.tables import EventBuffer
    from polins.site import PAPER_SITE

    buf = EventBuffer(2)
    for t in (1.0, 2.0, 3.0):
        buf.add(t, "imu-gap", "gap")
    assert buf.dropped == 1 and buf.counts["imu-gap"] == 3
    assert buf.drain()["t"].tolist() == [2.0, 3.0] and len(buf) == 0
    with pytest.raises(ValueError, match="not a valid EventKind"):
        buf.add(0.0, "something-else", "")
    assert "image-error" in set(EventKind) and set(buf.counts) == set(EventKind)

    log = read_log(sim_log)
    with pytest.warns(UserWarning, match="paper.s site") as caught:
        nav = NavigationStream(log.camera, log.imu_model, epoch_utc=log.epoch_utc,
                               options=LoopOptions(max_table_rows=3))  # fmt: skip
    assert len(caught) == 1 and nav.site == PAPER_SITE
    assert nav.state().aligning and nav.state().nav is None
    imu = log.imu.to_numpy()
    nav.add_imu(imu[0, 0], imu[0, 1:4], imu[0, 4:7])
    for k in range(1, 6):  # five bad samples: three kept, two dropped, all counted
        assert not nav.add_imu(imu[k, 0], [np.nan, 0.0, 0.0], imu[k, 4:7])
    assert nav.counts["imu-nonfinite"] == 5 and nav.events_dropped == 2
    assert len(nav.drain_events()) == 3 and len(nav.drain_events()) == 0
    with pytest.raises(ValueError, match="either site or lat_deg"):
        NavigationStream(log.camera, log.imu_model, site=log.site, lat_deg=1.0, lon_deg=2.0,
                         epoch_utc=log.epoch_utc)  # fmt: skip
