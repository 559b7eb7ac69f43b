"""The tilt-coupled yaw model with the prior polins.measure used (docs/model.md §10.2, "put the
coupling in H"): exactness, Jacobian, agreement with polins.measure, ESKF and graph use."""

import gtsam
import numpy as np
import pandas as pd
import pytest
from render_simple import render
from scipy.spatial.transform import Rotation

import polins
from polins.compass.measure import measure
from polins.frames import rot_nb_from_euler, wrap_angle, yaw_from_rot_nb
from polins.fusion.graph import yaw_factor
from polins.fusion.measurement import yaw_from_sun, yaw_measurement

CAM4 = polins.load_camera("paper-table1").downscaled(4)


def _setup(seed):
    rng = np.random.default_rng(seed)
    sun_n = polins.sun_vector_n(rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(25, 75)))
    truth = rot_nb_from_euler(rng.uniform(-np.pi, np.pi), *np.radians(rng.normal(0, 5, 2)))
    prior = Rotation.from_rotvec(np.radians(rng.normal(0, 1.0, 3))) * truth
    nominal = Rotation.from_rotvec(np.radians(rng.normal(0, 0.3, 3))) * truth
    return sun_n, truth, prior, nominal


@pytest.mark.parametrize("seed", range(6))
def test_model_is_exact_at_the_truth_and_its_jacobian_numerical(seed):
    sun_n, truth, prior, nominal = _setup(seed)
    z = yaw_from_sun(prior, truth.inv().apply(sun_n), sun_n)  # what a full-vector fit gives
    at_truth = yaw_measurement(truth, z, 0.01, sun_n=sun_n, rot_nb_prior=prior)
    assert abs(at_truth.residual[0]) < 1e-13
    lin = yaw_measurement(nominal, z, 0.01, sun_n=sun_n, rot_nb_prior=prior)
    eps = 1e-7
    num = np.zeros(3)
    for i in range(3):
        d = np.zeros(3)
        d[i] = eps
        up = yaw_measurement(Rotation.from_rotvec(d) * nominal, z, 0.01, sun_n=sun_n,
                             rot_nb_prior=prior)  # fmt: skip
        down = yaw_measurement(Rotation.from_rotvec(-d) * nominal, z, 0.01, sun_n=sun_n,
                               rot_nb_prior=prior)  # fmt: skip
        num[i] = -(up.residual[0] - down.residual[0]) / (2 * eps)
    np.testing.assert_allclose(lin.H[0, :3], num, atol=1e-7)
    np.testing.assert_array_equal(lin.H[0, 3:], 0.0)
    # first order: the residual at the nominal is H (truth - nominal) up to second order
    dtheta = (truth * nominal.inv()).as_rotvec()
    assert abs(lin.residual[0] - lin.H[0, :3] @ dtheta) < np.linalg.norm(dtheta) ** 2 * 5
    # without a prior the filter's own state is the prior
    own = yaw_measurement(nominal, z, 0.01, sun_n=sun_n)
    same = yaw_measurement(nominal, z, 0.01, sun_n=sun_n, rot_nb_prior=nominal)
    np.testing.assert_allclose(own.H, same.H, atol=1e-15)
    assert own.residual[0] == pytest.approx(same.residual[0], abs=1e-15)
    assert own.residual[0] == pytest.approx(float(wrap_angle(z - yaw_from_rot_nb(nominal))))


def test_model_matches_polins_measure_with_a_prior_off_the_truth():
    sun_n = polins.sun_vector_n(np.radians(247.11), np.radians(45.0))
    truth = rot_nb_from_euler(0.7, np.radians(3.0), np.radians(-2.0))
    raw = render(CAM4, sun_n, truth)
    for axis in ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0]):
        prior = Rotation.from_rotvec(np.radians(0.5) * np.array(axis)) * truth
        for method in ("traditional", "compensated"):
            m = measure(raw, CAM4, sun_n=sun_n, rot_nb_prior=prior, method=method)
            coupled = yaw_measurement(truth, m.yaw, 0.01, sun_n=sun_n, rot_nb_prior=prior)
            plain = float(wrap_angle(m.yaw - yaw_from_rot_nb(truth)))
            assert abs(plain) > 1e-3  # the tilt of the prior moves the measured yaw
            if method == "traditional":  # the full eigenvector: the model is exact
                assert abs(coupled.residual[0]) < 1e-12
            else:  # fixed zenith: first-order cross-talk of the zenith (docs/measurement.md)
                assert abs(coupled.residual[0]) < 0.1 * abs(plain)


def test_graph_yaw_factor_uses_the_same_model():
    sun_n, truth, prior, nominal = _setup(11)
    z = yaw_from_sun(prior, truth.inv().apply(sun_n), sun_n)
    factor = yaw_factor(0, z, 0.002, sun_n=sun_n, rot_nb_prior=prior)
    values = gtsam.Values()
    values.insert(0, gtsam.Pose3(gtsam.Rot3(nominal.as_matrix()), np.zeros(3)))
    lin = yaw_measurement(nominal, z, 0.002, sun_n=sun_n, rot_nb_prior=prior)
    np.testing.assert_allclose(factor.unwhitenedError(values), -lin.residual, atol=1e-15)
    values.update(0, gtsam.Pose3(gtsam.Rot3(truth.as_matrix()), np.zeros(3)))
    assert abs(factor.unwhitenedError(values)[0]) < 1e-13
    with pytest.raises(ValueError, match="both sun_n and rot_nb_prior"):
        yaw_factor(0, z, 0.002, sun_n=sun_n)


def test_measurement_table_prior_columns_are_validated():
    imu = pd.DataFrame(
        {
            "t": np.arange(400) / 200.0,
            "gx": 0.0,
            "gy": 0.0,
            "gz": 0.0,
            "ax": 0.0,
            "ay": 0.0,
            "az": 9.806,
        }
    )
    meas = pd.DataFrame({"t": [1.5], "yaw": [0.1], "yaw_std": [0.01], "prior_roll": [0.0],
                         "prior_pitch": [0.0]})  # fmt: skip
    with pytest.raises(ValueError, match="incomplete prior columns"):
        polins.fuse(imu, meas, lat_deg=45.0, lon_deg=126.0, alt_m=0.0)
    meas["prior_yaw"] = 20.0
    with pytest.raises(ValueError, match="radians"):
        polins.fuse(imu, meas, lat_deg=45.0, lon_deg=126.0, alt_m=0.0)
