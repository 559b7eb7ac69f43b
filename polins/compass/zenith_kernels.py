"""Compiled passes of the zenith angle of polarization: the cone's sums and the mirror-pair groups.

The sums of :func:`polins.compass.zenith.zenith_mean` over the cone about the level zenith
and the per-group sums of its mirror-pair jackknife, each one branch-light loop over the
field-of-view pixels. Compiled by :func:`polins.compass.kernels.compiled`
(docs/measurement.md §13; tests/test_kernels.py).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

ZENITH_SUMS = 13
"""Length of :func:`zenith_pass`'s sums."""


def zenith_terms(  # pragma: no cover - compiled by numba, which coverage cannot trace
    basis: NDArray, i: int, mat_lc: NDArray, w: float, s1: float, s2: float
) -> tuple[float, float, float, float, float, float]:
    """The doubled level-frame rows ``(q1x, q1y, q2x, q2y)`` of pixel ``i`` of the inverse
    basis ``basis`` (``(3, 2, n)``, or its third row ``(2, n)`` for the projection lens model,
    whose first two rows are the identity) turned by ``mat_lc``, and its contribution
    ``w (S1 q1 + S2 q2)`` (2) to the zenith cone's sum (:func:`zenith_pass`)."""
    if basis.ndim == 2:
        b00, b01, b10, b11 = 1.0, 0.0, 0.0, 1.0
        b20, b21 = np.float64(basis[0, i]), np.float64(basis[1, i])
    else:
        b00, b01 = np.float64(basis[0, 0, i]), np.float64(basis[0, 1, i])
        b10, b11 = np.float64(basis[1, 0, i]), np.float64(basis[1, 1, i])
        b20, b21 = np.float64(basis[2, 0, i]), np.float64(basis[2, 1, i])
    h1x = mat_lc[0, 0] * b00 + mat_lc[0, 1] * b10 + mat_lc[0, 2] * b20
    h1y = mat_lc[1, 0] * b00 + mat_lc[1, 1] * b10 + mat_lc[1, 2] * b20
    h2x = mat_lc[0, 0] * b01 + mat_lc[0, 1] * b11 + mat_lc[0, 2] * b21
    h2y = mat_lc[1, 0] * b01 + mat_lc[1, 1] * b11 + mat_lc[1, 2] * b21
    inv_norm = 2.0 / (h1x * h1x + h1y * h1y + h2x * h2x + h2y * h2y)  # one division
    q1x = 0.5 * (h1x * h1x - h1y * h1y - h2x * h2x + h2y * h2y) * inv_norm
    q1y = (h1x * h1y - h2x * h2y) * inv_norm
    q2x = (h1x * h2x - h1y * h2y) * inv_norm
    q2y = (h1x * h2y + h2x * h1y) * inv_norm
    return q1x, q1y, q2x, q2y, w * (q1x * s1 + q2x * s2), w * (q1y * s1 + q2y * s2)


