"""Error-state Kalman filter (ESKF): strapdown INS aided by polarization yaw / sun vector.

Error state (INTERFACES.md), 15 states, or 21 with ``scale_factors=True``::

    dx = [dtheta (0:3), dv_n (3:6), dp (6:9), dbg (9:12), dba (12:15), dsg (15:18), dsa (18:21)]

``rot_nb_true = exp(dtheta) rot_nb``; ``dp`` in local ENU metres; biases and scale factors
are "true minus estimate". The IMU error model is that of ``polins.models.loader.ImuModel``:
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
Van Loan matrix). The step is computed from sums over its IMU intervals
(:func:`step_exponent`, :func:`van_loan`); the same functions serve the streaming filter
and the batch steps. Inside a step the reported state (``ESKF.state``, the batch path's
output rows) is the step so far with the error dynamics frozen at their mean over the
step's first IMU interval: the batch path evaluates that from polynomials in the
partial-step length (:func:`partial_step_polynomials`), once per step for all its rows.

Filtering uses ``filterpy.kalman.predict`` and ``filterpy.kalman.update`` (Joseph form).
Innovations are gated with a chi-square test (each rejection is logged with its reason) and
the normalised innovation squared (NIS) of every update is recorded.

Reset policy ("closed loop at a reduced rate"): the error estimate is injected into the
nominal state and zeroed after the first processed measurement at least
``reset_interval_s`` after the previous reset, or as soon as the attitude error estimate
exceeds ``reset_angle_rad`` (defaults 20 s and 0.005 rad: Monte-Carlo runs with
``monte_carlo`` of tests/test_eskf.py, 50 runs of 120 s and 20 runs with the non-holonomic
constraint, give the same RMS(error / sigma) to 0.05 with resets every 5, 10 or 20 s, and
longer segments make the batch path faster). Between resets the updates act on the error
state (filterpy's innovation ``z - H dx`` is then the exact first-order innovation about
the nominal), and
the reported estimate is always ``nominal (+) dx``. This lets the batch path
(:mod:`polins.fusion.batch`: ``run_batch`` for ``polins.fuse``, ``ESKF.propagate_many``
for runs of samples in streaming use) propagate the nominal state and the transition
matrices between resets with vectorised numpy; the streaming path (``ESKF.propagate``, one
IMU sample at a time, the attitude as a matrix: no Rotation objects per sample) follows
the same rule and gives the same results to rounding error (tests/test_eskf.py: 1e-9 rad,
sigmas to 1e-9 relative).

Ground-vehicle constraints: ``nhc_std`` applies the non-holonomic constraint (no lateral,
no vertical body velocity) every ``nhc_every`` IMU samples, and measurement rows with
``zupt_std`` a zero-velocity update. The non-holonomic Jacobian depends on the nominal
velocity, so its sigma must also cover the linearisation error: with a poorly known forward
velocity (no zero-velocity updates or odometry) a sigma below ~0.01 m/s makes the filter
overconfident; 0.05 m/s is a sound default for a car-like vehicle.

Smoothing: ``batch.run_batch`` with ``smooth=True`` runs the Rauch-Tung-Striebel smoother
(``batch.rts_smooth``) over the epochs where the covariance was propagated; rows between
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
the velocity with the frame, and is corrected by the alignment rotation). When the
mechanization includes the Earth rate, the levelling also gyrocompasses
(:func:`polins.ins.alignment.gyrocompass`, with the yaw error's correlation with the
gyro bias), if that yaw is better than ``GYROCOMPASS_MAX_STD``: the Earth rate is then
compensated about the right axes until the first yaw measurement (with a yaw off by
``d`` the tilt would drift by ``2 sin(d/2) Omega cos L``, up to 1e-4 rad/s). That coarse
yaw is not reported; the first measurement still sets it.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple

import numpy as np
from filterpy.kalman import predict as kf_predict
from filterpy.kalman import update as kf_update
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from polins.frames import euler_from_rot_nb, heading_deg_from_yaw, skew, wrap_angle, yaw_from_rot_nb
from polins.fusion.items import (
    MeasurementItem,
    UpdateRecord,
    gate_limit,
    item_model,
    measurement_items,
)
from polins.fusion.measurement import (
    ATT,
    BA,
    BG,
    N_ERROR,
    POS,
    VEL,
    Linearized,
    yaw_from_sun,
)
from polins.ins.alignment import gyrocompass, level_from_accel
from polins.ins.earth import OMEGA_IE, normal_gravity, normal_gravity_gradient, radii_of_curvature
from polins.ins.strapdown import (
    Mechanization,
    NavState,
    NavTrack,
    nav_rates_n,
    rotation_vectors,
    strapdown_increment,
)
from polins.models.loader import ImuModel

FloatArray = NDArray[np.float64]
log = logging.getLogger("polins.fusion")

N_DYNAMIC = 9  # attitude, velocity, position: the error states with dynamics
SG = slice(15, 18)
SA = slice(18, 21)


# ============================================================================ options
GYROCOMPASS_MAX_STD = math.radians(5.0)  # self-alignment gyrocompasses below this sigma


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
        Yaw rows with ``sun_n`` were measured by ``polins.measure`` with a prior (the
        row's ``mat_nb_prior``, default this filter's attitude): use the tilt-coupled model
        of ``yaw_measurement`` (SPEC 10.2, the coupling in ``H``).
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
    reset_interval_s: float = 20.0
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


def nav_error_dynamics(
    vel_n: ArrayLike, lat: ArrayLike, height: ArrayLike, mech: Mechanization
) -> FloatArray:
    """The blocks of ``F`` among attitude, velocity and position that depend on the
    navigation state only, ``(..., 9, 9)`` (the velocity-attitude block ``-[f_n x]`` is
    left zero; :func:`error_dynamics` adds it)."""
    v = np.asarray(vel_n, dtype=float)
    lat_a = np.asarray(lat, dtype=float)
    h = np.asarray(height, dtype=float)
    batch = v.shape[:-1]
    F = np.zeros((*batch, N_DYNAMIC, N_DYNAMIC))
    if mech.earth_rotation or mech.transport_rate:
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
        sv = skew(v)
        F[..., VEL, VEL] = -skew(2.0 * w_ie + w_en) + sv @ dwen_dv
        F[..., VEL, POS] = sv @ (2.0 * dwie_dp + dw_dp)
    F[..., VEL.start + 2, POS.start + 2] -= normal_gravity_gradient(lat_a, h)
    F[..., POS, VEL] = np.eye(3)
    return F


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
    sf = gyro_scale is not None
    if sf and (mat_omega is None or mat_force is None):
        raise ValueError("error_dynamics with scale factors needs mat_omega and mat_force")
    n = n_states(sf)
    F = np.zeros((*fn.shape[:-1], n, n))
    F[..., :N_DYNAMIC, :] = step_exponent(
        nav_error_dynamics(vel_n, lat, height, mech),
        np.ones(fn.shape[:-1]),
        mat,
        fn,
        n,
        scale_divisors(gyro_scale, accel_scale),
        mat_omega,
        mat_force,
    )
    return F


def scale_divisors(
    gyro_scale: ArrayLike | None, accel_scale: ArrayLike | None
) -> tuple[FloatArray | float, FloatArray | float]:
    """``1 / (1 + s)`` for the gyro and accelerometer scale factors (1.0 without them)."""
    dg = 1.0 if gyro_scale is None else 1.0 / (1.0 + np.asarray(gyro_scale, dtype=float))
    da = 1.0 if accel_scale is None else 1.0 / (1.0 + np.asarray(accel_scale, dtype=float))
    return dg, da


# entries of -[v x] in the velocity-attitude block: rows, columns, components, signs
_SKEW_ROW = np.array([3, 3, 4, 4, 5, 5])
_SKEW_COL = np.array([1, 2, 0, 2, 0, 1])
_SKEW_SRC = np.array([2, 1, 2, 0, 1, 0])
_SKEW_SIGN = np.array([1.0, -1.0, -1.0, 1.0, 1.0, -1.0])


def step_exponent(
    F_nav: FloatArray,
    dt: ArrayLike,
    mat_dt: ArrayLike,
    dv_force: ArrayLike,
    n: int,
    divisors: tuple[FloatArray | float, FloatArray | float],
    mat_omega_dt: ArrayLike | None = None,
    mat_force_dt: ArrayLike | None = None,
) -> FloatArray:
    """The rows with dynamics of ``A = F dt`` over a covariance step, ``(..., 9, n)``.

    ``F dt`` of :func:`error_dynamics` written with the step sums: ``F_nav dt`` from
    :func:`nav_error_dynamics`, ``-[dv_force x]`` (``dv_force = int mat_nb f_b dt``), and
    the bias (and scale-factor) columns ``-int mat_nb dt (.) d`` with ``divisors`` ``d``
    from :func:`scale_divisors` (``mat_omega_dt = int mat_nb diag(omega_b) dt``,
    ``mat_force_dt = int mat_nb diag(f_b) dt``).
    """
    F_nav = np.asarray(F_nav, dtype=float)
    t = np.asarray(dt, dtype=float)
    mat = np.asarray(mat_dt, dtype=float)
    dv = np.asarray(dv_force, dtype=float)
    dg, da = divisors
    A = np.zeros((*F_nav.shape[:-2], N_DYNAMIC, n))
    np.multiply(F_nav, t[..., None, None], out=A[..., :N_DYNAMIC])
    # -[dv x] in the velocity-attitude block
    A[..., _SKEW_ROW, _SKEW_COL] = dv[..., _SKEW_SRC] * _SKEW_SIGN
    np.multiply(mat, -dg, out=A[..., ATT, BG])
    np.multiply(mat, -da, out=A[..., VEL, BA])
    if n > N_ERROR:
        if mat_omega_dt is None or mat_force_dt is None:
            raise ValueError("scale-factor states need mat_omega_dt and mat_force_dt")
        A[..., ATT, SG] = -np.asarray(mat_omega_dt, dtype=float) * dg
        A[..., VEL, SA] = -np.asarray(mat_force_dt, dtype=float) * da
    return A


def powers(A: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``Phi(T) - I`` and ``Phi(T/2) - I`` (top rows) of ``Phi = I + A + A^2/2 + A^3/6``
    from the top rows ``A`` ``(..., k, n)`` of ``F T`` (:func:`van_loan`)."""
    A_kk = A[..., : A.shape[-2]]
    A2 = A_kk @ A
    A3 = A_kk @ A2
    top = A3 * (1.0 / 6.0)
    top += A
    top += 0.5 * A2
    half = A3 * (1.0 / 48.0)
    half += 0.5 * A
    half += 0.125 * A2
    return top, half


