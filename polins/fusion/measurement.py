"""Measurement models shared by the ESKF and the GTSAM graph: residual, Jacobian, covariance.

Every model returns a :class:`Linearized` evaluated at a nominal state. The error state is
the 15-vector of docs/filter.md::

    dx = [dtheta (0:3), dv_n (3:6), dp (6:9), dbg (9:12), dba (12:15)]

with the attitude error in the navigation frame, ``rot_nb_true = Rotation.from_rotvec(dtheta)
* rot_nb_nominal``, ``vel_n_true = vel_n + dv_n``, ``dp`` the position error in local ENU
metres and ``bias_true = bias + dbias``.

Conventions of :class:`Linearized`:

* ``residual = z - h(x_nominal)`` (angles wrapped), the innovation when the error state is 0;
* ``H = d h(x_nominal (+) dx) / d dx`` at ``dx = 0``, so ``z ~ h(x_nominal) + H dx + noise``
  and the residual as a function of the error state is ``residual - H dx`` to first order;
* ``R`` the measurement noise covariance.

A Kalman update with ``filterpy.kalman.update(dx, P, z=residual, R=R, H=H)`` is then the
standard error-state update. A factor graph uses ``residual`` and ``H`` directly (GTSAM's
error is ``h(x) - z = -residual``; its Jacobian is ``H`` mapped to its own tangent space).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from polins.frames import rot_lb_from_rot_nb, skew, wrap_angle
from polins.ins.strapdown import rotvec_matrix

FloatArray = NDArray[np.float64]

N_ERROR = 15
ATT = slice(0, 3)
VEL = slice(3, 6)
POS = slice(6, 9)
BG = slice(9, 12)
BA = slice(12, 15)


@dataclass(eq=False, slots=True)
class Linearized:
    """One linearized measurement ``(z - h(x), H, R)`` at the nominal state.

    Attributes
    ----------
    residual : (m,) ndarray
        ``z - h(x_nominal)``, angles wrapped to (-pi, pi] [measurement units].
    H : (m, 15) ndarray
        Jacobian of ``h`` with respect to the error state (module docstring).
    R : (m, m) ndarray
        Measurement noise covariance [measurement units squared].
    name : str
        Model name: ``"yaw"``, ``"sun"``, ``"sun_azimuth"``, ``"zupt"``, ``"zaru"``,
        ``"level"``, ``"nhc"`` or ``"odo"``.
    vel_v : (3,) ndarray or None
        ``"nhc"``, ``"odo"``: the predicted velocity of the vehicle's reference point in
        the vehicle frame [m/s], for the mounting-error columns (:func:`mount_jacobian`).
    """

    residual: FloatArray
    H: FloatArray
    R: FloatArray
    name: str
    vel_v: FloatArray | None = None

    @property
    def dim(self) -> int:
        """Number of measurement components ``m``."""
        return int(self.residual.shape[0])


def as_mat_nb(rot_nb: Rotation | ArrayLike) -> FloatArray:
    """``mat_nb`` of a single scipy Rotation, or a (3, 3) rotation matrix given directly."""
    if isinstance(rot_nb, Rotation):
        if not rot_nb.single:
            raise ValueError("rot_nb must be a single scipy Rotation (body FLU -> ENU)")
        return rot_nb.as_matrix()
    mat = np.asarray(rot_nb, dtype=float)
    if mat.shape != (3, 3) or not np.all(np.isfinite(mat)):
        raise ValueError("rot_nb must be a single scipy Rotation or a finite (3, 3) matrix mat_nb")
    return mat


def _vector3(v: ArrayLike, name: str, *, unit: bool = False) -> FloatArray:
    arr = np.asarray(v, dtype=float)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be a finite 3-vector, got shape {arr.shape}")
    if unit:
        norm = np.linalg.norm(arr)
        if not 0.5 < norm < 1.5:
            raise ValueError(f"{name} must be a unit direction vector, got |{name}| = {norm:.3g}")
        arr = arr / norm
    return arr


def _variance(std: ArrayLike, m: int, name: str) -> FloatArray:
    s = np.broadcast_to(np.asarray(std, dtype=float), (m,))
    if not np.all(np.isfinite(s)) or not np.all(s > 0):
        raise ValueError(f"{name} must be finite and > 0, got {std!r}")
    return s * s


def _wrap(angle: float) -> float:
    """:func:`polins.frames.wrap_angle` of one float [rad] (cheaper per call)."""
    out = math.remainder(angle, 2.0 * math.pi)
    return math.pi if out == -math.pi else out


def wrap_residual(residual: FloatArray, name: str) -> FloatArray:
    """A model's residual with its angles wrapped to (-pi, pi] (``"yaw"``, ``"sun_azimuth"``)."""
    if name in ("yaw", "sun_azimuth"):
        return np.array([_wrap(float(r)) for r in residual])
    return residual


