"""IMU simulation: ideal physics (gravity, Earth rate, Coriolis, transport) and error model."""

import dataclasses

import allantools
import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from polins import load_imu
from polins.ins.earth import OMEGA_IE, normal_gravity, radii_of_curvature
from polins.sim.imu import ERROR_COLUMNS, IMU_COLUMNS, ideal_imu, imu_errors
from polins.sim.trajectory import Trajectory, turntable, ugv_drive

LAT = np.radians(45.6234)


def static_table(rate_hz: float, duration_s: float) -> pd.DataFrame:
    n = round(rate_hz * duration_s) + 1
    data = np.column_stack([np.arange(n) / rate_hz, np.zeros((n, 6))])
    return pd.DataFrame(data, columns=IMU_COLUMNS)


def test_ideal_imu_at_rest_level_east():
    imu = ideal_imu(turntable(duration_s=1.0, turn_rad=0.0))
    assert list(imu.columns) == IMU_COLUMNS
    g = normal_gravity(LAT, 148.74)
    assert g == pytest.approx(9.8063, abs=1e-3)
    # FLU body = ENU: specific force is +g up, the gyros read (0, W cos lat, W sin lat)
    assert np.allclose(imu[["ax", "ay", "az"]], [0.0, 0.0, g], atol=1e-15)
    assert np.allclose(imu[["gx", "gy", "gz"]], [0, OMEGA_IE * np.cos(LAT), OMEGA_IE * np.sin(LAT)])
    assert np.linalg.norm(imu[["gx", "gy", "gz"]].to_numpy(), axis=1) == pytest.approx(7.292115e-5)


def test_ideal_imu_at_rest_tilted_and_rotated():
    yaw, pitch, roll = np.radians(30.0), np.radians(5.0), np.radians(-8.0)
    imu = ideal_imu(turntable(duration_s=1.0, turn_rad=0.0, yaw0=yaw, pitch=pitch, roll=roll))
    rot_nb = Rotation.from_euler("ZYX", [yaw, pitch, roll])
    # copies: pandas >= 3 hands out read-only views, which Rotation.apply rejects
    f_b = imu[["ax", "ay", "az"]].to_numpy(copy=True)[0]
    w_b = imu[["gx", "gy", "gz"]].to_numpy(copy=True)[0]
    # back in ENU: -g_n straight up, and the Earth rate towards North and up
    assert rot_nb.apply(f_b) == pytest.approx([0.0, 0.0, normal_gravity(LAT, 148.74)], abs=1e-12)
    w_n = rot_nb.apply(w_b)
    assert w_n == pytest.approx([0.0, OMEGA_IE * np.cos(LAT), OMEGA_IE * np.sin(LAT)], abs=1e-18)
    # levelling: roll = atan2(fy, fz), pitch = atan2(-fx, hypot(fy, fz)) (nose down = +)
    assert np.arctan2(f_b[1], f_b[2]) == pytest.approx(roll, abs=1e-12)
    assert np.arctan2(-f_b[0], np.hypot(f_b[1], f_b[2])) == pytest.approx(pitch, abs=1e-12)
    # no Earth rotation: only the (zero) turn remains
    assert np.allclose(
        ideal_imu(turntable(duration_s=1.0, turn_rad=0.0), earth_rotation=False)[
            ["gx", "gy", "gz"]
        ],
        0.0,
    )


