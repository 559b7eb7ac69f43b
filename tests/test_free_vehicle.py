"""A vehicle without velocity aiding: what the headings observe, and the sigmas over drives.

The drives are ``polins simulate --scenario ugv``'s (benchmarks/bench_free_vehicle.py): the
same trajectory, mounting, road vibration and ``mems-typical`` errors for a seed, with no
``[vehicle]`` table (no non-holonomic, zero-velocity or odometer updates). The headings are
drawn in closed loop as the camera loop makes them: the sun's azimuth seen in the body,
levelled with the filter's own attitude (the tilt-coupled model of docs/filter.md §5.2),
0.011 deg at 5 Hz (docs/filter.md §12).
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
from polins.fusion.measurement import yaw_kernel
from polins.fusion.vehicle import vehicle_items
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
    return {seed: run(seed, 90.0) for seed in (2, 3)}


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
    assert {it.kind for it in items} == {"zaru"}
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


def test_the_headings_observe_one_direction_of_the_attitude(drives):
    """A tilt-coupled heading sees the sun's azimuth in the body: the attitude error is
    observed along H (at the heading noise), not about the sun vector nor about the
    horizontal axis across the sun's azimuth, which carry the error of a free vehicle."""
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
        assert np.sqrt(np.mean(hidden**2)) > 10.0 * np.sqrt(np.mean(seen**2)), seed
        # the filter knows it: its sigma along H is at the heading noise, across it 10x more
        var_seen = np.einsum("ni,nij,nj->n", h, covs[late], h) / np.einsum("ni,ni->n", h, h)
        var_sun = np.einsum("i,nij,j->n", sun_n, covs[late], sun_n)
        assert np.all(np.sqrt(var_sun) > 10.0 * np.sqrt(var_seen)), seed


def test_unaided_headings_are_consistent_and_the_sigmas_scatter_over_drives(drives):
    """The headings' NIS mean is 1 within its band on each drive (many independent
    innovations); the attitude's RMS(err/sigma) of one drive is a statistic of few
    degrees of freedom (a drive's hidden error is mostly a few random constants), 0.34-2.02
    over the drives of docs/filter.md §12.3; pooled over these two, near 1."""
    ratios = []
    for seed, (traj, _, out) in drives.items():
        nis = out[3]
        half = 1.96 * math.sqrt(2.0 / nis.size)
        assert abs(np.mean(nis) - 1.0) < half, (seed, np.mean(nis), nis.size)
        s = scores(traj, *out[:3])
        ratios.append([s[a][1] for a in ANGLES])
        for angle in ANGLES:
            assert 0.15 <= s[angle][1] <= 2.2, (seed, s)
            assert s[angle][0] < 0.25, (seed, s)  # [deg]
    pooled = np.sqrt(np.mean(np.square(ratios), axis=0))
    assert np.all((pooled >= 0.5) & (pooled <= 1.5)), pooled


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
    0.96 / 0.94 / 1.10 (docs/filter.md §12.3); single drives 0.34-2.02."""
    ratios = []
    for seed in range(12):
        traj, _, out = run(seed, 200.0)
        s = scores(traj, *out[:3])
        ratios.append([s[a][1] for a in ANGLES])
    pooled = np.sqrt(np.mean(np.square(ratios), axis=0))
    assert np.all((pooled >= 0.8) & (pooled <= 1.2)), pooled
    assert 0.3 < np.min(ratios) and np.max(ratios) < 2.2, ratios
