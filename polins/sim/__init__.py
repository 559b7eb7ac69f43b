"""Simulation: sky, polarization images, trajectories and IMU data (never imported by library code)."""
