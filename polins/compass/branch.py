"""The 180 deg branch of a sun seen without an ephemeris: elevation, sky brightness, prior.

The E-vector pattern is the same for the sun ``s`` and the antisun ``-s`` (every E-vector is
perpendicular to both), so an image gives the sun's direction up to sign
(docs/measurement.md §11). :func:`choose_branch` resolves it with, in this order:

1. the elevation: the sun is above the horizon, decisive when the estimated elevation is
   clearly positive (above ``elevation_min`` and ``z_min`` sigmas);
2. the brightness: the clear sky is brighter towards the sun (:func:`brightness_contrast`
   compares the mean S0 of the two image halves split by the line through the principal
   point perpendicular to the sun's image-plane direction);
3. a prior body-frame sun azimuth (e.g. from the previous image);

and otherwise reports the branch as ambiguous.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from polins.frames import wrap_angle

FloatArray = NDArray[np.float64]

__all__ = ["brightness_contrast", "choose_branch", "sun_angle_variances"]


def sun_angle_variances(sun: NDArray, cov_sun: NDArray) -> tuple[float, float]:
    """Variances [rad^2] of the azimuth ``atan2(s_y, s_x)`` and the elevation ``asin(s_z)``
    of a unit vector ``(3,)`` with the tangent-plane covariance ``(3, 3)`` (docs/model.md
    §10.2): ``h^T C h`` with ``h = (-s_y, s_x, 0)/(s_x^2 + s_y^2)``, and
    ``C_zz / (1 - s_z^2)``."""
    s = np.asarray(sun, dtype=float)
    c = np.asarray(cov_sun, dtype=float)
    rho2 = max(float(s[0] ** 2 + s[1] ** 2), 1e-300)
    h = np.array([-s[1], s[0], 0.0]) / rho2
    return float(h @ c @ h), float(c[2, 2] / rho2)


def brightness_contrast(
    s0: NDArray, used: NDArray, rays_c: NDArray, sun_c: NDArray, var_s0: NDArray | float
) -> tuple[float, float]:
    """Is the image brighter on the side of the candidate sun ``sun_c`` (3,)?

    The pixels ``used`` (n,) are split by the line through the principal point
    perpendicular to the sun's image-plane direction ``(s_x, s_y)``; a symmetric vignetting
    cancels. Returns the difference of the mean S0 [DN] (sun side minus antisun side) in
    units of its noise sigma (from the per-pixel S0 variance ``var_s0`` [DN^2]) and relative
    to the mean of the two: both positive when the sun side is brighter, 0 when a side is
    empty.

    Parameters
    ----------
    s0 : (n,)
        Stokes S0 [DN]. used : (n,) bool. rays_c : (3, n) camera rays.
    sun_c : (3,)
        Candidate camera-frame sun.
    var_s0 : (n,) or float
        Noise variance of S0 [DN^2].
    """
    side = rays_c[0] * sun_c[0] + rays_c[1] * sun_c[1]
    sun_side = used & (side > 0)
    anti_side = used & (side < 0)
    n_sun, n_anti = int(np.count_nonzero(sun_side)), int(np.count_nonzero(anti_side))
    if n_sun == 0 or n_anti == 0:
        return 0.0, 0.0
    s = s0.astype(np.float64)
    mean_sun = float(np.sum(s, where=sun_side)) / n_sun
    mean_anti = float(np.sum(s, where=anti_side)) / n_anti
    if isinstance(var_s0, np.ndarray):
        var_mean = float(np.sum(var_s0, where=sun_side)) / n_sun**2
        var_mean += float(np.sum(var_s0, where=anti_side)) / n_anti**2
    else:
        var_mean = float(var_s0) * (1.0 / n_sun + 1.0 / n_anti)
    diff = mean_sun - mean_anti
    level = 0.5 * (mean_sun + mean_anti)
    z = diff / np.sqrt(var_mean) if var_mean > 0 else 0.0
    return float(z), float(diff / level) if level > 0 else 0.0


def choose_branch(
    elevation: float,
    elevation_std: float,
    azimuth_b: float,
    brightness: tuple[float, float],
    azimuth_b_prior: float | None,
    *,
    elevation_min: float,
    z_min: float,
    contrast_min: float,
) -> tuple[float, str]:
    """The sign (+1: the candidate, -1: its antipode) of a sun seen up to sign, and what
    chose it.

    Parameters
    ----------
    elevation : float
        Level-frame elevation of the candidate [rad], >= 0.
    elevation_std : float
        Its 1-sigma [rad] (NaN or inf: undetermined).
    azimuth_b : float
        Body-frame azimuth of the candidate [rad].
    brightness : (float, float)
        :func:`brightness_contrast` of the candidate (significance, relative contrast).
    azimuth_b_prior : float or None
        Prior body-frame sun azimuth [rad].
    elevation_min : float
        Smallest elevation [rad] that decides by itself.
    z_min : float
        Significance [sigmas] an elevation or a brightness difference needs.
    contrast_min : float
        Minimum relative brightness contrast.

    Returns
    -------
    sign : float
        +1 or -1.
    label : {"elevation", "brightness", "prior", "ambiguous"}
    """
    if elevation > elevation_min and elevation > z_min * elevation_std:
        return 1.0, "elevation"
    z, contrast = brightness
    if abs(z) >= z_min and abs(contrast) >= contrast_min:
        return (1.0 if z > 0 else -1.0), "brightness"
    if azimuth_b_prior is not None:
        near = abs(float(wrap_angle(azimuth_b - azimuth_b_prior))) <= 0.5 * np.pi
        return (1.0 if near else -1.0), "prior"
    return 1.0, "ambiguous"
