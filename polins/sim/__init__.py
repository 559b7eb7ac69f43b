"""Simulation: sky, polarization images, trajectories and IMU data (never imported by library code)."""

from polins.sim.realsky import RealSky, ThinCloud, random_real_sky, render_real_raw
from polins.sim.render import CloudPatch, azimuth_band, render_raw

__all__ = [
    "CloudPatch",
    "RealSky",
    "ThinCloud",
    "azimuth_band",
    "random_real_sky",
    "render_raw",
    "render_real_raw",
]
