"""polins: bio-inspired polarization navigation.

A division-of-focal-plane (DoFP) polarization camera looks at the sky; polins turns its raw
images into a sun vector and a heading and fuses them with a gyro/accelerometer in an
error-state Kalman filter (filterpy) or a GTSAM factor graph.

The package reads in the order of the data flow (one subpackage per stage; the import
contract in pyproject.toml lets each stage import only the stages before it)::

    models/   camera and IMU model files (TOML)          polins.load_camera, polins.load_imu
    sky/      sun position (pvlib NREL SPA), sky models   polins.sun_position, polins.sun_vector_n
    compass/  one image -> heading                        polins.measure
              raw DoFP mosaic -> channels                 compass.pixels
              -> Stokes (S0, S1, S2), masks               compass.polarimetry, compass.sunlight
              -> per-pixel E-vectors (lens constants)     compass.camera, compass.lens
              -> sun vector: eigen / joint ML             compass.eigen, compass.jointml
              -> heading, 180 deg resolved, sigma         compass.heading, compass.measure
    ins/      Earth model, strapdown, static alignment
    fusion/   IMU + headings -> attitude: ESKF or graph   polins.fuse, polins.FuseConfig
    loop/     the INS attitude back into the next image   polins.NavigationStream, loop.run_log
    io/, tuning/, calibration/, sim/, cli: files, noise models, camera calibration,
              the simulator and the ``polins`` command

Conventions (docs/conventions.md has the full contract)
-------------------------------------------------------
Frames
    ``n`` local navigation frame ENU (x East, y North, z Up); ``b`` body/IMU frame FLU
    (x forward, y left, z up, ROS REP-103); ``c`` camera frame, OpenCV (x along image
    columns u, y along image rows v, z optical axis towards the sky); ``l`` level frame
    (z Up, x the horizontal projection of body x); ``e`` ECEF WGS-84.
Rotations
    ``mat_ab`` maps frame b to frame a (``v_a = mat_ab @ v_b``); code uses
    ``scipy.spatial.transform.Rotation`` objects named ``rot_ab``.
    ``rot_nb = Rotation.from_euler("ZYX", [yaw, pitch, roll])``: positive pitch is nose
    down, positive roll is right side down.
Angles
    ``yaw`` [rad] ENU, counter-clockwise from East, of body x, wrapped to (-pi, pi];
    ``heading_deg`` compass heading clockwise from true North in [0, 360),
    ``heading_deg = (90 - degrees(yaw)) mod 360``. Solar azimuth clockwise from North,
    solar zenith apparent (refracted). Image-plane angles (AoP, polarizer axes) are
    measured from +x_c towards +y_c; the AoP is axial and handled through doubled angles.
Units
    Radians, metres, seconds and SI inside the library; any other unit is carried in the
    name (``lat_deg``, ``gyro_arw_deg_per_sqrt_h``). Intensities are in digital numbers [DN].
Time
    All streams are stamped in float seconds ``t`` on one clock; a dataset carries one
    timezone-aware UTC epoch. A naive datetime is an error, never silently UTC.
Arrays
    Leading axes are batch (time, pixels), the trailing axis is the component: rays and
    vectors ``(..., 3)``, Stokes ``(..., 3)`` = (S0, S1, S2) with S1 = I0 - I90,
    S2 = I45 - I135.
"""

from __future__ import annotations

import importlib
from typing import Any

from polins.frames import (
    heading_deg_from_yaw,
    rot_nb_from_euler,
    wrap_angle,
    yaw_from_heading_deg,
)
from polins.models import CameraModel, ImuModel, load_camera, load_imu
from polins.site import Site
from polins.sky.ephemeris import SunPosition, sun_position, sun_vector_n

__version__ = "0.1.0"

# Heavy or optional parts load on first use: ``polins.sim`` is never imported by library
# code, and the fusion backends pull in filterpy (and gtsam for the graph).
_LAZY = {
    "measure": "polins.compass.measure",
    "Measurement": "polins.compass.measure",
    "fuse": "polins.fusion",
    "run_fusion": "polins.fusion",
    "FusionResult": "polins.fusion",
    "ImuUnitsError": "polins.fusion",
    "ImplausibleRunError": "polins.fusion",
    "measurement_table": "polins.fusion.inputs",
    "FuseConfig": "polins.fusion.config",
    "Aiding": "polins.fusion.config",
    "Initial": "polins.fusion.config",
    "Noise": "polins.fusion.config",
    "Gating": "polins.fusion.config",
    "SkyStates": "polins.fusion.config",
    "GraphSolver": "polins.fusion.config",
    "Output": "polins.fusion.config",
    "NavigationStream": "polins.loop",
    "LoopOptions": "polins.loop",
    "sim": "polins.sim",
}


def __getattr__(name: str) -> Any:
    module_name = _LAZY.get(name)
    if module_name is None:
        raise AttributeError(f"module 'polins' has no attribute {name!r}")
    module = importlib.import_module(module_name)
    return module if module_name == f"polins.{name}" else getattr(module, name)


__all__ = [
    "Aiding",
    "CameraModel",
    "FuseConfig",
    "FusionResult",
    "Gating",
    "GraphSolver",
    "ImplausibleRunError",
    "ImuModel",
    "ImuUnitsError",
    "Initial",
    "LoopOptions",
    "Measurement",
    "NavigationStream",
    "Noise",
    "Output",
    "Site",
    "SkyStates",
    "SunPosition",
    "fuse",
    "heading_deg_from_yaw",
    "load_camera",
    "load_imu",
    "measure",
    "measurement_table",
    "rot_nb_from_euler",
    "run_fusion",
    "sim",
    "sun_position",
    "sun_vector_n",
    "wrap_angle",
    "yaw_from_heading_deg",
]
