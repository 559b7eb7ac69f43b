"""GTSAM graph backend: factor semantics, Jacobians, equality with the ESKF, UGV consistency."""

import dataclasses
import functools
import importlib
import re
import sys

# The README's test command installs the graph extra: a missing gtsam is an error here, not a skip.
import gtsam
import numpy as np
import pandas as pd
import pytest
from numerics import numjac
from scipy.spatial.transform import Rotation
from test_robustness import SITE, check_gap_skipped, drive, yaw_z

import polins
import polins.fusion
import polins.fusion.graph as G
from polins.frames import wrap_angle, yaw_from_rot_nb
from polins.fusion.config import TIME_TOL_S, FuseConfig
from polins.fusion.graph.solvers import local_worst
from polins.fusion.measurement import sun_measurement
from polins.fusion.vehicle import with_standstill
from polins.ins.state import NavState, solution_table
from polins.sim.imu import ideal_imu, imu_errors
from polins.sim.trajectory import turntable, ugv_drive
from polins.sky.ephemeris import sun_vector_n

X, V, B = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.V, gtsam.symbol_shorthand.B

ZENITH = np.radians(49.0)
AZIMUTH = np.radians(200.0)
SUN_N = sun_vector_n(AZIMUTH, ZENITH)
ROT_NB = Rotation.from_euler("ZYX", [0.3, 0.05, -0.02])
ANGLES = ("roll", "pitch", "yaw")


def graph_run(imu, meas, rot_nb0=None, **options):
    """The graph backend's result (``run_fusion`` with ``FuseConfig`` options)."""
    return polins.fusion.run_fusion(imu, meas, "graph", rot_nb0, FuseConfig.from_options(**options))


def graph(imu, meas, rot_nb0=None, **options):
    """The graph backend's solution table."""
    return graph_run(imu, meas, rot_nb0, **options).solution


def pose_values(rot_nb, pos=(1.0, 2.0, 3.0), vel=None, bias=None):
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3(gtsam.Rot3(rot_nb.as_matrix()), np.asarray(pos, float)))
    if vel is not None:
        values.insert(V(0), np.asarray(vel, dtype=float))
    if bias is not None:
        values.insert(B(0), G.bias_from_polins(bias))
    return values


def check_factor_jacobians(factor, values, keys_dims):
    """GTSAM's (whitened) Jacobians of a factor equal central differences of its whitened
    error under GTSAM's retraction of each variable."""
    A, _b = factor.linearize(values).jacobian()
    col = 0
    for key, dim in keys_dims:

        def err(d, key=key):
            v = gtsam.Values(values)
            if gtsam.Symbol(key).chr() == ord("x"):
                v.update(key, values.atPose3(key).retract(d))
            elif gtsam.Symbol(key).chr() == ord("b"):
                v.update(key, values.atConstantBias(key).retract(d))
            else:
                v.update(key, values.atVector(key) + d)
            return factor.whitenedError(v)

        np.testing.assert_allclose(
            A[:, col : col + dim], numjac(err, dim, eps=1e-6), atol=1e-6, rtol=1e-6
        )
        col += dim


# ----------------------------------------------------------------------------- GTSAM semantics
def test_attitude_factor_pose3_semantics_and_error_size():
    """AttitudeFactorPose3(key, nRef=sun_n, model, bMeasured=sun_b) in GTSAM 4.3."""
    sun_b = ROT_NB.inv().apply(SUN_N)
    f = G.sun_factor(X(0), SUN_N, sun_b, np.radians(0.5))
    np.testing.assert_allclose(f.nRef().point3(), SUN_N, atol=1e-15)
    np.testing.assert_allclose(f.bMeasured().point3(), sun_b, atol=1e-15)
    # Zero error at the truth.
    assert np.max(np.abs(f.evaluateError(pose_values(ROT_NB).atPose3(X(0))))) < 1e-12
    # A 1 deg yaw offset: the predicted direction turns by theta about Up, with
    # 2 sin(theta/2) = 2 sin(Z) sin(0.5 deg); the error norm is sin(theta) (~ sin Z * 1 deg).
    for sign in (1.0, -1.0):
        rot = Rotation.from_euler("Z", sign * np.radians(1.0)) * ROT_NB
        e = f.evaluateError(pose_values(rot).atPose3(X(0)))
        theta = 2.0 * np.arcsin(np.sin(ZENITH) * np.sin(np.radians(0.5)))
        assert np.linalg.norm(e) == pytest.approx(np.sin(theta), rel=1e-9)
        assert np.linalg.norm(e) == pytest.approx(0.013172, abs=1e-6)
        # Frame and sign: e = B(sun_n)^T (R_nb sun_b), the rotated measurement in the
        # tangent basis of the reference; to first order B^T (dyaw z x sun_n) (the second
        # order term is dyaw^2 / 2 = 1.5e-4).
        basis = gtsam.Unit3(SUN_N).basis()
        np.testing.assert_allclose(e, basis.T @ rot.apply(sun_b), atol=1e-15)
        first_order = basis.T @ np.cross([0.0, 0.0, sign * np.radians(1.0)], SUN_N)
        np.testing.assert_allclose(e, first_order, atol=1.6e-4)
        assert np.dot(e, first_order) > 0.99 * np.linalg.norm(e) * np.linalg.norm(first_order)
    # The argument order matters: swapping reference and measurement is not zero at the truth.
    swapped = G.sun_factor(X(0), sun_b, SUN_N, np.radians(0.5))
    assert np.linalg.norm(swapped.evaluateError(pose_values(ROT_NB).atPose3(X(0)))) > 0.1


def test_attitude_factor_jacobian_frames_and_eskf_information():
    """GTSAM's Jacobian is on the body-right perturbation R exp(w_b); mapped to the ESKF's
    navigation-frame left perturbation (J_n = J_b R^T) it carries the same information as
    the ESKF's sun measurement (polins.fusion.measurement.sun_measurement)."""
    rot_true = Rotation.from_rotvec([0.004, -0.003, 0.01]) * ROT_NB
    sun_b = rot_true.inv().apply(SUN_N)
    std = np.radians(0.5)
    f = G.sun_factor(X(0), SUN_N, sun_b, std)
    values = pose_values(ROT_NB)
    check_factor_jacobians(f, values, [(X(0), 6)])
    A, _ = f.linearize(values).jacobian()
    j_b = A[:, :3] * std
    mat = ROT_NB.as_matrix()

    def err_left(d):
        return f.evaluateError(pose_values(Rotation.from_rotvec(d) * ROT_NB).atPose3(X(0)))

    j_n = j_b @ mat.T
    np.testing.assert_allclose(j_n, numjac(err_left, 3, eps=1e-6), atol=1e-8)
    # At the truth both models project the attitude error on the plane normal to sun_n:
    # J^T J = H^T H = [sun_n x]^T [sun_n x] (rotations about sun_n are unobserved).
    a_true, _ = f.linearize(pose_values(rot_true)).jacobian()
    j_true = a_true[:, :3] * std @ rot_true.as_matrix().T
    lin = sun_measurement(rot_true, sun_b, SUN_N, std)
    cross = np.cross(np.eye(3), SUN_N)  # rows: e_i x sun_n
    expected = cross @ cross.T
    np.testing.assert_allclose(j_true.T @ j_true, expected, atol=1e-10)
    np.testing.assert_allclose(lin.H[:, :3].T @ lin.H[:, :3], expected, atol=1e-10)


