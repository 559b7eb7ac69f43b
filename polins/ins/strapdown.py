"""Strapdown inertial navigation in the local ENU frame with geodetic position.

State: attitude ``rot_nb`` (body FLU -> ENU, scipy ``Rotation``), ENU velocity relative to
the Earth ``vel_n`` [m/s], geodetic latitude, longitude [rad] and height [m] (WGS-84,
``polins.ins.earth``). The continuous equations (Titterton & Weston 2004, Eq. 3.39-3.41;
Groves 2013, Eq. 5.53-5.56) are::

    d(mat_nb)/dt = mat_nb [omega_ib_b x] - [omega_in_n x] mat_nb,
                   omega_in_n = omega_ie_n + omega_en_n (Earth rate + transport rate)
    d(vel_n)/dt  = mat_nb f_b - (2 omega_ie_n + omega_en_n) x vel_n + g_n
    d(lat)/dt = v_N / (R_M + h),  d(lon)/dt = v_E / ((R_N + h) cos lat),  dh/dt = v_U

IMU samples are instantaneous rates ``omega_ib_b(t_k)`` and specific forces ``f_b(t_k)``
that vary linearly in time between samples (INTERFACES.md). One step from ``t_k`` to
``t_{k+1} = t_k + T`` (:func:`strapdown_step`):

* body rotation vector with the coning term of linear rates (Bortz equation, to second
  order): ``phi = (w_k + w_{k+1}) T/2 + T^2/12 w_k x w_{k+1}``; and at mid-interval
  ``phi_h = (3 w_k + w_{k+1}) T/8 + T^2/96 w_k x w_{k+1}``;
* navigation-frame rotation ``zeta = omega_in_n(t_k) T`` (exact for a constant rate):
  ``rot_nb(t_{k+1}) = exp(-zeta) rot_nb(t_k) exp(phi)``;
* velocity: Simpson's rule on ``mat_nb(t) f_b(t)`` using the exact attitude at
  ``t_k, t_k + T/2, t_{k+1}`` (this is the sculling / rotation correction, to fourth order),
  plus gravity and Coriolis at ``t_k``;
* position: trapezoid on the velocity, radii of curvature at ``t_k``.

:func:`strapdown` does the same steps for a whole block of samples with vectorised numpy
(prefix products of the rotation increments and a fixed-point iteration for the weak
coupling through gravity, Coriolis and transport rate); it matches repeated
:func:`strapdown_step` to rounding error (tests/test_ins.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from polins.ins.earth import (
    earth_rate_n,
    normal_gravity,
    radii_of_curvature,
    transport_rate_n,
)
from polins.models.loader import ImuModel

FloatArray = NDArray[np.float64]


def cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """``np.cross`` over the last axis, written out (several times faster for small arrays)."""
    return np.stack(
        [
            a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0],
        ],
        axis=-1,
    )


@dataclass(frozen=True)
class Mechanization:
    """Which Earth terms the strapdown equations include.

    Attributes
    ----------
    earth_rotation : bool
        Earth rate ``omega_ie_n`` in the attitude update and the Coriolis term.
    transport_rate : bool
        Transport rate ``omega_en_n`` (rotation of ENU over the ellipsoid) in the attitude
        update and the Coriolis term.
    """

    earth_rotation: bool = True
    transport_rate: bool = True

    @classmethod
    def from_imu_model(cls, model: ImuModel) -> Mechanization:
        """Both terms on for ``model.earth_rate`` (navigation grade), both off otherwise."""
        return cls(earth_rotation=model.earth_rate, transport_rate=model.earth_rate)


@dataclass(frozen=True, eq=False)
class NavState:
    """Nominal navigation state at time ``t``.

    Attributes
    ----------
    t : float
        Time [s].
    rot_nb : Rotation
        Attitude, body FLU -> ENU.
    vel_n : (3,) ndarray
        ENU velocity relative to the Earth [m/s].
    lat, lon : float
        Geodetic latitude and longitude [rad].
    height : float
        Height above the WGS-84 ellipsoid [m].
    """

    t: float
    rot_nb: Rotation
    vel_n: FloatArray
    lat: float
    lon: float
    height: float


@dataclass(frozen=True, eq=False)
class NavTrack:
    """Nominal navigation states at many times (the output of :func:`strapdown`).

    ``mat_nb`` ``(N, 3, 3)`` is the attitude as matrices (``Rotation.from_matrix`` gives
    the rotations); the other fields are as in :class:`NavState` with a leading axis N.
    Per interval (N - 1): ``mat_nb_mid`` the mid-interval attitude and ``dv_force_n`` the
    specific-force velocity increment (as in :func:`strapdown_step_detail`).
    """

    t: FloatArray
    mat_nb: FloatArray
    vel_n: FloatArray
    lat: FloatArray
    lon: FloatArray
    height: FloatArray
    mat_nb_mid: FloatArray
    dv_force_n: FloatArray

    @property
    def rot_nb(self) -> Rotation:
        """Attitudes as a stacked ``Rotation``."""
        return Rotation.from_matrix(self.mat_nb)

    def state(self, i: int) -> NavState:
        """The i-th state as a :class:`NavState`."""
        return NavState(
            t=float(self.t[i]),
            rot_nb=Rotation.from_matrix(self.mat_nb[i]),
            vel_n=self.vel_n[i].copy(),
            lat=float(self.lat[i]),
            lon=float(self.lon[i]),
            height=float(self.height[i]),
        )


def rotation_vectors(
    omega0_b: ArrayLike, omega1_b: ArrayLike, dt: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """Coning-corrected body rotation vectors over a sample interval and its first half.

    For a body rate varying linearly from ``omega0_b`` to ``omega1_b`` over ``dt``, the
    Bortz equation to second order gives the rotation vector over ``[0, dt]`` and over
    ``[0, dt/2]``:
    ``phi = (w0 + w1) dt/2 + dt^2/12 w0 x w1``,
    ``phi_h = (3 w0 + w1) dt/8 + dt^2/96 w0 x w1``.

    Parameters
    ----------
    omega0_b, omega1_b : (..., 3) array_like
        Body rates at the start and end of the interval [rad/s].
    dt : (...) array_like
        Interval length [s].

    Returns
    -------
    phi, phi_half : (..., 3) ndarray
        Rotation vectors [rad] (``exp(phi)`` maps body(t+dt) to body(t)).
    """
    w0 = np.asarray(omega0_b, dtype=float)
    w1 = np.asarray(omega1_b, dtype=float)
    t = np.asarray(dt, dtype=float)[..., None]
    coning = cross(w0, w1) * (t * t)
    phi = (w0 + w1) * (0.5 * t) + coning / 12.0
    phi_half = (3.0 * w0 + w1) * (0.125 * t) + coning / 96.0
    return phi, phi_half


def nav_rates_n(
    lat: ArrayLike, height: ArrayLike, vel_n: ArrayLike, mech: Mechanization
) -> tuple[FloatArray, FloatArray]:
    """Earth rate and transport rate in ENU ``(omega_ie_n, omega_en_n)``, zero when disabled."""
    v = np.asarray(vel_n, dtype=float)
    w_ie = earth_rate_n(lat) if mech.earth_rotation else np.zeros(v.shape)
    w_en = transport_rate_n(lat, height, v) if mech.transport_rate else np.zeros(v.shape)
    return w_ie, w_en


def strapdown_increment(
    mat_nb: FloatArray,
    vel_n: FloatArray,
    lat: float,
    lon: float,
    height: float,
    omega0_b: FloatArray,
    omega1_b: FloatArray,
    f0_b: FloatArray,
    f1_b: FloatArray,
    dt: float,
    mech: Mechanization,
) -> tuple[FloatArray, FloatArray, float, float, float, FloatArray, FloatArray]:
    """One strapdown interval (the module docstring's step) on plain arrays.

    The same step as :func:`strapdown_step_detail` with the attitude as a rotation matrix
    (no ``Rotation`` objects per sample: the streaming filter calls this once per IMU
    sample). The rotation increments come from ``Rotation.from_rotvec``.

    Parameters
    ----------
    mat_nb : (3, 3) ndarray
        Attitude matrix at ``t_k``.
    vel_n : (3,) ndarray
        ENU velocity at ``t_k`` [m/s].
    lat, lon, height : float
        Position at ``t_k`` [rad, rad, m].
    omega0_b, omega1_b, f0_b, f1_b : (3,) ndarray
        Corrected body rates [rad/s] and specific forces [m/s^2] at ``t_k`` and ``t_k + dt``.
    dt : float
        Interval [s], > 0.
    mech : Mechanization
        Earth terms to include.

    Returns
    -------
    mat_nb1, vel_n1, lat1, lon1, height1
        State at ``t_k + dt``.
    mat_nb_mid : (3, 3) ndarray
        Attitude at mid-interval.
    dv_force_n : (3,) ndarray
        Velocity increment of the specific force alone [m/s].
    """
    # rotation vectors of rotation_vectors() on Python floats (single sample: cheaper)
    a0, a1, a2 = omega0_b.tolist()
    b0, b1, b2 = omega1_b.tolist()
    dt = float(dt)
    k = dt * dt
    c0, c1, c2 = (a1 * b2 - a2 * b1) * k, (a2 * b0 - a0 * b2) * k, (a0 * b1 - a1 * b0) * k
    h, q = 0.5 * dt, 0.125 * dt
    rv = [
        [(a0 + b0) * h + c0 / 12.0, (a1 + b1) * h + c1 / 12.0, (a2 + b2) * h + c2 / 12.0],
        [(3.0 * a0 + b0) * q + c0 / 96.0, (3.0 * a1 + b1) * q + c1 / 96.0,
         (3.0 * a2 + b2) * q + c2 / 96.0],
    ]  # fmt: skip
    if mech.earth_rotation or mech.transport_rate:
        w_ie, w_en = nav_rates_n(lat, height, vel_n, mech)
        z0, z1, z2 = (w_ie + w_en).tolist()
        rv += [[-z0 * dt, -z1 * dt, -z2 * dt], [-0.5 * z0 * dt, -0.5 * z1 * dt, -0.5 * z2 * dt]]
        incr = Rotation.from_rotvec(rv).as_matrix()
        mat1 = incr[2] @ mat_nb @ incr[0]
        mat_h = incr[3] @ mat_nb @ incr[1]
        e0, e1, e2 = (2.0 * w_ie + w_en).tolist()
        u0, u1, u2 = vel_n.tolist()
        dv_other = np.array([e1 * u2 - e2 * u1, e2 * u0 - e0 * u2, e0 * u1 - e1 * u0]) * -dt
    else:
        incr = Rotation.from_rotvec(rv).as_matrix()
        mat1 = mat_nb @ incr[0]
        mat_h = mat_nb @ incr[1]
        dv_other = np.zeros(3)
    dv_f = (dt / 6.0) * (mat_nb @ f0_b + mat_h @ (2.0 * (f0_b + f1_b)) + mat1 @ f1_b)
    dv_other[2] -= float(normal_gravity(lat, height)) * dt
    v1 = vel_n + (dv_f + dv_other)
    r_m, r_n = radii_of_curvature(lat)
    v_mid = ((0.5 * dt) * (vel_n + v1)).tolist()
    lat1 = lat + v_mid[1] / float(r_m + height)
    lon1 = lon + v_mid[0] / (float(r_n + height) * math.cos(lat))
    return mat1, v1, lat1, lon1, height + v_mid[2], mat_h, dv_f


def strapdown_step_detail(
    state: NavState,
    omega0_b: ArrayLike,
    omega1_b: ArrayLike,
    f0_b: ArrayLike,
    f1_b: ArrayLike,
    t1: float,
    mech: Mechanization,
) -> tuple[NavState, Rotation, FloatArray]:
    """:func:`strapdown_step` that also returns mid-interval quantities.

    Returns
    -------
    state1 : NavState
        State at ``t1``.
    rot_nb_mid : Rotation
        Attitude at mid-interval.
    dv_force_n : (3,) ndarray
        Velocity increment of the specific force alone, ``int mat_nb f_b dt`` [m/s]
        (``dv_force_n / dt`` is the interval-mean specific force in ENU).
    """
    dt = float(t1) - state.t
    if not dt > 0:
        raise ValueError(f"t1={t1} must be after the state time {state.t}")
    mat1, v1, lat1, lon1, h1, mat_h, dv_f = strapdown_increment(
        state.rot_nb.as_matrix(),
        np.asarray(state.vel_n, dtype=float),
        state.lat,
        state.lon,
        state.height,
        np.asarray(omega0_b, dtype=float),
        np.asarray(omega1_b, dtype=float),
        np.asarray(f0_b, dtype=float),
        np.asarray(f1_b, dtype=float),
        dt,
        mech,
    )
    state1 = NavState(float(t1), Rotation.from_matrix(mat1), v1, lat1, lon1, h1)
    return state1, Rotation.from_matrix(mat_h), dv_f


def strapdown_step(
    state: NavState,
    omega0_b: ArrayLike,
    omega1_b: ArrayLike,
    f0_b: ArrayLike,
    f1_b: ArrayLike,
    t1: float,
    mech: Mechanization,
) -> NavState:
    """Propagate the nominal state over one IMU interval (the module docstring's step).

    Parameters
    ----------
    state : NavState
        State at ``t_k = state.t``.
    omega0_b, omega1_b : (3,) array_like
        Corrected body rates ``omega_ib_b`` at ``t_k`` and ``t1`` [rad/s].
    f0_b, f1_b : (3,) array_like
        Corrected specific forces at ``t_k`` and ``t1`` [m/s^2].
    t1 : float
        End time [s], ``> state.t``.
    mech : Mechanization
        Earth terms to include.

    Returns
    -------
    NavState
        State at ``t1``.
    """
    return strapdown_step_detail(state, omega0_b, omega1_b, f0_b, f1_b, t1, mech)[0]


def _mul_soa(a: FloatArray, b: FloatArray) -> FloatArray:
    """``a @ b`` for stacks of 3x3 matrices stored component-first, ``(3, 3, ...)``."""
    return np.einsum("ik...,kj...->ij...", a, b)


def _scan_soa(m: FloatArray, left: bool) -> FloatArray:
    """Inclusive prefix products along the last axis of ``(3, 3, n)`` matrices.

    ``out[..., i] = m_0 m_1 ... m_i`` (``left=False``) or ``m_i ... m_1 m_0`` (``left=True``).
    Two-level Hillis-Steele scan: inside blocks of ``~sqrt(n)`` matrices, over the block
    totals, and one product applying them (about ``log2(n) / 2 + 1`` batched products).
    """
    n = m.shape[-1]
    block = 1 << max(0, (math.ceil(math.log2(max(n, 1))) + 1) // 2)
    nb = -(-n // block)
    out = np.empty((3, 3, nb * block))
    out[..., :n] = m
    out[..., n:] = np.eye(3)[:, :, None]
    out = out.reshape(3, 3, nb, block)

    def mul(earlier: FloatArray, later: FloatArray) -> FloatArray:
        return _mul_soa(later, earlier) if left else _mul_soa(earlier, later)

    d = 1
    while d < block:
        out[..., d:] = mul(out[..., :-d], out[..., d:])
        d *= 2
    carry = out[..., -1].copy()
    d = 1
    while d < nb:
        carry[..., d:] = mul(carry[..., :-d], carry[..., d:])
        d *= 2
    out[..., 1:, :] = mul(carry[..., :-1, None], out[..., 1:, :])
    return out.reshape(3, 3, nb * block)[..., :n]


def prefix_products(mats: FloatArray, block: int = 16) -> FloatArray:
    """Inclusive prefix products ``out[i] = mats[0] @ mats[1] @ ... @ mats[i]``, ``(n, 3, 3)``.

    Two-level Hillis-Steele scan on the components (:func:`_scan_soa`); ``block`` is
    kept for compatibility (the block length is chosen from ``n``).
    """
    m = np.asarray(mats, dtype=float)
    if m.shape[0] == 0:
        return m.copy()
    return np.moveaxis(_scan_soa(np.moveaxis(m, 0, -1), left=False), -1, 0)


def _left_prefix_products(mats: FloatArray) -> FloatArray:
    """``out[i] = mats[i] @ ... @ mats[1] @ mats[0]`` (new factors on the left)."""
    m = np.asarray(mats, dtype=float)
    return np.moveaxis(_scan_soa(np.moveaxis(m, 0, -1), left=True), -1, 0)


def _force_increments(
    mat: FloatArray, mat_h: FloatArray, f: FloatArray, f_half: FloatArray, dt: FloatArray
) -> FloatArray:
    """Simpson's rule on ``mat_nb f_b`` over each interval (the sculling-exact increment).

    Component-first arrays: ``mat`` ``(3, 3, n + 1)``, ``mat_h`` ``(3, 3, n)``, ``f``
    ``(3, n + 1)``, ``f_half`` ``(3, n)``; returns ``(3, n)``.
    """
    force_n = mat[:, 0] * f[0] + mat[:, 1] * f[1] + mat[:, 2] * f[2]
    force_h = mat_h[:, 0] * f_half[0] + mat_h[:, 1] * f_half[1] + mat_h[:, 2] * f_half[2]
    return (dt / 6.0) * (force_n[:, :-1] + 4.0 * force_h + force_n[:, 1:])


def strapdown(
    state0: NavState,
    t: ArrayLike,
    omega_b: ArrayLike,
    f_b: ArrayLike,
    mech: Mechanization,
    *,
    max_iter: int = 12,
) -> NavTrack:
    """Propagate the nominal state through a block of IMU samples (vectorised).

    Mathematically identical to calling :func:`strapdown_step` for every interval.
    The attitude is ``mat_nb(t_k) = L_k mat_nb(t_0) B_k`` with ``B_k`` the prefix product
    of the body increments ``exp(phi)`` and ``L_k`` that of the navigation-frame increments
    ``exp(-zeta)``; velocity and position are cumulative sums. The Earth terms evaluated at
    ``t_k`` (gravity, Coriolis, transport rate) depend on the state itself, so they are
    found by a fixed-point iteration that contracts by ``~|omega_in| * duration`` (plus
    ``~3e-6 s^-2 * duration^2`` for gravity) per pass and stops at rounding level.

    Parameters
    ----------
    state0 : NavState
        State at ``t[0]`` (``state0.t`` must equal ``t[0]``).
    t : (n + 1,) array_like
        Sample times [s], strictly increasing.
    omega_b, f_b : (n + 1, 3) array_like
        Corrected body rates [rad/s] and specific forces [m/s^2] at ``t``.
    mech : Mechanization
        Earth terms to include.
    max_iter : int
        Iteration limit (a ``RuntimeError`` if it does not converge, which would mean
        an implausibly long block).

    Returns
    -------
    NavTrack
        States at all ``t`` (index 0 is ``state0``).
    """
    t = np.asarray(t, dtype=float)
    w = np.asarray(omega_b, dtype=float)
    f = np.asarray(f_b, dtype=float)
    n = t.shape[0] - 1
    if n < 1:
        raise ValueError("strapdown needs at least 2 samples")
    if abs(t[0] - state0.t) > 1e-9 * max(1.0, abs(t[0])):
        raise ValueError(f"t[0]={t[0]} differs from state0.t={state0.t}")
    dt = np.diff(t)
    if not np.all(dt > 0):
        raise ValueError("sample times must be strictly increasing")
    phi, phi_h = rotation_vectors(w[:-1], w[1:], dt)
    # Component-first (3, 3, k) matrices below: batched 3x3 products are elementwise.
    incr = Rotation.from_rotvec(np.concatenate([phi, phi_h])).as_matrix()
    incr = np.ascontiguousarray(np.moveaxis(incr, 0, -1))
    seq = np.empty((3, 3, n + 1))
    seq[..., 0] = state0.rot_nb.as_matrix()
    seq[..., 1:] = incr[..., :n]
    mat0_body = _scan_soa(seq, left=False)  # mat_nb(t_0) B_k
    f_c = np.ascontiguousarray(f.T)
    f_half = 0.5 * (f_c[:, :-1] + f_c[:, 1:])
    dt_col = dt[:, None]
    earth_terms = mech.earth_rotation or mech.transport_rate

    # Guesses of the states at t_0..t_{n-1} that the Earth terms depend on.
    lat = np.full(n, state0.lat)
    height = np.full(n, state0.height)
    vel = np.broadcast_to(state0.vel_n, (n, 3)).copy()
    mat = mat0_body  # without navigation-frame rotation
    mat_h = _mul_soa(mat[..., :-1], incr[..., n:])
    dv_force = _force_increments(mat, mat_h, f_c, f_half, dt).T
    coriolis = np.zeros((n, 3))
    v0 = state0.vel_n
    if earth_terms:
        # predictor: velocity without the Earth terms, a good first guess for them
        dv = dv_force.copy()
        dv[:, 2] -= normal_gravity(state0.lat, state0.height) * dt
        vel[1:] = v0 + np.cumsum(dv, axis=0)[:-1]
    for _ in range(max_iter):
        if earth_terms:
            w_ie, w_en = nav_rates_n(lat, height, vel, mech)
            zeta = (w_ie + w_en) * dt_col
            nav = Rotation.from_rotvec(np.concatenate([-zeta, -0.5 * zeta])).as_matrix()
            nav = np.ascontiguousarray(np.moveaxis(nav, 0, -1))
            left = np.empty((3, 3, n + 1))
            left[..., 0] = np.eye(3)
            left[..., 1:] = _scan_soa(nav[..., :n], left=True)
            mat = _mul_soa(left, mat0_body)
            mat_h = _mul_soa(_mul_soa(nav[..., n:], mat[..., :-1]), incr[..., n:])
            dv_force = _force_increments(mat, mat_h, f_c, f_half, dt).T
            coriolis = cross(2.0 * w_ie + w_en, vel)
        grav_u = -normal_gravity(lat, height)
        dv = dv_force - coriolis * dt_col
        dv[:, 2] += grav_u * dt
        vel_all = np.empty((n + 1, 3))
        vel_all[0] = v0
        np.cumsum(dv, axis=0, out=vel_all[1:])
        vel_all[1:] += v0
        dpos = 0.5 * (vel_all[:-1] + vel_all[1:]) * dt_col
        r_m, r_n = radii_of_curvature(lat)
        h_all = np.empty(n + 1)
        h_all[0] = 0.0
        np.cumsum(dpos[:, 2], out=h_all[1:])
        h_all += state0.height
        lat_all = np.empty(n + 1)
        lat_all[0] = 0.0
        np.cumsum(dpos[:, 1] / (r_m + height), out=lat_all[1:])
        lat_all += state0.lat
        # A pass contracts the error of the guesses by ~|2 omega_ie + omega_en| * duration
        # (< 3e-3 for 20 s): once a pass changes the guesses by less than these limits, the
        # result is within ~3e-9 m/s of the exact fixed point and the attitude (which sees
        # the velocity only through the transport rate v / R) within ~1e-15 rad.
        change = max(
            float(np.max(np.abs(vel_all[:-1] - vel))) / 1e-6,  # [m/s]
            float(np.max(np.abs(h_all[:-1] - height))) / 1e-4,  # [m]
            float(np.max(np.abs(lat_all[:-1] - lat))) / 1e-12,  # [rad]
        )
        vel, height, lat = vel_all[:-1], h_all[:-1], lat_all[:-1]
        if change <= 1.0:
            break
    else:
        raise RuntimeError("strapdown fixed-point iteration did not converge; split the block")
    dlon = dpos[:, 0] / ((r_n + height) * np.cos(lat))
    lon_all = np.empty(n + 1)
    lon_all[0] = 0.0
    np.cumsum(dlon, out=lon_all[1:])
    lon_all += state0.lon
    return NavTrack(
        t=t,
        mat_nb=np.ascontiguousarray(np.moveaxis(mat, -1, 0)),
        vel_n=vel_all,
        lat=lat_all,
        lon=lon_all,
        height=h_all,
        mat_nb_mid=np.ascontiguousarray(np.moveaxis(mat_h, -1, 0)),
        dv_force_n=dv_force,
    )
