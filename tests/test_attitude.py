"""Rotation and angle conventions (docs/conventions.md, docs/model.md §2)."""

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from polins.frames import (
    euler_from_rot_nb,
    heading_deg_from_yaw,
    rot_lb_from_rot_nb,
    rot_nb_from_euler,
    wrap_angle,
    wrap_axial,
    yaw_from_heading_deg,
    yaw_from_rot_nb,
)

angles = st.floats(-50.0, 50.0, allow_nan=False)
yaws = st.floats(-np.pi + 1e-9, np.pi, allow_nan=False)
tilts = st.floats(-1.4, 1.4, allow_nan=False)


def _r1(a):
    return np.array([[1, 0, 0], [0, np.cos(a), np.sin(a)], [0, -np.sin(a), np.cos(a)]])


def _r2(a):
    return np.array([[np.cos(a), 0, -np.sin(a)], [0, 1, 0], [np.sin(a), 0, np.cos(a)]])


def _r3(a):
    return np.array([[np.cos(a), np.sin(a), 0], [-np.sin(a), np.cos(a), 0], [0, 0, 1]])


@given(angles)
def test_wrap_range_and_equivalence(a):
    w = wrap_angle(a)
    assert -np.pi < w <= np.pi
    assert np.isclose(np.cos(w), np.cos(a)) and np.isclose(np.sin(w), np.sin(a))
    x = wrap_axial(a)
    assert -np.pi / 2 < x <= np.pi / 2 and np.isclose(np.sin(2 * x), np.sin(2 * a))


def test_wrap_boundaries():
    assert wrap_angle(-np.pi) == np.pi and wrap_angle(np.pi) == np.pi and wrap_angle(0.0) == 0.0


@given(yaws)
def test_heading_yaw_round_trip(yaw):
    h = heading_deg_from_yaw(yaw)
    assert 0.0 <= h < 360.0
    assert np.isclose(np.cos(yaw_from_heading_deg(h) - yaw), 1.0, atol=1e-12)


def test_heading_examples():
    # yaw 0 = East = compass 90; yaw +90 deg (North) = compass 0; compass 247.11 -> yaw
    np.testing.assert_allclose(heading_deg_from_yaw([0.0, np.pi / 2, -np.pi / 2]), [90, 0, 180])
    assert np.isclose(yaw_from_heading_deg(247.11), np.radians(90 - 247.11))


@given(yaws, tilts, tilts)
def test_euler_round_trip_and_spec_matrix(yaw, pitch, roll):
    rot = rot_nb_from_euler(yaw, pitch, roll)
    y, p, r = euler_from_rot_nb(rot)
    np.testing.assert_allclose([np.cos(y - yaw), p, r], [1.0, pitch, roll], atol=1e-9)
    # docs/model.md §2: C_n^b = R1(roll) R2(pitch) R3(yaw) (passive) is the transpose of mat_nb.
    c_nb = _r1(roll) @ _r2(pitch) @ _r3(yaw)
    np.testing.assert_allclose(rot.inv().as_matrix(), c_nb, atol=1e-12)
    assert np.isclose(np.cos(yaw_from_rot_nb(rot) - yaw), 1.0, atol=1e-12)
    # rot_nb = Rz(yaw) * rot_lb and rot_lb has no yaw
    rot_lb = rot_lb_from_rot_nb(rot)
    assert abs(yaw_from_rot_nb(rot_lb)) < 1e-9
    assert (Rotation.from_euler("Z", yaw) * rot_lb).approx_equal(rot, atol=1e-9)


def test_sign_conventions_flu():
    # Positive pitch is nose down, positive roll is right side down (ROS REP-103).
    nose = rot_nb_from_euler(0.0, 0.1, 0.0).apply([1.0, 0.0, 0.0])
    assert nose[2] < 0
    left = rot_nb_from_euler(0.0, 0.0, 0.1).apply([0.0, 1.0, 0.0])
    assert left[2] > 0  # left side up = right side down
    # yaw +90 deg points body x to North
    np.testing.assert_allclose(
        rot_nb_from_euler(np.pi / 2, 0, 0).apply([1, 0, 0]), [0, 1, 0], atol=1e-15
    )


def test_vectorised():
    rot = rot_nb_from_euler(np.linspace(-3, 3, 7), 0.1, -0.2)
    assert len(rot) == 7 and yaw_from_rot_nb(rot).shape == (7,)
