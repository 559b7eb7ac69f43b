"""Round trip of the camera-IMU calibration (docs/calibrate.md#camera-imu): time offset and boresight from a 2-minute log with turns."""

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation
from test_calibration_scenes import small_camera

from polins.calibration import apply_to_camera, calibrate_camera_imu
from polins.errors import UserInputError
from polins.sim.render import direction_n

SUN_N = direction_n(140.0, 35.0)


def _log(rng, *, dt_true, rot_bc, turning=True, noise_deg=0.05):
    """Attitudes at 100 Hz over 120 s (turns up to about 45 deg/s, small roll and pitch
    rocking) and camera sun vectors at 5 Hz stamped on a clock late by ``dt_true``."""
    t_att = np.arange(0.0, 120.0, 0.01)
    yaw = (
        np.radians(60.0) * np.sin(2 * np.pi * t_att / 20.0)
        + np.radians(30.0) * np.sin(2 * np.pi * t_att / 7.0)
        if turning
        else np.zeros_like(t_att)
    )
    pitch = np.radians(2.0) * np.sin(2 * np.pi * t_att / 3.0)
    roll = np.radians(2.0) * np.sin(2 * np.pi * t_att / 4.3)
    rot_nb = Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], -1))
    t_cam = np.arange(1.0, 119.0, 0.2)  # camera clock
    t_true = t_cam + dt_true  # when the images were really taken, on the IMU clock
    yaw_c = np.interp(t_true, t_att, yaw)
    rot_true = Rotation.from_euler(
        "ZYX",
        np.stack([yaw_c, np.interp(t_true, t_att, pitch), np.interp(t_true, t_att, roll)], -1),
    )
    sun_c = (rot_true * rot_bc).inv().apply(SUN_N)
    noise = Rotation.from_rotvec(np.radians(noise_deg) * rng.standard_normal((t_cam.size, 3)))
    return t_cam, noise.apply(sun_c), t_att, rot_nb


def test_camera_imu_recovers_a_10ms_offset_and_the_boresight():
    rng = np.random.default_rng(41)
    rot_bc = Rotation.from_euler("xyz", [0.3, -0.5, 1.2], degrees=True)
    t_cam, sun_c, t_att, rot_nb = _log(rng, dt_true=0.010, rot_bc=rot_bc)
    res = calibrate_camera_imu(t_cam, sun_c, t_att, rot_nb, SUN_N)
    assert abs(res.time_offset_s - 0.010) <= 1e-3
    boresight_err = (Rotation.from_matrix(res.mat_bc) * rot_bc.inv()).magnitude()
    assert np.degrees(boresight_err) <= 0.05
    assert res.time_offset_std_s < 5e-4
    assert np.degrees(np.sqrt(np.mean(res.residuals**2))) == pytest.approx(
        0.05 * np.sqrt(2), rel=0.2
    )
    cam = apply_to_camera(small_camera(8), res)
    np.testing.assert_allclose(cam.mat_bc, res.mat_bc)


def test_camera_imu_refuses_a_log_without_turns():
    rng = np.random.default_rng(42)
    t_cam, sun_c, t_att, rot_nb = _log(rng, dt_true=0.0, rot_bc=Rotation.identity(), turning=False)
    with pytest.raises(UserInputError, match="record turns"):
        calibrate_camera_imu(t_cam, sun_c, t_att, rot_nb, SUN_N)


# ----------------------------------------------------------------------------- no clock
SITE_LAT_DEG, SITE_LON_DEG = 45.6234, 126.7264


def _tilting_trajectory(tilt_deg, duration_s=120.0, rate_hz=200.0):
    """Turns (up to about 45 deg/s) with pitch and roll rocking of ``tilt_deg`` and
    ``0.8 tilt_deg``, at rest position: a handheld camera or a boat."""
    from polins.sim.trajectory import Trajectory, body_rate_from_euler_rates

    t = np.arange(0.0, duration_s + 1e-9, 1.0 / rate_hz)
    w = [2 * np.pi / p for p in (20.0, 7.0, 13.0, 9.3)]
    a_yaw, b_yaw = np.radians(60.0), np.radians(30.0)
    a_p, a_r = np.radians(tilt_deg), np.radians(0.8 * tilt_deg)
    yaw = a_yaw * np.sin(w[0] * t) + b_yaw * np.sin(w[1] * t)
    yaw_rate = a_yaw * w[0] * np.cos(w[0] * t) + b_yaw * w[1] * np.cos(w[1] * t)
    pitch, pitch_rate = a_p * np.sin(w[2] * t), a_p * w[2] * np.cos(w[2] * t)
    roll, roll_rate = a_r * np.sin(w[3] * t), a_r * w[3] * np.cos(w[3] * t)
    n = t.size
    return Trajectory(
        t=t,
        rot_nb=Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], -1)),
        vel_n=np.zeros((n, 3)),
        lat=np.full(n, np.radians(SITE_LAT_DEG)),
        lon=np.full(n, np.radians(SITE_LON_DEG)),
        alt_m=np.zeros(n),
        omega_nb_b=body_rate_from_euler_rates(roll, pitch, roll_rate, pitch_rate, yaw_rate),
        accel_n=np.zeros((n, 3)),
    )


