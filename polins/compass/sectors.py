"""Sky sectors and the delete-one-sector jackknife: the data-driven part of the heading sigma.

The pixel-noise covariance of an estimate (docs/measurement.md §6) assumes independent
pixels. Model errors (neutral points, clouds, a channel-gain residual, a sky that is not
Rayleigh) are smooth over the sky, hence correlated over thousands of pixels, and do not
average down. The jackknife over G contiguous sectors of the image sees them: removing one
sector moves the estimate by what that sector's error contributed
(docs/measurement.md §12)::

    var_J = (G - 1)/G sum_g (d_g - mean d)^2,      d_g = theta_(g) - theta

The leave-one-out estimates are one linearized step from the full-set normal equations
(``H = J^T W J``, ``b = J^T W r``; per sector ``H_g``, ``b_g``)::

    theta_(g) - theta = -(H - H_g)^-1 (b - b_g) + H^-1 b

and for the eigen solution the first-order change of its smallest eigenvector when the
sector's moment ``M_g`` is removed. The per-sector sums
run over the pixels in index order as ``np.add.reduceat`` over runs of equal sector
(sectors are contiguous in the image, so a row holds few runs); the eigen jackknife's in
one compiled pass (:func:`polins.compass.eigen_kernels.eigen_run_sums`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from polins.compass.eigen import EigenSolution, gap_pseudo_inverse
from polins.compass.kernels import compiled
from polins.compass.lens import camera_constants
from polins.models import CameraModel

FloatArray = NDArray[np.float64]

__all__ = [
    "SECTOR_AZIMUTHS",
    "SECTOR_RINGS",
    "SectorRuns",
    "eigen_jackknife",
    "eigen_jackknife_sums",
    "eigen_sandwich_sums",
    "group_sums",
    "jackknife_variance",
    "ml_jackknife",
    "sector_runs",
    "sector_sums",
]

SECTOR_AZIMUTHS = 8
"""Jackknife groups per ring: mirror pairs of azimuth slices about the sun's image azimuth."""
SECTOR_RINGS = 2
"""Field-angle rings (split at the median field angle of the field of view)."""
_FINE = 4 * SECTOR_AZIMUTHS  # fixed image slices per ring, grouped per image


@dataclass(frozen=True, eq=False)
class SectorRuns:
    """Sectors of a camera's field-of-view pixel set as runs of equal label in index order.

    Attributes
    ----------
    starts : (m,) int
        First pixel of every run.
    labels : (m,) int
        Sector of every run.
    n_sectors : int
        Fixed image sectors (``4 SECTOR_AZIMUTHS`` slices per ring).
    azimuth : (n_sectors,)
        Centre azimuth of every sector about the optical axis [rad].
    ring : (n_sectors,) int
    """

    starts: NDArray[np.intp]
    labels: NDArray[np.intp]
    n_sectors: int
    azimuth: FloatArray
    ring: NDArray[np.intp]

    def mirror_groups(self, sun_c: NDArray) -> NDArray[np.intp]:
        """Jackknife group ``(n_sectors,)`` of every sector for a camera-frame sun ``(3,)``:
        the :data:`SECTOR_AZIMUTHS` bands of ``|azimuth - sun azimuth|`` in [0, pi] per
        ring, so that each group holds mirror-image slices about the solar vertical."""
        folded = np.abs(np.angle(np.exp(1j * (self.azimuth - np.arctan2(sun_c[1], sun_c[0])))))
        band = np.minimum((folded * (SECTOR_AZIMUTHS / np.pi)).astype(np.intp), SECTOR_AZIMUTHS - 1)
        return band + SECTOR_AZIMUTHS * self.ring


