"""Compiled passes of the Stokes stage: raw mosaic -> Stokes rows, noise and validity, in one pass.

The integer-mosaic path of :func:`polins.compass.polarimetry.stokes_image` and the harmless
data of the invalid pixels (:func:`polins.compass.image.fill_invalid`), each one loop over
the field-of-view pixels that repeats the numpy expressions it replaces operation for
operation (bit-identical: tests/test_polarimetry.py, tests/test_kernels.py), and the
redundancy residual's sum of squares of the chain's noise estimate. Compiled by
:func:`polins.compass.kernels.compiled` (docs/measurement.md §10).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def stokes_pass(  # pragma: no cover  # noqa: C901, PLR0915 (one loop, compiled by numba)
    raw: NDArray,
    runs: NDArray,
    position: NDArray,
    matrix: NDArray,
    offset: NDArray,
    limits: NDArray,
    noise: NDArray,
    vertical: NDArray,
    rows: NDArray,
    sigma2: NDArray,
    valid: NDArray,
    unsaturated: NDArray,
    channels: NDArray,
) -> None:
    """Raw mosaic -> Stokes rows, channel noise variance and validity in one pass per pixel
    (:func:`polins.compass.polarimetry.stokes_image` for integer mosaics, float32 rows).

    ``raw (H, W)`` is the mosaic; ``runs (m + 1, 3)`` the pixel set's runs (superpixel
    row, first column, first position; a final row holds the set size); ``position (4,)``
    the mosaic position ``2 r + c`` of each channel; ``matrix (4, 4, 1)`` and ``offset
    (4, 1)`` float32 the Stokes rows (S0, S1, S2, nu) and their dark-offset part, or
    ``(4, 4, n)`` and ``(4, n)`` per pixel; ``limits`` = (saturation, s0_min,
    redundancy^2 [float32 when the noise is one number], dop_min^2, gradient_max^2 or -1);
    ``noise`` = (read^2, mean(g)/2, G_e, per-pixel flag); ``vertical (n,)`` the
    :class:`polins.compass.pixels.PixelSet`'s. ``sigma2`` is written only with the
    per-pixel flag, ``channels (4, n)`` float32 only when it is not empty.
    """
    f32 = np.float32
    zero = f32(0.0)
    sat, s0_min, dop2 = f32(limits[0]), f32(limits[1]), f32(limits[3])
    red2, grad2 = limits[2], limits[4]
    read2, gain_half, conversion_gain = noise[0], noise[1], noise[2]
    per_pixel = noise[3] != 0.0
    red2_read2 = f32(red2 * read2)  # a common sigma^2: numpy compares in float32
    # The matrix and offsets as scalars: the compiler cannot hoist them out of the loop
    # past the stores into ``rows``.
    per_pixel_rows = matrix.shape[2] > 1
    m = matrix
    m00, m01, m02, m03 = m[0, 0, 0], m[0, 1, 0], m[0, 2, 0], m[0, 3, 0]
    m10, m11, m12, m13 = m[1, 0, 0], m[1, 1, 0], m[1, 2, 0], m[1, 3, 0]
    m20, m21, m22, m23 = m[2, 0, 0], m[2, 1, 0], m[2, 2, 0], m[2, 3, 0]
    m30, m31, m32, m33 = m[3, 0, 0], m[3, 1, 0], m[3, 2, 0], m[3, 3, 0]
    o0, o1, o2, o3 = offset[0, 0], offset[1, 0], offset[2, 0], offset[3, 0]
    n_runs = runs.shape[0] - 1
    for k in range(n_runs):
        i2, p0, p1 = 2 * runs[k, 0], runs[k, 2], runs[k + 1, 2]
        col0 = 2 * runs[k, 1]
        ch_a = raw[i2 + position[0] // 2, col0 + position[0] % 2 :: 2]
        ch_b = raw[i2 + position[1] // 2, col0 + position[1] % 2 :: 2]
        ch_c = raw[i2 + position[2] // 2, col0 + position[2] % 2 :: 2]
        ch_d = raw[i2 + position[3] // 2, col0 + position[3] % 2 :: 2]
        r0, r1, r2, r3 = rows[0, p0:p1], rows[1, p0:p1], rows[2, p0:p1], rows[3, p0:p1]
        ok_run, unsat_run = valid[p0:p1], unsaturated[p0:p1]
        if channels.shape[1] > 0:
            for q in range(p1 - p0):
                channels[0, p0 + q] = f32(ch_a[q])
                channels[1, p0 + q] = f32(ch_b[q])
                channels[2, p0 + q] = f32(ch_c[q])
                channels[3, p0 + q] = f32(ch_d[q])
        # Two loops per run (a few kB, in cache): branch-free arithmetic the compiler
        # vectorises, then the tests.
        if per_pixel_rows:  # einsum("ikn,kn->in") order, then the offsets
            for i in range(4):
                ma, mb, mc = m[i, 0, p0:p1], m[i, 1, p0:p1], m[i, 2, p0:p1]
                md, oi, ri = m[i, 3, p0:p1], offset[i, p0:p1], rows[i, p0:p1]
                for q in range(p1 - p0):
                    a, b, c, d = f32(ch_a[q]), f32(ch_b[q]), f32(ch_c[q]), f32(ch_d[q])
                    ri[q] = (((zero + ma[q] * a) + mb[q] * b) + mc[q] * c) + md[q] * d - oi[q]
        for q in range(0 if per_pixel_rows else p1 - p0):
            a, b, c, d = f32(ch_a[q]), f32(ch_b[q]), f32(ch_c[q]), f32(ch_d[q])
            # einsum's order: ((m0 a + m1 b) + m2 c) + m3 d, then the offset
            r0[q] = (((zero + m00 * a) + m01 * b) + m02 * c) + m03 * d - o0
            r1[q] = (((zero + m10 * a) + m11 * b) + m12 * c) + m13 * d - o1
            r2[q] = (((zero + m20 * a) + m21 * b) + m22 * c) + m23 * d - o2
            r3[q] = (((zero + m30 * a) + m31 * b) + m32 * c) + m33 * d - o3
        for q in range(p1 - p0):
            unsat = (f32(ch_a[q]) < sat) & (f32(ch_b[q]) < sat)
            unsat &= (f32(ch_c[q]) < sat) & (f32(ch_d[q]) < sat)
            unsat_run[q] = unsat
            s0, s1, s2 = r0[q], r1[q], r2[q]
            ok_run[q] = unsat & (s0 >= s0_min) & (s1 * s1 + s2 * s2 >= dop2 * (s0 * s0))
        if per_pixel:
            for q in range(p1 - p0):
                var = read2 + (max(np.float64(r0[q]), 0.0) * gain_half) / conversion_gain
                sigma2[p0 + q] = var
                ok_run[q] &= np.float64(r3[q] * r3[q]) <= red2 * var
        else:
            for q in range(p1 - p0):
                ok_run[q] &= r3[q] * r3[q] <= red2_read2
    if grad2 < 0.0:
        return
    g2 = f32(grad2)
    half = f32(0.5)
    s0_row = rows[0]
    for k in range(n_runs):
        p0, p1 = runs[k, 2], runs[k + 1, 2]
        length = p1 - p0
        s, below, ok_run = s0_row[p0:p1], vertical[p0:p1], valid[p0:p1]
        for q in range(1, length - 1):  # central difference inside the run
            gx = ((s[q + 1] - s[q]) + (s[q] - s[q - 1])) * half
            gy = s0_row[below[q]] - s[q]
            ok_run[q] &= gx * gx + gy * gy < g2 * (s[q] * s[q])
        # One-sided at the ends (the same pixel when the run has one): the numbers of
        # numpy's sum of forward differences, where the missing side adds an exact zero.
        last = length - 1
        for q in (0, last):
            if q < last:
                gx = s[q + 1] - s[q]
            elif q > 0:
                gx = s[q] - s[q - 1]
            else:
                gx = zero
            gy = s0_row[below[q]] - s[q]
            ok_run[q] &= gx * gx + gy * gy < g2 * (s[q] * s[q])


def fill_pass(  # pragma: no cover - compiled by numba, which coverage cannot trace
    rows: NDArray, inv: NDArray, valid: NDArray
) -> None:
    """Harmless data for the invalid pixels in one pass, in place
    (:func:`polins.compass.image.fill_invalid`): ``rows (3 or 4, n)`` get (1, 0, 0[, 0]),
    ``inv (n,)`` (or ``(0,)`` for none) gets 1, where ``valid (n,)`` is False."""
    four, per_pixel = rows.shape[0] > 3, inv.size > 0
    for i in range(valid.size):
        if not valid[i]:
            rows[0, i] = 1.0
            rows[1, i] = 0.0
            rows[2, i] = 0.0
            if four:
                rows[3, i] = 0.0
            if per_pixel:
                inv[i] = 1.0


def square_sum_pass(x: NDArray, mask: NDArray) -> float:  # pragma: no cover
    """``sum_i x_i^2`` over the pixels of ``mask`` in one pass, in float64 (a reduction)."""
    total = 0.0
    for i in range(x.size):
        v = np.float64(x[i]) * mask[i]
        total += v * v
    return total
