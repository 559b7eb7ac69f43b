"""The zero-angular-rate update: its shared model, the items the standstill detector brings, the
graph's factor on the same model (docs/filter.md §12, "Zero angular rate")."""

from __future__ import annotations

import dataclasses
import math

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import B, X
from scipy.spatial.transform import Rotation

from polins.fusion.config import NHC_RATE_HZ, FuseConfig
from polins.fusion.graph.factors import zero_rate_factor
from polins.fusion.items import MeasurementItem, item_model
from polins.fusion.measurement import ATT, BG, zero_rate
from polins.fusion.vehicle import VehicleAiding, zero_rate_std
from polins.ins.earth import earth_rate_n
from polins.models import load_imu

MEMS = load_imu("mems-typical")
RATE_N = earth_rate_n(math.radians(48.0))
DT = 1.0 / MEMS.sample_rate_hz
BIAS = np.array([1e-4, -2e-4, 5e-5])  # [rad/s]


def at_rest(n: int, seed: int, bias: np.ndarray = BIAS):
    """``n`` samples of the MEMS model at rest (level): times [s], gyro [rad/s] with the
    constant ``bias``, specific force [m/s^2]."""
    rng = np.random.default_rng(seed)
    gyro = bias + rng.normal(0.0, MEMS.gyro_arw / math.sqrt(DT), (n, 3))
    accel = np.array([0.0, 0.0, 9.81]) + rng.normal(0.0, MEMS.accel_vrw / math.sqrt(DT), (n, 3))
    return np.arange(n) * DT, gyro, accel


def h_of(rot_nb: Rotation, bias_b: np.ndarray) -> np.ndarray:
    """The model's prediction: the bias plus the Earth rate in body axes."""
    return bias_b + rot_nb.inv().apply(RATE_N)


def test_zero_rate_jacobian_matches_finite_differences():
    rng = np.random.default_rng(4)
    rot = Rotation.from_euler("ZYX", [0.7, -0.2, 0.4])
    bias = rng.normal(0.0, 1e-4, 3)
    gyro = h_of(rot, bias) + rng.normal(0.0, 1e-5, 3)
    lin = zero_rate(rot, gyro, bias, 2e-4, rate_n=RATE_N)
    np.testing.assert_allclose(lin.residual, gyro - h_of(rot, bias), atol=1e-15)
    np.testing.assert_allclose(lin.R, np.eye(3) * 4e-8)
    eps = 1e-6
    for i in range(3):  # dtheta in ENU on the left (docs/filter.md §2.2), "true minus estimate"
        d = np.zeros(3)
        d[i] = eps
        num = (h_of(Rotation.from_rotvec(d) * rot, bias) - h_of(rot, bias)) / eps
        np.testing.assert_allclose(lin.H[:, ATT][:, i], num, rtol=1e-5, atol=1e-14)
        num_b = (h_of(rot, bias + d) - h_of(rot, bias)) / eps
        np.testing.assert_allclose(lin.H[:, BG][:, i], num_b, atol=1e-9)
    # without a mechanized Earth rate the bias state carries it: no attitude columns
    plain = zero_rate(rot, gyro, bias, 2e-4)
    assert np.all(plain.H[:, ATT] == 0.0)
    np.testing.assert_allclose(plain.residual, gyro - bias)


def test_the_graph_factor_is_the_shared_model():
    """GTSAM's error is minus the shared residual; its Jacobians are the shared H on the
    Pose3 body tangent and the bias tangent (accelerometer, then gyro)."""
    rot = Rotation.from_euler("ZYX", [-1.1, 0.05, 0.1])
    bias_g = np.array([2e-4, -1e-4, 5e-5])
    gyro = np.array([1e-4, 3e-5, -2e-4])
    std = 3e-4
    factor = zero_rate_factor(X(0), B(0), gyro, std, RATE_N)
    values = gtsam.Values()
    values.insert(X(0), gtsam.Pose3(gtsam.Rot3(rot.as_matrix()), np.zeros(3)))
    values.insert(B(0), gtsam.imuBias.ConstantBias(np.zeros(3), bias_g))
    lin = zero_rate(rot, gyro, bias_g, std, rate_n=RATE_N)
    whitened = factor.unwhitenedError(values)
    np.testing.assert_allclose(whitened, -lin.residual, atol=1e-15)
    gaussian = factor.linearize(values)
    A, _ = gaussian.jacobian()
    A = A * std  # unwhitened
    np.testing.assert_allclose(A[:, 0:3], lin.H[:, ATT] @ rot.as_matrix(), atol=1e-15)
    np.testing.assert_allclose(A[:, 6:9], 0.0)  # accelerometer bias
    np.testing.assert_allclose(A[:, 9:12], lin.H[:, BG], atol=1e-15)