def _camera_sun(traj, rng, *, dt_true, rot_bc, noise_deg=0.05):
    """Camera sun vectors at 5 Hz from the moving ephemeris sun, stamped ``dt_true`` late."""
    import pandas as pd
    from scipy.spatial.transform import Slerp

    from polins.sky.ephemeris import sun_position, sun_vector_n

    t_cam = np.arange(1.0, traj.t[-1] - 1.0, 0.2)
    t_true = t_cam + dt_true
    times = pd.Timestamp("2023-09-05T07:06:00Z") + pd.to_timedelta(t_true, unit="s")
    sun = sun_position(pd.DatetimeIndex(times), SITE_LAT_DEG, SITE_LON_DEG, 0.0)
    sun_n = sun_vector_n(sun.azimuth, sun.zenith)
    sun_c = (Slerp(traj.t, traj.rot_nb)(t_true) * rot_bc).inv().apply(sun_n)
    noise = Rotation.from_rotvec(np.radians(noise_deg) * rng.standard_normal((t_cam.size, 3)))
    return t_cam, noise.apply(sun_c), sun_n


ROT_BC = Rotation.from_euler("xyz", [0.3, -0.5, 1.2], degrees=True)


def test_no_clock_recovers_the_offset_and_boresight_from_the_gyro():
    """2-minute log, turns with 10 deg rocking, a navigation-grade gyro integrated from the
    first sample (no absolute attitude) and no clock: the same tolerances as the clock mode."""
    from polins.calibration.camera_imu_log import gyro_attitude
    from polins.models import load_imu
    from polins.sim.imu import ideal_imu, imu_errors

    rng = np.random.default_rng(43)
    traj = _tilting_trajectory(10.0)
    imu, _ = imu_errors(ideal_imu(traj), load_imu("fins-paper"), rng)
    rot_ref = gyro_attitude(
        imu["t"], imu[["gx", "gy", "gz"]].to_numpy(), imu[["ax", "ay", "az"]].to_numpy()
    )
    # The gyro's attitude is relative and fixed among the stars: over the 120 s it turns
    # like the truth (relative to ENU) but for the Earth's 15.04 deg/h.
    turn_ref, turn_true = rot_ref[0].inv() * rot_ref[-1], traj.rot_nb[0].inv() * traj.rot_nb[-1]
    earth_deg = 15.041 / 3600.0 * traj.t[-1]
    assert np.degrees((turn_ref * turn_true.inv()).magnitude()) == pytest.approx(
        earth_deg, abs=0.01
    )
    t_cam, sun_c, _ = _camera_sun(traj, rng, dt_true=0.010, rot_bc=ROT_BC)
    res = calibrate_camera_imu(t_cam, sun_c, imu["t"].to_numpy(), rot_ref)  # no sun_n: no clock
    assert res.mode == "no-clock" and res.held_axis_b is None
    assert abs(res.time_offset_s - 0.010) <= 1e-3  # measured: 0.01003 (std 0.0001)
    err = Rotation.from_matrix(res.mat_bc) * ROT_BC.inv()
    assert np.degrees(err.magnitude()) <= 0.05  # measured: 0.010 deg
    # Statistically consistent: the errors within 4 standard errors, the residual at the noise.
    assert abs(res.time_offset_s - 0.010) < 4 * res.time_offset_std_s
    assert np.all(np.abs(err.as_rotvec()) < 4 * res.boresight_std_b + 1e-4)
    rms_deg = np.degrees(np.sqrt(np.mean(res.residuals**2)))
    assert rms_deg == pytest.approx(0.05 * np.sqrt(2), rel=0.15)
    # The gyro's frame does not turn with the Earth: the sun stays put in it.
    assert res.sun_drift_deg_per_min < 0.03
    assert res.provenance["n_images"] == t_cam.size and "no clock" in res.provenance["method"]


def test_no_clock_with_an_enu_attitude_fits_the_sun_motion():
    """An attitude in ENU up to an unknown rotation (a fused solution with a wrong heading):
    the sun moves 0.25 deg/min in it; the drift term takes it, and without it the fit is
    biased and its residual doubles."""
    rng = np.random.default_rng(44)
    traj = _tilting_trajectory(10.0)
    t_cam, sun_c, sun_n = _camera_sun(traj, rng, dt_true=0.010, rot_bc=ROT_BC)
    ref = Rotation.from_euler("ZYX", [73.0, 1.0, -2.0], degrees=True) * traj.rot_nb
    res = calibrate_camera_imu(t_cam, sun_c, traj.t, ref)
    rate = np.degrees(np.arccos(sun_n[0] @ sun_n[-1])) / ((t_cam[-1] - t_cam[0]) / 60.0)
    assert res.sun_drift_deg_per_min == pytest.approx(rate, abs=0.01)  # measured 0.2518/0.2481
    assert abs(res.time_offset_s - 0.010) <= 1e-3
    assert np.degrees((Rotation.from_matrix(res.mat_bc) * ROT_BC.inv()).magnitude()) <= 0.05
    still = calibrate_camera_imu(t_cam, sun_c, traj.t, ref, sun_drift=False)
    assert np.mean(still.residuals**2) > 3 * np.mean(res.residuals**2)  # measured: 5x


