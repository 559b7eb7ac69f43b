"""The simulated ground vehicle's sensors: the IMU's mounting and lever arm, road vibration, a wheel odometer.

A :class:`~polins.sim.trajectory.Trajectory` of :func:`~polins.sim.trajectory.ugv_drive`
is the motion of the vehicle: its body frame is the vehicle frame ``v`` and its position
the vehicle's non-holonomic reference point. :func:`mounted_trajectory` gives the motion
of an IMU mounted on it (rotated by ``mat_vb``, displaced by the lever arm), the truth a
log then carries. :func:`road_vibration` adds the vibration a rolling vehicle feels (by default
in the specific force only: zero-mean, band-limited, proportional to speed up to
``full_speed_mps``): it is what lets an IMU tell a smooth drive at constant speed from a
standstill. :func:`odometer_speeds` is a noisy, scale-biased wheel-odometer stream.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray
from scipy.signal import butter, sosfilt
from scipy.spatial.transform import Rotation

from polins.fusion.vehicle import mat_vb_from_mount
from polins.ins.earth import radii_of_curvature
from polins.sim.trajectory import Trajectory

FloatArray = NDArray[np.float64]

# The UGV scenario's vehicle (polins simulate --scenario ugv): IMU mounted 0.5, -1, 2 deg
# (roll, pitch, yaw) off the vehicle axes, 0.6 m ahead of, 0.1 m right of and 0.3 m above
# the rear axle's centre; a 10 Hz odometer with a +1 % scale error and 0.05 m/s noise.
UGV_MOUNT_RPY_DEG = (0.5, -1.0, 2.0)
UGV_LEVER_ARM_B = (-0.6, 0.1, -0.3)
UGV_ODOMETER = {"rate_hz": 10.0, "scale": 0.01, "noise_std": 0.05}


def mounted_trajectory(
    traj: Trajectory, mount_rpy: ArrayLike, lever_arm_b: ArrayLike
) -> Trajectory:
    """The trajectory of an IMU mounted on the vehicle that follows ``traj``.

    Parameters
    ----------
    traj : Trajectory
        The vehicle: body frame = vehicle frame, position = its reference point.
    mount_rpy : (3,) array_like
        Roll, pitch, yaw of the IMU in the vehicle frame [rad] (``FuseConfig.mount_rpy``).
    lever_arm_b : (3,) array_like
        From the IMU to the reference point, IMU body axes [m] (``FuseConfig.lever_arm_b``).

    Returns
    -------
    Trajectory
        ``rot_nb = rot_nv rot_vb``, ``omega_b = mat_bv omega_v``, the IMU at
        ``p_ref - mat_nb lever_arm_b`` with ``vel_n = vel_ref - mat_nb (omega_b x l)`` and
        its derivative (``omega_b``'s derivative by central differences).
    """
    rot_vb = Rotation.from_matrix(mat_vb_from_mount(mount_rpy))
    lever = np.asarray(lever_arm_b, dtype=float).reshape(3)
    rot_nb = traj.rot_nb * rot_vb
    omega_b = rot_vb.inv().apply(traj.omega_nb_b)
    domega_b = np.gradient(omega_b, traj.t, axis=0)
    arm_n = rot_nb.apply(lever)
    vel_n = traj.vel_n - rot_nb.apply(np.cross(omega_b, lever))
    accel_b = np.cross(domega_b, lever) + np.cross(omega_b, np.cross(omega_b, lever))
    accel_n = traj.accel_n - rot_nb.apply(accel_b)
    r_m, r_n = radii_of_curvature(traj.lat)
    return Trajectory(
        t=traj.t,
        rot_nb=rot_nb,
        vel_n=vel_n,
        lat=traj.lat - arm_n[:, 1] / (r_m + traj.alt_m),
        lon=traj.lon - arm_n[:, 0] / ((r_n + traj.alt_m) * np.cos(traj.lat)),
        alt_m=traj.alt_m - arm_n[:, 2],
        omega_nb_b=omega_b,
        accel_n=accel_n,
    )


def road_vibration(
    t: FloatArray,
    speed_mps: FloatArray,
    rng: np.random.Generator,
    *,
    accel_rms: float = 0.1,
    gyro_rms: float = 0.0,
    band_hz: tuple[float, float] = (8.0, 40.0),
    full_speed_mps: float = 0.5,
) -> tuple[FloatArray, FloatArray]:
    """Vibration of a rolling vehicle at the IMU: ``(gyro (N, 3) [rad/s], accel (N, 3)
    [m/s^2])``, band-pass noise of ``band_hz`` with RMS ``gyro_rms``, ``accel_rms`` per axis
    at ``|speed| >= full_speed_mps`` [m/s], proportional below (zero at standstill).

    The default has no angular vibration: its attitude jitter (0.2 deg/s at 8-40 Hz is about
    0.002 deg) is not in the trajectory's truth, and a navigation-grade filter with
    zero-velocity updates resolves the tilt finer than that."""
    rate_hz = float((len(t) - 1) / (t[-1] - t[0]))
    high = min(band_hz[1], 0.45 * rate_hz)
    sos = butter(2, [band_hz[0], high], btype="band", fs=rate_hz, output="sos")
    noise = sosfilt(sos, rng.standard_normal((len(t), 6)), axis=0)
    noise /= np.sqrt(np.mean(noise**2, axis=0))
    level = np.clip(np.abs(np.asarray(speed_mps, dtype=float)) / full_speed_mps, 0.0, 1.0)
    return noise[:, :3] * (gyro_rms * level)[:, None], noise[:, 3:] * (accel_rms * level)[:, None]


def forward_speed(traj: Trajectory) -> FloatArray:
    """The vehicle's forward speed [m/s]: body-x velocity of the vehicle trajectory ``traj``."""
    return traj.rot_nb.inv().apply(traj.vel_n)[:, 0]


def odometer_speeds(
    traj: Trajectory,
    rng: np.random.Generator,
    *,
    rate_hz: float = 10.0,
    scale: float = 0.01,
    noise_std: float = 0.05,
) -> pd.DataFrame:
    """A wheel odometer on the vehicle ``traj``: ``t`` [s] at ``rate_hz`` (trajectory
    samples) and ``speed = (1 + scale) v_x + noise`` [m/s]."""
    every = max(1, round(traj.rate_hz / rate_hz))
    idx = np.arange(every, len(traj.t), every)
    speed = (1.0 + scale) * forward_speed(traj)[idx] + noise_std * rng.standard_normal(idx.size)
    return pd.DataFrame({"t": traj.t[idx], "speed": speed})


__all__ = [
    "UGV_LEVER_ARM_B",
    "UGV_MOUNT_RPY_DEG",
    "UGV_ODOMETER",
    "forward_speed",
    "mounted_trajectory",
    "odometer_speeds",
    "road_vibration",
]
