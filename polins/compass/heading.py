"""Heading from a sun vector: the level frame, the yaw, its variance, and the 180 deg choice.

The level frame ``l`` has z Up and x the horizontal projection of body x
(docs/conventions.md), so ``rot_nb = Rz(yaw) rot_lb`` (docs/model.md §2) and a sun seen in
the level frame gives the yaw directly (docs/model.md §10.1)::

    yaw = wrap(atan2(s_n_y, s_n_x) - atan2(s_l_y, s_l_x))

An eigenvector has no sign: the sun is above the horizon (``s_l_z > 0``), and only within a
few degrees of the horizon does the prior yaw choose between yaw and yaw + 180 deg
(:func:`resolve_sun_sign`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from polins.errors import UserInputError
from polins.frames import wrap_angle, yaw_from_rot_nb
from polins.models import CameraModel

FloatArray = NDArray[np.float64]

__all__ = [
    "Geometry",
    "check_sun_and_attitude",
    "filter_sigmas",
    "image_geometry",
    "level_frames",
    "resolve_sun_sign",
    "sun_level_from_angles",
    "yaw_from_sun_level",
    "yaw_variance_from_sun_covariance",
]


def check_sun_and_attitude(
    sun_n: ArrayLike, rot_nb: Rotation, name: str = "rot_nb_prior"
) -> FloatArray:
    """The unit ENU sun ``(3,)`` after checking ``sun_n`` and the attitude ``rot_nb``
    (called ``name`` in the message).

    Raises
    ------
    ValueError
        ``sun_n`` is not a finite non-zero (3,) vector, or ``rot_nb`` not one Rotation.
    """
    s = np.asarray(sun_n, dtype=float)
    if s.shape != (3,) or not np.all(np.isfinite(s)) or not np.linalg.norm(s) > 0:
        raise ValueError(f"sun_n must be a finite (3,) ENU vector, got {s!r}")
    if not isinstance(rot_nb, Rotation) or not rot_nb.single:
        raise ValueError(f"{name} must be a single scipy Rotation (body -> ENU)")
    return s / np.linalg.norm(s)


def level_frames(rot_nb: Rotation, cam: CameraModel) -> tuple[float, NDArray, NDArray, NDArray]:
    """Yaw [rad] of ``rot_nb`` and the matrices ``mat_lb`` (body -> level), ``mat_cl``
    (level -> camera) and ``mat_cn`` (ENU -> camera) of the camera mounted with
    ``cam.mat_bc``."""
    yaw = float(yaw_from_rot_nb(rot_nb))
    c, s = np.cos(yaw), np.sin(yaw)
    mat_nl = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    mat_nb = rot_nb.as_matrix()
    mat_lb = mat_nl.T @ mat_nb
    return yaw, mat_lb, (mat_lb @ cam.mat_bc).T, (mat_nb @ cam.mat_bc).T


def sun_level_from_angles(azimuth_l: float, zenith_l: float) -> FloatArray:
    """Level-frame sun ``(sin Z cos A, sin Z sin A, cos Z)``, A [rad] counter-clockwise from
    x_l, Z [rad] from the vertical."""
    return np.array(
        [
            np.sin(zenith_l) * np.cos(azimuth_l),
            np.sin(zenith_l) * np.sin(azimuth_l),
            np.cos(zenith_l),
        ]
    )


def yaw_from_sun_level(sun_l: ArrayLike, sun_n: ArrayLike) -> float:
    """Yaw [rad] of body x from the sun in the level and navigation frames (docs/model.md
    §10.1): ``wrap(atan2(s_n_y, s_n_x) - atan2(s_l_y, s_l_x))``."""
    sl, sn = np.asarray(sun_l, dtype=float), np.asarray(sun_n, dtype=float)
    return float(wrap_angle(np.arctan2(sn[1], sn[0]) - np.arctan2(sl[1], sl[0])))


def yaw_variance_from_sun_covariance(sun_l: ArrayLike, cov_sun_l: ArrayLike) -> float:
    """Yaw variance [rad^2] ``h^T Cov(s) h``, ``h = (-s_y, s_x, 0)/(s_x^2 + s_y^2)``
    (docs/model.md §10.2)."""
    s = np.asarray(sun_l, dtype=float)
    h = np.array([-s[1], s[0], 0.0]) / (s[0] ** 2 + s[1] ** 2)
    return float(h @ np.asarray(cov_sun_l, dtype=float) @ h)


def resolve_sun_sign(
    sun_l: NDArray, sun_n: NDArray, yaw_prior: float, horizon_fallback: float
) -> FloatArray:
    """The sign of an eigen sun ``(3,)`` (docs/model.md §10.1): above the horizon
    (``s_l_z > 0``); below the elevation ``horizon_fallback`` [rad] the prior yaw [rad]
    chooses between s and -s (yaw and yaw + 180 deg)."""
    s = sun_l if sun_l[2] >= 0 else -sun_l
    if s[2] < np.sin(horizon_fallback):
        err = abs(float(wrap_angle(yaw_from_sun_level(s, sun_n) - yaw_prior)))
        err_flip = abs(float(wrap_angle(yaw_from_sun_level(-s, sun_n) - yaw_prior)))
        if err_flip < err:
            s = -s
    return np.asarray(s, dtype=float)


def filter_sigmas(
    yaw_std_noise: float, yaw_std_model: float, zenith: float, tilt_std: float
) -> tuple[float, float]:
    """The 1-sigmas a filter needs from the parts of a heading sigma (docs/model.md §10.2,
    docs/measurement.md §12).

    Parameters
    ----------
    yaw_std_noise : float
        Pixel-noise part [rad].
    yaw_std_model : float
        Model-error part (jackknife over sky sectors, calibrated) [rad].
    zenith : float
        Sun zenith [rad].
    tilt_std : float
        Roll/pitch sigma about the horizontal axis towards the sun [rad].

    Returns
    -------
    yaw_std : float
        ``sqrt(yaw_std_noise^2 + yaw_std_model^2 + (cot Z tilt_std)^2)`` [rad].
    sun_std : float
        Sun-direction sigma along the azimuth, ``sin Z sqrt(yaw_std_noise^2 +
        yaw_std_model^2)`` [rad] (the tilt belongs in the filter's Jacobian of a vector
        measurement).
    """
    sin_z, cot_z = np.sin(zenith), np.cos(zenith) / np.sin(zenith)
    azimuth_std = float(np.hypot(yaw_std_noise, yaw_std_model))
    yaw_std = np.hypot(azimuth_std, cot_z * tilt_std)
    return float(yaw_std), float(sin_z * azimuth_std)


@dataclass(frozen=True)
class Geometry:
    """The frames of one image (docs/conventions.md).

    Attributes
    ----------
    sun_n : (3,) or None
        Unit ENU sun (None without an ephemeris).
    yaw_prior : float
        Yaw of the prior attitude [rad].
    mat_lb, mat_cl, mat_cn : (3, 3)
        Body -> level, level -> camera, ENU -> camera.
    zenith : float
        Sun zenith [rad] of ``sun_n`` (NaN without it).
    sun_azimuth_b_prior : float or None
        Without ``sun_n``: a prior body-frame sun azimuth [rad] for the 180 deg branch.
    """

    sun_n: NDArray | None
    yaw_prior: float
    mat_lb: NDArray
    mat_cl: NDArray
    mat_cn: NDArray
    zenith: float
    sun_azimuth_b_prior: float | None = None

    @property
    def mat_lc(self) -> NDArray:
        """Camera -> level."""
        return self.mat_cl.T


def image_geometry(
    cam: CameraModel,
    sun_n: ArrayLike | None,
    rot_nb_prior: Rotation | None,
    sun_azimuth_b_prior: float | None = None,
) -> Geometry:
    """The checked sun and the frames of the prior attitude (identity, a level body, when
    there is none and no ``sun_n``); the level frame has x the horizontal projection of
    body x.

    Raises
    ------
    UserInputError
        A bad ``sun_n``, ``rot_nb_prior`` or ``sun_azimuth_b_prior``, or ``sun_n`` without
        ``rot_nb_prior``.
    """
    if sun_azimuth_b_prior is not None and not np.isfinite(sun_azimuth_b_prior):
        raise UserInputError(f"sun_azimuth_b_prior={sun_azimuth_b_prior} must be finite [rad]")
    s_n = None
    if sun_n is None:
        rot = Rotation.identity() if rot_nb_prior is None else rot_nb_prior
        if not isinstance(rot, Rotation) or not rot.single:
            raise UserInputError("rot_nb_prior must be a single scipy Rotation (body -> ENU)")
    elif rot_nb_prior is None:
        raise UserInputError("sun_n needs rot_nb_prior: its roll and pitch level the sun")
    else:
        rot = rot_nb_prior
        s_n = check_sun_and_attitude(sun_n, rot_nb_prior)
    yaw_prior, mat_lb, mat_cl, mat_cn = level_frames(rot, cam)
    zenith = float("nan") if s_n is None else float(np.arccos(np.clip(s_n[2], -1.0, 1.0)))
    return Geometry(s_n, yaw_prior, mat_lb, mat_cl, mat_cn, zenith, sun_azimuth_b_prior)
