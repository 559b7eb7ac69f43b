"""The fusion's options: "off" turns off every option that can be off, through Python, ``--set``
and a manifest's ``[filter]`` table alike; "auto" is the automatic choice; one parser; a name
that is not an option fails with one line naming what replaces it."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import polins
from polins.cli.fuse import filter_changes
from polins.errors import UserInputError
from polins.fusion import run_fusion
from polins.fusion.config import (
    OFF,
    OPTION_FIELDS,
    FuseConfig,
    config_from_manifest,
    scaled_measurement_noise,
)
from polins.io import read_log, write_log
from polins.site import Site

SITE = Site(45.6234, 126.7264, 148.74)


def _can_be_off(name: str) -> bool:
    meta = OPTION_FIELDS[name].metadata
    return OFF in meta["special"] or meta["kind"] == "flag"


def _resolved(config: FuseConfig) -> FuseConfig:
    """The configuration of a run that has odometry and prior columns (what "auto" sees)."""
    return config.resolve(priors=True, odometry=True)


def _no_clock_off(c: FuseConfig) -> bool:
    """Off: not on, and a table of sun azimuths only is refused instead of turning it on."""
    try:
        c.resolve(sun_azimuth_only=True)
    except UserInputError as exc:
        return "no_clock=off" in str(exc) and not c.no_clock
    return False


# option -> (base options under which its default or "auto" is on, "it is off")
OFF_CASES: dict[str, tuple[dict[str, object], Callable[[FuseConfig], bool]]] = {
    "nhc_std": ({"vehicle": "ground"}, lambda c: c.nhc_sigma is None),
    "standstill_std": ({"vehicle": "ground"}, lambda c: c.standstill_sigma is None),
    "odometer_std": ({}, lambda c: _resolved(c).odometer_sigma is None),
    "mount_std": ({"mount_std": 0.01}, lambda c: c.mount_sigma is None),
    "lever_std": ({"lever_std": 0.1}, lambda c: c.lever_sigma is None),
    "scale_factors": ({}, lambda c: not c.use_scale_factors),
    "use_sun": ({}, lambda c: c.gating.use_sun is False),
    "tilt_coupling": ({}, lambda c: not _resolved(c).tilt_coupling),
    "gate_prob": ({}, lambda c: c.gate_probability is None),
    "earth_rate": ({}, lambda c: not c.mechanize_earth_rate),
    "site_std": ({"site_std": 1e-5}, lambda c: c.site_sigma is None),
    "no_clock": ({}, _no_clock_off),
    "heading_bias_std": ({}, lambda c: c.heading_bias == OFF and c.heading_bias_sigma is None),
    "smooth": ({"smooth": True}, lambda c: c.output.smooth is False),
}


def test_every_option_that_can_be_off_has_a_case():
    assert set(OFF_CASES) == {n for n in OPTION_FIELDS if _can_be_off(n)}


@pytest.fixture(scope="module")
def log_text(tmp_path_factory):
    """A small log (one image, 2 s of static IMU) and its manifest's text."""
    folder = tmp_path_factory.mktemp("log")
    t = np.arange(0.0, 2.0, 0.01)
    imu = pd.DataFrame({"t": t, "gx": 0.0, "gy": 0.0, "gz": 0.0, "ax": 0.0, "ay": 0.0,
                        "az": 9.80665})  # fmt: skip
    cam = polins.load_camera("paper-table1").downscaled(8)
    raw = np.zeros(cam.shape, dtype=np.uint16)
    manifest = write_log(folder, epoch_utc="2023-09-05T07:00:00Z", camera=cam,
                         imu_model="mems-typical", lat_deg=SITE.lat_deg, lon_deg=SITE.lon_deg,
                         alt_m=SITE.alt_m, imu=imu, images=[(0.5, raw)])  # fmt: skip
    return manifest, manifest.read_text()


