"""Filter tuning from a log: innovation statistics and maximum-likelihood noise parameters (docs/tuning.md)."""

import dataclasses
import math
import re
import warnings

import numpy as np
import pandas as pd
import pytest

import polins
from polins.errors import UserInputError
from polins.fusion import FuseConfig, run_fusion
from polins.io.model_files import imu_model_toml
from polins.sim.imu import ideal_imu, imu_errors
from polins.sim.trajectory import ugv_drive
from polins.site import PAPER_SITE
from polins.tuning import innovation_stats, negative_log_likelihood, tune, with_values

DURATION_S = 60.0
TABLE_STD = math.radians(0.01)  # what the compass claims
FLOOR_DEG = 0.1  # what it lacks: the true noise is hypot(TABLE_STD, FLOOR)


@pytest.fixture(scope="module")
def drive():
    """A 60 s MEMS drive (ARW 3.4 deg/sqrt(h)) with 10 Hz yaw measurements, and its model."""
    base = polins.load_imu("mems-typical")
    model = dataclasses.replace(base, gyro_arw=base.gyro_arw * 10.0)
    traj = ugv_drive(duration_s=DURATION_S, rate_hz=100.0, rng=np.random.default_rng(1))
    rng = np.random.default_rng(2)
    imu, _ = imu_errors(ideal_imu(traj, earth_rotation=False), model, rng)
    truth = traj.truth_frame()
    t = np.arange(0.1, DURATION_S, 0.1)
    yaw = np.interp(t, truth["t"], np.unwrap(truth["yaw"]))
    noise = rng.normal(0.0, math.hypot(TABLE_STD, math.radians(FLOOR_DEG)), t.size)
    meas = pd.DataFrame({"t": t, "yaw": polins.wrap_angle(yaw + noise), "yaw_std": TABLE_STD})
    config = FuseConfig(imu_model=model, site=PAPER_SITE, output_rate_hz=1.0)
    return imu, meas, config


def test_updates_carry_innovation_and_its_variance(drive):
    imu, meas, config = drive
    upd = run_fusion(imu, meas, config=config).updates
    used = upd[upd["accepted"] & np.isfinite(upd["nis"]) & (upd["name"] == "yaw")]
    nu = np.array([v[0] for v in used["innovation"]])
    S = np.array([v[0] for v in used["innovation_var"]])
    np.testing.assert_allclose(nu**2 / S, used["nis"], rtol=1e-12)
    assert (S > TABLE_STD**2).all()


def test_stats_see_a_too_small_r_and_recommend_its_floor(drive):
    imu, meas, config = drive
    config = config.replace(gate_prob="off")  # a gate truncates the NIS
    stats = innovation_stats(run_fusion(imu, meas, config=config).updates)
    yaw = stats["yaw"]
    assert len(meas) - 10 < yaw.n < len(meas) and yaw.dim == 1  # all but the yaw acquisition
    assert yaw.nis_mean > 10 and not yaw.consistent and "too small" in yaw.verdict
    # one step with this run's gains: R too small, the filter followed the noise, so the
    # floor is over-estimated (up to sqrt(2)); with the true floor the run is consistent
    assert FLOOR_DEG < math.degrees(yaw.sigma_floor) < 1.5 * FLOOR_DEG
    c, m = with_values(config, meas, {"yaw_floor_deg": FLOOR_DEG})
    again = innovation_stats(run_fusion(imu, m, config=c).updates)["yaw"]
    assert again.consistent and again.white, again
    lo, hi = again.nis_band
    assert 0.85 < lo < 1.0 < hi < 1.15


def test_likelihood_peaks_near_the_true_floor(drive):
    imu, meas, config = drive

    def nll(floor_deg):
        c, m = with_values(config, meas, {"yaw_floor_deg": floor_deg})
        return negative_log_likelihood(run_fusion(imu, m, config=c).updates)

    assert nll(FLOOR_DEG) < min(nll(FLOOR_DEG / 3), nll(FLOOR_DEG * 3)) - 100


