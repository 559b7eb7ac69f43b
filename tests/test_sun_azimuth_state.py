"""No clock (docs/filter.md, "No clock"): measurements of the sun's body azimuth only; the
sun's ENU azimuth and its rate are filter states and the heading is relative to the
initial yaw, consistent over a MEMS UGV drive, with a sigma that grows as the sun's rate
and the gyro bias allow. Also the 2x2 sun-direction covariance and the heading-bias state."""

import functools
import math

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

import polins
from polins.errors import UserInputError
from polins.frames import wrap_angle
from polins.fusion import run_fusion
from polins.fusion.config import FuseConfig
from polins.fusion.items import item_model, items_from_table
from polins.fusion.measurement import sun_azimuth_kernel
from polins.sim.imu import ideal_imu, imu_errors
from polins.sim.trajectory import ugv_drive
from polins.site import Site

SITE = Site(lat_deg=45.6234, lon_deg=126.7264, alt_m=148.74)
EPOCH = pd.Timestamp("2023-09-05T01:30:00+00:00")  # 09:30 local
AZ_STD = math.radians(0.3)
EL_STD = math.radians(1.0)


def sun_n_at(t_s):
    pos = polins.sun_position(EPOCH + pd.to_timedelta(t_s, unit="s"), SITE.lat_deg, SITE.lon_deg)
    return polins.sun_vector_n(pos.azimuth, pos.zenith).reshape(-1, 3)


@functools.cache
def drive(seed, duration_s):
    """A MEMS UGV drive at 100 Hz and the sun's body azimuth and elevation at 2 Hz."""
    model = polins.load_imu("mems-typical")
    rng = np.random.default_rng(seed)
    traj = ugv_drive(duration_s=duration_s, rate_hz=100.0, rng=rng, yaw0=rng.uniform(-3, 3))
    imu, _ = imu_errors(ideal_imu(traj), model, rng)
    tm = np.arange(0.5, duration_s, 0.5)
    k = np.searchsorted(traj.t, tm - 1e-9)
    sun_b = np.einsum("nji,nj->ni", traj.rot_nb[k].as_matrix(), sun_n_at(tm))
    meas = pd.DataFrame({"t": tm})
    meas["sun_azimuth_b"] = wrap_angle(
        np.arctan2(sun_b[:, 1], sun_b[:, 0]) + rng.normal(0.0, AZ_STD, tm.size)
    )
    meas["sun_azimuth_b_std"] = AZ_STD
    meas["sun_elevation_b"] = np.arcsin(sun_b[:, 2]) + rng.normal(0.0, EL_STD, tm.size)
    meas["sun_elevation_b_std"] = EL_STD
    speed = np.linalg.norm(traj.vel_n, axis=1)
    t_rest = traj.t[(speed < 1e-6) & (np.round(traj.t * 10.0, 6) % 1.0 == 0.0)]
    return model, traj, imu, meas, tuple(t_rest)


def relative_z(seed, duration_s, **options):
    """Relative-heading errors / sigma of the solution rows after 5 s, and the solution."""
    model, traj, imu, meas, t_rest = drive(seed, duration_s)
    config = FuseConfig.from_options(
        None, imu_model=model, site=SITE, output_rate_hz=1.0, zupt_std=0.01,
        stationary=t_rest, **options,
    )  # fmt: skip
    with pytest.warns(UserWarning, match="no-clock mode"):
        sol = run_fusion(imu, meas, config=config).solution
    k = np.searchsorted(traj.t, sol["t"].to_numpy() - 1e-9)
    yaw_true = traj.rot_nb[k].as_euler("ZYX")[:, 0]
    yaw_true0 = traj.rot_nb[0].as_euler("ZYX")[0]
    err = wrap_angle(sol["yaw"].to_numpy() - (yaw_true - yaw_true0))
    keep = sol["t"].to_numpy() >= 5.0
    return err[keep] / sol["yaw_std"].to_numpy()[keep], sol[keep]


