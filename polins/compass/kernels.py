"""Row kernels: BLAS-free dot products of component-first rows, and the chain's compiled passes.

The per-image pipeline stores per-pixel quantities component-first, one contiguous row of
``n`` pixels per component (``(3, n)``), because that layout makes every step one pass
over memory (docs/measurement.md §10). Thin products of such rows use ``einsum`` (numpy's
own loops), not BLAS: OpenBLAS threads stall for tens of milliseconds on a busy machine
for these shapes, and single-threaded they are no faster.

A full-resolution image is memory-bound: a pass over its 4e5 field-of-view pixels costs
about as much as the arithmetic of several. The hottest chains of passes are therefore
fused into single loops compiled with numba (:func:`compiled`, machine code cached on disk
next to this module). The passes that make Stokes rows and pixel masks repeat the numpy
expressions they replace operation for operation, in the same dtype and order, so that
their results are bit-identical to them; the float64 sums (:func:`moment_pass`,
:func:`eigen_run_sums`) add in another order, to float64 rounding, and the joint ML's
normal equations (:func:`ml_pass`) sum float32 terms reassociated, to float32 rounding
(tests/test_polarimetry.py, tests/test_kernels.py).
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
from numpy.typing import NDArray


def dot(a: NDArray, b: NDArray) -> float:
    """``a . b`` of two vectors ``(n,)``, without BLAS."""
    return float(np.einsum("i,i->", a, b))


def dot_rows(v: NDArray, rows: NDArray) -> NDArray:
    """``v @ rows`` ``(n,)`` for a vector ``(k,)`` and component-first rows ``(k, n)``,
    without BLAS."""
    return np.einsum("i,in->n", v, rows)


def moment(e: NDArray, omega: NDArray) -> NDArray:
    """Weighted moment ``sum_i omega_i e_i e_i^T`` ``(3, 3)`` of component-first vectors
    ``e`` ``(3, n)`` with weights ``omega`` ``(n,)``, in float64 (float32 or float64 input:
    one compiled pass, :func:`moment_pass`, float32 values cast to float64)."""
    floats = (np.float32, np.float64)
    if e.dtype in floats and omega.dtype in floats:
        out = np.empty((3, 3))
        compiled("moment_pass")(e, omega, out)
        return out
    return np.asarray(np.einsum("in,jn->ij", e * omega, e), dtype=float)


def stokes_pass(  # pragma: no cover - compiled by numba, which coverage cannot trace
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


def kept(  # pragma: no cover - compiled by numba, which coverage cannot trace
    n1, n2, e2, s0, s1, s2, p, use_p, valid, px, py, pz, sx, sy, sz, dop_min, cos_exclusion
):
    """The selection rule of one pixel (the tail shared by the selection passes): its
    polarized intensity along the predicted direction ``along = n1 S1 + n2 S2`` clears
    ``dop_min E^2 S0`` and (with ``use_p``) ``E^2 p``, it is valid, and its ray ``p`` is
    outside the sun circle of the camera-frame sun ``s``; in the rows' dtype, in numpy's
    order (compiled without fast-math, also inside the fast-math :func:`ml_pass`)."""
    zero = sx - sx
    along = n1 * s1
    along += n2 * s2
    ok = along >= (dop_min * e2) * s0
    if use_p:
        ok &= along >= e2 * p
    cos_sun = ((zero + sx * px) + sy * py) + sz * pz  # einsum's order
    return ok & valid & (cos_sun <= cos_exclusion)


def select_pass(  # pragma: no cover - compiled by numba, which coverage cannot trace
    s0: NDArray,
    s1: NDArray,
    s2: NDArray,
    n1: NDArray,
    n2: NDArray,
    e2: NDArray,
    valid: NDArray,
    rays: NDArray,
    sun_c: NDArray,
    p_min: NDArray,
    limits: NDArray,
    mask: NDArray,
) -> None:
    """The pixel selection of :func:`polins.compass.selection.select_pixels` in one pass:
    ``mask`` (n,) of the pixels :func:`kept`, with ``p_min`` (n,), or (1,) for one value,
    or (0,) for none; ``limits`` = (dop_min, cos_exclusion), ``sun_c`` (3,) in the rows'
    dtype."""
    dop_min, cos_exclusion = limits[0], limits[1]
    sx, sy, sz = sun_c[0], sun_c[1], sun_c[2]
    px, py, pz = rays[0], rays[1], rays[2]
    per_pixel, use_p = p_min.size > 1, p_min.size > 0
    p = p_min[0] if use_p else sx - sx
    for i in range(s0.size):
        if per_pixel:
            p = p_min[i]
        mask[i] = kept(n1[i], n2[i], e2[i], s0[i], s1[i], s2[i], p, use_p, valid[i],
                       px[i], py[i], pz[i], sx, sy, sz, dop_min, cos_exclusion)  # fmt: skip


def predicted_select_pass(  # pragma: no cover - compiled by numba, which coverage cannot trace
    s0: NDArray,
    s1: NDArray,
    s2: NDArray,
    lens_rays: NDArray,
    valid: NDArray,
    rays: NDArray,
    sun_c: NDArray,
    p_min: NDArray,
    limits: NDArray,
    mask: NDArray,
) -> None:
    """:func:`select_pass` with the prediction of the projection lens model (rays
    ``lens_rays (3, n)``) computed in the same pass
    (:func:`polins.compass.selection.selection_mask`): ``(x, y) = (s_y p_z - s_z p_y,
    s_z p_x - s_x p_z)``, ``n1 = x^2 - y^2``, ``n2 = 2 x y``, ``E^2 = x^2 + y^2 + 1e-30``
    in the order of :func:`polins.compass.prediction.image_plane_evector` and
    :func:`polins.compass.prediction.doubled_prediction`; ``limits`` = (dop_min,
    cos_exclusion, 1e-30)."""
    dop_min, cos_exclusion, tiny = limits[0], limits[1], limits[2]
    sx, sy, sz = sun_c[0], sun_c[1], sun_c[2]
    px, py, pz = rays[0], rays[1], rays[2]
    qx, qy, qz = lens_rays[0], lens_rays[1], lens_rays[2]
    per_pixel, use_p = p_min.size > 1, p_min.size > 0
    p = p_min[0] if use_p else sx - sx
    for i in range(s0.size):
        x = qz[i] * sy - sz * qy[i]
        y = qx[i] * sz - sx * qz[i]
        xx, yy, xy = x * x, y * y, x * y
        if per_pixel:
            p = p_min[i]
        mask[i] = kept(xx - yy, xy + xy, (xx + yy) + tiny, s0[i], s1[i], s2[i], p, use_p,
                       valid[i], px[i], py[i], pz[i], sx, sy, sz, dop_min,
                       cos_exclusion)  # fmt: skip


ML_SUMS = 15
"""Sums per group of :func:`ml_pass`: ``J^T J`` (10, upper triangle row by row), ``J^T r``
(4) and ``r^T r`` of the four columns (three sun/sky parameters, epsilon)."""


def ml_pass(  # pragma: no cover - compiled by numba, which coverage cannot trace
    s0: NDArray,
    s1: NDArray,
    s2: NDArray,
    c: NDArray,
    weight: NDArray,
    xy: NDArray,
    lens_rays: NDArray,
    cols: NDArray,
    valid: NDArray,
    rays: NDArray,
    sun_c: NDArray,
    p_min: NDArray,
    limits: NDArray,
    starts: NDArray,
    groups: NDArray,
    mask: NDArray,
    sums: NDArray,
) -> None:
    """The joint ML's residual, Jacobian and normal-equation sums in one pass
    (:func:`polins.compass.jointml.ml_evaluate` with the linear loss, then ``J^T J``,
    ``J^T r``, ``r^T r`` per group of runs of pixels, docs/measurement.md §3).

    Per-pixel arithmetic in the rows' dtype, sums in float64 (compiled with reassociation:
    summed in vector lanes). The variants are told by the arrays' dimensions (numba
    compiles one loop per variant: a test of a flag inside the loop would keep it out of
    vector lanes). ``xy (k, 2n)`` are the image-plane E-vector rows of the sun and its
    derivative columns, or ``(0,)`` with ``lens_rays (3, n)`` (projection lens model,
    Rayleigh sky): they are then ``lens_rays x cols``, ``cols (3, 4)`` the camera-frame
    sun and up to three derivative columns, zero-padded. ``weight (n,)``: per-pixel
    ``1/sigma_L``, or ``(0, 0)`` for none. ``valid (n,)``: the selection of :func:`kept`
    is made here (``rays``, ``sun_c`` as in :func:`select_pass`, ``p_min (n,)`` or one
    value ``(1, 1)``, -inf for none) and written to ``mask``; ``(0, 0)``: ``mask`` says
    which pixels count. ``limits`` = (dop_min, cos_exclusion, 1e-30,
    eps, w_0, w_1, 1, 2 alpha'_1, 2 alpha'_2, 2 alpha'_3) (``alpha'_j`` the derivative of
    the sun's image-plane azimuth, zero for absent columns). ``sums (G, ML_SUMS)``, zeroed
    by the caller: per group, the runs beginning at ``starts (m,)`` (the last ends at
    ``n``) added in order to the row ``groups (m,)`` of each.
    """
    n, m = s0.size, starts.size
    dop_min, cos_exclusion, tiny = limits[0], limits[1], limits[2]
    eps, w0, w1, one = limits[3], limits[4], limits[5], limits[6]
    a1, a2, a3 = limits[7], limits[8], limits[9]
    k_cols = cols.shape[1] if xy.ndim == 1 else xy.shape[0]
    # E-vector rows of the derivative columns (a missing one reads row 0, times 0)
    r1, r2, r3 = min(1, k_cols - 1), min(2, k_cols - 1), min(3, k_cols - 1)
    f1, f2, f3 = one * (k_cols > 1), one * (k_cols > 2), one * (k_cols > 3)
    sx, sy, sz = sun_c[0], sun_c[1], sun_c[2]
    b_eps, d_eps = one - eps, one - (eps + eps)
    # 1-D rows (indexed by an unsigned pixel number: the loops then run in vector lanes)
    s0_, s1_, s2_, c_, mask_ = s0, s1, s2, c, mask
    if xy.ndim == 1:
        px, py, pz = lens_rays[0], lens_rays[1], lens_rays[2]
    else:
        x0_, y0_ = xy[0, :n], xy[0, n:]
        x1_, y1_ = xy[r1, :n], xy[r1, n:]
        x2_, y2_ = xy[r2, :n], xy[r2, n:]
        x3_, y3_ = xy[r3, :n], xy[r3, n:]
    if valid.ndim == 1:
        valid_, rx, ry, rz = valid, rays[0], rays[1], rays[2]
    if p_min.ndim == 1:
        p_ = p_min
    else:
        p = p_min[0, 0]
    if weight.ndim == 1:
        weight_ = weight
    for run in range(m):
        lo = np.uintp(starts[run])
        hi = np.uintp(starts[run + 1] if run + 1 < m else n)
        h00 = h01 = h02 = h03 = h11 = h12 = h13 = h22 = h23 = h33 = 0.0
        g0 = g1 = g2 = g3 = rss = 0.0
        for i in range(lo, hi):
            if xy.ndim == 1:
                qx, qy, qz = px[i], py[i], pz[i]
                x = qz * cols[1, 0] - cols[2, 0] * qy
                y = qx * cols[2, 0] - cols[0, 0] * qz
            else:
                x, y = x0_[i], y0_[i]
            xx, yy, xy0 = x * x, y * y, x * y
            e2 = (xx + yy) + tiny
            n1, n2 = xx - yy, xy0 + xy0
            si0, si1, si2 = s0_[i], s1_[i], s2_[i]
            if valid.ndim == 2:
                ok = mask_[i]
            else:
                if p_min.ndim == 1:
                    p = p_[i]
                ok = kept(n1, n2, e2, si0, si1, si2, p, True, valid_[i], rx[i], ry[i], rz[i],
                          sx, sy, sz, dop_min, cos_exclusion)  # fmt: skip
                mask_[i] = ok
            inv_e = (one / e2) * ok  # zeroes r and the Jacobian of the pixels not used
            # u: the exact unpolarized intensity (polins.compass.sunlight.sunlight_unpolarized)
            b = si0 * b_eps - eps * (si1 * w0 + si2 * w1)
            u = c_[i] / (np.sqrt(abs(b * b - d_eps * c_[i])) + b)
            c2, sn = n1 * inv_e, n2 * inv_e
            u_nw = u * (c2 * w1 - sn * w0)
            r = (c2 * si2 - sn * si1) - eps * u_nw
            t_w = (c2 * w0 + sn * w1) * u * eps
            proj = (c2 * si1 + sn * si2 - t_w) * inv_e * -(one + one)
            if xy.ndim == 1:
                x1 = qz * cols[1, 1] - cols[2, 1] * qy
                y1 = qx * cols[2, 1] - cols[0, 1] * qz
                x2 = qz * cols[1, 2] - cols[2, 2] * qy
                y2 = qx * cols[2, 2] - cols[0, 2] * qz
                x3 = qz * cols[1, 3] - cols[2, 3] * qy
                y3 = qx * cols[2, 3] - cols[0, 3] * qz
            else:
                x1, y1 = x1_[i] * f1, y1_[i] * f1
                x2, y2 = x2_[i] * f2, y2_[i] * f2
                x3, y3 = x3_[i] * f3, y3_[i] * f3
            j1 = (x * y1 - y * x1) * proj - a1 * t_w
            j2 = (x * y2 - y * x2) * proj - a2 * t_w
            j3 = (x * y3 - y * x3) * proj - a3 * t_w
            je = -u_nw
            if weight.ndim == 1:
                wt = weight_[i]
                r, j1, j2, j3, je = r * wt, j1 * wt, j2 * wt, j3 * wt, je * wt
            d0, d1, d2, d3 = np.float64(j1), np.float64(j2), np.float64(j3), np.float64(je)
            dr = np.float64(r)
            h00 += d0 * d0
            h01 += d0 * d1
            h02 += d0 * d2
            h03 += d0 * d3
            h11 += d1 * d1
            h12 += d1 * d2
            h13 += d1 * d3
            h22 += d2 * d2
            h23 += d2 * d3
            h33 += d3 * d3
            g0 += d0 * dr
            g1 += d1 * dr
            g2 += d2 * dr
            g3 += d3 * dr
            rss += dr * dr
        out = sums[groups[run]]
        out[0] += h00
        out[1] += h01
        out[2] += h02
        out[3] += h03
        out[4] += h11
        out[5] += h12
        out[6] += h13
        out[7] += h22
        out[8] += h23
        out[9] += h33
        out[10] += g0
        out[11] += g1
        out[12] += g2
        out[13] += g3
        out[14] += rss


def moment_pass(e: NDArray, omega: NDArray, out: NDArray) -> int:  # pragma: no cover
    """``out (3, 3) = sum_i omega_i e_i e_i^T`` of ``e (3, n)``, ``omega (n,)`` in one pass
    (a float64 reduction: compiled with reassociation, i.e. summed in vector lanes; float32
    input is cast to float64 first); returns the number of non-zero weights."""
    a00 = a01 = a02 = a11 = a12 = a22 = 0.0
    count = 0
    for i in range(omega.size):
        count += omega[i] != 0
        w = np.float64(omega[i])
        x, y, z = np.float64(e[0, i]), np.float64(e[1, i]), np.float64(e[2, i])
        wx, wy = w * x, w * y
        a00 += wx * x
        a01 += wx * y
        a02 += wx * z
        a11 += wy * y
        a12 += wy * z
        a22 += (w * z) * z
    out[0, 0], out[1, 1], out[2, 2] = a00, a11, a22
    out[0, 1] = out[1, 0] = a01
    out[0, 2] = out[2, 0] = a02
    out[1, 2] = out[2, 1] = a12
    return count


def square_sum_pass(x: NDArray, mask: NDArray) -> float:  # pragma: no cover
    """``sum_i x_i^2`` over the pixels of ``mask`` in one pass, in float64 (a reduction)."""
    total = 0.0
    for i in range(x.size):
        v = np.float64(x[i]) * mask[i]
        total += v * v
    return total


def evector_pass(  # pragma: no cover - compiled by numba, which coverage cannot trace
    s1: NDArray,
    s2: NDArray,
    inv: NDArray,
    basis: NDArray,
    mask: NDArray,
    flags: NDArray,
    e: NDArray,
    omega: NDArray,
) -> None:
    """The E-vectors and weights of the eigen solution in one pass
    (:func:`polins.compass.eigen.eigen_level_rows`): the numpy expressions of
    :func:`polins.compass.lens.evector_rows` and of the weights, operation for operation in
    the rows' dtype (bit-identical to them).

    ``s1, s2 (n,)`` the Stokes rows; ``inv`` ``1/sigma_L^2`` ``(n,)``, or ``(1, 1)`` for one
    value, in their dtype; ``basis`` the inverse lens basis ``(3, 2, n)``, or its third row
    ``(2, n)`` for the projection model (whose first two rows are the identity); ``mask
    (n,)`` bool, or ``(0, 0)`` for all pixels; ``flags`` = (weighted, 1e-30, 1, 0) in the
    rows' dtype. Writes the unnormalised E-vectors ``e (3, n)`` and the weights ``omega
    (n,)`` (``w/|e|^2``, 0 for masked pixels) in the rows' dtype (float32 halves the pass's
    memory traffic; the sums that use them cast to float64). The variants are told by the
    arrays' dimensions, and there is no count or sum in the loop: it runs in vector lanes."""
    weighted = flags[0] != 0
    tiny, one, zero = flags[1], flags[2], flags[3]
    w = inv[0, 0] if inv.ndim == 2 else one
    for i in range(s1.size):
        a, b = s1[i], s2[i]
        p2 = a * a + b * b
        p = np.sqrt(p2)
        pos = a >= 0
        h1 = p + a if pos else b
        h2 = b if pos else p - a
        if basis.ndim == 2:
            e0, e1 = h1, h2
            e2 = basis[0, i] * h1 + basis[1, i] * h2
        else:
            e0 = basis[0, 0, i] * h1 + basis[0, 1, i] * h2
            e1 = basis[1, 0, i] * h1 + basis[1, 1, i] * h2
            e2 = basis[2, 0, i] * h1 + basis[2, 1, i] * h2
        norm2 = e0 * e0
        norm2 += e1 * e1
        norm2 += e2 * e2
        norm2 += tiny
        if inv.ndim == 1:
            om = p2 * inv[i] / norm2
        elif weighted:
            om = p2 * w / norm2
        else:
            om = one / norm2
        if mask.ndim == 1:
            om = om * (one if mask[i] else zero)
        e[0, i], e[1, i], e[2, i] = e0, e1, e2
        omega[i] = om


