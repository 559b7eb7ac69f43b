"""One fault policy for every path (docs/faults.md): ``polins fuse``, ``polins.fuse`` and
``NavigationStream`` bridge an IMU gap alike, report an undeclared deg/s gyro alike, and a
run whose NIS is far outside any plausible band is not a result."""

from __future__ import annotations

import math
import shutil

import numpy as np
import pandas as pd
import pytest
from scipy.stats import chi2

import polins
from polins.cli import main
from polins.frames import wrap_angle
from polins.fusion import ImplausibleRunError, ImuUnitsError, run_fusion
from polins.fusion.config import FuseConfig
from polins.fusion.faults import EventKind, ImuScreen, nis_verdict
from polins.io import load_raw, read_log
from polins.loop import LoopOptions, NavigationStream

DURATION_S = 30.0
GAP = (5.0, 8.0)  # the IMU samples strictly between are removed: a 3 s gap
IMAGE_RATE_HZ = 2.0
YAW_STD = math.radians(0.3)


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    """A 30 s simulated UGV log (turns from 20 s, 2 Hz images at 1/8 resolution) and two
    copies: the IMU stopping for 3 s while the images go on, and the gyro in deg/s without
    a units declaration."""
    from polins.sim.scenario import simulate_log

    root = tmp_path_factory.mktemp("faults")
    simulate_log(root / "clean", scenario="ugv", duration_s=DURATION_S, downscale=8,
                 image_rate_hz=IMAGE_RATE_HZ, imu="mems-typical", seed=0, progress=False)  # fmt: skip
    imu = pd.read_csv(root / "clean" / "imu.csv", comment="#")
    manifest = (root / "clean" / "manifest.toml").read_text()
    out = {"clean": root / "clean" / "manifest.toml"}
    for name in ("gap", "degs"):
        folder = root / name
        folder.mkdir()
        for item in (root / "clean").iterdir():
            if item.name not in ("imu.csv", "manifest.toml"):
                (folder / item.name).symlink_to(item)
        text = manifest
        if name == "gap":
            table = imu[(imu["t"] <= GAP[0]) | (imu["t"] >= GAP[1])]
        else:
            table = imu.assign(**{c: np.degrees(imu[c]) for c in ("gx", "gy", "gz")})
            text = text.replace('[units]\ngyro = "rad/s"\naccel = "m/s^2"\n', "")
            assert "[units]" not in text
        table.to_csv(folder / "imu.csv", index=False)
        (folder / "manifest.toml").write_text(text)
        out[name] = folder / "manifest.toml"
    return out


def headings(log, rng):
    """Heading rows at the image times: the truth with N(0, 0.3 deg) noise."""
    t = np.asarray(log.images.t, dtype=float)
    truth = log.truth
    yaw = np.interp(t, truth["t"], np.unwrap(truth["yaw"]))
    return pd.DataFrame({"t": t, "yaw": wrap_angle(yaw + rng.normal(0.0, YAW_STD, t.size)),
                         "yaw_std": YAW_STD})  # fmt: skip


def inside_gap(t):
    return (np.asarray(t) > GAP[0]) & (np.asarray(t) < GAP[1])


def stream_of(log, **kwargs):
    return NavigationStream(log.camera, log.imu_model, site=log.site, epoch_utc=log.epoch_utc,
                            config=FuseConfig.from_log(log), **kwargs)  # fmt: skip


def feed(nav, log, rows=None):
    """IMU samples one by one, each image (or heading row) after the samples up to it."""
    imu = log.imu.to_numpy()
    k = 0
    items = (
        list(log.images) if rows is None else list(zip(rows["t"], rows.itertuples(), strict=True))
    )
    for t, item in items:
        while k < len(imu) and imu[k, 0] <= t:
            nav.add_imu(imu[k, 0], imu[k, 1:4], imu[k, 4:7])
            k += 1
        if rows is None:
            nav.add_image(t, load_raw(item))
        else:
            nav.add_measurement(t, yaw=item.yaw, yaw_std=item.yaw_std)
    nav.add_imu_many(imu[k:, 0], imu[k:, 1:4], imu[k:, 4:7])
    nav.flush()


def check_gap_events(events, t_images):
    """One imu-gap event at the gap's start, one measurement-in-gap per image inside it and
    per odometer speed inside it; returns the odometer speeds skipped."""
    gap = events[events["kind"] == "imu-gap"]
    assert len(gap) == 1 and gap["t"].iloc[0] == pytest.approx(GAP[0])
    assert gap["detail"].iloc[0].startswith("IMU gap of 3 s")
    skipped = events[events["kind"] == "measurement-in-gap"]
    assert inside_gap(skipped["t"]).all()
    odo = skipped["detail"].str.startswith("odo skipped")
    n_inside = int(inside_gap(t_images).sum())
    assert n_inside == 5 and (~odo).sum() == n_inside
    return int(odo.sum())


