"""The estimator's Berry sky: the four-neutral-point E-vector as a rotation of the Rayleigh one.

Berry, Dennis & Lee (2004, New J. Phys. 6:162) write the clear sky's polarization as a
complex function on the stereographic plane whose zeros are the four neutral points; its
ratio to the Rayleigh sky's (both zeros at the sun and the anti-sun) is a product of
direction factors, so on the sphere (docs/model.md §6.3)::

    2 dchi = arg(a_1) + arg(a_2) - 2 arg(a_s)

where ``a_q`` is the tangential component at the ray ``p`` of the point ``q`` (the sun
``s``, the Babinet point ``n_1`` and the Brewster point ``n_2``, on the solar vertical
``neutral_sep / 2`` above and below the sun) in any orthonormal tangent basis, written as a
complex number (the basis cancels because the weights 1 + 1 - 2 sum to zero). The Berry
E-vector is the Rayleigh E-vector ``s x p`` turned by ``dchi`` about ``p``;
``|a_1| |a_2| = sin T_1 sin T_2`` is its unnormalised polarization, zero at the four
neutral points. No trigonometry and no stereographic projection: the tangent basis is the
rotation of ``(e_x, e_y)`` that takes ``e_z`` to ``p``. Everything is frame-free (all
vectors in one frame); the rows are component-first ``(3, n)``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

__all__ = [
    "berry_half_rotation",
    "berry_neutral_points_level",
    "berry_polarization",
    "berry_rotation",
    "tangent_components",
]


def tangent_components(rays: NDArray, inv_1pz: NDArray, q: NDArray) -> tuple[NDArray, NDArray]:
    """Components ``(b_1 . q, b_2 . q)`` of a vector ``q`` (3,) in the orthonormal tangent
    basis at each ray (``b_1 x b_2 = p``; the rotation taking ``e_z`` to ``p`` applied to
    ``e_x``, ``e_y``).

    ``b_j . q = q_j - p_j kappa``, ``kappa = (p_x q_x + p_y q_y) / (1 + p_z) + q_z``
    (regular except for ``p = -e_z``).

    Parameters
    ----------
    rays : (3, n)
        Unit rays ``p``, component-first.
    inv_1pz : (n,)
        ``1 / (1 + p_z)``.
    q : (3,)
        The vector (same frame as the rays).
    """
    dt = rays.dtype.type
    kappa = rays[0] * dt(q[0])
    kappa += rays[1] * dt(q[1])
    kappa *= inv_1pz
    kappa += dt(q[2])
    t1 = dt(q[0]) - rays[0] * kappa
    t2 = np.multiply(rays[1], kappa, out=kappa)
    np.subtract(dt(q[1]), t2, out=t2)
    return t1, t2


def berry_half_rotation(
    a_s: tuple[NDArray, NDArray], a_1: tuple[NDArray, NDArray], a_2: tuple[NDArray, NDArray]
) -> tuple[NDArray, NDArray, NDArray]:
    """``(c, s, m)`` ``(n,)`` each from the tangent components (:func:`tangent_components`)
    of the sun and the Babinet and Brewster points: ``(cos dchi, sin dchi)`` is parallel to
    ``(c, s)`` (not normalised, ``c >= 0``) and ``m = |a_s|^2 |a_1| |a_2|`` (module notes).

    With ``W = a_1 a_2 conj(a_s)^2 = m e^(2 i dchi)``: ``c = m + Re W``, ``s = Im W`` (the
    half-angle identity). ``W = 0`` at the sun, the anti-sun and the neutral points.
    """
    (sr, si), (ar, ai), (br, bi) = a_s, a_1, a_2
    pr = ar * br  # a_1 a_2
    pr -= ai * bi
    pi = ar * bi
    pi += ai * br
    qr = sr * sr  # conj(a_s)^2 = (sr^2 - si^2) - 2 i sr si
    qr -= si * si
    qi = sr * si
    qi *= -2.0
    wr = pr * qr
    wr -= pi * qi
    wi = np.multiply(pr, qi, out=pr)
    wi += pi * qr
    m = np.hypot(wr, wi)
    c = np.add(m, wr, out=wr)
    return c, wi, m


def berry_neutral_points_level(
    azimuth: float, zenith: float, neutral_sep: float
) -> tuple[FloatArray, FloatArray]:
    """Level-frame Babinet and Brewster points with their derivatives, ``(3, 4)`` each:
    the point, then ``d/dA``, ``d/dZ`` and ``d/d neutral_sep``, for a sun at ``azimuth``
    ``A`` and ``zenith`` ``Z`` [rad] (``sun = (sin Z cos A, sin Z sin A, cos Z)``): the
    suns at zenith ``Z -+ neutral_sep/2`` (through the zenith when ``Z < neutral_sep/2``)."""
    h = 0.5 * neutral_sep
    ca, sa = np.cos(azimuth), np.sin(azimuth)
    out = []
    for sign in (-1.0, 1.0):
        z = zenith + sign * h
        sz, cz = np.sin(z), np.cos(z)
        d_z = np.array([cz * ca, cz * sa, -sz])
        out.append(np.column_stack([np.array([sz * ca, sz * sa, cz]),
                                    np.array([-sz * sa, sz * ca, 0.0]), d_z, 0.5 * sign * d_z]))  # fmt: skip
    return out[0], out[1]


def _unit_rows(rays: ArrayLike) -> tuple[NDArray, NDArray]:
    """Component-first unit rays ``(3, n)`` of trailing-component rays and ``1/(1 + p_z)``."""
    p = np.asarray(rays, dtype=float).reshape(-1, 3)
    p = (p / np.linalg.norm(p, axis=1, keepdims=True)).T.copy()
    with np.errstate(divide="ignore"):
        return p, 1.0 / (1.0 + p[2])


def berry_rotation(
    rays: ArrayLike, sun: ArrayLike, neutral_sep: float, up: ArrayLike = (0.0, 0.0, 1.0)
) -> FloatArray:
    """Rotation ``dchi`` [rad] ``(...)`` about each ray that turns the Rayleigh E-vector
    ``s x p`` into the Berry sky's (module notes), in ``(-pi/2, pi/2]``; 0 for
    ``neutral_sep = 0``, NaN at the sun, the anti-sun and the neutral points.

    Parameters
    ----------
    rays : array_like, (..., 3)
        Observation rays (normalised here).
    sun : array_like, (3,)
        Unit sun vector, same frame.
    neutral_sep : float
        Separation of the Babinet and Brewster points [rad], in ``[0, pi)``.
    up : array_like, (3,)
        The local vertical in that frame (the neutral points lie on the solar vertical).
    """
    shape = np.shape(rays)[:-1]
    p, inv = _unit_rows(rays)
    n1, n2 = _points(sun, neutral_sep, up)
    a_s, a_1, a_2 = (tangent_components(p, inv, q) for q in (np.asarray(sun, float), n1, n2))
    c, s, m = berry_half_rotation(a_s, a_1, a_2)
    with np.errstate(invalid="ignore"):
        out = np.where(m > 0, np.arctan2(s, c), np.nan)
    return out.reshape(shape)


def berry_polarization(
    rays: ArrayLike, sun: ArrayLike, neutral_sep: float, up: ArrayLike = (0.0, 0.0, 1.0)
) -> FloatArray:
    """Unnormalised polarization ``|a_1| |a_2| = sin T_1 sin T_2`` ``(...)`` of the Berry
    sky (``T_k`` the angle from the ray to the Babinet and Brewster points): zero at the
    four neutral points, ``sin^2`` of the scattering angle for ``neutral_sep = 0`` (the
    degree of polarization is ``d_max |w| / (2 - |w|)``, docs/model.md §6.3)."""
    shape = np.shape(rays)[:-1]
    p, inv = _unit_rows(rays)
    n1, n2 = _points(sun, neutral_sep, up)
    mags = [np.hypot(*tangent_components(p, inv, q)) for q in (n1, n2)]
    return (mags[0] * mags[1]).reshape(shape)


def _points(sun: ArrayLike, neutral_sep: float, up: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Babinet and Brewster points (3,) of a unit ``sun`` with the vertical ``up``."""
    if not 0.0 <= neutral_sep < np.pi:
        raise ValueError(f"neutral_sep={neutral_sep} outside [0, pi) rad")
    s = np.asarray(sun, dtype=float)
    s = s / np.linalg.norm(s)
    u = np.asarray(up, dtype=float)
    u = u / np.linalg.norm(u)
    toward_up = u - (s @ u) * s
    norm = np.linalg.norm(toward_up)
    if not norm > 1e-12:
        raise ValueError("the sun is at the zenith or nadir: the solar vertical is undefined")
    toward_up /= norm
    h = 0.5 * neutral_sep
    return np.cos(h) * s + np.sin(h) * toward_up, np.cos(h) * s - np.sin(h) * toward_up
