"""Error-state Kalman filter (ESKF): strapdown INS aided by polarization yaw / sun vector.

Error state (INTERFACES.md), 15 states, or 21 with ``scale_factors=True``::

    dx = [dtheta (0:3), dv_n (3:6), dp (6:9), dbg (9:12), dba (12:15), dsg (15:18), dsa (18:21)]

``rot_nb_true = exp(dtheta) rot_nb``; ``dp`` in local ENU metres; biases and scale factors
are "true minus estimate". The IMU error model is that of ``polins.calibration.ImuModel``:
``measured = (1 + s) ideal + b + white noise``, so the corrected rate is
``w = (w_measured - bg) / (1 + sg)`` (and the same for the specific force).

Continuous error dynamics (``phi``-angle form; Titterton & Weston 2004 Sec. 12.2; Groves
2013 Sec. 14.2.4, here with "true minus estimate" errors)::

    dtheta' = -w_in x dtheta - dw_in(dv, dp) - C D_g (dbg + w (.) dsg) - C n_g
    dv'     = -f_n x dtheta - (2 w_ie + w_en) x dv + v x (2 dw_ie + dw_en) + dg(dp)
              - C D_a (dba + f (.) dsa) - C n_a
    dp'     = dv,   dbg' = n_bg,   dba' = n_ba,   dsg' = dsa' = 0

with ``C = mat_nb``, ``D = diag(1 / (1 + s))`` and white noises of densities ARW, VRW and
the bias random walks (``ImuModel``). The covariance is propagated in steps of ``cov_every`` IMU
intervals (default 20, i.e. 10 Hz at 200 Hz; a step also ends at every measurement time);
the error dynamics of a step use the step means of the attitude, of the specific force in
ENU and of the scale-factor terms (the first Magnus term of the time-varying ``F``), and
are discretised as ``Phi = exp(F T)`` (power series to third order: the neglected terms are
below 1e-8 relative for steps up to 0.1 s) and the Van Loan integral
``Q = int_0^T Phi(s) Qc Phi(s)^T ds`` by Simpson's rule (exact for the polynomial
entries of ``Phi``; tests/test_eskf.py checks both against ``scipy.linalg.expm`` of the
Van Loan matrix).

Filtering uses ``filterpy.kalman.predict`` and ``filterpy.kalman.update`` (Joseph form).
Innovations are gated with a chi-square test (each rejection is logged with its reason) and
the normalised innovation squared (NIS) of every update is recorded.

Reset policy ("closed loop at a reduced rate"): the error estimate is injected into the
nominal state and zeroed after the first processed measurement at least
``reset_interval_s`` after the previous reset, or as soon as the attitude error estimate
exceeds ``reset_angle_rad``. Between resets the updates act on the error state (filterpy's
innovation ``z - H dx`` is then the exact first-order innovation about the nominal), and
the reported estimate is always ``nominal (+) dx``. This lets the batch path propagate the
nominal state and the transition matrices between resets with vectorised numpy; the
streaming path (one IMU sample at a time) follows the same rule and gives the same
results to rounding error (tests/test_eskf.py, 1e-9 rad).

Ground-vehicle constraints: ``nhc_std`` applies the non-holonomic constraint (no lateral,
no vertical body velocity) every ``nhc_every`` IMU samples, and measurement rows with
``zupt_std`` a zero-velocity update. The non-holonomic Jacobian depends on the nominal
velocity, so its sigma must also cover the linearisation error: with a poorly known forward
velocity (no zero-velocity updates or odometry) a sigma below ~0.01 m/s makes the filter
overconfident; 0.05 m/s is a sound default for a car-like vehicle.

Smoothing: :func:`run_batch` with ``smooth=True`` runs the Rauch-Tung-Striebel smoother
(:func:`rts_smooth`) over the epochs where the covariance was propagated; rows between
epochs use the gain through the partial products (inside a covariance step, a first-order
inverse of the partial step). The alignment starts a new smoothing chain.

Alignment: ``rot_nb0`` given, or self-alignment. Self-alignment assumes that the vehicle
is static during the first ``align_s`` seconds: roll and pitch come from the averaged
specific force (levelling), with the covariance of the tilt error and its exact
correlation with the accelerometer bias (a horizontal bias ``b`` tilts the estimate by
``b / g``); the yaw is unknown (reported as NaN) until the first valid yaw or sun-vector
measurement, which sets it (its variance becomes the measurement's, its correlations
zero). The vehicle may move before that measurement only if the yaw does not matter for
the velocity then (e.g. it stands still or drives straight from rest, which only rotates
the velocity with the frame, and is corrected by the alignment rotation).
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from filterpy.kalman import predict as kf_predict
from filterpy.kalman import update as kf_update
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from polins.attitude import euler_from_rot_nb, heading_deg_from_yaw, wrap_angle, yaw_from_rot_nb
from polins.calibration import ImuModel
from polins.earth import OMEGA_IE, normal_gravity, radii_of_curvature
from polins.fusion.measurement import (
    ATT,
    BA,
    BG,
    N_ERROR,
    POS,
    VEL,
    Linearized,
    non_holonomic_kernel,
    sun_kernel,
    yaw_from_sun,
    yaw_kernel,
    zero_velocity_kernel,
)
from polins.ins import (
    Mechanization,
    NavState,
    NavTrack,
    nav_rates_n,
    rotation_vectors,
    skew,
    strapdown,
    strapdown_step_detail,
)

FloatArray = NDArray[np.float64]
log = logging.getLogger("polins.fusion")

N_DYNAMIC = 9  # attitude, velocity, position: the error states with dynamics
SG = slice(15, 18)
SA = slice(18, 21)
_KIND_ORDER = {"yaw": 0, "sun": 1, "zupt": 2, "nhc": 3}


@functools.lru_cache(maxsize=64)
def _chi2_limit(prob: float | None, dof: int) -> float:
    """Chi-square gate: the ``prob`` quantile with ``dof`` degrees of freedom (inf for None)."""
    return math.inf if prob is None else float(chi2.ppf(prob, dof))


# ============================================================================ options
@dataclass(frozen=True)
class EskfOptions:
    """Configuration of the :class:`ESKF` (all SI units, radians).

    Attributes
    ----------
    mech : Mechanization
        Earth terms of the strapdown (default: from ``ImuModel.earth_rate``).
    scale_factors : bool
        Estimate gyro and accelerometer scale-factor errors (21 states).
    gate_prob : float or None
        Chi-square gate probability (default 0.9973, "3 sigma"); None disables gating.
    reset_interval_s : float
        Inject and zero the error state at the first processed measurement this long
        after the previous reset [s].
    reset_angle_rad : float
        ... or as soon as ``|dtheta|`` exceeds this [rad].
    nhc_std : float or None
        Non-holonomic constraint 1-sigma [m/s] (ground vehicle); None: off.
    nhc_every : int
        Apply the non-holonomic constraint at every ``nhc_every``-th IMU sample.
    align_s : float
        Static levelling window for self-alignment [s].
    att_std0 : float or (3,) sequence
        Initial attitude-error 1-sigma when ``rot_nb0`` is given [rad].
    vel_std0, pos_std0 : float
        Initial velocity [m/s] and position [m] 1-sigma.
    use_sun : bool
        Use a row's sun vector (2-DOF) instead of its yaw when both are present.
    tilt_coupling : bool
        Yaw rows with ``sun_n`` were measured with this filter's attitude as the prior:
        put the SPEC 10.2 tilt coupling in ``H`` (see ``yaw_measurement``).
    time_tol : float
        Measurement times within this of an IMU sample use that sample [s].
    cov_every : int
        IMU intervals per covariance step (the covariance is also propagated to every
        measurement time). The error dynamics of a step use step means (first Magnus term).
    chunk : int
        Batch path: longest run of covariance steps multiplied into one block.
    """

    mech: Mechanization = field(default_factory=Mechanization)
    scale_factors: bool = False
    gate_prob: float | None = 0.9973
    reset_interval_s: float = 5.0
    reset_angle_rad: float = 0.005
    nhc_std: float | None = None
    nhc_every: int = 20
    align_s: float = 1.0
    att_std0: float | tuple[float, float, float] = float(np.radians(1.0))
    vel_std0: float = 0.1
    pos_std0: float = 1.0
    use_sun: bool = True
    tilt_coupling: bool = False
    time_tol: float = 1e-6
    cov_every: int = 20
    chunk: int = 32

    def __post_init__(self) -> None:
        if self.gate_prob is not None and not 0.0 < self.gate_prob < 1.0:
            raise ValueError(f"gate_prob must be in (0, 1) or None, got {self.gate_prob}")
        if not self.reset_interval_s >= 0.0:
            raise ValueError(f"reset_interval_s must be >= 0 [s], got {self.reset_interval_s}")
        if self.nhc_std is not None and not self.nhc_std > 0.0:
            raise ValueError(f"nhc_std must be > 0 [m/s] or None, got {self.nhc_std}")
        if int(self.nhc_every) < 1:
            raise ValueError(f"nhc_every must be a positive integer, got {self.nhc_every}")
        if not self.align_s > 0.0:
            raise ValueError(f"align_s must be > 0 [s], got {self.align_s}")
        if int(self.cov_every) < 1:
            raise ValueError(f"cov_every must be a positive integer, got {self.cov_every}")
        if int(self.chunk) < 1:
            raise ValueError(f"chunk must be a positive integer, got {self.chunk}")


# ============================================================================ error model
def n_states(scale_factors: bool) -> int:
    """Number of error states: 15, or 21 with scale factors."""
    return 21 if scale_factors else N_ERROR


def process_noise_density(model: ImuModel, scale_factors: bool = False) -> FloatArray:
    """Diagonal of the continuous process-noise density ``Qc`` (per error state).

    ARW^2 on the attitude, VRW^2 on the velocity [(m/s)^2/s], the bias random walks on the
    biases, zero on position and scale factors. The noises enter through ``-C`` (a
    rotation), so ``G Qc G^T`` stays diagonal for isotropic densities.
    """
    qc = np.zeros(n_states(scale_factors))
    qc[ATT] = model.gyro_arw**2
    qc[VEL] = model.accel_vrw**2
    qc[BG] = model.gyro_bias_rw**2
    qc[BA] = model.accel_bias_rw**2
    return qc


def _gravity_gradient(lat: FloatArray, height: FloatArray) -> FloatArray:
    """``d gamma / d h`` [1/s^2] (gamma is quadratic in h, so the central difference is exact)."""
    return 0.5 * (normal_gravity(lat, height + 1.0) - normal_gravity(lat, height - 1.0))


def error_dynamics(
    mat_nb: ArrayLike,
    force_n: ArrayLike,
    vel_n: ArrayLike,
    lat: ArrayLike,
    height: ArrayLike,
    mech: Mechanization,
    *,
    gyro_scale: ArrayLike | None = None,
    accel_scale: ArrayLike | None = None,
    mat_omega: ArrayLike | None = None,
    mat_force: ArrayLike | None = None,
) -> FloatArray:
    """Continuous error-dynamics matrix ``F`` (module docstring), vectorised.

    Over a covariance step the attitude-dependent blocks use means over the step (the
    first Magnus term of the time-varying ``F``): the mean attitude matrix, the mean
    specific force in ENU, and for the scale-factor columns the means of
    ``mat_nb diag(omega_b)`` and ``mat_nb diag(f_b)``.

    Parameters
    ----------
    mat_nb : (..., 3, 3) array_like
        Attitude matrix (step mean).
    force_n : (..., 3) array_like
        Specific force in ENU (step mean) [m/s^2].
    vel_n : (..., 3) array_like
        ENU velocity [m/s].
    lat, height : (...) array_like
        Latitude [rad], height [m].
    mech : Mechanization
        Earth terms (the same as the strapdown).
    gyro_scale, accel_scale : (3,) array_like, optional
        Estimated scale factors; when given the matrix has 21 states.
    mat_omega, mat_force : (..., 3, 3) array_like, optional
        Means of ``mat_nb diag(omega_b)`` [rad/s] and ``mat_nb diag(f_b)`` [m/s^2] with
        the corrected body rate and specific force (required with scale factors).

    Returns
    -------
    (..., 15, 15) or (..., 21, 21) ndarray
    """
    mat = np.asarray(mat_nb, dtype=float)
    fn = np.asarray(force_n, dtype=float)
    v = np.asarray(vel_n, dtype=float)
    lat_a = np.asarray(lat, dtype=float)
    h = np.asarray(height, dtype=float)
    sf = gyro_scale is not None
    n = n_states(sf)
    batch = fn.shape[:-1]
    F = np.zeros((*batch, n, n))
    w_ie, w_en = nav_rates_n(lat_a, h, v, mech)
    F[..., ATT, ATT] = -skew(w_ie + w_en)
    r_m, r_n = radii_of_curvature(lat_a)
    rmh, rnh = r_m + h, r_n + h
    dwen_dv = np.zeros((*batch, 3, 3))
    dw_dp = np.zeros((*batch, 3, 3))  # d(w_in)/dp
    dwie_dp = np.zeros((*batch, 3, 3))
    if mech.transport_rate:
        tan_l = np.tan(lat_a)
        dwen_dv[..., 0, 1] = -1.0 / rmh
        dwen_dv[..., 1, 0] = 1.0 / rnh
        dwen_dv[..., 2, 0] = tan_l / rnh
        ve, vn = v[..., 0], v[..., 1]
        dw_dp[..., 2, 1] = ve / (np.cos(lat_a) ** 2 * rnh * rmh)
        dw_dp[..., 0, 2] = vn / rmh**2
        dw_dp[..., 1, 2] = -ve / rnh**2
        dw_dp[..., 2, 2] = -ve * tan_l / rnh**2
    if mech.earth_rotation:
        dwie_dp[..., 1, 1] = -OMEGA_IE * np.sin(lat_a) / rmh
        dwie_dp[..., 2, 1] = OMEGA_IE * np.cos(lat_a) / rmh
    F[..., ATT, VEL] = -dwen_dv
    F[..., ATT, POS] = -(dw_dp + dwie_dp)
    dg = 1.0 if gyro_scale is None else 1.0 / (1.0 + np.asarray(gyro_scale, dtype=float))
    da = 1.0 if accel_scale is None else 1.0 / (1.0 + np.asarray(accel_scale, dtype=float))
    F[..., ATT, BG] = -mat * dg
    sv = skew(v)
    F[..., VEL, ATT] = -skew(fn)
    F[..., VEL, VEL] = -skew(2.0 * w_ie + w_en) + sv @ dwen_dv
    F[..., VEL, POS] = sv @ (2.0 * dwie_dp + dw_dp)
    F[..., VEL.start + 2, POS.start + 2] -= _gravity_gradient(lat_a, h)
    F[..., VEL, BA] = -mat * da
    F[..., POS, VEL] = np.eye(3)
    if sf:
        if mat_omega is None or mat_force is None:
            raise ValueError("error_dynamics with scale factors needs mat_omega and mat_force")
        F[..., ATT, SG] = -np.asarray(mat_omega, dtype=float) * dg
        F[..., VEL, SA] = -np.asarray(mat_force, dtype=float) * da
    return F


def discretize(F: ArrayLike, dt: ArrayLike, qc: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Transition matrix and process noise of one interval, vectorised.

    ``Phi = I + A + A^2/2 + A^3/6`` with ``A = F dt`` and the Van Loan integral
    ``Q = int_0^dt Phi(s) Qc Phi(s)^T ds`` by Simpson's rule,
    ``Q = dt/6 (Qc + 4 Phi(dt/2) Qc Phi(dt/2)^T + Phi Qc Phi^T)``.

    Parameters
    ----------
    F : (..., n, n) array_like
        Continuous error dynamics.
    dt : (...) array_like
        Interval [s].
    qc : (n,) array_like
        Diagonal of the continuous process-noise density.

    Returns
    -------
    Phi, Q : (..., n, n) ndarray
    """
    F = np.asarray(F, dtype=float)
    dt = np.asarray(dt, dtype=float)
    qc = np.asarray(qc, dtype=float)
    n = F.shape[-1]
    k = N_DYNAMIC if n >= N_DYNAMIC and not np.any(F[..., N_DYNAMIC:, :]) else n
    # Rows k.. of F are zero (sensor errors without dynamics): only the top rows of the
    # powers of A are non-zero, A^(p+1)[:k] = A[:k, :k] A^p[:k].
    A = F[..., :k, :] * dt[..., None, None]
    A_kk = A[..., :k]
    A2 = A_kk @ A
    A3 = A_kk @ A2
    idx = np.arange(n)
    Phi = np.zeros((*F.shape[:-2], n, n))
    Phi[..., :k, :] = A + 0.5 * A2 + A3 / 6.0
    Phi[..., idx, idx] += 1.0
    half = 0.5 * A + 0.125 * A2 + A3 / 48.0  # Phi(dt/2) - I, top rows
    half[..., idx[:k], idx[:k]] += 1.0
    # Simpson on int_0^dt Phi(s) Qc Phi(s)^T ds with Phi(0) = I, Phi(dt/2), Phi(dt).
    Phi_top = Phi[..., :k, :]
    Q = np.zeros_like(Phi)
    Q[..., :k, :k] = (Phi_top * qc) @ np.swapaxes(Phi_top, -1, -2)
    Q[..., :k, :k] += 4.0 * (half * qc) @ np.swapaxes(half, -1, -2)
    Q[..., :k, k:] = (Phi_top[..., k:] + 4.0 * half[..., k:]) * qc[k:]
    Q[..., k:, :k] = np.swapaxes(Q[..., :k, k:], -1, -2)
    Q[..., idx, idx] += qc
    Q[..., idx[k:], idx[k:]] += 5.0 * qc[k:]  # Phi(dt/2) and Phi(dt) are I there
    Q *= dt[..., None, None] / 6.0
    return Phi, Q