def test_ideal_imu_driving_north_coriolis_and_transport_rate():
    """Constant 10 m/s due North on the ellipsoid: hand-computed Coriolis and transport."""
    v, h0, n = 10.0, 100.0, 11
    t = np.linspace(0.0, 1.0, n)
    r_m, _ = radii_of_curvature(LAT)
    lat = LAT + v * t / (r_m + h0)  # first order is enough for this check
    traj = Trajectory(
        t=t,
        rot_nb=Rotation.from_euler("Z", np.full((n, 1), np.pi / 2)),  # body x North, y West
        vel_n=np.tile([0.0, v, 0.0], (n, 1)),
        lat=lat,
        lon=np.zeros(n),
        alt_m=np.full(n, h0),
        omega_nb_b=np.zeros((n, 3)),
        accel_n=np.zeros((n, 3)),
    )
    imu = ideal_imu(traj)
    r_m, _ = radii_of_curvature(lat)
    w_b = imu[["gx", "gy", "gz"]].to_numpy()
    # body x (North) senses W cos lat, body y (West) senses +v/(R_M + h), z W sin lat
    assert np.allclose(w_b[:, 0], OMEGA_IE * np.cos(lat), rtol=1e-12, atol=0)
    assert np.allclose(w_b[:, 1], v / (r_m + h0), rtol=1e-12, atol=0)
    assert np.allclose(w_b[:, 2], OMEGA_IE * np.sin(lat), rtol=1e-12, atol=0)
    # Coriolis: the road pushes the vehicle West (body +y) by 2 W sin(lat) v
    f_b = imu[["ax", "ay", "az"]].to_numpy()
    assert np.allclose(f_b[:, 1], 2 * OMEGA_IE * np.sin(lat) * v, rtol=1e-12, atol=0)
    assert np.allclose(f_b[:, 0], 0.0, atol=1e-15)
    # vertical: gravity minus the centripetal terms (2 W cos lat ve = 0; v^2/R_M from omega_en)
    assert np.allclose(f_b[:, 2], normal_gravity(lat, h0) - v**2 / (r_m + h0), rtol=1e-12)


def test_ideal_imu_ugv_consistent_with_navigation_equation():
    traj = ugv_drive(duration_s=60.0, rng=np.random.default_rng(2))
    imu = ideal_imu(traj)
    flat = ideal_imu(traj, earth_rotation=False)
    w_ie_b = traj.rot_nb.inv().apply(
        np.stack([0 * traj.lat, OMEGA_IE * np.cos(traj.lat), OMEGA_IE * np.sin(traj.lat)], -1)
    )
    g_cols, a_cols = ["gx", "gy", "gz"], ["ax", "ay", "az"]
    assert np.allclose(imu[g_cols].to_numpy() - flat[g_cols].to_numpy(), w_ie_b, atol=1e-18)
    # removing Earth rate changes the specific force by the Coriolis term only (< 2 W v)
    dv = np.abs(imu[a_cols].to_numpy() - flat[a_cols].to_numpy()).max()
    assert 0 < dv <= 2 * OMEGA_IE * np.linalg.norm(traj.vel_n, axis=1).max()
    # standing still (start of the drive): |f| = normal gravity
    f0 = np.linalg.norm(imu[a_cols].to_numpy()[0])
    assert f0 == pytest.approx(normal_gravity(traj.lat[0], traj.alt_m[0]), abs=1e-12)


@pytest.mark.parametrize("name", ["mems-typical", "fins-paper"])
def test_allan_deviation_white_noise_at_one_second(name):
    """ARW and VRW: the Allan deviation at tau = 1 s equals the noise density."""
    model = load_imu(name)
    measured, _ = imu_errors(static_table(200.0, 2000.0), model, np.random.default_rng(11))
    densities = [model.gyro_arw] * 3 + [model.accel_vrw] * 3
    for col, density in zip(IMU_COLUMNS[1:], densities, strict=True):
        x = measured[col].to_numpy()
        _, adev, _, _ = allantools.oadev(x, rate=200.0, data_type="freq", taus=[1.0])
        # bias random walk adds K sqrt(tau/3), negligible at 1 s for both models
        assert adev[0] / density == pytest.approx(1.0, abs=0.1), col


