"""No clock (docs/filter.md, "No clock"): measurements of the sun's body azimuth only; the
sun's ENU azimuth and its rate are filter states and the heading is relative to the
initial yaw, consistent over a MEMS UGV drive, with a sigma that grows as the sun's rate
and the gyro bias allow. Also the 2x2 sun-direction covariance and the heading-bias state."""

import functools
import math
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

import polins
from polins.errors import UserInputError
from polins.frames import wrap_angle
from polins.fusion import build_filter, run_fusion
from polins.fusion.config import FuseConfig
from polins.fusion.items import MeasurementItem, item_model, items_from_table, measurement_items
from polins.fusion.measurement import sun_azimuth_kernel, sun_direction_cov_b
from polins.fusion.sky_states import ModelPart, without_bias_part
from polins.fusion.vehicle import with_standstill
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


def mems_drive(rng, duration_s, period_s, **drive_options):
    """A ``mems-typical`` IMU on a 100 Hz UGV drive, the image times every ``period_s``
    from ``period_s`` on and their IMU sample indices."""
    model = polins.load_imu("mems-typical")
    traj = ugv_drive(duration_s=duration_s, rate_hz=100.0, rng=rng, **drive_options)
    imu, _ = imu_errors(ideal_imu(traj), model, rng)
    tm = np.arange(period_s, duration_s, period_s)
    return model, traj, imu, tm, np.searchsorted(traj.t, tm - 1e-9)


def rest_times(traj):
    """The drive's standstill times on a 0.1 s grid (zero-velocity updates)."""
    speed = np.linalg.norm(traj.vel_n, axis=1)
    return tuple(traj.t[(speed < 1e-6) & (np.round(traj.t * 10.0, 6) % 1.0 == 0.0)])


def fused(drive_out, backend="eskf", drop=(), **options):
    """The truth and the fused solution (1 Hz rows, zero-velocity updates at the stops) of
    a drive ``(model, traj, imu, meas, t_rest)``; ``drop``: measurement columns not given."""
    model, traj, imu, meas, t_rest = drive_out
    config = FuseConfig.from_options(
        None, imu_model=model, site=SITE, output_rate_hz=1.0, **options
    )
    meas = with_standstill(meas.drop(columns=list(drop)), t_rest, 0.01)
    return traj, run_fusion(imu, meas, backend, config=config).solution


@functools.cache
def drive(seed, duration_s):
    """A MEMS UGV drive at 100 Hz and the sun's body azimuth and elevation at 2 Hz."""
    rng = np.random.default_rng(seed)
    model, traj, imu, tm, k = mems_drive(rng, duration_s, 0.5, yaw0=rng.uniform(-3, 3))
    sun_b = np.einsum("nji,nj->ni", traj.rot_nb[k].as_matrix(), sun_n_at(tm))
    meas = pd.DataFrame({"t": tm})
    meas["sun_azimuth_b"] = wrap_angle(
        np.arctan2(sun_b[:, 1], sun_b[:, 0]) + rng.normal(0.0, AZ_STD, tm.size)
    )
    meas["sun_azimuth_b_std"] = AZ_STD
    meas["sun_elevation_b"] = np.arcsin(sun_b[:, 2]) + rng.normal(0.0, EL_STD, tm.size)
    meas["sun_elevation_b_std"] = EL_STD
    return model, traj, imu, meas, rest_times(traj)


def relative_z(seed, duration_s, backend="eskf", **options):
    """Relative-heading errors / sigma of the solution rows after 5 s, and the solution."""
    with pytest.warns(UserWarning, match="no-clock mode"):
        traj, sol = fused(drive(seed, duration_s), backend, **options)
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


def test_no_clock_false_is_refused_on_a_no_clock_table():
    model, _traj, imu, meas, _ = drive(0, 20.0)
    config = FuseConfig.from_options(None, imu_model=model, site=SITE)
    with pytest.raises(UserInputError, match="no_clock=off"):
        run_fusion(imu, meas, config=FuseConfig.from_options(config, no_clock=False))


