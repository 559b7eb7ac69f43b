"""Compiled passes of the pixel selection and of the joint ML's normal equations.

The selection rule along the predicted AoP (:func:`kept`, :mod:`polins.compass.selection`)
and the joint ML's residual, Jacobian and normal-equation sums
(:func:`polins.compass.residual.ml_pass_sums`), which makes the same selection inside its
pass. Compiled by :func:`polins.compass.kernels.compiled` (docs/measurement.md §3, §4, §10;
tests/test_kernels.py).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


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


def ml_pass(  # pragma: no cover  # noqa: PLR0915 (one loop, compiled by numba)
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
    (:func:`polins.compass.residual.ml_evaluate` with the linear loss, then ``J^T J``,
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