def euler_jacobian(rot_nb: Rotation) -> FloatArray:
    """``d(yaw, pitch, roll) / d dtheta`` for the navigation-frame attitude error, ``(..., 3, 3)``.

    For ``rot_nb = Rz(yaw) Ry(pitch) Rx(roll)``, ``dtheta = E d(yaw, pitch, roll)`` with
    ``E = [z, Rz(yaw) y, Rz(yaw) Ry(pitch) x]``; the result is ``E^-1``.
    """
    yaw, pitch, _ = euler_from_rot_nb(rot_nb)
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    E = np.zeros((*np.shape(yaw), 3, 3))
    E[..., 2, 0] = 1.0
    E[..., 0, 1], E[..., 1, 1] = -sy, cy
    E[..., 0, 2], E[..., 1, 2], E[..., 2, 2] = cp * cy, cp * sy, -sp
    return np.linalg.inv(E)


# ============================================================================ measurements
@dataclass(frozen=True, eq=False)
class MeasurementItem:
    """One scalar/vector measurement waiting to be applied at time ``t``.

    ``kind`` is ``"yaw"``, ``"sun"``, ``"zupt"`` or ``"nhc"``; ``valid`` is False for rows
    with NaN values (they are logged as rejected and not used).
    """

    t: float
    kind: str
    std: float
    yaw: float = math.nan
    sun_b: FloatArray | None = None
    sun_n: FloatArray | None = None
    valid: bool = True

    @property
    def order(self) -> tuple[float, int]:
        """Processing order: time, then yaw/sun before zero-velocity before NHC."""
        return (self.t, _KIND_ORDER[self.kind])