@lru_cache(maxsize=16)
def sector_runs(cam: CameraModel, stride: int = 1) -> SectorRuns:
    """The fixed image sectors (``4 SECTOR_AZIMUTHS`` slices x :data:`SECTOR_RINGS` rings)
    of the camera's field-of-view pixel set, or of every ``stride``-th pixel of it (the
    chain's subsample), cached."""
    rays = camera_constants(cam, np.float64).rays
    azimuth = np.arctan2(rays[1], rays[0])
    field = np.arccos(np.clip(rays[2], -1.0, 1.0))
    slice_ = np.floor((azimuth + np.pi) * (_FINE / (2 * np.pi))).astype(np.intp)
    slice_ = np.minimum(slice_, _FINE - 1)
    ring = np.searchsorted(np.quantile(field, np.arange(1, SECTOR_RINGS) / SECTOR_RINGS), field)
    labels = (slice_ + _FINE * ring.astype(np.intp))[::stride]
    starts = np.flatnonzero(np.r_[True, labels[1:] != labels[:-1]])
    n = _FINE * SECTOR_RINGS
    centre: FloatArray = np.asarray(
        -np.pi + (np.arange(n) % _FINE + 0.5) * (2 * np.pi / _FINE), dtype=np.float64
    )
    return SectorRuns(starts, labels[starts], n, centre, np.arange(n) // _FINE)


def sector_sums(rows: NDArray, runs: SectorRuns, sun_c: NDArray) -> FloatArray:
    """Per-group sums ``(G, m)`` of rows ``(m, n)`` over the field-of-view pixel set, in
    float64, the groups the mirror pairs of :meth:`SectorRuns.mirror_groups` for the
    camera-frame sun ``sun_c``. The runs (about a hundred pixels each) are summed in the
    rows' dtype, the runs' sums in float64."""
    run_sums = np.add.reduceat(rows, runs.starts, axis=1).astype(np.float64)
    return group_sums(run_sums, runs, sun_c)


def group_sums(run_sums: NDArray, runs: SectorRuns, sun_c: NDArray) -> FloatArray:
    """Per-group sums ``(G, m)`` of per-run sums ``(m, n_runs)`` (the groups of
    :meth:`SectorRuns.mirror_groups` for the camera-frame sun ``sun_c``)."""
    group_of_run = runs.mirror_groups(sun_c)[runs.labels]
    n_groups = SECTOR_AZIMUTHS * SECTOR_RINGS
    m = run_sums.shape[0]
    # one bincount over (row, group) bins: each bin sums its runs in order, as per row
    bins = group_of_run + n_groups * np.arange(m)[:, None]
    sums = np.bincount(bins.ravel(), weights=np.ravel(run_sums), minlength=m * n_groups)
    return np.asarray(sums.reshape(m, n_groups).T, dtype=np.float64)


def jackknife_variance(deltas: NDArray, share: NDArray, min_share: float = 1e-3) -> float:
    """Delete-one-group jackknife variance ``(G'-1)/G' sum (d_g - mean d)^2`` of the
    leave-one-out deviations ``deltas (G,)`` over the G' groups holding at least
    ``min_share`` of the information (``share (G,)``, summing to 1); NaN with fewer than 3
    such groups."""
    d = np.asarray(deltas, dtype=float)
    use = (np.asarray(share) >= min_share) & np.isfinite(d)
    g = int(np.count_nonzero(use))
    if g < 3:
        return float("nan")
    d = d[use]
    return float((g - 1) / g * np.sum((d - d.mean()) ** 2))


def ml_jackknife(jtj: NDArray, jtr: NDArray, sector_h: NDArray, sector_b: NDArray) -> FloatArray:
    """Leave-one-sector-out deviations ``(G, k)`` of a Gauss-Newton solution from its normal
    equations ``jtj (k, k)``, ``jtr (k,)`` and their per-sector parts ``sector_h (G, k, k)``,
    ``sector_b (G, k)``: ``-(H - H_g)^-1 (b - b_g) + H^-1 b`` (NaN where ``H - H_g`` is
    singular)."""
    base = np.linalg.solve(jtj, jtr)
    reduced = jtj[None] - sector_h
    rhs = (jtr[None] - sector_b)[..., None]
    out = np.full(sector_b.shape, np.nan)
    det = np.linalg.det(reduced)
    ok = np.abs(det) > 1e-12 * abs(float(np.linalg.det(jtj)))
    if np.any(ok):
        out[ok] = base[None] - np.linalg.solve(reduced[ok], rhs[ok])[..., 0]
    return out


def eigen_jackknife(
    e: NDArray,
    wr: NDArray,
    omega: NDArray,
    runs: SectorRuns,
    mat_lc: NDArray,
    solution: EigenSolution,
    sun_l: NDArray,
) -> tuple[FloatArray, FloatArray]:
    """Leave-one-group-out azimuth deviations ``(G,)`` [rad] of the eigen sun of
    camera-frame E-vectors ``e (3, n)`` with weights ``omega (n,)`` (the moment
    ``M = sum omega e e^T``), and each group's share of the weights ``(G,)``; ``wr (n,)``
    is ``omega_i (e_i . s)`` (:func:`polins.compass.eigen.weighted_residuals`). The
    per-run sums of :func:`eigen_jackknife_sums`, then that function."""
    run_sums = np.empty((runs.starts.size, 4))
    compiled("eigen_run_sums")(e, wr, omega, runs.starts, run_sums)  # one pass, float64
    return eigen_jackknife_sums(run_sums, runs, mat_lc, solution, sun_l)


def eigen_sandwich_sums(
    e: NDArray, omega: NDArray, sun_c: NDArray, runs: SectorRuns
) -> tuple[FloatArray, FloatArray]:
    """The middle ``sum_i (omega_i (e_i . s))^2 e_i e_i^T`` ``(3, 3)`` of the eigen
    solution's sandwich covariance (camera frame, docs/model.md §10.2) and the per-run
    sums ``(m, 4)`` of :func:`eigen_jackknife_sums`, in two compiled passes over ``e (3, n)``
    and ``omega (n,)`` with the camera-frame sun ``sun_c (3,)`` (the runs' in pixel order,
    the middle's in vector lanes)."""
    middle, run_sums = np.empty((3, 3)), np.empty((runs.starts.size, 4))
    sun = np.asarray(sun_c, dtype=np.float64)
    compiled("sandwich_pass")(e, omega, sun, runs.starts, run_sums)
    compiled("middle_pass")(e, omega, sun, middle)
    return middle, run_sums


def eigen_jackknife_sums(
    run_sums: NDArray,
    runs: SectorRuns,
    mat_lc: NDArray,
    solution: EigenSolution,
    sun_l: NDArray,
) -> tuple[FloatArray, FloatArray]:
    """:func:`eigen_jackknife` from the per-run sums ``(m, 4)`` = (``sum omega_i (e_i . s)
    e_i`` (3), ``sum omega_i``) of the runs of ``runs``.

    First order in the removed moment ``M_g``: ``ds_g = A+ M_g s`` with
    ``A+ = sum_{j=2,3} v_j v_j^T / (lambda_j - lambda_1)`` of the level-frame ``solution``
    (docs/model.md §10.2) and ``M_g s = sum_g omega_i (e_i . s) e_i``; ``sun_l`` (3,) is
    the full-set level-frame sun.
    """
    sun_c = mat_lc.T @ sun_l
    sums = group_sums(run_sums.T, runs, sun_c)
    with np.errstate(invalid="ignore"):  # a zero eigen gap: NaN deviations, no warning
        ds = (sums[:, :3] @ mat_lc.T) @ gap_pseudo_inverse(solution).T  # (G, 3) level frame
    rho2 = max(float(sun_l[0] ** 2 + sun_l[1] ** 2), 1e-300)
    deltas = (sun_l[0] * ds[:, 1] - sun_l[1] * ds[:, 0]) / rho2
    return deltas, sums[:, 3] / max(float(sums[:, 3].sum()), 1e-300)