# ----------------------------------------------------------------------------- kernels
# The kernels take validated inputs (mat_nb a rotation matrix, unit vectors, variances);
# the public functions below validate and call them. The ESKF calls the kernels directly.
def yaw_kernel(
    mat_nb: FloatArray,
    yaw: float,
    var: float,
    sun_n: FloatArray | None,
    mat_nb_prior: FloatArray | None = None,
) -> Linearized:
    """:func:`yaw_measurement` on validated inputs (``var`` = yaw_std^2, unit ``sun_n``)."""
    if sun_n is None:  # the yaw of body x
        ax, ay, az = mat_nb[:, 0].tolist()
        horiz2 = ax * ax + ay * ay
        if horiz2 < 1e-12:
            raise ValueError("yaw is undefined: body x is vertical")
        H = np.zeros((1, N_ERROR))
        H[0, :3] = (-ax * az / horiz2, -ay * az / horiz2, 1.0)
        predicted = math.atan2(ay, ax)
        return Linearized(np.array([_wrap(yaw - predicted)]), H, np.array([[var]]), "yaw")
    # The yaw polins.measure computes from the sun seen in the body frame, levelled with the
    # prior's tilt: h = alpha_s + yaw_P - azimuth(M sun_n), M = mat_nb_P mat_bn (module doc).
    prior = mat_nb if mat_nb_prior is None else mat_nb_prior
    M = prior @ mat_nb.T
    b = M @ sun_n
    horiz2 = float(b[0] * b[0] + b[1] * b[1])
    if horiz2 < 1e-12:
        raise ValueError("yaw is undefined: the sun is at the zenith of the prior's level frame")
    grad = np.array([-b[1], b[0], 0.0]) / horiz2  # d azimuth(b) / d b
    H = np.zeros((1, N_ERROR))
    H[0, ATT] = -(grad @ M) @ skew(sun_n)
    predicted = (
        math.atan2(float(sun_n[1]), float(sun_n[0]))
        + math.atan2(float(prior[1, 0]), float(prior[0, 0]))
        - math.atan2(float(b[1]), float(b[0]))
    )
    return Linearized(np.array([_wrap(yaw - predicted)]), H, np.array([[var]]), "yaw")


def sun_kernel(
    mat_nb: FloatArray,
    sun_b: FloatArray,
    sun_n: FloatArray,
    var: float,
    basis_b: FloatArray | None,
    cov_b: FloatArray | None = None,
) -> Linearized:
    """:func:`sun_measurement` on validated inputs (unit vectors, ``var`` = sun_std^2;
    ``cov_b`` a (3, 3) direction covariance in the body frame replacing ``var I``)."""
    s_pred_b = mat_nb.T @ sun_n
    basis = _basis(s_pred_b) if basis_b is None else basis_b
    H = np.zeros((2, N_ERROR))
    # h(dtheta) = mat_bn exp(-dtheta) sun_n ~ h + mat_bn [sun_n x] dtheta
    H[:, ATT] = (mat_nb @ basis).T @ skew(sun_n)
    R = np.eye(2) * var if cov_b is None else basis.T @ cov_b @ basis
    return Linearized(basis.T @ (sun_b - s_pred_b), H, R, "sun")