def test_yaw_factor_matches_eskf_model_and_numerical_jacobian():
    rot = Rotation.from_euler("ZYX", [2.9, 0.2, -0.15])
    yaw_meas = float(wrap_angle(yaw_from_rot_nb(rot) + 0.01))
    std = np.radians(0.3)
    f = G.yaw_factor(X(0), yaw_meas, std)
    values = pose_values(rot)
    # Error = h(x) - z = -(wrapped innovation), across the +-pi wrap.
    assert f.unwhitenedError(values)[0] == pytest.approx(-0.01, abs=1e-12)
    check_factor_jacobians(f, values, [(X(0), 6)])
    # Near the wrap: yaw 179.9 deg measured as -179.9 deg is a 0.2 deg error, not 359.8.
    rot_w = Rotation.from_euler("Z", np.radians(179.9))
    f_w = G.yaw_factor(X(0), np.radians(-179.9), std)
    assert f_w.unwhitenedError(pose_values(rot_w))[0] == pytest.approx(np.radians(-0.2))


def test_non_holonomic_and_levelling_factor_jacobians():
    rot = Rotation.from_euler("ZYX", [0.7, -0.1, 0.05])
    vel = np.array([3.0, -1.0, 0.4])
    nhc = G.non_holonomic_factor(X(0), V(0), 0.05)
    values = pose_values(rot, vel=vel, bias=np.array([1e-3, -2e-3, 3e-3, 0.02, -0.01, 0.03]))
    check_factor_jacobians(nhc, values, [(X(0), 6), (V(0), 3)])
    np.testing.assert_allclose(nhc.unwhitenedError(values), (rot.inv().apply(vel))[1:3], atol=1e-12)
    force_b = rot.inv().apply([0.0, 0.0, 9.8]) + np.array([0.02, -0.01, 0.03])
    lev = G.levelling_factor(X(0), B(0), force_b, 1e-3)
    assert np.max(np.abs(lev.unwhitenedError(values))) < 1e-12  # the bias explains it all
    check_factor_jacobians(lev, values, [(X(0), 6), (B(0), 6)])


def test_pose_covariance_frames_round_trip():
    rng = np.random.default_rng(0)
    a = rng.standard_normal((6, 6))
    cov_b = a @ a.T
    mat = ROT_NB.as_matrix()
    cov_n = G.pose_cov_nav_from_body(mat, cov_b)
    np.testing.assert_allclose(G.pose_cov_body_from_nav(mat, cov_n), cov_b, atol=1e-12)
    # The attitude block rotates like dtheta_n = R w_b.
    np.testing.assert_allclose(cov_n[:3, :3], mat @ cov_b[:3, :3] @ mat.T, atol=1e-12)


def test_preintegration_params_from_imu_model():
    model = polins.load_imu("fins-paper")
    p = G.preintegration_params(model, gravity_mps2=9.81, omega_ie_n=[0.0, 5e-5, 5e-5])
    np.testing.assert_allclose(p.n_gravity, [0.0, 0.0, -9.81])  # ENU (MakeSharedU)
    np.testing.assert_allclose(np.diag(p.getGyroscopeCovariance()), model.gyro_arw**2)
    np.testing.assert_allclose(np.diag(p.getAccelerometerCovariance()), model.accel_vrw**2)
    np.testing.assert_allclose(np.diag(p.getBiasOmegaCovariance()), model.gyro_bias_rw**2)
    np.testing.assert_allclose(np.diag(p.getBiasAccCovariance()), model.accel_bias_rw**2)
    np.testing.assert_allclose(p.getOmegaCoriolis(), [0.0, 5e-5, 5e-5])


def test_keyframes_and_imu_segments():
    t_key = G.keyframe_times(0.0, 3.0, [0.55, 0.5500000001, 2.0, 5.0], max_keyframe_dt_s=0.8)
    assert t_key[0] == 0.0 and t_key[-1] == 3.0
    assert np.max(np.diff(t_key)) <= 0.8 + 1e-12
    assert np.sum(np.abs(t_key - 0.55) < 1e-6) == 1 and np.any(np.abs(t_key - 2.0) < 1e-12)
    t = np.arange(0.0, 3.0001, 0.1)
    gyro = np.column_stack([0.1 + 0.05 * t, np.zeros_like(t), np.zeros_like(t)])
    accel = np.column_stack([np.zeros_like(t), np.zeros_like(t), 9.8 + t])
    seg = G.imu_segments(t, gyro, accel, t_key)
    assert seg.dt.sum() == pytest.approx(3.0)
    np.testing.assert_allclose(seg.t[seg.bounds], t_key)
    # Step means of a linear signal: the integral of the gyro is exact.
    assert np.sum(seg.gyro[:, 0] * seg.dt) == pytest.approx(0.1 * 3.0 + 0.025 * 9.0)


# ----------------------------------------------------------------------------- vs the ESKF
@functools.cache
def static_case(seed=1):
    """Static, tilted IMU (MEMS without scale-factor errors), yaw at 1 Hz: nearly linear."""
    model = dataclasses.replace(
        polins.load_imu("mems-typical"), gyro_scale_factor=0.0, accel_scale_factor=0.0
    )
    traj = turntable(duration_s=10.0, turn_rad=0.0, rate_hz=100.0, yaw0=0.3, roll=0.02, pitch=-0.01)
    imu, _ = imu_errors(ideal_imu(traj, earth_rotation=False), model, np.random.default_rng(seed))
    rng = np.random.default_rng(seed + 1)
    t_m = np.arange(1.0, 10.01, 1.0)
    std = np.radians(0.5)
    meas = pd.DataFrame(
        {"t": t_m, "yaw": 0.3 + std * rng.standard_normal(len(t_m)), "yaw_std": std}
    )
    opts = {"imu_model": model, "lat_deg": 45.0, "lon_deg": 0.0, "alt_m": 0.0, "earth_rate": False}
    return imu, meas, traj, opts


@pytest.mark.parametrize("aligned", [True, False])
def test_graph_equals_eskf_on_linear_gaussian_case(aligned):
    """isam2 (causal) = ESKF and batch = ESKF + RTS at every keyframe, estimates and sigmas."""
    imu, meas, traj, opts = static_case()
    rot0 = Rotation.from_euler("Z", np.radians(0.4)) * traj.rot_nb[0] if aligned else None
    # the graph keeps the headings of its yaw consensus as factors from the start: so does
    # the ESKF with a consensus of 1 (its default waits for 3 agreeing headings, §7.1)
    first = {"acquire_k": 1, "acquire_n": 1}
    eskf = polins.fuse(imu, meas, rot_nb0=rot0, **opts, **first)
    rts = polins.fuse(imu, meas, rot_nb0=rot0, smooth=True, **opts, **first)
    # self-aligned: the ESKF takes the zero-rate updates before the first heading with the
    # yaw as a consider state, the graph only from the heading on (docs/filter.md §9, §12.1)
    tol_est, tol_sig = (0.01, 1e-3) if aligned else (0.6, 0.1)
    for solver, ref in (("isam2", eskf), ("batch", rts)):
        res = graph_run(imu, meas, rot0, solver=solver, graph_output="keyframes", **opts)
        g = res.solution
        assert res.backend == "graph" and res.info["solver"] == solver
        r = ref.set_index("t").reindex(g["t"].to_numpy(), method="nearest")
        if solver == "isam2":  # causal: no yaw before the first measurement, like the ESKF
            assert np.array_equal(np.isnan(g["yaw"]), np.isnan(r["yaw"].to_numpy()))
        assert np.isfinite(g["yaw"]).sum() >= np.isfinite(r["yaw"]).sum()
        # before the yaw is acquired the ESKF's smoother chain stops (a new chain starts at
        # the acquisition, docs/filter.md §8): the batch graph's bias there already has the
        # later zero-rate updates (§12.1); compared from the first yaw on
        known = np.isfinite(r["yaw"].to_numpy()) & (aligned or g["t"].to_numpy() >= 3.0)
        for c in (*ANGLES, "bgx", "bgy", "bgz", "bax", "bay"):
            ok = np.isfinite(r[c].to_numpy()) & known
            d = np.asarray(wrap_angle(g[c].to_numpy() - r[c].to_numpy()))[ok]
            s = r[f"{c}_std"].to_numpy()[ok]
            assert np.max(np.abs(d) / s) < tol_est, (solver, c)
            np.testing.assert_allclose(g[f"{c}_std"].to_numpy()[ok], s, rtol=tol_sig)


