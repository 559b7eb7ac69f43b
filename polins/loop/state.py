"""What the navigation stream reports: :class:`StreamState`, its live estimate."""

from __future__ import annotations

from dataclasses import dataclass

from polins.ins.state import NavState


@dataclass(frozen=True, eq=False)
class StreamState:
    """What :meth:`NavigationStream.state` reports.

    Attributes
    ----------
    nav : NavState or None
        The filter's live estimate (all accepted IMU samples, all measurements known so
        far); its ``yaw_aligned`` is False until the first heading (self-alignment), and
        the yaw is then meaningless. None while ``aligning``.
    aligning : bool
        No attitude yet: no IMU sample, or the self-alignment is still levelling.
    images_pending : int
        Images added but not yet handed to the filter.
    """

    nav: NavState | None
    aligning: bool
    images_pending: int

    @property
    def heading_known(self) -> bool:
        """The estimate has a heading (levelled, and the yaw aligned)."""
        return self.nav is not None and bool(self.nav.yaw_aligned)


__all__ = ["StreamState"]
