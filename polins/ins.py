"""Strapdown inertial navigation in the local ENU frame with geodetic position.

State: attitude ``rot_nb`` (body FLU -> ENU, scipy ``Rotation``), ENU velocity relative to
the Earth ``vel_n`` [m/s], geodetic latitude, longitude [rad] and height [m] (WGS-84,
``polins.earth``). The continuous equations (Titterton & Weston 2004, Eq. 3.39-3.41;
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

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from polins.calibration import ImuModel
from polins.earth import (
    earth_rate_n,
    gravity_n,
    normal_gravity,
    radii_of_curvature,
    transport_rate_n,
)

FloatArray = NDArray[np.float64]


def skew(v: ArrayLike) -> FloatArray:
    """Cross-product matrix ``[v x]`` with ``skew(a) @ b == cross(a, b)``; ``(..., 3, 3)``."""
    v = np.asarray(v, dtype=float)
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


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
    f0 = np.array(f0_b, dtype=float)  # copies: Rotation.apply rejects read-only buffers
    f1 = np.array(f1_b, dtype=float)
    phi, phi_h = rotation_vectors(omega0_b, omega1_b, dt)
    w_ie, w_en = nav_rates_n(state.lat, state.height, state.vel_n, mech)
    zeta = (w_ie + w_en) * dt
    rot0 = state.rot_nb
    rot1 = Rotation.from_rotvec(-zeta) * rot0 * Rotation.from_rotvec(phi)
    rot_h = Rotation.from_rotvec(-0.5 * zeta) * rot0 * Rotation.from_rotvec(phi_h)
    dv_f = (dt / 6.0) * (rot0.apply(f0) + 4.0 * rot_h.apply(0.5 * (f0 + f1)) + rot1.apply(f1))
    v0 = state.vel_n
    grav = gravity_n(state.lat, state.height)
    v1 = v0 + dv_f + (grav - cross(2.0 * w_ie + w_en, v0)) * dt
    r_m, r_n = radii_of_curvature(state.lat)
    v_mid = 0.5 * (v0 + v1) * dt
    state1 = NavState(
        t=float(t1),
        rot_nb=rot1,
        vel_n=v1,
        lat=state.lat + float(v_mid[1] / (r_m + state.height)),
        lon=state.lon + float(v_mid[0] / ((r_n + state.height) * np.cos(state.lat))),
        height=state.height + float(v_mid[2]),
    )
    return state1, rot_h, dv_f


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


def prefix_products(mats: FloatArray, block: int = 16) -> FloatArray:
    """Inclusive prefix products ``out[i] = mats[0] @ mats[1] @ ... @ mats[i]``, ``(n, a, a)``.

    Two-level scan: Hillis-Steele inside blocks of ``block`` matrices (``log2(block)``
    batched products), a sequential product of the block totals, and one batched product
    applying them.
    """
    m = np.asarray(mats, dtype=float)
    n = m.shape[0]
    nb = -(-n // block)
    pad = nb * block - n
    out = (
        m
        if pad == 0
        else np.concatenate([m, np.broadcast_to(np.eye(m.shape[-1]), (pad, *m.shape[1:]))])
    )
    out = out.reshape(nb, block, *m.shape[1:]).copy()
    d = 1
    while d < block:
        out[:, d:] = out[:, :-d] @ out[:, d:]
        d *= 2
    carry = out[:, -1].copy()
    for i in range(1, nb):
        carry[i] = carry[i - 1] @ carry[i]
    out[1:] = carry[:-1, None] @ out[1:]
    return out.reshape(nb * block, *m.shape[1:])[:n]


def _left_prefix_products(mats: FloatArray) -> FloatArray:
    """``out[i] = mats[i] @ ... @ mats[1] @ mats[0]`` (new factors on the left)."""
    out = np.array(mats, dtype=float, copy=True)
    d = 1
    n = out.shape[0]
    while d < n:
        out[d:] = out[d:] @ out[:-d]
        d *= 2
    return out


def _force_increments(
    mat: FloatArray, mat_h: FloatArray, f: FloatArray, f_half: FloatArray, dt_col: FloatArray
) -> FloatArray:
    """Simpson's rule on ``mat_nb f_b`` over each interval (the sculling-exact increment)."""
    force_n = (mat @ f[..., None])[..., 0]
    force_h = (mat_h @ f_half[..., None])[..., 0]
    return (dt_col / 6.0) * (force_n[:-1] + 4.0 * force_h + force_n[1:])


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
    incr = Rotation.from_rotvec(np.concatenate([phi, phi_h])).as_matrix()
    body = np.empty((n + 1, 3, 3))
    body[0] = np.eye(3)
    body[1:] = prefix_products(incr[:n])
    mat0 = state0.rot_nb.as_matrix()
    f_half = 0.5 * (f[:-1] + f[1:])
    dt_col = dt[:, None]
    earth_terms = mech.earth_rotation or mech.transport_rate

    # Guesses of the states at t_0..t_{n-1} that the Earth terms depend on.
    lat = np.full(n, state0.lat)
    height = np.full(n, state0.height)
    vel = np.broadcast_to(state0.vel_n, (n, 3)).copy()
    mat = mat0 @ body  # (n + 1, 3, 3) without navigation-frame rotation
    mat_h = mat[:-1] @ incr[n:]
    dv_force = _force_increments(mat, mat_h, f, f_half, dt_col)
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
            left = np.empty((n + 1, 3, 3))
            left[0] = np.eye(3)
            left[1:] = _left_prefix_products(nav[:n])
            mat = left @ mat0 @ body
            mat_h = nav[n:] @ mat[:-1] @ incr[n:]
            dv_force = _force_increments(mat, mat_h, f, f_half, dt_col)
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
        mat_nb=mat,
        vel_n=vel_all,
        lat=lat_all,
        lon=lon_all,
        height=h_all,
        mat_nb_mid=mat_h,
        dv_force_n=dv_force,
    )
