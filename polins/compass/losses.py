"""Robust losses of the joint ML: IRLS weights, the objective and the sandwich variance factor.

``"linear"`` is least squares; ``"huber"`` (k = 1.345) and ``"cauchy"`` (c = 2.3849) are
M-estimators with 95 % efficiency at the normal, their scale the MAD of the residuals
(docs/model.md §9.2).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from polins.compass.kernels import dot

__all__ = [
    "CAUCHY_C",
    "HUBER_K",
    "LOSSES",
    "loss_objective",
    "loss_weights",
    "robust_variance_factor",
]

LOSSES = ("linear", "huber", "cauchy")
HUBER_K = 1.345
CAUCHY_C = 2.3849


def loss_weights(r: NDArray, loss: str, n: int) -> tuple[NDArray | None, float]:
    """IRLS weights of the robust loss and the residual scale (MAD of the n counted
    residuals; zeros from masked pixels are left out) used for them."""
    if loss == "linear":
        return None, 1.0
    a = np.abs(r)
    if n < r.size:
        a_used = np.sort(a)[r.size - n :]  # masked pixels have r = 0 exactly
    else:
        a_used = a
    scale = max(1.4826 * float(np.median(a_used)), 1e-12)
    t = a / scale
    if loss == "huber":
        return np.minimum(1.0, HUBER_K / np.maximum(t, 1e-30)).astype(r.dtype), scale
    if loss == "cauchy":
        return (1.0 / (1.0 + (t / CAUCHY_C) ** 2)).astype(r.dtype), scale
    raise ValueError(f"loss={loss!r}: expected one of {LOSSES}")


def loss_objective(r: NDArray, loss: str, scale: float) -> float:
    """The loss ``sum rho(r_i / scale) scale^2`` that Gauss-Newton/IRLS decreases (the
    line search compares it between iterations at one scale)."""
    r64 = r.astype(np.float64)  # float32 sums round at 1e-6, the size of a converged step
    if loss == "linear":
        return dot(r64, r64)
    t = np.abs(r64) / scale
    if loss == "huber":
        rho = np.where(t <= HUBER_K, 0.5 * t * t, HUBER_K * (t - 0.5 * HUBER_K))
    else:
        rho = 0.5 * CAUCHY_C**2 * np.log1p((t / CAUCHY_C) ** 2)
    return float(np.sum(rho)) * scale**2


def robust_variance_factor(r: NDArray, loss: str, scale: float, n: int, dof: int) -> float:
    """``sigma^2`` of ``Cov = sigma^2 (J^T J)^-1`` (Huber's M-estimator sandwich)."""
    t = r.astype(float) / scale
    if loss == "huber":
        psi = np.clip(t, -HUBER_K, HUBER_K)
        dpsi_sum = float(np.count_nonzero(np.abs(t) <= HUBER_K)) - (r.size - n)
    else:
        q = 1.0 + (t / CAUCHY_C) ** 2
        psi = t / q
        dpsi_sum = float(np.sum((1.0 - (t / CAUCHY_C) ** 2) / (q * q))) - (r.size - n)
    mean_dpsi = max(dpsi_sum / max(n, 1), 1e-12)
    return scale**2 * dot(psi, psi) / max(n - dof, 1) / mean_dpsi**2
