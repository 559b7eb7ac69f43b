"""Robust start, recovery and data faults of the fusion (docs/filter.md, docs/faults.md):
a bad first heading never locks the filter, outliers are still rejected, and faulty rows
or IMU samples give a finite solution and an event instead of an abort or NaN."""

import dataclasses
import functools
import warnings

import numpy as np
import pandas as pd
import pytest

import polins
from polins.frames import rot_nb_from_euler, wrap_angle
from polins.fusion import build_filter, run_fusion
from polins.fusion.config import FuseConfig
from polins.fusion.eskf.acquisition import consensus
from polins.fusion.inputs import validate_imu
from polins.fusion.sky_states import link_acquired_yaw
from polins.io.model_files import imu_model_toml
from polins.sim.imu import ideal_imu, imu_errors
from polins.sim.trajectory import ugv_drive
from polins.site import Site

SITE = Site(lat_deg=45.6234, lon_deg=126.7264, alt_m=148.74)
YAW_STD = np.radians(0.3)
DURATION = 60.0


@functools.cache
def drive(seed):
    """A 60 s MEMS UGV drive with a 5 Hz heading = truth + N(0, 0.3 deg)."""
    model = polins.load_imu("mems-typical")
    rng = np.random.default_rng(seed)
    traj = ugv_drive(duration_s=DURATION, rng=rng)
    imu, _ = imu_errors(ideal_imu(traj), model, rng)
    truth = traj.truth_frame()
    tm = np.arange(0.2, DURATION, 0.2)
    yaw = np.interp(tm, truth["t"], np.unwrap(truth["yaw"]))
    meas = pd.DataFrame({"t": tm, "yaw": wrap_angle(yaw + rng.normal(0.0, YAW_STD, tm.size))})
    meas["yaw_std"] = YAW_STD
    return model, traj, imu, truth, meas


def fuse(imu, meas, model, rot_nb0=None, backend="eskf", **options):
    config = FuseConfig.from_options(None, imu_model=model, site=SITE, output_rate_hz=2.0)
    config = FuseConfig.from_options(config, **options)
    res = run_fusion(imu, meas, backend, rot_nb0=rot_nb0, config=config)
    # the measurement rows' records (the zero-rate updates at rest have their own, §12.1)
    heads = res.updates[res.updates["name"] != "zaru"].reset_index(drop=True)
    return dataclasses.replace(res, updates=heads)


def yaw_z(solution, truth):
    """Times, yaw errors [rad] and yaw errors / sigma of the solution rows."""
    k = np.searchsorted(truth["t"].to_numpy(), solution["t"].to_numpy() - 1e-9)
    err = wrap_angle(solution["yaw"].to_numpy() - truth["yaw"].to_numpy()[k])
    return solution["t"].to_numpy(), err, err / solution["yaw_std"].to_numpy()


# ----------------------------------------------------------------------------- acquisition
def test_consensus_picks_the_agreeing_group():
    s = np.full(5, 0.01)
    mean, std, members = consensus(np.array([np.pi, 0.10, 0.11, 0.09, -2.0]), s, 3)
    assert members.tolist() == [1, 2, 3]
    assert mean == pytest.approx(0.10) and std == pytest.approx(0.01 / np.sqrt(3))
    assert consensus(np.array([np.pi, 0.1, 1.0]), s[:3], 2) is None
    # the wrap at +-pi: offsets on either side of it agree
    mean, _, members = consensus(np.array([np.pi - 0.01, -np.pi + 0.01, 0.5]), s[:3], 2)
    assert members.tolist() == [0, 1] and abs(wrap_angle(mean - np.pi)) < 1e-12


