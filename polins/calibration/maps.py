"""Per-pixel calibration maps: saving and loading the gain, angle and efficiency maps as .npy files.

A map is a float32 array ``(Hs, Ws, 4)``: one value per superpixel and polarizer channel,
channels in the camera model's order, angles in radians, NaN for "the channel's value"
(docs/calibrate.md#per-pixel-maps). The files are written with
``numpy.save(..., allow_pickle=False)`` and read back the same way, so a map file can never
execute code. The camera loader reads the same files with the same function
(:mod:`polins.models.maps`); a camera file names them in its ``[polarizer]`` table.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from polins.models import CameraModel, save_pixel_map
from polins.models import load_pixel_map as load_map_file

__all__ = ["load_pixel_map", "save_pixel_map"]


def load_pixel_map(path: str | Path, cam: CameraModel) -> NDArray[np.float64]:
    """Read a per-pixel map written by :func:`save_pixel_map` and check it fits ``cam``.

    Raises
    ------
    polins.models.ModelFileError
        (a ``UserInputError``) Missing, not a plain numeric .npy file, or a shape other than
        ``(*cam.superpixel_shape, 4)``.
    """
    return load_map_file(path, cam.superpixel_shape, what=f"camera {cam.name!r}")
