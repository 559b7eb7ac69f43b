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
from polins.compass.kernels import compiled, dot_rows
from polins.compass.measurement import MeasureOptions
from polins.compass.pixels import PixelSet
from polins.compass.skypixels import SkyPixels
from polins.compass.solution import Solution
from polins.compass.zenith_kernels import ZENITH_SUMS

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


def zenith_cone(img: ImageStokes, mat_lc: NDArray) -> float | None:
    """Cosine of the half-angle of the largest cone about the level zenith that lies inside
    the field (its edge and occlusions), or None when the cone is wider than
    :data:`CONE_MAX`. When the zenith is outside the field no pixel lies inside that
    cone (:func:`zenith_mean` then uses none)."""
    rays = img.cache.rays
    edge = _edge_pixels(img.cache.pixels)
    if edge.size == 0:
        return None
    up_edge = float(np.max(dot_rows(mat_lc[2].astype(rays.dtype), rays.take(edge, axis=1))))
    if up_edge < np.cos(CONE_MAX):  # a wide field: the eigen solution fixes the elevation
        return None
    return up_edge


MIRROR_SECTORS = 8
"""Groups of the mirror-pair jackknife: sectors of ``|pixel azimuth - sun azimuth|``."""


_MIRROR_BOUNDS = np.array(
    [np.cos(np.arange(1, MIRROR_SECTORS) * np.pi / MIRROR_SECTORS),
     np.sin(np.arange(1, MIRROR_SECTORS) * np.pi / MIRROR_SECTORS)]
)  # fmt: skip
"""(cos, sin) of the boundaries between the mirror-pair sectors [-]."""


def _mirror_jackknife(group_sums: NDArray) -> float:
    """Delete-one-group jackknife variance [rad^2] of the azimuth of the zenith cone's sum
    from its per-group sums ``(3, G)`` (contribution (2), pixel count) over groups of
    pixels mirrored about the sun's vertical plane (by the angle between the horizontal
    parts of their level rays and the sun's azimuth): on a symmetric sky every group's sum
    lies on that plane's doubled angle, so only asymmetries move it."""
    sums = group_sums[:2]  # (2, G)
    total = sums.sum(axis=1, keepdims=True)
    left = total - sums
    phi = 0.5 * np.unwrap(np.arctan2(left[1], left[0]) - np.arctan2(total[1], total[0]))
    used = group_sums[2] > 0
    g = int(np.count_nonzero(used))
    if g < 2:
        return float("nan")
    d = phi[used] - phi[used].mean()
    return float((g - 1) / g * np.sum(d * d))


def zenith_mean(
    img: ImageStokes, valid: NDArray, mat_lc: NDArray, cos_edge: float
) -> tuple[ZenithMean, NDArray]:
    """The zenith cone's sun azimuth, its noise variance and instrumental sensitivities.

    Parameters
    ----------
    img : ImageStokes
        The image's Stokes rows, noise and camera constants.
    valid : (n,) bool
        The pixels that may be used.
    mat_lc : (3, 3)
        Camera -> level.
    cos_edge : float
        Cosine of the cone's half-angle about the level zenith (:func:`zenith_cone`).

    Returns
    -------
    ZenithMean
        The estimate (``azimuth_l`` NaN when no pixel is used).
    mask : (n,) bool
        The pixels used.
    """
    inv = img.inv_sigma_l2
    inv_rows = inv if isinstance(inv, np.ndarray) else np.full((1, 1), inv, dtype=img.dtype)
    basis = img.cache.basis[2] if img.cache.projection else img.cache.basis
    mask, sums = np.empty(valid.size, bool), np.empty(ZENITH_SUMS)
    contrib = np.empty((2, valid.size))
    mat = np.ascontiguousarray(mat_lc, dtype=np.float64)
    compiled("zenith_pass")(img.estimate, inv_rows, basis, img.cache.rays, valid, mat,
                            float(cos_edge), mask, sums, contrib)  # fmt: skip
    k = int(np.count_nonzero(mask))
    if k == 0:  # the zenith is outside the field, or no valid pixel is inside the cone
        return ZenithMean(float("nan"), float("nan"), float("nan"), 0.0, 0.0), mask
    m = sums[0:2]
    norm = float(np.hypot(m[0], m[1]))
    perp = np.array([-m[1], m[0]]) / norm  # d(2 phi) per unit change of M along it: 1/|M|
    scale = img.noise_ratio**2 if np.isfinite(img.noise_ratio) else 1.0
    a = np.array([[sums[2], sums[3]], [sums[3], sums[4]]])
    var_2phi = scale * float(perp @ a @ perp) / norm**2
    d_azimuth = 0.5 * (sums[5:13].reshape(4, 2) @ perp) / norm  # per (S0, 0), (0, S0), mixing
    g_delta = float(np.hypot(d_azimuth[0], d_azimuth[1]))
    g_mixing = float(np.hypot(d_azimuth[2], d_azimuth[3]))
    azimuth = 0.5 * float(np.arctan2(m[1], m[0])) + 0.5 * np.pi
    group_sums = np.zeros((3, MIRROR_SECTORS))
    compiled("mirror_pass")(contrib, img.cache.rays, mask, mat,
                            np.array([np.cos(azimuth), np.sin(azimuth)]), _MIRROR_BOUNDS,
                            group_sums)  # fmt: skip
    var_jack = _mirror_jackknife(group_sums)
    return ZenithMean(azimuth, 0.25 * var_2phi, var_jack, g_delta, g_mixing), mask


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
    cos_edge = zenith_cone(img, mat_lc)
    if cos_edge is None:
        return None
    zm, mask = zenith_mean(img, px.valid, mat_lc, cos_edge)
    if np.count_nonzero(mask) < opt.min_pixels:
        return None
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
