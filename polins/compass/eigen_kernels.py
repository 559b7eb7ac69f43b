"""Compiled passes of the eigen sun vector: E-vectors and weights, the moment, the sandwich.

The E-vectors and weights of :func:`polins.compass.eigen.eigen_level_rows` (bit-identical
to the numpy expressions), their float64 moment, and the sandwich covariance's middle and
jackknife run sums (:func:`polins.compass.sectors.eigen_sandwich_sums`). Compiled by
:func:`polins.compass.kernels.compiled` (docs/model.md §9.1, §10.2; docs/measurement.md §6,
§10; tests/test_kernels.py).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


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
