"""Per-pixel calibration maps: saving and loading the gain, angle and efficiency maps as .npy files.

A map is a float32 array ``(Hs, Ws, 4)``: one value per superpixel and polarizer channel,
channels in the camera model's order, angles in radians (docs/calibrate.md#per-pixel-maps).
Maps are written with ``numpy.save(..., allow_pickle=False)`` and read back the same way, so
a map file can never execute code.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from polins.errors import UserInputError
from polins.models.loader import CameraModel

__all__ = ["load_pixel_map", "save_pixel_map"]


def save_pixel_map(path: str | Path, values: ArrayLike) -> Path:
    """Write a per-pixel map ``(Hs, Ws, 4)`` as a float32 ``.npy`` file (no pickle); returns
    the path written (``.npy`` appended if missing)."""
    arr = np.asarray(values, dtype=np.float32)
    if arr.ndim != 3 or arr.shape[-1] != 4:
        raise UserInputError(f"a per-pixel map must have shape (Hs, Ws, 4), got {arr.shape}")
    out = Path(path)
    if out.suffix != ".npy":
        out = out.with_name(out.name + ".npy")
    np.save(out, arr, allow_pickle=False)
    return out


def load_pixel_map(path: str | Path, cam: CameraModel) -> NDArray[np.float64]:
    """Read a per-pixel map written by :func:`save_pixel_map` and check it fits ``cam``.

    Raises
    ------
    UserInputError
        Not a plain numeric .npy file, or a shape other than ``(*cam.superpixel_shape, 4)``.
    """
    try:
        arr = np.load(Path(path), allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise UserInputError(f"{path}: not a plain .npy per-pixel map ({exc})") from None
    if arr.shape != (*cam.superpixel_shape, 4) or not np.issubdtype(arr.dtype, np.floating):
        raise UserInputError(
            f"{path}: per-pixel map of shape {arr.shape} ({arr.dtype}); camera {cam.name!r} "
            f"needs float {(*cam.superpixel_shape, 4)}"
        )
    return np.asarray(arr, dtype=np.float64)
