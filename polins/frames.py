"""Frames, rotations and angles: Euler conventions, angle wrapping, cross-product matrices.

``rot_nb = Rotation.from_euler("ZYX", [yaw, pitch, roll])`` maps body (FLU) to navigation
(ENU) vectors. Positive pitch is nose down, positive roll is right side down (ROS REP-103).
This equals docs/model.md §2: ``C_n^b = R1(roll) R2(pitch) R3(yaw)`` with passive
elementary rotations, i.e. ``mat_bn = rot_nb.inv().as_matrix()``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

FloatArray = NDArray[np.float64]


def wrap_angle(angle: ArrayLike) -> FloatArray:
    """Wrap an angle to (-pi, pi] [rad]."""
    a = np.asarray(angle, dtype=float)
    return np.pi - np.mod(np.pi - a, 2.0 * np.pi)


def wrap_axial(angle: ArrayLike) -> FloatArray:
    """Wrap an axial (mod pi) angle such as the AoP to (-pi/2, pi/2] [rad]."""
    return 0.5 * wrap_angle(2.0 * np.asarray(angle, dtype=float))


def heading_deg_from_yaw(yaw: ArrayLike) -> FloatArray:
    """Compass heading [deg, clockwise from North, in [0, 360)] from ENU yaw [rad]."""
    heading = np.mod(90.0 - np.degrees(np.asarray(yaw, dtype=float)), 360.0)
    # mod can return exactly 360.0 for tiny negative inputs; fold it back into [0, 360).
    return np.where(heading >= 360.0, 0.0, heading)


def yaw_from_heading_deg(heading_deg: ArrayLike) -> FloatArray:
    """ENU yaw [rad, counter-clockwise from East, in (-pi, pi]] from compass heading [deg]."""
    return wrap_angle(np.radians(90.0 - np.asarray(heading_deg, dtype=float)))


def rot_nb_from_euler(yaw: ArrayLike, pitch: ArrayLike, roll: ArrayLike) -> Rotation:
    """Body-to-ENU rotation from yaw, pitch, roll [rad] (intrinsic Z-Y-X); vectorised."""
    ypr = np.stack(np.broadcast_arrays(yaw, pitch, roll), axis=-1).astype(float)
    return Rotation.from_euler("ZYX", ypr)


def euler_from_rot_nb(rot_nb: Rotation) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Yaw, pitch, roll [rad] of a body-to-ENU rotation; yaw wrapped to (-pi, pi].

    From the matrix (``mat_nb = Rz(yaw) Ry(pitch) Rx(roll)``: ``yaw = atan2(m10, m00)``,
    ``pitch = -asin(m20)``, ``roll = atan2(m21, m22)``); within ~1e-6 rad of the gimbal lock
    (pitch +-90 deg) scipy's ``as_euler`` convention applies.
    """
    mat = rot_nb.as_matrix()
    m20 = mat[..., 2, 0]
    if np.any(np.abs(m20) > 1.0 - 1e-12):
        ypr = rot_nb.as_euler("ZYX")
        return wrap_angle(ypr[..., 0]), ypr[..., 1], ypr[..., 2]
    yaw = np.arctan2(mat[..., 1, 0], mat[..., 0, 0])
    roll = np.arctan2(mat[..., 2, 1], mat[..., 2, 2])
    return wrap_angle(yaw), -np.arcsin(m20), roll


def yaw_from_rot_nb(rot_nb: Rotation) -> FloatArray:
    """ENU yaw [rad] of the horizontal projection of body x (docs/model.md §2: atan2(C[0,1], C[0,0]))."""
    x_n = rot_nb.apply(np.array([1.0, 0.0, 0.0]))
    return wrap_angle(np.arctan2(x_n[..., 1], x_n[..., 0]))


def rot_lb_from_rot_nb(rot_nb: Rotation) -> Rotation:
    """Body-to-level rotation: ``rot_nb`` with its yaw removed (``rot_nb = Rz(yaw) rot_lb``)."""
    return Rotation.from_euler("Z", -yaw_from_rot_nb(rot_nb)) * rot_nb


def skew(v: ArrayLike) -> FloatArray:
    """Cross-product matrix ``[v x]`` with ``skew(a) @ b == cross(a, b)``; ``(..., 3, 3)``."""
    v = np.asarray(v, dtype=float)
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out
