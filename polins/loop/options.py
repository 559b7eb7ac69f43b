"""Options of the navigation loop: how images are measured and when, what the loop keeps in memory.

The filter itself is configured by one :class:`polins.fusion.config.FuseConfig` (its
``max_gap_s`` is also the loop's IMU gap length); the loop's ``update`` choice sets its
``use_sun`` (and, with ``tilt_coupling="auto"``, the tilt coupling) through
:meth:`LoopOptions.filter_config`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from polins.errors import UnknownOptionError, UserInputError
from polins.fusion.config import FuseConfig

UPDATES = ("yaw", "sun")
_NOT_LOOP_OPTIONS = {
    "max_imu_gap_s": "is FuseConfig's max_gap_s (one IMU gap length for the loop and the filter)"
}


@dataclass(frozen=True)
class LoopOptions:
    """Options of the Eq. 13 loop (docs/model.md; SI units, radians).

    Attributes
    ----------
    method : str
        ``polins.measure`` method ("compensated", "traditional").
    measure_options : mapping
        Keyword options of ``polins.measure`` (``polins.compass.MeasureOptions`` fields).
    update : {"yaw", "sun"}
        Filter update per image: the yaw with the tilt coupling in ``H`` (default), or the
        2-DOF sun vector. Either way the sun zenith is measured from the image
        (``fixed_zenith=False`` unless ``measure_options`` says otherwise): the filter's
        yaw model is then exact in the prior's tilt (docs/measurement.md, "The yaw in a
        filter"), and the free zenith costs no precision.
    prior_lag_s : float
        Age of the filter snapshot the image priors are propagated from [s]
        (``polins.loop.stream``).
    snapshot_every_s : float
        Grid of the filter snapshots [s].
    max_image_delay_s : float
        How long the filter waits for an image that is older than the newest IMU sample [s]
        (streaming: the camera's delivery latency).
    max_in_flight : int or None
        Images being measured at once; default ``2 * workers + 1``.
    max_table_rows : int
        Bound of the in-memory measurement, event and solution buffers.
    """

    method: str = "compensated"
    measure_options: Mapping[str, Any] = field(default_factory=dict)
    update: str = "yaw"
    prior_lag_s: float = 1.0
    snapshot_every_s: float = 0.1
    max_image_delay_s: float = 0.5
    max_in_flight: int | None = None
    max_table_rows: int = 1_000_000

    def __new__(cls, *args: Any, **kwargs: Any) -> LoopOptions:
        for name in kwargs:
            if name in _NOT_LOOP_OPTIONS:
                raise UnknownOptionError(f"LoopOptions: {name!r} {_NOT_LOOP_OPTIONS[name]}")
        return super().__new__(cls)

    def __post_init__(self) -> None:
        if self.update not in UPDATES:
            raise UserInputError(f"update={self.update!r}: expected one of {UPDATES}")
        for name in ("prior_lag_s", "max_image_delay_s"):
            if not getattr(self, name) >= 0.0:
                raise UserInputError(f"{name}={getattr(self, name)} must be >= 0 [s]")
        if not self.snapshot_every_s > 0.0:
            raise UserInputError(f"snapshot_every_s={self.snapshot_every_s} must be > 0 [s]")
        if self.max_in_flight is not None and self.max_in_flight < 1:
            raise UserInputError(f"max_in_flight={self.max_in_flight} must be >= 1")
        if self.max_table_rows < 1:
            raise UserInputError(f"max_table_rows={self.max_table_rows} must be >= 1")
        if self.update == "sun" and self.measure_options.get("fixed_zenith", False):
            raise UserInputError(
                "update='sun' needs the sun zenith measured from the image: "
                "measure_options fixed_zenith=False"
            )

    def measure_kwargs(self) -> dict[str, Any]:
        """The ``polins.measure`` options actually used."""
        opts = dict(self.measure_options)
        opts.setdefault("fixed_zenith", False)
        return opts

    def filter_config(self, config: FuseConfig) -> FuseConfig:
        """The filter configuration of this loop: ``config`` with ``use_sun`` set by
        ``update``, and ``tilt_coupling`` on for ``update="yaw"`` unless ``config`` sets it."""
        tilt = config.gating.tilt_coupling
        tilt = self.update == "yaw" if tilt == "auto" else tilt
        return config.replace(use_sun=self.update == "sun", tilt_coupling=tilt)


__all__ = ["UPDATES", "LoopOptions"]