def test_gating_rejects_an_outlier_and_logs_it():
    imu, meas, traj, opts = static_case()
    bad = meas.copy()
    bad.loc[4, "yaw"] += np.radians(8.0)  # 16 sigma
    for solver in ("batch", "isam2"):
        res = graph_run(imu, bad, traj.rot_nb[0], solver=solver, **opts)
        g, updates = res.solution, res.updates
        # beside the headings, the static IMU's zero-rate updates (docs/filter.md §12.1)
        assert set(updates["name"]) == {"yaw", "zaru"}
        log = updates[updates["name"] == "yaw"].reset_index(drop=True)
        assert len(log) == len(meas)
        assert not log["accepted"][4] and log["accepted"].drop(index=4).all(), solver
        assert "gate" in log["reason"][4]
        err = np.degrees(np.abs(wrap_angle(g["yaw"].to_numpy() - 0.3)))
        assert err.max() < 1.0  # the outlier did not pull the yaw


def test_local_worst_is_the_largest_within_the_span():
    t = np.array([0.0, 1.0, 20.0, 50.0, 51.0])
    nis = np.array([5.0, 100.0, 9.0, 40.0, 12.0])
    worst = local_worst(t, nis, 30.0)
    np.testing.assert_array_equal(worst, [100.0, 100.0, 100.0, 40.0, 40.0])
    np.testing.assert_array_equal(local_worst(t, nis, 0.5), nis)


@pytest.mark.parametrize(("t_weak", "solves"), [(70.0, 2), (12.0, 3)])
def test_post_fit_gate_takes_distant_outliers_in_one_round(t_weak, solves):
    """A 16-sigma and a 6-sigma heading (NIS ~256 and ~36 > 9): 60 s apart (beyond
    ``GATE_SPAN_S``) both are gated after the first solve; 2 s apart the weaker waits for
    the re-solve without the stronger, which inflated it."""
    model = dataclasses.replace(
        polins.load_imu("mems-typical"), gyro_scale_factor=0.0, accel_scale_factor=0.0
    )
    traj = turntable(duration_s=80.0, turn_rad=0.0, rate_hz=100.0, yaw0=0.3, roll=0.02, pitch=-0.01)
    imu, _ = imu_errors(ideal_imu(traj, earth_rotation=False), model, np.random.default_rng(5))
    t_m = np.arange(1.0, 80.01, 1.0)
    std = np.radians(0.5)
    yaw = 0.3 + std * np.random.default_rng(6).standard_normal(len(t_m))
    yaw[t_m == 10.0] += 16.0 * std
    yaw[t_m == t_weak] -= 6.0 * std
    meas = pd.DataFrame({"t": t_m, "yaw": yaw, "yaw_std": std})
    opts = {"imu_model": model, "lat_deg": 45.0, "lon_deg": 0.0, "alt_m": 0.0, "earth_rate": False}
    res = graph_run(imu, meas, traj.rot_nb[0], solver="batch", **opts)
    log = res.updates[res.updates["name"] == "yaw"].set_index("t")
    assert not log["accepted"][10.0] and not log["accepted"][t_weak]
    assert log["accepted"].sum() == len(t_m) - 2
    assert len(res.info["iterations"]) == solves


def test_fixed_lag_with_long_window_equals_batch_and_short_window_is_between():
    imu, meas, traj, opts = static_case()
    rot0 = traj.rot_nb[0]
    kw = {"rot_nb0": rot0, "graph_output": "keyframes", **opts}
    batch = graph(imu, meas, solver="batch", **kw)
    long = graph(imu, meas, solver="fixed_lag", lag_s=100.0, **kw)
    short = graph(imu, meas, solver="fixed_lag", lag_s=2.0, **kw)
    causal = graph(imu, meas, solver="isam2", **kw)
    for c in ANGLES:
        d = wrap_angle(long[c].to_numpy() - batch[c].to_numpy())
        assert np.max(np.abs(d) / batch[f"{c}_std"].to_numpy()) < 0.01
        np.testing.assert_allclose(long[f"{c}_std"], batch[f"{c}_std"], rtol=1e-3)
    # A 2 s lag: sigmas between the smoother's and the filter's (yaw at t = 3 s).
    i = 3
    assert batch["yaw_std"][i] <= short["yaw_std"][i] + 1e-12 <= causal["yaw_std"][i] + 2e-12
    assert short["yaw_std"][i] < causal["yaw_std"][i] * 0.99


# ----------------------------------------------------------------------------- navigation
def test_noise_free_navigation_grade_drive_is_reproduced():
    """Earth rate (omegaCoriolis), transport rate, gravity change and turns: a noise-free
    FINS drive with exact yaw keeps the attitude within 2e-5 rad and the velocity within
    1e-2 m/s (like the ESKF: 1.4e-5 rad). Without noise or road vibration the standstill
    detector fires at constant speed, where the drive still turns by up to 4e-4 rad/s: the
    zero-rate updates there that pass the gate (docs/filter.md §9, §12.1) leave errors above
    the mechanization's 1e-6 rad and 1e-3 m/s."""
    model = polins.load_imu("fins-paper")
    traj = ugv_drive(duration_s=60.0, rng=np.random.default_rng(5))
    imu = ideal_imu(traj)
    idx = np.arange(0, len(traj), 40)
    meas = pd.DataFrame(
        {"t": traj.t[idx], "yaw": yaw_from_rot_nb(traj.rot_nb[idx]), "yaw_std": 1e-4}
    )
    sol = graph(
        imu,
        meas,
        traj.rot_nb[0],
        imu_model=model,
        lat_deg=np.degrees(traj.lat[0]),
        lon_deg=np.degrees(traj.lon[0]),
        alt_m=traj.alt_m[0],
        att_std0=1e-5,
        vel_std0=1e-4,
        output_rate_hz=5.0,
    )
    truth = traj.truth_frame().set_index("t").reindex(sol["t"].to_numpy(), method="nearest")
    for c in ANGLES:
        assert np.max(np.abs(wrap_angle(sol[c].to_numpy() - truth[c].to_numpy()))) < 2e-5, c
    v_err = sol[["ve", "vn", "vu"]].to_numpy() - truth[["ve", "vn", "vu"]].to_numpy()
    assert np.max(np.abs(v_err)) < 1e-2
    assert np.max(np.abs(sol["lat_deg"].to_numpy() - truth["lat_deg"].to_numpy())) * 111e3 < 0.1


