"""The Cramer-Rao lower bound of the yaw from one image of a clear Rayleigh sky.

Per pixel ``L_i = p_i r(zeta_i(theta)) + eps u_i w(theta) + n_i``, ``n_i ~ N(0, sigma_L^2 I)``;
the polarized intensities p_i are nuisance parameters, so only the component along
``n_i = (-sin 2zeta_i, cos 2zeta_i)`` informs theta = (A_l[, Z_l], eps), and the Fisher
information is the joint ML's Jacobian at the truth (docs/errata.md §5,
docs/measurement.md §7)::

    F = sum_i g_i g_i^T / sigma_L^2,   g_i = d(n_i . m_i)/d theta,   CRLB(yaw) = sqrt([F^-1]_AA)
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from polins.compass.camera import pixel_rays_c
from polins.compass.heading import check_sun_and_attitude
from polins.compass.lens import lens_forward_rows
from polins.compass.pixels import pixel_set
from polins.compass.polarimetry import stokes_calibration
from polins.compass.prediction import pixel_data
from polins.compass.residual import ml_evaluate
from polins.compass.skypixels import SNR_MIN
from polins.compass.sunlight import stokes_with_sunlight, sunlight_direction
from polins.frames import rot_lb_from_rot_nb, yaw_from_rot_nb
from polins.models import CameraModel

__all__ = ["yaw_crlb"]


def yaw_crlb(
    cam: CameraModel,
    sun_n: ArrayLike,
    rot_nb: Rotation,
    *,
    dop_max: float,
    radiance: float,
    noise_std: float,
    epsilon: float = 0.0,
    pixel_mask: ArrayLike | None = None,
    fixed_zenith: bool = True,
    sun_exclusion: float = float(np.radians(10.0)),
    dop_min: float = 0.03,
    snr_min: float = SNR_MIN,
) -> float:
    """Cramer-Rao lower bound of the yaw [rad] for a clear Rayleigh sky (docs/errata.md §5).

    ``sigma_L = noise_std * sigma_l_factor`` (ideal sqrt(2) sigma) is the noise of each
    linear Stokes component.

    Parameters
    ----------
    cam : CameraModel
    sun_n : array_like, (3,)
        ENU sun.
    rot_nb : Rotation
        True body -> ENU attitude.
    dop_max, radiance : float
        Rayleigh sky (docs/model.md §6.1, constant radiance [DN]).
    noise_std : float
        Per-channel Gaussian noise [DN].
    epsilon : float
        Direct-sunlight coefficient (always estimated).
    pixel_mask : array_like, (Hs, Ws) bool, optional
        Pixels used; default the field of view, ``sun_exclusion`` [rad], ``DoP >= dop_min``
        and polarized intensity ``>= snr_min sigma_L`` (the estimator's masks on a
        noise-free image).
    fixed_zenith : bool
        Zenith known (the default estimator) or estimated as well.
    sun_exclusion, dop_min, snr_min : float
        The default mask's thresholds, as in :class:`polins.compass.measurement.MeasureOptions`
        and :data:`polins.compass.skypixels.SNR_MIN`.
    """
    s_n = check_sun_and_attitude(sun_n, rot_nb, "rot_nb")
    pixels = pixel_set(cam)
    rays = pixel_rays_c(cam).reshape(-1, 3)[pixels.index]
    rot_lb = rot_lb_from_rot_nb(rot_nb)
    mat_cl = (rot_lb * cam.rot_bc).inv().as_matrix()
    sun_l = Rotation.from_euler("Z", -yaw_from_rot_nb(rot_nb)).apply(s_n)
    sun_c = mat_cl @ sun_l
    cos_t = rays @ sun_c
    dop_v = dop_max * (1 - cos_t**2) / (1 + cos_t**2)
    sigma_l = noise_std * stokes_calibration(cam).sigma_l_factor
    if pixel_mask is None:
        use = (cos_t <= np.cos(sun_exclusion)) & (dop_v >= dop_min)
        use &= radiance * dop_v >= snr_min * sigma_l
    else:
        mask = np.asarray(pixel_mask, dtype=bool)
        if mask.shape != cam.superpixel_shape:
            raise ValueError(f"pixel_mask must have shape {cam.superpixel_shape}")
        use = mask.reshape(-1)[pixels.index]
    forward = lens_forward_rows(np.ascontiguousarray(rays[use].T), cam.polarization_model)
    xy = np.einsum("jkn,k->jn", forward, sun_c)
    e2 = xy[0] ** 2 + xy[1] ** 2
    p = radiance * dop_v[use]
    stokes_sky = np.stack(
        [
            np.full(p.shape, radiance),
            p * (xy[0] ** 2 - xy[1] ** 2) / e2,
            p * 2 * xy[0] * xy[1] / e2,
        ],
        -1,
    )
    stokes = stokes_with_sunlight(stokes_sky, epsilon, sunlight_direction(sun_c))
    data = pixel_data(stokes[:, 0], stokes[:, 1], stokes[:, 2], forward, 1.0)
    a_l, z_l = np.arctan2(sun_l[1], sun_l[0]), np.arccos(np.clip(sun_l[2], -1, 1))
    theta = np.array([a_l, epsilon] if fixed_zenith else [a_l, z_l, epsilon])
    _, jac, _, _ = ml_evaluate(data, theta, z_l if fixed_zenith else None, mat_cl, True)
    assert jac is not None
    fisher = jac @ jac.T / sigma_l**2
    return float(np.sqrt(np.linalg.inv(fisher)[0, 0]))
