"""Direct sunlight: the camera-fixed pseudo-polarization it adds, and its exact compensation.

Sunlight scattered inside the lens adds ``-eps u`` to S0 and ``eps u w`` to the linear
Stokes vector L, with ``u`` the sky's unpolarized intensity and ``w`` a doubled-angle
direction fixed by the sun's azimuth in the image plane (docs/model.md §6.2; the paper's
Eqs. 8/12 in Stokes form). :func:`stokes_with_sunlight` is this forward model as the
estimators use it (the Cramer-Rao bound, the tests); the renderer has its own,
independently written version. :func:`stokes_compensated` is the exact inverse
(docs/model.md §8.1), and :func:`sunlight_unpolarized` its row kernel, which the joint
maximum likelihood evaluates at every iteration.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from polins.compass.polarimetry import unpolarized_intensity

FloatArray = NDArray[np.float64]

__all__ = [
    "stokes_compensated",
    "stokes_with_sunlight",
    "sunlight_direction",
    "sunlight_unpolarized",
]


def sunlight_direction(sun_c: ArrayLike) -> FloatArray:
    """Doubled-angle direction ``w = -(cos 2alpha_s, sin 2alpha_s)`` ``(..., 2)`` of the
    direct-sunlight pseudo-polarization (docs/model.md §6.2), ``alpha_s = atan2(s_y, s_x)``
    the sun's azimuth in the image plane; computed without trigonometry."""
    s = np.asarray(sun_c, dtype=float)
    sx, sy = s[..., 0], s[..., 1]
    rho2 = sx * sx + sy * sy
    if np.any(rho2 <= 0.0):
        raise ValueError("the sun is on the optical axis: its image-plane azimuth is undefined")
    return -np.stack([(sx * sx - sy * sy) / rho2, 2.0 * sx * sy / rho2], axis=-1)


def sunlight_unpolarized(
    s0: NDArray,
    s1: NDArray,
    s2: NDArray,
    c: NDArray,
    eps: float | np.floating,
    w: NDArray,
    finite: bool = True,
) -> NDArray:
    """Exact sky unpolarized intensity ``u`` [DN] from measured Stokes rows (docs/model.md
    §8.1), any dtype and shape; ``c = S0^2 - |L|^2``, ``w`` the :func:`sunlight_direction`.

    The discriminant ``B^2 - (1 - 2 eps) C`` is a sum of squares for eps < 1/2 (it equals
    ``(eps S0 - (1 - eps) L.w)^2 + (1 - 2 eps)(|L|^2 - (L.w)^2)``), so its absolute value
    only removes rounding. ``finite=False`` is the fast path for callers that mask
    non-physical pixels themselves: no clean-up of ``S0 <= 0`` pixels and no ``u >= 0``
    clamp (a noisy pixel with DoP > 1 keeps its slightly negative, unbiased u).
    """
    b = s0 * (1.0 - eps)
    b -= eps * (s1 * w[0] + s2 * w[1])
    disc = b * b
    disc -= (1.0 - 2.0 * eps) * c
    np.abs(disc, out=disc)
    np.sqrt(disc, out=disc)
    disc += b
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.divide(c, disc, out=disc)
    if not finite:
        return u
    u = np.nan_to_num(u, nan=0.0, posinf=0.0, neginf=0.0, copy=False)
    return np.maximum(u, 0.0, out=u)


def stokes_with_sunlight(stokes_sky: ArrayLike, epsilon: float, w: ArrayLike) -> FloatArray:
    """Measured Stokes vectors ``(..., 3)`` [DN]: the sky's with the direct-sunlight term
    added (docs/model.md §6.2), the forward model of the estimators.

    ``S0 - eps u``, ``L + eps u w`` with ``u = S0_sky - |L_sky|``; the inverse is
    :func:`stokes_compensated`. (``polins.sim.render.add_direct_sunlight`` is the
    renderer's own version, kept independent of the estimator on purpose.)

    Parameters
    ----------
    stokes_sky : array_like, (..., 3)
        Sky Stokes vectors [DN].
    epsilon : float
        Direct-sunlight coefficient.
    w : array_like, (..., 2)
        Doubled-angle sunlight direction, :func:`sunlight_direction`.
    """
    s = np.asarray(stokes_sky, dtype=float)
    wv = np.asarray(w, dtype=float)
    u = unpolarized_intensity(s)
    out = s.copy()
    out[..., 0] -= epsilon * u
    out[..., 1] += epsilon * u * wv[..., 0]
    out[..., 2] += epsilon * u * wv[..., 1]
    return out


def stokes_compensated(stokes: ArrayLike, epsilon: float, w: ArrayLike) -> FloatArray:
    """Exact direct-sunlight compensation of measured Stokes vectors (docs/model.md §8.1).

    Solves ``S0 = p + (1 - eps) u`` and ``|L - eps u w| = p`` for the sky's unpolarized
    intensity ``u`` (physical, numerically stable root), then returns
    ``(S0 + eps u, L - eps u w)``.

    Parameters
    ----------
    stokes : array_like, (..., 3)
        Measured Stokes vectors [DN].
    epsilon : float
        Direct-sunlight coefficient (docs/model.md §6.2), >= 0 and < 0.5.
    w : array_like, (2,)
        Doubled-angle sunlight direction, :func:`sunlight_direction` of the sun vector.
    """
    if not 0.0 <= epsilon < 0.5:
        raise ValueError(f"epsilon={epsilon} outside [0, 0.5)")
    s = np.asarray(stokes, dtype=float)
    wv = np.asarray(w, dtype=float)
    s0, s1, s2 = s[..., 0], s[..., 1], s[..., 2]
    u = sunlight_unpolarized(s0, s1, s2, s0 * s0 - s1 * s1 - s2 * s2, epsilon, wv)
    return np.stack([s0 + epsilon * u, s1 - epsilon * u * wv[0], s2 - epsilon * u * wv[1]], -1)
