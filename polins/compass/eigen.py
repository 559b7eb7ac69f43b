"""The eigen sun vector: the direction closest to normal to all E-vectors, and its covariance.

Every Rayleigh E-vector is perpendicular to the sun, so the sun is the eigenvector of the
smallest eigenvalue of the weighted moment ``M = sum_i w_i e_i e_i^T`` (docs/model.md §9.1,
the paper's Eq. 31 with optional weights); its first-order covariance is the eigen-gap
sandwich of docs/model.md §10.2 and docs/errata.md §6. The eigen solution starts the joint
maximum likelihood and is the whole estimate of the ``"traditional"`` and ``"paper"``
methods.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from polins.compass.kernels import compiled, moment

FloatArray = NDArray[np.float64]

__all__ = [
    "EigenSolution",
    "eigen_from_moment",
    "eigen_gap",
    "eigen_level_rows",
    "eigen_sun_covariance",
    "gap_pseudo_inverse",
    "sandwich_covariance",
    "sun_eigen",
    "weighted_residuals",
]


@dataclass(frozen=True)
class EigenSolution:
    """Weighted eigen solution of docs/model.md §9.1 in the frame of the E-vectors.

    Attributes
    ----------
    sun : (3,)
        Eigenvector of the smallest eigenvalue, sign chosen with ``sun_z >= 0``.
    eigenvalues : (3,)
        Ascending.
    eigenvectors : (3, 3)
        Columns, the first one ``sun``.
    weight_sum : float
        Sum of the weights.
    n : int
        Pixels with a non-zero weight.
    """

    sun: FloatArray
    eigenvalues: FloatArray
    eigenvectors: FloatArray
    weight_sum: float
    n: int


def eigen_from_moment(moment_matrix: NDArray, weight_sum: float, n: int) -> EigenSolution:
    """The :class:`EigenSolution` of a moment matrix ``(3, 3)`` (symmetrised first)."""
    lam, vec = np.linalg.eigh(0.5 * (moment_matrix + moment_matrix.T))
    sun = vec[:, 0] * (1.0 if vec[2, 0] >= 0 else -1.0)
    vec = vec.copy()
    vec[:, 0] = sun
    return EigenSolution(sun, lam, vec, weight_sum, n)


def sun_eigen(evec: ArrayLike, weights: ArrayLike | None = None) -> EigenSolution:
    """Sun vector as the minimum-eigenvalue eigenvector of ``M = sum_i w_i e_i e_i^T``
    (docs/model.md §9.1, the paper's Eq. 31 with optional weights ``w_i = p_i^2/sigma_L,i^2``).

    Parameters
    ----------
    evec : array_like, (n, 3)
        Unit E-vectors, in the frame wanted for the sun (level frame for the heading).
    weights : array_like, (n,), optional
        Pixel weights; None = equal weights (the paper).
    """
    e = np.asarray(evec, dtype=float)
    if e.ndim != 2 or e.shape[1] != 3 or e.shape[0] < 3:
        raise ValueError(f"evec must have shape (n >= 3, 3), got {e.shape}")
    w = np.ones(e.shape[0]) if weights is None else np.asarray(weights, dtype=float)
    return eigen_from_moment(moment(e.T, w), float(w.sum()), e.shape[0])


def eigen_level_rows(
    s1: NDArray,
    s2: NDArray,
    inv_sigma2: NDArray | float,
    basis: NDArray,
    projection: bool,
    mat_lc: NDArray,
    weighted: bool,
    mask: NDArray | None = None,
) -> tuple[EigenSolution, NDArray, NDArray]:
    """Level-frame eigen solution of Stokes rows (the chain's row kernel).

    Parameters
    ----------
    s1, s2 : (n,)
        Stokes rows [DN].
    inv_sigma2 : (n,) or float
        ``1/sigma_L^2`` [1/DN^2] per pixel or common.
    basis : (3, 2, n)
        Inverse lens basis; ``projection`` says it is the projection model's.
    mat_lc : (3, 3)
        Camera -> level rotation matrix.
    weighted : bool
        Weights ``p^2/sigma_L^2`` (docs/model.md §9.1); False: equal weights (the paper).
    mask : (n,) bool, optional
        Pixels used.

    Returns
    -------
    solution : EigenSolution
        In the level frame.
    e : (3, n)
        Unnormalised camera-frame E-vectors, in the rows' dtype.
    omega : (n,)
        Their weights ``w/|e|^2`` (0 for masked pixels), in the rows' dtype.

    The moment matrix is summed in float64: its smallest eigenvalue is ~0, and float32
    accumulation over 4e5 pixels would move the eigenvector by ~1e-5 rad. E-vectors and
    weights come from one compiled pass (:func:`polins.compass.eigen_kernels.evector_pass`);
    the weight sum is the moment's trace ``sum omega_i |e_i|^2`` (pixels without
    polarization, ``e = 0``, add nothing to it).
    """
    dtype = s1.dtype
    inv = np.asarray(inv_sigma2, dtype=dtype)
    inv = np.ascontiguousarray(inv) if inv.ndim else inv.reshape(1, 1)
    flags = np.array([weighted, 1e-30, 1.0, 0.0], dtype=dtype)
    e, omega = np.empty((3, s1.size), dtype=dtype), np.empty(s1.size, dtype=dtype)
    compiled("evector_pass")(s1, s2, inv, basis[2] if projection else basis,
                             np.zeros((0, 0), bool) if mask is None else mask, flags, e,
                             omega)  # fmt: skip
    moment_c = np.empty((3, 3))
    n = int(compiled("moment_pass")(e, omega, moment_c))
    sol = eigen_from_moment(mat_lc @ moment_c @ mat_lc.T, float(np.trace(moment_c)), n)
    return sol, e, omega


def weighted_residuals(e: NDArray, omega: NDArray, sun: NDArray) -> NDArray:
    """``omega_i (e_i . s)`` ``(n,)`` of unnormalised E-vectors ``e`` (3, n) with weights
    ``omega = w_i/|e_i|^2``: the middle of the sandwich is ``sum (omega_i (e_i . s))^2 e_i
    e_i^T`` and the moment's derivative ``M s = sum omega_i (e_i . s) e_i``."""
    proj = sun[0] * e[0] + sun[1] * e[1] + sun[2] * e[2]
    proj *= omega
    return proj


def gap_pseudo_inverse(solution: EigenSolution) -> FloatArray:
    """``A+ = sum_{j=2,3} v_j v_j^T / (lambda_j - lambda_1)`` (3, 3) of the eigen solution
    (docs/model.md §10.2); infinite or NaN entries when an eigen gap is zero (no pixels
    selected): the covariances built on it then say so, without a numpy warning."""
    lam, vec = solution.eigenvalues, solution.eigenvectors
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.asarray(
            sum(np.outer(vec[:, j], vec[:, j]) / (lam[j] - lam[0]) for j in (1, 2)), dtype=float
        )


def sandwich_covariance(solution: EigenSolution, middle: NDArray) -> FloatArray:
    """``A+ middle A+`` with ``A+`` of :func:`gap_pseudo_inverse`."""
    a_plus = gap_pseudo_inverse(solution)
    with np.errstate(invalid="ignore"):
        return np.asarray(a_plus @ middle @ a_plus, dtype=float)


def eigen_sun_covariance(
    evec: ArrayLike, weights: ArrayLike | None, solution: EigenSolution
) -> FloatArray:
    """First-order (sandwich) covariance of the eigen sun vector (docs/model.md §10.2)::

        A+ = sum_{j=2,3} v_j v_j^T / (lambda_j - lambda_1),  r_i = e_i . s
        Cov(s) = A+ (sum_i w_i^2 r_i^2 e_i e_i^T) A+

    Parameters
    ----------
    evec, weights : as for :func:`sun_eigen` (unit E-vectors ``(n, 3)``).
    """
    e = np.asarray(evec, dtype=float)
    w = np.ones(e.shape[0]) if weights is None else np.asarray(weights, dtype=float)
    wr = w * (e @ solution.sun)
    return sandwich_covariance(solution, moment(e.T, wr * wr))


def eigen_gap(solution: EigenSolution) -> float:
    """Normalised eigen-gap ``(lambda_perp - lambda_1)/lambda_perp`` (docs/model.md §10.1),
    with lambda_perp the eigenvalue whose eigenvector is closest to the horizontal direction
    perpendicular to the solar vertical plane (``z x s``; the solution must be in a level
    frame)."""
    s = solution.sun
    perp = np.array([-s[1], s[0], 0.0])
    norm = np.linalg.norm(perp)
    if norm < 1e-12:
        return float("nan")
    j = 1 + int(np.argmax(np.abs(solution.eigenvectors[:, 1:].T @ (perp / norm))))
    lam = solution.eigenvalues
    return float((lam[j] - lam[0]) / lam[j]) if lam[j] > 0 else float("nan")
