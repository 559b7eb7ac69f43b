"""Skylight polarization: single-scattering Rayleigh model (docs/model.md §6.1) and the
Berry four-neutral-point sky (Berry, Dennis & Lee 2004, New J. Phys. 6:162).

For a unit ray ``p`` and the unit sun vector ``s`` in the same frame, the Rayleigh E-vector
is perpendicular to the scattering plane, ``e ~ s x p``, and the degree of linear
polarization is ``d = d_max sin^2(Theta) / (1 + cos^2(Theta))`` with ``cos(Theta) = p . s``.
The Berry sky splits each of the Rayleigh singularities at the sun and the anti-sun into
two neutral points (Babinet/Brewster, Arago/fourth) on the solar vertical, as multiple
scattering does in real clear skies; its ``neutral_sep = 0`` limit is the Rayleigh sky.
The estimators use only the Rayleigh E-vector geometry, never the DoP magnitude; the Berry
sky is a simulation option that puts realistic model error into the images.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


def rayleigh_evector(sun: ArrayLike, rays: ArrayLike) -> FloatArray:
    """Unit Rayleigh E-vector ``s x p / |s x p|``, ``(..., 3)``; NaN at the sun and anti-sun."""
    e = np.cross(np.asarray(sun, dtype=float), np.asarray(rays, dtype=float))
    with np.errstate(invalid="ignore", divide="ignore"):
        return e / np.linalg.norm(e, axis=-1, keepdims=True)


def rayleigh_dop(sun: ArrayLike, rays: ArrayLike, dop_max: float) -> FloatArray:
    """Rayleigh degree of linear polarization ``d_max sin^2 Theta / (1 + cos^2 Theta)``."""
    if not 0.0 <= dop_max <= 1.0:
        raise ValueError(f"dop_max={dop_max} outside [0, 1]")
    c = np.sum(np.asarray(sun, dtype=float) * np.asarray(rays, dtype=float), axis=-1)
    return dop_max * (1.0 - c * c) / (1.0 + c * c)


def rayleigh_radiance(sun: ArrayLike, rays: ArrayLike, radiance: float) -> FloatArray:
    """Rayleigh sky radiance ``radiance * (1 + cos^2 Theta)`` (equal to ``radiance`` at 90 deg
    from the sun)."""
    c = np.sum(np.asarray(sun, dtype=float) * np.asarray(rays, dtype=float), axis=-1)
    return radiance * (1.0 + c * c)


# ------------------------------------------------------------------ Berry four-neutral-point sky
# M. V. Berry, M. R. Dennis and R. L. Lee Jr (2004), "Polarization singularities in the clear
# sky", New J. Phys. 6:162. The sky sphere is mapped stereographically from the nadir,
# zeta = (x + i y) / (1 + z) in a frame whose z axis is the local vertical "up". The
# polarization (E-vector line field) is the complex function
#
#   w(zeta) = -4 (zeta - z1)(zeta - z2)(1 + zeta conj(z1))(1 + zeta conj(z2))
#             / [(1 + |zeta|^2)^2 (1 + |z1|^2)(1 + |z2|^2)]
#
# with z1, z2 the Babinet (above the sun) and Brewster (below the sun) neutral points; the
# factors (1 + zeta conj(z_k)) are the zeros at their antipodes, the Arago point (above the
# anti-sun) and the fourth (below the anti-sun) neutral point. This is Berry et al.'s
# -4 prod(zeta - zeta_k) / ((1 + |zeta|^2)^2 |z1 - z4| |z2 - z3|) times the phase
# exp(-2i phi_sun) that orients the field (their AoP is measured from the solar meridian),
# rewritten so that no azimuth appears: it is regular for a sun at the zenith and continuous
# when a neutral point crosses the zenith. The E-vector makes the angle chi = arg(w) / 2 with
# the image of the real axis in the zeta plane; |w| = sin(Theta_1) sin(Theta_2), Theta_k the
# angle to neutral point k, and the degree of polarization is d_max |w| / (2 - |w|).
# With z1 = z2 = the sun this is exactly the Rayleigh sky: |w| = sin^2 Theta and
# d = d_max sin^2 Theta / (1 + cos^2 Theta), E ~ s x p.


def _vertical_basis(up: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Orthonormal right-handed basis (ex, ey, up) with ``up`` the local vertical."""
    u = np.asarray(up, dtype=float)
    if u.shape != (3,) or not np.linalg.norm(u) > 0:
        raise ValueError(f"up must be a non-zero 3-vector, got {u!r}")
    u = u / np.linalg.norm(u)
    helper = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    ex = helper - (helper @ u) * u
    ex /= np.linalg.norm(ex)
    return ex, np.cross(u, ex), u


