"""Analytic trajectories: internal consistency of attitude, rates, velocity and position."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from polins.frames import yaw_from_rot_nb
from polins.ins.earth import radii_of_curvature
from polins.sim.trajectory import (
    Trajectory,
    body_rate_from_euler_rates,
    smooth_step,
    turntable,
    ugv_drive,
)


def numerical_body_rate(traj: Trajectory) -> np.ndarray:
    """Central-difference body rate [rad/s] at interior samples (O(h^2))."""
    h = traj.t[1] - traj.t[0]
    rot = traj.rot_nb
    return (rot[:-2].inv() * rot[2:]).as_rotvec() / (2.0 * h)


def five_point(x: np.ndarray, h: float) -> np.ndarray:
    """Fourth-order central derivative at samples 2..N-3."""
    return (x[:-4] - 8.0 * x[1:-3] + 8.0 * x[3:-1] - x[4:]) / (12.0 * h)


@pytest.fixture(scope="module")
def drive() -> Trajectory:
    return ugv_drive(duration_s=300.0, rate_hz=200.0, rng=np.random.default_rng(7))


def test_smooth_step_ends_and_derivatives():
    x = np.linspace(0.0, 1.0, 20001)
    s, ds, dds = smooth_step(x)
    assert s[0] == 0.0 and s[-1] == pytest.approx(1.0, abs=1e-15)
    assert ds[[0, -1]] == pytest.approx([0.0, 0.0]) and dds[[0, -1]] == pytest.approx([0, 0])
    h = x[1] - x[0]
    assert np.max(np.abs(np.gradient(s, h)[1:-1] - ds[1:-1])) < 1e-6
    assert np.max(np.abs(np.gradient(ds, h)[1:-1] - dds[1:-1])) < 1e-5
    assert ds.max() == pytest.approx(35.0 / 16.0)
    # clamped outside [0, 1]
    assert smooth_step(np.array([-1.0, 2.0]))[0] == pytest.approx([0.0, 1.0])


def test_body_rate_formula_matches_numerical_derivative():
    t = np.linspace(0.0, 2.0, 4001)
    h = t[1] - t[0]
    yaw, pitch, roll = 0.7 * np.sin(t) + 2.0, 0.3 * np.cos(1.3 * t), -0.4 * np.sin(0.9 * t)
    rates = (-0.4 * 0.9 * np.cos(0.9 * t), -0.3 * 1.3 * np.sin(1.3 * t), 0.7 * np.cos(t))
    omega = body_rate_from_euler_rates(roll, pitch, *rates)
    rot = Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], -1))
    num = (rot[:-2].inv() * rot[2:]).as_rotvec() / (2 * h)
    assert np.max(np.abs(num - omega[1:-1])) < 1e-6


def test_turntable_turns_exactly_720_deg_at_constant_rate():
    traj = turntable()
    assert len(traj) == 20001 and traj.t[-1] == pytest.approx(100.0)
    assert traj.rate_hz == pytest.approx(200.0)
    yaw = np.unwrap(yaw_from_rot_nb(traj.rot_nb))
    assert yaw[-1] - yaw[0] == pytest.approx(4 * np.pi, abs=1e-12)
    assert np.degrees(traj.omega_nb_b[:, 2]) == pytest.approx(np.full(len(traj), 7.2))
    assert np.all(traj.vel_n == 0.0) and np.all(traj.accel_n == 0.0)
    assert np.all(traj.lat == np.radians(45.6234)) and np.all(traj.alt_m == 148.74)


def test_tilted_ramped_turntable_is_consistent():
    traj = turntable(duration_s=40.0, roll=0.1, pitch=-0.05, yaw0=1.0, ramp_s=8.0)
    # central differences: h^2/6 * omega'' ~ 2e-7 rad/s at the ramps
    assert np.max(np.abs(numerical_body_rate(traj) - traj.omega_nb_b[1:-1])) < 1e-6
    assert np.allclose(traj.omega_nb_b[[0, -1]], 0.0, atol=1e-15)  # starts and ends at rest
    # the rotation axis is the ENU vertical, the tilt stays constant
    omega_n = traj.rot_nb.apply(traj.omega_nb_b)
    assert np.allclose(omega_n[:, :2], 0.0, atol=1e-15)
    ypr = traj.rot_nb.as_euler("ZYX")
    assert np.allclose(ypr[:, 1], -0.05) and np.allclose(ypr[:, 2], 0.1)
    yaw = np.unwrap(yaw_from_rot_nb(traj.rot_nb))
    assert yaw[-1] - yaw[0] == pytest.approx(4 * np.pi, abs=1e-12)


def test_ugv_attitude_rate_is_exact(drive):
    err = np.abs(numerical_body_rate(drive) - drive.omega_nb_b[1:-1])
    # central-difference truncation ~h^2/6 * omega'' (peak rates 0.5 rad/s)
    assert err.max() < 1e-5
    assert np.abs(drive.omega_nb_b[:, 2]).max() > np.radians(10.0)  # it does turn


def test_ugv_acceleration_is_exact(drive):
    h = drive.t[1] - drive.t[0]
    num = five_point(drive.vel_n, h)
    # 4th-order stencil; ~1e-7 where a smooth-step's 4th derivative jumps at its ends
    assert np.max(np.abs(num - drive.accel_n[2:-2])) < 1e-6
    assert np.abs(drive.accel_n).max() > 0.5


def test_ugv_position_integrates_velocity(drive):
    h = drive.t[1] - drive.t[0]
    r_m, r_n = radii_of_curvature(drive.lat)
    lat, hgt = drive.lat[2:-2], drive.alt_m[2:-2]
    vel_from_pos = np.stack(
        [
            five_point(drive.lon, h) * (r_n[2:-2] + hgt) * np.cos(lat),
            five_point(drive.lat, h) * (r_m[2:-2] + hgt),
            five_point(drive.alt_m, h),
        ],
        axis=-1,
    )
    # float64 round-off of lat/lon [rad] divided by h dominates: ~1e-6 m/s
    assert np.max(np.abs(vel_from_pos - drive.vel_n[2:-2])) < 1e-5
    assert drive.lat[0] == np.radians(45.6234) and drive.alt_m[0] == 148.74
    # it went somewhere: > 500 m of travel
    assert np.sum(np.linalg.norm(drive.vel_n, axis=1)) * h > 500.0


def test_ugv_is_non_holonomic_with_stops_slopes_and_both_turns(drive):
    vel_b = drive.rot_nb.inv().apply(drive.vel_n)
    assert np.max(np.abs(vel_b[:, 1:])) < 1e-12  # no lateral / vertical body velocity
    assert np.all(vel_b[:, 0] >= -1e-12)  # forward only
    speed = np.linalg.norm(drive.vel_n, axis=1)
    assert speed.max() <= 10.0 and speed.max() > 3.0
    still = speed == 0.0
    assert still[0]  # starts at rest
    starts = np.flatnonzero(np.diff(still.astype(int)) == 1)  # moving -> stopped
    assert len(starts) >= 3  # at most 60 s between stops over 300 s
    stop_len = np.diff(np.flatnonzero(np.diff(still.astype(int))))
    assert np.all(drive.accel_n[still] == 0.0)
    assert stop_len.size > 0
    pitch = drive.rot_nb.as_euler("ZYX")[:, 1]
    assert pitch.min() < -0.01 or pitch.max() > 0.01  # it drove on a grade
    assert drive.alt_m.max() - drive.alt_m.min() > 0.5
    yaw_rate = drive.omega_nb_b[:, 2]
    assert yaw_rate.min() < -0.1 and yaw_rate.max() > 0.1  # turns both ways
    roll = drive.rot_nb.as_euler("ZYX")[:, 2]
    assert 0.001 < np.abs(roll).max() < 0.1  # small roll


def test_ugv_is_seeded_and_rate_independent():
    a = ugv_drive(duration_s=60.0, rng=np.random.default_rng(3))
    b = ugv_drive(duration_s=60.0, rng=np.random.default_rng(3))
    c = ugv_drive(duration_s=60.0, rate_hz=50.0, rng=np.random.default_rng(3))
    d = ugv_drive(duration_s=60.0, rng=np.random.default_rng(4))
    assert np.array_equal(a.vel_n, b.vel_n) and np.array_equal(a.lat, b.lat)
    assert np.allclose(a.vel_n[::4], c.vel_n, atol=1e-12)
    assert np.allclose(a.lat[::4], c.lat, atol=1e-14) and np.allclose(a.alt_m[::4], c.alt_m)
    assert not np.allclose(a.vel_n, d.vel_n)


def test_truth_frame_columns_and_round_trip(drive):
    df = drive.truth_frame()
    assert list(df.columns) == [
        "t",
        "roll",
        "pitch",
        "yaw",
        "heading_deg",
        "qw",
        "qx",
        "qy",
        "qz",
        "ve",
        "vn",
        "vu",
        "lat_deg",
        "lon_deg",
        "alt_m",
    ]
    rot_q = Rotation.from_quat(df[["qx", "qy", "qz", "qw"]].to_numpy())
    rot_e = Rotation.from_euler("ZYX", df[["yaw", "pitch", "roll"]].to_numpy())
    assert np.max((rot_q.inv() * drive.rot_nb).magnitude()) < 1e-12
    assert np.max((rot_e.inv() * drive.rot_nb).magnitude()) < 1e-12
    heading = np.mod(90.0 - np.degrees(df["yaw"]), 360.0)
    assert np.allclose(np.cos(np.radians(heading - df["heading_deg"])), 1.0)
    assert df["lat_deg"].iloc[0] == pytest.approx(45.6234)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"duration_s": 0.0}, "duration_s"),
        ({"rate_hz": -1.0}, "rate_hz"),
        ({"lat_deg": 95.0}, "lat_deg"),
        ({"ramp_s": 80.0}, "ramp_s"),
    ],
)
def test_turntable_bad_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        turntable(**kwargs)


def test_ugv_bad_input():
    with pytest.raises(ValueError, match="Generator"):
        ugv_drive(rng=0)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="speed_mps"):
        ugv_drive(rng=np.random.default_rng(0), speed_mps=30.0)