@pytest.mark.slow
def test_tune_recovers_identifiable_and_names_unidentifiable(drive):
    imu, meas, config = drive
    model = config.imu
    truth = {"gyro_arw": model.gyro_arw, "yaw_floor_deg": FLOOR_DEG, "accel_vrw": model.accel_vrw}
    start = {"gyro_arw": 3 * truth["gyro_arw"], "yaw_floor_deg": FLOOR_DEG / 3,
             "accel_vrw": 3 * truth["accel_vrw"]}  # fmt: skip
    wrong = dataclasses.replace(model, gyro_arw=start["gyro_arw"], accel_vrw=start["accel_vrw"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the site is given: no warning
        res = tune(imu, meas, dataclasses.replace(config, imu_model=wrong),
                   params=tuple(truth), initial={"yaw_floor_deg": start["yaw_floor_deg"]})  # fmt: skip
    assert res.initial == pytest.approx(start)
    assert res.identifiable == {"gyro_arw": True, "yaw_floor_deg": True, "accel_vrw": False}, (
        res.report()
    )
    assert res.unidentifiable == ["accel_vrw"]
    for p in ("gyro_arw", "yaw_floor_deg"):
        err = abs(math.log(res.values[p] / truth[p]))
        assert err < max(math.log(1.3), 2 * res.cr_sigma_log[p]), (p, res.values[p], truth[p])
    assert res.values["accel_vrw"] == start["accel_vrw"]  # not invented
    assert res.config.imu.gyro_arw == res.values["gyro_arw"]
    before, after = res.stats_before["yaw"], res.stats_after["yaw"]
    assert not before.consistent and after.consistent
    assert res.nll_after < res.nll_before - 100
    assert "accel_vrw" in res.report() and "kept at start" in res.report()
    # the gyro ARW started 3x off: the report says it moved beyond its Cramér-Rao interval
    assert res.moved("gyro_arw") and not res.moved("accel_vrw")
    assert re.search(r"gyro_arw moved x0\.[234]", res.report()) and "effective one" in res.report()


def test_unknown_parameter_is_one_line(drive):
    imu, meas, config = drive
    with pytest.raises(UserInputError, match="gyro_arx"):
        tune(imu, meas, config, params=("gyro_arx",))
    with pytest.raises(UserInputError, match="must be > 0"):
        tune(imu, meas, config, params=("gyro_arw",), initial={"gyro_arw": 0.0})


def test_tune_runs_the_filter_that_fuses_with_the_odometer(drive):
    """The likelihood is that of the filter ``polins fuse`` runs: with the log's odometer."""
    from polins.sim.vehicle import forward_speed

    imu, meas, config = drive
    traj = ugv_drive(duration_s=DURATION_S, rate_hz=100.0, rng=np.random.default_rng(1))
    odometry = pd.DataFrame({"t": traj.t[::10], "speed": forward_speed(traj)[::10]})
    imu, meas, odometry = (x[x["t"] < 20.0] for x in (imu, meas, odometry))  # 20 s suffice
    res = tune(imu, meas, config, params=("yaw_floor_deg",), odometry=odometry)
    for run in (res.before, res.after):
        assert (run.updates["name"] == "odo").sum() > 0.9 * len(odometry)
    assert not (run_fusion(imu, meas, config=config).updates["name"] == "odo").any()


def test_every_tuned_value_acts_in_the_filter_that_fuses(drive, tmp_path):
    """The tuned file (the IMU model with its [filter] table), given to ``run_fusion`` as
    ``polins fuse --imu tuned.toml`` gives it, reproduces the tuned run exactly."""
    imu, meas, config = drive
    res = tune(imu, meas, config, params=("yaw_floor_deg",))
    assert set(res.fuse_options()) == {"yaw_floor_deg"} and res.identifiable["yaw_floor_deg"]
    path = tmp_path / "tuned.toml"
    path.write_text(imu_model_toml(res.tuned_model(name="tuned"), res.comment_lines()))
    assert dict(polins.load_imu(path).filter_options) == res.fuse_options()
    fused = run_fusion(imu, meas, config=config.replace(imu_model=path))
    np.testing.assert_array_equal(fused.updates["nis"], res.after.updates["nis"])
    assert res.stats_after["yaw"].consistent
