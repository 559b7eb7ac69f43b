"""The joint ML's normal equations: summed from residual rows, or in one compiled pass over the pixels.

Gauss-Newton (:func:`polins.compass.jointml.gauss_newton`) needs ``H = J^T W J``,
``b = J^T W r``, ``r^T W r`` and, for the sector jackknife (docs/measurement.md §12),
their parts per group of sky sectors. With a robust loss (IRLS weights from the residuals)
they are summed from the stored rows of ``r`` and ``J`` (:func:`normal_equations`,
:func:`sector_normal_equations`). With the linear loss the rows are never stored: the
compiled :func:`polins.compass.selection_kernels.ml_pass` evaluates the residual and the Jacobian
pixel after pixel, makes the pixel selection on the way, and sums per group of sky sectors
(:func:`pass_sums`; docs/measurement.md §5).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from polins.compass.kernels import compiled, dot
from polins.compass.prediction import PixelData
from polins.compass.sectors import SECTOR_AZIMUTHS, SECTOR_RINGS, SectorRuns, sector_sums
from polins.compass.selection import Selection, compiled_arguments
from polins.compass.selection_kernels import ML_SUMS

FloatArray = NDArray[np.float64]

__all__ = [
    "normal_equations",
    "pass_ready",
    "pass_sums",
    "sector_normal_equations",
    "sums_normal_equations",
    "sums_sector_normal_equations",
]

_PASS_COLUMNS = 3  # sun/sky parameter columns of the compiled pass (then epsilon)


def normal_equations(
    r: NDArray, jac: NDArray, weights: NDArray | None
) -> tuple[FloatArray, FloatArray, float]:
    """``J^T W J``, ``J^T W r`` and ``r^T W r`` in float64 of residuals ``r (n,)`` and
    Jacobian rows ``jac (k, n)`` (row dot products: BLAS gemm is slow for these thin
    shapes)."""
    k = jac.shape[0]
    jw = jac if weights is None else jac * weights
    jtj = np.empty((k, k))
    for a in range(k):
        for b in range(a, k):
            jtj[a, b] = jtj[b, a] = dot(jw[a], jac[b])
    jtr = np.array([dot(jw[a], r) for a in range(k)])
    rss = dot(r, r) if weights is None else dot(r * weights, r)
    return jtj, jtr, rss


def sector_normal_equations(
    r: NDArray,
    jac: NDArray,
    weights: NDArray | None,
    sectors: SectorRuns,
    sun_c: NDArray,
    sector_h: FloatArray | None,
) -> tuple[FloatArray, FloatArray]:
    """Per-group ``H_g (G, k, k)`` (``sector_h`` when given) and ``b_g (G, k)`` (masked
    pixels have a zero Jacobian) for the camera-frame sun ``sun_c``."""
    k = jac.shape[0]
    jw = jac if weights is None else jac * weights
    pairs = [] if sector_h is not None else [(a, b) for a in range(k) for b in range(a, k)]
    rows = np.empty((len(pairs) + k, r.size), dtype=r.dtype)
    for j, (a, b) in enumerate(pairs):
        np.multiply(jw[a], jac[b], out=rows[j])
    for a in range(k):
        np.multiply(jw[a], r, out=rows[len(pairs) + a])
    sums = sector_sums(rows, sectors, sun_c)
    if sector_h is not None:
        return sector_h, sums
    h = np.empty((sums.shape[0], k, k))
    for j, (a, b) in enumerate(pairs):
        h[:, a, b] = h[:, b, a] = sums[:, j]
    return h, sums[:, len(pairs) :]


def pass_ready(data: PixelData, select: Selection | None, k: int) -> bool:
    """The compiled pass can evaluate ``k`` parameters (the last epsilon) on ``data``: its
    arrays share one dtype, and a selection is made or a mask given (without either, the
    numpy evaluation cleans up non-physical pixels)."""
    if k - 1 > _PASS_COLUMNS or (select is None and data.mask is None):
        return False
    dt = data.s0.dtype
    arrays = [data.s1, data.s2, data.c, data.rays if data.rays is not None else data.forward]
    if isinstance(data.inv_sigma, np.ndarray):
        arrays.append(data.inv_sigma)
    if select is not None and compiled_arguments(data, select, np.zeros(3), ()) is None:
        return False
    return all(a is not None and a.dtype == dt for a in arrays)


def pass_sums(
    data: PixelData,
    cols: NDArray,
    xy: NDArray | None,
    eps: float,
    w: NDArray,
    alphas: Sequence[float],
    select: Selection | None,
    sectors: SectorRuns | None,
) -> tuple[FloatArray, NDArray]:
    """Per-group sums ``(G, ML_SUMS)`` of the residual and Jacobian products
    (:func:`polins.compass.selection_kernels.ml_pass`) and the mask in force: the groups of
    ``sectors`` (:meth:`SectorRuns.mirror_groups` for the sun ``cols[:, 0]``), or one.

    ``cols (3, 1 + j)`` are the camera-frame sun and its derivative columns, ``xy (1 + j,
    2n)`` their image-plane E-vector rows (None: the projection lens model's rays of
    ``data`` give them in the pass), ``w`` the sunlight direction, ``alphas`` the
    derivatives of the sun's image-plane azimuth by the ``j`` parameters, ``select`` the
    selection to make (None: ``data.mask``) (:func:`pass_ready` must hold).
    """
    dt = data.s0.dtype
    n = data.s0.size
    sun_c = cols[:, 0]
    args = None if select is None else compiled_arguments(data, select, sun_c, ())
    none = np.zeros((0, 0), dtype=dt)  # the pass's "no such array" (docs of ml_pass)
    if args is None:
        assert data.mask is not None
        mask = data.mask
        valid, rays, sun_arg, p_min = np.zeros((0, 0), dtype=bool), none, sun_c.astype(dt), none
        lim = np.array([0.0, 0.0, 1e-30])
    else:
        mask = np.empty(n, dtype=bool)
        valid, rays, sun_arg, p_min, lim = args
        if p_min.size <= 1:  # one value, or none
            p_min = np.full((1, 1), p_min[0] if p_min.size else -np.inf, dtype=dt)
    padded = np.zeros(_PASS_COLUMNS)
    padded[: len(alphas)] = alphas
    limits = np.array([*lim[:3], eps, w[0], w[1], 1.0, *(2.0 * padded)], dtype=dt)
    cols_arg = np.zeros((3, 1 + _PASS_COLUMNS), dtype=dt)
    cols_arg[:, : cols.shape[1]] = cols
    weight = data.inv_sigma if isinstance(data.inv_sigma, np.ndarray) else none
    projection = xy is None
    if sectors is None:
        starts, groups = np.zeros(1, dtype=np.intp), np.zeros(1, dtype=np.intp)
    else:  # consecutive runs of one group as one (about half as many)
        groups = sectors.mirror_groups(sun_c)[sectors.labels]
        first = np.flatnonzero(np.r_[True, groups[1:] != groups[:-1]])
        starts, groups = sectors.starts[first], groups[first]
    sums = np.zeros((1 if sectors is None else SECTOR_AZIMUTHS * SECTOR_RINGS, ML_SUMS))
    compiled("ml_pass")(data.s0, data.s1, data.s2, data.c, weight,
                        np.zeros(0, dt) if projection else xy,
                        data.rays if projection else none, cols_arg, valid, rays, sun_arg, p_min,
                        limits, starts, groups, mask, sums)  # fmt: skip
    return sums, mask


def _columns(k: int) -> list[int]:
    """The pass's columns of ``k`` parameters (the last epsilon)."""
    return [*range(k - 1), _PASS_COLUMNS]


