"""Self-alignment: levelling and gyrocompassing (polins.ins.alignment) and the ESKF's use
of them with a navigation-grade IMU whose Earth rate is mechanized."""

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

import polins
from polins.frames import rot_nb_from_euler, wrap_angle
from polins.ins.alignment import gyrocompass, level_from_accel
from polins.ins.earth import OMEGA_IE, earth_rate_n, gravity_n
from polins.sim.imu import ideal_imu, imu_errors
from polins.sim.trajectory import ugv_drive

SITE = {"lat_deg": 45.6234, "lon_deg": 126.7264, "alt_m": 148.74}
LAT = np.radians(SITE["lat_deg"])
ONE_HEADING = {"acquire_k": 1, "acquire_n": 1}


def test_levelling_and_gyrocompass_of_an_exact_static_imu():
    rng = np.random.default_rng(0)
    for _ in range(20):
        rot = rot_nb_from_euler(rng.uniform(-np.pi, np.pi), *np.radians(rng.normal(0, 5, 2)))
        f_b = rot.inv().apply(-gravity_n(LAT, 150.0))
        w_b = rot.inv().apply(earth_rate_n(LAT))
        yaw, pitch, roll = rot.as_euler("ZYX")
        roll_l, pitch_l = level_from_accel(f_b)
        assert roll_l == pytest.approx(roll, abs=1e-12)
        assert pitch_l == pytest.approx(pitch, abs=1e-12)
        level = rot_nb_from_euler(0.0, pitch_l, roll_l)
        yaw_gc, jac = gyrocompass(w_b, level, LAT)
        assert float(wrap_angle(yaw_gc - yaw)) == pytest.approx(0.0, abs=1e-12)
        # a gyro bias moves the yaw as the Jacobian says (dtheta_z = true - estimate)
        bias = rng.normal(0.0, 1e-9, 3)  # linear regime: 2e-5 of the Earth rate
        yaw_b, _ = gyrocompass(w_b + bias, level, LAT)
        assert float(wrap_angle(yaw - yaw_b)) == pytest.approx(jac @ bias, rel=1e-3, abs=1e-12)
        np.testing.assert_allclose(np.linalg.norm(jac), 1.0 / (OMEGA_IE * np.cos(LAT)))
    with pytest.raises(ValueError, match="horizontal Earth rate"):
        gyrocompass(w_b, level, np.pi / 2)


def _static_then_yaw(model, seed, duration=4.0, t_yaw=2.0):
    """A UGV standing still (its drive starts after 5 s) at a random heading, and one
    exact yaw measurement at t_yaw (fused with ``ONE_HEADING``: that one heading sets the
    yaw, no consensus of several, docs/filter.md 7.1)."""
    rng = np.random.default_rng(seed)
    traj = ugv_drive(duration_s=duration, rng=rng, yaw0=rng.uniform(-np.pi, np.pi))
    imu, errors = imu_errors(ideal_imu(traj), model, rng)
    truth = traj.truth_frame()
    k = int(np.searchsorted(truth["t"], t_yaw))
    meas = pd.DataFrame({"t": [truth["t"][k]], "yaw": [truth["yaw"][k]], "yaw_std": [1e-4]})
    return imu, errors, truth, meas


def test_self_alignment_with_earth_rate_keeps_the_tilt_consistent():
    # Navigation-grade IMU, Earth rate mechanized, yaw unknown for 1 s after the levelling:
    # without gyrocompassing the Earth rate would be compensated about wrong axes and tilt
    # the attitude by up to 2 Omega cos(L) t (1e-4 rad/s, 50x the tilt sigma after 2 s).
    model = polins.load_imu("fins-paper")
    ratios, errors_rad = [], []
    for seed in range(12):
        imu, _, truth, meas = _static_then_yaw(model, seed)
        assert np.all(truth["ve"] == 0.0) and np.all(truth["vn"] == 0.0)
        sol = polins.fuse(imu, meas, imu_model=model, **SITE, **ONE_HEADING, output_rate_hz=10.0)
        row = sol.iloc[-1]
        k = int(np.searchsorted(truth["t"], row["t"] - 1e-9))
        for c in ("roll", "pitch"):
            e = float(row[c] - truth[c].iloc[k])
            errors_rad.append(e)
            ratios.append(e / row[f"{c}_std"])
        # the exact yaw measurement sets the yaw; the tilt stays at the levelling error
        assert abs(wrap_angle(row["yaw"] - truth["yaw"].iloc[k])) < 1e-5
    rms = float(np.sqrt(np.mean(np.square(ratios))))
    assert 0.5 < rms < 1.5, rms
    # levelling error ~ accelerometer bias / g (2e-5 g -> 2e-5 rad), not the 2e-4 of a drift
    assert np.max(np.abs(errors_rad)) < 5 * model.accel_bias / 9.8


def test_self_alignment_of_a_mems_imu_with_earth_rate():
    model = polins.load_imu("mems-typical")
    imu, _, truth, meas = _static_then_yaw(model, 3)
    sol = polins.fuse(imu, meas, imu_model=model, **SITE, **ONE_HEADING, output_rate_hz=10.0)
    # before the yaw measurement the yaw is unknown (NaN) and the tilt is the levelling
    before = sol[sol["t"] < meas["t"].iloc[0] - 1e-6]
    assert before["yaw"].isna().all() and np.isfinite(before["roll"]).all()
    row = sol.iloc[-1]
    k = int(np.searchsorted(truth["t"], row["t"] - 1e-9))
    for c in ("roll", "pitch"):
        assert abs(row[c] - truth[c].iloc[k]) < 3 * row[f"{c}_std"]
    rot = Rotation.from_quat(sol[["qx", "qy", "qz", "qw"]].to_numpy()[-1])
    assert rot.as_euler("ZYX")[0] == pytest.approx(row["yaw"], abs=1e-12)
    assert abs(wrap_angle(row["yaw"] - truth["yaw"].iloc[k])) < 3 * row["yaw_std"]
