"""IMU simulation: ideal strapdown measurements of a trajectory, and the sensor error model.

The ideal IMU is physically complete in the local ENU frame (Titterton & Weston, Strapdown
Inertial Navigation Technology, 2nd ed., Eq. 3.39-3.41; Groves, Principles of GNSS,
Inertial and Multisensor Integrated Navigation, 2nd ed., Eq. 5.53-5.54)::

    omega_ib_b = omega_nb_b + C_bn (omega_ie_n + omega_en_n)
    f_b        = C_bn (a_n + (2 omega_ie_n + omega_en_n) x v_n - g_n)

with ``a_n = d(v_n)/dt``, WGS-84 normal gravity ``g_n`` (gravitation plus centrifugal) and the
Earth and transport rates from ``polins.ins.earth``. Row k holds the instantaneous values at
``t_k`` (docs/filter.md: the strapdown integrates assuming they vary linearly between rows).

The error model (``polins.models.ImuModel``), per axis and independently::

    measured = (1 + s) * ideal + b(t) + w_k
    b(t_k)   = b0 + sum_{j=1..k} q_j,   q_j ~ N(0, K^2 dt)      (bias random walk K)
    b0 ~ N(0, sigma_b^2),  s ~ N(0, sigma_s^2),  w_k ~ N(0, N^2 * rate_hz)

where ``N`` is the white-noise density (ARW [rad/sqrt(s)] or VRW [m/s/sqrt(s)]), so that
the Allan deviation is ``N / sqrt(tau)`` at short and ``K sqrt(tau / 3)`` at long ``tau``
(IEEE Std 952-1997, Annex C). A model with an axis misalignment ``m`` (``gyro_misalignment``,
``accel_misalignment``) couples the axes: ``ideal`` becomes ``(I + M) ideal`` with a constant
``M`` whose off-diagonal entries are ``N(0, m^2)`` and whose diagonal is zero (the scale
factors), drawn after all other errors so that the other draws do not change.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from polins.ins.earth import earth_rate_n, gravity_n, transport_rate_n
from polins.models import ImuModel
from polins.sim.trajectory import Trajectory

FloatArray = NDArray[np.float64]

IMU_COLUMNS = ["t", "gx", "gy", "gz", "ax", "ay", "az"]
ERROR_COLUMNS = [
    "t",
    "bgx",
    "bgy",
    "bgz",
    "bax",
    "bay",
    "baz",
    "sgx",
    "sgy",
    "sgz",
    "sax",
    "say",
    "saz",
]


def ideal_imu(traj: Trajectory, *, earth_rotation: bool = True) -> pd.DataFrame:
    """Error-free gyro and accelerometer samples along a trajectory.

    Parameters
    ----------
    traj : Trajectory
        True motion (``polins.sim.trajectory``).
    earth_rotation : bool
        True (default): a rotating Earth (the gyros sense the Earth rate, the
        accelerometers the Coriolis acceleration). False: a non-rotating Earth, for tests
        of a mechanization without Earth rate; the transport rate and ``omega_en x v``
        stay since they are kinematic, and ``g_n`` is the same normal gravity.

    Returns
    -------
    DataFrame
        Columns ``t`` [s], ``gx, gy, gz`` = ``omega_ib_b`` [rad/s] and ``ax, ay, az`` =
        specific force ``f_b`` [m/s^2], body FLU, instantaneous at ``t``.
    """
    if not isinstance(traj, Trajectory):
        raise ValueError(f"traj must be a polins.sim.trajectory.Trajectory, got {type(traj)}")
    omega_en_n = transport_rate_n(traj.lat, traj.alt_m, traj.vel_n)
    omega_ie_n = earth_rate_n(traj.lat) if earth_rotation else np.zeros_like(omega_en_n)
    rot_bn = traj.rot_nb.inv()
    gyro_b = traj.omega_nb_b + rot_bn.apply(omega_ie_n + omega_en_n)
    coriolis_n = np.cross(2.0 * omega_ie_n + omega_en_n, traj.vel_n)
    force_b = rot_bn.apply(traj.accel_n + coriolis_n - gravity_n(traj.lat, traj.alt_m))
    return pd.DataFrame(np.column_stack([traj.t, gyro_b, force_b]), columns=pd.Index(IMU_COLUMNS))


def _sample_rate(t: FloatArray) -> float:
    if len(t) < 2:
        raise ValueError("the IMU table needs at least 2 samples")
    dt = np.diff(t)
    if np.any(dt <= 0):
        raise ValueError("IMU times t must be strictly increasing")
    mean = (t[-1] - t[0]) / (len(t) - 1)
    if np.max(np.abs(dt - mean)) > 1e-6 * mean + 1e-9:
        raise ValueError("IMU times t must be uniformly spaced to simulate sensor noise")
    return float(1.0 / mean)


def imu_errors(
    ideal: pd.DataFrame, model: ImuModel, rng: np.random.Generator
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Corrupt ideal IMU samples with the model's errors (see the module docstring).

    Parameters
    ----------
    ideal : DataFrame
        Columns ``t, gx, gy, gz, ax, ay, az`` (e.g. from :func:`ideal_imu`), uniform ``t``.
    model : ImuModel
        Error model (``polins.load_imu``): white-noise densities, turn-on bias and scale
        factor 1-sigma, bias random-walk densities. The white-noise std per sample is
        ``density * sqrt(rate_hz)`` at the table's own rate.
    rng : numpy.random.Generator
        Source of all random draws (the same seed gives the same errors).

    Returns
    -------
    measured : DataFrame
        Same columns as ``ideal``: ``(1 + s) * ideal + b(t) + white noise``.
    errors : DataFrame
        The true error states per sample: ``t``, biases ``bgx, bgy, bgz`` [rad/s] and
        ``bax, bay, baz`` [m/s^2] at ``t`` (turn-on plus random walk), and the constant
        scale-factor errors ``sgx, sgy, sgz, sax, say, saz`` [-]. A model's axis
        misalignment is not among them: on a near-level vehicle a filter's accelerometer-bias
        states estimate ``b + M g_b``, not ``b`` (docs/imu-model.md, "Cross-axis coupling and
        misalignment").
    """
    missing = [c for c in IMU_COLUMNS if c not in ideal.columns]
    if missing:
        raise ValueError(f"ideal IMU table lacks columns {missing}; expected {IMU_COLUMNS}")
    if not isinstance(model, ImuModel):
        raise ValueError(f"model must be a polins.ImuModel (polins.load_imu), got {type(model)}")
    if not isinstance(rng, np.random.Generator):
        raise ValueError("rng must be a numpy.random.Generator, e.g. np.random.default_rng(0)")
    t = ideal["t"].to_numpy(dtype=float)
    rate_hz = _sample_rate(t)
    n = len(t)
    dt = 1.0 / rate_hz

    # Order of draws is fixed: turn-on biases, scale factors, random-walk steps, white noise.
    bias0 = rng.standard_normal(6) * np.repeat([model.gyro_bias, model.accel_bias], 3)
    scale = rng.standard_normal(6) * np.repeat(
        [model.gyro_scale_factor, model.accel_scale_factor], 3
    )
    rw_std = np.repeat([model.gyro_bias_rw, model.accel_bias_rw], 3) * np.sqrt(dt)
    steps = rng.standard_normal((n, 6)) * rw_std
    steps[0] = 0.0  # b(t_0) = b0
    bias = bias0 + np.cumsum(steps, axis=0)
    white_std = np.repeat([model.gyro_arw, model.accel_vrw], 3) * np.sqrt(rate_hz)
    white = rng.standard_normal((n, 6)) * white_std

    true = ideal[IMU_COLUMNS[1:]].to_numpy(dtype=float, copy=True)
    for cols, m in (
        (slice(0, 3), model.gyro_misalignment),
        (slice(3, 6), model.accel_misalignment),
    ):
        if m:
            mis = rng.standard_normal((3, 3)) * m
            np.fill_diagonal(mis, 0.0)
            true[:, cols] += true[:, cols] @ mis.T
    measured = (1.0 + scale) * true + bias + white
    measured_df = pd.DataFrame(np.column_stack([t, measured]), columns=pd.Index(IMU_COLUMNS))
    errors_df = pd.DataFrame(
        np.column_stack([t, bias, np.broadcast_to(scale, (n, 6))]),
        columns=pd.Index(ERROR_COLUMNS),
    )
    return measured_df, errors_df


__all__ = ["ERROR_COLUMNS", "IMU_COLUMNS", "ideal_imu", "imu_errors"]