def sun_direction_cov_b(sun_b: FloatArray, azimuth_std: float, elevation_std: float) -> FloatArray:
    """The (3, 3) covariance [rad^2] of a measured body sun direction whose errors are
    ``azimuth_std`` along the azimuth and ``elevation_std`` along the elevation [rad]
    (tangent displacements, docs/filter.md "Sun vector"): ``azimuth_std^2 u_a u_a^T +
    elevation_std^2 u_e u_e^T`` with ``u_a``, ``u_e`` the unit tangents of the body-frame
    azimuth and elevation at ``sun_b``."""
    s = sun_b / np.linalg.norm(sun_b)
    horiz = math.hypot(float(s[0]), float(s[1]))
    if horiz < 1e-9:  # at the body zenith the azimuth is undefined: isotropic
        return (np.eye(3) - np.outer(s, s)) * max(azimuth_std, elevation_std) ** 2
    u_a = np.array([-s[1], s[0], 0.0]) / horiz
    u_e = np.cross(s, u_a)
    return azimuth_std**2 * np.outer(u_a, u_a) + elevation_std**2 * np.outer(u_e, u_e)


def sun_azimuth_kernel(
    mat_nb: FloatArray,
    azimuth_b: float,
    var: float,
    sun_azimuth_n: float,
    sun_elevation_n: float,
    *,
    axis: bool = False,
) -> Linearized:
    """The sun's body-frame azimuth without a clock (docs/filter.md, "No clock").

    The sun's ENU azimuth ``sun_azimuth_n`` is a filter state (not known from an
    ephemeris); its ENU elevation ``sun_elevation_n`` is taken as known for the tilt
    terms. With ``sun_n = (cos e cos a, cos e sin a, sin e)`` and ``b = mat_bn sun_n``::

        h(x) = atan2(b_y, b_x),   H_theta = grad(b)^T mat_bn [sun_n x],
        grad(b) = (-b_y, b_x, 0) / (b_x^2 + b_y^2)

    so ``h = sun_azimuth_n - yaw`` for a level body, and ``dh / d sun_azimuth_n =
    -H_theta[2]`` (the sun turning about the vertical is the body turning the other way).
    With ``axis`` (the image could not tell the sun from the antisun) the residual is taken
    modulo pi, in (-pi/2, pi/2].
    """
    ce = math.cos(sun_elevation_n)
    sun_n = np.array(
        [ce * math.cos(sun_azimuth_n), ce * math.sin(sun_azimuth_n), math.sin(sun_elevation_n)]
    )
    b = mat_nb.T @ sun_n
    horiz2 = float(b[0] * b[0] + b[1] * b[1])
    if horiz2 < 1e-12:
        raise ValueError("the sun's body azimuth is undefined: the sun is on the body z axis")
    grad = np.array([-b[1], b[0], 0.0]) / horiz2
    H = np.zeros((1, N_ERROR))
    H[0, ATT] = (grad @ mat_nb.T) @ skew(sun_n)
    predicted = math.atan2(float(b[1]), float(b[0]))
    residual = np.array([_wrap(2.0 * (azimuth_b - predicted)) / 2.0 if axis
                         else _wrap(azimuth_b - predicted)])  # fmt: skip
    return Linearized(residual, H, np.array([[var]]), "sun_azimuth")


def zero_velocity_kernel(vel_n: FloatArray, var: FloatArray) -> Linearized:
    """:func:`zero_velocity` on validated inputs (``var`` (3,) variances)."""
    H = np.zeros((3, N_ERROR))
    H[:, VEL] = np.eye(3)
    return Linearized(-vel_n, H, np.diag(var), "zupt")


