"""IMU models from static recordings: Allan fit, plot, plausible ranges, the BROAD sensor."""

import dataclasses
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import polins
from polins.errors import UserInputError
from polins.io.model_files import imu_model_toml
from polins.models import ModelFileError
from polins.sim.imu import IMU_COLUMNS, imu_errors
from polins.tuning import (
    NoiseTerms,
    fit_allan,
    imu_model_from_static,
    model_random_walk,
    plot_allan,
)

BROAD = Path(__file__).parent / "data" / "broad"
RATE_HZ = 100.0


def _static_ideal(rate_hz: float, seconds: float) -> pd.DataFrame:
    n = int(rate_hz * seconds)
    data = np.zeros((n, 7))
    data[:, 0] = np.arange(n) / rate_hz
    data[:, 6] = 9.80665
    return pd.DataFrame(data, columns=IMU_COLUMNS)


@pytest.fixture(scope="module")
def truth_model():
    """A MEMS model whose random walks show within the record (crossover near 70 s)."""
    base = polins.load_imu("mems-typical")
    return dataclasses.replace(base, gyro_bias_rw=base.gyro_bias_rw * 10.0)


@pytest.fixture(scope="module")
def static_recording(truth_model):
    """1.5 h at 100 Hz from the simulator's error model (independent of the estimator)."""
    measured, _ = imu_errors(_static_ideal(RATE_HZ, 5400.0), truth_model, np.random.default_rng(16))
    return measured


@pytest.fixture(scope="module")
def static_fit(static_recording):
    return imu_model_from_static(static_recording, name="sim-static", grade="mems")


def test_static_recording_recovers_the_noise_model(
    static_recording, static_fit, truth_model, tmp_path, capsys
):
    """``polins imu-model`` on a static recording, then load_imu, recovers the noise model."""
    from polins.cli import main
    from polins.io import write_imu

    model, fit = static_fit
    csv = write_imu(tmp_path / "static.csv", static_recording)
    path, png = tmp_path / "my-imu.toml", tmp_path / "allan.png"
    assert main(["imu-model", str(csv), "--out", str(path), "--plot", str(png)]) == 0
    assert "wrote" in capsys.readouterr().out and png.is_file()
    loaded = polins.load_imu(path)
    assert loaded.gyro_arw == pytest.approx(model.gyro_arw, rel=1e-6)  # the CLI is the function
    assert imu_model_toml(loaded).count("[gyro]") == 1
    assert loaded.gyro_arw / truth_model.gyro_arw == pytest.approx(1.0, abs=0.10)
    assert loaded.accel_vrw / truth_model.accel_vrw == pytest.approx(1.0, abs=0.10)
    assert 0.5 < loaded.gyro_bias_rw / truth_model.gyro_bias_rw < 2.0
    assert 0.5 < loaded.accel_bias_rw / truth_model.accel_bias_rw < 2.0
    assert loaded.sample_rate_hz == pytest.approx(RATE_HZ)
    for sensor in (fit.gyro, fit.accel):
        assert sensor.combined.identified["white"] and sensor.combined.identified["random_walk"]
        assert not sensor.combined.identified["bias_instability"]  # none was simulated
    lo, hi = fit.gyro.combined.white_ci
    assert lo < truth_model.gyro_arw < hi
    assert fit.notes[0].startswith("gyro.arw_deg_per_sqrt_h = ")
    assert any("grade-typical" in n for n in fit.comment_lines())


def test_plot_is_written(static_fit, tmp_path):
    path = plot_allan(static_fit[1], tmp_path / "plots" / "allan.png")
    assert path.is_file() and 20_000 < path.stat().st_size < 300_000


def test_short_record_leaves_the_random_walk_unidentified(truth_model):
    measured, _ = imu_errors(_static_ideal(RATE_HZ, 60.0), truth_model, np.random.default_rng(3))
    model, fit = imu_model_from_static(measured)
    gyro = fit.gyro.combined
    assert not gyro.identified["random_walk"]
    # the model carries the upper bound, which cannot be below the truth here
    assert model.gyro_bias_rw == pytest.approx(gyro.random_walk_ci[1])
    assert model.gyro_bias_rw > truth_model.gyro_bias_rw


