"""GTSAM factor-graph backend: IMU preintegration with sun-vector and yaw factors.

The optional second backend of ``polins.fuse(..., backend="graph")`` (``pip install
"polins[graph]"``). It solves the same estimation problem as the ESKF (``polins.fusion.eskf``)
as a nonlinear least-squares problem over keyframe states, and returns the same solution
DataFrame (CONVENTIONS.md).

Graph
-----
Keyframes ``k`` sit at the first IMU sample, at every measurement time and wherever the gap
between them would exceed ``max_keyframe_dt``. Each holds ``X(k)`` (``gtsam.Pose3``: body
attitude ``rot_nb`` and position in local ENU metres), ``V(k)`` (ENU velocity) and ``B(k)``
(``imuBias.ConstantBias``: accelerometer, then gyro bias). Factors:

* ``CombinedImuFactor`` between consecutive keyframes: preintegrated IMU (Forster et al.,
  "On-manifold preintegration", TRO 2017) with the white-noise densities and the bias random
  walks of the :class:`~polins.calibration.ImuModel`, ENU gravity of WGS-84 normal gravity at
  the start (``PreintegrationCombinedParams.MakeSharedU``). With Earth rate on (navigation
  grade, ``ImuModel.earth_rate``) the Earth rate enters as ``omegaCoriolis`` and the transport
  rate is removed from the gyro samples (``omega_ib_b - C_bn omega_en_n``, evaluated at the
  current estimate of the velocity), so that the graph's navigation frame is the local-level
  ENU frame of the ESKF, not an Earth-fixed tangent plane.
* Sun vector: GTSAM's C++ ``AttitudeFactorPose3(key, nRef=sun_n, model, bMeasured=sun_b)``,
  error ``e = B(sun_n)^T (R_nb sun_b)`` (the measured direction rotated to ENU, in the tangent
  basis of the reference), isotropic ``sun_std``. ``tests/test_graph.py`` pins this.
* Yaw: a ``gtsam.CustomFactor`` whose residual and Jacobian are those of
  :func:`polins.fusion.measurement.yaw_measurement` (the ESKF's model): GTSAM's error is
  ``h(x) - z = -residual`` and its Jacobian ``H_theta R_nb`` because GTSAM perturbs a
  rotation on the right in the body frame (``R exp(w_b)``) while the ESKF's attitude error is
  on the left in the navigation frame (``exp(dtheta_n) R``, ``dtheta_n = R w_b``).
* Optional zero-velocity (``PriorFactorVector`` on ``V(k)``) and non-holonomic factors (a
  ``CustomFactor`` from :func:`polins.fusion.measurement.non_holonomic`).
* Priors on the first state from the initial attitude, velocity and the IMU model's turn-on
  bias sigmas.

Solvers
-------
``"batch"``: Levenberg-Marquardt over the whole log (smoothing, like ESKF + RTS), sigmas from
``gtsam.Marginals``. ``"isam2"``: incremental ``gtsam.ISAM2`` (online use); each keyframe is
reported as estimated when it was added, i.e. causally like a filter. ``"fixed_lag"``:
``gtsam.IncrementalFixedLagSmoother``; each keyframe is reported when it leaves the lag
window, i.e. smoothed with ``lag_s`` seconds of future data.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Any

try:
    import gtsam
    from gtsam.symbol_shorthand import B, V, X
except ImportError as exc:  # pragma: no cover - exercised by simulating a missing gtsam
    raise ImportError(
        'the graph backend (backend="graph") needs GTSAM >= 4.3: pip install "polins[graph]"'
    ) from exc

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import solve_triangular
from scipy.spatial.transform import Rotation

from polins.attitude import euler_from_rot_nb, heading_deg_from_yaw
from polins.calibration import ImuModel
from polins.earth import earth_rate_n, normal_gravity, radii_of_curvature, transport_rate_n
from polins.fusion.measurement import ATT, VEL, non_holonomic, yaw_measurement

FloatArray = NDArray[np.float64]

SOLVERS = ("batch", "isam2", "fixed_lag")


# ----------------------------------------------------------------------------- conversions
def rot3_from_rotation(rot_nb: Rotation) -> gtsam.Rot3:
    """GTSAM ``Rot3`` of a single scipy ``Rotation`` (same matrix ``mat_nb``)."""
    return gtsam.Rot3(rot_nb.as_matrix())


def rotation_from_rot3(rot3: gtsam.Rot3) -> Rotation:
    """scipy ``Rotation`` of a GTSAM ``Rot3``."""
    return Rotation.from_matrix(rot3.matrix())


def pose_cov_nav_from_body(mat_nb: ArrayLike, cov_pose_b: ArrayLike) -> FloatArray:
    """Pose covariance in GTSAM's body-frame tangent space -> navigation frame ``(6, 6)``.

    GTSAM retracts ``Pose3`` as ``(R exp(w_b), p + R v_b)``; the ESKF's errors are
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