def test_allan_deviation_bias_random_walk_slope():
    """Rate/acceleration random walk: Allan deviation K sqrt(tau / 3) at long tau."""
    base = load_imu("mems-typical")
    model = dataclasses.replace(
        base,
        gyro_arw=base.gyro_arw * 0.01,
        accel_vrw=base.accel_vrw * 0.01,
        gyro_bias_rw=base.gyro_bias_rw * 100.0,
        accel_bias_rw=base.accel_bias_rw * 100.0,
    )
    rate_hz = 2.0
    measured, errors = imu_errors(static_table(rate_hz, 100000.0), model, np.random.default_rng(5))
    taus = np.array([100.0, 300.0])  # >= 300 clusters: ~3 % scatter for 3 pooled axes
    for cols, k in [(IMU_COLUMNS[1:4], model.gyro_bias_rw), (IMU_COLUMNS[4:], model.accel_bias_rw)]:
        ratios = []
        for col in cols:
            _, adev, _, _ = allantools.oadev(
                measured[col].to_numpy(), rate=rate_hz, data_type="freq", taus=taus
            )
            ratios.append(adev / (k * np.sqrt(taus / 3.0)))
        rms = np.sqrt(np.mean(np.square(ratios), axis=0))  # pooled over the three axes
        assert rms == pytest.approx(np.ones(2), abs=0.1), (cols, rms)
    # the slope in log-log is +1/2 (random walk), not -1/2 (white noise)
    _, adev, _, _ = allantools.oadev(
        measured["gx"].to_numpy(), rate=rate_hz, data_type="freq", taus=[10.0, 1000.0]
    )
    assert np.log10(adev[1] / adev[0]) / 2.0 == pytest.approx(0.5, abs=0.15)
    # the reported bias is the random walk that was added
    steps = np.diff(errors[["bgx", "bgy", "bgz"]].to_numpy(), axis=0)
    expected = model.gyro_bias_rw * np.sqrt(1.0 / rate_hz)
    assert steps.std() / expected == pytest.approx(1.0, abs=0.02)


def test_error_states_explain_the_measurement():
    traj = turntable(duration_s=20.0)
    ideal = ideal_imu(traj)
    model = load_imu("mems-typical")
    measured, errors = imu_errors(ideal, model, np.random.default_rng(1))
    assert list(errors.columns) == ERROR_COLUMNS and list(measured.columns) == IMU_COLUMNS
    assert np.array_equal(errors["t"], ideal["t"]) and np.array_equal(measured["t"], ideal["t"])
    true = ideal[IMU_COLUMNS[1:]].to_numpy()
    scale = errors[ERROR_COLUMNS[7:]].to_numpy()
    bias = errors[ERROR_COLUMNS[1:7]].to_numpy()
    white = measured[IMU_COLUMNS[1:]].to_numpy() - (1 + scale) * true - bias
    expected = np.repeat([model.gyro_arw, model.accel_vrw], 3) * np.sqrt(200.0)
    assert white.std(axis=0) / expected == pytest.approx(np.ones(6), abs=0.05)
    assert np.all(scale == scale[0])  # constant scale factor
    # the scale factor is visible on the 7.2 deg/s turn axis
    assert np.abs(scale[0, :3]).max() > 0


def test_turn_on_bias_and_scale_factor_statistics():
    model = load_imu("mems-typical")
    ideal = static_table(200.0, 0.05)
    draws = np.array(
        [
            imu_errors(ideal, model, np.random.default_rng(s))[1].iloc[0, 1:].to_numpy()
            for s in range(400)
        ]
    )
    sig = np.repeat(
        [model.gyro_bias, model.accel_bias, model.gyro_scale_factor, model.accel_scale_factor], 3
    )
    # 1 sigma over 400 draws x 3 axes: relative standard error ~2 %
    for i in range(4):
        block = draws[:, 3 * i : 3 * i + 3] / sig[3 * i]
        assert block.std() == pytest.approx(1.0, abs=0.1)
        assert abs(block.mean()) < 0.15


def test_imu_errors_deterministic_under_seed():
    ideal = ideal_imu(turntable(duration_s=5.0))
    model = load_imu("fins-paper")
    a = imu_errors(ideal, model, np.random.default_rng(42))
    b = imu_errors(ideal, model, np.random.default_rng(42))
    c = imu_errors(ideal, model, np.random.default_rng(43))
    pd.testing.assert_frame_equal(a[0], b[0])
    pd.testing.assert_frame_equal(a[1], b[1])
    assert not np.allclose(a[0]["gx"], c[0]["gx"])


def test_imu_errors_bad_input():
    model = load_imu("fins-paper")
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="lacks columns"):
        imu_errors(static_table(10.0, 1.0).drop(columns="az"), model, rng)
    uneven = static_table(10.0, 1.0)
    uneven.loc[3, "t"] = 0.31
    with pytest.raises(ValueError, match="uniformly"):
        imu_errors(uneven, model, rng)
    with pytest.raises(ValueError, match="Generator"):
        imu_errors(static_table(10.0, 1.0), model, 0)  # type: ignore[arg-type]
