"""Simulation: sky, polarization images, trajectories and IMU data (never imported by library code)."""

from polins.sim.render import CloudPatch, azimuth_band, render_raw

__all__ = ["CloudPatch", "azimuth_band", "render_raw"]
