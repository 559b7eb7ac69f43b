"""Recorded logs: manifest, IMU tables, image folders and solution outputs."""
