"""Fusion of IMU with polarization measurements: measurement models, ESKF and GTSAM backends."""
