"""Predicted AoP: the pixel data of the joint ML and the Rayleigh angle a trial sun predicts there.

For a trial camera-frame sun ``s``, the Rayleigh E-vector ``s x p`` of pixel ray ``p``
appears in the image plane along ``(x, y) = (q1 . s, q2 . s)`` (the lens forward rows of
:mod:`polins.compass.lens`), linear in ``s``. The predicted doubled AoP is then
``E^2 (cos 2zeta_R, sin 2zeta_R) = (x^2 - y^2, 2xy)`` without trigonometry
(docs/measurement.md §2-3). :class:`PixelData` holds the component-first Stokes rows and
lens constants these predictions are evaluated on.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from polins.compass.lens import pack_forward

__all__ = ["PixelData", "doubled_prediction", "image_plane_evector", "pixel_data"]


@dataclass(frozen=True)
class PixelData:
    """Component-first pixel data of the joint ML (one dtype, n pixels).

    The lens enters as ``rays`` (3, n) for the projection model (P), whose forward rows
    ``q1 = p x (1, 0, 0)``, ``q2 = p x (0, 1, 0)`` need no storage, or as packed forward rows
    ``forward`` (3, 2n) = [q1 | q2] for any model. ``mask`` (optional) marks the pixels that
    count: the others are evaluated and zeroed, cheaper than compressing the arrays when
    nearly all pixels are valid; their data must be finite.

    Attributes
    ----------
    s0, s1, s2 : (n,)
        Stokes rows [DN].
    forward : (3, 2n) or None
        Packed forward rows [q1 | q2].
    rays : (3, n) or None
        Camera rays (projection model only).
    inv_sigma : (n,) or float
        ``1/sigma_L`` [1/DN] per pixel, or one value.
    mask : (n,) bool or None
        Pixels that count.
    """

    s0: NDArray
    s1: NDArray
    s2: NDArray
    forward: NDArray | None
    rays: NDArray | None
    inv_sigma: NDArray | float
    mask: NDArray | None = None
    derived: dict[str, NDArray] = field(default_factory=dict, repr=False, compare=False)
    """Rows computed from the others on first use, shared by the copies with another mask."""

    @property
    def c(self) -> NDArray:
        """``S0^2 - |L|^2`` ``(n,)`` [DN^2] (the joint ML's unpolarized intensity), computed
        on first use."""
        if "c" not in self.derived:
            c = self.s0 * self.s0
            c -= self.s1 * self.s1
            c -= self.s2 * self.s2
            self.derived["c"] = c
        return self.derived["c"]

    @property
    def n(self) -> int:
        """Pixels that count."""
        return int(self.s0.size) if self.mask is None else int(np.count_nonzero(self.mask))

    def sigma_scaled(self, r: NDArray) -> NDArray:
        """Residuals ``r`` ``(n,)`` divided by a common sigma_L (a per-pixel sigma_L is
        applied by the evaluation itself)."""
        return r if isinstance(self.inv_sigma, np.ndarray) else r * r.dtype.type(self.inv_sigma)


def pixel_data(
    s0: NDArray,
    s1: NDArray,
    s2: NDArray,
    forward: NDArray | None,
    inv_sigma: NDArray | float,
    mask: NDArray | None = None,
    packed: bool = False,
    rays: NDArray | None = None,
) -> PixelData:
    """:class:`PixelData` of Stokes rows ``(n,)``; ``forward``: (2, 3, n) forward rows, or
    already packed (3, 2n) with ``packed``; or None with ``rays`` (3, n) for the projection
    lens model."""
    fwd = forward if (packed or forward is None) else pack_forward(forward, s0.dtype)
    if fwd is None and rays is None:
        raise ValueError("need the forward lens rows or (projection model) the rays")
    return PixelData(s0, s1, s2, fwd, rays, inv_sigma, mask)


def image_plane_evector(data: PixelData, sun_cols: NDArray) -> NDArray:
    """``(x, y)`` of ``s x p`` in the image plane for each column of ``sun_cols`` (3, k):
    returns (k, 2n) rows [x | y]."""
    dt = data.s0.dtype
    cols = sun_cols.astype(dt)
    if data.rays is None:
        assert data.forward is not None
        return np.einsum("ik,in->kn", cols, data.forward)
    px, py, pz = data.rays
    n = px.size
    out = np.empty((cols.shape[1], 2 * n), dtype=dt)
    for j in range(cols.shape[1]):
        sx, sy, sz = cols[:, j]
        x, y = out[j, :n], out[j, n:]
        np.multiply(pz, sy, out=x)  # x = (s x p)_x = s_y p_z - s_z p_y
        x -= sz * py
        np.multiply(px, sz, out=y)  # y = (s x p)_y = s_z p_x - s_x p_z
        y -= sx * pz
    return out


def doubled_prediction(x: NDArray, y: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """``E^2 (cos 2zeta_R, sin 2zeta_R)`` and ``E^2 = x^2 + y^2`` (+1e-30: the sun's own
    direction, always masked, must not give 0/0) of image-plane E-vectors (x, y); ``x`` and
    ``y`` are not modified."""
    xx, yy, xy0 = x * x, y * y, x * y
    e2 = xx + yy
    e2 += e2.dtype.type(1e-30)
    n1 = np.subtract(xx, yy, out=xx)
    n2 = np.add(xy0, xy0, out=xy0)
    return n1, n2, e2
