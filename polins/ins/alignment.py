"""Self-alignment of a static IMU: levelling from the specific force, gyrocompassing.

Both use the means of the IMU samples over a static window. A static body measures
``f_b = mat_bn (0, 0, g)`` and ``omega_b = mat_bn w_ie_n`` with ``w_ie_n = Omega (0, cos L,
sin L)`` in ENU (Groves 2013 Sec. 14.2.1, analytic coarse alignment).

Levelling gives roll and pitch; a horizontal accelerometer bias ``b`` tilts them by ``b / g``.

Gyrocompassing gives the yaw from the horizontal Earth rate ``h = Omega cos L`` (10.5 deg/h
at 45 deg latitude). In the levelled frame with yaw 0 (``mat_nb_level``) the mean rate is
``w_l = mat_nb_level omega_b = Rz(-psi) w_ie_n``, whose horizontal part is
``h (sin psi, cos psi)``, so ``psi = atan2(w_l_x, w_l_y)``. A gyro bias ``b_g`` adds
``mat_nb b_g`` and moves the yaw estimate by ``b_E / h`` (``b_E`` its East component in the
aligned frame), so the yaw error ``dtheta_z = psi_true - psi_estimate = -b_E / h``. Only an
IMU whose gyro bias is far below ``h`` can do this (navigation grade: 0.02 deg/h gives
0.1 deg); the ESKF uses it when it mechanizes the Earth rate, where it matters: with an
unknown yaw the Earth-rate compensation ``w_in`` would be applied about wrong horizontal
axes and tilt the attitude by up to ``2 h`` per second until the first yaw measurement
(1e-4 rad/s, 20x the tilt sigma of a navigation-grade levelling after one second). The
leakage of the vertical rate through a tilt error ``e`` (``e tan L``, 1e-5 rad for a
navigation-grade levelling) is neglected.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from polins.ins.earth import OMEGA_IE

FloatArray = NDArray[np.float64]


def level_from_accel(accel_b: ArrayLike) -> tuple[float, float]:
    """Roll and pitch [rad] from a mean specific force of a static body (levelling).

    A static body measures ``f_b = mat_bn (0, 0, g)``: ``roll = atan2(f_y, f_z)``,
    ``pitch = atan2(-f_x, hypot(f_y, f_z))`` (FLU, positive pitch nose down).
    """
    f = np.asarray(accel_b, dtype=float)
    return float(np.arctan2(f[1], f[2])), float(np.arctan2(-f[0], np.hypot(f[1], f[2])))


def gyrocompass(gyro_b: ArrayLike, rot_nb_level: Rotation, lat: float) -> tuple[float, FloatArray]:
    """Yaw [rad] of a static, levelled IMU from the horizontal Earth rate (module docstring).

    Parameters
    ----------
    gyro_b : (3,) array_like
        Mean angular rate over the static window, body FLU [rad/s].
    rot_nb_level : Rotation
        Levelled attitude with yaw 0 (``level_from_accel``).
    lat : float
        Geodetic latitude [rad].

    Returns
    -------
    yaw : float
        ENU yaw of body x [rad].
    jac_bg : (3,) ndarray
        Yaw error per gyro-bias error, ``dtheta_z = jac_bg @ dbg`` [rad / (rad/s)]
        (``dbg`` = true minus estimated bias, ESKF convention), ``-mat_nb[0] / h``.

    Raises
    ------
    ValueError
        At the poles, where the horizontal Earth rate vanishes.
    """
    h = OMEGA_IE * math.cos(lat)
    if h < 1e-3 * OMEGA_IE:
        raise ValueError(f"gyrocompassing needs a horizontal Earth rate; latitude {lat} rad")
    w_l = rot_nb_level.apply(np.asarray(gyro_b, dtype=float))
    yaw = math.atan2(float(w_l[0]), float(w_l[1]))
    mat_nb = (Rotation.from_rotvec([0.0, 0.0, yaw]) * rot_nb_level).as_matrix()
    return yaw, -mat_nb[0] / h
