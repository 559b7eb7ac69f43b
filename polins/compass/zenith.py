"""The zenith angle of polarization: the sun's azimuth when the field does not fix its elevation.

A narrow field near the zenith (a pinhole looking up) sees E-vectors that are all nearly
horizontal and perpendicular to the sun's azimuth: the data fix the sun's vertical plane,
not its elevation, and the eigen solution's sun wanders in that plane. The heading then
comes from the weighted mean of the doubled level-frame E-vectors over the largest cone
about the prior's zenith that lies inside the field (docs/measurement.md §13):

* each pixel's E-vector tensor ``e e^T`` is, per unit linear intensity, linear in
  ``(S1, S2)``; projected on the level horizontal plane its doubled-angle vector is
  ``S1 q1 + S2 q2`` (plus a part without ``S1, S2``, dropped);
* ``M = sum_i (S1_i q1_i + S2_i q2_i) / sigma_L,i^2``; the horizontal zenith E-vector is
  at ``phi = atan2(M_2, M_1) / 2`` and the sun's azimuth at ``phi + pi/2`` (mod pi);
* the sky is symmetric about the sun's vertical plane and so is a cone about the zenith,
  so ``M`` lies on that plane's doubled angle whatever the sun's elevation.

The rule is automatic: it replaces an eigen solution (``"traditional"``, or the compensated
method's fallback to it) when the zenith lies inside the field and its sigma (pixel noise,
the jackknife over mirror-pair sectors, the camera-fixed part) is the smaller.
"""

from __future__ import annotations

import dataclasses
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import binary_erosion

from polins.compass.branch import sun_angle_variances
from polins.compass.heading import Geometry
from polins.compass.image import ImageStokes
from polins.compass.measurement import MeasureOptions
from polins.compass.pixels import PixelSet
from polins.compass.skypixels import SkyPixels
from polins.compass.solution import Solution

__all__ = [
    "CONE_MAX",
    "MIRROR_SECTORS",
    "ZenithMean",
    "total_std",
    "zenith_cone",
    "zenith_mean",
    "zenith_solution",
]


@dataclasses.dataclass(frozen=True)
class ZenithMean:
    """The weighted mean doubled E-vector of the zenith cone.

    Attributes
    ----------
    azimuth_l : float
        Level-frame sun azimuth [rad], one of its two 180 deg branches.
    var_azimuth : float
        Its pixel-noise variance [rad^2].
    var_jack : float
        Jackknife variance of the azimuth over mirror-pair sectors [rad^2].
    g_delta, g_mixing : float
        Azimuth change per unit camera-fixed polarization and mixing [rad]
        (:mod:`polins.compass.instrumental`).
    """

    azimuth_l: float
    var_azimuth: float
    var_jack: float
    g_delta: float
    g_mixing: float


@lru_cache(maxsize=8)
def _edge_pixels(pixels: PixelSet) -> NDArray:
    """Positions in ``pixels`` of the field's edge pixels (next to the border, an occlusion
    or outside the field)."""
    fov = pixels.to_image(np.ones(pixels.size), fill=0.0) > 0.5
    edge_img = fov & ~binary_erosion(fov, border_value=0)
    return pixels.to_image(np.arange(pixels.size), fill=-1.0)[edge_img].astype(np.intp)


# [rad] widest cone half-angle: a field that holds a wider cone about the zenith fixes the
# sun's elevation itself (on the shipped 88 deg fisheye the cone never wins, and computing
# it there costs six eigen solutions); docs/measurement.md §13
CONE_MAX = np.radians(45.0)


def zenith_cone(img: ImageStokes, mat_lc: NDArray) -> NDArray | None:
    """Field-of-view pixels ``(n,)`` bool inside the largest cone about the level zenith
    that lies inside the field (its edge and occlusions), or None when the zenith is
    outside the field or the cone is wider than :data:`CONE_MAX`."""
    rays = img.cache.rays
    up = mat_lc[2].astype(rays.dtype) @ rays  # cosine of the zenith angle
    edge = _edge_pixels(img.cache.pixels)
    if edge.size == 0:
        return None
    up_edge = float(np.max(up[edge]))
    if not float(np.max(up)) > up_edge:  # the zenith is on the edge or outside
        return None
    if up_edge < np.cos(CONE_MAX):  # a wide field: the eigen solution fixes the elevation
        return None
    return up > up_edge