def zero_rate_kernel(
    mat_nb: FloatArray,
    gyro_b: FloatArray,
    bias_b: FloatArray,
    var: FloatArray,
    rate_n: FloatArray | None = None,
) -> Linearized:
    """:func:`zero_rate` on validated inputs (``var`` (3,) variances)."""
    H = np.zeros((3, N_ERROR))
    H[:, BG] = np.eye(3)
    predicted = bias_b
    if (
        rate_n is not None
    ):  # mat_bn exp(-[dtheta x]) rate_n ~ mat_bn rate_n + mat_bn [rate_n x] dtheta
        mat_bn = mat_nb.T
        predicted = bias_b + mat_bn @ rate_n
        H[:, ATT] = mat_bn @ skew(rate_n)
    return Linearized(gyro_b - predicted, H, np.diag(var), "zaru")


def level_kernel(
    mat_nb: FloatArray, force_b: FloatArray, bias_b: FloatArray, var: FloatArray
) -> Linearized:
    """:func:`level` on validated inputs (``var`` (2,) variances)."""
    force_n = mat_nb @ (force_b - bias_b)
    H = np.zeros((2, N_ERROR))
    H[:, ATT] = -skew(force_n)[0:2]  # exp([dtheta x]) f_n ~ f_n - [f_n x] dtheta
    H[:, BA] = -mat_nb[0:2]
    return Linearized(-force_n[0:2], H, np.diag(var), "level")


def non_holonomic_kernel(
    mat_nb: FloatArray,
    vel_n: FloatArray,
    var: FloatArray,
    mat_vb: FloatArray | None = None,
    lever_vel_b: FloatArray | None = None,
) -> Linearized:
    """:func:`non_holonomic` on validated inputs (``var`` (2,) variances)."""
    vel_v, mat_vn = _vehicle_velocity(mat_nb, vel_n, mat_vb, lever_vel_b)
    H = np.zeros((2, N_ERROR))
    H[:, ATT] = (mat_vn @ skew(vel_n))[1:3]
    H[:, VEL] = mat_vn[1:3]
    return Linearized(-vel_v[1:3], H, np.diag(var), "nhc", vel_v)


def odometer_kernel(
    mat_nb: FloatArray,
    vel_n: FloatArray,
    speed: float,
    var: float,
    mat_vb: FloatArray | None = None,
    lever_vel_b: FloatArray | None = None,
) -> Linearized:
    """Wheel-odometer speed: ``h(x)`` the forward (vehicle x) velocity of the vehicle's
    reference point [m/s], as in :func:`non_holonomic` (docs/filter.md, "Ground-vehicle
    aiding"); ``speed`` already divided by ``1 + k`` of the odometer scale estimate."""
    vel_v, mat_vn = _vehicle_velocity(mat_nb, vel_n, mat_vb, lever_vel_b)
    H = np.zeros((1, N_ERROR))
    H[0, ATT] = (mat_vn @ skew(vel_n))[0]
    H[0, VEL] = mat_vn[0]
    return Linearized(np.array([speed - vel_v[0]]), H, np.array([[var]]), "odo", vel_v)


def mount_rotation(mount_error: FloatArray) -> FloatArray:
    """The mounting error's rotation of the vehicle frame, ``exp([(0, pitch, yaw) x])``
    (3, 3), of the mounting pitch and yaw errors ``mount_error`` (2,) [rad]: the true
    ``mat_vb`` is this times the configured one (docs/filter.md, "Ground-vehicle aiding")."""
    out = np.empty((3, 3))  # the strapdown's Rodrigues (scipy costs ~20 us a call)
    rotvec_matrix(0.0, float(mount_error[0]), float(mount_error[1]), out)
    return out