def test_items_carry_the_mean_rate_of_the_samples_since_the_last_epoch():
    """At rest every kind of vehicle gets a zero-rate item at the NHC cadence: the mean of
    the raw rates since the previous epoch, with sigma ARW / sqrt(m dt); the ESKF's model
    of it is the shared one at its bias estimate."""
    dt, bias, n = DT, BIAS, 400
    t, gyro, accel = at_rest(n, seed=1)
    every = round(1.0 / (NHC_RATE_HZ * dt))
    for vehicle in ("free", "ground", "static"):
        cfg = FuseConfig.from_options(imu_model=MEMS, vehicle=vehicle, lat_deg=48.0, lon_deg=11.0,
                                      alt_m=500.0)  # fmt: skip
        aid = VehicleAiding(cfg, dt)
        got = [(i, it) for i, it in aid.items(t[:150], gyro[:150], accel[:150], 0)]
        got += [(i + 150, it) for i, it in aid.items(t[150:], gyro[150:], accel[150:], 150)]
        zaru = [(i, it) for i, it in got if it.kind == "zaru"]
        kinds = {it.kind for _, it in got}
        assert ("zupt" in kinds) == (vehicle != "free"), (vehicle, kinds)
        assert len(zaru) >= (n - 100) // every, (vehicle, len(zaru))  # every epoch at rest
        std = zero_rate_std(MEMS, every, dt)
        for i, it in zaru:
            assert i % every == 0
            np.testing.assert_allclose(it.gyro_b, gyro[i - every + 1 : i + 1].mean(axis=0))
            assert it.std == pytest.approx(MEMS.gyro_arw / math.sqrt(every * dt)) == std
            np.testing.assert_allclose(it.rate_n, earth_rate_n(math.radians(48.0)))
        item = zaru[0][1]
        lin = item_model(item, np.eye(3), None, False, {"bg": bias})
        np.testing.assert_allclose(lin.residual, item.gyro_b - bias - RATE_N)


def test_zero_rate_items_are_consistent_with_the_bias():
    """Over many windows at rest the normalized residuals at the true bias are N(0, 1): the
    sigma ARW / sqrt(m dt) is that of the mean (non-overlapping samples)."""
    dt, bias, n = DT, BIAS, 40000
    t, gyro, accel = at_rest(n, seed=2)
    cfg = FuseConfig.from_options(
        imu_model=MEMS, vehicle="free"
    )  # no site: the bias state carries the Earth rate
    items = [it for _, it in VehicleAiding(cfg, dt).items(t, gyro, accel, 0) if it.kind == "zaru"]
    z = np.array([(it.gyro_b - bias) / it.std for it in items])
    assert all(it.rate_n is None for it in items)
    assert len(items) > 0.95 * n / round(1.0 / (NHC_RATE_HZ * dt))
    assert abs(np.mean(z**2) - 1.0) < 4.0 * math.sqrt(2.0 / z.size)


def test_a_turning_body_gets_no_zero_rate_item():
    dt = 1.0 / MEMS.sample_rate_hz
    t = np.arange(2000) * dt
    gyro = np.tile([0.0, 0.0, math.radians(1.0)], (t.size, 1))  # 1 deg/s about z
    accel = np.tile([0.0, 0.0, 9.81], (t.size, 1))
    cfg = FuseConfig.from_options(imu_model=MEMS, vehicle="free")
    got = VehicleAiding(cfg, dt).items(t, gyro, accel, 0)
    assert not [it for _, it in got if it.kind == "zaru"]


def test_zero_rate_item_kind_orders_with_zero_velocity():
    a = MeasurementItem(1.0, "zaru", 1e-4, gyro_b=np.zeros(3))
    b = MeasurementItem(1.0, "nhc", 0.05)
    assert a.order < b.order


def test_a_held_detector_model_keeps_the_rest_epochs_and_the_sigma_follows_the_arw():
    """``standstill_model`` (a tuning holds its start model) fixes which epochs are at rest
    while the filter's ARW changes; the zero-rate sigma is the filter's ARW / sqrt(m dt)."""
    dt = DT
    t, gyro, accel = at_rest(4000, seed=3, bias=np.zeros(3))
    gyro[:, 2] += np.where((t > 5.0) & (t < 12.0), math.radians(0.4), 0.0)  # a slow turn between
    base = FuseConfig.from_options(imu_model=MEMS, vehicle="ground")
    wide = dataclasses.replace(MEMS, gyro_arw=4.0 * MEMS.gyro_arw)

    def rest(cfg: FuseConfig) -> tuple[np.ndarray, set[float]]:
        items = [it for _, it in VehicleAiding(cfg, dt).items(t, gyro, accel, 0)]
        zaru = np.array([it.t for it in items if it.kind == "zaru"])
        assert np.array_equal(zaru, [it.t for it in items if it.kind == "zupt"])
        return zaru, {it.std for it in items if it.kind == "zaru"}

    t_base, std_base = rest(base)
    t_free, _ = rest(base.replace(imu_model=wide))  # the detector follows the model ...
    t_held, std_held = rest(base.replace(imu_model=wide, standstill_model=MEMS))  # ... or not
    assert t_free.size > t_base.size + 10  # a 4x ARW takes the slow turn for rest
    np.testing.assert_array_equal(t_held, t_base)
    assert len(std_base) == len(std_held) == 1
    assert std_held.pop() == pytest.approx(4.0 * std_base.pop())
    assert base.replace(standstill_model=MEMS).replace(gate_prob=0.99).standstill_imu is MEMS
