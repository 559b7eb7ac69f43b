"""Solar ephemeris: apparent sun position from pvlib's NREL SPA, and the ENU sun vector.

The solar position algorithm itself is pvlib's implementation of Reda & Andreas (2004),
"Solar position algorithm for solar radiation applications" (NREL/TP-560-34302); polins
only fixes the conventions: azimuth clockwise from true North, apparent (refracted)
zenith, radians, timezone-aware times.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from polins.site import TimeLike, to_utc_index

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SunPosition:
    """Apparent solar position.

    Attributes
    ----------
    azimuth : ndarray
        Solar azimuth [rad], clockwise from true North, in [0, 2 pi).
    zenith : ndarray
        Apparent (refraction-corrected) solar zenith angle [rad].
    """

    azimuth: FloatArray
    zenith: FloatArray


def sun_position(
    t: TimeLike,
    lat_deg: float,
    lon_deg: float,
    alt_m: float = 0.0,
    *,
    pressure_pa: float | None = None,
    temperature_c: float = 12.0,
    delta_t_s: float | None = None,
) -> SunPosition:
    """Apparent solar azimuth and zenith by the NREL SPA (pvlib).

    Parameters
    ----------
    t : datetime, str, Timestamp, DatetimeIndex or sequence of them
        Timezone-aware time(s). A naive time raises ``ValueError``.
    lat_deg, lon_deg : float
        Geodetic latitude [deg, North positive] and longitude [deg, East positive].
    alt_m : float
        Height above the ellipsoid [m].
    pressure_pa : float, optional
        Air pressure for refraction [Pa]; default: standard atmosphere at ``alt_m``.
    temperature_c : float
        Air temperature for refraction [deg C].
    delta_t_s : float, optional
        TT - UT1 [s]; default: pvlib's estimate for the date.

    Returns
    -------
    SunPosition
        Azimuth and apparent zenith [rad]; scalars (0-d) for a scalar ``t``, else arrays.
    """
    if not -90.0 <= lat_deg <= 90.0:
        raise ValueError(f"lat_deg={lat_deg} outside [-90, 90] (degrees expected)")
    if not -180.0 <= lon_deg <= 360.0:
        raise ValueError(f"lon_deg={lon_deg} outside [-180, 360] (degrees expected)")
    scalar = isinstance(t, str | dt.datetime)
    times = to_utc_index(t)
    import pvlib  # imported on first use: it costs a third of a second at import

    pressure = pvlib.atmosphere.alt2pres(alt_m) if pressure_pa is None else pressure_pa
    spa = pvlib.solarposition.spa_python(
        times,
        lat_deg,
        lon_deg,
        altitude=alt_m,
        pressure=pressure,
        temperature=temperature_c,
        delta_t=delta_t_s,
    )
    azimuth = np.radians(spa["azimuth"].to_numpy(dtype=float))
    zenith = np.radians(spa["apparent_zenith"].to_numpy(dtype=float))
    if scalar:
        return SunPosition(azimuth=azimuth[0], zenith=zenith[0])
    return SunPosition(azimuth=azimuth, zenith=zenith)


def sun_vector_n(azimuth: ArrayLike, zenith: ArrayLike) -> FloatArray:
    """Unit sun vector in ENU: ``(sin Z sin A, sin Z cos A, cos Z)``, shape ``(..., 3)``.

    Parameters
    ----------
    azimuth : array_like
        Solar azimuth [rad], clockwise from North.
    zenith : array_like
        Solar zenith angle [rad].
    """
    a = np.asarray(azimuth, dtype=float)
    z = np.asarray(zenith, dtype=float)
    return np.stack(
        np.broadcast_arrays(np.sin(z) * np.sin(a), np.sin(z) * np.cos(a), np.cos(z)), -1
    )


def sun_azimuth_zenith(sun_n: ArrayLike) -> SunPosition:
    """Inverse of :func:`sun_vector_n`: azimuth (clockwise from North) and zenith [rad]."""
    s = np.asarray(sun_n, dtype=float)
    s = s / np.linalg.norm(s, axis=-1, keepdims=True)
    azimuth = np.mod(np.arctan2(s[..., 0], s[..., 1]), 2.0 * np.pi)
    return SunPosition(azimuth=azimuth, zenith=np.arccos(np.clip(s[..., 2], -1.0, 1.0)))