def van_loan(A: FloatArray, dt: ArrayLike, qc: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """:func:`discretize` from the non-zero top rows ``A = (F dt)[..., :k, :]``.

    The rows ``k..`` of ``F`` (sensor errors without dynamics) are zero, so only the top
    rows of the powers of ``A`` are non-zero: ``A^(p+1)[:k] = A[:k, :k] A^p[:k]``.
    """
    A = np.asarray(A, dtype=float)
    return van_loan_full(*powers(A), np.asarray(dt, dtype=float), np.asarray(qc, dtype=float))


def van_loan_full(
    top: FloatArray, half: FloatArray, dt: FloatArray, qc: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """``Phi`` and ``Q`` (:func:`van_loan`) from :func:`powers` (``half`` is overwritten)."""
    k, n = top.shape[-2:]
    idx = np.arange(n)
    Phi = np.zeros((*top.shape[:-2], n, n))
    Phi[..., :k, :] = top
    Phi[..., idx, idx] += 1.0
    half[..., idx[:k], idx[:k]] += 1.0  # Phi(dt/2), top rows
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


def partial_step_polynomials(
    F: FloatArray, P0: FloatArray, x0: FloatArray, qc: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """What the solution table needs after a partial step with frozen error dynamics,
    as polynomials in the step length ``tau``.

    For a step with ``A = F tau`` (``F`` the top rows ``(..., k, n)`` of the error dynamics,
    frozen), ``x(tau) = Phi x0`` and ``P(tau) = Phi P0 Phi^T + Q`` of :func:`van_loan` are
    polynomials in ``tau``: ``Phi(c tau)[:k] = sum_j (c tau)^j B_j`` with ``B_0 = [I 0]``,
    ``B_1 = F``, ``B_2 = F_kk F / 2``, ``B_3 = F_kk^2 F / 6`` (:func:`powers`), and Simpson's
    ``Q = tau / 6 (Qc + 4 Phi(tau/2) Qc Phi(tau/2)^T + Phi(tau) Qc Phi(tau)^T)``, so
    ``(Phi(c tau) M Phi(c tau)^T)[i, i'] = sum_(j, l) c^(j+l) tau^(j+l) (B_j M B_l^T)[i, i']``.

    Parameters
    ----------
    F : (..., k, n) ndarray
        Rows with dynamics of the error dynamics matrix [1/s].
    P0 : (..., n, n) ndarray
        Covariance at the step start.
    x0 : (..., n) ndarray
        Error state at the step start.
    qc : (n,) ndarray
        Process noise densities (diagonal of ``Qc``).

    Returns
    -------
    cx : (..., 4, n) ndarray
        ``x(tau) = sum_j tau^j cx[j]``.
    cv : (..., 8, n) ndarray
        ``diag P(tau) = sum_p tau^p cv[p]``.
    ca : (..., 8, 3, 3) ndarray
        ``P(tau)[:3, :3] = sum_p tau^p ca[p]`` (the attitude block).
    """
    k, n = F.shape[-2:]
    lead = F.shape[:-2]
    Fk = F[..., :k]
    FF = Fk @ F
    B = np.empty((*lead, 4, k, n))
    B[..., 0, :, :] = np.eye(k, n)
    B[..., 1, :, :] = F
    B[..., 2, :, :] = 0.5 * FF
    B[..., 3, :, :] = (Fk @ FF) * (1.0 / 6.0)
    W = np.empty((*lead, 8, k, n))  # B_j P0 (j < 4) and B_j Qc (4 + j)
    W[..., :4, :, :] = (B.reshape(*lead, 4 * k, n) @ P0).reshape(*lead, 4, k, n)
    np.multiply(B, qc, out=W[..., 4:, :, :])
    # (B_j M B_l^T)[i, i] for all (j, l): per row i, (8, n) @ (n, 4)
    d = np.swapaxes(W, -3, -2) @ np.swapaxes(B, -3, -2).swapaxes(-1, -2)  # [..., i, m, l]
    # attitude blocks (B_j M B_l^T)[:3, :3]: (24, n) @ (n, 12) -> [..., (m, a), (l, b)]
    a = W[..., :3, :].reshape(*lead, 24, n) @ np.swapaxes(
        B[..., :3, :].reshape(*lead, 12, n), -1, -2
    )
    a = np.swapaxes(a.reshape(*lead, 8, 3, 4, 3), -3, -2).reshape(*lead, 2, 16, 9)
    # collect the terms of tau^(j+l); Q: tau/6 (Qc + sum_p tau^p (1 + 4 / 2^p) [...]_p)
    cx = np.zeros((*lead, 4, n))
    cx[..., :k] = (B @ x0[..., None, :, None])[..., 0]
    cx[..., 0, k:] = x0[..., k:]
    dd = np.moveaxis(d.reshape(*lead, k, 2, 16), -3, -1)  # [..., (P | Q), (j, l), i]
    cv = np.zeros((*lead, 8, n))
    cv[..., :7, :k] = _BY_POWER @ dd[..., 0, :, :]
    cv[..., 1:, :k] += _BY_POWER_Q @ dd[..., 1, :, :]
    cv[..., 1, :k] += qc[:k] / 6.0
    cv[..., 0, k:] = np.diagonal(P0, axis1=-2, axis2=-1)[..., k:]  # no dynamics there
    cv[..., 1, k:] = qc[k:]
    ca = np.zeros((*lead, 8, 9))
    ca[..., :7, :] = _BY_POWER @ a[..., 0, :, :]
    ca[..., 1:, :] += _BY_POWER_Q @ a[..., 1, :, :]
    ca[..., 1, (0, 4, 8)] += qc[:3] / 6.0
    return cx, cv, ca.reshape(*lead, 8, 3, 3)


# (7, 16): the pair (j, l) (flat index 4 j + l) contributes to the power p = j + l; for Q
# with Simpson's weight (1 + 4 / 2^p) / 6 (it multiplies the power p + 1 of tau)
_PAIR_POWER = np.add.outer(np.arange(4), np.arange(4)).ravel()
_BY_POWER = (np.arange(7)[:, None] == _PAIR_POWER).astype(float)
_BY_POWER_Q = _BY_POWER * ((1.0 + 4.0 / 2.0 ** np.arange(7)) / 6.0)[:, None]


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
    n = F.shape[-1]
    k = N_DYNAMIC if n >= N_DYNAMIC and not np.any(F[..., N_DYNAMIC:, :]) else n
    return van_loan(F[..., :k, :] * dt[..., None, None], dt, qc)


def euler_jacobian(rot_nb: Rotation) -> FloatArray:
    """``d(yaw, pitch, roll) / d dtheta`` for the navigation-frame attitude error, ``(..., 3, 3)``.

    For ``rot_nb = Rz(yaw) Ry(pitch) Rx(roll)``, ``dtheta = E d(yaw, pitch, roll)`` with
    ``E = [z, Rz(yaw) y, Rz(yaw) Ry(pitch) x]``; the result is ``E^-1``.
    """
    yaw, pitch, _ = euler_from_rot_nb(rot_nb)
    return _euler_jacobian(yaw, pitch)


def _euler_jacobian(yaw: FloatArray, pitch: FloatArray) -> FloatArray:
    """:func:`euler_jacobian` from the angles: ``E^-1`` in closed form,
    ``[[tan(p) cos(y), tan(p) sin(y), 1], [-sin(y), cos(y), 0], [cos(y), sin(y), 0] / cos(p)]``.
    """
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    J = np.zeros((*np.shape(yaw), 3, 3))
    J[..., 0, 0], J[..., 0, 1], J[..., 0, 2] = sp * cy / cp, sp * sy / cp, 1.0
    J[..., 1, 0], J[..., 1, 1] = -sy, cy
    J[..., 2, 0], J[..., 2, 1] = cy / cp, sy / cp
    return J


# ============================================================================ measurements
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
    J = _euler_jacobian(yaw, pitch)
    std = np.sqrt(np.clip(((J @ P_diag_att) * J).sum(axis=-1), 0.0, None))  # diag(J P J^T)
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
    # (dt, mat, dv, mat_omega, mat_force) of the step's first interval: the error dynamics
    # of a partial step (ESKF.state) are frozen at their mean over it
    first: tuple[float, FloatArray, FloatArray, FloatArray, FloatArray] | None = None


class _Nominal(NamedTuple):
    """Nominal navigation state as arrays (attitude as the matrix ``mat_nb``)."""

    t: float
    mat_nb: FloatArray
    vel_n: FloatArray
    lat: float
    lon: float
    height: float


_MIN_BATCH = 16  # propagate_many: fewer samples go through propagate one by one


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
    ``propagate_many(t, gyro_b, accel_b)`` consumes a run of samples at once (vectorised)
    with the same result as one ``propagate`` per sample; ``polins.fusion.batch.run_batch``
    runs a whole log through a fresh filter with the same results.
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
        self._nav_cache: NavState | None = None
        self._nom = _Nominal(float(t0), rot.as_matrix(), v0, float(lat), float(lon), float(height))
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
        duration = max(samples[-1][0] - samples[0][0], 1.0 / max(self.model.sample_rate_hz, 1.0))
        P = self.P.copy()
        P[ATT, :] = 0.0
        P[:, ATT] = 0.0
        yaw_var = 1.0  # yaw unknown until the first yaw measurement
        if self.options.mech.earth_rotation:
            # Gyrocompass so that the Earth rate is compensated about the right axes until
            # then (polins.ins.alignment); the yaw is still reported from that measurement.
            yaw0, j_bg = gyrocompass(gyro.mean(axis=0), rot, self.nav.lat)
            var = j_bg @ P[BG, BG] @ j_bg + (self.model.gyro_arw**2 / duration) * (j_bg @ j_bg)
            if var < GYROCOMPASS_MAX_STD**2:
                rot = Rotation.from_rotvec([0.0, 0.0, yaw0]) * rot
                yaw_var = float(var)
                P[2, BG] = j_bg @ P[BG, BG]
                P[BG, 2] = P[2, BG]
            else:
                log.warning(
                    "self-alignment: the gyro bias (%.3g deg/h) is too large to gyrocompass "
                    "(yaw sigma %.1f deg); with the Earth rate mechanized the tilt drifts "
                    "by up to %.2g rad/s until the first yaw measurement",
                    np.degrees(self.model.gyro_bias) * 3600.0,
                    np.degrees(math.sqrt(var)),
                    2.0 * OMEGA_IE * math.cos(self.nav.lat),
                )
        self.nav = replace(self.nav, rot_nb=rot, vel_n=np.zeros(3))
        # Tilt error = J dba exactly (a horizontal bias tilts the level by b/g), plus the
        # averaged white noise of the accelerometer.
        J = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0]]) @ rot.as_matrix() / g
        p_ba = P[BA, BA]
        noise = (self.model.accel_vrw / g) ** 2 / duration
        P[0:2, 0:2] = J @ p_ba @ J.T + np.eye(2) * noise
        P[0:2, BA] = J @ p_ba
        P[BA, 0:2] = (J @ p_ba).T
        P[2, 2] = yaw_var
        P[VEL, VEL] = np.eye(3) * self.options.vel_std0**2
        self.P = P

    # ------------------------------------------------------------------ nominal state
    # The nominal state is held as arrays (``_nom``, attitude as a matrix: no Rotation
    # objects per IMU sample); ``nav`` builds the NavState on demand.
    @property
    def t(self) -> float:
        """Current filter time [s]."""
        return float(self._nom.t)

    @property
    def nav(self) -> NavState:
        """Nominal navigation state (the estimate is ``nominal (+) x``)."""
        if self._nav_cache is None:
            nom = self._nom
            self._nav_cache = NavState(
                float(nom.t),
                Rotation.from_matrix(nom.mat_nb, assume_valid=True),
                np.array(nom.vel_n, dtype=float),
                float(nom.lat),
                float(nom.lon),
                float(nom.height),
            )
        return self._nav_cache

    @nav.setter
    def nav(self, value: NavState) -> None:
        self._nav_cache = value
        self._nom = _Nominal(
            value.t,
            value.rot_nb.as_matrix(),
            np.asarray(value.vel_n, dtype=float),
            value.lat,
            value.lon,
            value.height,
        )

    def _set_track(self, track: NavTrack, i: int) -> None:
        """Batch path: the nominal state is sample ``i`` of ``track``."""
        self._nav_cache = None
        self._nom = _Nominal(
            track.t[i], track.mat_nb[i], track.vel_n[i], track.lat[i], track.lon[i], track.height[i]
        )

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
        if (
            w.shape != (3,)
            or f.shape != (3,)
            or not (np.isfinite(w).all() and np.isfinite(f).all() and math.isfinite(t))
        ):
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

    def propagate_many(
        self, t: ArrayLike, gyro_b: ArrayLike, accel_b: ArrayLike
    ) -> list[UpdateRecord]:
        """Consume a run of IMU samples: the same as :meth:`propagate` for each sample.

        Runs the batch machinery (:func:`polins.fusion.batch.advance`: the nominal state
        propagated with vectorised numpy between resets, the covariance in block
        transitions between measurement epochs, filterpy ``predict``/``update`` at the
        epochs) and leaves the filter in the state that one :meth:`propagate` call per
        sample would (to rounding error; a covariance step in progress carries over to the
        next call). With a ``sample_hook`` (which must see every sample) or for a few
        samples, it calls :meth:`propagate` per sample.

        Parameters
        ----------
        t : (N,) array_like
            Sample times [s], strictly increasing, after the last consumed sample.
        gyro_b, accel_b : (N, 3) array_like
            Raw body rates [rad/s] and specific forces [m/s^2].

        Returns
        -------
        list of UpdateRecord
            Records of the measurements applied during this call.
        """
        t_a = np.asarray(t, dtype=float)
        W = np.asarray(gyro_b, dtype=float)
        A = np.asarray(accel_b, dtype=float)
        N = t_a.shape[0] if t_a.ndim == 1 else -1
        if N < 0 or W.shape != (N, 3) or A.shape != (N, 3):
            raise ValueError(
                f"propagate_many needs t (N,), gyro_b and accel_b (N, 3); got shapes "
                f"{t_a.shape}, {W.shape}, {A.shape}"
            )
        if not (np.isfinite(t_a).all() and np.isfinite(W).all() and np.isfinite(A).all()):
            raise ValueError("gyro_b and accel_b must be finite 3-vectors [rad/s], [m/s^2]")
        if N > 1 and not np.all(np.diff(t_a) > 0):
            k = int(np.flatnonzero(np.diff(t_a) <= 0)[0])
            raise ValueError(f"IMU time {t_a[k + 1]} is not after the previous sample {t_a[k]}")
        n_before = len(self.records)
        k = 0
        if self.sample_hook is not None or N < _MIN_BATCH:
            for k in range(N):
                self.propagate(t_a[k], W[k], A[k])
            return self.records[n_before:]
        buffered = self._align_buffer
        last = self._real if buffered is None else (buffered[-1] if buffered else None)
        if last is not None and t_a[0] <= last[0]:
            raise ValueError(f"IMU time {t_a[0]} is not after the previous sample {last[0]}")
        if self._align_buffer is not None:
            # Levelling: buffer samples until the window is complete, then run the batch
            # from the first buffered sample (as propagate replays the buffer).
            tol = self.options.time_tol
            if not self._align_buffer and abs(t_a[0] - self._t0) > tol:
                raise ValueError(f"the first IMU sample must be at t0={self._t0}, got {t_a[0]}")
            k = int(np.searchsorted(t_a - self._t0, self.options.align_s - tol, side="left"))
            if k >= N:
                self._align_buffer += [(float(t_a[i]), W[i].copy(), A[i].copy()) for i in range(N)]
                return []
            buffer, self._align_buffer = self._align_buffer, None
            buffer = buffer + [(float(t_a[i]), W[i].copy(), A[i].copy()) for i in range(k + 1)]
            self._level([s for s in buffer if s[0] - self._t0 <= self.options.align_s + tol])
            t_a = np.concatenate([[s[0] for s in buffer], t_a[k + 1 :]])
            W = np.concatenate([np.array([s[1] for s in buffer]), W[k + 1 :]])
            A = np.concatenate([np.array([s[2] for s in buffer]), A[k + 1 :]])
        from polins.fusion.batch import advance

        advance(self, t_a, W, A)
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
        rot_nb_prior: Rotation | None = None,
    ) -> list[UpdateRecord]:
        """Queue (or apply now, if ``t`` is the current time) one measurement row.

        Parameters are the ``measurements`` DataFrame columns (CONVENTIONS.md): a yaw and its
        1-sigma [rad]; and/or a measured body sun vector, its ENU reference and direction
        1-sigma [rad]; and/or a zero-velocity 1-sigma [m/s]; ``rot_nb_prior`` is the prior
        ``polins.measure`` used for the yaw (tilt coupling; default the filter's own state). A measurement older than the
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
            rot_nb_prior=rot_nb_prior,
        )
        return self.add_items(items)

    def add_items(self, items: Sequence[MeasurementItem]) -> list[UpdateRecord]:
        """Queue measurement items (see :meth:`add_measurement`)."""
        n_before = len(self.records)
        tol = self.options.time_tol
        started = self._cur is not None and self.ready
        queued = False
        for item in items:
            if started and item.t < self.t - tol:
                reason = f"out of sequence: t={item.t} is before the filter time {self.t}"
                self._record(item, 0, math.nan, False, reason)
            elif started and abs(item.t - self.t) <= tol and not self._pending:
                self._apply(item)
            else:
                self._pending.append(item)
                queued = True
        if queued:
            self._pending.sort(key=lambda it: it.order)
        return self.records[n_before:]

    def state(self) -> FilterState:
        """Current estimate ``nominal (+) x`` with the error covariance.

        Inside a covariance step the error state and covariance are propagated over the
        step so far with the error dynamics frozen at their mean over the step's first
        IMU interval (the step itself, once complete, uses its mean over the whole step).
        The batch path reports the same, from polynomials in the step length
        (:func:`partial_step_polynomials`).
        """
        if not self.ready:
            raise RuntimeError(
                "the filter is still levelling (self-alignment); feed more IMU samples"
            )
        x, P = self.x, self.P
        if self._sums.n:
            Phi, Q = self._step_matrices(self._sums, partial=True)
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
        nom = self._nom
        lin = item_model(item, nom.mat_nb, nom.vel_n, self.options.tilt_coupling)
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
            if abs(t - self._t0) > tol:
                raise ValueError(f"the first IMU sample must be at t0={self._t0}, got {t}")
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
        nom = self._nom
        mat1, v1, lat1, lon1, h1, mat, dv_force = strapdown_increment(
            nom.mat_nb, nom.vel_n, nom.lat, nom.lon, nom.height, wc0, wc1, fc0, fc1, dt,
            self.options.mech,
        )  # fmt: skip
        sums = self._sums
        mat_dt = mat * dt
        if self.n > N_ERROR:
            phi, _ = rotation_vectors(wc0, wc1, dt)
            mat_omega, mat_force = mat * phi, mat * (0.5 * (fc0 + fc1) * dt)
            sums.mat_omega += mat_omega
            sums.mat_force += mat_force
        if sums.n == 0:
            sums.vel_n, sums.lat, sums.height = nom.vel_n, nom.lat, nom.height
            sums.first = (dt, mat_dt, dv_force, sums.mat_omega.copy(), sums.mat_force.copy())
        sums.n += 1
        sums.dt += dt
        sums.mat += mat_dt
        sums.dv += dv_force
        self._nom = _Nominal(t1, mat1, v1, lat1, lon1, h1)
        self._nav_cache = None
        self._cur = (t1, w1, f1)
        if sums.n >= self.options.cov_every:
            self._flush()

    def _divisors(self) -> tuple[FloatArray | float, FloatArray | float]:
        """``1 / (1 + s)`` of the current scale-factor estimates (:func:`scale_divisors`)."""
        return scale_divisors(self.sg, self.sa) if self.n > N_ERROR else (1.0, 1.0)

    def _step_matrices(
        self, sums: _StepSums, partial: bool = False
    ) -> tuple[FloatArray, FloatArray]:
        """Transition and noise of a covariance step from its sums; ``partial``: of the step
        so far, with the error dynamics frozen at their mean over its first interval (what
        :meth:`state` reports inside a step)."""
        F_nav = nav_error_dynamics(sums.vel_n, sums.lat, sums.height, self.options.mech)
        dt, mat, dv, mat_omega, mat_force = (
            sums.first if partial and sums.first is not None
            else (sums.dt, sums.mat, sums.dv, sums.mat_omega, sums.mat_force)
        )  # fmt: skip
        A = step_exponent(F_nav, dt, mat, dv, self.n, self._divisors(), mat_omega, mat_force)
        if partial:
            A *= sums.dt / dt
        return van_loan(A, sums.dt, self.qc)

    def _flush(self) -> None:
        """Propagate the covariance over the step in progress (filterpy ``predict``)."""
        if self._sums.n:
            Phi, Q = self._step_matrices(self._sums)
            self.x, self.P = kf_predict(self.x, self.P, Phi, Q)
            self._sums = _StepSums()
            # keep the attitude matrix orthonormal (rounding of the per-sample products)
            nom = self._nom
            mat = Rotation.from_matrix(nom.mat_nb, assume_valid=True).as_matrix()
            self._nom = nom._replace(mat_nb=mat)
            self._nav_cache = None

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
        H, dim = lin.H, lin.residual.shape[0]
        y = lin.residual - H @ self.x
        S = H @ (self.P @ H.T) + lin.R
        nis = float(y[0] * y[0] / S[0, 0]) if dim == 1 else float(y @ np.linalg.solve(S, y))
        gate = self.options.gate_prob
        limit = gate_limit(gate, dim)
        if nis > limit:
            reason = f"NIS {nis:.3g} > gate {limit:.3g} (chi2, {dim} dof, p={gate})"
            self._record(item, dim, nis, False, reason)
        else:
            x_before = self.x
            self.x, self.P = kf_update(self.x, self.P, lin.residual, lin.R, H)
            if self._track_dx:
                self._dx_epoch = self._dx_epoch + (self.x - x_before)
            self._record(item, dim, nis, True, "")
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
            # The yaw that makes the residual of the measurement model zero: one step for
            # the yaw of body x (exact), three Newton steps with the tilt coupling (the
            # model then depends on the tilt of the prior).
            delta, std = 0.0, item.std
            coupled = self.options.tilt_coupling and item.sun_n is not None
            for _ in range(3 if coupled else 1):
                self.nav = replace(nav, rot_nb=Rotation.from_rotvec([0.0, 0.0, delta]) * nav.rot_nb)
                lin = self.linearize(item)
                delta += float(lin.residual[0] / lin.H[0, 2])
            self.nav = nav
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
# The batch path lives in polins.fusion.batch (it imports this module); these names are
# re-exported lazily for compatibility.
_BATCH_NAMES = ("BatchOutput", "block_transitions", "rts_smooth", "run_batch")


def __getattr__(name: str) -> Any:
    if name in _BATCH_NAMES:
        from polins.fusion import batch

        return getattr(batch, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