def test_acquired_yaw_keeps_the_tilt_part_of_its_error():
    """A tilt-coupled heading sets the yaw with the error ``n - a . dtheta_tilt``
    (docs/filter.md §7.1): the acquired covariance is that linear map's, checked against
    the sample covariance of 200,000 drawn errors (a common tilt part treated as noise
    left the forward heading at 66-77 % within 3 sigma on some MEMS drives)."""
    rng = np.random.default_rng(4)
    root = rng.standard_normal((6, 6)) * 1e-3
    P = root @ root.T
    gain, noise_std = np.array([0.4, -0.55]), 2e-4
    x = rng.multivariate_normal(np.zeros(6), P, size=200_000)
    x[:, 2] = noise_std * rng.standard_normal(len(x)) - x[:, 0:2] @ gain
    P_in = P.copy()
    P_in[2, :] = P_in[:, 2] = 0.0
    P_in[2, 2] = noise_std**2
    P_out = link_acquired_yaw(P_in, {}, tilt_gain=gain)
    scale = np.sqrt(np.outer(np.diag(P_out), np.diag(P_out)))
    np.testing.assert_allclose(np.cov(x.T) / scale, P_out / scale, atol=0.01)
    assert P_out[2, 2] > 3.0 * noise_std**2  # the tilt part dominates here
    np.testing.assert_array_equal(link_acquired_yaw(P_in, {}, tilt_gain=np.zeros(2)), P_in)


@pytest.mark.parametrize("offset_deg", [30.0, 180.0])
def test_bad_first_heading_does_not_lock_the_filter(offset_deg):
    # a first heading that set the yaw with its 0.3 deg sigma would make the gate reject every
    # later one, ending 22-28 (30 deg off) or 172-178 deg off: the yaw is acquired by consensus
    model, _, imu, truth, meas = drive(0)
    bad = meas.copy()
    bad.loc[0, "yaw"] = wrap_angle(bad.loc[0, "yaw"] + np.radians(offset_deg))
    res = fuse(imu, bad, model)
    t, err, z = yaw_z(res.solution, truth)
    aligned = np.isfinite(err)
    assert t[aligned][0] <= 1.0  # three agreeing headings after the bad one
    assert np.abs(z[aligned]).max() < 3.0 and np.degrees(np.abs(err[t >= 30.0])).max() < 0.5
    upd = res.updates
    assert not upd["accepted"].iloc[0] and "disagrees" in upd["reason"].iloc[0]
    assert upd["reason"].iloc[1].startswith("used for the yaw acquisition (3 of 4 agree)")
    assert res.events.empty  # no re-acquisition, no fault


@pytest.mark.parametrize("offset_deg", [30.0, 180.0])
def test_wrong_initial_yaw_is_reacquired(offset_deg):
    # a given initial attitude off in yaw, with a 1 deg sigma: the gate rejects the good
    # headings until reacquire_after of them agree
    model, _, imu, truth, meas = drive(1)
    y, p, r = truth[["yaw", "pitch", "roll"]].iloc[0]
    rot0 = rot_nb_from_euler(y + np.radians(offset_deg), p, r)
    res = fuse(imu, meas, model, rot_nb0=rot0)
    t, err, z = yaw_z(res.solution, truth)
    ev = res.events
    assert ev["kind"].tolist() == ["yaw-reacquired"] and ev["t"].iloc[0] == pytest.approx(1.0)
    assert "re-acquired: 5 consecutive rejections" in ev["detail"].iloc[0]
    assert (res.updates["reason"] == "re-acquired: 5 consecutive rejections").sum() == 1
    assert np.abs(z[t > ev["t"].iloc[0]]).max() < 3.0
    assert np.degrees(np.abs(err[t >= 30.0])).max() < 0.5


def test_stream_recovers_from_a_bad_first_heading():
    # the streaming filter (what NavigationStream runs) holds the headings the same way
    model, _, imu, truth, meas = drive(2)
    filt = build_filter(float(imu["t"].iloc[0]), 0.005, imu_model=model, site=SITE)
    for row in meas.itertuples():
        yaw = row.yaw + (np.pi if row.Index == 0 else 0.0)
        filt.add_measurement(row.t, yaw=wrap_angle(yaw), yaw_std=row.yaw_std)
    half = imu[imu["t"] <= 30.0]
    filt.propagate_many(half["t"].to_numpy(), half[["gx", "gy", "gz"]].to_numpy(),
                        half[["ax", "ay", "az"]].to_numpy())  # fmt: skip
    row = filt.state().row()
    true_yaw = np.interp(row["t"], truth["t"], np.unwrap(truth["yaw"]))
    err = wrap_angle(row["yaw"] - true_yaw)
    assert abs(err) < 3.0 * row["yaw_std"] and abs(np.degrees(err)) < 0.5
    reasons = [r.reason for r in filt.records[:5]]
    assert reasons[0].endswith("disagrees") and reasons[1].startswith("used for the yaw")


