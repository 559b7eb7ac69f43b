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
that vary linearly in time between samples (docs/filter.md). One step from ``t_k`` to
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

:func:`strapdown` does the same steps for a whole block of samples in a loop compiled with
numba (the one compiled kernel of polins: the strapdown is sequential, and a step costs
about 30 ns there against 10 us in Python); it matches repeated :func:`strapdown_step` to
rounding error (tests/test_ins.py).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from polins.ins.earth import (
    OMEGA_IE,
    earth_rate_n,
    radii_from_sin2,
    somigliana,
    transport_rate_n,
)
from polins.ins.state import NavState

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


@dataclass(frozen=True, eq=False)
class NavTrack:
    """The integrator's output over many samples (:func:`strapdown`): the nominal states
    with what the error dynamics need between them.

    ``mat_nb`` ``(N, 3, 3)`` is the attitude as matrices (``Rotation.from_matrix`` gives
    the rotations); the other fields are as in :class:`polins.ins.state.NavState` with a
    leading axis N (:meth:`state` gives one).
    Per interval (N - 1): ``mat_nb_mid`` the mid-interval attitude and ``dv_force_n`` the
    specific-force velocity increment (as in :func:`strapdown_step_detail`).
    """

    t: FloatArray
    mat_nb: FloatArray
    vel_n: FloatArray
    lat: FloatArray
    lon: FloatArray
    alt_m: FloatArray
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
            alt_m=float(self.alt_m[i]),
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

    The step of :func:`strapdown` (the same compiled loop, over one interval) with the
    attitude as a rotation matrix: the streaming filter calls this once per IMU sample.

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
    mat, vel, pos = np.empty((2, 3, 3)), np.empty((2, 3)), np.empty((2, 3))
    mat_mid, dv_force = np.empty((1, 3, 3)), np.empty((1, 3))
    _compiled()(
        np.array([0.0, dt]), np.array([omega0_b, omega1_b], dtype=float),
        np.array([f0_b, f1_b], dtype=float), mat_nb, np.asarray(vel_n, dtype=float),
        np.array([lat, lon, height]), mech.earth_rotation, mech.transport_rate, mat, vel, pos,
        mat_mid, dv_force,
    )  # fmt: skip
    lat1, lon1, h1 = pos[1].tolist()
    return mat[1], vel[1], lat1, lon1, h1, mat_mid[0], dv_force[0]


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
        state.alt_m,
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


def rotvec_matrix(x: float, y: float, z: float, out: FloatArray) -> None:
    """``exp([phi x])`` of the rotation vector ``(x, y, z)`` into ``out`` (3, 3) (Rodrigues,
    half-angle form; series below 1e-6 rad)."""
    theta2 = x * x + y * y + z * z
    if theta2 < 1e-12:
        a, b = 1.0 - theta2 / 6.0, 0.5 - theta2 / 24.0
    else:
        theta = math.sqrt(theta2)
        a = math.sin(theta) / theta
        h = math.sin(0.5 * theta)
        b = 2.0 * h * h / theta2
    out[0, 0] = 1.0 - b * (y * y + z * z)
    out[1, 1] = 1.0 - b * (x * x + z * z)
    out[2, 2] = 1.0 - b * (x * x + y * y)
    out[0, 1], out[1, 0] = b * x * y - a * z, b * x * y + a * z
    out[0, 2], out[2, 0] = b * x * z + a * y, b * x * z - a * y
    out[1, 2], out[2, 1] = b * y * z - a * x, b * y * z + a * x


