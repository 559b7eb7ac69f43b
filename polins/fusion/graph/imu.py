"""The graph's IMU: integration steps between keyframes, scale-factor variables and the IMU factor that uses them.

:func:`imu_segments` cuts the IMU signal at the keyframes (:class:`ImuSegments`). The gyro
and accelerometer scale factors ``sg, sa`` (3 each, constants) correct the IMU samples as
the ESKF's blocks do, ``omega = (w - b_g) / (1 + sg)`` and ``f = (f_m - b_a) / (1 + sa)``.
To first order in the scale factor this is a bias that changes with every sample,
``diag(w_k) sg``: the preintegrated increments change by ``J_s s`` with ``J_s`` the
bias-Jacobian recursion of Forster et al. (IEEE TRO 2017, Appendix) with ``diag(w_k)`` and
``diag(f_k)`` inserted (:func:`increment_jacobians`, docs/filter.md §9).
:func:`scale_factor_imu_factor` wraps GTSAM's ``CombinedImuFactor`` in a ``CustomFactor``
that adds ``J_s s`` to the wrapped factor's error.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from polins.frames import skew
from polins.fusion.graph.batched import ScaleImuBatch

FloatArray = NDArray[np.float64]

# The scale factors are constants, held per keyframe (``Vector3`` keys ``g<k>``, ``a<k>``)
# and linked by a random walk this slow: sigma * sqrt(dt / CONSTANT_S) per interval, 2 %
# of the turn-on sigma over a 400 s run. One key for the whole run sits in the separator
# of every clique of the Bayes tree; ISAM2 re-eliminates it at every keyframe and then
# back-substitutes the whole tree (docs/filter.md §9).
CONSTANT_S = 1e6


def scale_keys(k: int) -> tuple[int, int]:
    """The keys of ``sg`` and ``sa`` at keyframe ``k``."""
    return int(gtsam.symbol("g", k)), int(gtsam.symbol("a", k))


@dataclass(frozen=True, eq=False)
class ImuSegments:
    """The IMU signal cut at the keyframes: one row per integration step.

    The samples are instantaneous values that vary linearly between rows (docs/filter.md);
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


def increment_jacobians(
    gyro: FloatArray,
    accel: FloatArray,
    dt: FloatArray,
    bounds: NDArray[np.int_],
    *,
    weighted: bool = True,
) -> FloatArray:
    """Jacobians of the preintegrated increments of keyframe intervals with respect to the
    gyro and accelerometer scale factors ``(K - 1, 9, 6)`` (docs/filter.md §9).

    Rows: the rotation increment in Forster's form (``dR(s) = dR Exp(J_R s)``) [rad], the
    position and velocity increments in the frame of the interval's start [m], [m/s]
    (GTSAM's ``NavState`` order: rotation, position, velocity). Columns: ``sg`` (3), then
    ``sa`` (3), dimensionless. The recursion over the steps ``m`` of an interval, with
    ``R`` the rotation from the interval's start and ``D_w = diag(w_m)``, ``D_f =
    diag(f_m)``::

        J_p += J_v dt - 1/2 R [f]x J_R dt^2 - 1/2 R [0, D_f] dt^2
        J_v += -R [f]x J_R dt - R [0, D_f] dt
        J_R  = Exp(w dt)^T J_R - [Jr(w dt) D_w, 0] dt

    vectorised over the intervals (a loop over the step index only).

    Parameters
    ----------
    gyro, accel : (S, 3) ndarray
        The integration steps' rates [rad/s] and specific forces [m/s^2]
        (:class:`ImuSegments`).
    dt : (S,) ndarray
        Step lengths [s].
    bounds : (K,) int ndarray
        Index of every keyframe into the break points (``ImuSegments.bounds``).
    weighted : bool
        False: ``D_w = D_f = I``, the Jacobians with respect to the gyro and accelerometer
        biases (the same recursion GTSAM runs for its bias correction; a check).
    """
    gyro = np.asarray(gyro, dtype=float)
    accel = np.asarray(accel, dtype=float)
    dt = np.asarray(dt, dtype=float)
    counts = np.diff(bounds)
    n_int = counts.size
    phi = gyro * dt[:, None]
    step_rot = Rotation.from_rotvec(phi).as_matrix()
    phi_x = skew(phi)
    jr_step = np.eye(3) - 0.5 * phi_x + phi_x @ phi_x / 6.0  # right Jacobian, O(phi^3)
    eye = np.broadcast_to(np.eye(3), (len(dt), 3, 3))
    d_w = np.einsum("ij,sj->sij", np.eye(3), gyro) if weighted else eye
    d_f = np.einsum("ij,sj->sij", np.eye(3), accel) if weighted else eye
    rot = np.tile(np.eye(3), (n_int, 1, 1))
    jac = np.zeros((n_int, 9, 6))  # rows: rotation, position, velocity
    for m in range(int(counts.max(initial=0))):
        live = np.flatnonzero(counts > m)
        s = bounds[live] + m
        h = dt[s][:, None, None]
        r = rot[live]
        j_r, j_p, j_v = jac[live, 0:3], jac[live, 3:6], jac[live, 6:9]
        r_fx = r @ skew(accel[s])
        j_p = j_p + j_v * h - 0.5 * (r_fx @ j_r) * h**2
        j_v = j_v - (r_fx @ j_r) * h
        j_p[..., 3:] -= 0.5 * (r @ d_f[s]) * h**2
        j_v[..., 3:] -= (r @ d_f[s]) * h
        j_r = np.swapaxes(step_rot[s], 1, 2) @ j_r
        j_r[..., :3] -= (jr_step[s] @ d_w[s]) * h
        jac[live] = np.concatenate([j_r, j_p, j_v], axis=1)
        rot[live] = r @ step_rot[s]
    return jac


