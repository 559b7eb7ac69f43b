"""The tuned file (an IMU model whose ``[filter]`` table every configuration built with it applies), the default parameters and the sandwich sigma of polins tune (docs/tuning.md)."""

import dataclasses
import math

import numpy as np
import pandas as pd
import pytest

import polins
from polins.errors import UserInputError
from polins.fusion import FuseConfig
from polins.fusion.config import config_from_manifest
from polins.io.model_files import imu_model_toml
from polins.site import PAPER_SITE
from polins.tuning.likelihood import central_hessian, sandwich_sigma, score_information
from polins.tuning.parameters import default_params

TUNED = (("yaw_std_scale", 0.8), ("nhc_std", 0.01), ("standstill_std", "off"))


@pytest.fixture
def tuned_path(tmp_path):
    base = polins.load_imu("mems-typical")
    model = dataclasses.replace(base, name="tuned", gyro_arw=base.gyro_arw * 1.5,
                                filter_options=TUNED)  # fmt: skip
    path = tmp_path / "tuned.toml"
    path.write_text(imu_model_toml(model))
    return path


def test_the_filter_table_round_trips_and_acts_in_every_configuration(tuned_path):
    model = polins.load_imu(tuned_path)
    assert model.filter_options == TUNED
    assert model.gyro_arw == pytest.approx(polins.load_imu("mems-typical").gyro_arw * 1.5)
    assert polins.load_imu(tuned_path.write_text(imu_model_toml(model)) and tuned_path) == model

    config = FuseConfig(tuned_path, PAPER_SITE, vehicle="ground")
    assert config.noise.yaw_std_scale == 0.8
    assert (config.nhc_sigma, config.standstill_sigma) == (0.01, None)
    # an explicit option wins over the file's; replace keeps what was set
    assert FuseConfig(tuned_path, nhc_std=0.02).nhc_sigma == 0.02
    assert config.replace(yaw_std_scale=1.0).noise.yaw_std_scale == 1.0
    assert config.replace(gate_prob=0.99).noise.yaw_std_scale == 0.8
    # another configuration takes the tuned model: with its options, under the call's own
    plain = FuseConfig("mems-typical", PAPER_SITE, vehicle="ground")
    assert plain.replace(imu_model=model).noise.yaw_std_scale == 0.8
    assert plain.replace(imu_model=model, nhc_std=0.03).nhc_sigma == 0.03
    assert plain.replace(imu_model=model).options() == config.options()


def test_the_tuned_file_wins_over_the_manifest_filter_table(tuned_path):
    """A tuned file was fitted on top of the manifest's options: its values act, the
    manifest's other options stay."""
    manifest = {"vehicle": {"kind": "ground"},
                "filter": {"yaw_std_scale": 2.0, "gate_prob": 0.99}}  # fmt: skip
    config = config_from_manifest(manifest, polins.load_imu(tuned_path), PAPER_SITE)
    assert config.noise.yaw_std_scale == 0.8 and config.gate_probability == 0.99
    assert config.aiding.vehicle == "ground" and config.nhc_sigma == 0.01


@pytest.mark.parametrize(
    ("table", "match"),
    [("nhc_sdt = 0.1", r"tuned\.toml: unknown key 'filter\.nhc_sdt'; did you mean 'filter\.nhc_std'"),
     ("nhc_std = -1.0", r"tuned\.toml: table \[filter\]: nhc_std"),
     ("imu_model = 'x'", r"tuned\.toml: unknown key 'filter\.imu_model'")],
)  # fmt: skip
def test_a_bad_filter_table_is_one_line_naming_the_file(tuned_path, table, match):
    text = tuned_path.read_text().split("[filter]")[0] + f"[filter]\n{table}\n"
    tuned_path.write_text(text)
    with pytest.raises(UserInputError, match=match) as info:
        FuseConfig(tuned_path)
    assert "\n" not in str(info.value)


def test_default_parameters_are_the_gyro_and_the_fused_sigmas():
    ground = FuseConfig("mems-typical", PAPER_SITE, vehicle="ground")
    assert default_params(ground, odometry=True) == (
        "gyro_arw", "yaw_std_scale", "nhc_std", "odometer_std")  # fmt: skip
    assert default_params(ground.replace(nhc_std="off")) == ("gyro_arw", "yaw_std_scale")
    assert default_params(FuseConfig("mems-typical", PAPER_SITE)) == ("gyro_arw", "yaw_std_scale")


@pytest.mark.parametrize("rho", [0.0, 0.9])
def test_the_sandwich_sigma_sees_correlated_innovations(rho):
    """The log-variance of AR(1) samples: the Cramér-Rao sigma assumes independent terms;
    the sandwich's is larger by sqrt((1 + rho^2) / (1 - rho^2)) (the variance of a mean
    of x^2 whose autocorrelation is rho^2k)."""
    rng = np.random.default_rng(5)
    n = 20000
    x = np.empty(n)
    x[0] = rng.normal()
    for k in range(1, n):
        x[k] = rho * x[k - 1] + math.sqrt(1.0 - rho**2) * rng.normal()

    def terms(theta):
        nll = 0.5 * (math.log(2.0 * math.pi) + theta[0] + x**2 * math.exp(-theta[0]))
        return pd.DataFrame({"name": "x", "t": np.arange(n, dtype=float), "k": 0, "nll": nll})

    theta = np.array([math.log(np.mean(x**2))])
    step = 0.2
    H = central_hessian(lambda th: float(terms(th)["nll"].sum()), theta, step)
    assert H[0, 0] == pytest.approx(n / 2, rel=0.01)
    J = score_information([terms(theta + step)], [terms(theta - step)], step)
    ratio = sandwich_sigma(H, J)[0] / math.sqrt(1.0 / H[0, 0])
    expected = math.sqrt((1 + rho**2) / (1 - rho**2))
    assert ratio == pytest.approx(expected, rel=0.35), (ratio, expected)