def test_bias_instability_becomes_a_random_walk_at_the_floor():
    terms = NoiseTerms(
        white=1e-4,
        white_ci=(0.9e-4, 1.1e-4),
        bias_instability=1e-5,
        bias_instability_ci=(5e-6, 2e-5),
        random_walk=0.0,
        random_walk_ci=(0.0, 1e-7),
        tau_floor=300.0,
    )
    value, how = model_random_walk(terms)
    # the random walk whose Allan line touches the flicker floor 0.664 B at tau_floor
    k_b = 0.6643 * 1e-5 * np.sqrt(3.0 / 300.0)
    assert value == pytest.approx(np.hypot(1e-7, k_b), rel=1e-3)
    assert value * np.sqrt(300.0 / 3.0) == pytest.approx(0.6643e-5, rel=0.02)
    assert "upper bound" in how and "bias instability" in how


@pytest.mark.slow
def test_confidence_intervals_cover_the_truth():
    """95 % intervals: the white and random-walk terms are covered in most of 20 records."""
    n_white = n_walk = 0
    rng = np.random.default_rng(7)
    white, walk, n = 1e-4, 2e-6, int(RATE_HZ * 3600)
    for _ in range(20):
        x = white * np.sqrt(RATE_HZ) * rng.standard_normal(n)
        x += np.cumsum(walk / np.sqrt(RATE_HZ) * rng.standard_normal(n))
        _, terms = fit_allan([x], RATE_HZ)
        n_white += terms.white_ci[0] <= white <= terms.white_ci[1]
        n_walk += terms.random_walk_ci[0] <= walk <= terms.random_walk_ci[1]
    assert n_white >= 16 and n_walk >= 16


@pytest.mark.parametrize(
    ("change", "match"),
    [
        (lambda d: d.assign(gx=np.degrees(d.gx) + 60.0), "deg/s"),
        (lambda d: d.assign(az=d.az / 9.80665), "in g"),
        (lambda d: d.drop(columns="ay"), "lacks columns"),
        (lambda d: d.assign(t=d.t + np.where(d.index == 150, 0.003, 0.0)), "t = 1.49 s to 1.503 s"),
        (lambda d: d.assign(gz=np.where(d.index == 5, np.nan, d.gz)), "NaN"),
    ],
)
def test_bad_static_input_is_one_line(change, match, truth_model):
    measured, _ = imu_errors(_static_ideal(RATE_HZ, 20.0), truth_model, np.random.default_rng(1))
    with pytest.raises(UserInputError, match=match) as err:
        imu_model_from_static(change(measured))
    assert "\n" not in str(err.value)


def test_a_record_with_gaps_is_split_where_the_samples_are_missing(truth_model):
    """The gaps' places are named, and the pieces are the segments a list would give."""
    measured, _ = imu_errors(_static_ideal(200.0, 120.0), truth_model, np.random.default_rng(2))
    t = measured["t"]
    pieces = [measured[t <= 5.395], measured[(t >= 38.505) & (t <= 80.0)], measured[t >= 80.5]]
    model, fit = imu_model_from_static(pd.concat(pieces))
    split = [n for n in fit.notes if n.startswith("split at")]
    assert split == ["split at 2 gap(s) in the samples: 5.395 -> 38.505 s, 80 -> 80.5 s"]
    assert fit.n_segments == 3
    as_list, _ = imu_model_from_static(pieces)
    assert model.gyro_arw == as_list.gyro_arw and model.accel_bias_rw == as_list.accel_bias_rw