@pytest.mark.parametrize("backend", ["eskf", "graph"])
def test_outliers_are_still_rejected(backend):
    # 10 % of the headings off by 30 to 180 deg (either sign), the first one among them
    model, _, imu, truth, meas = drive(3)
    rng = np.random.default_rng(7)
    bad = meas.copy()
    idx = np.sort(np.concatenate([[0], rng.choice(np.arange(1, len(bad)), 30, replace=False)]))
    size = rng.uniform(30.0, 180.0, idx.size) * rng.choice([-1.0, 1.0], idx.size)
    bad.loc[idx, "yaw"] = wrap_angle(bad.loc[idx, "yaw"] + np.radians(size))
    res = fuse(imu, bad, model, backend=backend)
    upd = res.updates
    assert not upd.loc[idx, "accepted"].any()  # all of them (>= 99 % required)
    good = np.setdiff1d(np.arange(len(bad)), idx)
    assert upd.loc[good, "accepted"].mean() > 0.99
    assert res.events.empty  # no re-acquisition
    _, _, z = yaw_z(res.solution, truth)
    assert np.nanmax(np.abs(z)) < 3.5


def test_acquisition_options_are_checked():
    with pytest.raises(ValueError, match="acquire_k <= acquire_n <= reacquire_after"):
        FuseConfig(acquire_k=4, acquire_n=3)
    with pytest.raises(ValueError, match="acquire_k must be an integer >= 1"):
        FuseConfig(acquire_k=0)


# ----------------------------------------------------------------------------- faults
def test_unusable_sigma_rejects_its_row():
    # an update with yaw_std = inf, if applied, would make the solution NaN to the end, every
    # later update "accepted" with NIS NaN
    model, _, imu, truth, meas = drive(4)
    bad = meas.copy()
    bad.loc[20, "yaw_std"] = np.inf
    bad.loc[40, "yaw_std"] = 0.0
    bad.loc[60, "yaw_std"] = -0.01
    res = fuse(imu, bad, model)
    upd = res.updates
    assert upd.loc[20, "reason"] == "invalid yaw_std=inf: a 1-sigma must be finite and > 0"
    assert upd.loc[40, "reason"].startswith("invalid yaw_std=0")
    assert upd.loc[60, "reason"].startswith("invalid yaw_std=-0.01")
    assert not upd.loc[[20, 40, 60], "accepted"].any()
    assert np.isfinite(upd.loc[upd["accepted"], "nis"]).iloc[3:].all()
    sol = res.solution
    assert np.isfinite(sol[["yaw", "yaw_std", "roll", "pitch"]].iloc[2:].to_numpy()).all()
    _, _, z = yaw_z(sol, truth)
    assert np.nanmax(np.abs(z)) < 3.5


def check_gap_skipped(res, meas):
    """The 3 s IMU gap of 7-10 s reported once, and the 16 headings inside it skipped with
    an event and a reason each (both backends)."""
    ev = res.events
    gap = ev[ev["kind"] == "imu-gap"]
    assert len(gap) == 1 and gap["detail"].iloc[0].startswith("IMU gap of 3.0")
    inside = meas["t"].between(6.996, 10.004)  # the samples around the gap: 6.995, 10.005
    assert (ev["kind"] == "measurement-in-gap").sum() == inside.sum() == 16
    upd = res.updates
    assert upd.loc[inside.to_numpy(), "reason"].str.startswith("inside an IMU gap").all()
    return inside.to_numpy()


def test_imu_gap_with_images_inside():
    # a 3 s gap with images inside: bridged with events, a finite solution to the end
    model, _, imu, truth, meas = drive(5)
    gapped = imu[(imu["t"] < 7.0) | (imu["t"] > 10.0)]
    res = fuse(gapped, meas, model)
    check_gap_skipped(res, meas)
    sol = res.solution
    assert not sol["t"].between(7.001, 9.999).any()
    t, err, z = yaw_z(sol, truth)
    assert np.isfinite(err[t > 0.7]).all() and np.nanmax(np.abs(z)) < 3.5
    # the smoother runs across the inflated step
    _, _, z = yaw_z(fuse(gapped, meas, model, smooth=True).solution, truth)
    assert np.isfinite(z[t > 0.7]).all() and np.abs(z[t > 0.7]).max() < 3.5
    # a gap up to max_gap_s is bridged without an event
    assert "imu-gap" not in fuse(gapped, meas, model, max_gap_s=3.5).events["kind"].tolist()