@pytest.mark.parametrize("backend", ["eskf", "graph"])
def test_imu_gap_in_every_path(logs, tmp_path, capsys, backend):
    log = read_log(logs["gap"])
    t_images = np.asarray(log.images.t, dtype=float)
    # polins fuse: the camera loop
    code = main(["fuse", str(logs["gap"]), "--out", str(tmp_path / "run"), "--quiet",
                 "--no-plots", "--workers", "1", "--backend", backend])  # fmt: skip
    assert code == 0, capsys.readouterr().err
    n_odo = check_gap_events(pd.read_csv(tmp_path / "run" / "events.csv"), t_images)
    assert n_odo == 29  # 10 Hz odometer
    sol = pd.read_csv(tmp_path / "run" / "solution.csv")
    assert not sol["t"].between(GAP[0] + 1e-3, GAP[1] - 1e-3).any()
    after = sol[sol["t"] > 4.0]  # the yaw acquired from the first three headings
    assert np.isfinite(after[["yaw", "yaw_std", "roll", "pitch"]].to_numpy()).all()
    # polins.fuse: the same IMU table with heading rows at the image times
    rows = headings(read_log(logs["clean"]), np.random.default_rng(1))
    config = FuseConfig.from_log(log).replace(output_rate_hz="imu")  # the gap's last sample
    res = run_fusion(log.imu, rows, backend, config=config, odometry=log.odometry)
    assert check_gap_events(res.events, rows["t"]) == n_odo
    assert res.updates.loc[inside_gap(res.updates["t"]), "reason"].str.startswith(
        "inside an IMU gap").all()  # fmt: skip
    sol = res.solution[res.solution["t"] > 4.0]
    assert np.isfinite(sol[["yaw", "yaw_std", "roll", "pitch"]].to_numpy()).all()
    # the filter's covariance grew across the gap: the yaw sigma at its end above the run's
    # median; the graph is a smoother, the headings after the gap inform its end: its sigma
    # there is that of ESKF + RTS, whose backward pass crosses the same gap noise
    after_gap = res.solution.loc[res.solution["t"] >= GAP[1], "yaw_std"].iloc[0]
    if backend == "eskf":
        assert after_gap > 1.2 * sol["yaw_std"].median()
    else:
        rts = run_fusion(log.imu, rows, "eskf", config=config.replace(smooth=True),
                         odometry=log.odometry).solution  # fmt: skip
        assert after_gap == pytest.approx(rts.loc[rts["t"] >= GAP[1], "yaw_std"].iloc[0], rel=0.05)


def test_imu_gap_in_the_stream(logs):
    log = read_log(logs["gap"])
    nav = stream_of(log)
    feed(nav, log)
    assert check_gap_events(nav.drain_events(), np.asarray(log.images.t, dtype=float)) == 0
    m = nav.drain_measurements()
    assert (m.loc[inside_gap(m["t"]), "reason"].str.startswith("measurement-in-gap")).all()
    assert m["accepted"].sum() >= 40
    est = nav.state().nav
    assert est is not None and est.yaw_aligned and np.isfinite(est.sigma["att"]).all()
    sol = nav.drain_solution()
    assert np.isfinite(sol.loc[sol["t"] > 4.0, ["yaw", "yaw_std"]].to_numpy()).all()


def test_undeclared_deg_per_s_gyro_in_every_path(logs, tmp_path, capsys):
    log = read_log(logs["degs"])
    rows = headings(read_log(logs["clean"]), np.random.default_rng(2))
    # polins fuse: one line, exit 2, nothing written
    code = main(["fuse", str(logs["degs"]), "--out", str(tmp_path / "run"), "--quiet",
                 "--no-plots", "--workers", "1"])  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "looks like deg/s" in err[0], err
    assert not (tmp_path / "run" / "solution.csv").exists()
    # polins.fuse, both backends: the named exception
    for backend in ("eskf", "graph"):
        with pytest.raises(
            ImuUnitsError, match=r"turns 5\d(\.\d)? times as much .* looks like deg/s"
        ):
            run_fusion(log.imu, rows, backend, config=FuseConfig.from_log(log))
    # the stream: once the headings turn (from 20 s), the call that hands one over raises
    nav = stream_of(log)
    with pytest.raises(ImuUnitsError, match="looks like deg/s") as caught:
        feed(nav, log, rows)
    assert nav.t_latest > 20.0 and isinstance(caught.value, ValueError)
    # the right units pass the same checks in every path
    clean = read_log(logs["clean"])
    assert np.isfinite(
        run_fusion(clean.imu, rows, config=FuseConfig.from_log(clean)).solution["yaw"]
    ).any()
    nav = stream_of(clean)
    feed(nav, clean, rows)
    assert nav.state().heading_known