def test_a_short_record_is_refused_for_its_length(truth_model):
    """5.4 s cannot bound a MEMS gyro random walk: the message says so and how long to record."""
    measured, _ = imu_errors(_static_ideal(200.0, 5.4), truth_model, np.random.default_rng(1))
    with pytest.raises(UserInputError, match=r"too short.*gyro random walk.*5\.4 s") as err:
        imu_model_from_static(measured)
    need = float(re.search(r"record at least (\d+) s", str(err.value)).group(1))
    # ten crossover times of the measured white noise and a mid-range MEMS random walk
    k_mid = np.sqrt(0.01 * 1000.0) * np.radians(1.0) / 3600.0 / 60.0
    assert need == pytest.approx(10 * np.sqrt(3) * truth_model.gyro_arw / k_mid, rel=0.05)
    assert "units" not in str(err.value) and "grade right" not in str(err.value)
    measured, _ = imu_errors(_static_ideal(200.0, 1.0), truth_model, np.random.default_rng(1))
    with pytest.raises(UserInputError, match="record longer"):  # 200 samples, pieces of 64
        imu_model_from_static(measured.iloc[::4])


def test_the_allan_legend_is_the_model_file(static_fit, truth_model, tmp_path):
    """Each legend value is the written file's, a bound marked as a bound."""
    from polins.tuning.plot import legend_labels

    short, _ = imu_errors(_static_ideal(RATE_HZ, 60.0), truth_model, np.random.default_rng(3))
    for model, fit in (static_fit, imu_model_from_static(short)):
        path = tmp_path / "m.toml"
        path.write_text(imu_model_toml(model, fit.comment_lines()))
        values = polins.load_imu(path).toml_values()
        gyro, accel = legend_labels(fit)
        for label, table, key in [
            (gyro["white"], "gyro", "arw_deg_per_sqrt_h"),
            (gyro["walk"], "gyro", "bias_rw_deg_per_h_per_sqrt_h"),
            (accel["white"], "accel", "vrw_m_per_s_per_sqrt_h"),
            (accel["walk"], "accel", "bias_rw_mg_per_sqrt_h"),
        ]:
            shown = float(re.search(r"(?:=|<=) ([0-9.e+-]+)", label).group(1))
            assert shown == pytest.approx(values[table][key], rel=5e-4), label
        bound = not fit.gyro.combined.identified["random_walk"]
        assert ("<=" in gyro["walk"] and "upper bound" in gyro["walk"]) == bound
    assert bound  # the second fit (60 s) gives a bound, the first (1.5 h) a fitted value


def test_imu_model_takes_several_files(truth_model, tmp_path, capsys):
    """``polins imu-model a.csv b.csv``: each file a segment, pooled as a list would be."""
    from polins.cli import main
    from polins.io import write_imu

    rng = np.random.default_rng(5)
    parts = [imu_errors(_static_ideal(RATE_HZ, 30.0), truth_model, rng)[0] for _ in range(2)]
    files = [str(write_imu(tmp_path / f"{n}.csv", p)) for n, p in zip("ab", parts, strict=True)]
    out = tmp_path / "two.toml"
    assert main(["imu-model", *files, "--out", str(out)]) == 0
    assert "in 2 segment(s)" in out.read_text()
    expected, _ = imu_model_from_static(parts)
    assert polins.load_imu(out).gyro_arw == pytest.approx(expected.gyro_arw, rel=1e-9)


def test_fit_implausible_for_the_grade_is_refused(truth_model):
    measured, _ = imu_errors(_static_ideal(RATE_HZ, 20.0), truth_model, np.random.default_rng(1))
    with pytest.raises(UserInputError, match=r"gyro\.arw_deg_per_sqrt_h.*'navigation'"):
        imu_model_from_static(measured, grade="navigation")


# ----------------------------------------------------------------------------- loader ranges
def _imu_text(**replace: str) -> str:
    text = polins.load_imu("mems-typical").path.read_text()
    for old, new in replace.items():
        assert old in text
        text = text.replace(old, new)
    return text


