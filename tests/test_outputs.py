"""Outputs of the command line: whole output sets, honest exit status, tables and plots for people.

Most tests run ``polins fuse`` on a tiny simulated log with the navigation loop replaced by
a stand-in built from the log's reference trajectory (``fake_run_log``): they test what the
command line does around the loop, quickly and independently of the filter. One test runs
the real loop end to end.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import polins.loop
from polins.cli import main
from polins.compass.measure import NoiseModelWarning
from polins.evaluation import format_summary, heading_plot_series, summarize
from polins.fusion.config import FuseConfig
from polins.fusion.items import UpdateRecord, records_table
from polins.fusion.result import FusionResult
from polins.io import read_log
from polins.io.checks import run_verdict, time_base_hint
from polins.io.outputs import clean_stale, output_set, read_stamp
from polins.io.schema import schema_markdown
from polins.loop.tables import EVENT_COLUMNS, EventBuffer, measurement_frame

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def log_dir(tmp_path_factory):
    """A 10 s simulated UGV log at 1/8 resolution (51 images), written by the CLI."""
    out = tmp_path_factory.mktemp("cli") / "log"
    argv = ["simulate", "--scenario", "ugv", "--out", str(out), "--duration", "10",
            "--imu", "mems-typical", "--quiet"]  # fmt: skip
    assert main(argv) == 0
    return out


def fake_run_log(log, *, options=None, config=None, backend="eskf", workers=None, rot_nb0=None,
                 progress=True, calls=None):  # fmt: skip
    """A stand-in for ``polins.loop.run_log``: the reference as solution, every image inside
    the IMU's span measured at the reference heading (0.05 deg noise)."""
    if calls is not None:
        calls.append(config)
    truth = log.truth
    sol = truth[["t", "roll", "pitch", "yaw", "heading_deg"]].copy()
    for name in ("roll_std", "pitch_std", "yaw_std"):
        sol[name] = np.radians(0.1)
    t_imu = log.imu["t"].to_numpy(dtype=float)
    rng = np.random.default_rng(0)
    rows, events = [], list(log.events)
    for t, item in log.images:
        inside = t_imu.min() <= t <= t_imu.max()
        yaw = (
            float(np.interp(t, truth["t"], np.unwrap(truth["yaw"])))
            + np.radians(0.05) * rng.normal()
        )
        row = {"t": t, "ok": inside, "image": str(item), "accepted": inside}
        if inside:
            row |= {"yaw": yaw, "yaw_std": np.radians(0.05), "nis": 0.8, "nis_dof": 1,
                    "heading_deg": float(np.mod(90.0 - np.degrees(yaw), 360.0)),
                    "eigen_gap": 0.9, "residual_rms": 1.0, "epsilon": 0.1}  # fmt: skip
        else:
            row["reason"] = "image-outside-imu: image outside the IMU's time span"
            events.append((t, "image-outside-imu", "image outside the IMU's time span"))
        rows.append(row)
    timing = {"run_s": 0.1, "loop_s": 0.1, "fuse_s": 0.0, "images": len(rows),
              "imu_samples": len(t_imu), "workers": 1.0, "measure_s_mean": 0.0}  # fmt: skip
    var = np.radians(0.05) ** 2  # the innovation of NIS 0.8 for every measured image
    updates = records_table([UpdateRecord(r["t"], "yaw", 1, 0.8, True, "", (np.sqrt(0.8 * var),),
                                          (var,)) for r in rows if r["ok"]])  # fmt: skip
    return FusionResult(sol, updates, pd.DataFrame(events, columns=EVENT_COLUMNS),
                        config or FuseConfig.from_log(log), backend=backend,
                        info={"timing": timing, "settings": {"backend": backend}, "imu_used": log.imu},
                        measurements=measurement_frame(rows))  # fmt: skip


@pytest.fixture
def fake_loop(monkeypatch):
    """Replace the navigation loop by ``fake_run_log``; returns the configs it was given."""
    calls = []
    monkeypatch.setattr(polins.loop, "run_log",
                        lambda log, **kw: fake_run_log(log, calls=calls, **kw))  # fmt: skip
    return calls


def _fuse(log_dir, out, *extra):
    return main(["fuse", str(log_dir), "--out", str(out), "--quiet", "--workers", "1", *extra])


