"""polins: bio-inspired polarization navigation.

A division-of-focal-plane (DoFP) polarization camera looks at the sky; polins turns its raw
images into a sun vector and a heading and fuses them with a gyro/accelerometer in an
error-state Kalman filter (filterpy) or a GTSAM factor graph.

Data flow (one module per physical concept)::

    raw DoFP mosaic                     polins.compass.polarimetry   (mosaic -> channels -> Stokes)
      -> four polarizer channels        polins.compass.camera        (per-pixel rays, lens polarization)
      -> Stokes (traditional / paper / compensated)
      -> per-pixel E-vectors, camera    polins.sky.scattering           (Rayleigh single scattering)
      -> sun vector (eigen / joint ML)  polins.compass.measure       (polins.measure)
      -> heading, 180 deg resolved      polins.sky.ephemeris     (sun position, pvlib NREL SPA)
      -> ESKF or GTSAM graph            polins.ins.strapdown, polins.fusion (polins.fuse)
      -> INS attitude back into the next image's compensation and tilt handling

Conventions (the contract is ``CONVENTIONS.md``; ``docs/conventions.md`` explains it)
------------------------------------------------------------------------------------
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
from polins.models.loader import CameraModel, ImuModel, load_camera, load_imu
from polins.sky.ephemeris import SunPosition, sun_position, sun_vector_n

__version__ = "0.1.0"

# Heavy or optional parts load on first use: ``polins.sim`` is never imported by library
# code, and the fusion backends pull in filterpy (and gtsam for the graph).
_LAZY = {
    "measure": "polins.compass.measure",
    "Measurement": "polins.compass.measure",
    "fuse": "polins.fusion",
    "NavigationStream": "polins.loop",
    "sim": "polins.sim",
}


def __getattr__(name: str) -> Any:
    module_name = _LAZY.get(name)
    if module_name is None:
        raise AttributeError(f"module 'polins' has no attribute {name!r}")
    module = importlib.import_module(module_name)
    return module if module_name == f"polins.{name}" else getattr(module, name)


__all__ = [
    "CameraModel",
    "ImuModel",
    "Measurement",
    "NavigationStream",
    "SunPosition",
    "fuse",
    "heading_deg_from_yaw",
    "load_camera",
    "load_imu",
    "measure",
    "rot_nb_from_euler",
    "sim",
    "sun_position",
    "sun_vector_n",
    "wrap_angle",
    "yaw_from_heading_deg",
]
