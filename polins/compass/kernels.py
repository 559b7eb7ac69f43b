"""Row kernels: BLAS-free dot products of component-first rows, and the chain's compiled passes.

The per-image pipeline stores per-pixel quantities component-first, one contiguous row of
``n`` pixels per component (``(3, n)``), because that layout makes every step one pass
over memory (docs/measurement.md §10). Thin products of such rows use ``einsum`` (numpy's
own loops), not BLAS: OpenBLAS threads stall for tens of milliseconds on a busy machine
for these shapes, and single-threaded they are no faster.

A full-resolution image is memory-bound: a pass over its 4e5 field-of-view pixels costs
about as much as the arithmetic of several. The hottest chains of passes are therefore
fused into single loops compiled with numba (:func:`compiled`, machine code cached on disk
next to the modules), one module per stage: :mod:`~polins.compass.stokes_kernels`,
:mod:`~polins.compass.selection_kernels` (with the joint ML's normal equations),
:mod:`~polins.compass.eigen_kernels` and :mod:`~polins.compass.zenith_kernels`. The passes
that make Stokes rows, E-vectors and pixel masks repeat the numpy expressions they replace
operation for operation, in the same dtype and order, so that their results are
bit-identical to them; the float64 sums add in another order, to float64 rounding, and the
joint ML's normal equations sum float32 terms reassociated, to float32 rounding
(tests/test_polarimetry.py, tests/test_kernels.py).
"""

from __future__ import annotations

import functools
from types import ModuleType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from polins.compass import eigen_kernels, selection_kernels, stokes_kernels, zenith_kernels


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


_MODULES: tuple[ModuleType, ...] = (stokes_kernels, selection_kernels, eigen_kernels,
                                     zenith_kernels)  # fmt: skip
"""The modules of the compiled passes."""

_REDUCTIONS = ("moment_pass", "ml_pass", "zenith_pass", "middle_pass", "square_sum_pass")
"""Kernels that sum in float64 over long loops: compiled with reassociation (vector
lanes), which moves their results by float64 rounding only (``ml_pass``: its per-pixel
terms by the rows' rounding); the others keep numpy's order exactly. All are compiled with
numpy's error model: a division by zero gives numpy's inf or NaN, and the divisions are not
checked (a check keeps a loop out of vector lanes)."""

_HELPERS = ("kept", "zenith_terms")
"""Functions the kernels call: compiled first, without fast-math, in place of the Python
function in the module that holds it."""


def _module_of(name: str) -> ModuleType:
    for module in _MODULES:
        if name in vars(module):
            return module
    raise KeyError(f"no compiled pass {name!r}")


@functools.cache
def compiled(name: str) -> Any:
    """The numba-compiled version of the kernel ``name`` of the pass modules (numba is
    imported here, not with polins; the machine code is cached on disk next to them)."""
    import numba

    _compiled_helpers()
    fastmath = {"reassoc"} if name in _REDUCTIONS else set()
    return numba.njit(cache=True, nogil=True, fastmath=fastmath, error_model="numpy")(
        getattr(_module_of(name), name)
    )


@functools.cache
def _compiled_helpers() -> None:
    import numba

    for name in _HELPERS:
        module = _module_of(name)
        helper = numba.njit(cache=True, nogil=True, error_model="numpy")(getattr(module, name))
        setattr(module, name, helper)