def test_no_clock_relative_heading_fast():
    # 90 s, 3 seeds; measured: RMS(err/sigma) 1.00 (0.65 / 1.55 / 0.52), 100 % within 3 sigma
    z = np.concatenate([relative_z(seed, 90.0)[0] for seed in range(3)])
    rms = float(np.sqrt(np.mean(z**2)))
    assert 0.5 < rms < 1.3, rms
    assert np.mean(np.abs(z) < 3.0) >= 0.98
    sol = relative_z(0, 90.0)[1]
    # the sigma would grow at ~ 24*30/sqrt(24^2+30^2) = 19 deg/h (docs/filter.md); the
    # stops' zero-rate updates observe the z gyro bias (§12.1): 3.9 deg/h on this drive
    rate = np.polyfit(sol["t"], np.degrees(sol["yaw_std"]), 1)[0] * 3600.0
    assert 1.0 < rate < 12.0, rate
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


# ----------------------------------------------------------------------------- heading bias
WHITE_STD = math.radians(0.1)
CORR_STD = math.radians(0.5)
CORR_TAU_S = 60.0


@functools.cache
def biased_drive(seed):
    """A 120 s MEMS UGV drive with a 5 Hz yaw whose error is white (0.1 deg) plus a
    Gauss-Markov part (0.5 deg, 60 s): each row reports both parts, as polins.measure
    does (``yaw_std`` the total, ``yaw_std_model`` and ``yaw_std_correlated`` the
    correlated part)."""
    rng = np.random.default_rng(100 + seed)
    model, traj, imu, tm, k = mems_drive(rng, 120.0, 0.2)
    phi = math.exp(-0.2 / CORR_TAU_S)
    bias = np.empty(tm.size)
    bias[0] = rng.normal(0.0, CORR_STD)
    for i in range(1, tm.size):
        bias[i] = phi * bias[i - 1] + math.sqrt(1.0 - phi**2) * rng.normal(0.0, CORR_STD)
    yaw = traj.rot_nb[k].as_euler("ZYX")[:, 0] + bias + rng.normal(0.0, WHITE_STD, tm.size)
    meas = pd.DataFrame({"t": tm, "yaw": wrap_angle(yaw)})
    meas["yaw_std"] = math.hypot(WHITE_STD, CORR_STD)
    meas["yaw_std_correlated"] = CORR_STD
    meas["yaw_std_model"] = CORR_STD
    return model, traj, imu, meas, rest_times(traj)


def heading_z(seeds, backend="eskf", **options):
    """Heading errors / sigma after 10 s (self-alignment), pooled over seeds."""
    z = []
    for seed in seeds:
        traj, sol = fused(biased_drive(seed), backend, **options)
        sol = sol[sol["t"] >= 10.0]
        k = np.searchsorted(traj.t, sol["t"].to_numpy() - 1e-9)
        err = wrap_angle(sol["yaw"].to_numpy() - traj.rot_nb[k].as_euler("ZYX")[:, 0])
        z.append(err / sol["yaw_std"].to_numpy())
    return np.concatenate(z)


def test_heading_bias_state_pairs_with_the_correlated_sigma():
    # honest per-image sigmas (0.51 deg) whose 0.5 deg part is correlated over 60 s: without
    # the bias state (inf) the filter averages them down; with it (sigma and time of the
    # sky's correlated error) it is consistent, and so are the defaults, whose bias variance
    # follows the rows' yaw_std_model (correlation time 300 s, not the true 60 s)
    seeds = range(4)
    z_without = heading_z(seeds, heading_bias_std="off")
    z_with = heading_z(seeds, heading_bias_std=CORR_STD, heading_bias_tau_s=CORR_TAU_S)
    z_default = heading_z(seeds)
    rms = [float(np.sqrt(np.mean(z**2))) for z in (z_without, z_with, z_default)]
    assert rms[0] > 2.0, rms
    assert 0.6 < rms[1] < 1.4, rms
    assert 0.6 < rms[2] < 1.4, rms
    assert np.mean(np.abs(z_with) < 3.0) >= 0.98
    assert np.mean(np.abs(z_default) < 3.0) >= 0.98


