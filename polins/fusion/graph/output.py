"""Output of the graph: keyframe estimates carried to the output times, as one batched NavState.

Between keyframes the state is the preintegrated prediction from the previous keyframe
with the mismatch at the next keyframe spread linearly over the interval (attitude on the
rotation vector, velocity, position); bias and covariance are interpolated linearly. The
IMU steps are integrated per sample in GTSAM; the correction, the geodetic position and
the solution table (:func:`polins.ins.state.solution_table`) are vectorised.
"""

from __future__ import annotations

import gtsam
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from polins.fusion.graph.estimates import Estimates
from polins.fusion.graph.problem import Problem
from polins.fusion.measurement import ATT, BA, BG, N_ERROR, POS, VEL
from polins.ins.state import NavState

FloatArray = NDArray[np.float64]


def nav_state(
    prob: Problem,
    t: FloatArray,
    mat_nb: FloatArray,
    vel_n: FloatArray,
    pos_n: FloatArray,
    bias: FloatArray,
    cov: FloatArray,
    yaw_known: NDArray[np.bool_],
    extra: FloatArray | None = None,
    scale: tuple[FloatArray, FloatArray] | None = None,
) -> NavState:
    """A batched :class:`~polins.ins.state.NavState` from stacked estimates.

    ``mat_nb (N, 3, 3)``, ``vel_n (N, 3)`` [m/s], ``pos_n (N, 3)`` local ENU [m], ``bias
    (N, 6)`` (``bg`` [rad/s], ``ba`` [m/s^2]), ``cov (N, 15 + n, 15 + n)`` in the ESKF's
    order, ``extra (N, n)`` the variables of ``prob.states`` (their ESKF block names),
    ``scale`` the scale factors ``sg, sa (N, 6)`` [-] and their covariance ``(N, 6, 6)``.
    """
    lat, lon, alt_m = prob.geodetic(pos_n)
    sigma = np.sqrt(np.clip(np.diagonal(cov, axis1=1, axis2=2), 0.0, None))
    errors = {"bg": bias[:, 0:3], "ba": bias[:, 3:6]}
    sigmas = {"att": sigma[:, ATT], "vel": sigma[:, VEL], "pos": sigma[:, POS],
              "bg": sigma[:, BG], "ba": sigma[:, BA]}  # fmt: skip
    if scale is not None:  # the ESKF's block order: bg, ba, sg, sa, then the others
        scale_std = np.sqrt(np.clip(np.diagonal(scale[1], axis1=1, axis2=2), 0.0, None))
        errors.update(sg=scale[0][:, :3], sa=scale[0][:, 3:])
        sigmas.update(sg=scale_std[:, :3], sa=scale_std[:, 3:])
    for name, sl in prob.states.index.items():
        assert extra is not None
        errors[name] = extra[:, sl]
        sigmas[name] = sigma[:, N_ERROR + sl.start : N_ERROR + sl.stop]
    return NavState(
        t=np.asarray(t, dtype=float),
        rot_nb=Rotation.from_matrix(mat_nb),
        vel_n=vel_n,
        lat=lat,
        lon=lon,
        alt_m=alt_m,
        errors=errors,
        sigma=sigmas,
        att_cov=cov[:, ATT, ATT],
        yaw_aligned=yaw_known,
    )


def keyframe_output(prob: Problem, est: Estimates) -> NavState:
    """The keyframe estimates themselves (``graph_output="keyframes"``)."""
    return nav_state(
        prob, prob.t_key, est.mat_nb, est.vel_n, est.pos_n, est.bias, est.cov, est.yaw_known,
        est.extra, None if prob.scale_jac is None else (est.scale, est.scale_cov),
    )  # fmt: skip


def interpolate(prob: Problem, est: Estimates, t_out: FloatArray) -> NavState:
    """States at the times ``t_out`` [s] (break points of the IMU steps) between keyframes."""
    seg, t_key = prob.segments, prob.t_key
    n_key = len(t_key)
    idx = np.searchsorted(seg.t, t_out - 1e-9)  # break-point index of each output time
    key = np.clip(np.searchsorted(seg.bounds, idx, side="right") - 1, 0, n_key - 1)
    # Preintegrated predictions at the wanted break points, and at every interval's end.
    wanted = np.zeros(len(seg.t), dtype=bool)
    wanted[idx] = True
    mat_bp = np.empty((len(seg.t), 3, 3))
    vel_bp = np.empty((len(seg.t), 3))
    pos_bp = np.empty((len(seg.t), 3))
    end_mat = np.tile(np.eye(3), (n_key, 1, 1))  # C_bn(end prediction) C_nb(next keyframe)
    d_vel = np.zeros((n_key, 3))  # mismatch at the end of interval k
    d_pos = np.zeros((n_key, 3))
    for k in np.unique(key).tolist():
        lo = seg.bounds[k]
        mat_bp[lo], vel_bp[lo], pos_bp[lo] = est.mat_nb[k], est.vel_n[k], est.pos_n[k]
        if k == n_key - 1:
            continue
        hi = seg.bounds[k + 1]
        state, b = est.values(k)
        corr = prob.imu_correction(state)
        pim = gtsam.PreintegratedCombinedMeasurements(prob.params, b)
        accel, gyro = seg.accel[lo:hi] - corr[3:], seg.gyro[lo:hi] - corr[:3]
        for j, (a, w, dt) in enumerate(zip(accel, gyro, seg.dt[lo:hi], strict=True), lo + 1):
            pim.integrateMeasurement(a, w, dt)
            if j < hi and wanted[j]:
                p = pim.predict(state, b)
                mat_bp[j], vel_bp[j], pos_bp[j] = p.attitude().matrix(), p.velocity(), p.position()
        end = pim.predict(state, b)
        end_mat[k] = end.attitude().matrix().T @ est.mat_nb[k + 1]
        d_vel[k] = est.vel_n[k + 1] - end.velocity()
        d_pos[k] = est.pos_n[k + 1] - end.position()
    d_rot = Rotation.from_matrix(end_mat).as_rotvec()
    span = np.append(np.diff(t_key), 1.0)
    a = ((seg.t[idx] - t_key[key]) / span[key])[:, None]  # fraction of the interval
    nxt = np.minimum(key + 1, n_key - 1)
    mat = mat_bp[idx] @ Rotation.from_rotvec(a * d_rot[key]).as_matrix()
    bias = (1 - a) * est.bias[key] + a * est.bias[nxt]
    extra = (1 - a) * est.extra[key] + a * est.extra[nxt]
    cov = (1 - a[:, :, None]) * est.cov[key] + a[:, :, None] * est.cov[nxt]
    vel = vel_bp[idx] + a * d_vel[key]
    pos = pos_bp[idx] + a * d_pos[key]
    scale = None
    if prob.scale_jac is not None:
        scale = ((1 - a) * est.scale[key] + a * est.scale[nxt],
                 (1 - a[:, :, None]) * est.scale_cov[key] + a[:, :, None] * est.scale_cov[nxt])  # fmt: skip
    return nav_state(prob, t_out, mat, vel, pos, bias, cov, est.yaw_known[key], extra, scale)