def _run(  # pragma: no cover - compiled by numba, which coverage cannot trace
    t: FloatArray,
    w: FloatArray,
    f: FloatArray,
    mat0: FloatArray,
    vel0: FloatArray,
    pos0: FloatArray,
    earth: bool,
    transport: bool,
    mat: FloatArray,
    vel: FloatArray,
    pos: FloatArray,
    mat_mid: FloatArray,
    dv_force: FloatArray,
) -> None:
    """The steps of the module docstring, one interval after the other (compiled by numba:
    :func:`_compiled`). Fills ``mat`` (n+1, 3, 3), ``vel`` (n+1, 3), ``pos`` (n+1, 3) =
    (lat, lon, height), ``mat_mid`` (n, 3, 3) and ``dv_force`` (n, 3)."""
    n = t.shape[0] - 1
    mat[0] = mat0
    vel[0] = vel0
    pos[0] = pos0
    inc, inc_h = np.empty((3, 3)), np.empty((3, 3))
    nav, nav_h = np.eye(3), np.eye(3)
    tmp = np.empty((3, 3))
    z, e, dv, dv_f = np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3)
    for k in range(n):
        dt = t[k + 1] - t[k]
        a0, a1, a2 = w[k, 0], w[k, 1], w[k, 2]
        b0, b1, b2 = w[k + 1, 0], w[k + 1, 1], w[k + 1, 2]
        q = dt * dt
        c0, c1, c2 = (a1 * b2 - a2 * b1) * q, (a2 * b0 - a0 * b2) * q, (a0 * b1 - a1 * b0) * q
        h, o = 0.5 * dt, 0.125 * dt
        _rotvec((a0 + b0) * h + c0 / 12.0, (a1 + b1) * h + c1 / 12.0,
                (a2 + b2) * h + c2 / 12.0, inc)  # fmt: skip
        _rotvec((3.0 * a0 + b0) * o + c0 / 96.0, (3.0 * a1 + b1) * o + c1 / 96.0,
                (3.0 * a2 + b2) * o + c2 / 96.0, inc_h)  # fmt: skip
        lat, height = pos[k, 0], pos[k, 2]
        v0, v1, v2 = vel[k, 0], vel[k, 1], vel[k, 2]
        s2 = math.sin(lat) ** 2
        r_m, r_n = _radii(s2)
        dv[0] = dv[1] = dv[2] = 0.0
        if earth or transport:
            z[0] = z[1] = z[2] = 0.0  # omega_in_n
            e[0] = e[1] = e[2] = 0.0  # 2 omega_ie_n + omega_en_n
            if earth:
                z[1], z[2] = OMEGA_IE * math.cos(lat), OMEGA_IE * math.sin(lat)
                e[1], e[2] = 2.0 * z[1], 2.0 * z[2]
            if transport:
                w_en = (-v1 / (r_m + height), v0 / (r_n + height),
                        v0 * math.tan(lat) / (r_n + height))  # fmt: skip
                for i in range(3):
                    z[i] += w_en[i]
                    e[i] += w_en[i]
            _rotvec(-z[0] * dt, -z[1] * dt, -z[2] * dt, nav)
            _rotvec(-0.5 * z[0] * dt, -0.5 * z[1] * dt, -0.5 * z[2] * dt, nav_h)
            dv[0] = -dt * (e[1] * v2 - e[2] * v1)
            dv[1] = -dt * (e[2] * v0 - e[0] * v2)
            dv[2] = -dt * (e[0] * v1 - e[1] * v0)
        _mul3(nav, mat[k], tmp)
        _mul3(tmp, inc, mat[k + 1])
        _mul3(nav_h, mat[k], tmp)
        _mul3(tmp, inc_h, mat_mid[k])
        for i in range(3):  # Simpson on mat_nb f_b (sculling)
            acc = 0.0
            for j in range(3):
                f0, f1 = f[k, j], f[k + 1, j]
                acc += (
                    mat[k, i, j] * f0 + mat_mid[k, i, j] * 2.0 * (f0 + f1) + mat[k + 1, i, j] * f1
                )
            dv_f[i] = acc * (dt / 6.0)
        dv_force[k] = dv_f
        dv[2] -= _gravity(s2, height) * dt
        for i in range(3):
            vel[k + 1, i] = vel[k, i] + (dv_f[i] + dv[i])
            e[i] = 0.5 * dt * (vel[k, i] + vel[k + 1, i])  # the position increment
        pos[k + 1, 0] = lat + e[1] / (r_m + height)
        pos[k + 1, 1] = pos[k, 1] + e[0] / ((r_n + height) * math.cos(lat))
        pos[k + 1, 2] = height + e[2]


def _mul3_py(a: FloatArray, b: FloatArray, out: FloatArray) -> None:  # pragma: no cover
    """``out = a @ b`` for 3x3 matrices (written out: compiled, it avoids BLAS calls)."""
    for i in range(3):
        for j in range(3):
            out[i, j] = a[i, 0] * b[0, j] + a[i, 1] * b[1, j] + a[i, 2] * b[2, j]


# the functions _run calls: numba dispatchers once compiled (:func:`_compiled`)
_gravity, _radii, _rotvec, _mul3 = somigliana, radii_from_sin2, rotvec_matrix, _mul3_py


@functools.cache
def _compiled() -> Any:
    """:func:`_run` compiled by numba (imported here, not with polins; the machine code is
    cached on disk next to this module)."""
    import numba

    global _gravity, _radii, _rotvec, _mul3
    _gravity = numba.njit(cache=True)(somigliana)
    _radii = numba.njit(cache=True)(radii_from_sin2)
    _rotvec = numba.njit(cache=True)(rotvec_matrix)
    _mul3 = numba.njit(cache=True)(_mul3_py)
    return numba.njit(cache=True)(_run)


def strapdown(
    state0: NavState,
    t: ArrayLike,
    omega_b: ArrayLike,
    f_b: ArrayLike,
    mech: Mechanization,
) -> NavTrack:
    """Propagate the nominal state through a block of IMU samples (compiled loop).

    The steps of :func:`strapdown_step` for every interval, compiled with numba (the same
    arithmetic; tests/test_ins.py compares the two).

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

    Returns
    -------
    NavTrack
        States at all ``t`` (index 0 is ``state0``).
    """
    t = np.ascontiguousarray(t, dtype=float)
    w = np.ascontiguousarray(omega_b, dtype=float)
    f = np.ascontiguousarray(f_b, dtype=float)
    n = t.shape[0] - 1
    if n < 1:
        raise ValueError("strapdown needs at least 2 samples")
    if abs(t[0] - state0.t) > 1e-9 * max(1.0, abs(t[0])):
        raise ValueError(f"t[0]={t[0]} differs from state0.t={state0.t}")
    if not np.all(np.diff(t) > 0):
        raise ValueError("sample times must be strictly increasing")
    mat, vel, pos = np.empty((n + 1, 3, 3)), np.empty((n + 1, 3)), np.empty((n + 1, 3))
    mat_mid, dv_force = np.empty((n, 3, 3)), np.empty((n, 3))
    _compiled()(
        t, w, f, state0.rot_nb.as_matrix(), np.asarray(state0.vel_n, dtype=float),
        np.array([state0.lat, state0.lon, state0.alt_m], dtype=float),
        mech.earth_rotation, mech.transport_rate, mat, vel, pos, mat_mid, dv_force,
    )  # fmt: skip
    return NavTrack(t, mat, vel, pos[:, 0].copy(), pos[:, 1].copy(), pos[:, 2].copy(),
                    mat_mid, dv_force)  # fmt: skip