# ----------------------------------------------------------------------------- item 3
def test_output_set_is_whole_and_stamped(log_dir, tmp_path, fake_loop, capsys):
    out = tmp_path / "run"
    assert _fuse(log_dir, out) == 0
    stamp = read_stamp(out)
    assert stamp["status"] == "complete" and stamp["command"] == "fuse"
    assert stamp["polins_version"] and stamp["settings"]["filter"]["imu_model"] == "mems-typical"
    assert sorted(stamp["files"]) == sorted(p.name for p in out.iterdir())
    # the "wrote" line lists every file, measurements.csv and run.json included
    wrote = re.search(r"wrote (.*) to ", capsys.readouterr().out).group(1).split(", ")
    assert sorted(wrote) == sorted(p.name for p in out.iterdir())
    assert {"measurements.csv", "run.json", "schema.json", "heading.png"} <= set(wrote)
    assert [p.name for p in tmp_path.iterdir()] == ["run"]  # no temporary sibling left


def test_ctrl_c_leaves_the_previous_set(log_dir, tmp_path, fake_loop, monkeypatch, capsys):
    out = tmp_path / "run"
    assert _fuse(log_dir, out, "--no-plots") == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    import polins.evaluation.report as report

    real = report.plot_report

    def interrupted(folder, *args, **kwargs):  # Ctrl-C while plotting, one PNG written
        real(folder, *args, **kwargs)
        (Path(folder) / "heading.png").unlink()
        raise KeyboardInterrupt

    monkeypatch.setattr(report, "plot_report", interrupted)
    capsys.readouterr()
    assert _fuse(log_dir, out) == 130
    err = capsys.readouterr().err
    assert err.strip() == "polins fuse: interrupted; outputs unchanged"
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before  # old set, whole
    assert [p.name for p in tmp_path.iterdir()] == ["run"]  # temporary folder removed


def test_sigterm_unwinds_like_ctrl_c(log_dir, tmp_path, monkeypatch, capsys):
    from polins.io.outputs import Terminated

    def killed(log, **kwargs):
        raise Terminated

    monkeypatch.setattr(polins.loop, "run_log", killed)
    assert _fuse(log_dir, tmp_path / "run") == 143
    assert "terminated; outputs unchanged" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_forked_workers_ignore_ctrl_c():
    """Found: Ctrl-C printed a 38-line traceback (the image workers' among them)."""
    import signal

    from polins.io.outputs import signals_unwind

    # an interactive run's SIGINT (a test worker or a background job may have it ignored)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        _fork_and_interrupt(signals_unwind)
    finally:
        signal.signal(signal.SIGINT, previous)


def _fork_and_interrupt(signals_unwind):
    import os
    import signal
    import time

    with signals_unwind():
        pid = os.fork()
        if pid == 0:  # a worker process forked by the image pool
            try:
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.05)
                os._exit(0)
            except BaseException:
                os._exit(3)
        _, status = os.waitpid(pid, 0)
        with pytest.raises(KeyboardInterrupt):  # ... while the main process unwinds
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1.0)
    assert os.waitstatus_to_exitcode(status) == 0


def test_stale_temporaries_are_cleaned_at_the_start(tmp_path):
    final = tmp_path / "run"
    (tmp_path / ".run.polins-tmp-dead").mkdir()
    (tmp_path / ".run.polins-tmp-dead" / ".measurements.png.1234.tmp.png").write_text("x")
    old = tmp_path / ".run.polins-old-beef"  # killed between the two renames of a swap
    old.mkdir()
    (old / "run.json").write_text("{}")
    clean_stale(final)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]  # previous set restored
    assert (final / "run.json").is_file()
    with output_set(final, command="test") as s:
        (s.path / "a.csv").write_text("1\n")
    assert sorted(p.name for p in final.iterdir()) == ["a.csv", "run.json"]  # replaced whole


def test_foreign_folder_is_refused_before_any_work(log_dir, tmp_path, fake_loop, capsys):
    (tmp_path / "thesis.tex").write_text("mine")
    assert _fuse(log_dir, tmp_path) == 2
    assert "files polins did not write (thesis.tex" in capsys.readouterr().err
    assert fake_loop == []  # nothing ran


# ----------------------------------------------------------------------------- item 2
def _shifted_log(log_dir, tmp_path, offset):
    dst = tmp_path / "log"
    shutil.copytree(log_dir, dst)
    imu = pd.read_csv(dst / "imu.csv", comment="#")
    imu["t"] += offset
    (dst / "imu.csv").write_text("# units: gyro=rad/s, accel=m/s^2\n" + imu.to_csv(index=False))
    return dst


