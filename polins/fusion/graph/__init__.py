"""GTSAM factor-graph backend: IMU preintegration with sun-vector and yaw factors.

The optional second backend of ``polins.fuse(..., backend="graph")`` (``pip install
"polins[graph]"``). It estimates the same 15 error states as the ESKF
(:mod:`polins.fusion.eskf`) from the same inputs, as a nonlinear least-squares problem over
keyframe states, and returns the same solution table (CONVENTIONS.md).

Graph
-----
Keyframes ``k`` sit at the first and last IMU sample, at every measurement time, at the
``stationary`` times, at the non-holonomic epochs and wherever the gap between them would
exceed ``max_keyframe_dt``.
Each holds ``X(k)`` (``gtsam.Pose3``: attitude ``rot_nb`` and position in local ENU metres),
``V(k)`` (ENU velocity [m/s]) and ``B(k)`` (``imuBias.ConstantBias``: accelerometer, then
gyro bias). Factors:

* ``CombinedImuFactor`` between consecutive keyframes: preintegrated IMU (Forster et al.,
  "On-manifold preintegration for real-time visual-inertial odometry", IEEE TRO 2017) with
  the white-noise densities and bias random walks of the
  :class:`~polins.models.loader.ImuModel`, ENU gravity (``PreintegrationCombinedParams.
  MakeSharedU``, WGS-84 normal gravity at the start). The IMU samples vary linearly between
  rows (INTERFACES.md); each integration step uses the mean of that linear signal, the
  specific force rotated to the start of the step (GTSAM's velocity update is first order:
  without this a turn leaves mm/s-level velocity errors); GTSAM's gravity is constant, so
  the change of normal gravity along the drive is taken out of the accelerometer. With
  Earth rate (``ImuModel.earth_rate``, navigation grade) the Earth rate enters as
  ``omegaCoriolis`` and the transport rate is removed from the gyro samples
  (``omega_ib_b - C_bn omega_en_n`` at the current estimate of velocity and position), so
  that the graph's navigation frame is the local-level ENU frame of the ESKF rather than an
  Earth-fixed tangent plane.
* Sun vector: GTSAM's C++ ``AttitudeFactorPose3(key, nRef=sun_n, model, bMeasured=sun_b)``:
  error ``Unit3(sun_n).error(R_nb sun_b) = B(sun_n)^T R_nb sun_b`` (the measured body
  direction rotated to ENU, in the tangent basis ``B`` of the ephemeris direction),
  isotropic ``sun_std``; ``tests/test_graph.py`` pins these semantics.
* Yaw: a Python ``gtsam.CustomFactor`` with the residual and Jacobian of the ESKF's
  :func:`~polins.fusion.measurement.yaw_measurement` (kernel ``yaw_kernel``). GTSAM's
  error is ``h(x) - z = -residual``. GTSAM perturbs rotations on the right in the body
  frame, ``R exp(w_b)``; the ESKF's error is on the left in the navigation frame,
  ``exp(dtheta_n) R`` with ``dtheta_n = R w_b``; so the Jacobian is ``H_theta R_nb``.
* Non-holonomic (``CustomFactor``, :func:`~polins.fusion.measurement.non_holonomic`) at
  the ESKF's epochs (every IMU sample nearest to ``1 / nhc_rate_hz``; keyframes are added
  there: with a tight ``nhc_std`` the rate matters, and fewer keyframes with a scaled
  sigma lose pitch information); zero velocity (C++ ``PriorFactorVector`` on ``V(k)``) at
  the ``stationary`` times and ``zupt_std`` rows.
* First state: ``rot_nb0`` with ``att_std0``, or self-alignment like the ESKF: a levelling
  factor (mean specific force over ``align_s`` at rest equals ``C_bn (0, 0, g) + b_a``,
  horizontal components, white-noise sigma ``VRW / sqrt(align_s)``; this reproduces the
  ESKF's tilt covariance and its correlation with the accelerometer bias) and a 1 rad yaw
  prior at the first measured yaw; the velocity prior ``vel_std0``, position ``pos_std0`` and
  the IMU model's turn-on bias sigmas.

Solvers
-------
``"batch"``: Gauss-Newton over the whole log (a smoother, like ESKF + RTS), see
:func:`gauss_newton_qr` for why neither Levenberg-Marquardt (``optimizer=
"levenberg-marquardt"`` is available, slower) nor Cholesky; sigmas from the
QR-eliminated Bayes tree (:func:`marginal_covariance_qr`). Outliers are gated on the
post-fit residuals (``r^T (R - H P H^T)^-1 r`` against the chi-square quantile
``gate_prob``) and the graph is re-solved without them. ``"isam2"``: incremental
``gtsam.ISAM2`` as used online: each keyframe is reported as estimated when it was added
(causal, like the filter); gating on the predicted residual with the previous keyframe's
covariance. ``"fixed_lag"``: ``gtsam.IncrementalFixedLagSmoother``; each keyframe is
reported when it leaves the ``lag_s`` window (smoothed with ``lag_s`` of future data).

Output rows are IMU samples (``output_rate_hz``, as the ESKF) or the keyframes
(``output="keyframes"``). Between keyframes the state is the preintegrated prediction from
the previous keyframe with the discontinuity at the next keyframe spread linearly over the
interval; the covariance is interpolated linearly.
"""

from __future__ import annotations

import dataclasses
import itertools
import time
from dataclasses import dataclass, field
from typing import Any

try:
    import gtsam
    from gtsam.symbol_shorthand import B, V, X
except ImportError as exc:  # tests simulate a missing gtsam
    raise ImportError(
        'the graph backend (backend="graph") needs GTSAM >= 4.3: pip install "polins[graph]"'
    ) from exc

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from polins.frames import skew, wrap_angle, yaw_from_rot_nb
from polins.fusion.eskf import solution_columns
from polins.fusion.inputs import (
    validate_imu,
    validate_measurements,
)
from polins.fusion.items import MeasurementItem, gate_limit, item_model, items_from_table
from polins.fusion.measurement import (
    ATT,
    BA,
    BG,
    N_ERROR,
    POS,
    VEL,
    Linearized,
    as_mat_nb,
    non_holonomic_kernel,
    yaw_from_sun,
    yaw_kernel,
)
from polins.ins.alignment import level_from_accel
from polins.ins.earth import earth_rate_n, normal_gravity, radii_of_curvature, transport_rate_n
from polins.models.loader import ImuModel

FloatArray = NDArray[np.float64]

SOLVERS = ("batch", "isam2", "fixed_lag")


# ============================================================================ conversions
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