def berry_neutral_points(
    sun: ArrayLike, neutral_sep: float, up: ArrayLike = (0.0, 0.0, 1.0)
) -> FloatArray:
    """Unit vectors of the four neutral points of the Berry sky, ``(..., 4, 3)``.

    Parameters
    ----------
    sun : array_like, (..., 3)
        Unit sun vector.
    neutral_sep : float
        Angular separation [rad] of the two neutral points of each pair: the Babinet and
        Brewster points lie on the solar vertical ``neutral_sep / 2`` above and below the sun.
        Zero gives the Rayleigh sky (both at the sun). Clear skies: about 0.5-0.7 rad.
    up : array_like, (3,)
        Local vertical in the frame of ``sun``.

    Returns
    -------
    ndarray, (..., 4, 3)
        Babinet (above the sun), Brewster (below the sun), Arago (above the anti-sun, the
        antipode of Brewster) and the fourth point (below the anti-sun, antipode of Babinet).
    """
    if not 0.0 <= neutral_sep < np.pi:
        raise ValueError(f"neutral_sep={neutral_sep} outside [0, pi) rad")
    s = np.asarray(sun, dtype=float)
    s = s / np.linalg.norm(s, axis=-1, keepdims=True)
    ex, _, u = _vertical_basis(up)
    # Unit direction from the sun towards the zenith along the solar vertical (ex if the sun
    # is at the zenith or nadir, where the solar vertical is undefined).
    toward_up = u - (s @ u)[..., None] * s
    norm = np.linalg.norm(toward_up, axis=-1, keepdims=True)
    fallback = ex - (s @ ex)[..., None] * s
    fallback /= np.linalg.norm(fallback, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        toward_up = np.where(norm > 1e-12, toward_up / norm, fallback)
    h = 0.5 * neutral_sep
    babinet = np.cos(h) * s + np.sin(h) * toward_up
    brewster = np.cos(h) * s - np.sin(h) * toward_up
    return np.stack([babinet, brewster, -brewster, -babinet], axis=-2)


def _stereographic(v: FloatArray, basis: tuple[FloatArray, FloatArray, FloatArray]) -> NDArray:
    """Stereographic coordinate ``(x + i y) / (1 + z)`` (projection from the nadir)."""
    ex, ey, u = basis
    with np.errstate(invalid="ignore", divide="ignore"):
        return (v @ ex + 1j * (v @ ey)) / (1.0 + v @ u)


def berry_w(
    sun: ArrayLike, rays: ArrayLike, neutral_sep: float, up: ArrayLike = (0.0, 0.0, 1.0)
) -> NDArray[np.complex128]:
    """Berry et al.'s complex polarization function ``w`` at unit rays ``(..., 3)``.

    ``arg(w) / 2`` is the E-vector angle in the stereographic plane (projection from the
    nadir, frame ``(ex, ey, up)`` of :func:`_vertical_basis`) and ``|w|`` in [0, 1] the
    unnormalised polarization; see the module notes above.
    """
    basis = _vertical_basis(up)
    points = berry_neutral_points(sun, neutral_sep, up)
    zeta = _stereographic(np.asarray(rays, dtype=float), basis)
    z1 = _stereographic(points[..., 0, :], basis)
    z2 = _stereographic(points[..., 1, :], basis)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        num = (zeta - z1) * (zeta - z2) * (1.0 + zeta * np.conj(z1)) * (1.0 + zeta * np.conj(z2))
        den = (1.0 + np.abs(zeta) ** 2) ** 2 * (1.0 + np.abs(z1) ** 2) * (1.0 + np.abs(z2) ** 2)
        return -4.0 * num / den


def berry_evector(
    sun: ArrayLike, rays: ArrayLike, neutral_sep: float, up: ArrayLike = (0.0, 0.0, 1.0)
) -> FloatArray:
    """Unit E-vector ``(..., 3)`` of the Berry four-neutral-point sky (Berry et al. 2004).

    Same frame and meaning as :func:`rayleigh_evector` (to which it reduces exactly for
    ``neutral_sep = 0``). The sign of the axial E-vector is arbitrary; NaN at the nadir.

    Parameters
    ----------
    sun, rays : array_like, (..., 3)
        Unit sun vector and unit observation rays, in one frame.
    neutral_sep : float
        Neutral-point separation [rad] (see :func:`berry_neutral_points`).
    up : array_like, (3,)
        Local vertical in that frame (the neutral points lie on the solar vertical).
    """
    p = np.asarray(rays, dtype=float)
    ex, ey, u = _vertical_basis(up)
    w = berry_w(sun, p, neutral_sep, up)
    zeta = _stereographic(p, (ex, ey, u))
    xi, eta = zeta.real, zeta.imag
    # Unit tangent vector whose stereographic image points along +real: d p / d xi,
    # normalised (the map is conformal and orientation preserving about the outward ray, so
    # p x t1 maps to +imaginary).
    r2 = 1.0 + xi * xi + eta * eta
    t1 = (
        ((1.0 + eta * eta - xi * xi) / r2)[..., None] * ex
        + (-2.0 * xi * eta / r2)[..., None] * ey
        + (-2.0 * xi / r2)[..., None] * u
    )
    t2 = np.cross(p, t1)
    chi = 0.5 * np.angle(w)
    return np.cos(chi)[..., None] * t1 + np.sin(chi)[..., None] * t2


def berry_dop(
    sun: ArrayLike,
    rays: ArrayLike,
    dop_max: float,
    neutral_sep: float,
    up: ArrayLike = (0.0, 0.0, 1.0),
) -> FloatArray:
    """Degree of linear polarization of the Berry sky, ``d_max |w| / (2 - |w|)``.

    ``|w| = sin(Theta_1) sin(Theta_2)`` with ``Theta_k`` the angles from the ray to the
    Babinet and Brewster points: zero at all four neutral points, and equal to
    :func:`rayleigh_dop` for ``neutral_sep = 0``.
    """
    if not 0.0 <= dop_max <= 1.0:
        raise ValueError(f"dop_max={dop_max} outside [0, 1]")
    p = np.asarray(rays, dtype=float)
    points = berry_neutral_points(sun, neutral_sep, up)
    sin1 = np.linalg.norm(np.cross(points[..., 0, :], p), axis=-1)
    sin2 = np.linalg.norm(np.cross(points[..., 1, :], p), axis=-1)
    mag = sin1 * sin2
    return dop_max * mag / (2.0 - mag)