def test_unix_time_imu_exits_1_with_a_time_base_hint(log_dir, tmp_path, fake_loop, capsys):
    dst = _shifted_log(log_dir, tmp_path, 1_693_897_560.0)
    assert _fuse(dst, tmp_path / "run") == 1
    captured = capsys.readouterr()
    last = captured.err.strip().splitlines()[-1]
    assert "nothing usable: 0 of 51 images measured" in last and "image-outside-imu 51" in last
    assert "IMU times look like Unix seconds" in last
    assert "warning: time base mismatch" in captured.err  # said before the run too
    assert read_stamp(tmp_path / "run")["settings"]["status"].startswith("nothing usable")


def test_max_image_failures(log_dir, tmp_path, fake_loop, capsys):
    dst = _shifted_log(log_dir, tmp_path, 4.0)  # images 0..4 s lie before the IMU: 20 of 51
    assert _fuse(dst, tmp_path / "a") == 0  # 39% failed, within the default 50%
    assert _fuse(dst, tmp_path / "b", "--max-image-failures", "30%") == 1
    assert "more than the 30% allowed by --max-image-failures" in capsys.readouterr().err


def test_nothing_accepted_by_the_filter_is_exit_1():
    m = measurement_frame([{"t": 1.0, "ok": True, "accepted": False, "nis": 40.0}])
    summary = summarize(pd.DataFrame({"t": [1.0]}), m, pd.DataFrame(columns=EVENT_COLUMNS))
    verdict = run_verdict(summary, pd.DataFrame(columns=EVENT_COLUMNS), 0.5)
    assert verdict == "nothing usable: none of the 1 measured images was accepted by the filter"


def test_time_base_hint_either_way():
    t = np.arange(0.0, 30.0, 0.005)
    assert time_base_hint(t, np.arange(0.5, 29.0, 0.2)) is None
    assert "image times look like Unix nanoseconds" in time_base_hint(
        t, 1.69e18 + np.arange(5) * 2e8
    )


# ----------------------------------------------------------------------------- item 6
def test_csv_floats_are_short_and_every_column_is_documented(log_dir, tmp_path, fake_loop):
    out = tmp_path / "run"
    assert _fuse(log_dir, out, "--no-plots") == 0
    text = (out / "events.csv").read_text() + (out / "measurements.csv").read_text()
    assert "0.20000000000000001" not in text and "0.2," in text
    numbers = re.findall(r"(?<![\w.])-?\d+\.\d+(?:e[-+]?\d+)?", text)
    digits = [len(n.lstrip("-").split("e")[0].replace(".", "").lstrip("0")) for n in numbers]
    assert numbers and max(digits) <= 10  # %.10g
    schema = json.loads((out / "schema.json").read_text())
    for name in ("solution.csv", "measurements.csv", "events.csv"):
        header = pd.read_csv(out / name, nrows=0).columns
        assert list(schema[name]) == list(header)
        assert all(schema[name][c]["unit"] and schema[name][c]["meaning"] for c in header)
    assert "eigen-gap" in schema["measurements.csv"]["eigen_gap"]["meaning"]
    assert "noise" in schema["measurements.csv"]["residual_rms"]["meaning"]


def test_parquet_tables_hold_the_csv_tables(log_dir, tmp_path, fake_loop):
    """``table_format=parquet``: the same tables, columns and schema, as Parquet files."""
    csv_out, pq_out = tmp_path / "csv", tmp_path / "pq"
    assert _fuse(log_dir, csv_out, "--no-plots") == 0
    assert _fuse(log_dir, pq_out, "--no-plots", "--set", "table_format=parquet") == 0
    schema = json.loads((pq_out / "schema.json").read_text())
    assert not list(pq_out.glob("*.csv"))
    for name in ("solution", "measurements", "events"):
        a = pd.read_csv(csv_out / f"{name}.csv")
        b = pd.read_parquet(pq_out / f"{name}.parquet")
        assert list(a.columns) == list(b.columns) == list(schema[f"{name}.parquet"])
        assert len(a) == len(b)
        numeric = b.select_dtypes("number").columns
        np.testing.assert_allclose(
            a[numeric].to_numpy(float),
            b[numeric].to_numpy(float),
            rtol=1e-9,
            atol=1e-12,
            err_msg=name,
        )  # CSV: %.10g
    assert all(v["unit"] for v in schema["solution.parquet"].values())
    assert "solution.parquet" in read_stamp(pq_out)["files"]