def lever_jacobian(
    lin: Linearized, mat_vb: FloatArray | None, gyro_b: FloatArray | None
) -> FloatArray:
    """``d h / d lever`` (dim, 3) of the lever arm's error [m/s / m] for a non-holonomic or
    odometer model at the body rate ``gyro_b`` [rad/s] and the mounting ``mat_vb``, zero for
    the others (docs/filter.md, "Ground-vehicle aiding"): the reference point's velocity
    ``v_v`` has ``mat_vb (omega_b x lever)``, so ``d v_v / d lever = mat_vb [omega_b x]``
    (the model's rows: the NHC's lateral and vertical, the odometer's forward). The model is
    linear in the lever arm: exact with the configured mounting, first order with a mounting
    estimate ``e`` (which turns these columns by ``|e|``).
    """
    out = np.zeros((lin.H.shape[0], 3))
    if gyro_b is None:
        return out
    cols = skew(gyro_b) if mat_vb is None else mat_vb @ skew(gyro_b)
    if lin.name == "nhc":
        out[:] = cols[1:3]
    elif lin.name == "odo":
        out[:] = cols[0:1]
    return out


def mount_jacobian(lin: Linearized) -> FloatArray:
    """``d h / d (pitch, yaw)`` (dim, 2) of the mounting error for a non-holonomic or
    odometer model [m/s / rad], zero for the others (docs/filter.md, "Ground-vehicle
    aiding"). With ``mat_vb = exp([e x]) mat_vb_configured``, ``e = (0, pitch, yaw)``, the
    reference point's velocity ``v_v`` (``lin.vel_v``) turns to ``v_v + e x v_v``, so
    ``d v_v / d e = -[v_v x]``; its columns y, z and the model's rows: the NHC's lateral
    and vertical rows ``(0, v_x)``, ``(-v_x, 0)``, the odometer's forward row ``(v_z, -v_y)``.
    Exact at a zero estimate, first order elsewhere: the state is additive,
    ``exp([(e + d) x]) = exp([J_l(e) d x]) exp([e x])`` with ``J_l = I + O(|e|)``.
    """
    out = np.zeros((lin.H.shape[0], 2))
    if lin.vel_v is None:
        return out
    cols = -skew(lin.vel_v)[:, 1:3]
    if lin.name == "nhc":
        out[:] = cols[1:3]
    elif lin.name == "odo":
        out[:] = cols[0:1]
    return out


def _vehicle_velocity(
    mat_nb: FloatArray, vel_n: FloatArray, mat_vb: FloatArray | None, lever_vel_b: FloatArray | None
) -> tuple[FloatArray, FloatArray]:
    """Velocity of the vehicle's reference point in the vehicle frame,
    ``mat_vb (mat_bn vel_n + omega_b x lever_arm_b)``, and ``mat_vn = mat_vb mat_bn``."""
    mat_vn = mat_nb.T if mat_vb is None else mat_vb @ mat_nb.T
    vel_v = mat_vn @ vel_n
    if lever_vel_b is not None:
        vel_v = vel_v + (lever_vel_b if mat_vb is None else mat_vb @ lever_vel_b)
    return vel_v, mat_vn


def _basis(s_b: FloatArray) -> FloatArray:
    s = s_b / np.linalg.norm(s_b)
    helper = np.zeros(3)
    helper[int(np.argmin(np.abs(s)))] = 1.0
    e1 = np.cross(s, helper)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(s, e1)], axis=-1)


