"""A vehicle without velocity aiding: what the headings observe, and the sigmas over drives.

The drives are ``polins simulate --scenario ugv``'s (benchmarks/bench_free_vehicle.py): the
same trajectory, mounting, road vibration and ``mems-typical`` errors for a seed, with no
``[vehicle]`` table (no non-holonomic, zero-velocity or odometer updates). The headings are
drawn in closed loop as the camera loop makes them: the sun's azimuth seen in the body,
levelled with the filter's own attitude (the tilt-coupled model of docs/filter.md §5.2),
0.011 deg at 5 Hz (docs/filter.md §12). The filter levels with the accelerometer once a
second, with the sigma of the specific force's recent change (docs/filter.md §12.2).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from polins.fusion.api import run_fusion
from polins.fusion.config import FuseConfig
from polins.fusion.items import gate_limit
from polins.fusion.measurement import BG, level, yaw_kernel
from polins.fusion.vehicle import VehicleAiding, consider_states, consider_update, vehicle_items
from polins.models import load_imu

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_free_vehicle import ANGLES, SITE, closed_loop, drive, replay, scores

MEMS = load_imu("mems-typical")
HEADING_STD = math.radians(0.011)


def run(seed: int, duration_s: float, vibration: bool = True, rows: list | None = None):
    traj, imu, sun_n, rng, _ = drive(seed, duration_s, MEMS, vibration)
    return traj, sun_n, closed_loop(traj, imu, sun_n, rng, MEMS, rows=rows)


@pytest.fixture(scope="module")
def drives():
    return {seed: run(seed, 200.0) for seed in (2, 4)}


def test_the_updates_at_rest_come_only_at_the_stops():
    """The standstill detector fires for every vehicle kind; on the simulated drive its
    zero-rate items come where the vehicle stands (speed below 1 cm/s, no rotation: the
    road's vibration keeps it off while the vehicle rolls); the mean rate is the true bias
    plus the Earth rate within its sigma."""
    traj, imu, _, _, errors = drive(2, 90.0, MEMS)
    cfg = FuseConfig.from_options(imu_model=MEMS, **SITE)
    t = imu["t"].to_numpy()
    items = vehicle_items(cfg, t, imu[["gx", "gy", "gz"]].to_numpy(),
                          imu[["ax", "ay", "az"]].to_numpy())  # fmt: skip
    assert {it.kind for it in items} == {"zaru", "level"}
    items = [it for it in items if it.kind == "zaru"]
    k = np.searchsorted(t, [it.t for it in items])
    assert len(items) > 100
    assert np.linalg.norm(traj.vel_n[k], axis=1).max() < 0.01
    assert np.abs(traj.omega_nb_b[k]).max() == 0.0
    zaru = list(zip(k, items, strict=True))
    bias = errors[["bgx", "bgy", "bgz"]].to_numpy()
    z = np.array([(it.gyro_b - bias[j] - traj.rot_nb[j].inv().apply(it.rate_n)) / it.std
                  for j, it in zaru])  # fmt: skip
    assert abs(np.mean(z**2) - 1.0) < 4.0 * math.sqrt(2.0 / z.size), np.mean(z**2)


def test_the_gyro_bias_is_recovered_at_the_stops():
    """After the drive the filter's gyro bias is the simulated one within 3 sigma per axis,
    with a sigma well below the model's turn-on 30 deg/h (the stops observe it)."""
    rows: list = []
    traj, imu, sun_n, rng, errors = drive(3, 90.0, MEMS)
    closed_loop(traj, imu, sun_n, rng, MEMS, rows=rows)
    cfg = FuseConfig.from_options(imu_model=MEMS, **SITE, tilt_coupling=True)
    sol = run_fusion(imu, pd.DataFrame(rows), "eskf", None, cfg).solution.iloc[-1]
    truth = errors[["bgx", "bgy", "bgz"]].to_numpy()[-1]
    for i, c in enumerate("xyz"):
        est, std = sol[f"bg{c}"], sol[f"bg{c}_std"]
        assert abs(est - truth[i]) < 3.0 * std, (c, est, truth[i], std)
        assert std < 0.3 * MEMS.gyro_bias, (c, std)


def test_the_levelling_sigma_covers_the_acceleration():
    """Once a second the mean specific force, with the sigma of its recent horizontal
    change: at the true attitude and accelerometer bias, the horizontal specific force
    over that sigma has a mean square near 1 where the gate would take it (the vehicle's
    acceleration, the road's vibration, the white noise), and the gate holds back the
    onsets of the manoeuvres (a few percent)."""
    traj, imu, _, _, errors = drive(2, 200.0, MEMS)
    cfg = FuseConfig.from_options(imu_model=MEMS, **SITE)
    t = imu["t"].to_numpy()
    items = vehicle_items(cfg, t, imu[["gx", "gy", "gz"]].to_numpy(),
                          imu[["ax", "ay", "az"]].to_numpy())  # fmt: skip
    level = [it for it in items if it.kind == "level"]
    assert len(level) == 200  # one a second
    k = np.searchsorted(t, [it.t for it in level])
    bias = errors[["bax", "bay", "baz"]].to_numpy()
    z = np.array([traj.rot_nb[j].apply(it.force_b - bias[j])[:2] / it.std
                  for j, it in zip(k, level, strict=True)])  # fmt: skip
    taken = np.sum(z**2, axis=1) <= gate_limit(cfg.gate_probability, 2)
    assert 0.95 <= np.mean(taken) < 1.0, np.mean(taken)
    assert 0.6 <= np.mean(z[taken] ** 2) <= 1.4, np.mean(z[taken] ** 2)


def test_the_levelling_items_do_not_depend_on_how_the_samples_come():
    """The stream hands the samples over an epoch at a time, a log at once: the same
    levelling items (times, forces, sigmas), one a second."""
    _, imu, _, _, _ = drive(2, 30.0, MEMS)
    cfg = FuseConfig.from_options(imu_model=MEMS, **SITE)
    t = imu["t"].to_numpy()
    w, f = imu[["gx", "gy", "gz"]].to_numpy(), imu[["ax", "ay", "az"]].to_numpy()
    dt = float(t[1] - t[0])
    whole = [it for _, it in VehicleAiding(cfg, dt).items(t, w, f, 0) if it.kind == "level"]
    aiding, parts = VehicleAiding(cfg, dt), []
    for k in range(0, len(t), 37):
        s = slice(k, k + 37)
        parts += [it for _, it in aiding.items(t[s], w[s], f[s], k) if it.kind == "level"]
    assert [it.t for it in whole] == [it.t for it in parts] == list(np.arange(1.0, 31.0))
    for a, b in zip(whole, parts, strict=True):
        assert a.std == b.std and np.array_equal(a.force_b, b.force_b)


def test_the_levelling_leaves_the_gyro_bias_alone():
    """A levelling updates the tilt and the accelerometer bias, not the gyro's bias and
    scale factors (consider states: their rows of the gain are zero; docs/filter.md §12.2);
    with nothing held the update is filterpy's."""
    from filterpy.kalman import update

    rng = np.random.default_rng(1)
    a = rng.standard_normal((18, 18))
    P = a @ a.T / 18 + np.eye(18) * 1e-3
    x = rng.standard_normal(18) * 1e-3
    lin = level(Rotation.from_euler("ZYX", [0.3, 0.02, -0.01]), [0.1, -0.2, 9.81],
                np.zeros(3), 0.01)  # fmt: skip
    H = np.zeros((2, 18))
    H[:, :15] = lin.H
    index = {"bg": BG, "sg": slice(15, 18)}
    held = consider_states("level", True, index)
    assert held == [9, 10, 11, 15, 16, 17]
    assert consider_states("level", False, index) == [2, *held]
    assert consider_states("zaru", True, index) == []
    x1, P1 = consider_update(x, P, lin.residual, lin.R, H, held)
    np.testing.assert_array_equal(x1[held], x[held])
    PHt = P @ H.T
    K = np.linalg.solve(H @ PHt + lin.R, PHt.T).T
    K[held] = 0.0
    IKH = np.eye(18) - K @ H
    np.testing.assert_allclose(P1, IKH @ P @ IKH.T + K @ lin.R @ K.T, atol=1e-15)
    assert np.all(np.linalg.eigvalsh(P1) > 0)
    x2, P2 = consider_update(x, P, lin.residual, lin.R, H, [])
    x3, P3, *_ = update(x, P, lin.residual, lin.R, H)
    np.testing.assert_allclose(x2, x3, atol=1e-12)
    np.testing.assert_allclose(P2, P3, atol=1e-12)


def test_the_headings_observe_one_direction_the_levelling_the_tilt(drives):
    """A tilt-coupled heading sees the sun's azimuth in the body: the attitude error is
    observed along H (at the heading noise). The two directions it does not see (about
    the sun vector, about the horizontal axis across the sun's azimuth) are tilts the
    levelling observes, to the vehicle's acceleration: larger errors and sigmas there,
    bounded."""
    for seed, (traj, sun_n, (index, mats, covs, _)) in drives.items():
        late = traj.t[index] > 30.0
        err = (
            Rotation.from_matrix(traj.rot_nb[index[late]].as_matrix())
            * Rotation.from_matrix(mats[late]).inv()
        )
        dtheta = err.as_rotvec()  # ENU, true minus estimate
        h = np.stack([yaw_kernel(m, 0.0, 1.0, sun_n).H[0, :3] for m in mats[late]])
        seen = np.einsum("ni,ni->n", h, dtheta)
        across = np.cross([0.0, 0.0, 1.0], sun_n)
        across /= np.linalg.norm(across)
        hidden = np.hypot(dtheta @ sun_n, dtheta @ across)
        assert np.sqrt(np.mean(seen**2)) < 3.0 * HEADING_STD, seed
        assert np.sqrt(np.mean(hidden**2)) > 3.0 * np.sqrt(np.mean(seen**2)), seed
        # the filter knows it: its sigma along H is at the heading noise, across it more
        var_seen = np.einsum("ni,nij,nj->n", h, covs[late], h) / np.einsum("ni,ni->n", h, h)
        var_sun = np.einsum("i,nij,j->n", sun_n, covs[late], sun_n)
        var_across = np.einsum("i,nij,j->n", across, covs[late], across)
        assert np.all(np.sqrt(var_sun) > 2.0 * np.sqrt(var_seen)), seed
        assert np.all(np.sqrt(var_across) > 2.0 * np.sqrt(var_seen)), seed
        assert np.degrees(np.sqrt(var_across.max())) < 0.2, seed


def test_unaided_headings_and_attitude_are_consistent(drives):
    """The headings' NIS mean is 1 within its band on each drive (many independent
    innovations); each drive's attitude RMS(err/sigma) is within 0.6-1.5 on every angle,
    its errors below 0.1 deg (docs/filter.md §12.4)."""
    for seed, (traj, _, out) in drives.items():
        nis = out[3]
        half = 1.96 * math.sqrt(2.0 / nis.size)
        assert abs(np.mean(nis) - 1.0) < half, (seed, np.mean(nis), nis.size)
        s = scores(traj, *out[:3])
        for angle in ANGLES:
            assert 0.6 <= s[angle][1] <= 1.5, (seed, s)
            assert s[angle][0] < 0.1, (seed, s)  # [deg]


def test_the_graph_is_consistent_without_velocity_aiding(drives):
    """The graph (batch) on the headings of a closed-loop drive, with its zero-rate factors
    at the stops: RMS(err/sigma) and errors like the ESKF's."""
    rows: list = []
    traj, imu, sun_n, rng, _ = drive(2, 90.0, MEMS)
    closed_loop(traj, imu, sun_n, rng, MEMS, rows=rows)
    s = replay(traj, imu, rows, MEMS, "graph")
    for angle in ANGLES:
        assert 0.2 <= s[angle][1] <= 2.2, s
        assert s[angle][0] < 0.25, s


@pytest.mark.slow
def test_unaided_attitude_sigmas_over_drives():
    """Twelve drives of 200 s (seeds 0-11): pooled RMS(err/sigma) yaw / pitch / roll
    0.93 / 0.93 / 0.94 (docs/filter.md §12.4); ten of the twelve drives within 0.6-1.5 on
    every angle, the others drawn small (0.44, 0.55: the accelerometer bias's draw before
    the first turn); errors below 0.15 deg."""
    ratios, errors = [], []
    for seed in range(12):
        traj, _, out = run(seed, 200.0)
        s = scores(traj, *out[:3])
        ratios.append([s[a][1] for a in ANGLES])
        errors.append([s[a][0] for a in ANGLES])
    pooled = np.sqrt(np.mean(np.square(ratios), axis=0))
    assert np.all((pooled >= 0.8) & (pooled <= 1.2)), pooled
    assert 0.4 <= np.min(ratios) and np.max(ratios) <= 1.5, ratios
    assert np.mean((np.array(ratios) >= 0.6).all(axis=1)) >= 0.8, ratios  # drives in band
    assert np.max(errors) < 0.15, errors  # [deg]