def _finite(*values: Any) -> bool:
    return all(
        v is not None and bool(np.all(np.isfinite(np.asarray(v, dtype=float)))) for v in values
    )


def measurement_items(
    t: float,
    *,
    yaw: float | None = None,
    yaw_std: float | None = None,
    sun_b: ArrayLike | None = None,
    sun_n: ArrayLike | None = None,
    sun_std: float | None = None,
    zupt_std: float | None = None,
    use_sun: bool = True,
) -> list[MeasurementItem]:
    """The measurement items of one row (``measurements`` DataFrame columns).

    A row with a complete sun vector (``sun_b``, ``sun_n``, ``sun_std``) gives a sun item
    when ``use_sun``; otherwise a row with yaw columns gives a yaw item (carrying ``sun_n``
    for the optional tilt coupling). NaN values give an invalid item (logged, not used).
    ``zupt_std`` adds a zero-velocity item.
    """
    items: list[MeasurementItem] = []
    t = float(t)
    has_sun = sun_b is not None or sun_std is not None
    sun_ok = has_sun and _finite(sun_b, sun_n, sun_std) and float(sun_std) > 0  # type: ignore[arg-type]
    s_n = None if not _finite(sun_n) else np.asarray(sun_n, dtype=float).copy()
    if use_sun and sun_ok:
        items.append(
            MeasurementItem(
                t,
                "sun",
                float(sun_std),  # type: ignore[arg-type]
                sun_b=np.asarray(sun_b, dtype=float).copy(),
                sun_n=s_n,
            )
        )
    elif yaw is not None or yaw_std is not None:
        ok = _finite(yaw, yaw_std) and float(yaw_std) > 0  # type: ignore[arg-type]
        items.append(
            MeasurementItem(
                t,
                "yaw",
                float(yaw_std) if ok else math.nan,  # type: ignore[arg-type]
                yaw=float(yaw) if ok else math.nan,  # type: ignore[arg-type]
                sun_n=s_n,
                valid=ok,
            )
        )
    elif has_sun:
        items.append(MeasurementItem(t, "sun", math.nan, valid=False))
    if zupt_std is not None and not (isinstance(zupt_std, float) and math.isnan(zupt_std)):
        ok = _finite(zupt_std) and float(zupt_std) > 0
        items.append(MeasurementItem(t, "zupt", float(zupt_std) if ok else math.nan, valid=ok))
    return items


@dataclass(frozen=True)
class UpdateRecord:
    """Log entry of one measurement: NIS, acceptance, and the reason for a rejection."""

    t: float
    name: str
    dim: int
    nis: float
    accepted: bool
    reason: str


# ============================================================================ state
@dataclass(frozen=True, eq=False)
class FilterState:
    """Estimate at time ``t``: navigation state, sensor errors, covariance.

    ``P`` is the error-state covariance (15 or 21 states, module docstring); ``yaw_aligned``
    is False while self-alignment still waits for the first yaw measurement.
    """

    t: float
    rot_nb: Rotation
    vel_n: FloatArray
    lat: float
    lon: float
    height: float
    bg: FloatArray
    ba: FloatArray
    sg: FloatArray
    sa: FloatArray
    P: FloatArray
    yaw_aligned: bool

    @property
    def sigma(self) -> FloatArray:
        """Square roots of the covariance diagonal (error-state order)."""
        return np.sqrt(np.clip(np.diag(self.P), 0.0, None))

    def euler_std(self) -> FloatArray:
        """1-sigma of (yaw, pitch, roll) [rad] from the attitude-error covariance."""
        J = euler_jacobian(self.rot_nb)
        cov = J @ self.P[ATT, ATT] @ J.T
        return np.sqrt(np.clip(np.diag(cov), 0.0, None))

    def row(self) -> dict[str, float]:
        """The state as one row of the solution table (:func:`solution_frame` columns)."""
        return {k: float(v[0]) for k, v in solution_columns(**_state_arrays([self])).items()}


def _state_arrays(states: Sequence[FilterState]) -> dict[str, Any]:
    rot = Rotation.concatenate([s.rot_nb for s in states])
    return {
        "t": np.array([s.t for s in states]),
        "rot_nb": rot,
        "vel_n": np.array([s.vel_n for s in states]),
        "lat": np.array([s.lat for s in states]),
        "lon": np.array([s.lon for s in states]),
        "height": np.array([s.height for s in states]),
        "bg": np.array([s.bg for s in states]),
        "ba": np.array([s.ba for s in states]),
        "sg": np.array([s.sg for s in states]) if states[0].P.shape[0] > N_ERROR else None,
        "sa": np.array([s.sa for s in states]) if states[0].P.shape[0] > N_ERROR else None,
        "P_diag_att": np.array([s.P[ATT, ATT] for s in states]),
        "sigma": np.array([s.sigma for s in states]),
        "yaw_aligned": np.array([s.yaw_aligned for s in states]),
    }


def solution_columns(
    *,
    t: FloatArray,
    rot_nb: Rotation,
    vel_n: FloatArray,
    lat: FloatArray,
    lon: FloatArray,
    height: FloatArray,
    bg: FloatArray,
    ba: FloatArray,
    sg: FloatArray | None,
    sa: FloatArray | None,
    P_diag_att: FloatArray,
    sigma: FloatArray,
    yaw_aligned: FloatArray,
) -> dict[str, FloatArray]:
    """Solution-table columns (CONVENTIONS.md) from arrays of states.

    Columns: ``t, roll, pitch, yaw, heading_deg, roll_std, pitch_std, yaw_std, bgx, bgy,
    bgz, bax, bay, baz`` then ``bgx_std .. baz_std, ve, vn, vu, ve_std, vn_std, vu_std,
    lat_deg, lon_deg, height_m, pe_std, pn_std, pu_std`` [m], ``qw, qx, qy, qz`` and, with
    scale factors, ``sgx .. saz`` and their ``_std``. Yaw-dependent columns are NaN before
    the yaw alignment.
    """
    yaw, pitch, roll = euler_from_rot_nb(rot_nb)
    J = euler_jacobian(rot_nb)
    cov = J @ P_diag_att @ np.swapaxes(J, -1, -2)
    std = np.sqrt(np.clip(np.diagonal(cov, axis1=-2, axis2=-1), 0.0, None))
    nan_yaw = ~np.asarray(yaw_aligned, dtype=bool)
    yaw = np.where(nan_yaw, np.nan, yaw)
    quat = rot_nb.as_quat()
    cols: dict[str, FloatArray] = {
        "t": t,
        "roll": roll,
        "pitch": pitch,
        "yaw": yaw,
        "heading_deg": heading_deg_from_yaw(yaw),
        "roll_std": std[:, 2],
        "pitch_std": std[:, 1],
        "yaw_std": np.where(nan_yaw, np.nan, std[:, 0]),
    }
    for i, ax in enumerate("xyz"):
        cols[f"bg{ax}"] = bg[:, i]
    for i, ax in enumerate("xyz"):
        cols[f"ba{ax}"] = ba[:, i]
    for i, ax in enumerate("xyz"):
        cols[f"bg{ax}_std"] = sigma[:, BG.start + i]
    for i, ax in enumerate("xyz"):
        cols[f"ba{ax}_std"] = sigma[:, BA.start + i]
    for i, c in enumerate("enu"):
        cols[f"v{c}"] = vel_n[:, i]
    for i, c in enumerate("enu"):
        cols[f"v{c}_std"] = sigma[:, VEL.start + i]
    cols["lat_deg"] = np.degrees(lat)
    cols["lon_deg"] = np.degrees(lon)
    cols["height_m"] = height
    for i, c in enumerate("enu"):
        cols[f"p{c}_std"] = sigma[:, POS.start + i]
    cols["qw"], cols["qx"], cols["qy"], cols["qz"] = quat[:, 3], quat[:, 0], quat[:, 1], quat[:, 2]
    if sg is not None and sa is not None:
        for i, ax in enumerate("xyz"):
            cols[f"sg{ax}"] = sg[:, i]
        for i, ax in enumerate("xyz"):
            cols[f"sa{ax}"] = sa[:, i]
        for i, ax in enumerate("xyz"):
            cols[f"sg{ax}_std"] = sigma[:, SG.start + i]
        for i, ax in enumerate("xyz"):
            cols[f"sa{ax}_std"] = sigma[:, SA.start + i]
    return cols


# ============================================================================ alignment
def level_from_accel(accel_b: ArrayLike) -> tuple[float, float]:
    """Roll and pitch [rad] from a mean specific force of a static body (levelling).

    A static body measures ``f_b = mat_bn (0, 0, g)``: ``roll = atan2(f_y, f_z)``,
    ``pitch = atan2(-f_x, hypot(f_y, f_z))`` (FLU, positive pitch nose down).
    """
    f = np.asarray(accel_b, dtype=float)
    return float(np.arctan2(f[1], f[2])), float(np.arctan2(-f[0], np.hypot(f[1], f[2])))