def zenith_pass(  # pragma: no cover - compiled by numba, which coverage cannot trace
    est: NDArray, inv: NDArray, basis: NDArray, rays: NDArray, valid: NDArray,
    mat_lc: NDArray, cos_edge: float, mask: NDArray, sums: NDArray, contrib: NDArray,
) -> None:  # fmt: skip
    """The zenith cone's sums in one pass over the field-of-view pixels
    (:func:`polins.compass.zenith.zenith_mean`, docs/measurement.md §13), in float64.

    A pixel is used when ``valid`` and its ray's level zenith cosine exceeds ``cos_edge``
    (``mask`` out). Per used pixel, with ``w = inv`` (``(n,)``, or ``(1, 1)`` for one
    value) and the doubled rows ``q1, q2`` of its basis turned by ``mat_lc`` (camera ->
    level; :func:`zenith_terms`): ``sums`` (13,) holds ``sum c`` (2) of the contributions
    ``c = w (S1 q1 + S2 q2)`` (written to ``contrib (2, n)``, 0 for the pixels not used),
    ``sum w (q1 q1^T + q2 q2^T)`` (xx, xy, yy) and the four sums ``sum w (q1 d1 + q2 d2)``
    (2 each) of the camera-fixed perturbations ``(d1, d2)`` = ``(S0, 0), (0, S0), (S1,
    -S2), (S2, S1)``. Branch-free (a pixel not used has weight 0; its data are finite): the
    loop runs in vector lanes."""
    l20, l21, l22 = mat_lc[2, 0], mat_lc[2, 1], mat_lc[2, 2]
    a0 = a1 = a2 = a3 = a4 = a5 = a6 = a7 = a8 = a9 = a10 = a11 = a12 = 0.0
    w = 0.0 if inv.ndim == 1 else np.float64(inv[0, 0])
    for i in range(valid.size):
        ok = valid[i] & (l20 * rays[0, i] + l21 * rays[1, i] + l22 * rays[2, i] > cos_edge)
        mask[i] = ok
        if inv.ndim == 1:
            w = np.float64(inv[i])
        w_ok = w * ok
        s0, s1, s2 = np.float64(est[0, i]), np.float64(est[1, i]), np.float64(est[2, i])
        q1x, q1y, q2x, q2y, cx, cy = zenith_terms(basis, i, mat_lc, w_ok, s1, s2)
        contrib[0, i], contrib[1, i] = cx, cy
        a0 += cx
        a1 += cy
        a2 += w_ok * (q1x * q1x + q2x * q2x)
        a3 += w_ok * (q1x * q1y + q2x * q2y)
        a4 += w_ok * (q1y * q1y + q2y * q2y)
        ws0 = w_ok * s0
        a5 += q1x * ws0
        a6 += q1y * ws0
        a7 += q2x * ws0
        a8 += q2y * ws0
        a9 += w_ok * (q1x * s1 - q2x * s2)
        a10 += w_ok * (q1y * s1 - q2y * s2)
        a11 += w_ok * (q1x * s2 + q2x * s1)
        a12 += w_ok * (q1y * s2 + q2y * s1)
    sums[0], sums[1], sums[2], sums[3], sums[4] = a0, a1, a2, a3, a4
    sums[5], sums[6], sums[7], sums[8] = a5, a6, a7, a8
    sums[9], sums[10], sums[11], sums[12] = a9, a10, a11, a12


def mirror_pass(  # pragma: no cover - compiled by numba, which coverage cannot trace
    contrib: NDArray, rays: NDArray, mask: NDArray, mat_lc: NDArray, azimuth: NDArray,
    bounds: NDArray, out: NDArray,
) -> None:  # fmt: skip
    """Per-group sums of the mirror-pair jackknife (:func:`polins.compass.zenith.zenith_mean`)
    over the pixels of ``mask`` (``contrib (2, n)`` the contributions :func:`zenith_pass`
    wrote, ``rays``, ``mat_lc`` its), in pixel order: ``out (3, G)`` += (``sum c`` (2),
    pixel count) of group ``g``, the number of boundaries ``bounds (2, G - 1)`` = (cos b_j,
    sin b_j) (ascending angles b_j in ``(0, pi)``) that the angle between the pixel's
    horizontal level ray and the sun's azimuth ``azimuth`` = (cos A, sin A) reaches (no
    trigonometry: a sign of a cross product)."""
    c, s = azimuth[0], azimuth[1]
    l00, l01, l02 = mat_lc[0, 0], mat_lc[0, 1], mat_lc[0, 2]
    l10, l11, l12 = mat_lc[1, 0], mat_lc[1, 1], mat_lc[1, 2]
    n_bounds = bounds.shape[1]
    for i in range(mask.size):
        if not mask[i]:
            continue
        rx, ry, rz = rays[0, i], rays[1, i], rays[2, i]
        hx = l00 * rx + l01 * ry + l02 * rz
        hy = l10 * rx + l11 * ry + l12 * rz
        x = c * hx + s * hy
        y = abs(c * hy - s * hx)
        g = 0
        for j in range(n_bounds):
            g += y * bounds[0, j] - x * bounds[1, j] >= 0.0
        out[0, g] += contrib[0, i]
        out[1, g] += contrib[1, i]
        out[2, g] += 1.0