# ============================================================================ factors
def preintegration_params(
    imu_model: ImuModel,
    *,
    gravity_mps2: float,
    omega_ie_n: ArrayLike | None = None,
    integration_std: float = 1e-2,
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
    """
    params = gtsam.PreintegrationCombinedParams.MakeSharedU(float(gravity_mps2))
    eye = np.eye(3)
    params.setGyroscopeCovariance(eye * imu_model.gyro_arw**2)
    params.setAccelerometerCovariance(eye * imu_model.accel_vrw**2)
    params.setIntegrationCovariance(eye * integration_std**2)
    # GTSAM needs a regular bias covariance; 1e-30 per second is far below any real IMU.
    params.setBiasOmegaCovariance(eye * max(imu_model.gyro_bias_rw**2, 1e-30))
    params.setBiasAccCovariance(eye * max(imu_model.accel_bias_rw**2, 1e-30))
    if omega_ie_n is not None:
        params.setOmegaCoriolis(np.asarray(omega_ie_n, dtype=float))
    return params


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
) -> gtsam.CustomFactor:
    """Yaw factor on ``X(k)`` with the ESKF's model (:func:`~.measurement.yaw_measurement`).

    GTSAM error ``h(x) - z = -residual`` [rad] (wrapped); Jacobian with respect to the
    ``Pose3`` tangent ``[w_b, v_b]``: ``[H_theta R_nb, 0]``. With ``sun_n`` and
    ``rot_nb_prior`` (the SPEC 10.2 tilt coupling, option ``tilt_coupling``) ``h(x)`` is the
    yaw ``polins.measure`` computes with that prior from the sun seen at attitude ``x``: it
    depends on the tilt of ``x``. A graph re-linearizes away from the prior, so the tilt
    coupling needs the prior (the ESKF may default it to its own state).
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

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians: Any) -> FloatArray:
        mat_nb = values.atPose3(this.keys()[0]).rotation().matrix()
        lin = yaw_kernel(mat_nb, z, var, sun, prior)
        if jacobians is not None:
            jac = np.zeros((1, 6))
            jac[:, :3] = lin.H[:, ATT] @ mat_nb
            jacobians[0] = jac
        return -lin.residual

    return gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, float(yaw_std)), [key], error)


def zero_velocity_factor(vel_key: int, std: float) -> gtsam.PriorFactorVector:
    """Zero-velocity factor (vehicle at rest): C++ ``PriorFactorVector(V(k), 0, std)`` [m/s]."""
    return gtsam.PriorFactorVector(
        vel_key, np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, float(std))
    )


def non_holonomic_factor(pose_key: int, vel_key: int, std: float) -> gtsam.CustomFactor:
    """Non-holonomic factor: zero lateral and vertical body velocity [m/s] (``CustomFactor``).

    Residual and Jacobian of :func:`polins.fusion.measurement.non_holonomic`; the attitude
    columns are mapped to GTSAM's body-right tangent as in :func:`yaw_factor`, the velocity
    columns are used as they are (``Vector3`` tangent = ENU velocity change).
    """
    var = np.full(2, float(std) ** 2)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians: Any) -> FloatArray:
        pkey, vkey = this.keys()
        mat_nb = values.atPose3(pkey).rotation().matrix()
        lin = non_holonomic_kernel(mat_nb, values.atVector(vkey), var)
        if jacobians is not None:
            jac_pose = np.zeros((2, 6))
            jac_pose[:, :3] = lin.H[:, ATT] @ mat_nb
            jacobians[0] = jac_pose
            jacobians[1] = np.ascontiguousarray(lin.H[:, VEL])
        return -lin.residual

    return gtsam.CustomFactor(
        gtsam.noiseModel.Isotropic.Sigma(2, float(std)), [pose_key, vel_key], error
    )


def levelling_factor(
    pose_key: int, bias_key: int, force_b: ArrayLike, gravity_mps2: float, std: float
) -> gtsam.CustomFactor:
    """Static levelling: a mean specific force ``force_b`` [m/s^2] of a body at rest.

    Model ``force_b = C_bn (0, 0, g) + b_a``; the factor uses the horizontal (E, N)
    components of ``C_nb (force_b - b_a) - (0, 0, g)`` [m/s^2] (as the ESKF's levelling,
    which does not use the vertical component), with sigma ``std`` (``VRW / sqrt(T)``).
    Jacobians: ``-C_nb [force_b - b_a x]`` (body-right rotation), ``-C_nb`` (accel bias).
    """
    f_b = np.asarray(force_b, dtype=float)
    up_g = np.array([0.0, 0.0, float(gravity_mps2)])

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians: Any) -> FloatArray:
        pkey, bkey = this.keys()
        mat_nb = values.atPose3(pkey).rotation().matrix()
        b_a = values.atConstantBias(bkey).accelerometer()
        f = f_b - b_a
        if jacobians is not None:
            jac_pose = np.zeros((2, 6))
            jac_pose[:, :3] = -(mat_nb @ skew(f))[:2]
            jac_bias = np.zeros((2, 6))
            jac_bias[:, :3] = -mat_nb[:2]
            jacobians[0] = jac_pose
            jacobians[1] = jac_bias
        return (mat_nb @ f - up_g)[:2]

    return gtsam.CustomFactor(
        gtsam.noiseModel.Isotropic.Sigma(2, float(std)), [pose_key, bias_key], error
    )


# ============================================================================ IMU steps
@dataclass(frozen=True, eq=False)
class ImuSegments:
    """The IMU signal cut at the keyframes: one row per integration step.

    The samples are instantaneous values that vary linearly between rows (INTERFACES.md);
    a step between consecutive break points (IMU sample times and keyframe times) uses the
    mean of that linear signal, its value at the step's midpoint, with the specific force
    rotated to the start of the step (``f + dt/2 w x f``, see :func:`imu_segments`).

    Attributes
    ----------
    t : (S + 1,) ndarray
        Break points [s] (the step ``i`` runs from ``t[i]`` to ``t[i + 1]``).
    dt : (S,) ndarray
        Step lengths [s].
    gyro, accel : (S, 3) ndarray
        Step means [rad/s], [m/s^2].
    bounds : (K,) int ndarray
        Index into ``t`` of every keyframe (``bounds[0] = 0``).
    """

    t: FloatArray
    dt: FloatArray
    gyro: FloatArray
    accel: FloatArray
    bounds: NDArray[np.int_]


def imu_segments(
    t_imu: FloatArray, gyro: FloatArray, accel: FloatArray, t_key: FloatArray
) -> ImuSegments:
    """Integration steps between keyframe times ``t_key`` (inside the IMU's time span)."""
    inside = (t_imu > t_key[0]) & (t_imu < t_key[-1])
    samples = t_imu[inside]
    pos = np.clip(np.searchsorted(t_key, samples), 1, len(t_key) - 1)
    near = np.minimum(np.abs(samples - t_key[pos - 1]), np.abs(samples - t_key[pos])) < 1e-6
    breaks = np.union1d(samples[~near], t_key)
    mid = 0.5 * (breaks[1:] + breaks[:-1])
    gyro_mid = np.column_stack([np.interp(mid, t_imu, gyro[:, i]) for i in range(3)])
    accel_mid = np.column_stack([np.interp(mid, t_imu, accel[:, i]) for i in range(3)])
    dt = np.diff(breaks)
    # GTSAM integrates the velocity with the attitude at the start of a step (first
    # order); expressing the step's mean specific force in that frame, f + dt/2 w x f,
    # makes the velocity increment second order (the sculling-type error of turns).
    accel_mid = accel_mid + 0.5 * dt[:, None] * np.cross(gyro_mid, accel_mid)
    bounds = np.searchsorted(breaks, t_key)
    return ImuSegments(breaks, dt, gyro_mid, accel_mid, bounds)


def keyframe_times(
    t_start: float, t_end: float, t_events: ArrayLike, max_keyframe_dt: float
) -> FloatArray:
    """Keyframe times [s]: start, end, every event time inside, and evenly spaced fill-ins
    so that no interval exceeds ``max_keyframe_dt``. Events closer than 1 us merge."""
    ev = np.asarray(t_events, dtype=float)
    base = np.union1d([t_start, t_end], ev[(ev >= t_start) & (ev <= t_end)])
    base = base[np.concatenate([[True], np.diff(base) > 1e-6])]
    if base[-1] < t_end:  # the merge may have dropped t_end
        base[-1] = t_end
    out = [base[:1]]
    for a, b in itertools.pairwise(base):
        n = int(np.ceil((b - a) / max_keyframe_dt - 1e-9))
        out.append(a + (b - a) * np.arange(1, n + 1) / n)
    return np.concatenate(out)


