"""Row kernels: BLAS-free dot products of component-first rows, the inner loops of the chain.

The per-image pipeline stores per-pixel quantities component-first, one contiguous row of
``n`` pixels per component (``(3, n)``), because that layout makes every step one pass
over memory (docs/measurement.md §10). Thin products of such rows use ``einsum`` (numpy's
own loops), not BLAS: OpenBLAS threads stall for tens of milliseconds on a busy machine
for these shapes, and single-threaded they are no faster.
"""

from __future__ import annotations

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
    ``e`` ``(3, n)`` with weights ``omega`` ``(n,)``, in float64."""
    return np.asarray(np.einsum("in,jn->ij", e * omega, e), dtype=float)
