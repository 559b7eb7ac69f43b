"""WGS-84 Earth model: normal gravity, Earth rate, radii of curvature, transport rate (ENU).

References: NIMA TR8350.2 (WGS-84), Somigliana's closed formula for normal gravity on the
ellipsoid and its second-order height expansion (TR8350.2 Eq. 4-1 and 4-3).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

A = 6378137.0  # semi-major axis [m]
F = 1.0 / 298.257223563  # flattening
B = A * (1.0 - F)  # semi-minor axis [m]
E2 = F * (2.0 - F)  # first eccentricity squared
OMEGA_IE = 7.292115e-5  # Earth rotation rate [rad/s]
GM = 3.986004418e14  # gravitational constant [m^3/s^2]
GAMMA_E = 9.7803253359  # normal gravity at the equator [m/s^2]
GAMMA_P = 9.8321849378  # normal gravity at the poles [m/s^2]
_K = B * GAMMA_P / (A * GAMMA_E) - 1.0
_M = OMEGA_IE**2 * A**2 * B / GM


def somigliana(sin2_lat: Any, height: Any) -> Any:
    """:func:`normal_gravity` from ``sin(lat)^2`` (plain arithmetic on floats or arrays: the
    compiled strapdown calls it too)."""
    gamma0 = GAMMA_E * (1.0 + _K * sin2_lat) / np.sqrt(1.0 - E2 * sin2_lat)
    return gamma0 * (
        1.0 - 2.0 / A * (1.0 + F + _M - 2.0 * F * sin2_lat) * height + 3.0 * height * height / A**2
    )


def radii_from_sin2(sin2_lat: Any) -> tuple[Any, Any]:
    """:func:`radii_of_curvature` from ``sin(lat)^2`` (plain arithmetic, as :func:`somigliana`)."""
    w = np.sqrt(1.0 - E2 * sin2_lat)
    return A * (1.0 - E2) / w**3, A / w


def normal_gravity(lat: ArrayLike, height: ArrayLike = 0.0) -> FloatArray:
    """Magnitude of WGS-84 normal gravity [m/s^2] at geodetic latitude [rad] and height [m]."""
    s2 = np.sin(np.asarray(lat, dtype=float)) ** 2
    return somigliana(s2, np.asarray(height, dtype=float))


def normal_gravity_gradient(lat: ArrayLike, height: ArrayLike = 0.0) -> FloatArray:
    """Vertical gradient ``d gamma / d h`` of :func:`normal_gravity` [1/s^2] (the free-air
    gradient, about -3.086e-6 1/s^2 at the surface)."""
    s2 = np.sin(np.asarray(lat, dtype=float)) ** 2
    h = np.asarray(height, dtype=float)
    gamma0 = GAMMA_E * (1.0 + _K * s2) / np.sqrt(1.0 - E2 * s2)
    return gamma0 * (-2.0 / A * (1.0 + F + _M - 2.0 * F * s2) + 6.0 * h / A**2)


def gravity_n(lat: ArrayLike, height: ArrayLike = 0.0) -> FloatArray:
    """Normal gravity vector in ENU, ``(..., 3)`` = (0, 0, -gamma) [m/s^2]."""
    g = normal_gravity(lat, height)
    return np.stack([np.zeros_like(g), np.zeros_like(g), -g], axis=-1)


def earth_rate_n(lat: ArrayLike) -> FloatArray:
    """Earth rotation rate in ENU, ``(..., 3)`` = (0, w cos lat, w sin lat) [rad/s]."""
    phi = np.asarray(lat, dtype=float)
    return np.stack([np.zeros_like(phi), OMEGA_IE * np.cos(phi), OMEGA_IE * np.sin(phi)], -1)


def radii_of_curvature(lat: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Meridian and prime-vertical radii of curvature ``(R_M, R_N)`` [m]."""
    return radii_from_sin2(np.sin(np.asarray(lat, dtype=float)) ** 2)


def transport_rate_n(lat: ArrayLike, height: ArrayLike, vel_n: ArrayLike) -> FloatArray:
    """Rotation rate of ENU relative to ECEF, ``(..., 3)`` [rad/s], for velocity ``vel_n`` [m/s]."""
    phi = np.asarray(lat, dtype=float)
    h = np.asarray(height, dtype=float)
    v = np.asarray(vel_n, dtype=float)
    r_m, r_n = radii_of_curvature(phi)
    ve, vn = v[..., 0], v[..., 1]
    return np.stack([-vn / (r_m + h), ve / (r_n + h), ve * np.tan(phi) / (r_n + h)], axis=-1)