def test_imu_screen_is_the_same_sample_by_sample_and_whole():
    rng = np.random.default_rng(0)
    t = np.arange(200) * 0.01
    t[[50, 120]] = t[[49, 100]]  # a duplicate and an old sample
    t[150:] += 0.5  # a gap
    w = rng.normal(0.0, 0.1, (200, 3))
    f = rng.normal(0.0, 0.1, (200, 3)) + np.array([0.0, 0.0, 9.8])
    w[70, 1] = np.nan
    w[90, 2] = 100.0  # beyond the 2000 deg/s full scale
    full_scale = polins.load_imu("mems-typical").full_scale()
    whole = ImuScreen(full_scale, 0.05)
    keep, events, ends = whole.screen(t, w, f)
    one = ImuScreen(full_scale, 0.05)
    parts = [one.screen(t[i : i + 1], w[i : i + 1], f[i : i + 1]) for i in range(200)]
    assert keep.tolist() == [bool(p[0][0]) for p in parts]
    assert events == [e for p in parts for e in p[1]]
    assert [e.kind for e in events] == ["imu-out-of-order", "imu-nonfinite", "imu-out-of-range",
                                        "imu-out-of-order"]  # fmt: skip
    assert ends.tolist() == [150] and whole.gaps == one.gaps == [(t[149], t[150])]
    assert set(EventKind) >= {e.kind for e in events}


def test_nis_verdict_flags_only_implausible_runs():
    rng = np.random.default_rng(0)
    dof = rng.choice([1, 2], 500)
    nis = chi2.rvs(dof, random_state=rng)
    assert nis_verdict(nis, dof) is None
    assert nis_verdict(nis * 30.0, dof) is None  # mis-tuned (R 5x too small), still a run
    nis[:100] = 1e6  # a fifth of outliers leave the median in place
    assert nis_verdict(nis, dof) is None
    line = nis_verdict(chi2.rvs(dof, random_state=rng) * 1000.0, dof)
    assert line is not None and "\n" not in line
    for cause in ("units", "time base", "IMU model", "camera file"):
        assert cause in line


def test_implausible_run_raises_with_its_result(logs):
    # the headings 100 times more confident than they are: the filter cannot fit them
    log = read_log(logs["clean"])
    rows = headings(log, np.random.default_rng(3))
    rows["yaw_std"] = YAW_STD / 100.0
    config = FuseConfig.from_options(FuseConfig.from_log(log), acquire_k=1, acquire_n=1)
    with pytest.raises(ImplausibleRunError, match="implausible run") as caught:
        run_fusion(log.imu, rows, config=config)
    assert len(caught.value.result.solution) == 301  # 30 s at 10 Hz
    res = run_fusion(log.imu, headings(log, np.random.default_rng(3)), config=config)
    assert res.updates["accepted"].mean() > 0.95


def test_missing_image_folder_is_refused_before_any_work(logs, tmp_path, capsys):
    folder = tmp_path / "log"
    folder.mkdir()
    for item in logs["clean"].parent.iterdir():
        if item.is_file():  # the index lists the images, their folder is gone
            shutil.copy(item, folder / item.name)
    code = main(["fuse", str(folder / "manifest.toml"), "--out", str(tmp_path / "run"),
                 "--quiet", "--no-plots", "--workers", "1"])  # fmt: skip
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert code == 2 and len(err) == 1 and captured.out == "", err
    n = len(read_log(logs["clean"]).images)
    assert f"images does not exist: all {n} images of the index are missing" in err[0]


def test_rejections_are_printed_grouped_by_reason():
    from polins.evaluation.summary import format_summary, summarize
    from polins.loop.tables import measurement_frame

    rows = [{"t": 0.1 * i, "ok": False, "reason": f"unreadable image: img_{i}.png not found"}
            for i in range(60)]  # fmt: skip
    rows += [{"t": 10 + 0.1 * i, "ok": True, "yaw": 0.0, "accepted": False,
              "update_reason": f"NIS above the gate: {100 + i} > 9 (chi2, 1 dof, p=0.9973)"}
             for i in range(50)]  # fmt: skip
    rows += [{"t": 20 + 0.1 * i, "ok": False, "reason": f"too few valid pixels ({i} < 500)"}
             for i in range(40)]  # fmt: skip
    m = measurement_frame(rows)
    summary = summarize(
        pd.DataFrame({"t": [0.0]}), m, pd.DataFrame(columns=["t", "kind", "detail"])
    )
    lines = [ln for ln in format_summary(summary).splitlines() if "rejected" in ln]
    assert [ln.split(None, 2)[1:] for ln in lines] == [
        ["60", "unreadable image"], ["50", "NIS above the gate"],
        ["40", "too few valid pixels (# < #)"]]  # fmt: skip


def test_the_imu_gap_has_one_option():
    with pytest.raises(TypeError, match=r"'max_imu_gap_s' is FuseConfig's max_gap_s"):
        LoopOptions(max_imu_gap_s=0.2)
    assert FuseConfig(max_gap_s=0.5).gap_s == 0.5