def euler_cov_from_att_cov(rot_nb: Rotation, cov_att_n: ArrayLike) -> FloatArray:
    """Covariance of (roll, pitch, yaw) [rad^2] from a navigation-frame attitude error.

    For ``rot_nb = Rz(yaw) Ry(pitch) Rx(roll)`` a small change of the Euler angles is the
    navigation-frame rotation ``dtheta_n = E [droll, dpitch, dyaw]`` with the columns of
    ``E`` the rotation axes in ENU: ``Rz Ry x``, ``Rz y`` and ``z``. Hence
    ``cov_euler = E^-1 cov_n E^-T`` (singular at pitch = +-90 deg).
    """
    yaw, pitch, _roll = euler_from_rot_nb(rot_nb)
    rz = Rotation.from_euler("Z", float(yaw))
    rzy = rz * Rotation.from_euler("Y", float(pitch))
    e = np.column_stack([rzy.apply([1.0, 0.0, 0.0]), rz.apply([0.0, 1.0, 0.0]), [0, 0, 1.0]])
    e_inv = np.linalg.inv(e)
    return e_inv @ np.asarray(cov_att_n, dtype=float) @ e_inv.T


# ----------------------------------------------------------------------------- factors
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
        continuous-time gyro/accelerometer covariances; the bias random walks
        [rad/s/sqrt(s)], [m/s^2/sqrt(s)] the bias covariances (variance growth per second).
    gravity_mps2 : float
        Magnitude of gravity [m/s^2]: ``n_gravity = (0, 0, -g)`` (``MakeSharedU``).
    omega_ie_n : (3,) array_like, optional
        Earth rate in ENU [rad/s] (``polins.earth.earth_rate_n``) as ``omegaCoriolis``; None
        for a non-rotating navigation frame.
    integration_std : float
        Position-integration noise density [m/s/sqrt(s)] (GTSAM's integration covariance;
        tiny, it only keeps the position block regular).
    """
    params = gtsam.PreintegrationCombinedParams.MakeSharedU(float(gravity_mps2))
    eye = np.eye(3)
    params.setGyroscopeCovariance(eye * imu_model.gyro_arw**2)
    params.setAccelerometerCovariance(eye * imu_model.accel_vrw**2)
    params.setIntegrationCovariance(eye * integration_std**2)
    # GTSAM needs a regular bias covariance; 1e-15 per second is far below any real IMU.
    params.setBiasOmegaCovariance(eye * max(imu_model.gyro_bias_rw**2, 1e-30))
    params.setBiasAccCovariance(eye * max(imu_model.accel_bias_rw**2, 1e-30))
    if omega_ie_n is not None:
        params.setOmegaCoriolis(np.asarray(omega_ie_n, dtype=float))
    return params


def sun_factor(
    key: int, sun_n: ArrayLike, sun_b: ArrayLike, sun_std: float
) -> gtsam.AttitudeFactorPose3:
    """Sun-vector factor: GTSAM's ``AttitudeFactorPose3(key, nRef=sun_n, model, bMeasured=sun_b)``.

    Error ``B(sun_n)^T (R_nb sun_b)`` [rad] (2,), zero when the measured body direction,
    rotated to ENU, is the ephemeris direction; ``B`` is ``Unit3(sun_n).basis()``.
    Isotropic noise ``sun_std`` [rad] (``Measurement.sun_std``).
    """
    if not np.isfinite(sun_std) or sun_std <= 0:
        raise ValueError(f"sun_std must be finite and > 0 [rad], got {sun_std!r}")
    model = gtsam.noiseModel.Isotropic.Sigma(2, float(sun_std))
    return gtsam.AttitudeFactorPose3(
        key,
        gtsam.Unit3(np.asarray(sun_n, dtype=float)),
        model,
        gtsam.Unit3(np.asarray(sun_b, dtype=float)),
    )


def _pose_rotation(values: gtsam.Values, key: int) -> tuple[FloatArray, Rotation]:
    mat_nb = values.atPose3(key).rotation().matrix()
    return mat_nb, Rotation.from_matrix(mat_nb)


def yaw_factor(
    key: int, yaw: float, yaw_std: float, *, sun_n: ArrayLike | None = None
) -> gtsam.CustomFactor:
    """Yaw factor on ``X(k)`` with the ESKF's model :func:`~polins.fusion.measurement.yaw_measurement`.

    GTSAM error ``h(x) - z = -residual`` [rad] (wrapped), Jacobian with respect to the
    ``Pose3`` tangent ``[w_b, v_b]``: ``[H_theta R_nb, 0]`` (body-right perturbation,
    ``dtheta_n = R_nb w_b``).
    """
    model = gtsam.noiseModel.Isotropic.Sigma(1, float(yaw_std))
    sun = None if sun_n is None else np.asarray(sun_n, dtype=float)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians: Any) -> FloatArray:
        mat_nb, rot_nb = _pose_rotation(values, this.keys()[0])
        lin = yaw_measurement(rot_nb, yaw, yaw_std, sun_n=sun)
        if jacobians is not None:
            jac = np.zeros((1, 6))
            jac[:, :3] = lin.H[:, ATT] @ mat_nb
            jacobians[0] = jac
        return -lin.residual

    return gtsam.CustomFactor(model, [key], error)


def zero_velocity_factor(vel_key: int, std: float) -> gtsam.PriorFactorVector:
    """Zero-velocity factor (vehicle at rest): C++ ``PriorFactorVector(V(k), 0, std)``."""
    return gtsam.PriorFactorVector(
        vel_key, np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, float(std))
    )


def non_holonomic_factor(pose_key: int, vel_key: int, std: float) -> gtsam.CustomFactor:
    """Non-holonomic factor: zero lateral and vertical body velocity (``CustomFactor``).

    Residual and Jacobian from :func:`polins.fusion.measurement.non_holonomic`; the attitude
    columns are mapped to GTSAM's body-right tangent as in :func:`yaw_factor`, the velocity
    columns are used as they are (``Vector3`` tangent = ENU velocity change).
    """
    model = gtsam.noiseModel.Isotropic.Sigma(2, float(std))

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians: Any) -> FloatArray:
        pkey, vkey = this.keys()
        mat_nb, rot_nb = _pose_rotation(values, pkey)
        lin = non_holonomic(rot_nb, values.atVector(vkey), std)
        if jacobians is not None:
            jac_pose = np.zeros((2, 6))
            jac_pose[:, :3] = lin.H[:, ATT] @ mat_nb
            jacobians[0] = jac_pose
            jacobians[1] = lin.H[:, VEL].copy()
        return -lin.residual

    return gtsam.CustomFactor(model, [pose_key, vel_key], error)


# ----------------------------------------------------------------------------- IMU segments
@dataclass(frozen=True, eq=False)
class ImuSegments:
    """The IMU signal cut at the keyframes: one row per integration step.

    The samples are instantaneous values that vary linearly between rows (INTERFACES.md);
    each step between consecutive break points (IMU sample times and keyframe times) uses the
    mean of that linear signal, i.e. its value at the step's midpoint.
    """

    dt: FloatArray  # (S,) [s]
    gyro: FloatArray  # (S, 3) [rad/s]
    accel: FloatArray  # (S, 3) [m/s^2]
    bounds: NDArray[np.int_]  # (K,) index of the first step after keyframe k (bounds[0] = 0)


def imu_segments(
    t_imu: FloatArray, gyro: FloatArray, accel: FloatArray, t_key: FloatArray
) -> ImuSegments:
    """Integration steps between keyframe times ``t_key`` (within the IMU's time span)."""
    inside = (t_imu > t_key[0]) & (t_imu < t_key[-1])
    breaks = np.union1d(t_imu[inside], t_key)
    # Drop IMU break points closer than 1 us to a keyframe (keep the keyframe).
    near = np.abs(breaks[:, None] - t_key[None, :]).min(axis=1) < 1e-6
    breaks = np.union1d(breaks[~near], t_key)
    mid = 0.5 * (breaks[1:] + breaks[:-1])
    gyro_mid = np.column_stack([np.interp(mid, t_imu, gyro[:, i]) for i in range(3)])
    accel_mid = np.column_stack([np.interp(mid, t_imu, accel[:, i]) for i in range(3)])
    bounds = np.searchsorted(breaks, t_key)
    return ImuSegments(np.diff(breaks), gyro_mid, accel_mid, bounds)


def keyframe_times(
    t_start: float, t_end: float, t_meas: FloatArray, max_keyframe_dt: float
) -> FloatArray:
    """Keyframe times: start, end, every measurement time, and fill-ins so no gap exceeds
    ``max_keyframe_dt`` [s]."""
    base = np.union1d([t_start, t_end], t_meas[(t_meas >= t_start) & (t_meas <= t_end)])
    out = [base[:1]]
    for a, b in itertools.pairwise(base):
        n = int(np.ceil((b - a) / max_keyframe_dt - 1e-9))
        out.append(a + (b - a) * np.arange(1, n + 1) / n)
    return np.concatenate(out)


# ----------------------------------------------------------------------------- configuration
@dataclass(frozen=True)
class GraphConfig:
    """Everything the graph needs besides the data (built by :func:`fuse_graph`).

    Attributes
    ----------
    imu_model : ImuModel
        Noise densities, bias random walks and turn-on bias sigmas.
    lat, lon, height : float
        Start position [rad, rad, m] (gravity, Earth rate, output geodetic position).
    earth_rate : bool
        Mechanize the Earth rate (``omegaCoriolis``) and the transport rate.
    att_std0 : (3,) ndarray
        Prior 1-sigma of the initial attitude error, navigation frame (E, N, U axes) [rad].
    vel_std0, pos_std0 : float
        Prior 1-sigma of the initial velocity [m/s] and position [m].
    max_keyframe_dt : float
        Longest interval between keyframes [s].
    zupt_std, nhc_std : float or None
        1-sigma of zero-velocity [m/s] (at keyframes inside ``stationary``) and
        non-holonomic [m/s] factors (every keyframe); None: not used.
    lag_s : float
        Window of the fixed-lag smoother [s].
    """

    imu_model: ImuModel
    lat: float
    lon: float
    height: float
    earth_rate: bool
    att_std0: FloatArray
    vel_std0: float = 0.1
    pos_std0: float = 1e-3
    max_keyframe_dt: float = 1.0
    zupt_std: float | None = None
    nhc_std: float | None = None
    lag_s: float = 10.0
    max_iterations: int = 20
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def gravity(self) -> float:
        """WGS-84 normal gravity at the start [m/s^2]."""
        return float(normal_gravity(self.lat, self.height))

    @property
    def omega_ie_n(self) -> FloatArray | None:
        """Earth rate in ENU at the start [rad/s], or None without Earth rate."""
        return earth_rate_n(self.lat) if self.earth_rate else None


@dataclass(frozen=True, eq=False)
class MeasurementSet:
    """Measurements mapped to keyframes (one entry per accepted measurement)."""

    yaw_key: NDArray[np.int_]
    yaw: FloatArray
    yaw_std: FloatArray
    yaw_sun_n: FloatArray  # (m, 3) or NaN rows: sun reference for the tilt coupling
    sun_key: NDArray[np.int_]
    sun_b: FloatArray
    sun_n: FloatArray
    sun_std: FloatArray
    zupt_key: NDArray[np.int_]


def _bias_from_vector(b: ArrayLike) -> gtsam.imuBias.ConstantBias:
    """GTSAM bias from polins order ``[bg (3), ba (3)]`` (GTSAM stores accel first)."""
    b = np.asarray(b, dtype=float)
    return gtsam.imuBias.ConstantBias(b[3:6], b[0:3])


class _Graph:
    """State of one graph build: keyframes, IMU steps, parameters, measurement factors."""

    def __init__(
        self,
        config: GraphConfig,
        t_key: FloatArray,
        segments: ImuSegments,
        meas: MeasurementSet,
    ) -> None:
        self.config = config
        self.t_key = t_key
        self.segments = segments
        self.params = preintegration_params(
            config.imu_model, gravity_mps2=config.gravity, omega_ie_n=config.omega_ie_n
        )
        self.meas_factors: list[list[gtsam.NonlinearFactor]] = [[] for _ in t_key]
        for k, y, s, sn in zip(meas.yaw_key, meas.yaw, meas.yaw_std, meas.yaw_sun_n, strict=True):
            sun = None if not np.all(np.isfinite(sn)) else sn
            self.meas_factors[k].append(yaw_factor(X(int(k)), float(y), float(s), sun_n=sun))
        for k, sb, sn, s in zip(meas.sun_key, meas.sun_b, meas.sun_n, meas.sun_std, strict=True):
            self.meas_factors[k].append(sun_factor(X(int(k)), sn, sb, float(s)))
        if config.zupt_std is not None:
            for k in np.unique(meas.zupt_key):
                self.meas_factors[k].append(zero_velocity_factor(V(int(k)), config.zupt_std))
        if config.nhc_std is not None:
            for k in range(len(t_key)):
                self.meas_factors[k].append(non_holonomic_factor(X(k), V(k), config.nhc_std))

    def gyro_correction(
        self, mat_nb: FloatArray, vel_n: FloatArray, pos_n: FloatArray
    ) -> FloatArray:
        """Transport rate in body axes [rad/s] to remove from the gyro (zero without Earth rate)."""
        if not self.config.earth_rate:
            return np.zeros(3)
        lat, _lon, h = self.geodetic(pos_n)
        return mat_nb.T @ transport_rate_n(lat, h, vel_n)

    def geodetic(self, pos_n: FloatArray) -> tuple[float, float, float]:
        """Latitude, longitude [rad] and height [m] of a local ENU position [m]."""
        c = self.config
        r_m, r_n = radii_of_curvature(c.lat)
        lat = c.lat + pos_n[1] / (r_m + c.height)
        lon = c.lon + pos_n[0] / ((r_n + c.height) * np.cos(c.lat))
        return float(lat), float(lon), float(c.height + pos_n[2])

    def preintegrate(
        self, k: int, bias: gtsam.imuBias.ConstantBias, gyro_corr_b: FloatArray
    ) -> gtsam.PreintegratedCombinedMeasurements:
        """Preintegrated IMU from keyframe ``k`` to ``k + 1``."""
        seg = self.segments
        pim = gtsam.PreintegratedCombinedMeasurements(self.params, bias)
        lo, hi = seg.bounds[k], seg.bounds[k + 1]
        gyro = seg.gyro[lo:hi] - gyro_corr_b
        for a, w, dt in zip(seg.accel[lo:hi], gyro, seg.dt[lo:hi], strict=True):
            pim.integrateMeasurement(a, w, dt)
        return pim

    def prior_factors(
        self, state: gtsam.NavState, bias: gtsam.imuBias.ConstantBias
    ) -> list[gtsam.NonlinearFactor]:
        """Priors on keyframe 0: attitude/position (ENU sigmas mapped to GTSAM's body
        tangent), velocity, and the turn-on biases of the IMU model."""
        c = self.config
        mat_nb = state.attitude().matrix()
        cov_n = np.diag(np.concatenate([np.asarray(c.att_std0) ** 2, np.full(3, c.pos_std0**2)]))
        cov_b = pose_cov_body_from_nav(mat_nb, cov_n)
        m = c.imu_model
        bias_sigmas = np.concatenate([np.full(3, m.accel_bias), np.full(3, m.gyro_bias)])
        return [
            gtsam.PriorFactorPose3(X(0), state.pose(), gtsam.noiseModel.Gaussian.Covariance(cov_b)),
            gtsam.PriorFactorVector(
                V(0), state.velocity(), gtsam.noiseModel.Isotropic.Sigma(3, c.vel_std0)
            ),
            gtsam.PriorFactorConstantBias(
                B(0), bias, gtsam.noiseModel.Diagonal.Sigmas(np.maximum(bias_sigmas, 1e-12))
            ),
        ]


# ----------------------------------------------------------------------------- solutions
@dataclass
class _Estimates:
    """Keyframe estimates in polins conventions (filled by the solvers)."""

    mat_nb: FloatArray  # (K, 3, 3)
    vel_n: FloatArray  # (K, 3)
    pos_n: FloatArray  # (K, 3) local ENU [m]
    bias: FloatArray  # (K, 6): bg, ba
    cov: FloatArray  # (K, 15, 15) ESKF error-state order, navigation-frame attitude

    @classmethod
    def empty(cls, k: int) -> _Estimates:
        nan = np.full
        return cls(
            nan((k, 3, 3), np.nan),
            nan((k, 3), np.nan),
            nan((k, 3), np.nan),
            nan((k, 6), np.nan),
            nan((k, 15, 15), np.nan),
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
    ) -> None:
        """Store keyframe ``k`` from GTSAM values and marginal covariances."""
        mat_nb = pose.rotation().matrix()
        self.mat_nb[k] = mat_nb
        self.pos_n[k] = pose.translation()
        self.vel_n[k] = vel
        self.bias[k] = np.concatenate([bias.gyroscope(), bias.accelerometer()])
        cov = np.zeros((15, 15))
        cov_pose_n = pose_cov_nav_from_body(mat_nb, cov_pose_b)
        cov[0:3, 0:3] = cov_pose_n[:3, :3]
        cov[6:9, 6:9] = cov_pose_n[3:, 3:]
        cov[0:3, 6:9] = cov_pose_n[:3, 3:]
        cov[6:9, 0:3] = cov_pose_n[3:, :3]
        cov[3:6, 3:6] = cov_vel
        cov[9:12, 9:12] = cov_bias[3:6, 3:6]  # GTSAM bias tangent: accel, then gyro
        cov[12:15, 12:15] = cov_bias[0:3, 0:3]
        cov[9:12, 12:15] = cov_bias[3:6, 0:3]
        cov[12:15, 9:12] = cov_bias[0:3, 3:6]
        self.cov[k] = cov


def _initial_state(
    rot_nb0: Rotation, vel_n0: ArrayLike, bias0: ArrayLike
) -> tuple[gtsam.NavState, gtsam.imuBias.ConstantBias]:
    state = gtsam.NavState(rot3_from_rotation(rot_nb0), np.zeros(3), np.asarray(vel_n0, float))
    return state, _bias_from_vector(bias0)


def _build_batch(
    g: _Graph,
    state0: gtsam.NavState,
    bias0: gtsam.imuBias.ConstantBias,
    linearization: gtsam.Values | None,
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """Whole-log graph and initial values (dead reckoning, or ``linearization``)."""
    graph = gtsam.NonlinearFactorGraph()
    for f in g.prior_factors(state0, bias0):
        graph.add(f)
    values = gtsam.Values()
    state, bias = state0, bias0
    values.insert(X(0), state.pose())
    values.insert(V(0), state.velocity())
    values.insert(B(0), bias)
    for k in range(len(g.t_key) - 1):
        if linearization is not None:
            state = gtsam.NavState(linearization.atPose3(X(k)), linearization.atVector(V(k)))
            bias = linearization.atConstantBias(B(k))
        corr = g.gyro_correction(state.attitude().matrix(), state.velocity(), state.position())
        pim = g.preintegrate(k, bias, corr)
        graph.add(gtsam.CombinedImuFactor(X(k), V(k), X(k + 1), V(k + 1), B(k), B(k + 1), pim))
        if linearization is None:
            state = pim.predict(state, bias)
            values.insert(X(k + 1), state.pose())
            values.insert(V(k + 1), state.velocity())
            values.insert(B(k + 1), bias)
    for factors in g.meas_factors:
        for f in factors:
            graph.add(f)
    return graph, (values if linearization is None else linearization)


def gauss_newton_qr(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    *,
    max_iterations: int = 20,
    rel_tol: float = 1e-7,
) -> tuple[gtsam.Values, int]:
    """Gauss-Newton with sparse multifrontal QR, iterated to a relative cost change < rel_tol.

    Why not GTSAM's Levenberg-Marquardt or Cholesky: without position aiding (and without
    velocity aiding) the position and velocity marginals grow to km and tens of m/s while
    the bias random-walk links between 0.2 s keyframes carry information ~1e14; the
    normal equations then have condition numbers beyond 1e16 (Cholesky reports an
    "indeterminate system") and LM's ``lambda I`` damping dominates the weakly observed
    directions, so it creeps for a hundred iterations. QR on the Jacobian only meets the
    square root of that condition number, and the problem is nearly linear (the only
    nonlinearity is attitude), so undamped Gauss-Newton converges in 3-5 iterations. The
    first step from dead reckoning may raise the cost; convergence is therefore judged on
    the change of the cost after that, not on a decrease.
    """
    params = gtsam.GaussNewtonParams()
    params.setLinearSolverType("MULTIFRONTAL_QR")
    optimizer = gtsam.GaussNewtonOptimizer(graph, values, params)
    previous = optimizer.error()
    for iteration in range(1, max_iterations + 1):
        optimizer.iterate()
        error = optimizer.error()
        if not np.isfinite(error):
            raise RuntimeError("Gauss-Newton diverged (non-finite cost)")
        if iteration > 1 and abs(previous - error) <= rel_tol * max(error, 1.0):
            return optimizer.values(), iteration
        previous = error
    return optimizer.values(), max_iterations


def marginal_covariance_qr(bayes_tree: gtsam.GaussianBayesTree, key: int) -> FloatArray:
    """Marginal covariance of one variable from a QR-eliminated Bayes tree.

    ``marginalFactor(key, EliminateQR)`` gives the square-root information ``R`` of the
    marginal; the covariance is ``R^-1 R^-T`` (triangular solves, never ``J^T J``).
    """
    conditional = bayes_tree.marginalFactor(key, gtsam.EliminateQR)
    # R() is a view into the conditional's memory: copy it while the conditional is alive.
    r = np.array(conditional.R(), dtype=float, copy=True)
    r_inv = solve_triangular(r, np.eye(r.shape[0]))
    return r_inv @ r_inv.T


def _solve_batch(
    g: _Graph, state0: gtsam.NavState, bias0: gtsam.imuBias.ConstantBias
) -> tuple[_Estimates, dict[str, Any]]:
    """Gauss-Newton (QR) over the whole log; sigmas from the QR Bayes tree."""
    graph, values = _build_batch(g, state0, bias0, None)
    result, iterations = gauss_newton_qr(graph, values, max_iterations=g.config.max_iterations)
    info: dict[str, Any] = {"iterations": [iterations]}
    if g.config.earth_rate:
        # Re-preintegrate with the transport rate and bias of the first solution.
        graph, values = _build_batch(g, state0, bias0, result)
        result, iterations = gauss_newton_qr(graph, values, max_iterations=g.config.max_iterations)
        info["iterations"].append(iterations)
    info["error"] = graph.error(result)
    info["n_factors"] = graph.size()
    bayes_tree = graph.linearize(result).eliminateMultifrontal(
        gtsam.Ordering.OrderingType.COLAMD, gtsam.EliminateQR
    )
    est = _Estimates.empty(len(g.t_key))
    for k in range(len(g.t_key)):
        est.store(
            k,
            result.atPose3(X(k)),
            result.atVector(V(k)),
            result.atConstantBias(B(k)),
            marginal_covariance_qr(bayes_tree, X(k)),
            marginal_covariance_qr(bayes_tree, V(k)),
            marginal_covariance_qr(bayes_tree, B(k)),
        )
    return est, info


def _solve_incremental(
    g: _Graph, state0: gtsam.NavState, bias0: gtsam.imuBias.ConstantBias, solver: str
) -> tuple[_Estimates, dict[str, Any]]:
    """ISAM2 (causal estimates) or the incremental fixed-lag smoother."""
    isam_params = gtsam.ISAM2Params()
    isam_params.setRelinearizeThreshold(1e-3)
    isam_params.relinearizeSkip = 1
    lag = g.config.lag_s
    engine: Any = (
        gtsam.ISAM2(isam_params)
        if solver == "isam2"
        else gtsam.IncrementalFixedLagSmoother(lag, isam_params)
    )
    est = _Estimates.empty(len(g.t_key))
    pending: list[int] = []  # fixed-lag: keyframes not reported yet

    def record(k: int) -> None:
        est.store(
            k,
            engine.calculateEstimatePose3(X(k)),
            engine.calculateEstimateVector(V(k)),
            engine.calculateEstimateConstantBias(B(k)),
            engine.marginalCovariance(X(k)),
            engine.marginalCovariance(V(k)),
            engine.marginalCovariance(B(k)),
        )

    def update(k: int, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> None:
        if solver == "isam2":
            engine.update(graph, values)
            engine.update()  # one more relinearization/solve step
            record(k)
            return
        t_k = float(g.t_key[k])
        while pending and g.t_key[pending[0]] < t_k - lag:
            record(pending.pop(0))  # last chance before it is marginalized
        stamps = {X(k): t_k, V(k): t_k, B(k): t_k}
        engine.update(graph, values, stamps)
        pending.append(k)

    graph = gtsam.NonlinearFactorGraph()
    for f in g.prior_factors(state0, bias0):
        graph.add(f)
    for f in g.meas_factors[0]:
        graph.add(f)
    values = gtsam.Values()
    values.insert(X(0), state0.pose())
    values.insert(V(0), state0.velocity())
    values.insert(B(0), bias0)
    update(0, graph, values)
    for k in range(len(g.t_key) - 1):
        state = gtsam.NavState(
            engine.calculateEstimatePose3(X(k)), engine.calculateEstimateVector(V(k))
        )
        bias = engine.calculateEstimateConstantBias(B(k))
        corr = g.gyro_correction(state.attitude().matrix(), state.velocity(), state.position())
        pim = g.preintegrate(k, bias, corr)
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.CombinedImuFactor(X(k), V(k), X(k + 1), V(k + 1), B(k), B(k + 1), pim))
        for f in g.meas_factors[k + 1]:
            graph.add(f)
        pred = pim.predict(state, bias)
        values = gtsam.Values()
        values.insert(X(k + 1), pred.pose())
        values.insert(V(k + 1), pred.velocity())
        values.insert(B(k + 1), bias)
        update(k + 1, graph, values)
    for k in pending:
        record(k)
    return est, {"passes": 1}


# ----------------------------------------------------------------------------- inputs
def _column(df: pd.DataFrame, name: str) -> FloatArray:
    return df[name].to_numpy(dtype=float) if name in df.columns else np.full(len(df), np.nan)


def _measurement_set(
    measurements: pd.DataFrame,
    t_key: FloatArray,
    *,
    use: str,
    stationary_t: FloatArray,
) -> MeasurementSet:
    """Map measurement rows to keyframes; choose yaw or sun factor per row (``use``)."""
    t = measurements["t"].to_numpy(dtype=float) if len(measurements) else np.zeros(0)
    key = np.clip(np.searchsorted(t_key, t - 1e-9), 0, len(t_key) - 1)
    inside = (t >= t_key[0] - 1e-9) & (t <= t_key[-1] + 1e-9)
    yaw, yaw_std = _column(measurements, "yaw"), _column(measurements, "yaw_std")
    sun_b = np.column_stack([_column(measurements, f"sun_b{c}") for c in "xyz"])
    sun_n = np.column_stack([_column(measurements, f"sun_n{c}") for c in "xyz"])
    sun_std = _column(measurements, "sun_std")
    has_sun = inside & np.all(np.isfinite(sun_b), axis=1) & np.all(np.isfinite(sun_n), axis=1)
    has_sun &= np.isfinite(sun_std) & (sun_std > 0)
    has_yaw = inside & np.isfinite(yaw) & np.isfinite(yaw_std) & (yaw_std > 0)
    if use == "auto":
        use_sun, use_yaw = has_sun, has_yaw & ~has_sun
    elif use == "yaw":
        use_sun, use_yaw = np.zeros_like(has_sun), has_yaw
    elif use == "sun":
        use_sun, use_yaw = has_sun, np.zeros_like(has_yaw)
    elif use == "both":
        use_sun, use_yaw = has_sun, has_yaw
    else:
        raise ValueError(f"use={use!r}: expected 'auto', 'yaw', 'sun' or 'both'")
    zkey = np.searchsorted(t_key, stationary_t - 1e-9)
    zkey = zkey[
        (zkey < len(t_key))
        & (np.abs(t_key[np.minimum(zkey, len(t_key) - 1)] - stationary_t) < 1e-6)
    ]
    return MeasurementSet(
        yaw_key=key[use_yaw],
        yaw=yaw[use_yaw],
        yaw_std=yaw_std[use_yaw],
        yaw_sun_n=np.full((int(use_yaw.sum()), 3), np.nan),
        sun_key=key[use_sun],
        sun_b=sun_b[use_sun],
        sun_n=sun_n[use_sun],
        sun_std=sun_std[use_sun],
        zupt_key=zkey,
    )


def _self_alignment(
    t_imu: FloatArray,
    accel: FloatArray,
    measurements: pd.DataFrame,
    align_s: float,
) -> Rotation:
    """Roll and pitch from the mean specific force over the first ``align_s`` seconds
    (vehicle at rest: ``f_b = C_bn (0, 0, g)``), yaw from the first yaw measurement or the
    first sun vector with that tilt (SPEC 10.1)."""
    f = accel[t_imu <= t_imu[0] + align_s].mean(axis=0)
    roll = float(np.arctan2(f[1], f[2]))
    pitch = float(np.arctan2(-f[0], np.hypot(f[1], f[2])))
    level = Rotation.from_euler("ZYX", [0.0, pitch, roll])
    yaw = _column(measurements, "yaw")
    sun_b = np.column_stack([_column(measurements, f"sun_b{c}") for c in "xyz"])
    sun_n = np.column_stack([_column(measurements, f"sun_n{c}") for c in "xyz"])
    for i in range(len(measurements)):
        if np.isfinite(yaw[i]):
            return Rotation.from_euler("ZYX", [yaw[i], pitch, roll])
        if np.all(np.isfinite(sun_b[i])) and np.all(np.isfinite(sun_n[i])):
            from polins.fusion.measurement import yaw_from_sun

            y = yaw_from_sun(level, sun_b[i], sun_n[i])
            return Rotation.from_euler("ZYX", [y, pitch, roll])
    raise ValueError(
        "self-alignment needs a yaw or sun-vector measurement: give rot_nb0 or measurements"
    )


# ----------------------------------------------------------------------------- output
def _solution_frame(g: _Graph, est: _Estimates) -> pd.DataFrame:
    """The CONVENTIONS.md solution table at the keyframes."""
    rot_nb = Rotation.from_matrix(est.mat_nb)
    yaw, pitch, roll = euler_from_rot_nb(rot_nb)
    euler_std = np.array(
        [
            np.sqrt(
                np.clip(np.diag(euler_cov_from_att_cov(rot_nb[k], est.cov[k, :3, :3])), 0, None)
            )
            for k in range(len(g.t_key))
        ]
    )
    geo = np.array([g.geodetic(p) for p in est.pos_n])
    diag = np.sqrt(np.clip(np.diagonal(est.cov, axis1=1, axis2=2), 0.0, None))
    quat = rot_nb.as_quat()
    out = {
        "t": g.t_key,
        "roll": roll,
        "pitch": pitch,
        "yaw": yaw,
        "heading_deg": heading_deg_from_yaw(yaw),
        "roll_std": euler_std[:, 0],
        "pitch_std": euler_std[:, 1],
        "yaw_std": euler_std[:, 2],
        "qw": quat[:, 3],
        "qx": quat[:, 0],
        "qy": quat[:, 1],
        "qz": quat[:, 2],
    }
    for i, c in enumerate(("bgx", "bgy", "bgz", "bax", "bay", "baz")):
        out[c] = est.bias[:, i]
    for i, c in enumerate(("bgx", "bgy", "bgz", "bax", "bay", "baz")):
        out[f"{c}_std"] = diag[:, 9 + i]
    for i, c in enumerate(("ve", "vn", "vu")):
        out[c] = est.vel_n[:, i]
    for i, c in enumerate(("ve", "vn", "vu")):
        out[f"{c}_std"] = diag[:, 3 + i]
    out["lat_deg"] = np.degrees(geo[:, 0])
    out["lon_deg"] = np.degrees(geo[:, 1])
    out["height_m"] = geo[:, 2]
    for i, c in enumerate(("pe", "pn", "pu")):
        out[c] = est.pos_n[:, i]
    return pd.DataFrame(out)


# ----------------------------------------------------------------------------- entry point
def fuse_graph(
    imu: pd.DataFrame,
    measurements: pd.DataFrame,
    rot_nb0: Rotation | None = None,
    *,
    imu_model: ImuModel,
    lat_deg: float,
    lon_deg: float = 0.0,
    alt_m: float = 0.0,
    solver: str = "batch",
    earth_rate: bool | None = None,
    vel_n0: ArrayLike = (0.0, 0.0, 0.0),
    bias0: ArrayLike = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    att_std0: ArrayLike | None = None,
    vel_std0: float = 0.1,
    max_keyframe_dt: float = 1.0,
    lag_s: float = 10.0,
    use: str = "auto",
    zupt_std: float | None = None,
    nhc_std: float | None = None,
    stationary: ArrayLike | None = None,
    align_s: float = 1.0,
    return_info: bool = False,
) -> pd.DataFrame | tuple[pd.DataFrame, dict[str, Any]]:
    """Fuse an IMU log with yaw / sun-vector measurements in a GTSAM factor graph.

    Parameters
    ----------
    imu : DataFrame
        Columns ``t`` [s], ``gx, gy, gz`` [rad/s], ``ax, ay, az`` [m/s^2] (body FLU).
    measurements : DataFrame
        Columns ``t`` and ``yaw, yaw_std`` [rad] and/or ``sun_bx, sun_by, sun_bz``,
        ``sun_nx, sun_ny, sun_nz``, ``sun_std`` [rad] (CONVENTIONS.md); NaN rows are skipped.
    rot_nb0 : Rotation, optional
        Initial attitude (body -> ENU) at the first IMU sample; None: self-alignment (roll
        and pitch from the accelerometer averaged over ``align_s`` at rest, yaw from the
        first measurement).
    imu_model : ImuModel
        Noise densities, bias random walks and turn-on bias sigmas (``polins.load_imu``).
    lat_deg, lon_deg, alt_m : float
        Start position (gravity, Earth rate, geodetic output).
    solver : {"batch", "isam2", "fixed_lag"}
        Batch Levenberg-Marquardt smoother, causal ISAM2, or fixed-lag smoother (``lag_s``).
    earth_rate : bool, optional
        Mechanize Earth and transport rate; default ``imu_model.earth_rate``.
    vel_n0, bias0 : array_like
        Initial ENU velocity [m/s] and bias ``[bg (3) rad/s, ba (3) m/s^2]``.
    att_std0 : (3,) array_like, optional
        Prior 1-sigma of the initial attitude about E, N, U [rad]; default 1 deg tilt and
        10 deg yaw (self-alignment) or 1 deg about every axis (``rot_nb0`` given).
    vel_std0 : float
        Prior 1-sigma of the initial velocity [m/s].
    max_keyframe_dt : float
        Longest interval between keyframes [s].
    use : {"auto", "yaw", "sun", "both"}
        Which factor a row becomes: "auto" uses the sun vector where the row has one and the
        yaw otherwise ("both" double-counts a yaw derived from the same sun vector).
    zupt_std, nhc_std : float, optional
        Zero-velocity (at keyframes at ``stationary`` times) and non-holonomic factor sigmas.
    stationary : array_like, optional
        Times [s] at which the vehicle is known to be at rest (keyframes are added there).
    return_info : bool
        Also return a dict with solver diagnostics.

    Returns
    -------
    DataFrame
        One row per keyframe: ``t, roll, pitch, yaw, heading_deg, roll_std, pitch_std,
        yaw_std``, quaternion ``qw..qz``, biases ``bgx..baz`` and their ``_std``, velocity
        ``ve, vn, vu`` (+ ``_std``), ``lat_deg, lon_deg, height_m`` and local ``pe, pn, pu``.
    """
    if solver not in SOLVERS:
        raise ValueError(f"solver={solver!r}: expected one of {SOLVERS}")
    t_imu = imu["t"].to_numpy(dtype=float)
    gyro = imu[["gx", "gy", "gz"]].to_numpy(dtype=float)
    accel = imu[["ax", "ay", "az"]].to_numpy(dtype=float)
    t_meas = measurements["t"].to_numpy(dtype=float) if len(measurements) else np.zeros(0)
    stationary_t = np.zeros(0) if stationary is None else np.asarray(stationary, dtype=float)
    stationary_t = stationary_t[(stationary_t >= t_imu[0]) & (stationary_t <= t_imu[-1])]
    t_key = keyframe_times(t_imu[0], t_imu[-1], np.union1d(t_meas, stationary_t), max_keyframe_dt)
    if rot_nb0 is None:
        rot_nb0 = _self_alignment(t_imu, accel, measurements, align_s)
        default_att = np.radians([1.0, 1.0, 10.0])
    else:
        default_att = np.radians([1.0, 1.0, 1.0])
    config = GraphConfig(
        imu_model=imu_model,
        lat=float(np.radians(lat_deg)),
        lon=float(np.radians(lon_deg)),
        height=float(alt_m),
        earth_rate=imu_model.earth_rate if earth_rate is None else bool(earth_rate),
        att_std0=default_att if att_std0 is None else np.asarray(att_std0, dtype=float),
        vel_std0=vel_std0,
        max_keyframe_dt=max_keyframe_dt,
        zupt_std=zupt_std,
        nhc_std=nhc_std,
        lag_s=lag_s,
    )
    meas = _measurement_set(measurements, t_key, use=use, stationary_t=stationary_t)
    g = _Graph(config, t_key, imu_segments(t_imu, gyro, accel, t_key), meas)
    state0, b0 = _initial_state(rot_nb0, vel_n0, bias0)
    if solver == "batch":
        est, info = _solve_batch(g, state0, b0)
    else:
        est, info = _solve_incremental(g, state0, b0, solver)
    frame = _solution_frame(g, est)
    return (frame, info) if return_info else frame