# ----------------------------------------------------------------------------- public
def yaw_measurement(
    rot_nb: Rotation | ArrayLike,
    yaw: float,
    yaw_std: float,
    *,
    sun_n: ArrayLike | None = None,
    rot_nb_prior: Rotation | ArrayLike | None = None,
) -> Linearized:
    """Polarization (or any absolute) yaw measurement, docs/model.md §10.2 "Filter update".

    Without ``sun_n``, ``h(x)`` is the yaw of body x of the attitude. With ``sun_n`` the
    model is the yaw as :func:`polins.measure` computes it, including the docs/model.md §10.2 tilt
    coupling in ``H`` (instead of the cot(Z) inflation of ``R``): the camera sees the sun
    in the body frame, ``sun_b = mat_bn(x) sun_n``, and ``polins.measure`` levels it with
    the tilt of its prior ``P`` (``rot_nb_prior``), so::

        h(x) = alpha_s + yaw_P - azimuth(mat_nb_P mat_bn(x) sun_n)

    with ``alpha_s`` the azimuth of ``sun_n`` (ENU, counter-clockwise from East) and
    ``yaw_P`` the prior's yaw; ``h = yaw(x)`` when the prior equals ``x``. With the error
    state ``mat_bn(x (+) dtheta) = mat_bn exp(-[dtheta x])``, and ``M = mat_nb_P mat_bn``,
    ``b = M sun_n``::

        H_theta = -grad(b)^T M [sun_n x],   grad(b) = (-b_y, b_x, 0) / (b_x^2 + b_y^2)

    which for ``P = x`` is ``[-a_x a_z, -a_y a_z, a_x^2 + a_y^2] / (a_x^2 + a_y^2)`` with
    ``a = sun_n``: a tilt ``d`` about the horizontal axis towards the sun moves the
    measured yaw by ``-cot(Z) d``. With the fixed-zenith estimator
    (``MeasureOptions.fixed_zenith``) the image gives only the sun's azimuth in the level
    frame of the prior; by the symmetry of the sky about the solar meridian its first-order
    dependence on the attitude is the same (tests/test_eskf.py checks the model against
    ``polins.measure`` with a prior off the truth).

    Parameters
    ----------
    rot_nb : Rotation or (3, 3) array_like
        Nominal attitude, body FLU -> ENU (a Rotation, or the matrix ``mat_nb``).
    yaw : float
        Measured ENU yaw of body x [rad] (docs/conventions.md).
    yaw_std : float
        Its 1-sigma [rad], e.g. ``Measurement.yaw_std`` (already inflated per docs/model.md §10.2).
    sun_n : (3,) array_like, optional
        ENU sun vector: the yaw was computed by ``polins.measure`` (tilt-coupled model).
    rot_nb_prior : Rotation or (3, 3) array_like, optional
        The ``rot_nb_prior`` given to ``polins.measure`` for this image (needs ``sun_n``);
        default: the nominal attitude ``rot_nb`` (a filter measuring with its own state).

    Returns
    -------
    Linearized
        ``residual = wrap(yaw - h(x))``, ``H`` on the attitude error only, ``R = yaw_std^2``.
    """
    mat = as_mat_nb(rot_nb)
    if not np.isfinite(yaw):
        raise ValueError(f"yaw must be finite [rad], got {yaw!r}")
    s_n = None if sun_n is None else _vector3(sun_n, "sun_n", unit=True)
    prior = None if rot_nb_prior is None else as_mat_nb(rot_nb_prior)
    if prior is not None and s_n is None:
        raise ValueError("rot_nb_prior needs sun_n (the tilt-coupled model)")
    return yaw_kernel(mat, float(yaw), float(_variance(yaw_std, 1, "yaw_std")[0]), s_n, prior)


def sun_basis_b(sun_b: ArrayLike) -> FloatArray:
    """Orthonormal basis ``(3, 2)`` of the plane perpendicular to a unit vector ``sun_b``."""
    return _basis(_vector3(sun_b, "sun_b", unit=True))


def sun_measurement(
    rot_nb: Rotation | ArrayLike,
    sun_b: ArrayLike,
    sun_n: ArrayLike,
    sun_std: float,
    *,
    basis_b: ArrayLike | None = None,
) -> Linearized:
    """Sun-vector direction measurement (2 degrees of freedom).

    The camera measures the sun direction in the body frame, ``sun_b`` (``Measurement.sun_b``);
    the ephemeris gives ``sun_n``. Prediction ``h(x) = mat_bn(x) sun_n``. The residual is the
    measured direction minus the prediction projected on a basis ``E`` of the plane
    perpendicular to the predicted direction: ``residual = E^T (sun_b - h)`` (small-angle
    components [rad]). It observes the attitude error except the rotation about ``sun_n``,
    hence yaw and tilt.

    Parameters
    ----------
    rot_nb : Rotation or (3, 3) array_like
        Nominal attitude, body FLU -> ENU.
    sun_b : (3,) array_like
        Measured unit sun vector, body frame (normalised here).
    sun_n : (3,) array_like
        Reference unit sun vector, ENU (``polins.sun_vector_n``).
    sun_std : float
        Direction 1-sigma per tangent axis [rad] (``Measurement.sun_std``).
    basis_b : (3, 2) array_like, optional
        Tangent basis to use instead of :func:`sun_basis_b` of the prediction (for
        evaluating the same residual function at perturbed states).

    Returns
    -------
    Linearized
        ``H[:, 0:3] = (mat_nb E)^T [sun_n x]`` and ``R = sun_std^2 I_2``.
    """
    mat = as_mat_nb(rot_nb)
    basis = None
    if basis_b is not None:
        basis = np.asarray(basis_b, dtype=float)
        if basis.shape != (3, 2):
            raise ValueError(f"basis_b must have shape (3, 2), got {basis.shape}")
    return sun_kernel(
        mat,
        _vector3(sun_b, "sun_b", unit=True),
        _vector3(sun_n, "sun_n", unit=True),
        float(_variance(sun_std, 1, "sun_std")[0]),
        basis,
    )