# ============================================================================ options
@dataclass(frozen=True)
class GraphOptions:
    """Configuration of :func:`fuse_graph` (SI units, radians).

    Options shared with the ESKF (:class:`~polins.fusion.eskf.EskfOptions`, same meaning):
    ``earth_rate``, ``gate_prob``, ``align_s``, ``att_std0``, ``vel_std0``, ``pos_std0``,
    ``use_sun``, ``tilt_coupling``, ``nhc_std``, ``nhc_rate_hz``, ``zupt_std``. Graph only:

    Attributes
    ----------
    solver : {"batch", "isam2", "fixed_lag"}
        See the module docstring.
    lag_s : float
        Window of the fixed-lag smoother [s].
    max_keyframe_dt : float
        Longest interval between keyframes [s].
    max_iterations : int
        Gauss-Newton iterations of the batch solver (per pass).
    integration_std : float
        GTSAM's position-integration noise density [m/sqrt(s)] (see
        :func:`preintegration_params`).
    output : {"samples", "keyframes"}
        Report IMU samples (``output_rate_hz``) or the keyframes.
    max_gate_rounds : int
        Batch solver: most re-solves after gating outliers on their post-fit residuals.
    optimizer : {"gauss-newton", "levenberg-marquardt"}
        Batch solver: Gauss-Newton with QR (default, :func:`gauss_newton_qr`) or GTSAM's
        Levenberg-Marquardt with QR (slower; also the fallback if Gauss-Newton diverges).
    """

    earth_rate: bool = False
    gate_prob: float | None = 0.9973
    align_s: float = 1.0
    att_std0: tuple[float, float, float] = (float(np.radians(1.0)),) * 3
    vel_std0: float = 0.1
    pos_std0: float = 1.0
    use_sun: bool = True
    tilt_coupling: bool = False
    nhc_std: float | None = None
    nhc_rate_hz: float = 10.0
    zupt_std: float | None = None
    solver: str = "batch"
    lag_s: float = 10.0
    max_keyframe_dt: float = 1.0
    max_iterations: int = 20
    integration_std: float = 1e-2
    output: str = "samples"
    max_gate_rounds: int = 10
    optimizer: str = "gauss-newton"

    def __post_init__(self) -> None:
        if self.solver not in SOLVERS:
            raise ValueError(f"solver={self.solver!r}: expected one of {SOLVERS}")
        if self.optimizer not in ("gauss-newton", "levenberg-marquardt"):
            raise ValueError(
                f"optimizer={self.optimizer!r}: expected 'gauss-newton' or 'levenberg-marquardt'"
            )
        if self.output not in ("samples", "keyframes"):
            raise ValueError(f"output={self.output!r}: expected 'samples' or 'keyframes'")
        if self.gate_prob is not None and not 0.0 < self.gate_prob < 1.0:
            raise ValueError(f"gate_prob must be in (0, 1) or None, got {self.gate_prob}")
        for name in ("align_s", "vel_std0", "pos_std0", "nhc_rate_hz", "lag_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not self.max_keyframe_dt > 0:
            raise ValueError(f"max_keyframe_dt must be > 0 [s], got {self.max_keyframe_dt}")
        for name in ("nhc_std", "zupt_std"):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise ValueError(f"{name} must be > 0 [m/s] or None, got {value}")
        if len(self.att_std0) != 3 or not all(a > 0 for a in self.att_std0):
            raise ValueError(f"att_std0 must be 3 positive sigmas [rad], got {self.att_std0}")


# ============================================================================ the problem
@dataclass(frozen=True, eq=False)
class _MeasFactor:
    """A yaw or sun factor with what is needed to gate and log it."""

    k: int
    item: MeasurementItem
    factor: gtsam.NonlinearFactor

    def linearized(self, mat_nb: FloatArray, tilt_coupling: bool) -> Linearized:
        return item_model(self.item, mat_nb, None, tilt_coupling)


class _Problem:
    """One fusion problem: keyframes, IMU steps, GTSAM parameters, factors per keyframe."""

    def __init__(
        self,
        opts: GraphOptions,
        model: ImuModel,
        site: tuple[float, float, float],
        t_imu: FloatArray,
        gyro: FloatArray,
        accel: FloatArray,
        items: list[MeasurementItem],
        stationary: FloatArray,
        rot_nb0: Rotation | None,
        vel_n0: FloatArray,
    ) -> None:
        self.opts = opts
        self.model = model
        self.lat, self.lon, self.height = site
        self.gravity = float(normal_gravity(self.lat, self.height))
        self.omega_ie_n = earth_rate_n(self.lat) if opts.earth_rate else None
        self.params = preintegration_params(
            model,
            gravity_mps2=self.gravity,
            omega_ie_n=self.omega_ie_n,
            integration_std=opts.integration_std,
        )
        t0, t1 = float(t_imu[0]), float(t_imu[-1])
        self.items = items
        aiding = [it for it in items if it.valid and it.kind in ("yaw", "sun")]
        zupt_items = [it for it in items if it.valid and it.kind == "zupt"]
        # Non-holonomic pseudo-measurements at the ESKF's epochs: every nhc_every-th sample.
        nhc_t = np.zeros(0)
        if opts.nhc_std is not None:
            dt_median = float(np.median(np.diff(t_imu)))
            every = max(1, round(1.0 / (opts.nhc_rate_hz * dt_median)))
            nhc_t = t_imu[every::every]
        events = np.concatenate(
            [[it.t for it in aiding], [it.t for it in zupt_items], stationary, nhc_t]
        )
        self.t_key = keyframe_times(t0, t1, events, opts.max_keyframe_dt)
        self.segments = imu_segments(t_imu, gyro, accel, self.t_key)
        n_key = len(self.t_key)

        def key_of(t: float) -> int | None:
            k = int(np.clip(np.searchsorted(self.t_key, t), 1, n_key - 1))
            k = k if abs(self.t_key[k] - t) < abs(self.t_key[k - 1] - t) else k - 1
            return k if abs(self.t_key[k] - t) < 1e-6 else None

        self.meas: list[_MeasFactor] = []
        self.outside: list[MeasurementItem] = []
        for it in aiding:
            k = key_of(it.t)
            if k is None:
                self.outside.append(it)
                continue
            factor: gtsam.NonlinearFactor
            if it.kind == "yaw" and opts.tilt_coupling:
                if it.sun_n is None or it.mat_nb_prior is None:
                    raise ValueError(
                        f"tilt_coupling: the yaw row at t={it.t} needs sun_nx/ny/nz and the "
                        "prior_roll/prior_pitch/prior_yaw of the image (the graph "
                        "re-linearizes away from the prior polins.measure used)"
                    )
                factor = yaw_factor(
                    X(k), it.yaw, it.std, sun_n=it.sun_n, rot_nb_prior=it.mat_nb_prior
                )
            elif it.kind == "yaw":
                factor = yaw_factor(X(k), it.yaw, it.std)
            else:
                factor = sun_factor(X(k), it.sun_n, it.sun_b, it.std)  # type: ignore[arg-type]
            self.meas.append(_MeasFactor(k, it, factor))
        self.aux: list[list[gtsam.NonlinearFactor]] = [[] for _ in range(n_key)]
        for it in zupt_items:
            k = key_of(it.t)
            if k is not None:
                self.aux[k].append(zero_velocity_factor(V(k), it.std))
        if opts.zupt_std is not None:
            for t in stationary:
                k = key_of(float(t))
                if k is not None:
                    self.aux[k].append(zero_velocity_factor(V(k), opts.zupt_std))
        if opts.nhc_std is not None:
            for t in nhc_t:
                k = key_of(float(t))
                if k is not None:
                    self.aux[k].append(non_holonomic_factor(X(k), V(k), opts.nhc_std))
        self.meas_at: list[list[int]] = [[] for _ in range(n_key)]
        for i, mf in enumerate(self.meas):
            self.meas_at[mf.k].append(i)
        self.yaw_given = rot_nb0 is not None  # else unknown until the first yaw / sun
        self.state0, self.bias0, self.priors = self._first_state(
            t_imu, accel, rot_nb0, np.asarray(vel_n0, dtype=float)
        )

    # ------------------------------------------------------------------ first state
    def _first_state(
        self,
        t_imu: FloatArray,
        accel: FloatArray,
        rot_nb0: Rotation | None,
        vel_n0: FloatArray,
    ) -> tuple[gtsam.NavState, gtsam.imuBias.ConstantBias, list[gtsam.NonlinearFactor]]:
        o, m = self.opts, self.model
        bias0 = gtsam.imuBias.ConstantBias()
        bias_sigmas = np.concatenate([np.full(3, m.accel_bias), np.full(3, m.gyro_bias)])
        priors: list[gtsam.NonlinearFactor] = [
            gtsam.PriorFactorConstantBias(
                B(0), bias0, gtsam.noiseModel.Diagonal.Sigmas(np.maximum(bias_sigmas, 1e-12))
            )
        ]
        if rot_nb0 is not None:
            rot = rot_nb0
            att_var = np.asarray(o.att_std0, dtype=float) ** 2
        else:
            window = t_imu <= t_imu[0] + o.align_s
            f_mean = accel[window].mean(axis=0)
            duration = max(float(t_imu[window][-1] - t_imu[0]), 1.0 / m.sample_rate_hz)
            roll, pitch = level_from_accel(f_mean)
            level = Rotation.from_euler("ZYX", [0.0, pitch, roll])
            yaw0 = self._initial_yaw(level, vel_n0)
            rot = Rotation.from_euler("ZYX", [yaw0, pitch, roll])
            std = max(m.accel_vrw / np.sqrt(duration), 1e-9)
            priors.append(levelling_factor(X(0), B(0), f_mean, self.gravity, std))
            # Tilt from the levelling factor only (1e4 rad is no information); yaw 1 rad
            # until the first yaw / sun measurement (the ESKF's P[2, 2] = 1).
            att_var = np.array([1e8, 1e8, 1.0])
            vel_n0 = np.zeros(3)
        mat_nb = rot.as_matrix()
        cov_n = np.diag(np.concatenate([att_var, np.full(3, o.pos_std0**2)]))
        state0 = gtsam.NavState(gtsam.Rot3(mat_nb), np.zeros(3), vel_n0)
        priors.append(
            gtsam.PriorFactorPose3(
                X(0),
                state0.pose(),
                gtsam.noiseModel.Gaussian.Covariance(pose_cov_body_from_nav(mat_nb, cov_n)),
            )
        )
        priors.append(
            gtsam.PriorFactorVector(V(0), vel_n0, gtsam.noiseModel.Isotropic.Sigma(3, o.vel_std0))
        )
        return state0, bias0, priors

    def _initial_yaw(self, level: Rotation, vel_n0: FloatArray) -> float:
        """Yaw at the first keyframe from the first measurement, carried back by the gyro."""
        if not self.meas:
            raise ValueError(
                "self-alignment (rot_nb0=None) needs a valid yaw or sun-vector measurement; "
                "give rot_nb0 or measurements"
            )
        first = min(self.meas, key=lambda mf: mf.k)
        state = gtsam.NavState(gtsam.Rot3(level.as_matrix()), np.zeros(3), vel_n0)
        bias = gtsam.imuBias.ConstantBias()
        for k in range(first.k):
            state = self.preintegrate(k, bias, np.zeros(6)).predict(state, bias)
        rot_k = Rotation.from_matrix(state.attitude().matrix())
        it = first.item
        if it.kind == "yaw":
            measured = it.yaw
        else:
            measured = yaw_from_sun(rot_k, it.sun_b, it.sun_n)  # type: ignore[arg-type]
        return float(wrap_angle(measured - yaw_from_rot_nb(rot_k)))

    # ------------------------------------------------------------------ IMU
    def imu_correction(self, state: gtsam.NavState) -> FloatArray:
        """What to subtract from the (gyro, accelerometer) samples of the next interval (6,).

        Gyro: the transport rate in body axes, ``C_bn omega_en_n`` [rad/s] (with Earth rate
        only, like the ESKF's mechanization). Accelerometer: ``C_bn (0, 0, g(lat, h) - g0)``
        [m/s^2], the change of normal gravity since the start, since GTSAM's gravity is
        constant. Both at the current estimate ``state`` of the keyframe.
        """
        lat, _lon, h = self.geodetic(state.position())
        mat_bn = state.attitude().matrix().T
        corr = np.zeros(6)
        corr[3:] = mat_bn @ np.array([0.0, 0.0, float(normal_gravity(lat, h)) - self.gravity])
        if self.opts.earth_rate:
            corr[:3] = mat_bn @ transport_rate_n(lat, h, state.velocity())
        return corr

    def geodetic(self, pos_n: FloatArray) -> tuple[float, float, float]:
        """Latitude, longitude [rad] and height [m] of a local ENU position [m]."""
        r_m, r_n = radii_of_curvature(self.lat)
        lat = self.lat + pos_n[1] / (r_m + self.height)
        lon = self.lon + pos_n[0] / ((r_n + self.height) * np.cos(self.lat))
        return float(lat), float(lon), float(self.height + pos_n[2])

    def preintegrate(
        self, k: int, bias: gtsam.imuBias.ConstantBias, correction: FloatArray
    ) -> gtsam.PreintegratedCombinedMeasurements:
        """Preintegrated IMU from keyframe ``k`` to ``k + 1`` (``correction``: see
        :meth:`imu_correction`)."""
        seg = self.segments
        pim = gtsam.PreintegratedCombinedMeasurements(self.params, bias)
        lo, hi = seg.bounds[k], seg.bounds[k + 1]
        gyro = seg.gyro[lo:hi] - correction[:3]
        accel = seg.accel[lo:hi] - correction[3:]
        for a, w, dt in zip(accel, gyro, seg.dt[lo:hi], strict=True):
            pim.integrateMeasurement(a, w, dt)
        return pim

    def imu_factor(self, k: int, pim: gtsam.PreintegratedCombinedMeasurements) -> Any:
        return gtsam.CombinedImuFactor(X(k), V(k), X(k + 1), V(k + 1), B(k), B(k + 1), pim)

    def factors_at(self, k: int, rejected: set[int]) -> list[gtsam.NonlinearFactor]:
        """Measurement and pseudo-measurement factors of keyframe ``k``."""
        out = list(self.aux[k])
        out += [self.meas[i].factor for i in self.meas_at[k] if i not in rejected]
        return out


# ============================================================================ estimates
@dataclass
class _Estimates:
    """Keyframe estimates in polins conventions, filled by the solvers."""

    mat_nb: FloatArray  # (K, 3, 3)
    vel_n: FloatArray  # (K, 3)
    pos_n: FloatArray  # (K, 3) local ENU [m]
    bias: FloatArray  # (K, 6): bg, ba
    cov: FloatArray  # (K, 15, 15) ESKF error-state order, navigation-frame attitude
    yaw_known: NDArray[np.bool_]  # (K,) a yaw/sun factor was in the graph when reported

    @classmethod
    def empty(cls, k: int) -> _Estimates:
        return cls(
            np.full((k, 3, 3), np.nan),
            np.full((k, 3), np.nan),
            np.full((k, 3), np.nan),
            np.full((k, 6), np.nan),
            np.full((k, 15, 15), np.nan),
            np.zeros(k, dtype=bool),
        )

    def store(
        self,
        k: int,
        pose: gtsam.Pose3,
        vel: FloatArray,
        bias: gtsam.imuBias.ConstantBias,
        cov_pose_b: FloatArray,
        cov_vel: FloatArray,
        cov_bias: FloatArray,
        yaw_known: bool,
    ) -> None:
        """Keyframe ``k`` from GTSAM values and marginal covariances (block diagonal in
        pose / velocity / bias; GTSAM's bias tangent is accelerometer, then gyro)."""
        mat_nb = pose.rotation().matrix()
        self.mat_nb[k] = mat_nb
        self.pos_n[k] = pose.translation()
        self.vel_n[k] = vel
        self.bias[k] = np.concatenate([bias.gyroscope(), bias.accelerometer()])
        cov = np.zeros((N_ERROR, N_ERROR))
        cov_pose_n = pose_cov_nav_from_body(mat_nb, cov_pose_b)
        cov[ATT, ATT] = cov_pose_n[:3, :3]
        cov[POS, POS] = cov_pose_n[3:, 3:]
        cov[ATT, POS] = cov_pose_n[:3, 3:]
        cov[POS, ATT] = cov_pose_n[3:, :3]
        cov[VEL, VEL] = cov_vel
        cov[BG, BG] = cov_bias[3:6, 3:6]
        cov[BA, BA] = cov_bias[0:3, 0:3]
        cov[BG, BA] = cov_bias[3:6, 0:3]
        cov[BA, BG] = cov_bias[0:3, 3:6]
        self.cov[k] = cov
        self.yaw_known[k] = yaw_known

    def values(self, k: int) -> tuple[gtsam.NavState, gtsam.imuBias.ConstantBias]:
        state = gtsam.NavState(gtsam.Rot3(self.mat_nb[k]), self.pos_n[k], self.vel_n[k])
        return state, bias_from_polins(self.bias[k])


@dataclass
class _Log:
    """Measurement log (``attrs["updates"]``) and solver diagnostics."""

    rows: list[tuple[float, str, int, float, bool, str]] = field(default_factory=list)
    info: dict[str, Any] = field(default_factory=dict)

    def frame(self) -> pd.DataFrame:
        rows = sorted(self.rows, key=lambda r: r[0])
        cols: list[Any] = list(zip(*rows, strict=True)) if rows else [[] for _ in range(6)]
        return pd.DataFrame(
            {
                "t": np.asarray(cols[0], dtype=float),
                "name": list(cols[1]),
                "dim": np.asarray(cols[2], dtype=int),
                "nis": np.asarray(cols[3], dtype=float),
                "accepted": np.asarray(cols[4], dtype=bool),
                "reason": list(cols[5]),
            }
        )


# ============================================================================ batch
def gauss_newton_qr(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    *,
    max_iterations: int = 20,
    rel_tol: float = 1e-6,
) -> tuple[gtsam.Values, int]:
    """Gauss-Newton with sparse multifrontal QR until the cost changes by < ``rel_tol``.

    Why not GTSAM's Levenberg-Marquardt or Cholesky: without position (and, with yaw-only
    aiding, velocity) measurements the position and velocity marginals grow to km and tens
    of m/s while the bias random-walk links between 0.2 s keyframes carry an information
    of ~1e14; the normal equations then have condition numbers beyond 1e16 (Cholesky
    reports an "indeterminate system") and LM's ``lambda I`` damping dominates the weakly
    observed directions, so LM creeps for a hundred iterations. QR on the Jacobian meets
    only the square root of that condition number, and the problem is nearly linear (the
    nonlinearity is the attitude), so undamped Gauss-Newton converges in 3-10 iterations.
    The first step from dead reckoning may raise the cost; convergence is judged on the
    change of the cost, not on a decrease. (The loop is written out: it is ~10x faster
    than ``gtsam.GaussNewtonOptimizer.iterate`` from Python on these graphs.)
    """
    ordering = graph.orderingCOLAMD()
    previous = graph.error(values)
    for iteration in range(1, max_iterations + 1):
        linear = graph.linearize(values)
        delta = linear.eliminateMultifrontal(ordering, gtsam.EliminateQR).optimize()
        values = values.retract(delta)
        error = graph.error(values)
        if not np.isfinite(error):
            raise RuntimeError("Gauss-Newton diverged (non-finite cost)")
        if iteration > 1 and abs(previous - error) <= rel_tol * max(error, 1.0):
            return values, iteration
        previous = error
    return values, max_iterations


def levenberg_marquardt_qr(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    *,
    max_iterations: int = 100,
    rel_tol: float = 1e-6,
) -> tuple[gtsam.Values, int]:
    """GTSAM's Levenberg-Marquardt with multifrontal QR (``optimizer="levenberg-marquardt"``,
    and the fallback if Gauss-Newton diverges). Robust far from the solution, but its
    ``lambda I`` damping slows it down in the weakly observed directions (see
    :func:`gauss_newton_qr`): expect tens of iterations."""
    params = gtsam.LevenbergMarquardtParams()
    params.setLinearSolverType("MULTIFRONTAL_QR")
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(rel_tol)
    params.setAbsoluteErrorTol(0.0)
    params.setlambdaInitial(1e-9)
    params.setlambdaLowerBound(1e-15)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = optimizer.optimize()
    return result, int(optimizer.iterations())


def marginal_covariance_qr(bayes_tree: gtsam.GaussianBayesTree, key: int) -> FloatArray:
    """Marginal covariance of one variable from a QR-eliminated Bayes tree.

    ``marginalFactor(key, EliminateQR)`` gives the square-root information ``R`` of the
    marginal; the covariance is ``R^-1 R^-T`` (never ``J^T J``).
    """
    conditional = bayes_tree.marginalFactor(key, gtsam.EliminateQR)
    # R() is a view into the conditional's memory: copy it while the conditional is alive.
    r = np.array(conditional.R(), dtype=float, order="C", copy=True)
    r_inv = np.linalg.inv(r)
    return r_inv @ r_inv.T


def _batch_graph(
    prob: _Problem, rejected: set[int], linearization: gtsam.Values | None
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """Whole-log graph with initial values (dead reckoning, or ``linearization``, whose
    velocity, position and bias also set the transport rate and the bias of the
    preintegration)."""
    graph = gtsam.NonlinearFactorGraph()
    for f in prob.priors:
        graph.add(f)
    values = gtsam.Values()
    state, bias = prob.state0, prob.bias0
    values.insert(X(0), state.pose())
    values.insert(V(0), state.velocity())
    values.insert(B(0), bias)
    for k in range(len(prob.t_key)):
        for f in prob.factors_at(k, rejected):
            graph.add(f)
        if k == len(prob.t_key) - 1:
            break
        if linearization is not None:
            state = gtsam.NavState(linearization.atPose3(X(k)), linearization.atVector(V(k)))
            bias = linearization.atConstantBias(B(k))
        pim = prob.preintegrate(k, bias, prob.imu_correction(state))
        graph.add(prob.imu_factor(k, pim))
        if linearization is None:
            state = pim.predict(state, bias)
            values.insert(X(k + 1), state.pose())
            values.insert(V(k + 1), state.velocity())
            values.insert(B(k + 1), bias)
    return graph, (values if linearization is None else linearization)


def _solve_batch(prob: _Problem, log: _Log) -> _Estimates:
    """Gauss-Newton (QR) over the whole log, post-fit gating, QR marginals."""
    o = prob.opts
    rejected: dict[int, tuple[float, str]] = {}
    result: gtsam.Values | None = None
    iterations: list[int] = []
    for _round in range(1 + o.max_gate_rounds):
        for p in range(2 if o.earth_rate else 1):
            # Second pass: re-preintegrate with the transport rate and bias of the first.
            lin = result if (p > 0 or result is not None) else None
            graph, values = _batch_graph(prob, set(rejected), lin)
            result, it = _optimize(graph, values, o)
            iterations.append(it)
        assert result is not None
        bayes_tree = graph.linearize(result).eliminateMultifrontal(
            graph.orderingCOLAMD(), gtsam.EliminateQR
        )
        est = _Estimates.empty(len(prob.t_key))
        for k in range(len(prob.t_key)):
            est.store(
                k,
                result.atPose3(X(k)),
                result.atVector(V(k)),
                result.atConstantBias(B(k)),
                marginal_covariance_qr(bayes_tree, X(k)),
                marginal_covariance_qr(bayes_tree, V(k)),
                marginal_covariance_qr(bayes_tree, B(k)),
                prob.yaw_given or bool(prob.meas),
            )
        new = _post_fit_gate(prob, est, rejected, log, final=_round == o.max_gate_rounds)
        if not new:
            break
        rejected.update(new)
    assert result is not None
    log.info.update(
        iterations=iterations,
        error=graph.error(result),
        n_factors=graph.size(),
        rejected=sorted(rejected),
    )
    return est


def _optimize(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, o: GraphOptions
) -> tuple[gtsam.Values, int]:
    if o.optimizer == "gauss-newton":
        try:
            return gauss_newton_qr(graph, values, max_iterations=o.max_iterations)
        except RuntimeError:  # diverged: fall back to the damped method
            pass
    return levenberg_marquardt_qr(graph, values, max_iterations=5 * o.max_iterations)


def _post_fit_gate(
    prob: _Problem,
    est: _Estimates,
    rejected: dict[int, tuple[float, str]],
    log: _Log,
    *,
    final: bool,
) -> dict[int, tuple[float, str]]:
    """Post-fit chi-square gate of the yaw/sun factors.

    The post-fit residual of a correct measurement has covariance ``R - H P H^T``
    (``P`` the smoothed covariance), so ``r^T (R - H P H^T)^-1 r`` is chi-square with
    ``dim`` degrees of freedom. An outlier also inflates its neighbours' residuals, so each
    round gates only the grossest exceedances (NIS at least half the largest); the graph is
    re-solved and the gate repeated. Returns the newly gated factors (empty: the log, one
    row per factor, has been written).
    """
    o = prob.opts
    rows: list[tuple[float, str, int, float, bool, str]] = []
    exceed: dict[int, tuple[float, str]] = {}
    for i, mf in enumerate(prob.meas):
        lin = mf.linearized(est.mat_nb[mf.k], o.tilt_coupling)
        if i in rejected:
            nis, reason = rejected[i]
            rows.append((mf.item.t, mf.item.kind, lin.dim, nis, False, reason))
            continue
        s = lin.R - lin.H @ est.cov[mf.k] @ lin.H.T
        s = 0.5 * (s + s.T) + 1e-6 * lin.R  # kept regular when the measurement dominates
        nis = float(lin.residual @ np.linalg.solve(s, lin.residual))
        limit = gate_limit(o.gate_prob, lin.dim)
        if nis > limit and not final:
            reason = f"post-fit NIS {nis:.3g} > gate {limit:.3g} (chi2, {lin.dim} dof)"
            exceed[i] = (nis, reason)
        rows.append((mf.item.t, mf.item.kind, lin.dim, nis, True, ""))
    if not exceed:
        log.rows.extend(rows)
        return {}
    worst = max(nis for nis, _ in exceed.values())
    return {i: v for i, v in exceed.items() if v[0] >= 0.5 * worst}


# ============================================================================ incremental
def _solve_incremental(prob: _Problem, log: _Log) -> _Estimates:
    """ISAM2 (causal estimates) or the incremental fixed-lag smoother (lagged estimates)."""
    o = prob.opts
    isam_params = gtsam.ISAM2Params()
    isam_params.setFactorization("QR")
    # Relinearize on attitude changes only: the IMU factors are linear in velocity and
    # position, whose (unobserved) values keep moving by centimetres; relinearizing on
    # them re-eliminates most of the tree at every check.
    thresholds = gtsam.ISAM2ThresholdMap()
    thresholds.insert(("x", np.array([1e-2, 1e-2, 1e-2, 1e6, 1e6, 1e6])))
    thresholds.insert(("v", np.full(3, 1e6)))
    thresholds.insert(("b", np.full(6, 1e6)))
    isam_params.setRelinearizeThreshold(thresholds)
    isam_params.relinearizeSkip = 10
    if o.solver == "fixed_lag":
        # GTSAM's default "wildfire" threshold (1e-3) leaves the deltas of older variables
        # stale by up to 1e-3 rad, a sizeable fraction of a sigma, and the fixed-lag
        # smoother reports them late: update them all (cheap in a bounded window). ISAM2
        # reports the newest keyframe, whose delta is always current.
        isam_params.setOptimizationParams(gtsam.ISAM2GaussNewtonParams(0.0))
    engine: Any = (
        gtsam.ISAM2(isam_params)
        if o.solver == "isam2"
        else gtsam.IncrementalFixedLagSmoother(o.lag_s, isam_params)
    )
    n_key = len(prob.t_key)
    est = _Estimates.empty(n_key)
    seen_aiding = False
    pending: list[int] = []  # fixed lag: keyframes not reported yet

    def record(k: int) -> None:
        est.store(
            k,
            engine.calculateEstimatePose3(X(k)),
            engine.calculateEstimateVector(V(k)),
            engine.calculateEstimateConstantBias(B(k)),
            engine.marginalCovariance(X(k)),
            engine.marginalCovariance(V(k)),
            engine.marginalCovariance(B(k)),
            seen_aiding or prob.yaw_given,
        )

    def gated(k: int, state: gtsam.NavState, cov_prev: FloatArray) -> list[gtsam.NonlinearFactor]:
        """Measurement factors at keyframe k that pass the chi-square gate."""
        nonlocal seen_aiding
        out = []
        mat = state.attitude().matrix()
        for i in prob.meas_at[k]:
            mf = prob.meas[i]
            lin = mf.linearized(mat, o.tilt_coupling)
            if not seen_aiding and not np.isfinite(cov_prev).all():
                nis = np.nan  # first keyframe
            else:
                s = lin.H @ cov_prev @ lin.H.T + lin.R
                nis = float(lin.residual @ np.linalg.solve(s, lin.residual))
            limit = gate_limit(o.gate_prob, lin.dim)
            if seen_aiding and nis > limit:
                reason = f"NIS {nis:.3g} > gate {limit:.3g} (chi2, {lin.dim} dof)"
                log.rows.append((mf.item.t, mf.item.kind, lin.dim, nis, False, reason))
                continue
            # The first yaw/sun measurement aligns the yaw (no gate, like the ESKF).
            log.rows.append((mf.item.t, mf.item.kind, lin.dim, nis, True, ""))
            out.append(mf.factor)
            seen_aiding = True
        return out

    def update(k: int, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> None:
        if o.solver == "isam2":
            engine.update(graph, values)
            record(k)
            return
        t_k = float(prob.t_key[k])
        while pending and prob.t_key[pending[0]] < t_k - o.lag_s:
            record(pending.pop(0))  # last chance before it is marginalized
        engine.update(graph, values, {X(k): t_k, V(k): t_k, B(k): t_k})
        pending.append(k)

    graph = gtsam.NonlinearFactorGraph()
    for f in prob.priors + list(prob.aux[0]) + gated(0, prob.state0, np.full((15, 15), np.nan)):
        graph.add(f)
    values = gtsam.Values()
    values.insert(X(0), prob.state0.pose())
    values.insert(V(0), prob.state0.velocity())
    values.insert(B(0), prob.bias0)
    update(0, graph, values)
    state, bias = prob.state0, prob.bias0
    for k in range(n_key - 1):
        if o.solver == "isam2":
            state, bias = est.values(k)
            cov_prev = est.cov[k]
        else:
            state = gtsam.NavState(
                engine.calculateEstimatePose3(X(k)), engine.calculateEstimateVector(V(k))
            )
            bias = engine.calculateEstimateConstantBias(B(k))
            cov_prev = _fixed_lag_cov(engine, k, state)
        pim = prob.preintegrate(k, bias, prob.imu_correction(state))
        pred = pim.predict(state, bias)
        graph = gtsam.NonlinearFactorGraph()
        graph.add(prob.imu_factor(k, pim))
        for f in list(prob.aux[k + 1]) + gated(k + 1, pred, cov_prev):
            graph.add(f)
        values = gtsam.Values()
        values.insert(X(k + 1), pred.pose())
        values.insert(V(k + 1), pred.velocity())
        values.insert(B(k + 1), bias)
        update(k + 1, graph, values)
    for k in pending:
        record(k)
    log.info.update(n_keyframes=n_key)
    return est


def _fixed_lag_cov(engine: Any, k: int, state: gtsam.NavState) -> FloatArray:
    """Attitude block of the current marginal of keyframe ``k`` (for the gate), ESKF order."""
    cov = np.zeros((N_ERROR, N_ERROR))
    pose = pose_cov_nav_from_body(state.attitude().matrix(), engine.marginalCovariance(X(k)))
    cov[ATT, ATT] = pose[:3, :3]
    return cov


# ============================================================================ output
def _interpolate(prob: _Problem, est: _Estimates, t_out: FloatArray) -> dict[str, Any]:
    """States at the times ``t_out`` (break points of the IMU steps) between keyframes."""
    seg = prob.segments
    n = len(t_out)
    mat = np.empty((n, 3, 3))
    vel = np.empty((n, 3))
    pos = np.empty((n, 3))
    bias = np.empty((n, 6))
    cov = np.empty((n, N_ERROR, N_ERROR))
    known = np.empty(n, dtype=bool)
    idx = np.searchsorted(seg.t, t_out - 1e-9)  # break-point index of each output time
    key = np.clip(np.searchsorted(seg.bounds, idx, side="right") - 1, 0, len(prob.t_key) - 1)
    for k in np.unique(key):
        rows = np.flatnonzero(key == k)
        state, b = est.values(int(k))
        if k == len(prob.t_key) - 1:
            mat[rows], vel[rows], pos[rows] = est.mat_nb[k], est.vel_n[k], est.pos_n[k]
            bias[rows], cov[rows], known[rows] = est.bias[k], est.cov[k], est.yaw_known[k]
            continue
        lo, hi = seg.bounds[k], seg.bounds[k + 1]
        corr = prob.imu_correction(state)
        pim = gtsam.PreintegratedCombinedMeasurements(prob.params, b)
        preds: dict[int, gtsam.NavState] = {lo: state}
        wanted = set(idx[rows].tolist()) | {hi}
        for j in range(lo, hi):
            pim.integrateMeasurement(seg.accel[j] - corr[3:], seg.gyro[j] - corr[:3], seg.dt[j])
            if j + 1 in wanted:
                preds[j + 1] = pim.predict(state, b)
        # Spread the mismatch at the next keyframe linearly over the interval.
        end = preds[hi]
        d_rot = Rotation.from_matrix(end.attitude().matrix().T @ est.mat_nb[k + 1]).as_rotvec()
        d_vel = est.vel_n[k + 1] - end.velocity()
        d_pos = est.pos_n[k + 1] - end.position()
        span = prob.t_key[k + 1] - prob.t_key[k]
        for r in rows:
            p = preds[int(idx[r])]
            a = (seg.t[idx[r]] - prob.t_key[k]) / span
            mat[r] = p.attitude().matrix() @ Rotation.from_rotvec(a * d_rot).as_matrix()
            vel[r] = p.velocity() + a * d_vel
            pos[r] = p.position() + a * d_pos
            bias[r] = (1 - a) * est.bias[k] + a * est.bias[k + 1]
            cov[r] = (1 - a) * est.cov[k] + a * est.cov[k + 1]
            known[r] = est.yaw_known[k]
    return {"mat": mat, "vel": vel, "pos": pos, "bias": bias, "cov": cov, "known": known}


def _solution_frame(prob: _Problem, t: FloatArray, s: dict[str, Any]) -> pd.DataFrame:
    """The CONVENTIONS.md solution table (the ESKF's :func:`solution_columns`)."""
    geo = np.array([prob.geodetic(p) for p in s["pos"]]).reshape(-1, 3)
    cov = s["cov"]
    sigma = np.sqrt(np.clip(np.diagonal(cov, axis1=1, axis2=2), 0.0, None))
    cols = solution_columns(
        t=t,
        rot_nb=Rotation.from_matrix(s["mat"]),
        vel_n=s["vel"],
        lat=geo[:, 0],
        lon=geo[:, 1],
        height=geo[:, 2],
        bg=s["bias"][:, 0:3],
        ba=s["bias"][:, 3:6],
        sg=None,
        sa=None,
        P_diag_att=cov[:, ATT, ATT],
        sigma=sigma,
        yaw_aligned=s["known"],
    )
    return pd.DataFrame(cols)


# ============================================================================ entry point
_ESKF_ONLY = {
    "scale_factors": "the graph estimates no scale factors (15 states)",
    "reset_interval_s": "the graph has no error-state resets",
    "reset_angle_rad": "the graph has no error-state resets",
    "smooth": "the graph's 'batch' solver is a smoother; use solver='isam2' for causal output",
    "fast": "an ESKF path option",
    "cov_every": "an ESKF covariance-step option",
    "chunk": "an ESKF batch-path option",
    "time_tol": "the graph snaps measurement times to IMU samples within 1 us",
}
_GRAPH_OPTIONS = {
    "imu_model": "IMU error model (ImuModel; polins.fuse also takes a name or TOML path)",
    "lat_deg": "start latitude [deg]",
    "lon_deg": "start longitude [deg]",
    "alt_m": "start height [m]",
    "vel_n0": "initial ENU velocity [m/s] (default 0)",
    "stationary": "times [s] at which the vehicle stands still (zero-velocity, zupt_std)",
    "output_rate_hz": "output rows per second (default None: every IMU sample)",
    "max_gap_s": "longest allowed IMU gap [s] (default 5 median intervals)",
    **{f.name: "see GraphOptions" for f in dataclasses.fields(GraphOptions)},
}


def fuse_graph(
    imu: pd.DataFrame,
    measurements: pd.DataFrame | None = None,
    rot_nb0: Rotation | None = None,
    **options: Any,
) -> pd.DataFrame:
    """Fuse an IMU log with yaw / sun-vector measurements in a GTSAM factor graph.

    ``polins.fuse(imu, measurements, backend="graph", rot_nb0=..., **options)`` calls this.

    Parameters
    ----------
    imu : DataFrame
        Columns ``t`` [s], ``gx, gy, gz`` [rad/s], ``ax, ay, az`` [m/s^2] (body FLU,
        instantaneous; validated by :func:`polins.fusion.inputs.validate_imu`).
    measurements : DataFrame, optional
        Columns ``t`` and ``yaw, yaw_std`` [rad] and/or ``sun_bx, sun_by, sun_bz``,
        ``sun_nx, sun_ny, sun_nz``, ``sun_std`` [rad], optionally ``zupt_std`` [m/s]
        (CONVENTIONS.md); rows become factors by the ESKF's rules
        (:func:`polins.fusion.inputs.items_from_table`).
    rot_nb0 : Rotation, optional
        Initial attitude (body -> ENU) at the first IMU sample; None: self-alignment (module
        docstring).
    **options
        ``imu_model`` (required, an ``ImuModel``), ``lat_deg``, ``lon_deg``, ``alt_m``
        (start position, default the equator at 0 m), ``vel_n0``, ``stationary`` (times
        [s]), ``output_rate_hz``, ``max_gap_s``, and the fields of :class:`GraphOptions`
        (``solver``, ``lag_s``, ``nhc_std``, ``zupt_std``, ...). ``earth_rate`` defaults to
        ``imu_model.earth_rate``. Unknown options raise ``TypeError``.

    Returns
    -------
    DataFrame
        The ESKF's solution columns (:func:`polins.fusion.eskf.solution_columns`): ``t,
        roll, pitch, yaw, heading_deg, roll_std, pitch_std, yaw_std, bgx .. baz``, their
        sigmas, velocity, geodetic position and sigmas, quaternion. ``attrs``:
        ``"updates"`` (one row per yaw/sun measurement: ``t, name, dim, nis, accepted,
        reason``; the batch solver's NIS is post-fit), ``"backend"`` = "graph",
        ``"solver"``, ``"imu_model"``, ``"info"`` (iterations, keyframes, timings [s]).
    """
    t_start = time.perf_counter()
    unknown = sorted(set(options) - set(_GRAPH_OPTIONS) - {"scale_factors"})
    if unknown:
        why = "; ".join(f"{k}: {_ESKF_ONLY[k]}" for k in unknown if k in _ESKF_ONLY)
        valid = "\n".join(f"  {k}: {v}" for k, v in _GRAPH_OPTIONS.items())
        raise TypeError(
            f"unknown graph option(s) {unknown}{' (' + why + ')' if why else ''}; "
            f"valid options:\n{valid}"
        )
    if options.pop("scale_factors", False):
        raise ValueError("the graph backend estimates no scale factors (15 states); use the ESKF")
    model = options.pop("imu_model", None)
    if not isinstance(model, ImuModel):
        raise ValueError("fuse_graph needs imu_model=ImuModel (polins.load_imu(name))")
    lat_deg = float(options.pop("lat_deg", 0.0))
    if not -90.0 <= lat_deg <= 90.0:
        raise ValueError(f"lat_deg={lat_deg} outside [-90, 90] (degrees expected)")
    lon_deg = float(options.pop("lon_deg", 0.0))
    alt_m = float(options.pop("alt_m", 0.0))
    vel_n0 = np.asarray(options.pop("vel_n0", (0.0, 0.0, 0.0)), dtype=float)
    if vel_n0.shape != (3,) or not np.all(np.isfinite(vel_n0)):
        raise ValueError(f"vel_n0 must be a finite 3-vector [m/s], got {vel_n0!r}")
    stationary = np.ravel(np.asarray(options.pop("stationary", ()), dtype=float))
    output_rate_hz = options.pop("output_rate_hz", None)
    max_gap_s = options.pop("max_gap_s", None)
    if options.get("earth_rate") is None:
        options["earth_rate"] = model.earth_rate
    if "att_std0" in options:
        att = np.broadcast_to(np.asarray(options["att_std0"], dtype=float), (3,))
        options["att_std0"] = tuple(float(a) for a in att)
    opts = GraphOptions(**options)
    if opts.zupt_std is None and stationary.size:
        raise ValueError("stationary times need zupt_std [m/s]")
    if rot_nb0 is not None and (not isinstance(rot_nb0, Rotation) or not rot_nb0.single):
        raise ValueError("rot_nb0 must be a single scipy Rotation (body FLU -> ENU) or None")

    arrays = validate_imu(imu, max_gap_s=max_gap_s)
    meas = validate_measurements(measurements)
    items = items_from_table(meas, use_sun=opts.use_sun)
    t_imu = arrays.t
    stationary = stationary[(stationary >= t_imu[0]) & (stationary <= t_imu[-1])]
    prob = _Problem(
        opts,
        model,
        (float(np.radians(lat_deg)), float(np.radians(lon_deg)), alt_m),
        t_imu,
        arrays.gyro_b,
        arrays.accel_b,
        items,
        stationary,
        rot_nb0,
        vel_n0,
    )
    log = _Log()
    for it in items:
        if not it.valid:
            log.rows.append((it.t, it.kind, 0, np.nan, False, "invalid measurement (NaN)"))
    for it in prob.outside:
        log.rows.append((it.t, it.kind, 0, np.nan, False, "outside the IMU time span"))
    t_built = time.perf_counter()
    est = _solve_batch(prob, log) if opts.solver == "batch" else _solve_incremental(prob, log)
    t_solved = time.perf_counter()
    if opts.output == "keyframes":
        t_out = prob.t_key
        states = {
            "mat": est.mat_nb,
            "vel": est.vel_n,
            "pos": est.pos_n,
            "bias": est.bias,
            "cov": est.cov,
            "known": est.yaw_known,
        }
    else:
        from polins.fusion import output_mask

        t_out = t_imu[output_mask(t_imu, output_rate_hz)]
        states = _interpolate(prob, est, t_out)
    sol = _solution_frame(prob, t_out, states)
    log.info.update(
        n_keyframes=len(prob.t_key),
        n_measurement_factors=len(prob.meas),
        time_build_s=t_built - t_start,
        time_solve_s=t_solved - t_built,
        time_output_s=time.perf_counter() - t_solved,
    )
    sol.attrs["updates"] = log.frame()
    sol.attrs["backend"] = "graph"
    sol.attrs["solver"] = opts.solver
    sol.attrs["imu_model"] = model.name
    sol.attrs["info"] = log.info
    return sol


__all__ = [
    "GraphOptions",
    "ImuSegments",
    "fuse_graph",
    "gauss_newton_qr",
    "imu_segments",
    "keyframe_times",
    "levelling_factor",
    "marginal_covariance_qr",
    "non_holonomic_factor",
    "pose_cov_body_from_nav",
    "pose_cov_nav_from_body",
    "preintegration_params",
    "sun_factor",
    "yaw_factor",
    "zero_velocity_factor",
]
