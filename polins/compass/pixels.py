"""Pixels of a DoFP camera: the raw mosaic, its four polarizer channels, and pixel sets.

A raw image is the full-resolution mosaic ``(H, W)`` (docs/conventions.md); superpixel
(i, j) covers rows 2i..2i+1 and columns 2j..2j+1, and the camera model's ``channel_at``
says which polarizer channel sits at each mosaic position. Channel arrays are ordered by
the camera model's nominal labels (0, 45, 90, 135 deg for the IMX250MZR).

A :class:`PixelSet` is a fixed set of superpixels (by default the field of view) with the
indices the fast pipeline needs: one gather fetches two channels, and intensity gradients
use shifts instead of gathers where the set's row-major order allows it.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from polins.compass.camera import roi_mask
from polins.models import CameraModel

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
IntArray = NDArray[np.intp]

__all__ = ["PixelSet", "check_raw", "gather_channels", "mosaic_channels", "pixel_set"]


def check_raw(raw: ArrayLike, cam: CameraModel) -> NDArray:
    """Validate a raw mosaic: shape ``cam.shape`` and an unsigned-integer or float dtype.

    Float mosaics (e.g. simulated, or dark-corrected by the user) are accepted; their
    non-finite pixels are masked downstream, never propagated.

    Raises
    ------
    ValueError
        Wrong shape or dtype; the message names the expected shape.
    """
    arr = np.asarray(raw)
    if arr.shape != cam.shape:
        raise ValueError(
            f"raw mosaic has shape {arr.shape}; camera {cam.name!r} expects the full-resolution "
            f"mosaic of shape {cam.shape} (H, W), unsigned integer (e.g. uint16)"
        )
    if not (np.issubdtype(arr.dtype, np.unsignedinteger) or np.issubdtype(arr.dtype, np.floating)):
        raise ValueError(
            f"raw mosaic has dtype {arr.dtype}; expected an unsigned integer (e.g. uint16) or a "
            f"float mosaic of shape {cam.shape}"
        )
    return arr


def mosaic_channels(raw: ArrayLike, cam: CameraModel) -> FloatArray:
    """Split a raw mosaic into its four polarizer channels, ``(Hs, Ws, 4)`` [DN].

    Channel ``k`` (ordered by ``cam.nominal_angle_deg``) of superpixel (i, j) is the raw pixel
    at row ``2i + r``, column ``2j + c`` with ``cam.channel_at[r, c] == k``.
    """
    arr = check_raw(raw, cam)
    hs, ws = cam.superpixel_shape
    out = np.empty((hs, ws, 4))
    for r in range(2):
        for c in range(2):
            out[..., cam.channel_at[r, c]] = arr[r::2, c::2]
    return out


@dataclass(frozen=True, eq=False)
class PixelSet:
    """A fixed set of superpixels of one camera, with the indices the fast pipeline needs.

    Attributes
    ----------
    shape : tuple of int
        Superpixel image shape ``(Hs, Ws)``.
    index : (n,) int
        Flat superpixel index ``i * Ws + j``, increasing.
    pair_index : (2, n) int
        Index of the two horizontally adjacent raw pixels of mosaic row r (0, 1) of every
        superpixel, in the raw image viewed as pixel pairs (one gather fetches two channels).
    channel_at : (2, 2) int
        Channel index at mosaic position (row % 2, col % 2), from the camera model.
    right_step : (n - 1,) float32
        1 where position k + 1 is the right neighbour of position k, else 0.
    horizontal_scale : (n,) float32
        1 / (number of horizontal neighbours in the set; 2 for a central difference), 0 if
        none.
    vertical : (n,) int
        Position of the lower neighbour, else of the upper one, else of the pixel itself.
    vertical_step : (n,) float32
        +1 (lower neighbour), -1 (upper) or 0 (none): the one-sided vertical difference is
        ``(s0[vertical] - s0) * vertical_step``.
    runs : (m + 1, 3) int
        The set as runs of horizontally adjacent superpixels: superpixel row, first column
        and first position of every run; a last row ``(0, 0, n)`` closes the final run (the
        compiled passes stream the mosaic rows run by run).
    vertical_runs : (m,) int
        Per run, the position of its first pixel's ``vertical`` neighbour when the run's
        ``vertical`` positions are consecutive (the neighbours are a run themselves: read
        without a gather), else -1.
    """

    shape: tuple[int, int]
    index: IntArray
    pair_index: IntArray
    channel_at: IntArray
    right_step: NDArray[np.float32]
    horizontal_scale: NDArray[np.float32]
    vertical: IntArray
    vertical_step: NDArray[np.float32]
    runs: IntArray
    vertical_runs: IntArray

    @property
    def size(self) -> int:
        """Number of superpixels in the set."""
        return int(self.index.size)

    def to_image(self, values: ArrayLike, fill: float = np.nan) -> FloatArray:
        """Scatter per-pixel ``values`` ``(n, ...)`` into a superpixel image ``(Hs, Ws, ...)``."""
        vals = np.asarray(values)
        out = np.full((self.shape[0] * self.shape[1], *vals.shape[1:]), fill, dtype=float)
        out[self.index] = vals
        return out.reshape(*self.shape, *vals.shape[1:])


def _build_pixel_set(cam: CameraModel, mask: BoolArray) -> PixelSet:
    hs, ws = cam.superpixel_shape
    if mask.shape != (hs, ws):
        raise ValueError(f"pixel mask has shape {mask.shape}, expected {(hs, ws)}")
    index = np.flatnonzero(mask)
    i, j = np.divmod(index, ws)
    pair_index = np.stack([(2 * i + r) * ws + j for r in range(2)]).astype(np.intp)
    channel_at = np.array(cam.channel_at, dtype=np.intp)
    position = np.full(hs * ws, -1, dtype=np.intp)
    position[index] = np.arange(index.size)
    own = np.arange(index.size)

    def neighbour(di: int, dj: int) -> IntArray:
        ni, nj = i + di, j + dj
        inside = (ni >= 0) & (ni < hs) & (nj >= 0) & (nj < ws)
        return np.where(inside, position[np.clip(ni, 0, hs - 1) * ws + np.clip(nj, 0, ws - 1)], -1)

    right, left, down, up = neighbour(0, 1), neighbour(0, -1), neighbour(1, 0), neighbour(-1, 0)
    right_step = (right[:-1] == own[:-1] + 1).astype(np.float32)
    count = (right >= 0).astype(np.float32) + (left >= 0)
    horizontal_scale = np.where(count > 0, 1.0 / np.maximum(count, 1), 0.0).astype(np.float32)
    vertical = np.where(down >= 0, down, np.where(up >= 0, up, own))
    vertical_step = np.where(down >= 0, 1.0, np.where(up >= 0, -1.0, 0.0)).astype(np.float32)
    start = np.flatnonzero(np.r_[index.size > 0, (index[1:] != index[:-1] + 1) | (j[1:] == 0)])
    runs = np.stack([i[start], j[start], start], -1)
    runs = np.vstack([runs, [0, 0, index.size]]).astype(np.intp)
    arrays = (index, pair_index, channel_at, right_step, horizontal_scale, vertical, vertical_step,
              runs, _vertical_runs(vertical, runs[:, 2]))  # fmt: skip
    for arr in arrays:
        arr.setflags(write=False)
    return PixelSet((hs, ws), *arrays)


def _vertical_runs(vertical: IntArray, bounds: IntArray) -> IntArray:
    """:attr:`PixelSet.vertical_runs` of the runs between ``bounds (m + 1,)``."""
    consecutive = np.r_[np.diff(vertical) == 1, True]  # position q: q + 1 follows it
    out = np.full(bounds.size - 1, -1, dtype=np.intp)
    for k in range(bounds.size - 1):
        p0, p1 = int(bounds[k]), int(bounds[k + 1])
        if p1 > p0 and consecutive[p0 : p1 - 1].all():
            out[k] = vertical[p0]
    return out


@lru_cache(maxsize=8)
def _fov_pixel_set(cam: CameraModel) -> PixelSet:
    return _build_pixel_set(cam, np.asarray(roi_mask(cam)))


def pixel_set(cam: CameraModel, mask: ArrayLike | None = None) -> PixelSet:
    """The superpixels of ``mask`` (default: the camera's field of view, static occlusion
    mask and region of interest, :func:`polins.compass.camera.roi_mask`, cached per
    camera)."""
    if mask is None:
        return _fov_pixel_set(cam)
    return _build_pixel_set(cam, np.asarray(mask, dtype=bool))


def gather_channels(raw: NDArray, pixels: PixelSet, dtype: type = np.float64) -> NDArray:
    """Channel intensities ``(4, n)`` [DN] of the set's superpixels, component-first, in
    ``dtype``.

    The raw image is viewed as pairs of horizontally adjacent pixels, so two gathers (one
    per mosaic row) fetch all four channels.
    """
    arr = np.ascontiguousarray(raw)
    pairs = arr.view(np.dtype((np.void, 2 * arr.itemsize))).reshape(-1)
    fetched = pairs.take(pixels.pair_index).view(arr.dtype).reshape(2, -1, 2)
    out: NDArray = np.empty((4, pixels.size), dtype=dtype)
    for r in range(2):
        for c in range(2):
            out[pixels.channel_at[r, c]] = fetched[r, :, c]
    return out
