"""Pixel selection: which pixels enter the estimate, decided along the predicted AoP.

The final selection of the per-image chain (docs/measurement.md §4) keeps a pixel when it
is valid (:func:`polins.compass.polarimetry.validity_rows`), outside the sun circle, and
its polarized intensity *along the predicted direction* clears both a DoP and a noise
threshold. That component's noise is independent of the residual's, so the cut selects no
noise (a cut on |L| would, and bias epsilon near the sun). On the chain's arrays (one dtype)
the rule runs as one compiled pass, :func:`polins.compass.selection_kernels.select_pass`, with the
numbers of the numpy expressions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from polins.compass.kernels import compiled, dot_rows
from polins.compass.prediction import PixelData, doubled_prediction, image_plane_evector

__all__ = ["Selection", "compiled_arguments", "select_pixels", "selection_mask"]


@dataclass(frozen=True)
class Selection:
    """The selection rule, applied inside the full-set evaluation (it shares the predicted
    AoP).

    Attributes
    ----------
    valid : (n,) bool
        All criteria that do not depend on the sun.
    rays : (3, n)
        Camera rays.
    cos_exclusion : float
        Cosine of the sun-exclusion radius.
    dop_min : float
        Minimum DoP along the predicted direction.
    p_min : (n,) or float
        Minimum polarized intensity along it [DN] (``SNR_MIN sigma_L``).
    """

    valid: NDArray
    rays: NDArray
    cos_exclusion: float
    dop_min: float
    p_min: NDArray | float = 0.0


def select_pixels(
    data: PixelData, select: Selection, sun_c: NDArray, n1: NDArray, n2: NDArray, e2: NDArray
) -> NDArray:
    """Mask ``(n,)`` of the selected pixels for the camera-frame sun ``sun_c`` whose
    :func:`polins.compass.prediction.doubled_prediction` is ``(n1, n2, e2)``."""
    compiled_args = compiled_arguments(data, select, sun_c, (n1, n2, e2))
    if compiled_args is not None:
        # One compiled pass, the same numbers as the numpy expressions below.
        mask = np.empty(data.s0.shape, dtype=bool)
        compiled("select_pass")(data.s0, data.s1, data.s2, n1, n2, e2, *compiled_args, mask)
        return mask
    along = n1 * data.s1
    along += n2 * data.s2
    mask = along >= (select.dop_min * e2) * data.s0
    if np.any(select.p_min):
        mask &= along >= e2 * select.p_min
    mask &= select.valid
    mask &= dot_rows(sun_c.astype(data.s0.dtype), select.rays) <= select.cos_exclusion
    return mask


def compiled_arguments(
    data: PixelData, select: Selection, sun_c: NDArray, more: tuple[NDArray, ...]
) -> tuple[NDArray, ...] | None:
    """``(valid, rays, sun_c, p_min, limits)`` for the compiled passes, in the rows' dtype,
    or None when the arrays do not share it (the numpy expressions then run)."""
    dt = data.s0.dtype
    p_min = np.asarray(select.p_min)
    arrays = (data.s1, data.s2, select.rays, *more) + ((p_min,) if p_min.ndim else ())
    if not all(a.dtype == dt for a in arrays) or select.valid.dtype != np.bool_:
        return None
    p_min = p_min.astype(dt).reshape(-1) if np.any(p_min) else np.zeros(0, dt)
    limits = np.array([select.dop_min, select.cos_exclusion, 1e-30], dtype=dt)
    return select.valid, select.rays, np.asarray(sun_c, dtype=float).astype(dt), p_min, limits


def selection_mask(data: PixelData, select: Selection, sun_c: NDArray) -> NDArray:
    """:func:`select_pixels` for a given camera-frame sun ``(3,)`` (no residuals)."""
    n = data.s0.size
    if data.rays is not None:  # the projection lens model: one compiled pass
        compiled_args = compiled_arguments(data, select, sun_c, (data.rays,))
        if compiled_args is not None:
            mask = np.empty(n, dtype=bool)
            compiled("predicted_select_pass")(data.s0, data.s1, data.s2, data.rays,
                                              *compiled_args, mask)  # fmt: skip
            return mask
    xy = image_plane_evector(data, np.asarray(sun_c, dtype=float)[:, None])
    n1, n2, e2 = doubled_prediction(xy[0, :n], xy[0, n:])
    return select_pixels(data, select, sun_c, n1, n2, e2)