def test_bias_part_taken_out_of_the_heading_items():
    # a yaw keeps its white part; a sun vector loses the part from its azimuth displacement
    # (the heading variance times cos^2 of the body elevation), not from its elevation
    yaw = MeasurementItem(0.0, "yaw", math.hypot(0.003, 0.004), yaw=0.1, model_std=0.004)
    assert without_bias_part(yaw, 1.0).std == pytest.approx(0.003)
    assert without_bias_part(yaw, 0.002**2).std == pytest.approx(math.sqrt(0.005**2 - 0.002**2))
    assert without_bias_part(replace(yaw, model_std=0.0), 1.0).std == yaw.std
    elev = 0.5
    s = np.array([math.cos(elev) * math.cos(1.0), math.cos(elev) * math.sin(1.0), math.sin(elev)])
    az_std = math.cos(elev) * 0.005  # the heading sigma 0.005 rad as a tangent displacement
    cov = sun_direction_cov_b(s, az_std, 0.02)
    sun = MeasurementItem(0.0, "sun", 0.01, sun_b=s, sun_n=s, cov_b=cov, model_std=0.004)
    white = without_bias_part(sun, 1.0).cov_b
    np.testing.assert_allclose(white, sun_direction_cov_b(s, math.cos(elev) * 0.003, 0.02),
                               atol=1e-15)  # fmt: skip
    # the default bias variance: the median of the rows' squared model parts
    part, P = ModelPart(300.0), np.zeros((1, 1))
    densities = [part.take(replace(yaw, model_std=m), P, 0)[1] for m in (0.001, 0.003, 0.002)]
    assert part.var == pytest.approx(0.002**2)
    assert P[0, 0] == pytest.approx((0.001**2 + 0.003**2) / 2)  # the largest median seen
    assert densities[-1] == pytest.approx(2.0 * 0.002**2 / 300.0)
    window = ModelPart(300.0, window=2)  # the median of the last two rows only
    for m in (0.004, 0.001, 0.003):
        window.take(replace(yaw, model_std=m), np.zeros((1, 1)), 0)
    assert window.var == pytest.approx((0.001**2 + 0.003**2) / 2)


# ----------------------------------------------------------------------------- 2x2 sun covariance
def test_sun_direction_covariance_axes():
    s = np.array([math.cos(0.5) * math.cos(1.0), math.cos(0.5) * math.sin(1.0), math.sin(0.5)])
    cov = sun_direction_cov_b(s, 0.01, 0.05)
    u_a = np.array([-math.sin(1.0), math.cos(1.0), 0.0])
    assert u_a @ cov @ u_a == pytest.approx(1e-4)
    assert np.trace(cov) == pytest.approx(1e-4 + 2.5e-3)
    np.testing.assert_allclose(cov @ s, 0.0, atol=1e-15)


@functools.cache
def narrow_drive(seed):
    """A 60 s MEMS UGV drive; sun vectors at 5 Hz from a narrow-field fit: 0.2 deg along the
    azimuth, 3 deg along the elevation (``sun_elevation_b_std``)."""
    rng = np.random.default_rng(200 + seed)
    model, traj, imu, tm, k = mems_drive(rng, 60.0, 0.2)
    sun_n = sun_n_at(tm)
    sun_b = np.einsum("nji,nj->ni", traj.rot_nb[k].as_matrix(), sun_n)
    az = np.arctan2(sun_b[:, 1], sun_b[:, 0]) + rng.normal(0.0, math.radians(0.2), tm.size)
    el = np.arcsin(sun_b[:, 2]) + rng.normal(0.0, math.radians(3.0), tm.size)
    meas = pd.DataFrame({"t": tm})
    meas[["sun_bx", "sun_by", "sun_bz"]] = np.column_stack(
        [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]
    )
    meas[["sun_nx", "sun_ny", "sun_nz"]] = sun_n
    meas["sun_std"] = math.radians(0.2) * np.cos(el)  # along the azimuth (tangent)
    meas["sun_elevation_b_std"] = math.radians(3.0)
    return model, traj, imu, meas, rest_times(traj)


def attitude_z(seeds, drop, backend="eskf"):
    """Roll, pitch, yaw errors / sigma after 5 s, pooled; ``drop``: columns not given."""
    z = []
    for seed in seeds:
        traj, sol = fused(narrow_drive(seed), backend, drop)
        sol = sol[sol["t"] >= 5.0]
        k = np.searchsorted(traj.t, sol["t"].to_numpy() - 1e-9)
        ypr = traj.rot_nb[k].as_euler("ZYX")
        for j, name in enumerate(("yaw", "pitch", "roll")):
            err = wrap_angle(sol[name].to_numpy() - ypr[:, j])
            z.append(err / sol[f"{name}_std"].to_numpy())
    return np.concatenate(z)


