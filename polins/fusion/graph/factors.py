"""GTSAM factors of the graph: IMU preintegration, sun, yaw, zero-velocity, zero-rate, levelling, non-holonomic

Every ``CustomFactor`` here evaluates the shared measurement models of
:mod:`polins.fusion.measurement` (the ESKF's ``(z, H, R)``) and maps their navigation-frame
attitude columns to GTSAM's body-right tangent (:func:`body_jacobian`).
"""

from __future__ import annotations

from typing import Any

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from polins.fusion.graph.batched import NonHolonomicBatch, YawBatch
from polins.fusion.measurement import (
    ATT,
    BA,
    BG,
    VEL,
    as_mat_nb,
    level_kernel,
    non_holonomic_kernel,
    yaw_kernel,
    zero_rate_kernel,
)
from polins.models import ImuModel

FloatArray = NDArray[np.float64]


def pose_cov_nav_from_body(mat_nb: ArrayLike, cov_pose_b: ArrayLike) -> FloatArray:
    """Pose covariance in GTSAM's body-frame tangent space -> navigation frame ``(6, 6)``.

    GTSAM retracts a ``Pose3`` as ``(R exp(w_b), p + R v_b)``; the ESKF's errors are
    ``dtheta_n = R w_b`` and ``dp_n = R v_b``, so ``cov_n = T cov_b T^T`` with
    ``T = blockdiag(R, R)``.
    """
    r = np.asarray(mat_nb, dtype=float)
    t = np.zeros((6, 6))
    t[:3, :3] = r
    t[3:, 3:] = r
    return t @ np.asarray(cov_pose_b, dtype=float) @ t.T


def pose_cov_body_from_nav(mat_nb: ArrayLike, cov_pose_n: ArrayLike) -> FloatArray:
    """Inverse of :func:`pose_cov_nav_from_body` ``(6, 6)``."""
    return pose_cov_nav_from_body(np.asarray(mat_nb, dtype=float).T, cov_pose_n)


def bias_from_polins(bias: ArrayLike) -> gtsam.imuBias.ConstantBias:
    """GTSAM bias from polins order ``[bg (3) rad/s, ba (3) m/s^2]`` (GTSAM: accel first)."""
    b = np.asarray(bias, dtype=float)
    return gtsam.imuBias.ConstantBias(b[3:6], b[0:3])


def body_jacobian(h_att_n: FloatArray, mat_nb: FloatArray) -> FloatArray:
    """Jacobian on a ``Pose3`` tangent ``[w_b, v_b]`` ``(m, 6)`` from one on the ESKF's
    navigation-frame attitude error ``(m, 3)``: ``dtheta_n = R_nb w_b``, so ``H_n R_nb``."""
    jac = np.zeros((h_att_n.shape[0], 6))
    jac[:, :3] = h_att_n @ mat_nb
    return jac


