"""The batch solver's vectorized factors (polins/fusion/graph/batched.py): at the values a
batch was evaluated at, every factor linearizes exactly as its own callback does; at any
other values, and after the linearization, the callback evaluates itself (never a stale
row)."""

import gtsam
import numpy as np
import pandas as pd
from gtsam.symbol_shorthand import B, V, X
from scipy.spatial.transform import Rotation

from polins.fusion.config import FuseConfig
from polins.fusion.graph.batched import (
    NonHolonomicBatch,
    ScaleImuBatch,
    YawBatch,
    linearize,
    prepare_all,
)
from polins.fusion.graph.factors import non_holonomic_factor, preintegration_params, yaw_factor
from polins.fusion.graph.imu import scale_factor_imu_factor, scale_keys
from polins.fusion.graph.states import GraphStates
from polins.fusion.items import MeasurementItem
from polins.models import load_imu

N = 6  # keyframes
SO = gtsam.symbol("o", 0)


def random_values(rng):
    """Poses, velocities, biases, scale factors and the odometer scale of N keyframes."""
    values = gtsam.Values()
    for k in range(N):
        rot = Rotation.from_rotvec(rng.normal(0.0, 0.6, 3)).as_matrix()
        values.insert(X(k), gtsam.Pose3(gtsam.Rot3(rot), rng.normal(0.0, 5.0, 3)))
        values.insert(V(k), rng.normal(0.0, 3.0, 3))
        values.insert(
            B(k), gtsam.imuBias.ConstantBias(rng.normal(0, 0.05, 3), rng.normal(0, 1e-3, 3))
        )
        for key in scale_keys(k):
            values.insert(key, rng.normal(0.0, 1e-3, 3))
    values.insert(SO, np.array([0.02]))
    return values


def factor_pairs(rng):
    """(batch, [(batched factor, the same factor without a batch)]) of every batched type."""
    mount = Rotation.from_euler("xyz", [0.01, -0.02, 0.03]).as_matrix()
    nhc, plain, tilt = NonHolonomicBatch(), YawBatch(False), YawBatch(True)
    pairs = []
    for k in range(N):
        lever = rng.normal(0.0, 0.01, 3)
        args = (X(k), V(k), 0.05, mount if k % 2 else None, lever if k % 3 else None)
        pairs.append((non_holonomic_factor(*args, batch=nhc), non_holonomic_factor(*args)))
        yaw = float(rng.uniform(-np.pi, np.pi))
        pairs.append((yaw_factor(X(k), yaw, 0.01, batch=plain), yaw_factor(X(k), yaw, 0.01)))
        sun_n = np.array([0.5, -0.4, 0.6]) / np.linalg.norm([0.5, -0.4, 0.6])
        prior = Rotation.from_rotvec(rng.normal(0.0, 0.3, 3))
        kw = {"sun_n": sun_n, "rot_nb_prior": prior}
        pairs.append(
            (yaw_factor(X(k), yaw, 0.01, batch=tilt, **kw), yaw_factor(X(k), yaw, 0.01, **kw))
        )
    config = FuseConfig.from_options(None, odometer_std=0.05, heading_bias_std="off")
    states = GraphStates(config, np.arange(N, dtype=float))
    assert states.odometer_batch is not None
    unbatched = GraphStates(config, np.arange(N, dtype=float))
    unbatched.odometer_batch = None
    for k in range(N):
        item = MeasurementItem(float(k), "odo", 0.05, speed=float(rng.uniform(0.5, 5.0)),
                               mat_vb=mount, lever_vel_b=rng.normal(0.0, 0.01, 3))  # fmt: skip
        pairs.append((states.factor(item, k, X(k), V(k), False),
                      unbatched.factor(item, k, X(k), V(k), False)))  # fmt: skip
    imu = ScaleImuBatch()
    params = preintegration_params(load_imu("mems-typical"), gravity_mps2=9.81)
    for k in range(N - 1):
        pim = gtsam.PreintegratedCombinedMeasurements(params, gtsam.imuBias.ConstantBias())
        for _ in range(20):
            pim.integrateMeasurement(rng.normal([0, 0, 9.81], 0.5), rng.normal(0.0, 0.3, 3), 0.005)
        factor = gtsam.CombinedImuFactor(X(k), V(k), X(k + 1), V(k + 1), B(k), B(k + 1), pim)
        jac = rng.normal(0.0, 0.05, (9, 6))
        pairs.append((scale_factor_imu_factor(factor, jac, *scale_keys(k), imu),
                      scale_factor_imu_factor(factor, jac, *scale_keys(k))))  # fmt: skip
    batches = [nhc, plain, tilt, states.odometer_batch, imu]
    return batches, pairs