def test_no_clock_holds_the_boresight_about_a_single_turn_axis():
    """Turns about the vertical only: the boresight's yaw trades with the sun's azimuth.
    It is held at the start value, with a warning; the rest is still recovered."""
    from polins.calibration import HeldAxisWarning

    rng = np.random.default_rng(45)
    traj = _tilting_trajectory(0.0)
    t_cam, sun_c, _ = _camera_sun(traj, rng, dt_true=0.010, rot_bc=ROT_BC)
    start = Rotation.from_euler("z", 0.7, degrees=True)
    with pytest.warns(HeldAxisWarning, match="held at the start value"):
        res = calibrate_camera_imu(
            t_cam, sun_c, traj.t, traj.rot_nb, mat_bc_start=start.as_matrix()
        )
    assert abs(abs(res.held_axis_b[2]) - 1.0) < 1e-3  # the body's z axis
    assert res.provenance["held_axis_b"] == pytest.approx(list(res.held_axis_b), abs=1e-4)
    assert abs(res.time_offset_s - 0.010) <= 1e-3
    err = (Rotation.from_matrix(res.mat_bc) * ROT_BC.inv()).as_rotvec(degrees=True)
    assert np.abs(err[:2]).max() <= 0.05  # roll and pitch of the boresight: fitted
    assert err[2] == pytest.approx(0.7 - 1.2, abs=0.02)  # yaw: the start value's, not fitted


def test_gyro_attitude_integrates_the_body_rates():
    """The running product of the scan equals the sequential one, and the integrated ideal
    gyro of a non-rotating Earth follows the trajectory's attitude from its first sample."""
    from polins.calibration.camera_imu_log import cumulative_rotation, gyro_attitude
    from polins.sim.imu import ideal_imu

    steps = Rotation.random(37, random_state=1)
    running = [steps[0]]
    for k in range(1, 37):
        running.append(running[-1] * steps[k])
    np.testing.assert_allclose(
        cumulative_rotation(steps).as_matrix(),
        Rotation.concatenate(running).as_matrix(),
        atol=1e-12,
    )
    traj = _tilting_trajectory(10.0, duration_s=30.0)
    imu = ideal_imu(traj, earth_rotation=False)
    rot = gyro_attitude(imu["t"], imu[["gx", "gy", "gz"]].to_numpy())  # from the body at t = 0
    err = (rot * (traj.rot_nb[0].inv() * traj.rot_nb).inv()).magnitude()
    assert np.degrees(err.max()) < 1e-3  # measured: 7e-5 deg after 30 s
    with pytest.raises(UserInputError, match=r"gyro_b of shape \(6001, 3\)"):
        gyro_attitude(imu["t"], imu[["gx", "gy"]].to_numpy())


@pytest.mark.parametrize("clock", [True, False])
def test_camera_imu_drops_sun_vectors_on_the_wrong_branch(clock):
    """4% of the sun vectors turned 180 deg about the camera axis (the polarization's
    branch ambiguity): dropped as outliers, and the fit is as good as without them."""
    rng = np.random.default_rng(46)
    traj = _tilting_trajectory(10.0)
    t_cam, sun_c, _ = _camera_sun(traj, rng, dt_true=0.010, rot_bc=ROT_BC)
    bad = rng.choice(t_cam.size, int(0.04 * t_cam.size), replace=False)
    sun_c[bad] = sun_c[bad] * [-1.0, -1.0, 1.0]
    if clock:  # the ephemeris per attitude sample
        from polins.sky.ephemeris import sun_position, sun_vector_n

        times = pd.Timestamp("2023-09-05T07:06:00Z") + pd.to_timedelta(traj.t, unit="s")
        sun = sun_position(pd.DatetimeIndex(times[::100]), SITE_LAT_DEG, SITE_LON_DEG, 0.0)
        s_n = sun_vector_n(sun.azimuth, sun.zenith)
        s_n = np.stack([np.interp(traj.t, traj.t[::100], s_n[:, i]) for i in range(3)], -1)
        res = calibrate_camera_imu(t_cam, sun_c, traj.t, traj.rot_nb, s_n)
    else:
        res = calibrate_camera_imu(t_cam, sun_c, traj.t, traj.rot_nb)
    assert res.provenance["n_outliers"] == bad.size
    assert res.residuals.size == t_cam.size - bad.size
    assert abs(res.time_offset_s - 0.010) <= 1e-3
    assert np.degrees((Rotation.from_matrix(res.mat_bc) * ROT_BC.inv()).magnitude()) <= 0.05