def preintegration_params(
    imu_model: ImuModel,
    *,
    gravity_mps2: float,
    omega_ie_n: ArrayLike | None = None,
    integration_std: float = 1e-2,
    gyro_density: float | None = None,
    accel_density: float | None = None,
    gyro_bias_density: float | None = None,
) -> gtsam.PreintegrationCombinedParams:
    """``PreintegrationCombinedParams`` for an ENU navigation frame from an IMU model.

    Parameters
    ----------
    imu_model : ImuModel
        White-noise densities (ARW [rad/sqrt(s)], VRW [m/s/sqrt(s)]) become GTSAM's
        continuous-time gyro and accelerometer covariances; the bias random walks
        [rad/s/sqrt(s)], [m/s^2/sqrt(s)] the bias covariances (variance growth per second).
    gravity_mps2 : float
        Magnitude of gravity [m/s^2]: ``n_gravity = (0, 0, -g)`` (``MakeSharedU``).
    omega_ie_n : (3,) array_like, optional
        Earth rate in ENU [rad/s] (:func:`polins.ins.earth.earth_rate_n`) as ``omegaCoriolis``;
        None for a non-rotating navigation frame.
    integration_std : float
        Position-integration noise density [m/sqrt(s)] (GTSAM's integration covariance).
        Without position measurements the positions are a sink of the graph and this value
        does not change the attitude, velocity or bias estimates; 1 cm/sqrt(s) keeps the
        position chain from dominating the conditioning.
    gyro_density, accel_density, gyro_bias_density : float, optional
        Replace the model's white-noise variance densities ``ARW^2`` [rad^2/s], ``VRW^2``
        [m^2/s^3] and gyro bias random-walk density [rad^2/s^3] (one keyframe interval's
        rotation-proportional noise and IMU-gap inflation, :func:`gyro_noise_density`; the
        unmechanized Earth rate).
    """
    params = gtsam.PreintegrationCombinedParams.MakeSharedU(float(gravity_mps2))
    eye = np.eye(3)
    gyro = imu_model.gyro_arw**2 if gyro_density is None else gyro_density
    accel = imu_model.accel_vrw**2 if accel_density is None else accel_density
    bias_rw = imu_model.gyro_bias_rw**2 if gyro_bias_density is None else gyro_bias_density
    params.setGyroscopeCovariance(eye * gyro)
    params.setAccelerometerCovariance(eye * accel)
    params.setIntegrationCovariance(eye * integration_std**2)
    # GTSAM needs a regular bias covariance; 1e-30 per second is far below any real IMU.
    params.setBiasOmegaCovariance(eye * max(bias_rw, 1e-30))
    params.setBiasAccCovariance(eye * max(imu_model.accel_bias_rw**2, 1e-30))
    if omega_ie_n is not None:
        params.setOmegaCoriolis(np.asarray(omega_ie_n, dtype=float))
    return params


def gyro_noise_density(imu_model: ImuModel, rate_sq: ArrayLike) -> FloatArray:
    """Gyro white-noise variance density of keyframe intervals [rad^2/s] (docs/filter.md §9).

    ``ARW^2 + m^2 mean|omega_b|^2 tau``: the axis misalignment ``m``
    (``ImuModel.gyro_misalignment``, ``tau = gyro_misalignment_corr_time``) turns rotation
    into attitude error, covered as the ESKF covers it (docs/filter.md,
    "Rotation-proportional attitude noise"). The scale factors are variables of the graph
    (:mod:`polins.fusion.graph.imu`), not noise.

    Parameters
    ----------
    imu_model : ImuModel
        ``gyro_arw`` [rad/sqrt(s)], ``gyro_misalignment`` [rad] and its correlation time [s].
    rate_sq : array_like
        Mean of ``|omega_b|^2`` over each interval [rad^2/s^2].
    """
    m = imu_model
    rate_sq = np.asarray(rate_sq, dtype=float)
    return m.gyro_arw**2 + m.gyro_misalignment**2 * m.gyro_misalignment_corr_time * rate_sq


def sun_factor(
    key: int, sun_n: ArrayLike, sun_b: ArrayLike, sun_std: float
) -> gtsam.AttitudeFactorPose3:
    """Sun-vector factor ``AttitudeFactorPose3(key, nRef=sun_n, model, bMeasured=sun_b)``.

    Error ``B(sun_n)^T (R_nb sun_b)`` [rad] (2,) with ``B = Unit3(sun_n).basis()``: zero
    when the measured body direction, rotated to ENU, is the ephemeris direction; its norm
    is the sine of the angle between them. Isotropic ``sun_std`` [rad].
    """
    if not np.isfinite(sun_std) or sun_std <= 0:
        raise ValueError(f"sun_std must be finite and > 0 [rad], got {sun_std!r}")
    return gtsam.AttitudeFactorPose3(
        key,
        gtsam.Unit3(np.asarray(sun_n, dtype=float)),
        gtsam.noiseModel.Isotropic.Sigma(2, float(sun_std)),
        gtsam.Unit3(np.asarray(sun_b, dtype=float)),
    )