def _doubled_rows(basis: NDArray, mat_lc: NDArray) -> tuple[NDArray, NDArray]:
    """``q1, q2`` ``(2, n)``: the level horizontal doubled-angle vectors of the E-vector
    tensor per unit ``S1`` and ``S2`` (docs/measurement.md §13), normalised by
    ``(|h1|^2 + |h2|^2)/2``."""
    h1 = (mat_lc[:2] @ basis[:, 0]).astype(np.float64)
    h2 = (mat_lc[:2] @ basis[:, 1]).astype(np.float64)
    norm = 0.5 * (np.sum(h1 * h1, axis=0) + np.sum(h2 * h2, axis=0))
    q1 = 0.5 * np.stack([h1[0] ** 2 - h1[1] ** 2 - h2[0] ** 2 + h2[1] ** 2,
                         2.0 * (h1[0] * h1[1] - h2[0] * h2[1])])  # fmt: skip
    q2 = np.stack([h1[0] * h2[0] - h1[1] * h2[1], h1[0] * h2[1] + h2[0] * h1[1]])
    return q1 / norm, q2 / norm


MIRROR_SECTORS = 8
"""Groups of the mirror-pair jackknife: sectors of ``|pixel azimuth - sun azimuth|``."""


def _mirror_jackknife(contrib: NDArray, azimuth_px: NDArray, azimuth_sun: float) -> float:
    """Delete-one-group jackknife variance [rad^2] of the azimuth of ``sum contrib`` (2, n)
    over groups of pixels mirrored about the sun's vertical plane: on a symmetric sky every
    group's sum lies on that plane's doubled angle, so only asymmetries move it."""
    rel = np.abs(np.angle(np.exp(1j * (azimuth_px - azimuth_sun))))
    group = np.minimum((rel / np.pi * MIRROR_SECTORS).astype(int), MIRROR_SECTORS - 1)
    sums = np.stack([np.bincount(group, c, MIRROR_SECTORS) for c in contrib])  # (2, G)
    total = sums.sum(axis=1, keepdims=True)
    left = total - sums
    phi = 0.5 * np.unwrap(np.arctan2(left[1], left[0]) - np.arctan2(total[1], total[0]))
    used = np.bincount(group, minlength=MIRROR_SECTORS) > 0
    g = int(np.count_nonzero(used))
    if g < 2:
        return float("nan")
    d = phi[used] - phi[used].mean()
    return float((g - 1) / g * np.sum(d * d))


def zenith_mean(
    stokes: NDArray, inv_sigma_l2: NDArray | float, basis: NDArray, mat_lc: NDArray,
    noise_ratio: float, azimuth_px: NDArray,
) -> ZenithMean:  # fmt: skip
    """The zenith cone's sun azimuth, its noise variance and instrumental sensitivities.

    Parameters
    ----------
    stokes : (3, n)
        (S0, S1, S2) [DN] of the cone's pixels.
    inv_sigma_l2 : (n,) or float
        ``1/sigma_L^2`` [1/DN^2].
    basis : (3, 2, n)
        Inverse lens basis of the pixels (camera frame).
    mat_lc : (3, 3)
        Camera -> level.
    noise_ratio : float
        Measured / declared noise; scales the variance when finite.
    azimuth_px : (n,)
        Level-frame azimuths of the pixels' rays [rad] (for the jackknife).
    """
    s0, s1, s2 = (np.asarray(r, dtype=np.float64) for r in stokes)
    w = np.broadcast_to(np.asarray(inv_sigma_l2, dtype=np.float64), s1.shape)
    q1, q2 = _doubled_rows(basis, mat_lc)
    contrib = q1 * (w * s1) + q2 * (w * s2)
    m = contrib.sum(axis=1)
    norm = float(np.hypot(m[0], m[1]))
    perp = np.array([-m[1], m[0]]) / norm  # d(2 phi) per unit change of M along it: 1/|M|
    scale = noise_ratio**2 if np.isfinite(noise_ratio) else 1.0
    var_2phi = scale * float(np.sum(w * ((perp @ q1) ** 2 + (perp @ q2) ** 2))) / norm**2

    def d_azimuth(d1: NDArray, d2: NDArray) -> float:
        return 0.5 * float(perp @ (q1 @ (w * d1) + q2 @ (w * d2))) / norm

    g_delta = np.hypot(d_azimuth(s0, 0 * s0), d_azimuth(0 * s0, s0))
    g_mixing = np.hypot(d_azimuth(s1, -s2), d_azimuth(s2, s1))
    azimuth = 0.5 * float(np.arctan2(m[1], m[0])) + 0.5 * np.pi
    var_jack = _mirror_jackknife(contrib, azimuth_px, azimuth)
    return ZenithMean(azimuth, 0.25 * var_2phi, var_jack, float(g_delta), float(g_mixing))