def eigen_run_sums(  # pragma: no cover - compiled by numba, which coverage cannot trace
    e: NDArray, wr: NDArray, omega: NDArray, starts: NDArray, out: NDArray
) -> None:
    """Per-run sums ``out (m, 4)`` = (``sum wr_i e_i`` (3), ``sum omega_i``) over the runs
    of pixels beginning at ``starts (m,)`` (the last run ends at ``n``): the sector sums
    of the eigen jackknife (:func:`polins.compass.sectors.eigen_jackknife`), in float64,
    pixel after pixel (runs of about 50 pixels: vector lanes would cost more than they
    save)."""
    n, m = omega.size, starts.size
    for r in range(m):
        end = starts[r + 1] if r + 1 < m else n
        s0 = s1 = s2 = s3 = 0.0
        for i in range(starts[r], end):
            w = wr[i]
            s0 += e[0, i] * w
            s1 += e[1, i] * w
            s2 += e[2, i] * w
            s3 += omega[i]
        out[r, 0], out[r, 1], out[r, 2], out[r, 3] = s0, s1, s2, s3


def sandwich_pass(  # pragma: no cover - compiled by numba, which coverage cannot trace
    e: NDArray, omega: NDArray, sun_c: NDArray, starts: NDArray, out: NDArray
) -> None:
    """The eigen solution's jackknife run sums in one pass, in float64
    (:func:`polins.compass.sectors.eigen_sandwich_sums`): per pixel the weighted residual
    ``wr = (s . e) omega`` in the order of :func:`polins.compass.eigen.weighted_residuals`
    (bit-identical) and, per run of pixels beginning at ``starts (m,)`` (``starts[0] =
    0``, the last run ends at ``n``), ``out (m, 4)`` = (``sum wr e`` (3), ``sum omega``)
    as :func:`eigen_run_sums`. Float32 ``e`` and ``omega`` are cast to float64 first; sums
    in pixel order (the runs are about 50 pixels long: vector lanes would cost more than
    they save)."""
    n, m = omega.size, starts.size
    sx, sy, sz = sun_c[0], sun_c[1], sun_c[2]
    for r in range(m):
        end = starts[r + 1] if r + 1 < m else n
        s0 = s1 = s2 = s3 = 0.0
        for i in range(starts[r], end):
            x, y, z = np.float64(e[0, i]), np.float64(e[1, i]), np.float64(e[2, i])
            om = np.float64(omega[i])
            w = (sx * x + sy * y + sz * z) * om
            s0 += x * w
            s1 += y * w
            s2 += z * w
            s3 += om
        out[r, 0], out[r, 1], out[r, 2], out[r, 3] = s0, s1, s2, s3