def yaw_factor(
    key: int,
    yaw: float,
    yaw_std: float,
    *,
    sun_n: ArrayLike | None = None,
    rot_nb_prior: Rotation | ArrayLike | None = None,
    batch: YawBatch | None = None,
) -> gtsam.CustomFactor:
    """Yaw factor on ``X(k)`` with the ESKF's model (:func:`~polins.fusion.measurement.yaw_kernel`).

    GTSAM error ``h(x) - z = -residual`` [rad] (wrapped); Jacobian with respect to the
    ``Pose3`` tangent ``[w_b, v_b]``: ``[H_theta R_nb, 0]``. With ``sun_n`` and
    ``rot_nb_prior`` (the tilt coupling of docs/model.md §10.2, option ``tilt_coupling``)
    ``h(x)`` is the yaw ``polins.measure`` computes with that prior from the sun seen at
    attitude ``x``: it depends on the tilt of ``x``. A graph re-linearizes away from the
    prior, so the tilt coupling needs the prior (the ESKF may default it to its own state).
    ``batch``: evaluated with the other yaw factors of the same kind (with or without the
    tilt coupling; :mod:`polins.fusion.graph.batched`).
    """
    if not (np.isfinite(yaw) and np.isfinite(yaw_std) and yaw_std > 0):
        raise ValueError(f"yaw and yaw_std must be finite, yaw_std > 0; got {yaw}, {yaw_std}")
    var = float(yaw_std) ** 2
    sun = None if sun_n is None else np.asarray(sun_n, dtype=float)
    if sun is not None:
        sun = sun / np.linalg.norm(sun)
    if (sun is None) != (rot_nb_prior is None):
        raise ValueError("the tilt-coupled yaw factor needs both sun_n and rot_nb_prior")
    prior = None if rot_nb_prior is None else as_mat_nb(rot_nb_prior)
    z = float(yaw)
    slot = -1
    if batch is not None:
        if batch.tilt != (sun is not None):
            raise ValueError("a yaw factor's batch must match its tilt coupling")
        slot = batch.add([key], z) if sun is None else batch.add([key], z, sun, prior)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians: Any) -> FloatArray:
        if batch is not None:
            hit = batch.lookup(slot, values, jacobians)
            if hit is not None:
                return hit
        mat_nb = values.atPose3(this.keys()[0]).rotation().matrix()
        lin = yaw_kernel(mat_nb, z, var, sun, prior)
        if jacobians is not None:
            jacobians[0] = body_jacobian(lin.H[:, ATT], mat_nb)
        return -lin.residual

    return gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, float(yaw_std)), [key], error)


def zero_velocity_factor(vel_key: int, std: float) -> gtsam.PriorFactorVector:
    """Zero-velocity factor (vehicle at rest): C++ ``PriorFactorVector(V(k), 0, std)`` [m/s]."""
    return gtsam.PriorFactorVector(
        vel_key, np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, float(std))
    )


def zero_rate_factor(
    pose_key: int,
    bias_key: int,
    gyro_b: FloatArray,
    std: float,
    rate_n: FloatArray | None = None,
) -> gtsam.CustomFactor:
    """Zero-angular-rate factor (the body at rest): the mean measured rate ``gyro_b``
    [rad/s] is the gyro bias plus ``mat_bn rate_n`` (the Earth rate, when mechanized)
    (``CustomFactor`` on ``X(k)``, ``B(k)``; docs/filter.md §12).

    Residual and Jacobian of :func:`polins.fusion.measurement.zero_rate`; the attitude
    columns are mapped to GTSAM's body-right tangent (:func:`body_jacobian`), the bias
    columns to ``ConstantBias``' tangent (accelerometer, then gyro).
    """
    var = np.full(3, float(std) ** 2)
    rate = np.asarray(gyro_b, dtype=float)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians: Any) -> FloatArray:
        pkey, bkey = this.keys()
        mat_nb = values.atPose3(pkey).rotation().matrix()
        bias_g = values.atConstantBias(bkey).gyroscope()
        lin = zero_rate_kernel(mat_nb, rate, bias_g, var, rate_n)
        if jacobians is not None:
            jacobians[0] = body_jacobian(lin.H[:, ATT], mat_nb)
            jac_bias = np.zeros((3, 6))
            jac_bias[:, 3:] = lin.H[:, BG]
            jacobians[1] = jac_bias
        return -lin.residual

    return gtsam.CustomFactor(
        gtsam.noiseModel.Isotropic.Sigma(3, float(std)), [pose_key, bias_key], error
    )