def ugv_monte_carlo(runs, duration, *, aiding, seed0=100, model_name="mems-typical"):
    """Graph (batch) and ESKF + RTS on the same simulated UGV logs.

    IMU without scale-factor errors (the 15-state models have none), initial attitude drawn
    from its prior (1 deg), measurements at 5 Hz: sun vectors (sigma 0.2 deg, sun at
    Z = 49 deg) with zero-velocity at the stops, or polarization yaw (0.2 deg) with
    non-holonomic and zero-velocity constraints.
    """
    model = polins.load_imu(model_name)
    sim_model = dataclasses.replace(model, gyro_scale_factor=0.0, accel_scale_factor=0.0)
    errs = {s: {c: [] for c in ANGLES} for s in ("rts", "graph")}
    for run in range(runs):
        traj = ugv_drive(duration_s=duration, rng=np.random.default_rng(seed0 + run))
        imu, _ = imu_errors(ideal_imu(traj), sim_model, np.random.default_rng(seed0 + 1000 + run))
        idx = np.arange(0, len(traj), 40)
        rng = np.random.default_rng(seed0 + 2000 + run)
        std = np.radians(0.2)
        if aiding == "sun":
            noise = Rotation.from_rotvec(std * rng.standard_normal((len(idx), 3)))
            sun_b = noise.apply(traj.rot_nb[idx].inv().apply(SUN_N))
            meas = pd.DataFrame({"t": traj.t[idx], "sun_std": std})
            for i, c in enumerate("xyz"):
                meas[f"sun_b{c}"], meas[f"sun_n{c}"] = sun_b[:, i], SUN_N[i]
            extra = {}
        else:
            yaw = yaw_from_rot_nb(traj.rot_nb[idx]) + std * rng.standard_normal(len(idx))
            meas = pd.DataFrame({"t": traj.t[idx], "yaw": wrap_angle(yaw), "yaw_std": std})
            extra = {"nhc_std": 0.05}
        stationary = traj.t[np.linalg.norm(traj.vel_n, axis=1) < 1e-9][::40]
        meas = with_standstill(meas, stationary, 0.01)
        rot0 = Rotation.from_rotvec(np.radians(1.0) * rng.standard_normal(3)) * traj.rot_nb[0]
        opts = {
            "imu_model": model,
            "lat_deg": np.degrees(traj.lat[0]),
            "lon_deg": np.degrees(traj.lon[0]),
            "alt_m": traj.alt_m[0],
            "earth_rate": True,
            "output_rate_hz": 10.0,
            **extra,
        }
        truth = traj.truth_frame().set_index("t")
        sols = {
            "rts": polins.fuse(imu, meas, rot_nb0=rot0, smooth=True, **opts),
            "graph": graph(imu, meas, rot0, **opts),
        }
        for name, sol in sols.items():
            tr = truth.reindex(sol["t"].to_numpy(), method="nearest")
            for c in ANGLES:
                e = wrap_angle(sol[c].to_numpy() - tr[c].to_numpy())
                errs[name][c].append((e, sol[f"{c}_std"].to_numpy()))
    out = {}
    for name, per in errs.items():
        for c, pairs in per.items():
            e = np.concatenate([p[0] for p in pairs])
            s = np.concatenate([p[1] for p in pairs])
            out[name, c] = (np.sqrt(np.mean(e**2)), np.sqrt(np.mean((e / s) ** 2)))
    return out


def test_ugv_graph_as_accurate_as_rts_and_consistent():
    res = ugv_monte_carlo(6, 40.0, aiding="sun")
    for c in ANGLES:
        rmse_g, nees_g = res["graph", c]
        rmse_r, _ = res["rts", c]
        assert rmse_g <= 1.05 * rmse_r, (c, np.degrees([rmse_g, rmse_r]))
        assert 0.7 <= nees_g <= 1.5, (c, nees_g)


@pytest.mark.slow
@pytest.mark.parametrize("aiding", ["sun", "yaw"])
def test_ugv_graph_vs_rts_monte_carlo_long(aiding):
    res = ugv_monte_carlo(20, 120.0, aiding=aiding, seed0=500)
    for c in ANGLES:
        rmse_g, nees_g = res["graph", c]
        rmse_r, nees_r = res["rts", c]
        assert rmse_g <= 1.05 * rmse_r, (c, np.degrees([rmse_g, rmse_r]))
        assert 0.7 <= nees_g <= 1.5, (c, nees_g)
        assert abs(nees_g - nees_r) < 0.1, (c, nees_g, nees_r)


def test_self_alignment_on_a_drive():
    """rot_nb0=None: levelling at rest and yaw from the first sun vector."""
    res_imu = ugv_drive(duration_s=30.0, rng=np.random.default_rng(7))
    model = dataclasses.replace(
        polins.load_imu("mems-typical"), gyro_scale_factor=0.0, accel_scale_factor=0.0
    )
    imu, _ = imu_errors(ideal_imu(res_imu), model, np.random.default_rng(8))
    idx = np.arange(200, len(res_imu), 40)  # the first measurement at t = 1 s
    sun_b = res_imu.rot_nb[idx].inv().apply(SUN_N)
    meas = pd.DataFrame({"t": res_imu.t[idx], "sun_std": np.radians(0.2)})
    for i, c in enumerate("xyz"):
        meas[f"sun_b{c}"], meas[f"sun_n{c}"] = sun_b[:, i], SUN_N[i]
    opts = {"imu_model": model, "lat_deg": 45.6, "lon_deg": 126.7, "alt_m": 150.0}
    truth = res_imu.truth_frame().set_index("t")
    for solver in ("batch", "isam2"):
        sol = graph(imu, meas, solver=solver, output_rate_hz=5.0, **opts)
        tr = truth.reindex(sol["t"].to_numpy(), method="nearest")
        yaw_ok = np.isfinite(sol["yaw"].to_numpy())
        assert yaw_ok.all() if solver == "batch" else (~yaw_ok[sol["t"] < 0.99]).all()
        for c in ANGLES:
            e = np.abs(wrap_angle(sol[c].to_numpy() - tr[c].to_numpy()))[yaw_ok]
            assert np.all(e < 4.0 * sol[f"{c}_std"].to_numpy()[yaw_ok] + 1e-4), (solver, c)


# ----------------------------------------------------------------------------- interface
@pytest.mark.parametrize("solver", ["batch", "isam2"])
def test_graph_shows_its_progress_only_when_asked(solver, capsys):
    imu, meas, traj, opts = static_case()
    config = FuseConfig.from_options(solver=solver, **opts)
    quiet = polins.fusion.run_fusion(imu, meas, "graph", traj.rot_nb[0], config)
    assert capsys.readouterr().err == ""
    shown = polins.fusion.run_fusion(imu, meas, "graph", traj.rot_nb[0], config, progress=True)
    err = capsys.readouterr().err
    assert f"graph {solver}" in err
    if solver == "batch":  # its stages
        assert "gate round 1, marginals" in err
    else:  # its keyframes, to the last
        done = re.findall(r"(\d+)/(\d+)", err)[-1]
        assert done[0] == done[1] and int(done[0]) > 0, err
    pd.testing.assert_frame_equal(quiet.solution, shown.solution)


