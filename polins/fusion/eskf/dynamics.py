"""Continuous error dynamics of the strapdown navigation and their discretisation (Van Loan).

The error state (docs/filter.md) is ``dtheta`` (attitude, ``rot_nb_true = exp(dtheta)
rot_nb``), ``dv_n``, ``dp`` (local ENU metres) and the sensor-error blocks
(:mod:`polins.fusion.eskf.blocks`), all "true minus estimate". The navigation part
(``phi``-angle form; Titterton & Weston 2004 Sec. 12.2; Groves 2013 Sec. 14.2.4)::

    dtheta' = -w_in x dtheta - dw_in(dv, dp) - C D_g (dbg + w (.) dsg) - C n_g
    dv'     = -f_n x dtheta - (2 w_ie + w_en) x dv + v x (2 dw_ie + dw_en) + dg(dp)
              - C D_a (dba + f (.) dsa) - C n_a
    dp'     = dv

with ``C = mat_nb`` and ``D = diag(1 / (1 + s))``. Over a covariance step (at most
``cov_step_s``, ending early at measurement times) the attitude-dependent terms use their
means over the step (:class:`StepNominal`: the first Magnus term of the time-varying
``F``) and the Earth terms their values at the step start. The step is discretised as
``Phi = exp(F T)`` (series to third order) and ``Q = int_0^T Phi(s) Qc Phi(s)^T ds`` by
Simpson's rule (:func:`discretize`; tests/test_eskf.py checks both against
``scipy.linalg.expm`` of the Van Loan matrix).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from polins.frames import skew
from polins.ins.earth import OMEGA_IE, normal_gravity_gradient, radii_of_curvature
from polins.ins.strapdown import Mechanization, nav_rates_n, rotation_vectors

FloatArray = NDArray[np.float64]

NAV = 9  # attitude, velocity, position: the error states of the navigation dynamics


@dataclass
class StepSums:
    """Sums over the IMU intervals of the covariance step in progress (streaming)."""

    n: int = 0
    dt: float = 0.0
    mat: FloatArray = field(default_factory=lambda: np.zeros((3, 3)))  # sum C dt
    dv: FloatArray = field(default_factory=lambda: np.zeros(3))  # sum int C f dt
    mat_omega: FloatArray = field(default_factory=lambda: np.zeros((3, 3)))  # sum C diag(phi)
    mat_force: FloatArray = field(default_factory=lambda: np.zeros((3, 3)))  # sum C diag(f) dt
    rate_sq: float = 0.0  # sum |omega_b|^2 dt [rad^2/s]
    start: tuple[FloatArray, float, float] = (np.zeros(3), 0.0, 0.0)  # vel, lat, alt

    def add(
        self,
        start: tuple[FloatArray, float, float],
        mat_h: FloatArray,
        dv_force_n: FloatArray,
        gyro_b: tuple[FloatArray, FloatArray],
        accel_b: tuple[FloatArray, FloatArray],
        dt: float,
        *,
        scale_factors: bool,
        rate_noise: bool,
    ) -> None:
        """One IMU interval of ``dt`` [s]: its mid-interval attitude ``mat_h``, its
        velocity increment ``dv_force_n`` [m/s] and the corrected samples at its ends
        ``gyro_b`` [rad/s], ``accel_b`` [m/s^2]; ``start`` (velocity, latitude, height at
        the interval's start) is kept for the step's first interval. ``scale_factors``:
        the scale-factor sums; ``rate_noise``: the rotation-proportional noise's."""
        (wc0, wc1), (fc0, fc1) = gyro_b, accel_b
        if self.n == 0:
            self.start = start
        if scale_factors:
            phi, _ = rotation_vectors(wc0, wc1, dt)
            self.mat_omega += mat_h * phi
            self.mat_force += mat_h * (0.5 * (fc0 + fc1) * dt)
        self.n += 1
        self.dt += dt
        if rate_noise:
            self.rate_sq += float(np.sum((0.5 * (wc0 + wc1)) ** 2)) * dt
        self.mat += mat_h * dt
        self.dv += dv_force_n

    def nominal(
        self, mech: Mechanization, divisors: tuple[FloatArray, FloatArray], scale_factors: bool
    ) -> StepNominal:
        """The :class:`StepNominal` of the step so far (one step)."""
        vel, lat, alt = self.start
        return step_nominal(
            np.array([self.dt]), self.mat[None], self.dv[None], vel[None], np.array([lat]),
            np.array([alt]), mech, divisors,
            self.mat_omega[None] if scale_factors else None,
            self.mat_force[None] if scale_factors else None, np.array([self.rate_sq]),
        )  # fmt: skip


@dataclass(eq=False)
class StepNominal:
    """The nominal quantities of covariance steps that the error dynamics need (S steps).

    Attributes
    ----------
    dt : (S,) ndarray
        Step length [s].
    mat_nb : (S, 3, 3) ndarray
        Mean attitude matrix over the step.
    force_n : (S, 3) ndarray
        Mean specific force in ENU [m/s^2].
    vel_n : (S, 3) ndarray
        ENU velocity at the step start [m/s].
    lat, alt_m : (S,) ndarray
        Latitude [rad] and height [m] at the step start.
    mech : Mechanization
        Earth terms of the strapdown.
    gyro_divisor, accel_divisor : (3,) ndarray
        ``1 / (1 + s)`` of the estimated scale factors (ones without them).
    mat_omega, mat_force : (S, 3, 3) ndarray or None
        Means of ``mat_nb diag(omega_b)`` [rad/s] and ``mat_nb diag(f_b)`` [m/s^2] (the
        scale-factor columns), with the corrected rate and specific force.
    rate_sq : (S,) ndarray or None
        Mean of ``|omega_b|^2`` over the step [rad^2/s^2] (the rotation-proportional
        attitude noise, docs/filter.md); None: zero.
    """

    dt: FloatArray
    mat_nb: FloatArray
    force_n: FloatArray
    vel_n: FloatArray
    lat: FloatArray
    alt_m: FloatArray
    mech: Mechanization
    gyro_divisor: FloatArray
    accel_divisor: FloatArray
    mat_omega: FloatArray | None = None
    mat_force: FloatArray | None = None
    rate_sq: FloatArray | None = None
    _f_nav: FloatArray | None = field(default=None, repr=False)

    @property
    def f_nav(self) -> FloatArray:
        """:func:`nav_error_dynamics` of the steps, ``(S, 9, 9)`` (computed once)."""
        if self._f_nav is None:
            self._f_nav = nav_error_dynamics(self.vel_n, self.lat, self.alt_m, self.mech)
        return self._f_nav


def step_nominal(
    dt: FloatArray,
    mat_dt: FloatArray,
    dv_force_n: FloatArray,
    vel_n: FloatArray,
    lat: FloatArray,
    alt_m: FloatArray,
    mech: Mechanization,
    divisors: tuple[FloatArray, FloatArray],
    mat_omega_dt: FloatArray | None = None,
    mat_force_dt: FloatArray | None = None,
    rate_sq_dt: FloatArray | None = None,
) -> StepNominal:
    """A :class:`StepNominal` from the sums over the IMU intervals of each step.

    ``mat_dt = sum mat_nb_mid dt``, ``dv_force_n = sum int mat_nb f_b dt`` [m/s],
    ``mat_omega_dt = sum mat_nb_mid diag(phi)`` (``phi`` the interval's rotation vector)
    and ``mat_force_dt = sum mat_nb_mid diag(f_b) dt``, ``rate_sq_dt = sum |omega_b|^2 dt``
    [rad^2/s]; ``vel_n, lat, alt_m`` at the step starts.
    """
    inv = 1.0 / dt
    sf = mat_omega_dt is not None and mat_force_dt is not None
    return StepNominal(
        dt=dt,
        mat_nb=mat_dt * inv[:, None, None],
        force_n=dv_force_n * inv[:, None],
        vel_n=vel_n,
        lat=lat,
        alt_m=alt_m,
        mech=mech,
        gyro_divisor=divisors[0],
        accel_divisor=divisors[1],
        mat_omega=mat_omega_dt * inv[:, None, None] if sf else None,  # type: ignore[operator]
        mat_force=mat_force_dt * inv[:, None, None] if sf else None,  # type: ignore[operator]
        rate_sq=None if rate_sq_dt is None else rate_sq_dt * inv,
    )


def nav_error_dynamics(
    vel_n: ArrayLike, lat: ArrayLike, alt_m: ArrayLike, mech: Mechanization
) -> FloatArray:
    """The blocks of ``F`` among attitude, velocity and position that depend on the
    navigation state only, ``(..., 9, 9)`` (the velocity-attitude block ``-[f_n x]`` is
    left zero; the attitude block adds it)."""
    v = np.asarray(vel_n, dtype=float)
    lat_a = np.asarray(lat, dtype=float)
    h = np.asarray(alt_m, dtype=float)
    batch = v.shape[:-1]
    F = np.zeros((*batch, NAV, NAV))
    if mech.earth_rotation or mech.transport_rate:
        w_ie, w_en = nav_rates_n(lat_a, h, v, mech)
        F[..., 0:3, 0:3] = -skew(w_ie + w_en)
        r_m, r_n = radii_of_curvature(lat_a)
        rmh, rnh = r_m + h, r_n + h
        dwen_dv = np.zeros((*batch, 3, 3))
        dw_dp = np.zeros((*batch, 3, 3))  # d(w_en)/dp
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
        F[..., 0:3, 3:6] = -dwen_dv
        F[..., 0:3, 6:9] = -(dw_dp + dwie_dp)
        sv = skew(v)
        F[..., 3:6, 3:6] = -skew(2.0 * w_ie + w_en) + sv @ dwen_dv
        F[..., 3:6, 6:9] = sv @ (2.0 * dwie_dp + dw_dp)
    F[..., 5, 8] -= normal_gravity_gradient(lat_a, h)
    F[..., 6:9, 3:6] = np.eye(3)
    return F


def discretize(F: ArrayLike, dt: ArrayLike, qc: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Transition matrix and process noise of steps of constant dynamics, vectorised.

    ``Phi = I + A + A^2/2 + A^3/6`` with ``A = F dt`` (the neglected terms are below 1e-8
    relative for steps up to 0.1 s) and the Van Loan integral
    ``Q = int_0^dt Phi(s) Qc Phi(s)^T ds`` by Simpson's rule,
    ``Q = dt/6 (Qc + 4 Phi(dt/2) Qc Phi(dt/2)^T + Phi Qc Phi^T)``.

    Parameters
    ----------
    F : (..., n, n) array_like
        Continuous error dynamics [1/s].
    dt : (...) array_like
        Step length [s].
    qc : (n,) or (..., n) array_like
        Diagonal of the continuous process-noise density (one, or one per step).

    Returns
    -------
    Phi, Q : (..., n, n) ndarray
    """
    dt = np.asarray(dt, dtype=float)
    qc = np.asarray(qc, dtype=float)
    A = np.asarray(F, dtype=float) * dt[..., None, None]
    n = A.shape[-1]
    # rows without dynamics (sensor errors) stay those of I in Phi: only the rows r with
    # dynamics are computed, A^(p+1)[r] = A[r, r] A^p[r]
    r = np.flatnonzero(np.any(A.reshape(-1, n, n), axis=(0, 2)))
    Ar = A[..., r, :]
    Arr = Ar[..., r]
    A2 = Arr @ Ar
    A3 = Arr @ A2
    eye = np.eye(n)
    Phi = np.broadcast_to(eye, A.shape).copy()
    half = Phi.copy()  # Phi(dt/2)
    Phi[..., r, :] += Ar + 0.5 * A2 + A3 * (1.0 / 6.0)
    half[..., r, :] += 0.5 * Ar + 0.125 * A2 + A3 * (1.0 / 48.0)
    # Simpson: Q = dt/6 (Qc + 4 Phi(dt/2) Qc Phi(dt/2)^T + Phi Qc Phi^T); in the rows and
    # columns without dynamics the terms are those of I (6 Qc on the diagonal)
    qc_row = qc[..., None, :]
    Qr = (Phi[..., r, :] * qc_row) @ np.swapaxes(Phi, -1, -2)
    Qr += 4.0 * (half[..., r, :] * qc_row) @ np.swapaxes(half, -1, -2)
    Q = np.zeros(A.shape)
    diag = np.arange(n)
    Q[..., diag, diag] = 6.0 * qc
    Q[..., r, :] = Qr
    Q[..., :, r] = np.swapaxes(Qr, -1, -2)
    Q[..., r, r] += qc[..., r]
    Q *= dt[..., None, None] / 6.0
    return Phi, Q
