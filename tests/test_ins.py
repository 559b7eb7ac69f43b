"""Strapdown mechanization: reproduction of simulated trajectories, the compiled loop
against a plain-Python reference step."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from polins.frames import skew
from polins.ins.earth import gravity_n, normal_gravity, radii_of_curvature
from polins.ins.state import NavState
from polins.ins.strapdown import (
    Mechanization,
    cross,
    nav_rates_n,
    rotation_vectors,
    strapdown,
    strapdown_step,
)
from polins.sim.imu import ideal_imu
from polins.sim.trajectory import turntable, ugv_drive


def _start(traj):
    return NavState(
        float(traj.t[0]),
        traj.rot_nb[0],
        traj.vel_n[0].copy(),
        float(traj.lat[0]),
        float(traj.lon[0]),
        float(traj.alt_m[0]),
    )


def _run(traj, earth_rotation):
    imu = ideal_imu(traj, earth_rotation=earth_rotation)
    mech = Mechanization(earth_rotation=earth_rotation, transport_rate=True)
    return strapdown(
        _start(traj),
        imu["t"].to_numpy(),
        imu[["gx", "gy", "gz"]].to_numpy(),
        imu[["ax", "ay", "az"]].to_numpy(),
        mech,
    )


@pytest.mark.parametrize("earth_rotation", [True, False])
def test_turntable_noise_free_reproduction(earth_rotation):
    # The paper's turntable: 720 deg in 100 s at Harbin, with Earth rate (FINS) or without.
    traj = turntable(duration_s=100.0, roll=0.02, pitch=-0.03)
    track = _run(traj, earth_rotation)
    att_err = (traj.rot_nb * track.rot_nb.inv()).magnitude()
    assert att_err.max() < 1e-6
    assert np.abs(track.vel_n).max() < 1e-5  # standing still: velocity stays ~0
    assert np.abs(track.alt_m - traj.alt_m).max() < 1e-4


@pytest.mark.parametrize("seed", [3, 11])
def test_ugv_noise_free_reproduction(seed):
    traj = ugv_drive(duration_s=100.0, rng=np.random.default_rng(seed))
    track = _run(traj, True)
    att_err = (traj.rot_nb * track.rot_nb.inv()).magnitude()
    assert att_err.max() < 1e-6
    assert np.abs(track.vel_n - traj.vel_n).max() < 1e-3
    north_err_m = np.abs(track.lat - traj.lat).max() * 6.4e6
    assert north_err_m < 0.05
    assert np.abs(track.alt_m - traj.alt_m).max() < 0.01


def _reference_step(s, w0, w1, f0, f1, t1, mech):
    """The module docstring's step written plainly with scipy Rotations (the reference of
    the compiled loop)."""
    dt = t1 - s.t
    f0, f1 = np.array(f0), np.array(f1)
    phi, phi_h = rotation_vectors(w0, w1, dt)
    w_ie, w_en = nav_rates_n(s.lat, s.alt_m, s.vel_n, mech)
    zeta = (w_ie + w_en) * dt
    rot1 = Rotation.from_rotvec(-zeta) * s.rot_nb * Rotation.from_rotvec(phi)
    rot_h = Rotation.from_rotvec(-0.5 * zeta) * s.rot_nb * Rotation.from_rotvec(phi_h)
    dv_f = dt / 6.0 * (s.rot_nb.apply(f0) + rot_h.apply(2.0 * (f0 + f1)) + rot1.apply(f1))
    dv = dv_f - np.cross(2.0 * w_ie + w_en, s.vel_n) * dt
    dv[2] -= normal_gravity(s.lat, s.alt_m) * dt
    v1 = s.vel_n + dv
    r_m, r_n = radii_of_curvature(s.lat)
    d = 0.5 * dt * (s.vel_n + v1)
    return NavState(t1, rot1, v1, s.lat + d[1] / (r_m + s.alt_m),
                    s.lon + d[0] / ((r_n + s.alt_m) * np.cos(s.lat)), s.alt_m + d[2])  # fmt: skip


@pytest.mark.parametrize("earth", [True, False])
def test_compiled_loop_equals_reference_steps(earth):
    traj = ugv_drive(duration_s=8.0, rng=np.random.default_rng(5))
    imu = ideal_imu(traj)
    t = imu["t"].to_numpy()
    w = imu[["gx", "gy", "gz"]].to_numpy()
    f = imu[["ax", "ay", "az"]].to_numpy()
    mech = Mechanization(earth, earth)
    n = 300
    track = strapdown(_start(traj), t[: n + 1], w[: n + 1], f[: n + 1], mech)
    s = one = _start(traj)
    for k in range(n):
        s = _reference_step(s, w[k], w[k + 1], f[k], f[k + 1], t[k + 1], mech)
        one = strapdown_step(one, w[k], w[k + 1], f[k], f[k + 1], t[k + 1], mech)
    for last in (track.state(n), one):
        assert (s.rot_nb * last.rot_nb.inv()).magnitude() < 1e-13
        np.testing.assert_allclose(s.vel_n, last.vel_n, atol=1e-12)
        assert abs(s.lat - last.lat) < 1e-15 and abs(s.lon - last.lon) < 1e-15
        assert abs(s.alt_m - last.alt_m) < 1e-10


def test_static_level_body_feels_somigliana_gravity():
    # At rest on the equator and at the pole the ideal accelerometer reads the WGS-84
    # normal gravity (Somigliana: 9.7803253359 and 9.8321849378 m/s^2) and the
    # mechanization keeps the state still.
    for lat_deg, gamma in ((0.0, 9.7803253359), (89.0, normal_gravity(np.radians(89.0)))):
        traj = turntable(duration_s=20.0, turn_rad=0.0, lat_deg=lat_deg, alt_m=0.0)
        imu = ideal_imu(traj)
        assert imu["az"].to_numpy() == pytest.approx(gamma, abs=1e-12)
        track = _run(traj, True)
        assert np.abs(track.vel_n).max() < 1e-9
        assert (traj.rot_nb * track.rot_nb.inv()).magnitude().max() < 1e-9
    assert gravity_n(0.0)[2] == pytest.approx(-9.7803253359, abs=1e-10)


def test_coning_rotation_vector_of_linear_rate():
    # A rate varying linearly between samples: the second-order Bortz rotation vector is
    # the exact integral up to O(dt^3 |w|^2 |dw|); compare with a fine integration.
    w0, w1, dt = np.array([0.3, -0.2, 0.5]), np.array([0.1, 0.4, 0.2]), 0.01
    phi, phi_h = rotation_vectors(w0, w1, dt)
    rot = Rotation.identity()
    rot_h = None
    m = 20000
    for i in range(m):
        s = (i + 0.5) / m
        rot = rot * Rotation.from_rotvec((w0 + (w1 - w0) * s) * dt / m)
        if i == m // 2 - 1:
            rot_h = rot
    assert np.abs(rot.as_rotvec() - phi).max() < 1e-9
    assert np.abs(rot_h.as_rotvec() - phi_h).max() < 1e-9
    # Without the coning term the error would be ~dt^2/12 |w0 x w1| = 3e-6 rad.
    assert np.abs(rot.as_rotvec() - (w0 + w1) * dt / 2).max() > 1e-6


def test_helpers():
    a, b = np.array([[1.0, 2.0, 3.0]]), np.array([[-2.0, 0.5, 4.0]])
    np.testing.assert_allclose(cross(a, b), np.cross(a, b))
    np.testing.assert_allclose(skew(a[0]) @ b[0], np.cross(a[0], b[0]))


def test_strapdown_input_errors():
    s = NavState(0.0, Rotation.identity(), np.zeros(3), 0.5, 0.1, 0.0)
    with pytest.raises(ValueError, match="after the state time"):
        strapdown_step(s, np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3), 0.0, Mechanization())
    with pytest.raises(ValueError, match="strictly increasing"):
        strapdown(s, [0.0, 0.0], np.zeros((2, 3)), np.zeros((2, 3)), Mechanization())