def test_result_is_the_shared_solution_table():
    imu, meas, traj, opts = static_case()
    res = polins.fusion.run_fusion(
        imu, meas, "graph", traj.rot_nb[0], FuseConfig.from_options(**opts)
    )
    one = NavState(
        t=0.0, rot_nb=traj.rot_nb[0], vel_n=np.zeros(3), lat=0.0, lon=0.0, alt_m=0.0,
        errors={"bg": np.zeros(3), "ba": np.zeros(3), "heading_bias": np.zeros(1)},
        sigma={**{k: np.ones(3) for k in ("att", "vel", "pos", "bg", "ba")},
               "heading_bias": np.ones(1)},  # the default heading bias (zero here), as the ESKF's
        att_cov=np.eye(3),
    )  # fmt: skip
    g = res.solution
    assert list(g.columns) == list(solution_table(one).columns)
    # polins.fuse(backend="graph") runs the graph; the ESKF writes the same table.
    pd.testing.assert_frame_equal(polins.fuse(imu, meas, "graph", traj.rot_nb[0], **opts), g)
    assert list(polins.fuse(imu, meas, rot_nb0=traj.rot_nb[0], **opts).columns) == list(g.columns)
    np.testing.assert_allclose(g["t"], imu["t"][::10])  # 10 rows per second by default
    assert res.backend == "graph" and res.info["solver"] == "batch" and not g.attrs
    # the yaw rows and, the IMU at rest, the zero-rate updates (docs/filter.md §12.1)
    names = res.updates["name"]
    assert (names == "yaw").sum() == len(meas) and set(names) == {"yaw", "zaru"}
    assert res.config.imu.name == opts["imu_model"].name
    t_zaru = res.updates.loc[names == "zaru", "t"].to_numpy()
    keys = np.union1d(np.concatenate([imu["t"].iloc[[0, -1]], meas["t"]]), t_zaru)
    assert res.info["n_keyframes"] == keys.size
    assert res.info["n_measurement_factors"] == len(res.updates)
    # Keyframe output: the same states at the keyframe times (interpolation is exact there).
    k = graph(imu, meas, traj.rot_nb[0], graph_output="keyframes", **opts)
    at_k = g.set_index("t").loc[k["t"].to_numpy()]
    for c in (*ANGLES, "yaw_std", "bgz", "ve", "lat_deg", "alt_m", "pu_std"):
        np.testing.assert_allclose(at_k[c].to_numpy(), k[c].to_numpy(), rtol=1e-9, atol=1e-12)


def test_measurement_times_within_the_time_tolerance_use_the_imu_sample():
    """As the ESKF: a measurement within TIME_TOL_S of an IMU sample is applied there."""
    imu, meas, traj, opts = static_case()
    late = meas.assign(t=meas["t"] + 2e-4)  # IMU at 100 Hz
    kw = {"graph_output": "keyframes", **opts}
    ref = graph(imu, meas, traj.rot_nb[0], **kw)
    snapped_run = graph_run(imu, meas.assign(t=meas["t"] + 0.5 * TIME_TOL_S), traj.rot_nb[0], **kw)
    apart_run = graph_run(imu, late, traj.rot_nb[0], **kw)
    snapped, apart = snapped_run.solution, apart_run.solution
    np.testing.assert_array_equal(snapped["t"], ref["t"])
    np.testing.assert_allclose(snapped["yaw"], ref["yaw"], rtol=0, atol=1e-12)
    assert np.all(np.isin(late["t"][:-1].round(9), apart["t"].round(9)))  # own keyframes
    assert apart_run.updates["reason"].iloc[-1] == "outside the IMU time span"
    assert snapped_run.updates["accepted"].all()


def test_without_a_site_the_paper_site_is_assumed_with_one_warning():
    imu, meas, traj, opts = static_case()
    opts = {k: v for k, v in opts.items() if k not in ("lat_deg", "lon_deg", "alt_m")}
    with pytest.warns(UserWarning, match="paper's site") as caught:
        sol = graph(imu, meas, traj.rot_nb[0], output_rate_hz=1.0, **opts)
    assert len(caught) == 1
    site = polins.site.PAPER_SITE
    ref = graph(imu, meas, traj.rot_nb[0], output_rate_hz=1.0, site=site, **opts)
    assert sol["lat_deg"][0] == pytest.approx(site.lat_deg, abs=1e-7)
    np.testing.assert_array_equal(sol["yaw"], ref["yaw"])


def test_bad_options_raise_clear_errors():
    imu, meas, _traj, opts = static_case()
    with pytest.raises(ValueError, match="smooth applies to the eskf backend only"):
        graph(imu, meas, smooth=True, **opts)
    with pytest.raises(ValueError, match="bogus"):
        graph(imu, meas, bogus=1, **opts)
    with pytest.raises(ValueError, match="solver"):
        graph(imu, meas, solver="lm", **opts)
    with pytest.raises(ValueError, match="self-alignment"):
        graph(imu, meas.iloc[:0], **opts)
    with pytest.raises(ValueError, match="zupt_std column"):  # with_standstill
        graph(imu, meas, stationary=[1.0], **opts)
    with pytest.raises(ValueError, match="imu"):
        graph(imu.iloc[::-1], meas, **opts)
    with pytest.raises(ValueError, match="rot_nb0"):
        graph(imu, meas, Rotation.identity(2), **opts)


