"""The site: where on the Earth a recording was made, and the one way polins reads absolute times.

One :class:`Site` serves every entry point (``polins.fuse``, ``build_filter``, the graph,
the stream, the manifest and the CLI). There is no silent default site: where a site is
optional, its absence is reported (docs/faults.md).
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any, TypeAlias

import pandas as pd

from polins.errors import UserInputError

TimeLike: TypeAlias = (
    str | dt.datetime | pd.Timestamp | pd.DatetimeIndex | Iterable[str | dt.datetime]
)


@dataclass(frozen=True)
class Site:
    """A geodetic position on the WGS-84 ellipsoid.

    Attributes
    ----------
    lat_deg : float
        Geodetic latitude [deg], in [-90, 90].
    lon_deg : float
        Longitude [deg], east positive, in [-180, 360).
    alt_m : float
        Height above the WGS-84 ellipsoid [m] (default 0).
    """

    lat_deg: float
    lon_deg: float
    alt_m: float = 0.0

    def __post_init__(self) -> None:
        for name in ("lat_deg", "lon_deg", "alt_m"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise UserInputError(f"Site.{name} must be a number, got {value!r}")
            if not math.isfinite(value):
                raise UserInputError(f"Site.{name} must be finite, got {value}")
            object.__setattr__(self, name, float(value))
        if not -90.0 <= self.lat_deg <= 90.0:
            raise UserInputError(
                f"Site.lat_deg={self.lat_deg} outside [-90, 90] (degrees expected)"
            )
        if not -180.0 <= self.lon_deg < 360.0:
            raise UserInputError(
                f"Site.lon_deg={self.lon_deg} outside [-180, 360) (degrees expected)"
            )
        if not -1.0e4 <= self.alt_m <= 1.0e5:
            raise UserInputError(
                f"Site.alt_m={self.alt_m} outside [-10 km, 100 km] (metres expected)"
            )

    @property
    def lat(self) -> float:
        """Latitude [rad]."""
        return math.radians(self.lat_deg)

    @property
    def lon(self) -> float:
        """Longitude [rad]."""
        return math.radians(self.lon_deg)

    @classmethod
    def coerce(cls, value: Site | Mapping[str, Any] | tuple[float, ...]) -> Site:
        """A :class:`Site` from a Site, a mapping with its fields or a (lat_deg, lon_deg[, alt_m]) tuple."""
        if isinstance(value, Site):
            return value
        if isinstance(value, Mapping):
            return cls(**value)
        if isinstance(value, tuple | list):
            return cls(*value)
        raise TypeError(
            f"site must be a polins.Site, a mapping or (lat_deg, lon_deg, alt_m), got {value!r}"
        )


PAPER_SITE = Site(45.6234, 126.7264, 148.74)
"""The paper's experiment site (Harbin): the default of the simulator, never of the filter."""


def utc_timestamp(value: Any, what: str | None = "epoch_utc") -> pd.Timestamp:
    """A timezone-aware time as a UTC ``Timestamp``; a naive time is a ``ValueError``.

    ``what`` names the value in messages (None: the caller names it).
    """
    prefix = f"{what} = {value!r}: " if what else ""
    try:
        ts = pd.Timestamp(value)
    except (ValueError, TypeError):
        raise UserInputError(f"{prefix}not an ISO time") from None
    if ts is pd.NaT:
        raise UserInputError(f"{prefix}not an ISO time")
    if ts.tzinfo is None:
        raise UserInputError(
            f"{prefix}naive datetime: give a timezone, e.g. '2023-09-05T07:00:00+00:00'; "
            "polins never assumes UTC"
        )
    return ts.tz_convert("UTC")


def to_utc_index(t: TimeLike) -> pd.DatetimeIndex:
    """Timezone-aware times as a UTC ``DatetimeIndex``; naive times raise ``ValueError``."""
    items = [t] if isinstance(t, str | dt.datetime) else list(t)
    return pd.DatetimeIndex([utc_timestamp(item, what=None) for item in items])
