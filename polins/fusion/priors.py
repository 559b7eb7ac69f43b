"""The turn-on sigmas and random-walk time scales of error states that the ESKF and the graph share.

Both backends model these states alike (docs/filter.md): the ESKF's blocks
(:mod:`polins.fusion.eskf.blocks`) and the graph's variables (:mod:`polins.fusion.graph`)
take their values from here.
"""

from __future__ import annotations

# Without a site the Earth rate is not mechanized: the gyro bias covers it, as a turn-on
# term of the Earth rate and a random walk that lets its horizontal part turn with the
# heading over about EARTH_RATE_TURN_S [s] (docs/filter.md, "Without a site").
EARTH_RATE_TURN_S = 60.0

# No clock: the sun's azimuth is unknown at the start (its first measurement sets it, with
# the yaw's sigma); its rate may change by its own 1-sigma over SUN_RATE_CHANGE_S [s].
SUN_AZIMUTH_STD0 = 10.0  # [rad], "unknown"
SUN_RATE_CHANGE_S = 3600.0

__all__ = ["EARTH_RATE_TURN_S", "SUN_AZIMUTH_STD0", "SUN_RATE_CHANGE_S"]