def zero_velocity(vel_n: ArrayLike, std: ArrayLike) -> Linearized:
    """Zero-velocity update (vehicle at rest): ``z = 0``, ``h(x) = vel_n`` [m/s].

    Parameters
    ----------
    vel_n : (3,) array_like
        Nominal ENU velocity [m/s].
    std : float or (3,) array_like
        1-sigma of the zero-velocity pseudo-measurement [m/s].
    """
    return zero_velocity_kernel(_vector3(vel_n, "vel_n"), _variance(std, 3, "zero-velocity std"))


def zero_rate(
    rot_nb: Rotation | ArrayLike,
    gyro_b: ArrayLike,
    bias_b: ArrayLike,
    std: ArrayLike,
    *,
    rate_n: ArrayLike | None = None,
) -> Linearized:
    """Zero angular rate (the body at rest): the gyro's mean over an interval at rest
    observes its bias (docs/filter.md §12, "Zero angular rate").

    ``z = gyro_b`` (the mean measured rate [rad/s]), ``h(x) = b_g + mat_bn rate_n`` with
    ``rate_n`` the rate a body at rest senses (the Earth rate in ENU when the mechanization
    has it; None: the bias state carries it). ``H = [mat_bn [rate_n x] | 0 | 0 | I | 0]``
    (``mat_bn exp(-[dtheta x]) rate_n``, docs/filter.md §2.2), ``R = diag(std^2)``: for the
    mean of ``m`` samples at the interval ``dt``, ``std = ARW / sqrt(m dt)``.

    Parameters
    ----------
    rot_nb : Rotation or (3, 3) array_like
        Nominal attitude, body FLU -> ENU.
    gyro_b : (3,) array_like
        Mean measured body rate over the interval at rest [rad/s].
    bias_b : (3,) array_like
        Nominal gyro bias [rad/s].
    std : float or (3,) array_like
        1-sigma of the mean rate [rad/s].
    rate_n : (3,) array_like, optional
        ENU rate sensed at rest [rad/s] (:func:`polins.ins.earth.earth_rate_n`).
    """
    return zero_rate_kernel(
        as_mat_nb(rot_nb), _vector3(gyro_b, "gyro_b"), _vector3(bias_b, "bias_b"),
        _variance(std, 3, "zero-rate std"), None if rate_n is None else _vector3(rate_n, "rate_n"),
    )  # fmt: skip


