"""Real consumer-MEMS data (BROAD trials, CC BY 4.0, tests/data/broad/README.md) through the ESKF.

The IMU model ``broad-aktos-t`` was built from the trials' rest segments and the sensor's
published cross-axis figure before any scored run (docs/imu-model.md). The aiding: a 1 Hz
heading (truth + N(0, 0.5 deg)), zero-velocity updates at 10 Hz while
the IMU rests, the initial attitude from the truth. The options are the defaults: for a
MEMS model scale-factor states, the rotation-proportional attitude noise of the model's
misalignment, and the Earth rate mechanized at the given site (TU Berlin).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

import polins
from polins.frames import wrap_angle
from polins.fusion import FuseConfig, run_fusion

BROAD = Path(__file__).parent / "data" / "broad"
SITE = {"lat_deg": 52.512, "lon_deg": 13.327, "alt_m": 40.0}
HEADING_STD = np.radians(0.5)


def broad_trial(trial: str, seed: int = 7):
    """IMU table, measurement table and truth Euler angles of a BROAD trial."""
    d = pd.read_csv(BROAD / f"trial_{trial}.csv.gz")
    d = d.iloc[int(np.flatnonzero(np.isfinite(d["qw"].to_numpy()))[0]) :].reset_index(drop=True)
    t = d["t"].to_numpy()
    ok = np.isfinite(d["qw"].to_numpy())
    quat = np.where(ok[:, None], d[["qx", "qy", "qz", "qw"]].to_numpy(), [0.0, 0.0, 0.0, 1.0])
    ypr = Rotation.from_quat(quat).as_euler("ZYX")
    imu = pd.DataFrame(
        {"t": t, **{c: d[c].to_numpy() for c in ("gx", "gy", "gz", "ax", "ay", "az")}}
    )
    rng = np.random.default_rng(seed)
    k = np.searchsorted(t, np.arange(t[0] + 1.0, t[-1], 1.0) - 1e-9)
    k = k[ok[k] & (np.abs(ypr[k, 1]) < np.radians(80.0))]  # yaw undefined near pitch 90 deg
    heading = pd.DataFrame({"t": t[k], "yaw": wrap_angle(ypr[k, 0] + rng.normal(0.0, HEADING_STD, k.size)),
                            "yaw_std": HEADING_STD})  # fmt: skip
    rest = np.arange(0, t.size, round(0.1 / np.median(np.diff(t))))
    rest = rest[d["moving"].to_numpy()[rest] == 0]
    zupt = pd.DataFrame({"t": t[rest], "zupt_std": 0.01})
    meas = heading.merge(zupt, on="t", how="outer").sort_values("t").reset_index(drop=True)
    truth = pd.DataFrame(
        {"t": t, "yaw": ypr[:, 0], "pitch": ypr[:, 1], "roll": ypr[:, 2], "ok": ok}
    )
    return imu, meas, truth, Rotation.from_quat(quat[0])


def score(sol: pd.DataFrame, truth: pd.DataFrame):
    """Per-angle RMS(err/sigma) and % within 3 sigma, away from |pitch| > 60 deg."""
    k = np.searchsorted(truth["t"].to_numpy(), sol["t"].to_numpy() - 1e-9)
    tr = truth.iloc[k]
    keep = tr["ok"].to_numpy() & (np.abs(tr["pitch"].to_numpy()) < np.radians(60.0))
    out = {}
    for c in ("yaw", "pitch", "roll"):
        err = wrap_angle(sol[c].to_numpy() - tr[c].to_numpy())[keep]
        z = err / sol[f"{c}_std"].to_numpy()[keep]
        out[c] = (float(np.sqrt(np.mean(z**2))), float(100 * np.mean(np.abs(z) <= 3.0)),
                  float(np.degrees(np.sqrt(np.mean(err**2)))))  # fmt: skip
    return out


@pytest.mark.parametrize("trial", ["02", "15"])
def test_broad_trials_are_accurate_and_consistent_with_the_defaults(trial):
    imu, meas, truth, rot0 = broad_trial(trial)
    config = FuseConfig.from_options(imu_model="broad-aktos-t", output_rate_hz=2.0, **SITE)
    res = run_fusion(imu, meas, rot_nb0=rot0, config=config)
    sol, upd = res.solution, res.updates
    zupt = upd[upd["name"] == "zupt"]
    assert zupt["accepted"].mean() > 0.99  # no lock-out of the rests after the motion
    for angle, (rms, within3, err_deg) in score(sol, truth).items():
        assert rms <= 1.5 and within3 >= 95.0, (trial, angle, rms, within3)
        assert err_deg < 1.5, (trial, angle, err_deg)  # the motion turns ~400-700 deg


def test_broad_without_the_misalignment_noise_is_overconfident():
    # The same trial with the model's misalignment set to zero: the attitude error grows with
    # the angle turned and the sigmas no longer cover it (the reason for the model key).
    import dataclasses

    imu, meas, truth, rot0 = broad_trial("02")
    model = dataclasses.replace(polins.load_imu("broad-aktos-t"), gyro_misalignment=0.0)
    sol = polins.fuse(imu, meas, imu_model=model, rot_nb0=rot0, output_rate_hz=2.0, **SITE)
    worst = max(rms for rms, _, _ in score(sol, truth).values())
    assert worst > 1.5


@pytest.mark.parametrize("trial", ["02", "15"])
def test_broad_without_zero_velocity_updates(trial):
    """Headings only (no zero-velocity rows): the standstill detector's zero-rate updates
    at the rests find the turn-on gyro biases (0.1-0.5 deg/s); yaw / pitch / roll
    RMS(err/sigma) 1.11 / 0.40 / 0.82 (trial 02) and 1.09 / 0.27 / 0.61 (trial 15), errors
    0.22 / 0.39 / 0.86 and 0.23 / 0.61 / 0.92 deg (docs/filter.md §12.3); without them
    0.33 / 2.45 / 4.74 and 0.29 / 3.41 / 2.18 deg. The pitch sigma is conservative: the
    model's misalignment and scale-factor terms are its largest published values."""
    imu, meas, truth, rot0 = broad_trial(trial)
    heading = meas[meas["yaw"].notna()][["t", "yaw", "yaw_std"]]
    config = FuseConfig.from_options(imu_model="broad-aktos-t", output_rate_hz=2.0, **SITE)
    res = run_fusion(imu, heading, rot_nb0=rot0, config=config)
    upd = res.updates
    assert "zupt" not in set(upd["name"])
    zaru = upd[upd["name"] == "zaru"]
    assert len(zaru) > 600 and zaru["accepted"].mean() > 0.99
    assert abs(zaru["nis"].mean() / 3.0 - 1.0) < 0.25  # per degree of freedom
    for angle, (rms, within3, err_deg) in score(res.solution, truth).items():
        assert 0.2 <= rms <= 1.5 and within3 >= 95.0, (trial, angle, rms, within3)
        assert err_deg < 1.0, (trial, angle, err_deg)