def total_std(
    var_yaw: float, var_jack: float, std_instrumental: float, model_scale: float
) -> float:
    """The sun-free azimuth sigma [rad] of §12: pixel noise, ``model_scale`` times the
    jackknife's variance beyond it, and the camera-fixed part."""
    var_model = max(var_jack - var_yaw, 0.0) if np.isfinite(var_jack) else 0.0
    return float(np.sqrt(var_yaw + model_scale**2 * var_model + std_instrumental**2))


def zenith_solution(
    img: ImageStokes,
    px: SkyPixels,
    sol: Solution,
    geo: Geometry,
    opt: MeasureOptions,
    std_instrumental: float,
    instrumental: tuple[float, float],
    model_scale: float,
) -> tuple[Solution, float] | None:
    """The zenith cone's solution and its camera-fixed sigma [rad], when the zenith lies in
    the field and its sigma (:func:`total_std`) is below that of the eigen solution ``sol``
    (``std_instrumental`` [rad] its camera-fixed part; ``instrumental`` the camera's
    ``(dop_std, mixing_std)``); else None (docs/measurement.md §13). The sun is put in the
    cone's vertical half-plane nearest to ``sol``'s, at ``sol``'s elevation; its 180 deg
    branch is then chosen as for any solution."""
    mat_lc = geo.mat_lc
    cone = zenith_cone(img, mat_lc)
    if cone is None:
        return None
    mask = cone & px.valid
    idx = np.flatnonzero(mask)
    if idx.size < opt.min_pixels:
        return None
    inv = img.inv_sigma_l2
    inv_m = inv.take(idx) if isinstance(inv, np.ndarray) else inv
    rays_l = mat_lc[:2] @ img.cache.rays.take(idx, axis=1).astype(np.float64)
    zm = zenith_mean(img.estimate.take(idx, axis=1), inv_m, img.cache.basis.take(idx, axis=2),
                     mat_lc, img.noise_ratio, np.arctan2(rays_l[1], rays_l[0]))  # fmt: skip
    std_zm = float(np.hypot(instrumental[0] * zm.g_delta, instrumental[1] * zm.g_mixing))
    std_sol = total_std(sol.var_yaw, sol.var_jack, std_instrumental, model_scale)
    if not total_std(zm.var_azimuth, zm.var_jack, std_zm, model_scale) < std_sol:
        return None
    sun_l = sol.sun_l / np.linalg.norm(sol.sun_l)
    _, var_el = sun_angle_variances(sun_l, sol.cov_sun_l)
    a = zm.azimuth_l
    horizontal = np.array([np.cos(a), np.sin(a), 0.0])
    if horizontal @ sun_l < 0:
        horizontal, a = -horizontal, a + np.pi
    z_cos = float(np.clip(sun_l[2], -1.0, 1.0))
    sun_new = np.sqrt(1.0 - z_cos**2) * horizontal + np.array([0.0, 0.0, z_cos])
    across = np.array([-np.sin(a), np.cos(a), 0.0])
    along = np.cross(across, sun_new)
    cov = zm.var_azimuth * (1.0 - z_cos**2) * np.outer(across, across)
    cov += var_el * np.outer(along, along)
    theta = np.array([np.arctan2(sun_new[1], sun_new[0]), np.arccos(z_cos), 0.0])
    note = (
        f"zenith angle of polarization (sigma {np.degrees(std_sol):.3g} -> "
        f"{np.degrees(total_std(zm.var_azimuth, zm.var_jack, std_zm, model_scale)):.3g} deg)"
    )
    fallback = "; ".join(r for r in (sol.fallback, note) if r)
    new = dataclasses.replace(
        sol, fallback=fallback, sun_l=sun_new, cov_sun_l=cov, var_yaw=zm.var_azimuth,
        var_jack=zm.var_jack, theta=theta, zenith=None, mask=mask, mask_sub=mask[img.sub.index],
    )  # fmt: skip
    return new, std_zm