def _unpack(sums: NDArray, k: int) -> tuple[FloatArray, FloatArray]:
    """``H (..., k, k)`` and ``b (..., k)`` of pass sums ``(..., ML_SUMS)``."""
    full = np.empty((*sums.shape[:-1], 1 + _PASS_COLUMNS, 1 + _PASS_COLUMNS))
    j = 0
    for a in range(1 + _PASS_COLUMNS):
        for b in range(a, 1 + _PASS_COLUMNS):
            full[..., a, b] = full[..., b, a] = sums[..., j]
            j += 1
    use = _columns(k)
    return full[..., use, :][..., use], sums[..., j:][..., use]


def sums_normal_equations(sums: NDArray, k: int) -> tuple[FloatArray, FloatArray, float]:
    """``J^T J``, ``J^T r``, ``r^T r`` of ``k`` parameters from :func:`pass_sums`."""
    total = sums.sum(axis=0)
    jtj, jtr = _unpack(total, k)
    return jtj, jtr, float(total[-1])


def sums_sector_normal_equations(
    sums: NDArray, k: int, sector_h: FloatArray | None
) -> tuple[FloatArray, FloatArray]:
    """:func:`sector_normal_equations` from the per-group :func:`pass_sums`."""
    h, b = _unpack(sums, k)
    return (h if sector_h is None else sector_h), b
