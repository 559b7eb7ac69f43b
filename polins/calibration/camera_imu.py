"""Camera-IMU calibration: the camera's time offset and its camera-to-body rotation from a recording with turns.

With the clock and the site known, the ephemeris gives the sun in ENU (``sun_n``), the
IMU (or the fused solution) gives the attitude ``rot_nb(t)``, and every camera image gives
the sun in the camera frame (``sun_c``, e.g. ``Measurement.sun_b`` turned back through the
base camera's ``mat_bc``). For an image stamped ``t_j`` on the camera's clock::

    sun_c_j = mat_bc^T  rot_nb(t_j + dt)^T  sun_n(t_j + dt)

so the rotation ``mat_bc`` is the solution of Wahba's problem between the predicted body
vectors and the measured camera vectors (``scipy.spatial.transform.Rotation.align_vectors``),
and the time offset ``dt`` [s] (camera clock minus IMU clock) the scalar that minimises
its residual (``scipy.optimize.minimize_scalar``). A 10 ms offset during a 45 deg/s turn
is 0.45 deg of heading, and a boresight error goes one to one into heading
(docs/calibrate.md#camera-imu). The turns make both observable: without them the sun
stays at one place in the body frame, and a rotation about it is unobservable.

**Without the clock** (``sun_n=None``; docs/calibrate.md#camera-imu-without-a-clock) the
attitude need not be absolute either: any reference frame will do (the gyro integrated
from the first sample, or a fused solution). Over a short recording the sun is fixed in
that frame up to a slow drift (in ENU it moves about 0.25 deg/min; in the frame of an
integrated gyro, which does not turn with the Earth, it stays put, and a vertical gyro
bias turns the frame slowly), so every measured camera vector, carried into the reference
frame, must land on one direction ``sun_r(t) = normalise(s0 + (t - t_mid) v)``, ``v``
perpendicular to ``s0``::

    mat_bc  sun_c_j = rot_rb(t_j + dt)^T  sun_r(t_j + dt)

``dt``, ``mat_bc``, ``s0`` (2 unknowns) and, optionally, the drift ``v`` (2) are fitted
jointly by ``scipy.optimize.least_squares``, with standard errors from its Jacobian. What
this cannot see: a rotation common to the reference frame and the sun (none is needed),
and, when every turn is about one body axis ``a``, a boresight rotation about ``a``,
which trades one for one with the sun's azimuth about ``a`` (with turns about the vertical:
the boresight's yaw, i.e. the absolute heading, needs the clock). Such an axis is held at
the start value (the base camera's ``mat_bc``), named in the result and warned about.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares, minimize_scalar
from scipy.spatial.transform import Rotation, Slerp

from polins.calibration.images import provenance
from polins.errors import UserInputError

FloatArray = NDArray[np.float64]

__all__ = [
    "CameraImuResult",
    "HeldAxisWarning",
    "calibrate_camera_imu",
    "fit_ephemeris_sun",
    "fit_fixed_sun",
]

BORESIGHT_STD_MAX_DEG = 0.1  # hold a boresight axis known worse than this [deg] (no clock)
BORESIGHT_PRIOR_STD = np.radians(10.0)  # weak prior on the boresight's change [rad] (no clock)
OUTLIER_FACTOR = 6.0  # drop images whose residual exceeds this many times the median


class HeldAxisWarning(UserWarning):
    """The no-clock camera-IMU fit cannot see the boresight about one axis and held it."""


@dataclass(frozen=True)
class CameraImuResult:
    """Camera time offset and camera-to-body rotation.

    Attributes
    ----------
    time_offset_s : float
        ``dt`` [s]: add it to a camera timestamp to get the IMU time of the image.
    time_offset_std_s : float
        Its standard error [s] (from the curvature of the residual).
    mat_bc : (3, 3)
        Camera-to-body rotation.
    boresight_std : float
        RMS angular residual over sqrt(number of images) [rad]: the order of the
        rotation's standard error.
    residuals : (m,)
        Angle between measured and predicted sun vectors per image [rad].
    provenance : dict
    mode : {"clock", "no-clock"}
        Ephemeris sun in ENU, or one unknown sun in the attitude's reference frame.
    boresight_std_b : (3,)
        No clock: standard errors [rad] of the boresight about the body axes x, y, z
        (near 0 about a held axis); with the clock: ``boresight_std`` on each axis.
    held_axis_b : (3,) or None
        No clock: the body axis about which the boresight could not be seen and was held
        at its start value (the warning says so); None when all three were fitted.
    sun_r : (3,) or None
        No clock: the fitted sun direction in the attitude's reference frame at the
        middle of the record.
    sun_drift_deg_per_min : float
        No clock: the fitted drift of that direction [deg/min] (the sun's motion plus a
        turn of the reference frame, e.g. a vertical gyro bias); NaN with the clock.
    """

    time_offset_s: float
    time_offset_std_s: float
    mat_bc: FloatArray
    boresight_std: float
    residuals: FloatArray
    provenance: dict[str, Any] = field(default_factory=dict)
    mode: str = "clock"
    boresight_std_b: FloatArray = field(default_factory=lambda: np.full(3, np.nan))
    held_axis_b: FloatArray | None = None
    sun_r: FloatArray | None = None
    sun_drift_deg_per_min: float = float("nan")

    def camera_changes(self) -> dict[str, Any]:
        """The camera-model fields this calibration sets (the time offset belongs to the
        recording, not to the camera file)."""
        return {"mat_bc": self.mat_bc.copy()}


def calibrate_camera_imu(
    t_images: ArrayLike,
    sun_c: ArrayLike,
    t_attitude: ArrayLike,
    rot_nb: Rotation,
    sun_n: ArrayLike | None = None,
    *,
    max_offset_s: float = 0.2,
    mat_bc_start: ArrayLike | None = None,
    sun_drift: bool = True,
) -> CameraImuResult:
    """Camera time offset and camera-to-body rotation from sun vectors seen during turns.

    Parameters
    ----------
    t_images : array_like, (m,)
        Image timestamps on the camera's clock [s].
    sun_c : array_like, (m, 3)
        Measured unit sun vectors in the camera frame.
    t_attitude : array_like, (k,)
        Attitude timestamps on the IMU clock [s], increasing.
    rot_nb : Rotation, (k,)
        Body-to-ENU attitudes at ``t_attitude`` (slerp-interpolated between them); without
        the clock, body-to-reference attitudes in any fixed reference frame (e.g.
        :func:`polins.calibration.camera_imu_log.gyro_attitude`).
    sun_n : array_like, (3,) or (k, 3), optional
        Unit ENU sun vector from the ephemeris: one, or one per attitude sample (it moves
        ~0.25 deg/min). None: no clock, the sun is fitted (:func:`fit_fixed_sun`).
    max_offset_s : float
        Search the offset in ``[-max_offset_s, max_offset_s]`` [s].
    mat_bc_start : array_like, (3, 3), optional
        No clock: start value of ``mat_bc`` (the base camera's), kept about an axis the
        turns cannot show. Default identity.
    sun_drift : bool
        No clock: fit a linear drift of the sun in the reference frame (default).

    Returns
    -------
    CameraImuResult
        Images whose residual exceeds 6 times the median (a sun vector on the wrong 180 deg
        branch, a cloud) are dropped and the fit repeated; ``provenance["n_outliers"]``
        counts them.

    Raises
    ------
    UserInputError
        Mismatched shapes, fewer than 10 images inside the attitude record, or a sun that
        stays put in the body frame (no turns).

    Warns
    -----
    HeldAxisWarning
        No clock, and turns about one axis only: the boresight about it was held.
    """
    t_img = np.asarray(t_images, dtype=float)
    s_c = np.asarray(sun_c, dtype=float)
    t_att = np.asarray(t_attitude, dtype=float)
    if s_c.shape != (t_img.size, 3) or len(rot_nb) != t_att.size:
        raise UserInputError(
            f"camera-imu: {t_img.size} image times need sun_c of shape ({t_img.size}, 3), got "
            f"{s_c.shape}; {t_att.size} attitude times need as many attitudes, got {len(rot_nb)}"
        )
    s_c = s_c / np.linalg.norm(s_c, axis=1, keepdims=True)
    s_n = None if sun_n is None else np.broadcast_to(np.asarray(sun_n, float), (t_att.size, 3))
    inside = (t_img - max_offset_s >= t_att[0]) & (t_img + max_offset_s <= t_att[-1])
    if inside.sum() < 10:
        raise UserInputError(
            f"camera-imu: only {int(inside.sum())} images fall inside the attitude record"
        )
    t_img, s_c = t_img[inside], s_c[inside]
    mean_c = s_c.mean(axis=0) / np.linalg.norm(s_c.mean(axis=0))
    if np.degrees(np.arccos(np.clip(s_c @ mean_c, -1.0, 1.0))).max() < 5.0:
        raise UserInputError(
            "camera-imu: the sun moves less than 5 deg in the camera frame; record turns"
        )
    slerp = Slerp(t_att, rot_nb)
    rot0 = Rotation.identity() if mat_bc_start is None else Rotation.from_matrix(mat_bc_start)

    def run(keep: NDArray[np.bool_]) -> CameraImuResult:
        if s_n is None:
            return fit_fixed_sun(t_img[keep], s_c[keep], slerp, rot0, max_offset_s=max_offset_s,
                                 sun_drift=sun_drift)  # fmt: skip
        return fit_ephemeris_sun(t_img[keep], s_c[keep], slerp, t_att, s_n, max_offset_s)

    # Images whose residual is far beyond the others' (a sun vector on the wrong 180 deg
    # branch, a cloud) are dropped and the fit repeated, up to three times.
    keep = np.ones(t_img.size, dtype=bool)
    for _ in range(4):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", HeldAxisWarning)
            result = run(keep)
        outlier = result.residuals > OUTLIER_FACTOR * np.median(result.residuals)
        if not outlier.any() or keep.sum() - outlier.sum() < 10:
            break
        keep[np.flatnonzero(keep)[outlier]] = False
    for w in caught:
        warnings.warn(w.message, w.category, stacklevel=2)
    n_out = int((~keep).sum())
    if n_out:
        result = replace(result, provenance={**result.provenance, "n_outliers": n_out})
    return result


def fit_ephemeris_sun(
    t_images: FloatArray,
    sun_c: FloatArray,
    slerp: Slerp,
    t_att: FloatArray,
    s_n: FloatArray,
    max_offset_s: float,
) -> CameraImuResult:
    """Clock camera-IMU fit: Wahba's problem between ephemeris sun vectors in the body frame
    and the measured camera vectors, the time offset by a grid and a bounded scalar search
    (module docstring; docs/calibrate.md#camera-imu).

    Parameters
    ----------
    t_images : (m,)
        Image times on the camera clock [s], inside the attitude record by ``max_offset_s``.
    sun_c : (m, 3)
        Measured unit sun vectors in the camera frame.
    slerp : scipy.spatial.transform.Slerp
        Body-to-ENU attitude as a function of IMU time [s].
    t_att : (k,)
        Attitude times [s].
    s_n : (k, 3)
        Unit ENU sun vector at ``t_att``.
    max_offset_s : float
        Search the offset in ``[-max_offset_s, max_offset_s]`` [s].

    Returns
    -------
    CameraImuResult
        ``mode="clock"``.
    """

    def predicted_b(dt: float) -> FloatArray:
        t = t_images + dt
        sun = np.stack([np.interp(t, t_att, s_n[:, i]) for i in range(3)], -1)
        sun /= np.linalg.norm(sun, axis=1, keepdims=True)
        return slerp(t).inv().apply(sun)

    def misfit(dt: float) -> float:
        _, rssd = Rotation.align_vectors(predicted_b(dt), sun_c)
        return float(rssd**2)

    # A coarse grid first (the misfit may have side minima over a wide search), then a
    # bounded scalar search around its best point.
    grid = np.linspace(-max_offset_s, max_offset_s, 81)
    best = grid[int(np.argmin([misfit(x) for x in grid]))]
    step = grid[1] - grid[0]
    sol = minimize_scalar(
        misfit,
        bounds=(max(best - step, -max_offset_s), min(best + step, max_offset_s)),
        method="bounded",
        options={"xatol": 1e-6},
    )
    dt = float(sol.x)
    rot_bc, _ = Rotation.align_vectors(predicted_b(dt), sun_c)
    residuals = np.arccos(np.clip(np.sum(rot_bc.apply(sun_c) * predicted_b(dt), axis=1), -1, 1))
    m = residuals.size
    # Standard error of dt from the misfit's curvature, scaled by the residual variance.
    h = 1e-4
    curvature = (misfit(dt + h) - 2.0 * misfit(dt) + misfit(dt - h)) / h**2
    var = float(np.mean(residuals**2))
    dt_std = float(np.sqrt(2.0 * var / curvature)) if curvature > 0 else float("nan")
    boresight_std = float(np.sqrt(var / m))
    return CameraImuResult(
        mode="clock",
        boresight_std_b=np.full(3, boresight_std),
        time_offset_s=dt,
        time_offset_std_s=dt_std,
        mat_bc=rot_bc.as_matrix(),
        boresight_std=boresight_std,
        residuals=residuals,
        provenance=provenance(
            "camera-imu",
            "Wahba fit of ephemeris sun vectors in the body frame to measured camera sun "
            "vectors, time offset by bounded scalar search (docs/calibrate.md#camera-imu)",
            m,
            time_offset_s=float(f"{dt:.6g}"),
            residual_rms_deg=float(f"{np.degrees(np.sqrt(var)):.3g}"),
        ),
    )


def fit_fixed_sun(
    t_images: FloatArray,
    sun_c: FloatArray,
    slerp: Slerp,
    rot_bc_start: Rotation,
    *,
    max_offset_s: float = 0.2,
    sun_drift: bool = True,
    max_boresight_std_deg: float = BORESIGHT_STD_MAX_DEG,
) -> CameraImuResult:
    """No-clock camera-IMU fit: ``dt``, ``mat_bc`` and one (drifting) sun in the attitude's
    reference frame (module docstring; docs/calibrate.md#camera-imu-without-a-clock).

    Parameters
    ----------
    t_images : (m,)
        Image times on the camera clock [s], inside the attitude record by ``max_offset_s``.
    sun_c : (m, 3)
        Measured unit sun vectors in the camera frame.
    slerp : scipy.spatial.transform.Slerp
        Body-to-reference attitude as a function of IMU time [s].
    rot_bc_start : Rotation
        Start value of the camera-to-body rotation, kept about an axis the turns cannot show.
    max_offset_s : float
        Offsets are started from a grid over ``[-max_offset_s, max_offset_s]`` [s].
    sun_drift : bool
        Fit a linear drift of the sun in the reference frame (2 unknowns).
    max_boresight_std_deg : float
        Hold the boresight about an axis whose standard error exceeds this [deg].

    Returns
    -------
    CameraImuResult
        ``mode="no-clock"``; ``held_axis_b`` when an axis was held.
    """
    m = t_images.size
    t_mid = 0.5 * (t_images[0] + t_images[-1])
    tau = (t_images - t_mid) / 60.0  # [min]: the drift in rad/min is of order 1e-3
    s0 = np.mean(slerp(t_images).apply(rot_bc_start.apply(sun_c)), axis=0)
    s0 /= np.linalg.norm(s0)
    tangent = np.linalg.svd(s0[None, :])[2][1:]  # (2, 3): orthonormal, perpendicular to s0
    n_drift = 2 if sun_drift else 0

    def unpack(x: FloatArray, axes: FloatArray) -> tuple[float, Rotation, FloatArray]:
        dt, k = float(x[0]), axes.shape[0]
        rot_bc = Rotation.from_rotvec(x[1 : 1 + k] @ axes) * rot_bc_start
        ab = x[1 + k : 3 + k]
        rate = x[3 + k : 3 + k + n_drift] if sun_drift else np.zeros(2)
        sun = s0 + (ab[None, :] + tau[:, None] * rate[None, :]) @ tangent  # (m, 3)
        return dt, rot_bc, sun / np.linalg.norm(sun, axis=1, keepdims=True)

    def residual(x: FloatArray, axes: FloatArray) -> FloatArray:
        dt, rot_bc, sun = unpack(x, axes)
        predicted_b = slerp(t_images + dt).inv().apply(sun)
        # A weak prior (BORESIGHT_PRIOR_STD, weighted as if the residuals were 1 mrad)
        # keeps an unobservable axis from wandering; an observable one hardly feels it.
        prior = x[1 : 1 + axes.shape[0]] * (1e-3 / BORESIGHT_PRIOR_STD)
        return np.concatenate([(predicted_b - rot_bc.apply(sun_c)).ravel(), prior])

    def solve(axes: FloatArray) -> Any:
        """Least squares from a grid of offsets (side minima), the best solution."""
        best = None
        for dt0 in np.linspace(-max_offset_s, max_offset_s, 5):
            x0 = np.concatenate([[dt0], np.zeros(axes.shape[0] + 2 + n_drift)])
            sol = least_squares(residual, x0, args=(axes,), x_scale="jac", method="lm", xtol=1e-12)
            inside = abs(sol.x[0]) <= max_offset_s
            if inside and (best is None or sol.cost < best.cost):
                best = sol
        if best is None:
            raise UserInputError(
                f"camera-imu: no time offset within +-{max_offset_s:g} s explains the images"
            )
        return best

    def covariance(sol: Any) -> FloatArray:
        dof = 2 * m - sol.x.size  # two angular components per image
        var = float(np.sum(sol.fun[: 3 * m] ** 2)) / max(dof, 1)
        jac = sol.jac[: 3 * m]
        info = jac.T @ jac / var
        k = sol.x.size - 3 - n_drift
        info[1 : 1 + k, 1 : 1 + k] += np.eye(k) / BORESIGHT_PRIOR_STD**2
        return np.asarray(np.linalg.inv(info), dtype=float)

    axes = np.eye(3)
    sol = solve(axes)
    cov = covariance(sol)
    eigval, eigvec = np.linalg.eigh(cov[1:4, 1:4])
    held = None
    if np.sqrt(max(eigval[-1], 0.0)) > np.radians(max_boresight_std_deg):
        held = eigvec[:, -1] * np.sign(eigvec[np.argmax(np.abs(eigvec[:, -1])), -1])
        warnings.warn(
            "camera-imu without a clock: the turns are all about one body axis "
            f"({np.array2string(held, precision=2)}); the boresight about it trades with the "
            "sun's direction and is held at the start value (use the clock, or tilt the "
            "platform during the turns)",
            HeldAxisWarning,
            stacklevel=2,
        )
        axes = eigvec[:, :2].T
        sol = solve(axes)
        cov = covariance(sol)
    k = axes.shape[0]
    dt, rot_bc, _ = unpack(sol.x, axes)
    std_b = np.sqrt(np.maximum(np.diag(axes.T @ cov[1 : 1 + k, 1 : 1 + k] @ axes), 0.0))
    diff = sol.fun[: 3 * m].reshape(m, 3)
    residuals = 2.0 * np.arcsin(np.clip(0.5 * np.linalg.norm(diff, axis=1), 0.0, 1.0))
    rate = sol.x[3 + k : 3 + k + n_drift] if sun_drift else np.zeros(2)
    drift = float(np.degrees(np.linalg.norm(rate)))
    dt_std = float(np.sqrt(max(cov[0, 0], 0.0)))
    sun_mid = s0 + sol.x[1 + k : 3 + k] @ tangent
    rms_deg = float(np.degrees(np.sqrt(np.mean(residuals**2))))
    figures: dict[str, Any] = {
        "time_offset_s": float(f"{dt:.6g}"),
        "time_offset_std_s": float(f"{dt_std:.3g}"),
        "boresight_std_deg": [float(f"{x:.3g}") for x in np.degrees(std_b)],
        "residual_rms_deg": float(f"{rms_deg:.3g}"),
        "sun_drift_deg_per_min": float(f"{drift:.3g}"),
    }
    if held is not None:
        figures["held_axis_b"] = [float(f"{x:.4f}") for x in held]
    return CameraImuResult(
        time_offset_s=dt,
        time_offset_std_s=dt_std,
        mat_bc=rot_bc.as_matrix(),
        boresight_std=float(std_b.max()),
        residuals=residuals,
        provenance=provenance(
            "camera-imu",
            "no clock: one drifting sun in the attitude's reference frame, time offset, "
            "camera-to-body rotation and sun fitted jointly by least squares"
            + (", the boresight about the turn axis held" if held is not None else "")
            + " (docs/calibrate.md#camera-imu-without-a-clock)",
            m,
            **figures,
        ),
        mode="no-clock",
        boresight_std_b=std_b,
        held_axis_b=held,
        sun_r=sun_mid / np.linalg.norm(sun_mid),
        sun_drift_deg_per_min=drift,
    )