def inject(
    nav: NavState, bg: FloatArray, ba: FloatArray, sg: FloatArray, sa: FloatArray, dx: FloatArray
) -> tuple[NavState, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Apply an error-state estimate to the nominal state (``nominal (+) dx``)."""
    r_m, r_n = radii_of_curvature(nav.lat)
    nav2 = NavState(
        t=nav.t,
        rot_nb=Rotation.from_rotvec(dx[ATT]) * nav.rot_nb,
        vel_n=nav.vel_n + dx[VEL],
        lat=nav.lat + float(dx[POS.start + 1] / (r_m + nav.height)),
        lon=nav.lon + float(dx[POS.start] / ((r_n + nav.height) * np.cos(nav.lat))),
        height=nav.height + float(dx[POS.start + 2]),
    )
    if dx.shape[0] > N_ERROR:
        sg, sa = sg + dx[SG], sa + dx[SA]
    return nav2, bg + dx[BG], ba + dx[BA], sg, sa


# ============================================================================ the filter
@dataclass
class _StepSums:
    """Sums over the IMU intervals of the covariance step in progress."""

    n: int = 0
    dt: float = 0.0
    mat: FloatArray = field(default_factory=lambda: np.zeros((3, 3)))  # sum C dt
    dv: FloatArray = field(default_factory=lambda: np.zeros(3))  # sum of int C f dt
    mat_omega: FloatArray = field(default_factory=lambda: np.zeros((3, 3)))  # sum C diag(w) dt
    mat_force: FloatArray = field(default_factory=lambda: np.zeros((3, 3)))  # sum C diag(f) dt
    vel_n: FloatArray = field(default_factory=lambda: np.zeros(3))  # at the step start
    lat: float = 0.0
    height: float = 0.0


class ESKF:
    """Error-state Kalman filter holding its state; incremental (streaming) interface.

    Parameters
    ----------
    model : ImuModel
        IMU error model (``polins.load_imu``): process noise and initial bias covariance.
    t0 : float
        Time of the first IMU sample [s] (the filter starts there).
    lat, lon, height : float
        Initial position: latitude, longitude [rad], height [m].
    rot_nb0 : Rotation, optional
        Initial attitude; None for self-alignment (module docstring).
    vel_n0 : (3,) array_like
        Initial ENU velocity [m/s] (self-alignment assumes 0).
    options : EskfOptions
        Configuration.

    Notes
    -----
    Use: ``propagate(t, gyro_b, accel_b)`` once per IMU sample (the first call must be at
    ``t0``), ``add_measurement(t, ...)`` for each measurement (applied when the IMU
    reaches ``t``, with the IMU interpolated linearly to ``t``), ``state()`` for the
    current estimate with its covariance. ``records`` logs every measurement.
    :func:`run_batch` runs a whole log through a fresh filter with the same results.
    """

    def __init__(
        self,
        model: ImuModel,
        t0: float,
        lat: float,
        lon: float,
        height: float,
        *,
        rot_nb0: Rotation | None = None,
        vel_n0: ArrayLike = (0.0, 0.0, 0.0),
        options: EskfOptions | None = None,
    ) -> None:
        if not isinstance(model, ImuModel):
            raise ValueError(
                f"model must be a polins.ImuModel (polins.load_imu), got {type(model)}"
            )
        self.model = model
        self.options = options if options is not None else EskfOptions()
        self.n = n_states(self.options.scale_factors)
        self.qc = process_noise_density(model, self.options.scale_factors)
        self.records: list[UpdateRecord] = []
        self.bg = np.zeros(3)
        self.ba = np.zeros(3)
        self.sg = np.zeros(3)
        self.sa = np.zeros(3)
        self.x = np.zeros(self.n)
        self._pending: list[MeasurementItem] = []
        self._cur: tuple[float, FloatArray, FloatArray] | None = None  # last (virtual) sample
        self._real: tuple[float, FloatArray, FloatArray] | None = None  # last real IMU sample
        self._count = 0  # real IMU samples consumed
        self._t0 = float(t0)
        self._align_buffer: list[tuple[float, FloatArray, FloatArray]] | None = None
        self._sums = _StepSums()
        # Called as hook(filter, k) after the k-th real IMU sample has been consumed.
        self.sample_hook: Callable[[ESKF, int], None] | None = None
        self.t_reset = float(t0)
        self.n_resets = 0
        self._dx_epoch = np.zeros(self.n)  # sum of update corrections at an epoch (smoother)
        self._track_dx = False
        v0 = np.array(vel_n0, dtype=float)
        if v0.shape != (3,) or not np.all(np.isfinite(v0)):
            raise ValueError(f"vel_n0 must be a finite 3-vector [m/s], got {vel_n0!r}")
        rot = rot_nb0 if rot_nb0 is not None else Rotation.identity()
        if not isinstance(rot, Rotation) or not rot.single:
            raise ValueError("rot_nb0 must be a single scipy Rotation (body FLU -> ENU) or None")
        self._lazy: tuple[NavTrack, int] | None = None
        self._nav = NavState(float(t0), rot, v0, float(lat), float(lon), float(height))
        self.P = self._initial_covariance()
        self.yaw_aligned = rot_nb0 is not None
        if rot_nb0 is None:
            self._align_buffer = []

    # ------------------------------------------------------------------ setup
    def _initial_covariance(self) -> FloatArray:
        o, m = self.options, self.model
        P = np.zeros((self.n, self.n))
        att = np.broadcast_to(np.asarray(o.att_std0, dtype=float), (3,))
        P[ATT, ATT] = np.diag(att**2)
        P[VEL, VEL] = np.eye(3) * o.vel_std0**2
        P[POS, POS] = np.eye(3) * o.pos_std0**2
        P[BG, BG] = np.eye(3) * m.gyro_bias**2
        P[BA, BA] = np.eye(3) * m.accel_bias**2
        if self.n > N_ERROR:
            P[SG, SG] = np.eye(3) * m.gyro_scale_factor**2
            P[SA, SA] = np.eye(3) * m.accel_scale_factor**2
        return P

    def _level(self, samples: list[tuple[float, FloatArray, FloatArray]]) -> None:
        """Self-alignment of roll/pitch from the static window (module docstring)."""
        accel = np.array([s[2] for s in samples])
        gyro = np.array([s[1] for s in samples])
        f_mean = accel.mean(axis=0)
        g = float(normal_gravity(self.nav.lat, self.nav.height))
        if abs(np.linalg.norm(f_mean) - g) > 0.05 * g or np.max(np.abs(gyro)) > 0.2:
            log.warning(
                "self-alignment: the IMU does not look static in the first %.2f s "
                "(|f| = %.3f m/s^2, max |w| = %.3f rad/s); roll/pitch may be wrong",
                self.options.align_s,
                np.linalg.norm(f_mean),
                np.max(np.abs(gyro)),
            )
        roll, pitch = level_from_accel(f_mean)
        rot = Rotation.from_euler("ZYX", [0.0, pitch, roll])
        self.nav = replace(self.nav, rot_nb=rot, vel_n=np.zeros(3))
        # Tilt error = J dba exactly (a horizontal bias tilts the level by b/g), plus the
        # averaged white noise of the accelerometer.
        J = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0]]) @ rot.as_matrix() / g
        P = self.P.copy()
        P[ATT, :] = 0.0
        P[:, ATT] = 0.0
        p_ba = P[BA, BA]
        duration = max(samples[-1][0] - samples[0][0], 1.0 / max(self.model.sample_rate_hz, 1.0))
        noise = (self.model.accel_vrw / g) ** 2 / duration
        P[0:2, 0:2] = J @ p_ba @ J.T + np.eye(2) * noise
        P[0:2, BA] = J @ p_ba
        P[BA, 0:2] = (J @ p_ba).T
        P[2, 2] = 1.0  # yaw unknown until the first yaw measurement
        P[VEL, VEL] = np.eye(3) * self.options.vel_std0**2
        self.P = P

    # ------------------------------------------------------------------ nominal state
    @property
    def t(self) -> float:
        """Current filter time [s]."""
        if self._lazy is not None:
            return float(self._lazy[0].t[self._lazy[1]])
        return self._nav.t

    @property
    def nav(self) -> NavState:
        """Nominal navigation state (the estimate is ``nominal (+) x``)."""
        if self._lazy is not None:
            track, i = self._lazy
            self._nav = track.state(i)
            self._lazy = None
        return self._nav

    @nav.setter
    def nav(self, value: NavState) -> None:
        self._nav = value
        self._lazy = None

    def _set_track(self, track: NavTrack, i: int) -> None:
        """Batch path: the nominal state is sample ``i`` of ``track`` (built on demand)."""
        self._lazy = (track, i)

    def _nominal_mat_vel(self) -> tuple[FloatArray, FloatArray]:
        if self._lazy is not None:
            track, i = self._lazy
            return track.mat_nb[i], track.vel_n[i]
        return self._nav.rot_nb.as_matrix(), self._nav.vel_n

    @property
    def ready(self) -> bool:
        """True once levelling is done (a state is available)."""
        return self._align_buffer is None

    # ------------------------------------------------------------------ public API
    def propagate(self, t: float, gyro_b: ArrayLike, accel_b: ArrayLike) -> list[UpdateRecord]:
        """Consume one IMU sample (instantaneous rate and specific force at ``t``).

        Applies the pending measurements with times up to ``t`` on the way.

        Returns
        -------
        list of UpdateRecord
            Records of the measurements applied during this call.
        """
        t = float(t)
        w = np.array(gyro_b, dtype=float)
        f = np.array(accel_b, dtype=float)
        if w.shape != (3,) or f.shape != (3,) or not np.all(np.isfinite(np.r_[w, f])):
            raise ValueError("gyro_b and accel_b must be finite 3-vectors [rad/s], [m/s^2]")
        n_before = len(self.records)
        tol = self.options.time_tol
        if self._align_buffer is not None:
            if self._align_buffer and t <= self._align_buffer[-1][0]:
                raise ValueError(f"IMU time {t} is not after the previous sample")
            if not self._align_buffer and abs(t - self._t0) > tol:
                raise ValueError(f"the first IMU sample must be at t0={self._t0}, got {t}")
            self._align_buffer.append((t, w, f))
            if t - self._t0 >= self.options.align_s - tol:
                buffer, self._align_buffer = self._align_buffer, None
                self._level([s for s in buffer if s[0] - self._t0 <= self.options.align_s + tol])
                for s in buffer:
                    self._consume(*s)
        else:
            self._consume(t, w, f)
        return self.records[n_before:]

    def add_measurement(
        self,
        t: float,
        *,
        yaw: float | None = None,
        yaw_std: float | None = None,
        sun_b: ArrayLike | None = None,
        sun_n: ArrayLike | None = None,
        sun_std: float | None = None,
        zupt_std: float | None = None,
    ) -> list[UpdateRecord]:
        """Queue (or apply now, if ``t`` is the current time) one measurement row.

        Parameters are the ``measurements`` DataFrame columns (CONVENTIONS.md): a yaw and its
        1-sigma [rad]; and/or a measured body sun vector, its ENU reference and direction
        1-sigma [rad]; and/or a zero-velocity 1-sigma [m/s]. A measurement older than the
        filter time is rejected (logged) since the filter does not re-process the past.

        Returns
        -------
        list of UpdateRecord
            Records of the items applied now (empty if queued).
        """
        items = measurement_items(
            t,
            yaw=yaw,
            yaw_std=yaw_std,
            sun_b=sun_b,
            sun_n=sun_n,
            sun_std=sun_std,
            zupt_std=zupt_std,
            use_sun=self.options.use_sun,
        )
        return self.add_items(items)

    def add_items(self, items: Sequence[MeasurementItem]) -> list[UpdateRecord]:
        """Queue measurement items (see :meth:`add_measurement`)."""
        n_before = len(self.records)
        tol = self.options.time_tol
        started = self._cur is not None and self.ready
        for item in items:
            if started and item.t < self.t - tol:
                reason = f"out of sequence: t={item.t} is before the filter time {self.t}"
                self._record(item, 0, math.nan, False, reason)
            elif started and abs(item.t - self.t) <= tol and not self._pending:
                self._apply(item)
            else:
                self._pending.append(item)
                self._pending.sort(key=lambda it: it.order)
        return self.records[n_before:]

    def state(self) -> FilterState:
        """Current estimate ``nominal (+) x`` with the error covariance."""
        if not self.ready:
            raise RuntimeError(
                "the filter is still levelling (self-alignment); feed more IMU samples"
            )
        x, P = self.x, self.P
        if self._sums.n:
            Phi, Q = self._step_matrices(self._sums)
            x, P = kf_predict(x, P, Phi, Q)
        nav, bg, ba, sg, sa = inject(self.nav, self.bg, self.ba, self.sg, self.sa, x)
        return FilterState(
            nav.t,
            nav.rot_nb,
            nav.vel_n,
            nav.lat,
            nav.lon,
            nav.height,
            bg,
            ba,
            sg,
            sa,
            P.copy(),
            self.yaw_aligned,
        )

    def reset(self) -> None:
        """Inject the error estimate into the nominal state and zero it (reset Jacobian I)."""
        self._flush()
        self.nav, self.bg, self.ba, self.sg, self.sa = inject(
            self.nav, self.bg, self.ba, self.sg, self.sa, self.x
        )
        self.x = np.zeros(self.n)
        self.t_reset = self.t
        self.n_resets += 1

    def linearize(self, item: MeasurementItem) -> Linearized:
        """The measurement model of ``item`` at the current nominal state."""
        mat, vel = self._nominal_mat_vel()
        var = item.std * item.std
        if item.kind == "yaw":
            sun_n = item.sun_n if self.options.tilt_coupling else None
            lin = yaw_kernel(mat, item.yaw, var, sun_n)
        elif item.kind == "sun":
            lin = sun_kernel(mat, item.sun_b, item.sun_n, var, None)  # type: ignore[arg-type]
        elif item.kind == "zupt":
            lin = zero_velocity_kernel(vel, np.full(3, var))
        elif item.kind == "nhc":
            lin = non_holonomic_kernel(mat, vel, np.full(2, var))
        else:  # pragma: no cover - items are built by measurement_items
            raise ValueError(f"unknown measurement kind {item.kind!r}")
        if self.n > N_ERROR:
            H = np.zeros((lin.dim, self.n))
            H[:, :N_ERROR] = lin.H
            lin = Linearized(lin.residual, H, lin.R, lin.name)
        return lin

    # ------------------------------------------------------------------ internals
    def _corrected(self, w: FloatArray, f: FloatArray) -> tuple[FloatArray, FloatArray]:
        if self.n > N_ERROR:
            return (w - self.bg) / (1.0 + self.sg), (f - self.ba) / (1.0 + self.sa)
        return w - self.bg, f - self.ba

    def _consume(self, t: float, w: FloatArray, f: FloatArray) -> None:
        """One real IMU sample: apply pending measurements up to ``t``, step to ``t``."""
        tol = self.options.time_tol
        if self._cur is None:
            self._cur = self._real = (t, w, f)
            self._count = 1
        else:
            t_a, w_a, f_a = self._real  # type: ignore[misc]
            if t <= t_a:
                raise ValueError(f"IMU time {t} is not after the previous sample {t_a}")
            while self._pending and self._pending[0].t <= t + tol:
                item = self._pending.pop(0)
                if item.t < self.t - tol:
                    reason = f"out of sequence: t={item.t} is before the filter time {self.t}"
                    self._record(item, 0, math.nan, False, reason)
                    continue
                if item.t > self.t + tol:
                    if item.t >= t - tol:
                        self._step(t, w, f)
                    else:
                        frac = (item.t - t_a) / (t - t_a)
                        self._step(item.t, w_a + (w - w_a) * frac, f_a + (f - f_a) * frac)
                self._apply(item)
            if t > self.t + tol:
                self._step(t, w, f)
            self._real = (t, w, f)
            self._count += 1
        o = self.options
        if o.nhc_std is not None and self._count > 1 and (self._count - 1) % o.nhc_every == 0:
            self._apply(MeasurementItem(t, "nhc", o.nhc_std))
        while self._pending and abs(self._pending[0].t - self.t) <= tol:
            self._apply(self._pending.pop(0))
        if self.sample_hook is not None:
            self.sample_hook(self, self._count - 1)

    def _step(self, t1: float, w1: FloatArray, f1: FloatArray) -> None:
        """Propagate the nominal state to ``t1``; accumulate the covariance step."""
        t0, w0, f0 = self._cur  # type: ignore[misc]
        wc0, fc0 = self._corrected(w0, f0)
        wc1, fc1 = self._corrected(w1, f1)
        dt = t1 - t0
        nav0 = self.nav
        nav1, rot_mid, dv_force = strapdown_step_detail(
            nav0, wc0, wc1, fc0, fc1, t1, self.options.mech
        )
        sums = self._sums
        if sums.n == 0:
            sums.vel_n, sums.lat, sums.height = nav0.vel_n, nav0.lat, nav0.height
        mat = rot_mid.as_matrix()
        sums.n += 1
        sums.dt += dt
        sums.mat = sums.mat + mat * dt
        sums.dv = sums.dv + dv_force
        if self.n > N_ERROR:
            phi, _ = rotation_vectors(wc0, wc1, dt)
            sums.mat_omega = sums.mat_omega + mat * phi
            sums.mat_force = sums.mat_force + mat * (0.5 * (fc0 + fc1) * dt)
        self.nav = nav1
        self._cur = (t1, w1, f1)
        if sums.n >= self.options.cov_every:
            self._flush()

    def _step_matrices(self, sums: _StepSums) -> tuple[FloatArray, FloatArray]:
        """Transition and noise of a covariance step from its sums."""
        inv = 1.0 / sums.dt
        sf = self.n > N_ERROR
        F = error_dynamics(
            sums.mat * inv,
            sums.dv * inv,
            sums.vel_n,
            sums.lat,
            sums.height,
            self.options.mech,
            gyro_scale=self.sg if sf else None,
            accel_scale=self.sa if sf else None,
            mat_omega=sums.mat_omega * inv if sf else None,
            mat_force=sums.mat_force * inv if sf else None,
        )
        return discretize(F, np.array(sums.dt), self.qc)

    def _flush(self) -> None:
        """Propagate the covariance over the step in progress (filterpy ``predict``)."""
        if self._sums.n:
            Phi, Q = self._step_matrices(self._sums)
            self.x, self.P = kf_predict(self.x, self.P, Phi, Q)
            self._sums = _StepSums()

    def _record(
        self, item: MeasurementItem, dim: int, nis: float, accepted: bool, reason: str
    ) -> UpdateRecord:
        rec = UpdateRecord(item.t, item.kind, dim, nis, accepted, reason)
        self.records.append(rec)
        if not accepted:
            log.info("t=%.6f %s rejected: %s", item.t, item.kind, reason)
        return rec

    def _apply(self, item: MeasurementItem) -> None:
        """Gate and apply one measurement at the current time; then maybe reset."""
        if self._sums.n:
            self._flush()
        if not item.valid:
            self._record(item, 0, math.nan, False, "invalid measurement (NaN or non-positive std)")
            return
        if not self.yaw_aligned and item.kind in ("yaw", "sun"):
            self._align_yaw(item)
            return
        lin = self.linearize(item)
        y = lin.residual - lin.H @ self.x
        S = lin.H @ self.P @ lin.H.T + lin.R
        nis = float(y[0] * y[0] / S[0, 0]) if lin.dim == 1 else float(y @ np.linalg.solve(S, y))
        gate = self.options.gate_prob
        limit = _chi2_limit(gate, lin.dim)
        if nis > limit:
            reason = f"NIS {nis:.3g} > gate {limit:.3g} (chi2, {lin.dim} dof, p={gate})"
            self._record(item, lin.dim, nis, False, reason)
        else:
            x_before = self.x
            self.x, self.P = kf_update(self.x, self.P, lin.residual, lin.R, lin.H)
            if self._track_dx:
                self._dx_epoch = self._dx_epoch + (self.x - x_before)
            self._record(item, lin.dim, nis, True, "")
        x_att = self.x[ATT]
        if (
            self.t - self.t_reset >= self.options.reset_interval_s
            or float(x_att @ x_att) > self.options.reset_angle_rad**2
        ):
            self.reset()

    def _align_yaw(self, item: MeasurementItem) -> None:
        """Set the yaw from the first yaw / sun measurement (module docstring)."""
        self.reset()
        nav = self.nav
        if item.kind == "yaw":
            yaw_meas, std = item.yaw, item.std
        else:
            s_n = np.asarray(item.sun_n, dtype=float)
            s_n = s_n / np.linalg.norm(s_n)
            yaw_meas = yaw_from_sun(nav.rot_nb, item.sun_b, s_n)  # type: ignore[arg-type]
            std = item.std / max(float(np.hypot(s_n[0], s_n[1])), 1e-3)
        delta = float(wrap_angle(yaw_meas - yaw_from_rot_nb(nav.rot_nb)))
        rz = Rotation.from_rotvec([0.0, 0.0, delta])
        self.nav = replace(nav, rot_nb=rz * nav.rot_nb, vel_n=rz.apply(nav.vel_n))
        T = np.eye(self.n)
        T[ATT, ATT] = rz.as_matrix()
        T[VEL, VEL] = rz.as_matrix()
        P = T @ self.P @ T.T
        P[2, :] = 0.0
        P[:, 2] = 0.0
        P[2, 2] = std**2
        self.P = P
        self.yaw_aligned = True
        self._record(item, 1, math.nan, True, "used for the yaw alignment")


# ============================================================================ batch path
@dataclass(frozen=True, eq=False)
class BatchOutput:
    """Estimates at the output IMU samples of :func:`run_batch` (arrays over rows).

    ``P`` holds the full error covariance per row; ``smoothed`` (if requested) is another
    :class:`BatchOutput` with the Rauch-Tung-Striebel estimates.
    """

    t: FloatArray
    rot_nb: Rotation
    vel_n: FloatArray
    lat: FloatArray
    lon: FloatArray
    height: FloatArray
    bg: FloatArray
    ba: FloatArray
    sg: FloatArray | None
    sa: FloatArray | None
    P: FloatArray
    yaw_aligned: FloatArray
    smoothed: BatchOutput | None = None

    def columns(self) -> dict[str, FloatArray]:
        """Solution-table columns (:func:`solution_columns`)."""
        sigma = np.sqrt(np.clip(np.diagonal(self.P, axis1=-2, axis2=-1), 0.0, None))
        return solution_columns(
            t=self.t,
            rot_nb=self.rot_nb,
            vel_n=self.vel_n,
            lat=self.lat,
            lon=self.lon,
            height=self.height,
            bg=self.bg,
            ba=self.ba,
            sg=self.sg,
            sa=self.sa,
            P_diag_att=self.P[:, ATT, ATT],
            sigma=sigma,
            yaw_aligned=self.yaw_aligned,
        )


def _inject_many(
    mat_nb: FloatArray,
    vel_n: FloatArray,
    lat: FloatArray,
    lon: FloatArray,
    height: FloatArray,
    dx: FloatArray,
) -> tuple[Rotation, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Vectorised ``nominal (+) dx`` for the navigation part (see :func:`inject`)."""
    r_m, r_n = radii_of_curvature(lat)
    rot = Rotation.from_rotvec(dx[:, ATT]) * Rotation.from_matrix(mat_nb)
    return (
        rot,
        vel_n + dx[:, VEL],
        lat + dx[:, POS.start + 1] / (r_m + height),
        lon + dx[:, POS.start] / ((r_n + height) * np.cos(lat)),
        height + dx[:, POS.start + 2],
    )


@dataclass
class _Chain:
    """Smoother storage: epochs (where the covariance was propagated to) and output rows."""

    P_prior: list[FloatArray] = field(default_factory=list)
    P_post: list[FloatArray] = field(default_factory=list)
    Phi: list[FloatArray | None] = field(default_factory=list)  # from the previous epoch
    dx: list[FloatArray] = field(default_factory=list)
    out_next: list[NDArray[np.int_]] = field(default_factory=list)  # next epoch or -1
    out_gain: list[FloatArray] = field(default_factory=list)  # per output row: C_o


def _assign_samples(
    t: FloatArray, items: Sequence[MeasurementItem], tol: float
) -> tuple[
    list[tuple[int, float]],
    list[int | tuple[int, int]],
    list[MeasurementItem],
    list[MeasurementItem],
]:
    """Map measurement items to real samples or to virtual (interpolated) samples.

    Mirrors the streaming rule: an item within ``tol`` of a real sample uses it; otherwise a
    virtual sample at the item time between the two real samples, shared by later items
    within ``tol`` of it.

    Returns
    -------
    virtual : list of (interval k, time)
        Virtual samples between real samples ``k - 1`` and ``k``.
    where : list
        Per used item: real index (int) or ``(k, j)`` = j-th virtual sample of the list.
    used, early : lists of MeasurementItem
        Items inside the log; items before its first sample (rejected). Items after the
        last sample are in neither (they stay pending).
    """
    virtual: list[tuple[int, float]] = []
    where: list[int | tuple[int, int]] = []
    used: list[MeasurementItem] = []
    early: list[MeasurementItem] = []
    n = len(t)
    for item in items:
        k = int(np.searchsorted(t, item.t - tol, side="left"))
        if k >= n:
            continue
        if t[k] <= item.t + tol:
            where.append(k)
        elif k == 0:
            early.append(item)
            continue
        elif virtual and virtual[-1][0] == k and item.t <= virtual[-1][1] + tol:
            where.append((k, len(virtual) - 1))
        else:
            virtual.append((k, item.t))
            where.append((k, len(virtual) - 1))
        used.append(item)
    return virtual, where, used, early


def block_transitions(
    Phi: FloatArray,
    Q: FloatArray,
    starts: NDArray[np.int_],
    ends: NDArray[np.int_],
    at_block: NDArray[np.int_],
    at_pos: NDArray[np.int_],
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Products of per-step transitions over consecutive blocks of steps.

    Block ``s`` covers steps ``starts[s] .. ends[s] - 1``. Returns the block transition
    ``Pi[s] = Phi[e-1] ... Phi[b]`` and noise ``Qa[s]`` (the recursion
    ``Qa <- Phi Qa Phi^T + Q``, i.e. what filterpy's ``predict`` does step by step), and
    the partial products after ``at_pos[i]`` steps of block ``at_block[i]`` (position 0 is
    the identity / zero). The loop runs over the positions inside the blocks and is
    vectorised across the blocks.
    """
    n = Phi.shape[-1]
    lengths = ends - starts
    S, L = len(ends), int(lengths.max())
    Pi = np.broadcast_to(np.eye(n), (S, n, n)).copy()
    Qa = np.zeros((S, n, n))
    Pi_at = np.empty((at_block.size, n, n))
    Qa_at = np.empty((at_block.size, n, n))
    order = np.argsort(at_pos, kind="stable")
    bounds = np.searchsorted(at_pos[order], np.arange(L + 1))
    short = int(lengths.min())
    for j in range(L):
        want = order[bounds[j] : bounds[j + 1]]
        if want.size:
            Pi_at[want] = Pi[at_block[want]]
            Qa_at[want] = Qa[at_block[want]]
        if j < short:
            Pj = Phi[starts + j]
            Pi = Pj @ Pi
            Qa = Pj @ Qa @ np.swapaxes(Pj, -1, -2) + Q[starts + j]
        else:
            act = np.flatnonzero(lengths > j)
            Pj = Phi[starts[act] + j]
            Pi[act] = Pj @ Pi[act]
            Qa[act] = Pj @ Qa[act] @ np.swapaxes(Pj, -1, -2) + Q[starts[act] + j]
    return Pi, Qa, Pi_at, Qa_at


def _split_gaps(marks: NDArray[np.int_], every: int) -> NDArray[np.int_]:
    """Split ``0 < marks[0] < marks[1] < ...`` into pieces of at most ``every``.

    Returns the piece ends: for each gap ``(previous mark, mark]`` the points
    ``previous + every, previous + 2 every, ...`` before the mark, then the mark.
    """
    prev = np.concatenate([[0], marks[:-1]])
    count = (marks - prev + every - 1) // every  # pieces per gap
    first = np.repeat(prev, count)
    k = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count) + 1
    return np.minimum(first + k * every, np.repeat(marks, count))


def _step_boundaries(n: int, epochs: NDArray[np.int_], every: int) -> NDArray[np.int_]:
    """Ends of the covariance steps over intervals ``0 .. n - 1`` (relative sample indices).

    A step ends after ``every`` intervals or at an epoch (a sample with measurements),
    whichever comes first (the streaming rule), and at ``n``.
    """
    marks = np.unique(np.concatenate([epochs[(epochs > 0) & (epochs < n)], [n]]))
    return _split_gaps(marks.astype(int), every)


@dataclass(frozen=True, eq=False)
class _SegmentSteps:
    """The covariance steps of a batch segment: per-interval terms and their step sums."""

    track: NavTrack
    step_start: NDArray[np.int_]
    per_interval: list[FloatArray]  # dt, C dt, dv_force [, C diag(w) dt, C diag(f) dt]
    full: list[FloatArray]  # the same summed over each step
    mech: Mechanization
    scales: tuple[FloatArray | None, FloatArray | None]
    qc: FloatArray

    def matrices(
        self, q: NDArray[np.int_], j: NDArray[np.int_] | None
    ) -> tuple[FloatArray, FloatArray]:
        """Transition and noise over the first ``j`` intervals of steps ``q`` (None: all)."""
        a = self.step_start[q]
        if j is None:
            sums = [x[q] for x in self.full]
        else:  # partial steps (output rows inside a step): sums of the first j terms
            width = int(j.max())
            idx = a[:, None] + np.arange(width)[None, :]
            take = np.arange(width)[None, :] < j[:, None]
            idx = np.where(take, idx, 0)
            sums = []
            for x in self.per_interval:
                terms = x[idx] * take.reshape(take.shape + (1,) * (x.ndim - 1))
                sums.append(terms.sum(axis=1))
        inv = 1.0 / sums[0]
        sf = self.scales[0] is not None
        F = error_dynamics(
            sums[1] * inv[:, None, None],
            sums[2] * inv[:, None],
            self.track.vel_n[a],
            self.track.lat[a],
            self.track.height[a],
            self.mech,
            gyro_scale=self.scales[0],
            accel_scale=self.scales[1],
            mat_omega=sums[3] * inv[:, None, None] if sf else None,
            mat_force=sums[4] * inv[:, None, None] if sf else None,
        )
        return discretize(F, sums[0], self.qc)


def run_batch(
    eskf: ESKF,
    t: ArrayLike,
    gyro_b: ArrayLike,
    accel_b: ArrayLike,
    items: Sequence[MeasurementItem],
    *,
    output_mask: ArrayLike | None = None,
    smooth: bool = False,
    max_segment: int = 4096,
) -> BatchOutput:
    """Run a fresh :class:`ESKF` over a whole IMU log (vectorised between resets).

    Gives the same estimates as feeding the samples one by one to :meth:`ESKF.propagate`
    (with the items queued by :meth:`ESKF.add_items`), to rounding error: between resets
    the nominal state does not depend on the updates, so it is propagated for a whole
    segment at once (:func:`polins.ins.strapdown`); the covariance-step transitions are
    computed for the whole segment and multiplied into block transitions between
    measurement epochs (:func:`block_transitions`), and filterpy's ``predict`` and
    ``update`` run once per epoch. Outputs between epochs use the partial products.

    Parameters
    ----------
    eskf : ESKF
        A filter that has not consumed any sample yet; it is left at the end of the log.
    t : (N,) array_like
        IMU sample times [s], strictly increasing, ``t[0] = eskf.t``.
    gyro_b, accel_b : (N, 3) array_like
        Raw IMU samples [rad/s], [m/s^2].
    items : sequence of MeasurementItem
        Measurements (any order).
    output_mask : (N,) bool array_like, optional
        IMU samples to report (default all).
    smooth : bool
        Also run the Rauch-Tung-Striebel smoother.
    max_segment : int
        Longest run of samples propagated at once (memory bound).

    Returns
    -------
    BatchOutput
    """
    o = eskf.options
    tol = o.time_tol
    t = np.asarray(t, dtype=float)
    W = np.asarray(gyro_b, dtype=float)
    A = np.asarray(accel_b, dtype=float)
    N = t.shape[0]
    if eskf._cur is not None or (eskf._align_buffer is not None and eskf._align_buffer):
        raise ValueError("run_batch needs a filter that has not consumed any IMU sample")
    if N < 2 or W.shape != (N, 3) or A.shape != (N, 3):
        raise ValueError("run_batch needs at least 2 samples: t (N,), gyro_b and accel_b (N, 3)")
    if abs(t[0] - eskf._t0) > tol:
        raise ValueError(f"the first IMU sample must be at t0={eskf._t0}, got {t[0]}")
    out = np.ones(N, dtype=bool) if output_mask is None else np.asarray(output_mask, dtype=bool)
    if out.shape != (N,):
        raise ValueError(f"output_mask must have shape ({N},), got {out.shape}")
    row_bytes = eskf.n * eskf.n * 8 * (3 if smooth else 1)
    if out.sum() * row_bytes > 4e9:
        raise ValueError(
            f"{int(out.sum())} output rows with full covariances need "
            f"{out.sum() * row_bytes / 1e9:.1f} GB; report fewer rows (output_rate_hz)"
        )
    max_segment = max(int(max_segment), 2 * o.cov_every)
    sf = eskf.n > N_ERROR

    # ---- self-alignment (levelling), as the streaming path does it
    if not eskf.ready:
        k_end = int(np.searchsorted(t - eskf._t0, o.align_s - tol, side="left"))
        if k_end >= N:
            raise ValueError(
                f"the IMU log ({t[-1] - t[0]:.3f} s) is shorter than the alignment window "
                f"align_s={o.align_s} s; give rot_nb0 or a longer log"
            )
        window = [
            (float(t[k]), W[k].copy(), A[k].copy())
            for k in range(k_end + 1)
            if t[k] - eskf._t0 <= o.align_s + tol
        ]
        eskf._align_buffer = None
        eskf._level(window)

    # ---- measurement items -> (virtual) samples
    user = sorted(items, key=lambda it: it.order)
    virtual, where, used, early = _assign_samples(t, user, tol)
    for item in early:
        reason = f"out of sequence: t={item.t} is before the first IMU sample"
        eskf._record(item, 0, math.nan, False, reason)
    used_ids = {id(it) for it in used} | {id(it) for it in early}
    eskf._pending = [it for it in user if id(it) not in used_ids]
    n_virt = len(virtual)
    v_k = np.array([v[0] for v in virtual], dtype=int)
    v_t = np.array([v[1] for v in virtual], dtype=float)
    aug_real = np.arange(N) + np.searchsorted(v_k, np.arange(N), side="right")
    aug_virt = v_k + np.arange(n_virt)  # virtual j sits just before real sample v_k[j]
    M = N + n_virt
    T = np.empty(M)
    Wa = np.empty((M, 3))
    Aa = np.empty((M, 3))
    real_of_aug = np.full(M, -1)
    T[aug_real], Wa[aug_real], Aa[aug_real] = t, W, A
    real_of_aug[aug_real] = np.arange(N)
    if n_virt:
        frac = (v_t - t[v_k - 1]) / (t[v_k] - t[v_k - 1])
        T[aug_virt] = v_t
        Wa[aug_virt] = W[v_k - 1] + (W[v_k] - W[v_k - 1]) * frac[:, None]
        Aa[aug_virt] = A[v_k - 1] + (A[v_k] - A[v_k - 1]) * frac[:, None]
    out_aug = np.zeros(M, dtype=bool)
    out_aug[aug_real] = out
    items_at: dict[int, list[MeasurementItem]] = {}
    for item, w_ in zip(used, where, strict=True):
        idx = int(aug_real[w_]) if isinstance(w_, int) else int(aug_virt[w_[1]])
        items_at.setdefault(idx, []).append(item)
    if o.nhc_std is not None:
        for k in range(o.nhc_every, N, o.nhc_every):
            nhc = MeasurementItem(float(t[k]), "nhc", o.nhc_std)
            items_at.setdefault(int(aug_real[k]), []).append(nhc)
    item_idx = np.array(sorted(items_at), dtype=int)
    valid_idx = np.array(sorted(i for i, its in items_at.items() if any(x.valid for x in its)))
    valid_idx = valid_idx.astype(int)
    align_idx = np.array(
        sorted(
            i
            for i, its in items_at.items()
            if any(x.valid and x.kind in ("yaw", "sun") for x in its)
        ),
        dtype=int,
    )

    # ---- output storage
    keys = ("t", "mat", "vel", "lat", "lon", "h", "x", "P", "bg", "ba", "sg", "sa", "al")
    rows: dict[str, list[Any]] = {k: [] for k in keys}
    chain = _Chain()

    def chain_epoch(P_prior: FloatArray, Phi: FloatArray | None, aligned_before: bool) -> None:
        if smooth:
            chain.P_prior.append(P_prior)
            chain.P_post.append(eskf.P)
            chain.Phi.append(Phi if aligned_before == eskf.yaw_aligned else None)
            chain.dx.append(eskf._dx_epoch)

    # ---- first sample
    eskf._track_dx = smooth
    eskf._cur = eskf._real = (float(T[0]), Wa[0].copy(), Aa[0].copy())
    eskf._count = 1
    eskf._dx_epoch = np.zeros(eskf.n)
    P_prior0, al0 = eskf.P, eskf.yaw_aligned
    for item in items_at.get(0, []):
        eskf._apply(item)
    chain_epoch(P_prior0, None, al0)

    cur = 0
    n_ep = 1  # chain epochs so far
    while cur < M - 1:
        # ---- plan the segment: up to the next reset (time rule) or yaw alignment
        stop = min(M - 1, cur + max_segment)
        capped = stop < M - 1
        later = valid_idx[valid_idx > cur]
        due = later[T[later] - eskf.t_reset >= o.reset_interval_s]
        if due.size and due[0] <= stop:
            stop, capped = int(due[0]), False
        if not eskf.yaw_aligned:
            nxt = align_idx[align_idx > cur]
            if nxt.size and nxt[0] <= stop:
                stop, capped = int(nxt[0]), False
        epochs = item_idx[(item_idx > cur) & (item_idx <= stop)] - cur
        ends = _step_boundaries(stop - cur, epochs, o.cov_every)
        if capped and ends.size > 1:
            # a capped segment must end where the streaming filter ends a step too
            last, prev = int(ends[-1]), int(ends[-2])
            if last - prev != o.cov_every and last not in epochs:
                ends = ends[:-1]
                stop = cur + prev
        # ---- nominal track
        sl = slice(cur, stop + 1)
        Wc, Ac = eskf._corrected(Wa[sl], Aa[sl])
        track = strapdown(eskf.nav, T[sl], Wc, Ac, o.mech)
        dt = np.diff(T[sl])
        # ---- step sums of the per-interval quantities, summed in the streaming order
        step_start = np.concatenate([[0], ends[:-1]])
        per_interval = [dt, track.mat_nb_mid * dt[:, None, None], track.dv_force_n]
        if sf:
            phi, _ = rotation_vectors(Wc[:-1], Wc[1:], dt)
            f_mid = 0.5 * (Ac[:-1] + Ac[1:]) * dt[:, None]
            per_interval += [
                track.mat_nb_mid * phi[:, None, :],
                track.mat_nb_mid * f_mid[:, None, :],
            ]
        full = [np.add.reduceat(x, step_start, axis=0) for x in per_interval]
        scales = (eskf.sg, eskf.sa) if sf else (None, None)  # fixed until the next reset

        steps = _SegmentSteps(track, step_start, per_interval, full, o.mech, scales, eskf.qc)
        Phi, Q = steps.matrices(np.arange(ends.size), None)
        # ---- blocks of steps between epochs (at most `chunk` steps each)
        is_epoch = np.isin(ends, epochs) | (ends == stop - cur)
        b_end = _split_gaps(np.flatnonzero(is_epoch) + 1, o.chunk)
        b_start = np.concatenate([[0], b_end[:-1]])
        ep = ends[b_end - 1]  # sample (relative) where each block ends
        # candidate output rows: real samples in [cur, stop)
        rel = np.arange(stop - cur)
        sel = rel[out_aug[cur + rel]]
        q_of = np.searchsorted(ends, sel, side="right")  # step containing the sample
        s_of = np.searchsorted(b_end, q_of, side="right")  # block containing the step
        Pi, Qa, Pi_sel, Qa_sel = block_transitions(
            Phi, Q, b_start, b_end, s_of, q_of - b_start[s_of]
        )
        # ---- sequential pass over the block ends: filterpy predict, updates, resets
        x_post, P_post, P_prior = [eskf.x], [eskf.P], []
        bg_seg, ba_seg, sg_seg, sa_seg = eskf.bg, eskf.ba, eskf.sg, eskf.sa
        aligned_seg = eskf.yaw_aligned
        n_done = len(ep)
        for s in range(len(ep)):
            e_abs = cur + int(ep[s])
            eskf.x, eskf.P = kf_predict(eskf.x, eskf.P, Pi[s], Qa[s])
            P_prior.append(eskf.P)
            eskf._set_track(track, int(ep[s]))
            resets, aligned_before = eskf.n_resets, eskf.yaw_aligned
            if smooth:
                eskf._dx_epoch = np.zeros(eskf.n)
            for item in items_at.get(e_abs, ()):
                eskf._apply(item)
            chain_epoch(P_prior[-1], Pi[s], aligned_before)
            x_post.append(eskf.x)
            P_post.append(eskf.P)
            if eskf.n_resets != resets:
                n_done = s + 1
                break
        # ---- outputs inside the processed blocks (block start .. before its end)
        rel_end = int(ep[n_done - 1])
        keep = sel < rel_end
        if np.any(keep):
            sel, q_of, s_of = sel[keep], q_of[keep], s_of[keep]
            Pi_o, Qa_o = Pi_sel[keep], Qa_sel[keep]
            x_o = (Pi_o @ np.array(x_post)[s_of][..., None])[..., 0]
            P_o = Pi_o @ np.array(P_post)[s_of] @ np.swapaxes(Pi_o, -1, -2) + Qa_o
            a_o = step_start[q_of]
            mid = sel > a_o  # inside a step: propagate the partial step (as state() does)
            if np.any(mid):
                Phi_p, Q_p = steps.matrices(q_of[mid], (sel - a_o)[mid])
                x_o[mid] = (Phi_p @ x_o[mid][..., None])[..., 0]
                P_o[mid] = Phi_p @ P_o[mid] @ np.swapaxes(Phi_p, -1, -2) + Q_p
            rows["t"].append(T[cur + sel])
            rows["mat"].append(track.mat_nb[sel])
            rows["vel"].append(track.vel_n[sel])
            rows["lat"].append(track.lat[sel])
            rows["lon"].append(track.lon[sel])
            rows["h"].append(track.height[sel])
            rows["x"].append(x_o)
            rows["P"].append(P_o)
            for key, val in (("bg", bg_seg), ("ba", ba_seg), ("sg", sg_seg), ("sa", sa_seg)):
                rows[key].append(np.broadcast_to(val, (sel.size, 3)))
            rows["al"].append(np.full(sel.size, aligned_seg))
            if smooth:
                # C_o = P_o Pi(end <- o)^T P_prior(end)^-1 with Pi(end <- o) from the block
                # transition and the partial products (mid-step: first-order inverse).
                trans = np.swapaxes(
                    np.linalg.solve(np.swapaxes(Pi_o, -1, -2), np.swapaxes(Pi[s_of], -1, -2)),
                    -1,
                    -2,
                )
                if np.any(mid):
                    trans[mid] = np.swapaxes(
                        np.linalg.solve(
                            np.swapaxes(Phi_p, -1, -2), np.swapaxes(trans[mid], -1, -2)
                        ),
                        -1,
                        -2,
                    )
                Pp = np.array(P_prior)[s_of]
                gain = np.swapaxes(np.linalg.solve(Pp, trans @ P_o), -1, -2)
                chain.out_next.append(n_ep + s_of)
                chain.out_gain.append(gain)
        n_ep += n_done
        cur += rel_end
    eskf._cur = eskf._real = (float(t[-1]), W[-1].copy(), A[-1].copy())
    eskf._count = N
    eskf._track_dx = False
    if out[-1]:
        st = eskf.state()
        rows["t"].append(np.array([st.t]))
        rows["mat"].append(eskf.nav.rot_nb.as_matrix()[None])
        rows["vel"].append(eskf.nav.vel_n[None])
        rows["lat"].append(np.array([eskf.nav.lat]))
        rows["lon"].append(np.array([eskf.nav.lon]))
        rows["h"].append(np.array([eskf.nav.height]))
        rows["x"].append(eskf.x[None])
        rows["P"].append(eskf.P[None])
        for key, val in (("bg", eskf.bg), ("ba", eskf.ba), ("sg", eskf.sg), ("sa", eskf.sa)):
            rows[key].append(val[None])
        rows["al"].append(np.array([eskf.yaw_aligned]))
        if smooth:
            chain.out_next.append(np.array([-1]))
            chain.out_gain.append(np.zeros((1, eskf.n, eskf.n)))
    return _assemble(eskf, rows, chain if smooth else None)


def _assemble(eskf: ESKF, rows: dict[str, list[Any]], chain: _Chain | None) -> BatchOutput:
    """Stack the output rows, apply the error state, and run the smoother if asked."""
    cat = {k: np.concatenate(v) for k, v in rows.items()}
    x = cat["x"]
    sf = eskf.n > N_ERROR

    def build(dx: FloatArray, P: FloatArray) -> BatchOutput:
        rot, vel, lat, lon, h = _inject_many(
            cat["mat"], cat["vel"], cat["lat"], cat["lon"], cat["h"], dx
        )
        return BatchOutput(
            t=cat["t"],
            rot_nb=rot,
            vel_n=vel,
            lat=lat,
            lon=lon,
            height=h,
            bg=cat["bg"] + dx[:, BG],
            ba=cat["ba"] + dx[:, BA],
            sg=cat["sg"] + dx[:, SG] if sf else None,
            sa=cat["sa"] + dx[:, SA] if sf else None,
            P=P,
            yaw_aligned=cat["al"].astype(bool),
        )

    result = build(x, cat["P"])
    if chain is None:
        return result
    nxt = np.concatenate(chain.out_next)
    gain = np.concatenate(chain.out_gain)
    delta, P_s = rts_smooth(chain.P_prior, chain.P_post, chain.Phi, chain.dx)
    d_out = np.zeros_like(x)
    P_out = cat["P"].copy()
    idx = np.flatnonzero(nxt >= 0)
    if idx.size:
        i = nxt[idx]
        linked = np.array([chain.Phi[k] is not None for k in i])
        idx, i = idx[linked], i[linked]
        innov = np.array(chain.dx)[i] + delta[i]
        d_out[idx] = (gain[idx] @ innov[..., None])[..., 0]
        dP = P_s[i] - np.array(chain.P_prior)[i]
        P_out[idx] = cat["P"][idx] + gain[idx] @ dP @ np.swapaxes(gain[idx], -1, -2)
    return replace(result, smoothed=build(x + d_out, P_out))


def rts_smooth(
    P_prior: Sequence[FloatArray],
    P_post: Sequence[FloatArray],
    Phi: Sequence[FloatArray | None],
    dx: Sequence[FloatArray],
) -> tuple[FloatArray, FloatArray]:
    """Rauch-Tung-Striebel smoother in error-state (correction) form.

    With the filtered estimates ``x_i`` at epochs ``i``, the transitions ``Phi_i`` from
    epoch ``i - 1`` to ``i`` (None starts a new chain, e.g. at the yaw alignment), the
    prior and posterior covariances and the filter's update corrections ``dx_i`` at each
    epoch, the smoothed estimate is ``x_i (+) delta_i`` with::

        C_i     = P_i^+ Phi_{i+1}^T (P_{i+1}^-)^-1
        delta_i = C_i (dx_{i+1} + delta_{i+1}),            delta_last = 0
        P_i^s   = P_i^+ + C_i (P_{i+1}^s - P_{i+1}^-) C_i^T

    Returns
    -------
    delta : (E, n) ndarray
        Smoothed corrections at the epochs.
    P_s : (E, n, n) ndarray
        Smoothed covariances.
    """
    E = len(P_post)
    n = P_post[0].shape[0]
    delta = np.zeros((E, n))
    P_s = np.array(P_post, dtype=float)
    for i in range(E - 2, -1, -1):
        phi = Phi[i + 1]
        if phi is None:
            continue
        C = np.linalg.solve(P_prior[i + 1], phi @ P_post[i]).T
        delta[i] = C @ (dx[i + 1] + delta[i + 1])
        P_s[i] = P_post[i] + C @ (P_s[i + 1] - P_prior[i + 1]) @ C.T
    return delta, P_s