def test_impossible_imu_samples_are_dropped():
    # a gyro sample of 1e300 would stop the strapdown ("fixed-point iteration did not
    # converge"), an accelerometer sample of 1e300 too ("zero norm quaternions"): dropped
    model, _, imu, truth, meas = drive(6)
    bad = imu.copy()
    bad.loc[1500, "gx"] = 1e300
    bad.loc[2500, "az"] = 1e300
    bad.loc[3500, "gy"] = 40.0  # beyond the MEMS gyro's 2000 deg/s
    bad.loc[4500, "ay"] = np.nan
    with warnings.catch_warnings():  # and no numpy overflow warning reaches the user
        warnings.simplefilter("error", RuntimeWarning)
        res = fuse(bad, meas, model)
    ev = res.events
    assert ev["kind"].tolist() == ["imu-out-of-range"] * 3 + ["imu-nonfinite"]
    np.testing.assert_allclose(ev["t"], imu["t"].iloc[[1500, 2500, 3500, 4500]])
    _, _, z = yaw_z(res.solution, truth)
    assert np.isfinite(res.solution[["roll", "pitch", "ve"]].to_numpy()).all()
    assert np.nanmax(np.abs(z)) < 3.5


def test_fast_motion_is_not_taken_for_deg_per_s():
    # real MEMS trials turn at 11-19 rad/s: within the 2000 deg/s full scale
    model, _, imu, _, _ = drive(0)
    fast = imu.copy()
    fast.loc[1000:1400, "gz"] = 15.0  # 2 s of a 15 rad/s spin (> 1 % of the samples)
    assert validate_imu(fast, model=model).t.size == len(imu)
    with pytest.raises(ValueError, match="looks like deg/s"):
        validate_imu(fast.assign(gz=np.degrees(fast["gz"])), model=model)
    # the range comes from the IMU model: a 300 deg/s gyro refuses the spin
    small = polins.models.ImuModel(**{**model.__dict__, "gyro_range": np.radians(300.0)})
    with pytest.raises(ValueError, match=r"full scale 5\.24 rad/s"):
        validate_imu(fast, model=small)


def test_imu_range_keys_round_trip(tmp_path):
    model = polins.load_imu("mems-typical")
    assert model.gyro_range is None
    assert model.full_scale() == pytest.approx((np.radians(2000.0), 16 * 9.80665))
    assert polins.load_imu("fins-paper").full_scale()[0] == pytest.approx(np.radians(1000.0))
    ranged = polins.models.ImuModel(
        **{**model.__dict__, "gyro_range": np.radians(450.0), "accel_range": 8 * 9.80665}
    )
    text = imu_model_toml(ranged)
    assert "range_deg_per_s = 450" in text and "range_g = 8" in text
    path = tmp_path / "ranged.toml"
    path.write_text(text)
    back = polins.load_imu(path)
    assert back.full_scale() == pytest.approx((np.radians(450.0), 8 * 9.80665))


def test_yaw_given_then_no_acquisition_needed():
    # a given attitude that is right: no hold, the first heading is an ordinary update
    model, _, imu, truth, meas = drive(0)
    y, p, r = truth[["yaw", "pitch", "roll"]].iloc[0]
    res = fuse(imu, meas, model, rot_nb0=rot_nb_from_euler(y, p, r))
    assert res.updates["accepted"].mean() > 0.99 and res.events.empty


def test_slow_turns_in_deg_per_s_are_caught_by_the_headings():
    # An undeclared deg/s gyro on a slow drive stays below the full scale; the headings show
    # that it turns 57x too much. The right units pass the same check.
    model, _, imu, _, meas = drive(0)
    deg = imu.assign(**{c: np.degrees(imu[c]) for c in ("gx", "gy", "gz")})
    assert np.percentile(np.linalg.norm(deg[["gx", "gy", "gz"]], axis=1), 99) < 35.0
    validate_imu(deg, model=model)  # the full-scale check alone lets it through
    with pytest.raises(ValueError, match=r"turns 5\d(\.\d)? times as much .* looks like deg/s"):
        fuse(deg, meas, model)
    res = fuse(imu, meas, model)
    assert np.isfinite(res.solution["yaw"].iloc[2:]).all()  # set by the first consensus