def test_graph_backend_without_gtsam_says_which_extra_to_install(monkeypatch):
    imu, meas, traj, opts = static_case()
    monkeypatch.setitem(sys.modules, "gtsam", None)
    monkeypatch.setitem(sys.modules, "gtsam.symbol_shorthand", None)
    for name in [m for m in sys.modules if m.startswith("polins.fusion.graph")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.delattr(polins.fusion, "graph")
    sol = polins.fuse(imu, meas, rot_nb0=traj.rot_nb[0], **opts)  # the ESKF still runs
    assert np.isfinite(sol["yaw"]).all()
    with pytest.raises(ImportError, match=r'pip install "polins\[graph\]"'):
        importlib.import_module("polins.fusion.graph")


# ----------------------------------------------------------------------------- robustness
def robust_run(imu, meas, model, rot_nb0=None, **options):
    """The graph's FusionResult on a drive of tests/test_robustness.py (2 Hz output rows)."""
    config = FuseConfig.from_options(None, imu_model=model, site=SITE, output_rate_hz=2.0)
    config = FuseConfig.from_options(config, **options)
    res = polins.fusion.run_fusion(imu, meas, "graph", rot_nb0, config)
    # the measurement rows' records (the zero-rate updates at rest have their own, §12.1)
    heads = res.updates[res.updates["name"] != "zaru"].reset_index(drop=True)
    return dataclasses.replace(res, updates=heads)


@pytest.mark.parametrize("solver", ["batch", "isam2"])
@pytest.mark.parametrize("offset_deg", [30.0, 180.0])
def test_bad_first_heading_does_not_lock_the_graph(offset_deg, solver):
    # a first heading that set the initial yaw (1 rad prior) would hold the graph near it:
    # the yaw is acquired by consensus of the headings (docs/filter.md 7.1)
    model, _, imu, truth, meas = drive(0)
    bad = meas.copy()
    bad.loc[0, "yaw"] = wrap_angle(bad.loc[0, "yaw"] + np.radians(offset_deg))
    res = robust_run(imu, bad, model, solver=solver)
    t, err, z = yaw_z(res.solution, truth)
    aligned = np.isfinite(err)
    assert aligned.all() if solver == "batch" else aligned[t >= 0.4].all()
    assert np.abs(z[aligned]).max() < 3.0 and np.degrees(np.abs(err[t >= 30.0])).max() < 0.5
    upd = res.updates
    assert upd["reason"].iloc[0] == "held for the yaw acquisition: disagrees"
    assert not upd["accepted"].iloc[0] and upd["accepted"].iloc[1:].mean() > 0.99
    assert res.events.empty


@pytest.mark.parametrize("offset_deg", [30.0, 180.0])
def test_wrong_initial_yaw_is_reacquired_by_the_graph(offset_deg):
    model, _, imu, truth, meas = drive(1)
    y, p, r = truth[["yaw", "pitch", "roll"]].iloc[0]
    rot0 = Rotation.from_euler("ZYX", [y + np.radians(offset_deg), p, r])
    res = robust_run(imu, meas, model, rot_nb0=rot0)
    ev = res.events
    assert ev["kind"].tolist() == ["yaw-reacquired"] and ev["t"].iloc[0] == pytest.approx(0.6)
    assert ev["detail"].iloc[0].startswith("re-acquired: 3 of 3 headings agree")
    t, err, z = yaw_z(res.solution, truth)
    assert np.abs(z).max() < 3.0 and np.degrees(np.abs(err[t >= 30.0])).max() < 0.5
    assert res.updates["accepted"].mean() > 0.99
    # a right initial yaw: no re-acquisition
    right = robust_run(imu, meas, model, rot_nb0=Rotation.from_euler("ZYX", [y, p, r]))
    assert right.events.empty and right.updates["accepted"].mean() > 0.99


def test_graph_without_consensus_leaves_the_yaw_unknown():
    # two headings never make a consensus of 3: no heading is used, the yaw is NaN; a
    # consensus of 1 takes the first (docs/filter.md 7.1)
    model, _, imu, _, meas = drive(0)
    two = meas.iloc[[5, 10]]
    res = robust_run(imu, two, model)
    assert np.isnan(res.solution["yaw"]).all() and np.isfinite(res.solution["pitch"]).all()
    assert (res.updates["reason"] == "held for the yaw acquisition: no consensus of 3 in 5").all()
    one = robust_run(imu, two, model, acquire_k=1, acquire_n=1)
    assert np.isfinite(one.solution["yaw"]).all() and one.updates["accepted"].all()


def test_graph_imu_gap_with_images_inside():
    # the 3 s gap is not preintegrated with the rates interpolated: the headings inside are
    # skipped with events
    model, _, imu, truth, meas = drive(5)
    gapped = imu[(imu["t"] < 7.0) | (imu["t"] > 10.0)]
    res = robust_run(gapped, meas, model)
    inside = check_gap_skipped(res, meas)
    assert res.updates.loc[~inside, "accepted"].mean() > 0.99
    _, err, z = yaw_z(res.solution, truth)
    assert np.isfinite(err).all() and np.abs(z).max() < 3.5
    # the gap's intervals carry the inflation: the yaw sigma peaks in the gap
    sol = robust_run(gapped, meas, model, graph_output="keyframes").solution
    peak = sol["t"].iloc[int(np.argmax(sol["yaw_std"]))]
    assert 7.0 <= peak <= 10.0
    # the graph's events are the ESKF's: one preparation for both backends
    eskf = polins.fusion.run_fusion(gapped, meas, "eskf", None, FuseConfig.from_options(
        imu_model=model, site=SITE))  # fmt: skip
    assert res.events[res.events["kind"] != "yaw-reacquired"].reset_index(drop=True).equals(
        eskf.events[eskf.events["kind"] != "yaw-reacquired"].reset_index(drop=True))  # fmt: skip


# ----------------------------------------------------------------------------- MEMS defaults
def test_rotation_proportional_gyro_noise():
    """ARW^2 + m^2 |w|^2 tau per keyframe interval (filter.md 9); the scale factors are
    variables (graph/imu.py), not noise."""
    broad = polins.load_imu("broad-aktos-t")
    m, tau = broad.gyro_misalignment, broad.gyro_misalignment_corr_time
    assert (m, tau) == pytest.approx((6e-3, 0.1))
    rate_sq = np.array([0.0, 4.0])
    np.testing.assert_allclose(
        G.gyro_noise_density(broad, rate_sq), broad.gyro_arw**2 + m**2 * tau * rate_sq, rtol=1e-14
    )
    # in the problem: a turntable at rest, then spinning at 2 rad/s from t = 5 s
    model = polins.load_imu("mems-typical")
    traj = turntable(duration_s=10.0, turn_rad=10.0, rate_hz=100.0)
    imu = ideal_imu(traj, earth_rotation=False)
    imu.loc[imu["t"] < 5.0, ["gx", "gy", "gz"]] = 0.0
    imu.loc[imu["t"] >= 5.0, ["gx", "gy"]] = 0.0
    imu.loc[imu["t"] >= 5.0, "gz"] = 2.0
    meas = pd.DataFrame({"t": [2.0, 4.0, 6.0], "yaw": 0.0, "yaw_std": 0.01})
    spun = model.gyro_arw**2 + model.gyro_misalignment**2 * model.gyro_misalignment_corr_time * 4.0
    for flag in ("auto", False, True):
        cfg = FuseConfig.from_options(imu_model=model, site=SITE, scale_factors=flag)
        items = polins.fusion.items.items_from_table(meas, use_sun=True)
        arr = imu[["gx", "gy", "gz"]].to_numpy(), imu[["ax", "ay", "az"]].to_numpy()
        prob = G.problem.Problem(cfg, False, imu["t"].to_numpy(), *arr, items, traj.rot_nb[0])
        assert (prob.scale_jac is None) == (flag is False)
        cov = np.array([p.getGyroscopeCovariance() for p in prob.interval_params])
        rest = prob.t_key[1:] < 4.999  # the last sample interval before 5 s turns
        np.testing.assert_allclose(cov[rest, 2, 2], model.gyro_arw**2, rtol=1e-12)
        spin = prob.t_key[:-1] >= 5.0  # 4 rad^2/s^2
        np.testing.assert_allclose(cov[spin][:, [0, 1, 2], [0, 1, 2]], spun, rtol=1e-9)


# ----------------------------------------------------------------------------- scale factors
def scale_case():
    """Two keyframe intervals of a turning, accelerating IMU (GTSAM parameters, steps)."""
    n, dt = 200, 0.005
    t = np.arange(n) * dt
    gyro = np.column_stack([0.3 * np.sin(3 * t), 0.2 * np.cos(2 * t), 0.8 + 0.1 * t])
    accel = np.column_stack([1.0 + np.sin(t), 0.5 * np.cos(4 * t), 9.8 + 0.3 * np.sin(5 * t)])
    params = G.preintegration_params(polins.load_imu("mems-typical"), gravity_mps2=9.8)
    return gyro, accel, np.full(n, dt), np.array([0, 80, 200]), params


def preintegrated(params, gyro, accel, dt, bias=None):
    pim = gtsam.PreintegratedCombinedMeasurements(params, bias or gtsam.imuBias.ConstantBias())
    for a, w, h in zip(accel, gyro, dt, strict=True):
        pim.integrateMeasurement(a, w, h)
    return pim


def increments(pim, bias=None):
    """(dR, dp, dv) of a preintegration at a bias (GTSAM's first-order bias correction)."""
    s = pim.predict(gtsam.NavState(), bias or pim.biasHat())
    return s.attitude(), s.position(), s.velocity()


def increment_change(a, b):
    """(Log(dR_a^T dR_b), dp_b - dp_a, dv_b - dv_a): Forster's form, GTSAM's order."""
    return np.concatenate([gtsam.Rot3.Logmap(a[0].between(b[0])), b[1] - a[1], b[2] - a[2]])


def test_scale_factor_jacobians_match_gtsam_and_reintegration():
    gyro, accel, dt, bounds, params = scale_case()
    jac_bias = G.imu.increment_jacobians(gyro, accel, dt, bounds, weighted=False)
    s = np.array([1e-3, -2e-3, 3e-3, 2e-3, -1e-3, 1.5e-3])  # sg, sa
    b_g, b_a = np.array([0.01, 0.02, -0.01]), np.array([1e-3, -2e-3, 5e-4])
    bias = G.bias_from_polins(np.r_[b_g, b_a])
    # the scale factors act on the bias-corrected samples: (w - b_g) / (1 + sg)
    jac = G.imu.increment_jacobians(gyro - b_g, accel - b_a, dt, bounds)
    for k in range(2):
        sl = slice(bounds[k], bounds[k + 1])
        pim = preintegrated(params, gyro[sl], accel[sl], dt[sl])
        # unweighted, the recursion is GTSAM's bias Jacobian (its first-order correction)
        num = np.zeros((9, 6))
        for i in range(6):
            d = 1e-6 * np.eye(6)[i]
            step = gtsam.imuBias.ConstantBias(d[3:], d[:3])
            num[:, i] = increment_change(increments(pim), increments(pim, step)) / 1e-6
        np.testing.assert_allclose(jac_bias[k], num, atol=2e-5 * np.abs(num).max())
        # weighted: re-preintegrating the samples corrected by a known scale factor
        pim = preintegrated(params, gyro[sl], accel[sl], dt[sl], bias)
        w, f = (gyro[sl] - b_g) / (1 + s[:3]) + b_g, (accel[sl] - b_a) / (1 + s[3:]) + b_a
        brute = preintegrated(params, w, f, dt[sl], bias)
        change = increment_change(increments(pim), increments(brute))
        assert np.abs(change).max() > 1e-3
        np.testing.assert_allclose(jac[k] @ s, change, atol=5e-3 * np.abs(change).max())
        # the wrapped factor at S = s equals GTSAM's factor on the corrected samples: zero at
        # the end state that factor predicts, as large as the plain factor's error 1 cm off
        keys = (X(0), V(0), X(1), V(1), B(0), B(1))
        plain = gtsam.CombinedImuFactor(*keys, pim)
        wrapped = G.imu.scale_factor_imu_factor(plain, jac[k], *G.imu.scale_keys(0))
        ref = gtsam.CombinedImuFactor(*keys, brute)
        state = gtsam.NavState(gtsam.Rot3(ROT_NB.as_matrix()), np.ones(3), np.array([3.0, 1, 0]))
        end = ref.preintegratedMeasurements().predict(state, bias)
        values = gtsam.Values()
        for key, value in zip(keys, (state.pose(), state.velocity(), end.pose(), end.velocity(),
                                     bias, bias), strict=True):  # fmt: skip
            values.insert(key, value)
        values.insert(G.imu.scale_keys(0)[0], s[:3])
        values.insert(G.imu.scale_keys(0)[1], s[3:])
        shift = np.abs(plain.whitenedError(values)).max()
        assert shift > 5.0 and np.abs(ref.whitenedError(values)).max() < 1e-6
        assert np.abs(wrapped.whitenedError(values)).max() < 0.01 * shift
        values.update(X(1), end.pose().retract(np.r_[1e-4, 2e-4, -1e-4, 1e-2, 1e-2, 1e-2]))
        np.testing.assert_allclose(wrapped.whitenedError(values), ref.whitenedError(values),
                                   atol=0.01 * shift)  # fmt: skip
        dims = (6, 3, 6, 3, 6, 6, 3, 3)
        check_factor_jacobians(wrapped, values, list(zip(wrapped.keys(), dims, strict=True)))


def test_graph_recovers_a_gyro_scale_factor_like_the_eskf():
    # a level IMU turning back and forth about z (0.8 sin(2 pi t / 20) rad/s, 40 s) with a
    # +0.3 % z gyro scale factor, the ARW and VRW of mems-typical, yaw at 1 Hz (0.2 deg):
    # graph sgz 2.777e-3 +- 0.294e-3 (0.76 sigma from the truth), the ESKF's at the end
    # 2.782e-3 +- 0.294e-3
    model = polins.load_imu("mems-typical")
    rate_hz, dur = 100.0, 40.0
    traj = turntable(duration_s=dur, turn_rad=0.0, rate_hz=rate_hz)
    imu = ideal_imu(traj, earth_rotation=False)
    t = imu["t"].to_numpy()
    gz = 0.8 * np.sin(2 * np.pi * t / 20.0)
    yaw_true = 0.3 + 0.8 * 20.0 / (2 * np.pi) * (1 - np.cos(2 * np.pi * t / 20.0))
    rng = np.random.default_rng(5)
    noise = rng.standard_normal((len(t), 6)) * np.sqrt(rate_hz)
    imu[["gx", "gy", "gz"]] = noise[:, :3] * model.gyro_arw + np.c_[0 * t, 0 * t, 1.003 * gz]
    imu[["ax", "ay", "az"]] += noise[:, 3:] * model.accel_vrw
    std = np.radians(0.2)
    idx = np.arange(100, len(t), 100)
    yaw = wrap_angle(yaw_true[idx] + std * rng.standard_normal(idx.size))
    meas = pd.DataFrame({"t": t[idx], "yaw": yaw, "yaw_std": std})
    rot0 = Rotation.from_euler("Z", 0.3)
    opts = {"imu_model": model, "lat_deg": 45.0, "lon_deg": 0.0, "alt_m": 0.0,
            "earth_rate": False, "scale_factors": True}  # fmt: skip
    g = graph(imu, meas, rot0, **opts)
    eskf = polins.fuse(imu, meas, rot_nb0=rot0, **opts).iloc[-1]
    sg, sg_std = g["sgz"].to_numpy(), g["sgz_std"].to_numpy()
    assert np.ptp(sg) < 0.05 * sg_std[0] and sg_std[0] < 0.5 * model.gyro_scale_factor  # constant
    assert abs(sg[0] - 3e-3) < 2.0 * sg_std[0], (sg[0], sg_std[0])
    # the batch graph at any time = the filter at the end (all the data), for a constant
    assert abs(sg[0] - eskf["sgz"]) < 0.1 * sg_std[0], (sg[0], eskf["sgz"])
    assert sg_std[0] == pytest.approx(eskf["sgz_std"], rel=0.05)

    # causal: ISAM2's last keyframe has seen what the filter has at the end
    last = graph(imu, meas, rot0, solver="isam2", **opts).iloc[-1]
    assert abs(last["sgz"] - eskf["sgz"]) < 0.1 * sg_std[0], (last["sgz"], eskf["sgz"])
    assert last["sgz_std"] == pytest.approx(eskf["sgz_std"], rel=0.05)

    def imu_columns(table):
        return [c for c in table.columns if c[:2] in ("bg", "ba", "sg", "sa")]

    assert imu_columns(g) == imu_columns(polins.fuse(imu, meas, rot_nb0=rot0, **opts))
    yaw_err = wrap_angle(g["yaw"].to_numpy() - np.interp(g["t"], t, yaw_true))
    assert np.sqrt(np.mean((yaw_err / g["yaw_std"]) ** 2)) < 1.5


def ugv_defaults(seeds, duration):
    """Pooled RMS(err/sigma) and % within 3 sigma per angle of the graph with the default
    options on simulated MEMS UGV drives: ``mems-typical`` with all its errors (scale
    factors included), the Earth rotating, the site known (Earth rate mechanized), the
    non-holonomic constraint at 0.05 m/s, a 5 Hz yaw = truth + N(0, 0.2 deg), ``rot_nb0`` =
    truth + N(0, 1 deg) per axis."""
    model = polins.load_imu("mems-typical")
    std = np.radians(0.2)
    pairs = {c: [] for c in ANGLES}
    for seed in seeds:
        traj = ugv_drive(duration_s=duration, rng=np.random.default_rng(seed))
        rng = np.random.default_rng([seed, 1])
        imu, _ = imu_errors(ideal_imu(traj), model, rng)
        idx = np.arange(0, len(traj), 40)[1:]
        yaw = yaw_from_rot_nb(traj.rot_nb[idx]) + rng.normal(0.0, std, idx.size)
        meas = pd.DataFrame({"t": traj.t[idx], "yaw": wrap_angle(yaw), "yaw_std": std})
        rot0 = Rotation.from_rotvec(np.radians(1.0) * rng.standard_normal(3)) * traj.rot_nb[0]
        site = polins.Site(np.degrees(traj.lat[0]), np.degrees(traj.lon[0]), traj.alt_m[0])
        sol = graph(imu, meas, rot0, imu_model=model, site=site, nhc_std=0.05,
                    output_rate_hz=5.0)  # fmt: skip
        truth = traj.truth_frame().set_index("t").reindex(sol["t"].to_numpy(), method="nearest")
        for c in ANGLES:
            err = wrap_angle(sol[c].to_numpy() - truth[c].to_numpy())
            pairs[c].append(err / sol[f"{c}_std"].to_numpy())
    out = {}
    for c in ANGLES:
        z = np.concatenate(pairs[c])
        out[c] = (float(np.sqrt(np.mean(z**2))), 100.0 * float(np.mean(np.abs(z) < 3.0)))
    return out


def test_graph_consistent_on_mems_ugv_defaults():
    # one 60 s drive (seed 1): yaw/pitch/roll RMS(err/sigma) 1.12/0.47/0.28, 100 % within
    # 3 sigma (the tilt still carries its 1 deg prior after 60 s)
    res = ugv_defaults([1], 60.0)
    for c, (rms_z, within) in res.items():
        assert rms_z <= 1.5 and within >= 95.0, (c, res)
    assert res["yaw"][0] >= 0.7, res


def test_graph_gates_the_standstill_detector_like_the_eskf():
    # vehicle="ground": the IMU-only standstill detector also fires at constant speed (253 of
    # its 367 epochs on this drive, up to 5 m/s). Every detection as a zero-velocity factor
    # gives pitch/roll errors of 2.2/1.1 deg with RMS(err/sigma) 95/11; a causal pass gates
    # them first, as the ESKF does: the same 114 at rest accepted.
    model = polins.load_imu("mems-typical")
    traj = ugv_drive(duration_s=60.0, rng=np.random.default_rng(11))
    rng = np.random.default_rng([11, 1])
    imu, _ = imu_errors(ideal_imu(traj), model, rng)
    idx = np.arange(0, len(traj), 40)[1:]
    std = np.radians(0.2)
    yaw = yaw_from_rot_nb(traj.rot_nb[idx]) + rng.normal(0.0, std, idx.size)
    meas = pd.DataFrame({"t": traj.t[idx], "yaw": wrap_angle(yaw), "yaw_std": std})
    site = polins.Site(np.degrees(traj.lat[0]), np.degrees(traj.lon[0]), traj.alt_m[0])
    opts = {"imu_model": model, "site": site, "vehicle": "ground", "output_rate_hz": 5.0}
    speed = np.linalg.norm(traj.vel_n, axis=1)
    outcome = {}
    for backend in ("graph", "eskf"):
        cfg = FuseConfig.from_options(**opts)
        res = polins.fusion.run_fusion(imu, meas, backend, traj.rot_nb[0], cfg)
        zupt = res.updates[res.updates["name"] == "zupt"]
        k = np.searchsorted(traj.t, zupt["t"].to_numpy() - 1e-9)
        outcome[backend] = zupt["accepted"].to_numpy()
        assert (speed[k][outcome[backend]] < 0.01).all() and (speed[k] > 0.01).sum() > 200
        if backend == "graph":
            truth = traj.truth_frame().set_index("t").reindex(res.solution["t"], method="nearest")
            for c in ("pitch", "roll"):
                err = wrap_angle(res.solution[c].to_numpy() - truth[c].to_numpy())
                assert np.sqrt(np.mean((err / res.solution[f"{c}_std"]) ** 2)) < 1.5, c
    np.testing.assert_array_equal(outcome["graph"], outcome["eskf"])


@pytest.mark.slow
def test_graph_consistent_on_mems_ugv_defaults_long():
    # three 240 s drives (seeds 11-13): 1.11/0.71/0.94, 99.4/100/100 % (with the
    # scale-factor noise over each interval alone, mean|w|^2 tau: 1.27/0.81/1.30, 97.3 %)
    res = ugv_defaults([11, 12, 13], 240.0)
    for c, (rms_z, within) in res.items():
        assert 0.6 <= rms_z <= 1.5 and within >= 95.0, (c, res)


def test_tree_marginals_equal_the_per_key_marginals():
    """One pass over the Bayes tree gives every variable's marginal covariance as
    GTSAM's ``marginalFactor`` does key by key (a pose-velocity chain with loop closures:
    cliques with wide separators)."""
    from gtsam.symbol_shorthand import V, X

    from polins.fusion.graph.solvers import marginal_covariances

    rng = np.random.default_rng(0)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 0.1)))
    graph.add(gtsam.PriorFactorVector(V(0), np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, 1.0)))

    def pose() -> gtsam.Pose3:
        return gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0.0, 0.1, 3)), rng.normal(0.0, 1.0, 3))

    for k in range(120):
        values.insert(X(k), pose())
        values.insert(V(k), rng.normal(0.0, 1.0, 3))
        if k:
            sigmas = gtsam.noiseModel.Diagonal.Sigmas(rng.uniform(0.01, 0.2, 6))
            graph.add(gtsam.BetweenFactorPose3(X(k - 1), X(k), pose(), sigmas))
            link = gtsam.noiseModel.Isotropic.Sigma(3, 0.1)
            graph.add(gtsam.BetweenFactorVector(V(k - 1), V(k), np.zeros(3), link))
        if k % 7 == 3:
            loop = gtsam.noiseModel.Isotropic.Sigma(6, 0.5)
            graph.add(gtsam.BetweenFactorPose3(X(k), X(max(0, k - 20)), gtsam.Pose3(), loop))
    tree = graph.linearize(values).eliminateMultifrontal(graph.orderingCOLAMD(), gtsam.EliminateQR)
    zero = tree.optimize()
    keys = list(values.keys())
    every = marginal_covariances(tree, {key: zero.dim(key) for key in keys})
    assert sorted(every) == sorted(keys)
    for key in keys:
        one = G.marginal_covariance_qr(tree, key)
        np.testing.assert_allclose(every[key], one, rtol=1e-9, atol=1e-12 * np.abs(one).max())


