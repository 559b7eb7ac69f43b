"""Raw polarization images on disk: 16-bit PNG/TIFF mosaics and their timestamp index.

An image is the full-resolution DoFP mosaic exactly as the camera delivered it: one channel,
unsigned 8- or 16-bit, shape ``(H, W)`` = ``cam.shape`` (docs/conventions.md). Two ways to give the
times of a folder of images:

* an index CSV with columns ``t, file`` (``file`` relative to the CSV's folder), e.g.
  ``images.csv``::

      t,file
      0.0,images/000000.png
      0.2,images/000001.png

* or the time in each file name: the stem ends with a number followed by its unit
  ``s``, ``ms``, ``us`` or ``ns``, optionally after a prefix ending in ``_`` or ``-``:
  ``000012.250000s.png``, ``cam_12250ms.tiff``, ``img-1693897560123456789ns.png``. The time is
  on the log's clock (seconds after the manifest's ``epoch_utc``). Other files are ignored;
  the unit suffix is required so that frame counters (``000001.png``) are never read as times.

A file that cannot be decoded, is not single-channel, or not unsigned integer raises
:class:`ImageReadError` (the navigation loop skips and reports it; it never aborts a run).
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass
from decimal import Decimal
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd
from numpy.typing import NDArray

from polins.errors import UserInputError
from polins.io.atomic import atomic_path
from polins.io.tables import read_table, write_table

IMAGE_SUFFIXES = (".png", ".tif", ".tiff")
TIME_IN_NAME = re.compile(r"^(?:.*[_-])?(?P<t>[0-9]+(?:\.[0-9]*)?)(?P<unit>s|ms|us|ns)$")
_UNIT_S = {"s": Decimal(1), "ms": Decimal("1e-3"), "us": Decimal("1e-6"), "ns": Decimal("1e-9")}


class ImageReadError(UserInputError):
    """An image file or message that cannot be used as a raw mosaic."""


def write_image(path: str | Path, raw: NDArray[np.unsignedinteger]) -> Path:
    """Write a raw mosaic losslessly as PNG or TIFF (by suffix), atomically.

    Parameters
    ----------
    path : str or Path
        ``.png``, ``.tif`` or ``.tiff``.
    raw : ndarray
        ``(H, W)`` uint8 or uint16 mosaic.
    """
    path = Path(path)
    if path.suffix.lower() not in IMAGE_SUFFIXES:
        raise UserInputError(f"{path}: image suffix must be one of {IMAGE_SUFFIXES}")
    raw = np.asarray(raw)
    if raw.ndim != 2 or raw.dtype not in (np.uint8, np.uint16):
        raise UserInputError(
            f"raw image must be a 2-D uint8 or uint16 mosaic, got shape {raw.shape} {raw.dtype}"
        )
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(raw)):
            raise OSError(f"OpenCV could not write {path}")
    return path


def decode_image(
    raw: NDArray | None, source: str, shape: tuple[int, int] | None = None
) -> NDArray[np.unsignedinteger]:
    """Check a decoded array is a usable mosaic; ``ImageReadError`` naming ``source`` if not."""
    if raw is None:
        raise ImageReadError(f"{source}: cannot decode image (missing, truncated or not an image)")
    if raw.ndim != 2:
        raise ImageReadError(
            f"{source}: expected a single-channel raw mosaic, got shape {raw.shape}"
        )
    if raw.dtype not in (np.uint8, np.uint16):
        raise ImageReadError(f"{source}: expected uint8 or uint16 pixels, got {raw.dtype}")
    if shape is not None and raw.shape != tuple(shape):
        raise ImageReadError(
            f"{source}: image shape {raw.shape} does not match the camera model {tuple(shape)}"
        )
    return raw


def bit_depth_warning(raw: NDArray[np.unsignedinteger], bit_depth: int, source: str) -> str | None:
    """A warning if ``raw`` holds values above the camera's ``2**bit_depth - 1``, else None.

    Such an image would be counted as saturated everywhere; the warning names the likely
    cause, a ``bit_depth``-bit image stored shifted left into 16 bits (12-bit x16).
    """
    top = int(np.max(raw)) if raw.size else 0
    limit = 2**bit_depth - 1
    if top <= limit:
        return None
    low_bits = int(np.bitwise_or.reduce(raw, axis=None))
    shift = (low_bits & -low_bits).bit_length() - 1 if low_bits else 0
    cause = (
        f"the image looks stored shifted left by {shift} bits (x{2**shift}): divide it by "
        f"{2**shift} (raw >> {shift})"
        if shift > 0
        else "the camera model's sensor.bit_depth may be wrong"
    )
    return (
        f"{source}: values up to {top} exceed the camera's {bit_depth}-bit range (max {limit}); "
        f"{cause}, or fix sensor.bit_depth"
    )


def read_image(
    path: str | Path, *, shape: tuple[int, int] | None = None
) -> NDArray[np.unsignedinteger]:
    """Read a raw mosaic (PNG/TIFF, unchanged bit depth).

    Raises
    ------
    ImageReadError
        Unreadable, truncated, multi-channel, non-integer, or (with ``shape``) wrong size.
    """
    path = Path(path)
    if not path.is_file():
        raise ImageReadError(f"{path}: image file not found")
    try:
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:  # pragma: no cover - OpenCV usually returns None instead
        raise ImageReadError(f"{path}: {exc}") from None
    return decode_image(raw, str(path), shape)


def load_raw(item: Any, *, shape: tuple[int, int] | None = None) -> NDArray[np.unsignedinteger]:
    """Load one image item of an image source: a path, an array, or a bag message.

    Items are what iterating a log's ``images`` yields (``ImageIndex``: paths;
    ``BagImages``: :class:`polins.io.rosbag.ImageMessage`). Picklable, so worker
    processes can decode images themselves. Raises :class:`ImageReadError`.
    """
    if isinstance(item, str | Path):
        return read_image(item, shape=shape)
    if isinstance(item, np.ndarray):
        return decode_image(item, "image array", shape)
    to_array = getattr(item, "to_array", None)
    if to_array is None:
        raise ImageReadError(f"cannot load an image from a {type(item).__name__}")
    return to_array(shape)


def time_from_name(name: str) -> float | None:
    """Time [s] encoded at the end of a file stem (see module docstring), or None."""
    match = TIME_IN_NAME.match(Path(name).stem)
    if match is None:
        return None
    return float(Decimal(match.group("t")) * _UNIT_S[match.group("unit")])


@dataclass(frozen=True)
class ImageIndex:
    """Times and files of a folder of raw images, in the order given.

    Attributes
    ----------
    t : ndarray
        ``(N,)`` image times [s] on the log's clock.
    files : tuple of Path
        ``N`` image paths (absolute or relative to the working folder).
    """

    t: NDArray[np.float64]
    files: tuple[Path, ...]

    def __len__(self) -> int:
        return len(self.files)

    def __iter__(self) -> Iterator[tuple[float, Path]]:
        """Yield ``(t, path)``; the image is read later (possibly in a worker process)."""
        return zip(self.t.tolist(), self.files, strict=True)

    def read(self, i: int, *, shape: tuple[int, int] | None = None) -> NDArray[np.unsignedinteger]:
        """Read image ``i`` (``ImageReadError`` if unusable)."""
        return read_image(self.files[i], shape=shape)


def read_image_index(path: str | Path) -> ImageIndex:
    """Image index from an index CSV (``t, file``) or from a folder of time-named files.

    Raises
    ------
    ValueError
        Missing columns, non-finite times, or a folder without time-named images.
    """
    path = Path(path)
    if path.is_dir():
        found = []
        for f in sorted(path.iterdir()):
            if (
                f.suffix.lower() in IMAGE_SUFFIXES
                and (t_name := time_from_name(f.name)) is not None
            ):
                found.append((t_name, f))
        if not found:
            raise UserInputError(
                f"{path}: no image named with its time (e.g. '000012.250000s.png' or "
                "'img_12250ms.tiff'); or give an index CSV with columns t, file"
            )
        found.sort(key=lambda item: item[0])
        return ImageIndex(
            t=np.array([t for t, _ in found], dtype=float), files=tuple(f for _, f in found)
        )
    df = read_table(path)
    missing = [c for c in ("t", "file") if c not in df.columns]
    if missing:
        raise UserInputError(f"{path}: image index lacks column(s) {missing}; expected t, file")
    t = pd.to_numeric(df["t"], errors="coerce").to_numpy(dtype=float)
    if not np.all(np.isfinite(t)):
        row = int(np.flatnonzero(~np.isfinite(t))[0])
        raise UserInputError(f"{path}: row {row}: image time {df['t'].iloc[row]!r} is not a number")
    files = tuple(path.parent / str(f) for f in df["file"])
    return ImageIndex(t=t, files=files)


def write_image_index(path: str | Path, t: NDArray[np.float64], files: list[str]) -> Path:
    """Write an index CSV (``t, file``; ``file`` relative to the CSV's folder), atomically."""
    return write_table(path, pd.DataFrame({"t": np.asarray(t, dtype=float), "file": files}))


__all__ = [
    "IMAGE_SUFFIXES",
    "ImageIndex",
    "ImageReadError",
    "bit_depth_warning",
    "decode_image",
    "load_raw",
    "read_image",
    "read_image_index",
    "time_from_name",
    "write_image",
    "write_image_index",
]