def middle_pass(  # pragma: no cover - compiled by numba, which coverage cannot trace
    e: NDArray, omega: NDArray, sun_c: NDArray, middle: NDArray
) -> None:
    """The eigen solution's sandwich middle ``middle (3, 3) = sum wr^2 e e^T`` in one pass,
    in float64 (:func:`polins.compass.sectors.eigen_sandwich_sums`), ``wr`` as in
    :func:`sandwich_pass`; float32 ``e`` and ``omega`` are cast to float64 first."""
    sx, sy, sz = sun_c[0], sun_c[1], sun_c[2]
    a00 = a01 = a02 = a11 = a12 = a22 = 0.0
    for i in range(omega.size):
        x, y, z = np.float64(e[0, i]), np.float64(e[1, i]), np.float64(e[2, i])
        w = (sx * x + sy * y + sz * z) * np.float64(omega[i])
        w2 = w * w
        wx, wy = w2 * x, w2 * y
        a00 += wx * x
        a01 += wx * y
        a02 += wx * z
        a11 += wy * y
        a12 += wy * z
        a22 += (w2 * z) * z
    middle[0, 0], middle[1, 1], middle[2, 2] = a00, a11, a22
    middle[0, 1] = middle[1, 0] = a01
    middle[0, 2] = middle[2, 0] = a02
    middle[1, 2] = middle[2, 1] = a12


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


_REDUCTIONS = ("moment_pass", "ml_pass", "zenith_pass", "middle_pass", "square_sum_pass")
"""Kernels that sum in float64 over long loops: compiled with reassociation (vector
lanes), which moves their results by float64 rounding only (:func:`ml_pass`: its per-pixel
terms by the rows' rounding); the others keep numpy's order exactly. All are compiled with
numpy's error model: a division by zero gives numpy's inf or NaN, and the divisions are not
checked (a check keeps a loop out of vector lanes)."""

_HELPERS = ("kept", "zenith_terms")
"""Functions the kernels call: compiled first, without fast-math, in place of the Python
function."""


@functools.cache
def compiled(name: str) -> Any:
    """The numba-compiled version of this module's kernel ``name`` (numba is imported here,
    not with polins; the machine code is cached on disk next to this module)."""
    import numba

    _compiled_helpers()
    fastmath = {"reassoc"} if name in _REDUCTIONS else set()
    return numba.njit(cache=True, nogil=True, fastmath=fastmath, error_model="numpy")(
        globals()[name]
    )


@functools.cache
def _compiled_helpers() -> None:
    import numba

    for name in _HELPERS:
        globals()[name] = numba.njit(cache=True, nogil=True, error_model="numpy")(globals()[name])