def test_graph_summary_says_which_filter_each_figure_comes_from(log_dir):
    """A graph run's printed NIS are the loop's ESKF's; its accuracy rows the graph's."""
    log = read_log(log_dir)
    res = fake_run_log(log, backend="graph")
    timing = {**res.info["timing"], "imu_samples": 2001.0, "run_s": 2.0}
    summary = summarize(res.solution, res.measurements, res.events, truth=log.truth,
                        timing=timing, settings={"backend": "graph", "solver": "batch"})  # fmt: skip
    text = format_summary(summary).splitlines()
    first_nis = next(i for i, line in enumerate(text) if line.startswith("NIS "))
    assert "navigation loop's ESKF" in text[first_nis - 1]
    assert any(line.startswith("vs reference      graph batch solution") for line in text)
    # the IMU samples filtered, not the solution's rows
    assert summary["imu_samples"] == 2001 and summary["timing"]["imu_samples_per_s"] == 1000.5
    eskf = format_summary({**summary, "settings": {"backend": "eskf"}})
    assert "navigation loop's ESKF" not in eskf and "vs reference      eskf solution" in eskf


def test_docs_outputs_page_holds_the_schema():
    page = (ROOT / "docs" / "outputs.md").read_text(encoding="utf-8")
    assert schema_markdown() in page  # regenerate with polins.io.schema.schema_markdown()


def test_real_run_end_to_end(log_dir, tmp_path, capsys):
    """The real navigation loop: exit 0, every solution column documented in schema.json."""
    out = tmp_path / "run"
    assert _fuse(log_dir, out, "--no-plots") == 0
    schema = json.loads((out / "schema.json").read_text())
    assert all(v["unit"] for v in schema["solution.csv"].values())
    assert read_stamp(out)["settings"]["status"] == "ok"


def test_heading_plot_does_not_spike_where_the_reference_wraps():
    """The 720 deg spike: the reference wrapped past 360 deg where the fused line did not."""
    t = np.linspace(0.0, 10.0, 501)
    heading = np.mod(359.0 + 0.4 * t, 360.0)  # crosses North at t = 2.5 s
    fused = np.mod(heading - 0.3, 360.0)  # ... and the fused heading at t = 3.25 s
    solution = pd.DataFrame({"t": t, "heading_deg": fused})
    truth = pd.DataFrame({"t": t, "roll": 0.0, "pitch": 0.0,
                          "yaw": np.radians(90.0 - heading)})  # fmt: skip
    m = measurement_frame([{"t": 5.0, "ok": True, "heading_deg": 1.2}])
    s = heading_plot_series(solution, m, truth)
    assert np.all(np.abs(np.diff(s["fused"])) < 1.0)  # unwrapped
    assert np.max(np.abs(s["ref"] - s["fused"])) < 1.0  # no 360/720 deg jump
    assert abs(s["mh"][0] - s["mh_fused"][0]) < 1.0


def test_report_plots_are_written_and_readable(log_dir, tmp_path, fake_loop, monkeypatch):
    import matplotlib.pyplot as plt

    figures = []
    real_close = plt.close
    monkeypatch.setattr(plt, "close", lambda fig=None: figures.append(fig) or real_close(fig))
    assert _fuse(log_dir, tmp_path / "run") == 0
    heading = figures[0]
    top, resid = heading.axes
    for ax in heading.axes:
        assert "[" in ax.get_ylabel() and ax.get_legend() is not None
    assert resid.get_xlabel() == "time t [s]"
    fused = next(line for line in top.lines if line.get_label() == "fused heading")
    meas = next(line for line in top.lines if line.get_label() == "polarization measurements")
    assert fused.get_zorder() > meas.get_zorder() and meas.get_markersize() <= 3
    # the settled 3-sigma band (0.3 deg) fills a visible part of the panel, and the whole
    # band is inside it (symlog beyond the settled band)
    y0, y1 = (resid.transData.transform([(0.0, v)])[0, 1] for v in (-0.3, 0.3))
    p0, p1 = (resid.transData.transform([(0.0, v)])[0, 1] for v in resid.get_ylim())
    assert (y1 - y0) / (p1 - p0) > 0.1
    band = resid.collections[0].get_paths()[0].vertices[:, 1]
    lo, hi = resid.get_ylim()
    assert lo <= band.min() and band.max() <= hi
    # the heading axis is a compass: 0..360 deg, every line inside it
    assert top.get_ylim() == (0.0, 360.0) and "0..360" in top.get_ylabel()
    for line in top.lines:
        y = np.asarray(line.get_ydata(), dtype=float)
        assert np.all((y[np.isfinite(y)] >= 0.0) & (y[np.isfinite(y)] < 360.0)), line.get_label()


