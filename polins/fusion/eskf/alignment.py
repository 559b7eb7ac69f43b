"""Self-alignment of the ESKF: levelling (with gyrocompassing) over a static window, and the yaw set from the heading measurements.

Levelling assumes the vehicle static during the first ``align_s`` seconds: roll and pitch
from the averaged specific force, with the tilt error's exact correlation with the
accelerometer bias (a horizontal bias ``b`` tilts the estimate by ``b / g``); the yaw is
unknown (reported as NaN) until the heading measurements agree on it
(:mod:`polins.fusion.eskf.acquisition`: each gives a
:func:`~polins.fusion.acquisition.yaw_offset`, the consensus sets the yaw with :func:`rotate_yaw`: its variance becomes the consensus', its
correlations zero). The vehicle may move before that only if the yaw does not matter for
the velocity then (it stands still, or drives straight from rest: the velocity is rotated with the
frame at the alignment). When the mechanization includes the Earth rate, the levelling
also gyrocompasses (:func:`polins.ins.alignment.gyrocompass`, with the yaw error's
correlation with the gyro bias) if that yaw is better than ``GYROCOMPASS_MAX_STD``, so that
the Earth rate is compensated about the right axes until the first yaw measurement (with a
yaw off by ``d`` the tilt would drift by ``2 sin(d/2) Omega cos L``); that coarse yaw is
not reported.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from polins.fusion.config import FuseConfig
from polins.fusion.eskf.blocks import Layout
from polins.fusion.sky_states import link_acquired_yaw
from polins.ins.alignment import gyrocompass, level_from_accel
from polins.ins.earth import OMEGA_IE, normal_gravity
from polins.ins.strapdown import Mechanization

FloatArray = NDArray[np.float64]
log = logging.getLogger("polins.fusion")

GYROCOMPASS_MAX_STD = math.radians(5.0)  # self-alignment gyrocompasses below this sigma


def level(
    t: FloatArray,
    gyro_b: FloatArray,
    accel_b: FloatArray,
    lat: float,
    alt_m: float,
    P: FloatArray,
    layout: Layout,
    config: FuseConfig,
    mech: Mechanization,
) -> tuple[FloatArray, FloatArray]:
    """The levelled attitude ``mat_nb`` and the covariance after the static window.

    Parameters
    ----------
    t : (K,) ndarray
        Sample times of the window [s].
    gyro_b, accel_b : (K, 3) ndarray
        Raw body rates [rad/s] and specific forces [m/s^2].
    lat, alt_m : float
        Position [rad], [m].
    P : (n, n) ndarray
        The initial covariance (its sensor-error blocks are kept).
    layout : Layout
        The error-state blocks.
    config : FuseConfig
        ``align_s`` and ``vel_std0``; ``config.imu`` for the noise.
    mech : Mechanization
        With the Earth rate: gyrocompass.
    """
    model = config.imu
    f_mean = accel_b.mean(axis=0)
    g = float(normal_gravity(lat, alt_m))
    if abs(np.linalg.norm(f_mean) - g) > 0.05 * g or np.max(np.abs(gyro_b)) > 0.2:
        log.warning(
            "self-alignment: the IMU does not look static in the first %.2f s "
            "(|f| = %.3f m/s^2, max |w| = %.3f rad/s); roll/pitch may be wrong",
            config.initial.align_s, np.linalg.norm(f_mean), np.max(np.abs(gyro_b)),
        )  # fmt: skip
    roll, pitch = level_from_accel(f_mean)
    rot = Rotation.from_euler("ZYX", [0.0, pitch, roll])
    duration = max(float(t[-1] - t[0]), 1.0 / max(model.sample_rate_hz, 1.0))
    att, bg, ba, vel = (layout[k] for k in ("att", "bg", "ba", "vel"))
    P = P.copy()
    P[att, :] = 0.0
    P[:, att] = 0.0
    yaw_var = 1.0  # yaw unknown until the first yaw measurement
    if mech.earth_rotation:
        yaw0, j_bg = gyrocompass(gyro_b.mean(axis=0), rot, lat)
        var = j_bg @ P[bg, bg] @ j_bg + (model.gyro_arw**2 / duration) * (j_bg @ j_bg)
        if var < GYROCOMPASS_MAX_STD**2:
            rot = Rotation.from_rotvec([0.0, 0.0, yaw0]) * rot
            yaw_var = float(var)
            P[2, bg] = j_bg @ P[bg, bg]
            P[bg, 2] = P[2, bg]
        else:  # the covariance carries it: the yaw variance couples into the tilt
            log.info(
                "self-alignment: the gyro bias (%.3g deg/h) is too large to gyrocompass "
                "(yaw sigma %.1f deg); with the Earth rate mechanized the tilt drifts "
                "by up to %.2g rad/s until the first yaw measurement",
                np.degrees(model.gyro_bias) * 3600.0, np.degrees(math.sqrt(var)),
                2.0 * OMEGA_IE * math.cos(lat),
            )  # fmt: skip
    # tilt error = J dba exactly, plus the averaged white noise of the accelerometer
    J = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0]]) @ rot.as_matrix() / g
    p_ba = P[ba, ba]
    P[0:2, 0:2] = J @ p_ba @ J.T + np.eye(2) * ((model.accel_vrw / g) ** 2 / duration)
    P[0:2, ba] = J @ p_ba
    P[ba, 0:2] = (J @ p_ba).T
    P[2, 2] = yaw_var
    P[vel, vel] = np.eye(3) * config.initial.vel_std0**2
    if config.no_clock:  # the heading is relative to the levelled yaw (docs/filter.md §5.7)
        P[2, :] = P[:, 2] = 0.0
    return rot.as_matrix(), P


def rotate_yaw(
    delta: float,
    std: float,
    mat_nb: FloatArray,
    vel_n: FloatArray,
    P: FloatArray,
    layout: Layout,
    sun_n: FloatArray | None = None,
    tilt_gain: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Attitude, velocity and covariance with the yaw turned by ``delta`` [rad] (the error
    state is zero: called after a reset). The rotation turns the velocity and the
    attitude/velocity covariance with it; the yaw variance becomes ``std**2`` [rad^2], its
    correlations zero, except with the states that turn the measured heading (a heading
    bias, a site error seen with the ENU sun ``sun_n`` of the headings, the tilt through
    the headings' ``tilt_gain`` (2,) [-]: :func:`~polins.fusion.sky_states.link_acquired_yaw`)."""
    rz = Rotation.from_rotvec([0.0, 0.0, delta]).as_matrix()
    att, vel = layout["att"], layout["vel"]
    T = np.eye(layout.n)
    T[att, att] = rz
    T[vel, vel] = rz
    P = T @ P @ T.T
    P[2, :] = 0.0
    P[:, 2] = 0.0
    P[2, 2] = std**2
    return rz @ mat_nb, rz @ vel_n, link_acquired_yaw(P, layout.index, sun_n, tilt_gain=tilt_gain)