@pytest.mark.parametrize(
    ("old", "new", "key"),
    [
        ("arw_deg_per_sqrt_h = 0.34", "arw_deg_per_sqrt_h = 340", "gyro.arw_deg_per_sqrt_h"),
        ("arw_deg_per_sqrt_h = 0.34", "arw_deg_per_sqrt_h = 0.0059", "gyro.arw_deg_per_sqrt_h"),
        ("bias_mg = 2.0", "bias_mg = 2000.0", "accel.bias_mg"),
        ('grade = "mems"', 'grade = "navigation"', "gyro.arw_deg_per_sqrt_h"),
    ],
)
def test_loader_names_the_implausible_key(tmp_path, old, new, key):
    path = tmp_path / "imu.toml"
    path.write_text(_imu_text(**{old: new}))
    with pytest.raises(ModelFileError) as err:
        polins.load_imu(path)
    msg = str(err.value)
    assert str(path) in msg and f"'{key}'" in msg and "expected" in msg and "\n" not in msg


def test_loader_accepts_zero_to_switch_a_term_off(tmp_path):
    path = tmp_path / "imu.toml"
    path.write_text(_imu_text(**{"scale_factor_ppm = 1000.0": "scale_factor_ppm = 0.0"}))
    assert polins.load_imu(path).gyro_scale_factor == 0.0


def test_shipped_models_are_plausible_and_round_trip():
    for name in polins.models.shipped_models("imus"):
        model = polins.load_imu(name)
        model.check_plausible()
        values = model.toml_values()
        assert set(values) == {"gyro", "accel"}
        extra = {"misalignment_mrad", "misalignment_corr_s"} if model.gyro_misalignment else set()
        assert (
            set(values["gyro"])
            == {
                "arw_deg_per_sqrt_h",
                "bias_deg_per_h",
                "bias_rw_deg_per_h_per_sqrt_h",
                "scale_factor_ppm",
            }
            | extra
        )


def test_accelerometer_misalignment_round_trips_and_widens_the_bias_turn_on(tmp_path):
    model = dataclasses.replace(polins.load_imu("mems-typical"), accel_misalignment=4e-3)
    path = tmp_path / "imu.toml"
    path.write_text(imu_model_toml(model))
    back = polins.load_imu(path)
    assert back.accel_misalignment == pytest.approx(4e-3)
    # 2 mg turn-on and 4 mrad of 1 g in quadrature: 4.47 mg
    assert back.accel_bias_turn_on == pytest.approx(np.hypot(2.0, 4.0) * 9.80665e-3)


# ----------------------------------------------------------------------------- BROAD sensor
def broad_rest_segments(margin_s: float = 2.0) -> list[pd.DataFrame]:
    """The rests (moving == 0) before and after the motion of both trials, minus a margin."""
    segments = []
    for trial in ("trial_02", "trial_15"):
        df = pd.read_csv(BROAD / f"{trial}.csv.gz")
        t = df["t"].to_numpy()
        moving = np.flatnonzero(df["moving"].to_numpy() == 1)
        segments.append(df[t < t[moving[0]] - margin_s])
        segments.append(df[t > t[moving[-1]] + margin_s])
    return segments


def test_broad_model_loads_and_matches_its_rest_segments():
    shipped = polins.load_imu("broad-aktos-t")
    assert shipped.grade == "mems"
    assert shipped.sample_rate_hz == pytest.approx(1.0 / 0.0035)
    segments = broad_rest_segments()
    assert all((s["moving"] == 0).all() for s in segments)
    model, fit = imu_model_from_static(segments, grade="mems")
    assert fit.n_segments == 4 and 130.0 < fit.duration_s < 150.0
    assert model.sample_rate_hz == pytest.approx(shipped.sample_rate_hz, rel=1e-9)
    assert model.gyro_arw / shipped.gyro_arw == pytest.approx(1.0, abs=0.10)
    assert model.accel_vrw / shipped.accel_vrw == pytest.approx(1.0, abs=0.10)
    # the two sessions' turn-on biases (RMS over segments and axes) stay within the 1-sigma
    assert np.degrees(model.gyro_bias) == pytest.approx(0.23, abs=0.02)
    assert shipped.gyro_bias > model.gyro_bias
    # 40-s rests cannot show the bias random walk: the shipped value stays below the bound
    assert not fit.gyro.combined.identified["random_walk"]
    assert shipped.gyro_bias_rw <= fit.gyro.combined.random_walk_ci[1]
    assert shipped.accel_bias_rw >= fit.accel.combined.random_walk_ci[1]
