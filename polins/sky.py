"""Skylight polarization: single-scattering Rayleigh model (SPEC.md section 6.1).

For a unit ray ``p`` and the unit sun vector ``s`` in the same frame, the E-vector is
perpendicular to the scattering plane, ``e ~ s x p``, and the degree of linear
polarization is ``d = d_max sin^2(Theta) / (1 + cos^2(Theta))`` with ``cos(Theta) = p . s``.
The estimators use only the E-vector geometry, never the DoP magnitude.
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
