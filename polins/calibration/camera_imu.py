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
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import minimize_scalar
from scipy.spatial.transform import Rotation, Slerp

from polins.calibration.images import provenance
from polins.errors import UserInputError

FloatArray = NDArray[np.float64]

__all__ = ["CameraImuResult", "calibrate_camera_imu"]


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
    """

    time_offset_s: float
    time_offset_std_s: float
    mat_bc: FloatArray
    boresight_std: float
    residuals: FloatArray
    provenance: dict[str, Any] = field(default_factory=dict)

    def camera_changes(self) -> dict[str, Any]:
        """The camera-model fields this calibration sets (the time offset belongs to the
        recording, not to the camera file)."""
        return {"mat_bc": self.mat_bc.copy()}


def calibrate_camera_imu(
    t_images: ArrayLike,
    sun_c: ArrayLike,
    t_attitude: ArrayLike,
    rot_nb: Rotation,
    sun_n: ArrayLike,
    *,
    max_offset_s: float = 0.2,
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
        Body-to-ENU attitudes at ``t_attitude`` (slerp-interpolated between them).
    sun_n : array_like, (3,) or (k, 3)
        Unit ENU sun vector: one, or one per attitude sample (it moves ~0.25 deg/min).
    max_offset_s : float
        Search the offset in ``[-max_offset_s, max_offset_s]`` [s].

    Returns
    -------
    CameraImuResult

    Raises
    ------
    UserInputError
        Mismatched shapes, fewer than 10 images inside the attitude record, or a sun that
        stays put in the body frame (no turns).
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
    s_n = np.broadcast_to(np.asarray(sun_n, dtype=float), (t_att.size, 3))
    inside = (t_img - max_offset_s >= t_att[0]) & (t_img + max_offset_s <= t_att[-1])
    if inside.sum() < 10:
        raise UserInputError(
            f"camera-imu: only {int(inside.sum())} images fall inside the attitude record"
        )
    t_img, s_c = t_img[inside], s_c[inside]
    slerp = Slerp(t_att, rot_nb)

    def predicted_b(dt: float) -> FloatArray:
        t = t_img + dt
        sun = np.stack([np.interp(t, t_att, s_n[:, i]) for i in range(3)], -1)
        sun /= np.linalg.norm(sun, axis=1, keepdims=True)
        return slerp(t).inv().apply(sun)

    def misfit(dt: float) -> float:
        _, rssd = Rotation.align_vectors(predicted_b(dt), s_c)
        return float(rssd**2)

    sun_b0 = predicted_b(0.0)
    spread = np.degrees(
        np.arccos(
            np.clip(sun_b0 @ sun_b0.mean(axis=0) / np.linalg.norm(sun_b0.mean(axis=0)), -1, 1)
        )
    )
    if spread.max() < 5.0:
        raise UserInputError(
            "camera-imu: the sun moves less than 5 deg in the body frame; record turns"
        )
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
    rot_bc, _ = Rotation.align_vectors(predicted_b(dt), s_c)
    residuals = np.arccos(np.clip(np.sum(rot_bc.apply(s_c) * predicted_b(dt), axis=1), -1, 1))
    m = residuals.size
    # Standard error of dt from the misfit's curvature, scaled by the residual variance.
    h = 1e-4
    curvature = (misfit(dt + h) - 2.0 * misfit(dt) + misfit(dt - h)) / h**2
    var = float(np.mean(residuals**2))
    dt_std = float(np.sqrt(2.0 * var / curvature)) if curvature > 0 else float("nan")
    boresight_std = float(np.sqrt(var / m))
    return CameraImuResult(
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