def test_demo_colours_are_fixed_per_method(tmp_path, monkeypatch):
    import matplotlib.pyplot as plt
    from matplotlib.colors import to_rgba

    from polins.sim.paper import _COLORS, ESTIMATORS, plot_reproduction, run_demo

    _, runs = run_demo(downscale=8, n_images=3, progress=False, occluder=False)
    figures = []
    real_close = plt.close
    monkeypatch.setattr(plt, "close", lambda fig=None: figures.append(fig) or real_close(fig))
    plot_reproduction(runs[0], tmp_path)
    labels = {e.label: e.key for e in ESTIMATORS}
    seen = 0
    for fig in figures:
        for ax in fig.axes:
            for line in ax.lines:
                key = next((k for lab, k in labels.items()
                            if line.get_label().startswith(lab)), None)  # fmt: skip
                if key in _COLORS:
                    assert to_rgba(line.get_color()) == to_rgba(_COLORS[key]), line.get_label()
                    seen += 1
    assert seen >= 7  # 4 methods in Fig. 6, 4 + 3 in the two panels of Fig. 7


# ----------------------------------------------------------------------------- item 5
def test_event_buffer_stays_bounded_under_a_million_duplicates():
    buf = EventBuffer(maxlen=1000)
    for _ in range(1_000_000):
        buf.add(1.0, "imu-out-of-order", "duplicate IMU sample dropped")
    assert len(buf) == 1000 and buf.dropped == 999_000
    assert buf.counts["imu-out-of-order"] == 1_000_000
    assert len(buf.drain()) == 1000 and len(buf) == 0


# ----------------------------------------------------------------------------- item 4
HEADING_SITE = ["--time", "2023-09-05T15:06+08:00", "--lat", "45.6234", "--lon", "126.7264"]


def test_paths_outside_the_log_are_skipped_and_reported(log_dir, tmp_path, fake_loop):
    dst = tmp_path / "log"
    shutil.copytree(log_dir, dst)
    index = pd.read_csv(dst / "images.csv")
    index.loc[3, "file"] = "../../../../etc/hostname"
    index.loc[4, "file"] = "/etc/hostname"
    index.to_csv(dst / "images.csv", index=False)
    log = read_log(dst)
    assert [e[1] for e in log.events] == ["path-outside-log"] * 2
    assert "/etc/hostname" not in map(str, log.images.files) and len(log.images) == 49
    followed = read_log(dst, allow_outside_paths=True)
    assert followed.events == () and len(followed.images) == 51
    assert _fuse(dst, tmp_path / "run") == 0
    events = pd.read_csv(tmp_path / "run" / "events.csv")
    assert (events["kind"] == "path-outside-log").sum() == 2


def test_heading_and_fuse_refuse_the_same_image_types(log_dir, tmp_path, capsys):
    """Found: ``polins heading`` accepted a float32 TIFF that ``fuse`` refused."""
    import cv2

    from polins.io import ImageReadError, load_raw

    raw = load_raw(log_dir / "images" / "000010.png")
    tiff = tmp_path / "float.tiff"
    cv2.imwrite(str(tiff), raw.astype(np.float32))
    with pytest.raises(ImageReadError, match="expected uint8 or uint16"):
        load_raw(tiff)  # the reader of the navigation loop
    code = main(["heading", str(tiff), "--camera", str(log_dir / "camera.toml"), *HEADING_SITE])
    err = capsys.readouterr().err
    assert code == 2 and "expected uint8 or uint16 pixels, got float32" in err


def test_12_bit_image_stored_shifted_is_named(log_dir, tmp_path, capsys):
    """Found: a 12-bit image stored x16 was silently counted as saturated."""
    from polins.io import load_raw, write_image

    raw = load_raw(log_dir / "images" / "000010.png")
    write_image(tmp_path / "shifted.png", (raw.astype(np.uint16) << 4).astype(np.uint16))
    with pytest.warns(NoiseModelWarning, match="measured noise is 1[5-9]"):  # 16x in DN
        main(["heading", str(tmp_path / "shifted.png"), "--camera",
              str(log_dir / "camera.toml"), *HEADING_SITE])  # fmt: skip
    err = capsys.readouterr().err
    assert "exceed the camera's 12-bit range" in err and "shifted left by 4 bits (x16)" in err


