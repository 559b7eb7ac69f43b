"""Per-pixel calibration map files: gain, transmission-angle and efficiency maps as .npy without pickle.

A map is a float array ``(Hs, Ws, 4)``: one value per superpixel and polarizer channel,
channels in the camera model's order, angles in radians; NaN means "use the channel's
value" (docs/calibrate.md#per-pixel-maps). Maps are written with
``numpy.save(..., allow_pickle=False)`` (float32) and read back with
``numpy.load(..., allow_pickle=False)``, so a map file can never execute code. The camera
loader (:mod:`polins.models.camera`) and the calibration (:mod:`polins.calibration.maps`)
both use these two functions.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from polins.models.schema import ModelFileError

__all__ = ["load_pixel_map", "save_pixel_map"]


def save_pixel_map(path: str | Path, values: ArrayLike) -> Path:
    """Write a per-pixel map ``(Hs, Ws, 4)`` as a float32 ``.npy`` file (no pickle); returns
    the path written (``.npy`` appended if missing).

    Raises
    ------
    ModelFileError
        Not an ``(Hs, Ws, 4)`` array.
    """
    arr = np.asarray(values, dtype=np.float32)
    if arr.ndim != 3 or arr.shape[-1] != 4:
        raise ModelFileError(f"a per-pixel map must have shape (Hs, Ws, 4), got {arr.shape}")
    out = Path(path)
    if out.suffix != ".npy":
        out = out.with_name(out.name + ".npy")
    out.parent.mkdir(parents=True, exist_ok=True)
    np.save(out, arr, allow_pickle=False)
    return out


def load_pixel_map(
    path: str | Path, superpixel_shape: tuple[int, int], *, what: str = "per-pixel map"
) -> NDArray[np.float64]:
    """Read a per-pixel map written by :func:`save_pixel_map` and check its shape.

    Parameters
    ----------
    path : str or Path
        The ``.npy`` file.
    superpixel_shape : (int, int)
        The camera's superpixel image shape ``(Hs, Ws)``.
    what : str
        What the map is, for messages (e.g. the camera file and key that name it).

    Raises
    ------
    ModelFileError
        Missing, not a plain numeric ``.npy`` file, or a shape other than
        ``(*superpixel_shape, 4)``.
    """
    try:
        arr = np.load(Path(path), allow_pickle=False)
    except FileNotFoundError:
        raise ModelFileError(f"{what}: map file not found: {path}") from None
    except (OSError, ValueError) as exc:
        raise ModelFileError(f"{what}: {path} is not a plain .npy per-pixel map ({exc})") from None
    if not isinstance(arr, np.ndarray):  # an .npz archive
        arr.close()
        raise ModelFileError(f"{what}: {path} is an .npz archive, not one .npy per-pixel map")
    expected = (*superpixel_shape, 4)
    if arr.shape != expected or not np.issubdtype(arr.dtype, np.floating):
        raise ModelFileError(
            f"{what}: {path} holds a per-pixel map of shape {arr.shape} ({arr.dtype}); the "
            f"camera needs float {expected} (superpixel rows, columns, 4 channels)"
        )
    return np.asarray(arr, dtype=np.float64)