def assert_same_linearization(pairs, values):
    for batched, own in pairs:
        a_b, b_b = batched.linearize(values).jacobian()
        a_o, b_o = own.linearize(values).jacobian()
        np.testing.assert_allclose(a_b, a_o, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(b_b, b_o, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(batched.error(values), own.error(values), rtol=1e-9, atol=1e-12)


def test_batched_factors_linearize_as_their_callbacks():
    rng = np.random.default_rng(7)
    batches, pairs = factor_pairs(rng)
    values = random_values(rng)
    prepare_all(batches, values)
    # every factor is served by its batch at these values (its callback is not called)
    served = [
        b.lookup(slot, values, None) is not None for b in batches for slot in range(len(b.keys))
    ]
    assert all(served) and len(served) == len(pairs)
    assert_same_linearization(pairs, values)


def test_batched_factors_never_serve_other_values():
    rng = np.random.default_rng(8)
    batches, pairs = factor_pairs(rng)
    values = random_values(rng)
    prepare_all(batches, values)
    for key in (X(2), V(3), B(1), scale_keys(4)[1], SO):  # one key of each kind moved
        moved = gtsam.Values(values)
        delta = gtsam.VectorValues()
        delta.insert(key, np.full(values.dims()[key], 1e-9))
        moved.update(key, values.retract(delta).atPose3(key) if key == X(2) else
                     values.retract(delta).atConstantBias(key) if key == B(1) else
                     values.retract(delta).atVector(key))  # fmt: skip
        touched = [(b, s) for b in batches for s, keys in enumerate(b.keys) if key in keys]
        assert touched
        assert all(b.lookup(s, moved, None) is None for b, s in touched)
        assert_same_linearization(pairs, moved)


def test_batched_linearization_of_a_graph():
    # the whole graph linearized through the batches equals GTSAM's own linearization,
    # and the batches serve nothing afterwards
    rng = np.random.default_rng(9)
    batches, pairs = factor_pairs(rng)
    values = random_values(rng)
    batched, own = gtsam.NonlinearFactorGraph(), gtsam.NonlinearFactorGraph()
    for a, b in pairs:
        batched.add(a)
        own.add(b)
    lin_b, lin_o = linearize(batched, values, batches), own.linearize(values)
    for i in range(lin_o.size()):
        for x, y in zip(lin_b.at(i).jacobian(), lin_o.at(i).jacobian(), strict=True):
            np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-9)
    assert all(b.lookup(s, values, None) is None for b in batches for s in range(len(b.keys)))


def test_windowed_batch_agrees_with_the_whole_log_batch(monkeypatch):
    # a 150 s MEMS UGV drive in 60 s windows (overlap 30 s): the last window, whose prior
    # carries everything before its join, reproduces the whole-log batch (to a tenth of a sigma: the past is linearized at the earlier windows' estimates); before it each
    # window lacks the later drive's information on the constants (scale factors), so its
    # sigmas are no smaller and its attitude agrees within them
    import polins.fusion.graph.windows as W
    from polins.frames import wrap_angle
    from polins.fusion import FuseConfig, run_fusion
    from polins.sim.imu import ideal_imu, imu_errors
    from polins.sim.trajectory import ugv_drive

    model = load_imu("mems-typical")
    rng = np.random.default_rng(3)
    traj = ugv_drive(duration_s=150.0, rng=rng)
    imu, _ = imu_errors(ideal_imu(traj), model, rng)
    truth = traj.truth_frame()
    t = np.arange(0.2, 150.0, 0.2)
    yaw = np.interp(t, truth["t"], np.unwrap(truth["yaw"]))
    std = np.radians(0.3)
    meas = pd.DataFrame(
        {"t": t, "yaw": wrap_angle(yaw + rng.normal(0.0, std, t.size)), "yaw_std": std}
    )
    site = {"lat_deg": 45.6234, "lon_deg": 126.7264, "alt_m": 148.74}
    config = FuseConfig.from_options(imu_model=model, vehicle="ground", output_rate_hz=2.0, **site)
    whole = run_fusion(imu, meas, "graph", config=config)
    monkeypatch.setattr(W, "WINDOW_S", 60.0)
    monkeypatch.setattr(W, "OVERLAP_S", 30.0)
    import polins.fusion.graph.solvers as S

    monkeypatch.setattr(S, "OVERLAP_S", 30.0)
    parts = run_fusion(imu, meas, "graph", config=config)
    assert parts.info["windows"] == 4 and whole.info["windows"] == 1
    a, b = whole.solution, parts.solution
    last = a["t"].to_numpy() >= 90.0  # the last window's own keyframes
    for c in ("roll", "pitch", "yaw"):
        diff = wrap_angle(b[c].to_numpy() - a[c].to_numpy())
        sig_a, sig_b = a[f"{c}_std"].to_numpy(), b[f"{c}_std"].to_numpy()
        np.testing.assert_allclose(diff[last] / sig_a[last], 0.0, atol=0.1)
        np.testing.assert_allclose(sig_b[last], sig_a[last], rtol=0.05)
        assert np.all(sig_b >= 0.99 * sig_a), c
        assert np.all(np.abs(diff) <= 3.0 * sig_b), c
    same = whole.updates.reset_index(drop=True), parts.updates.reset_index(drop=True)
    assert len(same[0]) == len(same[1])
    np.testing.assert_array_equal(same[0]["t"], same[1]["t"])