def _toml(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return f'"{value}"' if isinstance(value, str) else repr(value)


def _entry_points(base: dict[str, object], name: str, manifest: Path, text: str):
    """The configuration with ``name`` off, from Python, ``--set`` and ``[filter]``."""
    python = FuseConfig("mems-typical", SITE, **{**base, name: "off"})
    args = argparse.Namespace(set=[f"{name}=off"], smooth=False, scale_factors=False, nhc=None)
    cli = FuseConfig("mems-typical", SITE, **base).replace(**filter_changes(args))
    table = "".join(f"{k} = {_toml(v)}\n" for k, v in {**base, name: "off"}.items())
    manifest.write_text(text + f"\n[filter]\n{table}")
    from_manifest = FuseConfig.from_log(read_log(manifest))
    return {"python": python, "--set": cli, "[filter]": from_manifest}


@pytest.mark.parametrize("name", sorted(OFF_CASES))
def test_off_turns_the_option_off_from_every_entry_point(name, log_text):
    base, is_off = OFF_CASES[name]
    default = FuseConfig("mems-typical", SITE, **base)
    assert not is_off(default), f"{name}: the case's base must have it on"
    configs = _entry_points(base, name, *log_text)
    for where, config in configs.items():
        assert is_off(config), (name, where)
        assert config == configs["python"], (name, where)  # one parser, one value


def _nhc_rows(config: FuseConfig) -> int:
    """NHC and zero-velocity rows of a 3 s static ground run's update log."""
    t = np.arange(0.0, 3.0, 0.01)
    imu = pd.DataFrame({"t": t, "gx": 0.0, "gy": 0.0, "gz": 0.0, "ax": 0.0, "ay": 0.0,
                        "az": 9.80665})  # fmt: skip
    names = run_fusion(imu, None, config=config).updates["name"]
    return int(np.isin(names, ["nhc"]).sum()), int(np.isin(names, ["zupt"]).sum())


@pytest.mark.parametrize("name", ["nhc_std", "standstill_std"])
def test_off_leaves_no_update_rows(name, log_text):
    base = {"vehicle": "ground"}
    on = _nhc_rows(FuseConfig("mems-typical", SITE, **base))
    assert min(on) > 10  # auto: both on for a ground vehicle
    column = 0 if name == "nhc_std" else 1
    for where, config in _entry_points(base, name, *log_text).items():
        rows = _nhc_rows(config)
        assert rows[column] == 0 and rows[1 - column] == on[1 - column], (name, where)


@pytest.mark.parametrize(
    ("value", "message"),
    [(None, "nhc_std=None: give 'auto' or 'off'"), (math.inf, "nhc_std=inf: give 'auto' or 'off'"),
     (-1.0, "nhc_std=-1.0: expected a number > 0, 'auto', 'off'"),
     ("fast", "nhc_std='fast': expected a number")],
)  # fmt: skip
def test_a_bad_value_is_one_line_naming_the_option(value, message):
    with pytest.raises(UserInputError) as info:
        FuseConfig(nhc_std=value)
    assert str(info.value).startswith(message) and "\n" not in str(info.value)


def test_auto_and_numbers_as_text_parse_as_in_python():
    text = FuseConfig(nhc_std="0.1", gate_prob="0.99", earth_rate="on", att_std0="0.01",
                      mount_rpy="0.1,0,-0.1", acquire_k="2")  # fmt: skip
    assert text == FuseConfig(nhc_std=0.1, gate_prob=0.99, earth_rate=True, att_std0=0.01,
                              mount_rpy=(0.1, 0.0, -0.1), acquire_k=2)  # fmt: skip
    assert text.initial.att_std0 == (0.01,) * 3
    assert FuseConfig(nhc_std="AUTO").aiding.nhc_std == "auto"
    assert FuseConfig().options()["earth_rate"] == "auto"


@pytest.mark.parametrize(
    ("name", "replacement"),
    [("cov_step_s", "COV_STEP_S"), ("time_tol_s", "TIME_TOL_S"), ("site_assumed", "no site"),
     ("integration_std", "INTEGRATION_STD"), ("max_gate_rounds", "MAX_GATE_ROUNDS"),
     ("reset_interval_s", "RESET_INTERVAL_S"), ("nhc_rate_hz", "NHC_RATE_HZ"),
     ("zupt_std", "with_standstill"), ("stationary", "with_standstill")],
)  # fmt: skip
def test_an_old_name_fails_with_one_line_naming_the_new(name, replacement, log_text):
    with pytest.raises(UserInputError, match=replacement):
        FuseConfig(**{name: 1.0})
    args = argparse.Namespace(set=[f"{name}=1"], smooth=False, scale_factors=False, nhc=None)
    with pytest.raises(UserInputError, match=replacement):
        filter_changes(args)
    manifest, _ = log_text
    with pytest.raises(UserInputError, match=replacement) as info:
        config_from_manifest({"filter": {name: 1.0}}, "mems-typical", SITE, manifest)
    assert "\n" not in str(info.value)


def test_parts_and_flat_names_are_one_configuration():
    flat = FuseConfig(vehicle="ground", nhc_std=0.1, solver="isam2", smooth=True)
    parts = FuseConfig(
        aiding=polins.Aiding(vehicle="ground", nhc_std=0.1),
        graph=polins.GraphSolver(solver="isam2"),
        output=polins.Output(smooth=True),
    )
    assert flat == parts and flat.replace(nhc_std="off").aiding.nhc_std == OFF
    assert flat.changes() == {"imu_model": "mems-typical", "vehicle": "ground", "nhc_std": 0.1,
                              "solver": "isam2", "smooth": True}  # fmt: skip
    with pytest.raises(UserInputError, match="graph backend only"):
        flat.check_backend("eskf")


def test_lat_lon_shorthand_is_the_site_everywhere():
    assert FuseConfig(lat_deg=45.0, lon_deg=126.0).site == Site(45.0, 126.0, 0.0)
    with pytest.raises(UserInputError, match="both lat_deg and lon_deg"):
        FuseConfig(lat_deg=45.0)
    with pytest.raises(UserInputError, match="not both"):
        FuseConfig(site=SITE, lat_deg=45.0, lon_deg=126.0)


def test_measurement_noise_scale_and_floor():
    meas = pd.DataFrame({"t": [1.0, 2.0], "yaw": [0.1, 0.2], "yaw_std": [0.01, 0.02]})
    assert scaled_measurement_noise(meas, FuseConfig()) is meas
    out = scaled_measurement_noise(meas, FuseConfig(yaw_std_scale=0.81, yaw_floor_deg=0.5))
    floor = math.radians(0.5)
    np.testing.assert_allclose(out["yaw_std"], np.hypot(0.81 * meas["yaw_std"], floor), rtol=1e-15)
    assert meas["yaw_std"].tolist() == [0.01, 0.02]  # the caller's table is not touched


def _static_case(n_s: float = 6.0):
    """A static IMU (100 Hz) and heading rows at 2 Hz after the levelling second."""
    t = np.arange(0.0, n_s, 0.01)
    g = 9.80665
    imu = pd.DataFrame({"t": t, "gx": 0.0, "gy": 0.0, "gz": 0.0, "ax": 0.0, "ay": 0.0, "az": g})
    tm = np.arange(1.5, n_s, 0.5)
    yaw = 0.3 + 0.01 * np.random.default_rng(0).standard_normal(tm.size)
    return imu, pd.DataFrame({"t": tm, "yaw": yaw, "yaw_std": 0.01})


def test_a_tuned_measurement_noise_is_applied_by_fuse_and_the_stream():
    """``yaw_std_scale`` / ``yaw_floor_deg`` (what ``polins tune`` fits) act as the rows'
    own sigmas would: in ``run_fusion`` and in ``NavigationStream`` (the loop of ``polins
    fuse``), set from Python, ``--set`` and ``[filter]`` alike."""
    imu, meas = _static_case()
    args = argparse.Namespace(set=["yaw_std_scale=3", "yaw_floor_deg=0.2"], smooth=False,
                              scale_factors=False, nhc=None)  # fmt: skip
    tuned = FuseConfig("mems-typical", SITE).replace(**filter_changes(args))
    assert tuned == FuseConfig("mems-typical", SITE, yaw_std_scale=3.0, yaw_floor_deg=0.2)
    own = meas.assign(yaw_std=np.hypot(3.0 * meas["yaw_std"], math.radians(0.2)))
    a = run_fusion(imu, meas, config=tuned).solution
    b = run_fusion(imu, own, config=FuseConfig("mems-typical", SITE)).solution
    pd.testing.assert_frame_equal(a, b)
    assert a["yaw_std"].iloc[-1] > 1.5 * run_fusion(imu, meas, config=FuseConfig(
        "mems-typical", SITE)).solution["yaw_std"].iloc[-1]  # fmt: skip

    def streamed(config: FuseConfig, rows: pd.DataFrame) -> float:
        stream = polins.NavigationStream(polins.load_camera("paper-table1"),
                                         config.imu, config=config,
                                         epoch_utc="2023-09-05T07:00:00Z")  # fmt: skip
        data = imu.to_numpy()
        stream.add_imu_many(data[:300, 0], data[:300, 1:4], data[:300, 4:7])
        for row in rows.itertuples(index=False):
            stream.add_measurement(row.t, yaw=row.yaw, yaw_std=row.yaw_std)
        stream.add_imu_many(data[300:, 0], data[300:, 1:4], data[300:, 4:7])
        stream.flush()
        nav = stream.state().nav
        assert nav is not None
        return float(np.sqrt(nav.att_cov[2, 2]))

    base = FuseConfig("mems-typical", SITE)
    assert streamed(tuned, meas) == pytest.approx(streamed(base, own), rel=1e-12)


def test_one_imu_gap_length_for_the_loop_and_the_filter():
    with pytest.raises(UserInputError, match="is FuseConfig's max_gap_s") as info:
        polins.LoopOptions(max_imu_gap_s=0.1)
    assert "\n" not in str(info.value)
    assert FuseConfig(max_gap_s="auto").gap_s is None and FuseConfig(max_gap_s=0.2).gap_s == 0.2


def test_zero_velocity_at_known_times_is_rows_of_the_table():
    """One way to ask for zero velocity at known times: ``zupt_std`` rows (no heading row)."""
    from polins.fusion.vehicle import with_standstill

    imu, meas = _static_case()
    rows = with_standstill(meas, [2.25, 3.25, 4.25], 0.01)
    assert list(rows["t"]) == sorted(rows["t"]) and len(rows) == len(meas) + 3
    config = FuseConfig("mems-typical", SITE, acquire_k=1, acquire_n=1)
    updates = run_fusion(imu, rows, config=config).updates
    assert (updates["name"] == "zupt").sum() == 3 and updates["accepted"].all()
    assert (updates["name"] == "yaw").sum() == len(meas)  # the zero-velocity rows are no yaw