def test_sun_azimuth_model_jacobians():
    # the kernel against finite differences, in the attitude and the sun azimuth
    mat = Rotation.from_euler("ZYX", [0.7, 0.08, -0.05]).as_matrix()
    a, e, z = 1.1, 0.6, 0.3
    lin = sun_azimuth_kernel(mat, z, 1e-6, a, e)
    for i in range(3):
        d = np.zeros(3)
        d[i] = 1e-6
        plus = sun_azimuth_kernel(Rotation.from_rotvec(d).as_matrix() @ mat, z, 1e-6, a, e)
        assert (lin.residual[0] - plus.residual[0]) / 1e-6 == pytest.approx(lin.H[0, i], abs=1e-5)
    plus = sun_azimuth_kernel(mat, z, 1e-6, a + 1e-6, e)
    assert (lin.residual[0] - plus.residual[0]) / 1e-6 == pytest.approx(-lin.H[0, 2], abs=1e-5)
    # level body: h = sun azimuth - yaw
    level = Rotation.from_euler("z", 0.4).as_matrix()
    lin = sun_azimuth_kernel(level, 0.0, 1e-6, a, e)
    assert lin.residual[0] == pytest.approx(-(a - 0.4))


def test_no_clock_rows_become_sun_azimuth_items():
    rows = {"t": [0.0, 1.0], "sun_azimuth_b": [0.5, np.nan], "sun_azimuth_b_std": [0.01, 0.01]}
    items = items_from_table(rows)
    assert [it.kind for it in items] == ["sun_azimuth", "sun_azimuth"]
    assert items[0].valid and not items[1].valid and "NaN" in items[1].reason
    with pytest.raises(ValueError, match="sun azimuth state"):
        item_model(items[0], np.eye(3), None, False)
    # a table with a yaw is not the no-clock mode: its sun_azimuth_b is information only
    rows["yaw"], rows["yaw_std"] = [0.1, 0.2], [0.01, 0.01]
    assert [it.kind for it in items_from_table(rows)] == ["yaw", "yaw"]


def test_no_clock_refused_on_the_graph():
    model, _traj, imu, meas, _ = drive(0, 20.0)
    config = FuseConfig.from_options(None, imu_model=model, site=SITE)
    with pytest.raises(UserInputError, match="need the ESKF"):
        run_fusion(imu, meas, backend="graph", config=config)
    with pytest.raises(UserInputError, match="no_clock=False"):
        run_fusion(imu, meas, config=FuseConfig.from_options(config, no_clock=False))


def test_no_clock_relative_heading_fast():
    # 90 s, 3 seeds; measured: RMS(err/sigma) 1.00 (0.65 / 1.55 / 0.52), 100 % within 3 sigma
    z = np.concatenate([relative_z(seed, 90.0)[0] for seed in range(3)])
    rms = float(np.sqrt(np.mean(z**2)))
    assert 0.5 < rms < 1.3, rms
    assert np.mean(np.abs(z) < 3.0) >= 0.98
    sol = relative_z(0, 90.0)[1]
    # the sun's azimuth is reported with its sigma; its rate too
    assert {"sun_azimuth_n", "sun_azimuth_n_std", "sun_azimuth_rate"} <= set(sol.columns)


@pytest.mark.slow
def test_no_clock_relative_heading_ten_minutes():
    # 10 min, 3 seeds (measured: RMS(err/sigma) 1.16 / 0.91 / 1.22, 100 % within 3 sigma);
    # the sigma grows about linearly, 2.6-2.8 deg after 10 min (docs/filter.md, "No clock")
    zs, sols = zip(*(relative_z(seed, 600.0) for seed in range(3)), strict=True)
    z = np.concatenate(zs)
    rms = float(np.sqrt(np.mean(z**2)))
    assert 0.5 < rms < 1.3, rms
    assert np.mean(np.abs(z) < 3.0) >= 0.98
    for sol in sols:
        std = np.degrees(sol["yaw_std"].to_numpy())
        t = sol["t"].to_numpy()
        rate = np.polyfit(t, std, 1)[0] * 3600.0  # [deg/h]
        assert 10.0 < rate < 24.0, rate  # below the sun's rate bound and the gyro bias
        assert std[-1] > 5.0 * std[np.searchsorted(t, 60.0)]