# The columns of the CombinedImuFactor's keys X_i, V_i, X_j, V_j, B_i, B_j in its Jacobian.
COLUMNS = ((0, 6), (6, 9), (9, 15), (15, 18), (18, 24), (24, 30))


def scale_factor_imu_factor(
    imu_factor: gtsam.CombinedImuFactor,
    jac: FloatArray,
    sg_key: int,
    sa_key: int,
    batch: ScaleImuBatch | None = None,
) -> gtsam.CustomFactor:
    """A ``CombinedImuFactor`` that also depends on the scale factors ``sg, sa`` (keys
    ``sg_key``, ``sa_key``, ``Vector3``).

    Error (whitened, unit noise model): the wrapped factor's whitened error plus
    ``W G J_s s``, with ``W`` its square-root information, ``J_s = jac`` (9, 6) from
    :func:`increment_jacobians` and ``G = blockdiag(I, R_j^T R_i, R_j^T R_i)`` the
    derivative of GTSAM's ``NavState`` error with respect to the increments (rotation in
    Forster's form; position and velocity in the frame of keyframe ``i``), exact at a
    zero residual; the 6 bias rows do not depend on ``s``. Jacobians: the wrapped
    factor's (via ``linearize``) and ``W G J_s`` for ``sg, sa``. First order in ``s``:
    the neglected terms are ``O(s^2)`` and ``O(s r)`` (``r`` the residual). ``batch``:
    evaluated with the other IMU factors of the graph (:mod:`polins.fusion.graph.batched`).
    """
    keys = [*imu_factor.keys(), sg_key, sa_key]
    model: Any = imu_factor.noiseModel()  # a Gaussian: the preintegration covariance
    sqrt_info: FloatArray = np.array(model.R(), dtype=np.float64)
    jac = np.asarray(jac, dtype=float)
    h_rot = sqrt_info[:, 0:3] @ jac[0:3]  # the rotation rows: G = I
    w_pv = sqrt_info[:, 3:9]
    jac_pv = jac[3:9].reshape(2, 3, 6)
    slot = -1 if batch is None else batch.add(keys, imu_factor, h_rot, w_pv, jac_pv)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians: Any) -> FloatArray:
        if batch is not None:
            hit = batch.lookup(slot, values, jacobians)
            if hit is not None:
                return hit
        mat_i = values.atPose3(keys[0]).rotation().matrix()
        mat_j = values.atPose3(keys[2]).rotation().matrix()
        mat_ji = mat_j.T @ mat_i
        h_s = h_rot + w_pv @ (mat_ji @ jac_pv).reshape(6, 6)
        s = np.concatenate([values.atVector(sg_key), values.atVector(sa_key)])
        if jacobians is None:
            return imu_factor.whitenedError(values) + h_s @ s
        a_mat, b_vec = imu_factor.linearize(values).jacobian()
        # the s-term's rotations: R_i Exp(d_i) gives -R_ji [u]x d_i, R_j Exp(d_j) gives
        # [R_ji u]x d_j, for u = J_p s and J_v s
        u = jac_pv @ s
        a_mat[:, 0:3] -= w_pv @ (mat_ji @ skew(u)).reshape(6, 3)
        a_mat[:, 9:12] += w_pv @ skew(u @ mat_ji.T).reshape(6, 3)
        for i, (lo, hi) in enumerate(COLUMNS):
            jacobians[i] = np.ascontiguousarray(a_mat[:, lo:hi])
        jacobians[6] = np.ascontiguousarray(h_s[:, :3])
        jacobians[7] = np.ascontiguousarray(h_s[:, 3:])
        return -b_vec + h_s @ s

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(15), keys, error)


def scale_factor_priors(gyro_std: float, accel_std: float) -> list[gtsam.NonlinearFactor]:
    """Zero-mean priors of ``sg`` and ``sa`` at the first keyframe with their turn-on
    1-sigmas [-] (``ImuModel.gyro_scale_factor``, ``accel_scale_factor``; 1e-12 if zero)."""
    return [
        gtsam.PriorFactorVector(
            key, np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, max(float(std), 1e-12))
        )
        for key, std in zip(scale_keys(0), (gyro_std, accel_std), strict=True)
    ]


def scale_link_std(gyro_std: float, accel_std: float, dt: float) -> tuple[float, float]:
    """The 1-sigmas [-] of the scale factors' change over ``dt`` [s]: ``std * sqrt(dt /
    CONSTANT_S)`` (at least 1e-12)."""
    f = np.sqrt(dt / CONSTANT_S)
    return max(float(gyro_std) * f, 1e-12), max(float(accel_std) * f, 1e-12)


def scale_factor_links(
    k: int, dt: float, gyro_std: float, accel_std: float
) -> list[gtsam.NonlinearFactor]:
    """``BetweenFactorVector`` from keyframe ``k - 1``'s scale factors to keyframe ``k``'s
    (zero change, :func:`scale_link_std` over the interval ``dt`` [s])."""
    return [
        gtsam.BetweenFactorVector(ki, kj, np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, std))
        for ki, kj, std in zip(
            scale_keys(k - 1), scale_keys(k), scale_link_std(gyro_std, accel_std, dt), strict=True
        )
    ]