def test_sun_update_carries_the_fits_2x2_covariance():
    # with the elevation sigma the sun update is consistent (measured: roll/pitch/yaw
    # RMS(err/sigma) 0.59, 100 % within 3 sigma); with R = sun_std^2 I (an old table) the
    # poorly determined elevation makes it overconfident (2.4, 75 %)
    z_cov = attitude_z(range(3), ())
    z_iso = attitude_z(range(3), ("sun_elevation_b_std",))
    rms_cov = float(np.sqrt(np.mean(z_cov**2)))
    rms_iso = float(np.sqrt(np.mean(z_iso**2)))
    assert 0.4 < rms_cov < 1.3, rms_cov
    assert np.mean(np.abs(z_cov) < 3.0) >= 0.98
    assert rms_iso > 1.8, rms_iso


def test_no_clock_streaming_matches_fuse():
    # build_filter(no_clock=True) fed row by row gives fuse's relative heading
    model, _traj, imu, meas, t_rest = drive(1, 30.0)
    options = dict(imu_model=model, site=SITE)
    rows = with_standstill(meas, t_rest, 0.01)
    with pytest.warns(UserWarning, match="no-clock mode"):
        batch = run_fusion(imu, rows, config=FuseConfig.from_options(None, **options)).solution
    filt = build_filter(0.0, 0.01, no_clock=True, **options)
    for row in meas.itertuples(index=False):
        sky = {c: getattr(row, c) for c in meas.columns if c != "t"}
        filt.add_items(measurement_items(row.t, sky=sky))
    filt.add_items([MeasurementItem(ts, "zupt", 0.01) for ts in t_rest])
    data = imu.to_numpy()
    filt.propagate_many(data[:, 0], data[:, 1:4], data[:, 4:7])
    st, last = filt.state(), batch.iloc[-1]
    assert st.t == pytest.approx(last["t"])
    yaw = st.rot_nb.as_euler("ZYX")[0]
    assert abs(wrap_angle(yaw - last["yaw"])) < 1e-3
    assert math.sqrt(st.att_cov[2, 2]) == pytest.approx(last["yaw_std"], rel=0.05)


def test_ambiguous_rows_are_axes():
    # a third of the rows could not tell the sun from the antisun: measure reports one
    # candidate at random and the other in sun_azimuth_b_alt; taken as axes they keep the
    # relative heading consistent, taken as directions half of them are gated out
    model, traj, imu, meas, t_rest = drive(2, 90.0)
    rng = np.random.default_rng(7)
    amb = rng.random(len(meas)) < 1.0 / 3.0
    amb[:3] = False  # the first rows set the sun's azimuth
    flip = amb & (rng.random(len(meas)) < 0.5)
    meas = meas.copy()
    meas.loc[flip, "sun_azimuth_b"] = wrap_angle(meas.loc[flip, "sun_azimuth_b"] + np.pi)
    meas["sun_azimuth_b_alt"] = np.where(amb, wrap_angle(meas["sun_azimuth_b"] + np.pi), np.nan)
    config = FuseConfig.from_options(None, imu_model=model, site=SITE, output_rate_hz=1.0)
    with pytest.warns(UserWarning, match="no-clock mode"):
        result = run_fusion(imu, with_standstill(meas, t_rest, 0.01), config=config)
    assert result.updates["accepted"].mean() > 0.98
    sol = result.solution[result.solution["t"] >= 5.0]
    k = np.searchsorted(traj.t, sol["t"].to_numpy() - 1e-9)
    yaw_rel = traj.rot_nb[k].as_euler("ZYX")[:, 0] - traj.rot_nb[0].as_euler("ZYX")[0]
    z = wrap_angle(sol["yaw"].to_numpy() - yaw_rel) / sol["yaw_std"].to_numpy()
    assert np.max(np.abs(z)) < 3.0
    with pytest.warns(UserWarning, match="no-clock mode"):
        directions = run_fusion(imu, meas.drop(columns="sun_azimuth_b_alt"), config=config)
    rejected = ~directions.updates["accepted"].to_numpy()
    assert rejected.sum() >= 0.8 * flip.sum()