@pytest.mark.slow
def test_readme_flow_graph_is_consistent_over_seeds(tmp_path):
    """The README flow (``polins simulate --scenario ugv --imu mems-typical``, then ``polins
    fuse --backend graph`` with the options the ESKF run takes) over 8 seeds: heading, roll
    and pitch RMS(err/sigma) pooled in [0.8, 1.2], at least 98.5 % within 3 sigma."""
    from polins.io import read_log
    from polins.loop import run_log
    from polins.sim.scenario import simulate_log

    z: dict[str, list[np.ndarray]] = {c: [] for c in ANGLES}
    for seed in range(8):
        folder = tmp_path / f"seed{seed}"
        simulate_log(folder, scenario="ugv", imu="mems-typical", seed=seed, progress=False)
        log = read_log(folder / "manifest.toml")
        sol = run_log(log, backend="graph", workers=1, progress=False).solution
        sol = sol[np.isfinite(sol["yaw"].to_numpy())]
        t = sol["t"].to_numpy()
        for c in ANGLES:
            truth = np.interp(t, log.truth["t"], np.unwrap(log.truth[c].to_numpy()))
            err = wrap_angle(sol[c].to_numpy() - truth)
            z[c].append(err / sol[f"{c}_std"].to_numpy())
    for c in ANGLES:
        zc = np.concatenate(z[c])
        rms, within = float(np.sqrt(np.mean(zc**2))), float(np.mean(np.abs(zc) < 3.0))
        print(f"{c}: RMS(err/sigma) {rms:.2f}, {100 * within:.1f} % within 3 sigma")
        assert 0.8 <= rms <= 1.2 and within >= 0.985, (c, rms, within)