@pytest.mark.parametrize(
    ("line", "new", "message"),
    [("fov_max_deg = 80.0", "fov_max_deg = 1.396", "in radians it would be 80.0 deg"),
     ("fx_superpixel = 32.3875", "fx_superpixel = 3238.75", "lens.fx_superpixel")],
)  # fmt: skip
def test_implausible_camera_file_is_named(log_dir, tmp_path, capsys, line, new, message):
    """Found: ``fov_max_deg = 1.396`` (radians) ran with yaw NaN for the whole run, exit 0."""
    text = (log_dir / "camera.toml").read_text()
    assert line in text
    (tmp_path / "cam.toml").write_text(text.replace(line, new))
    code = main(["heading", str(log_dir / "images" / "000010.png"), "--camera",
                 str(tmp_path / "cam.toml"), *HEADING_SITE])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1


# ----------------------------------------------------------------------------- [filter] table and --set
def test_cli_overrides_the_manifest_filter_table(log_dir, tmp_path, fake_loop):
    dst = tmp_path / "log"
    shutil.copytree(log_dir, dst)
    with open(dst / "manifest.toml", "a") as fh:
        fh.write("\n[filter]\nnhc_std = 0.05\ngate_prob = 0.99\n")
    model = tmp_path / "my-imu.toml"
    model.write_text((ROOT / "models" / "imus" / "fins-paper.toml").read_text())
    assert _fuse(dst, tmp_path / "a") == 0
    assert _fuse(dst, tmp_path / "b", "--set", "nhc_std=0.2", "--set", "align_s=2",
                 "--scale-factors", "--imu", str(model)) == 0  # fmt: skip
    manifest_only, overridden = fake_loop
    assert (manifest_only.aiding.nhc_std, manifest_only.gating.gate_prob) == (0.05, 0.99)
    assert manifest_only.imu.name == "mems-typical" and manifest_only.noise.scale_factors == "auto"
    assert overridden.aiding.nhc_std == 0.2 and overridden.initial.align_s == 2.0
    assert overridden.gating.gate_prob == 0.99
    assert overridden.noise.scale_factors and overridden.imu.name == "fins-paper"
    stamp = read_stamp(tmp_path / "b")["settings"]["filter"]
    assert stamp["nhc_std"] == 0.2 and stamp["scale_factors"] is True


def test_stream_events_are_bounded_and_counted():
    """Found: 1M duplicate IMU samples grew RSS from 251 MB to 600 MB (unbounded events)."""
    import polins
    from polins.loop import LoopOptions, NavigationStream

    cam = polins.load_camera("paper-table1").downscaled(8)
    nav = NavigationStream(cam, polins.load_imu("mems-typical"), site=(45.6, 126.7, 0.0),
                           epoch_utc="2023-09-05T07:06Z",
                           options=LoopOptions(max_table_rows=500))  # fmt: skip
    t = 0.005 * np.arange(200)
    nav.add_imu_many(t, np.zeros((200, 3)), np.tile([0.0, 0.0, 9.8], (200, 1)))
    n = 50_000  # duplicates of the last sample (1M take 7 s: the buffer test above)
    nav.add_imu_many(np.full(n, t[-1]), np.zeros((n, 3)), np.tile([0.0, 0.0, 9.8], (n, 1)))
    assert nav.counts["imu-out-of-order"] == n and nav.events_dropped == n - 500
    assert len(nav.drain_events()) == 500 and len(nav.drain_events()) == 0


def test_tune_command_writes_a_model_that_loads(log_dir, tmp_path, capsys):
    """``polins tune`` on a log: a tuned IMU file that load_imu reads, the report printed;
    an unknown parameter is one line and exit 2 before any work."""
    out = tmp_path / "tuned.toml"
    argv = ["tune", str(log_dir / "manifest.toml"), "--params", "yaw_std_scale", "--out", str(out),
            "--workers", "1", "--quiet"]  # fmt: skip
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "yaw_std_scale" in printed and f"wrote {out}" in printed
    tuned = polins.load_imu(out)
    assert tuned.name == "tuned" and tuned.gyro_arw == polins.load_imu("mems-typical").gyro_arw
    bad = ["tune", str(log_dir / "manifest.toml"), "--params", "gyro_arx", "--out", str(out)]
    assert main(bad) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "gyro_arx" in err


def test_docs_outputs_page_lists_the_filter_options(capsys):
    assert main(["fuse", "--list-options"]) == 0
    listing = capsys.readouterr().out.rstrip("\n")
    page = (ROOT / "docs" / "outputs.md").read_text(encoding="utf-8")
    assert listing in page  # regenerate with polins fuse --list-options