def non_holonomic_factor(
    pose_key: int,
    vel_key: int,
    std: float,
    mat_vb: FloatArray | None = None,
    lever_vel_b: FloatArray | None = None,
    batch: NonHolonomicBatch | None = None,
) -> gtsam.CustomFactor:
    """Non-holonomic factor: zero lateral and vertical velocity of the vehicle's reference
    point in the vehicle frame [m/s] (``CustomFactor``; ``mat_vb`` the IMU mounting,
    ``lever_vel_b = omega_b x lever_arm_b`` [m/s], both optional).

    Residual and Jacobian of :func:`polins.fusion.measurement.non_holonomic`; the attitude
    columns are mapped to GTSAM's body-right tangent (:func:`body_jacobian`), the velocity
    columns are used as they are (``Vector3`` tangent = ENU velocity change). ``batch``:
    evaluated with the other non-holonomic factors (:mod:`polins.fusion.graph.batched`).
    """
    var = np.full(2, float(std) ** 2)
    slot = -1
    if batch is not None:
        slot = batch.add([pose_key, vel_key], np.eye(3) if mat_vb is None else mat_vb,
                         np.zeros(3) if lever_vel_b is None else lever_vel_b)  # fmt: skip

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians: Any) -> FloatArray:
        if batch is not None:
            hit = batch.lookup(slot, values, jacobians)
            if hit is not None:
                return hit
        pkey, vkey = this.keys()
        mat_nb = values.atPose3(pkey).rotation().matrix()
        lin = non_holonomic_kernel(mat_nb, values.atVector(vkey), var, mat_vb, lever_vel_b)
        if jacobians is not None:
            jacobians[0] = body_jacobian(lin.H[:, ATT], mat_nb)
            jacobians[1] = np.ascontiguousarray(lin.H[:, VEL])
        return -lin.residual

    return gtsam.CustomFactor(
        gtsam.noiseModel.Isotropic.Sigma(2, float(std)), [pose_key, vel_key], error
    )


def levelling_factor(
    pose_key: int, bias_key: int, force_b: ArrayLike, std: float
) -> gtsam.CustomFactor:
    """Levelling: a mean specific force ``force_b`` [m/s^2] of a body at rest.

    The shared model :func:`polins.fusion.measurement.level`: the horizontal (E, N)
    components of ``C_nb (force_b - b_a)`` are zero [m/s^2], sigma ``std`` (``VRW /
    sqrt(T)``): the self-alignment's levelling (docs/filter.md §7, §9). Jacobians: the attitude columns on GTSAM's body-right tangent
    (:func:`body_jacobian`), the accelerometer-bias columns on ``ConstantBias``' tangent.
    """
    f_b = np.asarray(force_b, dtype=float)
    var = np.full(2, float(std) ** 2)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians: Any) -> FloatArray:
        pkey, bkey = this.keys()
        mat_nb = values.atPose3(pkey).rotation().matrix()
        lin = level_kernel(mat_nb, f_b, values.atConstantBias(bkey).accelerometer(), var)
        if jacobians is not None:
            jacobians[0] = body_jacobian(lin.H[:, ATT], mat_nb)
            jac_bias = np.zeros((2, 6))
            jac_bias[:, :3] = lin.H[:, BA]
            jacobians[1] = jac_bias
        return -lin.residual

    return gtsam.CustomFactor(
        gtsam.noiseModel.Isotropic.Sigma(2, float(std)), [pose_key, bias_key], error
    )