def level(
    rot_nb: Rotation | ArrayLike, force_b: ArrayLike, bias_b: ArrayLike, std: ArrayLike
) -> Linearized:
    """Levelling (the body at rest): the accelerometer's mean over an interval measures
    gravity, no horizontal specific force in ENU (docs/filter.md §7, §12.1).

    ``z = 0``, ``h(x) = (mat_nb (force_b - b_a))[E, N]`` [m/s^2] with ``force_b`` the mean
    measured specific force; ``H_theta = -[f_n x]`` (rows E, N; ``f_n`` the specific force
    in ENU, ``exp([dtheta x]) f_n``), ``H_ba = -mat_nb`` (rows E, N), ``R = diag(std^2)``:
    for the mean of ``m`` samples at the interval ``dt``, ``std = VRW / sqrt(m dt)``. The
    vertical component is not used (it would measure gravity's magnitude, not the tilt).
    The graph's self-alignment factor uses this model (``levelling_factor``).

    Parameters
    ----------
    rot_nb : Rotation or (3, 3) array_like
        Nominal attitude, body FLU -> ENU.
    force_b : (3,) array_like
        Mean measured specific force over the interval at rest [m/s^2].
    bias_b : (3,) array_like
        Nominal accelerometer bias [m/s^2].
    std : float or (2,) array_like
        1-sigma of the mean's horizontal components [m/s^2].
    """
    return level_kernel(
        as_mat_nb(rot_nb), _vector3(force_b, "force_b"), _vector3(bias_b, "bias_b"),
        _variance(std, 2, "levelling std"),
    )  # fmt: skip


def non_holonomic(
    rot_nb: Rotation | ArrayLike,
    vel_n: ArrayLike,
    std: ArrayLike,
    *,
    mat_vb: ArrayLike | None = None,
    lever_vel_b: ArrayLike | None = None,
) -> Linearized:
    """Non-holonomic constraint of a ground vehicle: no lateral, no vertical velocity of
    its reference point in the vehicle frame (docs/filter.md, "Ground-vehicle aiding").

    ``z = 0``, ``h(x) = (mat_vb (mat_bn vel_n + omega_b x lever_arm_b))[1:3]`` (vehicle y
    and z velocity) [m/s]; with the IMU aligned at the reference point, the body y and z
    velocity. With ``v_b = mat_bn exp(-dtheta)(vel_n + dv_n)``: ``dh/ddtheta = mat_vb
    mat_bn [vel_n x]``, ``dh/ddv_n = mat_vb mat_bn`` (rows y and z); ``omega_b x
    lever_arm_b`` is taken as known (the measured rate).

    Parameters
    ----------
    rot_nb : Rotation or (3, 3) array_like
        Nominal attitude, body FLU -> ENU.
    vel_n : (3,) array_like
        Nominal ENU velocity [m/s].
    std : float or (2,) array_like
        1-sigma of the lateral and vertical pseudo-measurements [m/s].
    mat_vb : (3, 3) array_like, optional
        IMU mounting: body -> vehicle frame (default identity).
    lever_vel_b : (3,) array_like, optional
        ``omega_b x lever_arm_b`` [m/s]: the reference point's velocity relative to the
        IMU, body axes (default zero).
    """
    return non_holonomic_kernel(
        as_mat_nb(rot_nb), _vector3(vel_n, "vel_n"), _variance(std, 2, "non-holonomic std"),
        None if mat_vb is None else as_mat_nb(mat_vb),
        None if lever_vel_b is None else _vector3(lever_vel_b, "lever_vel_b"),
    )  # fmt: skip


def yaw_from_sun(rot_nb: Rotation | ArrayLike, sun_b: ArrayLike, sun_n: ArrayLike) -> float:
    """Yaw [rad] from a measured body sun vector using the tilt of ``rot_nb`` (docs/model.md §10.1).

    ``yaw = wrap(alpha_s^n - atan2(s^l_y, s^l_x))`` with ``s^l = mat_lb s^b`` and
    ``alpha_s^n = atan2(sun_n_y, sun_n_x)``. Used for self-alignment from a sun vector.
    """
    if not isinstance(rot_nb, Rotation):
        rot_nb = Rotation.from_matrix(as_mat_nb(rot_nb))
    s_l = rot_lb_from_rot_nb(rot_nb).apply(_vector3(sun_b, "sun_b", unit=True))
    s_n = _vector3(sun_n, "sun_n", unit=True)
    return float(wrap_angle(np.arctan2(s_n[1], s_n[0]) - np.arctan2(s_l[1], s_l[0])))
