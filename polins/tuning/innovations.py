"""Innovation statistics of a fusion run: NIS against its chi-square band, whiteness, a measurement sigma floor.

A consistent Kalman filter's innovations ``nu`` are zero-mean, white, with covariance ``S``
(docs/tuning.md): the normalized innovation squared ``NIS = nu' S^-1 nu`` of a ``dim``-
dimensional update is chi-square with ``dim`` degrees of freedom, so the mean NIS of ``n``
updates lies in ``chi2.ppf([a/2, 1 - a/2], n dim) / n`` with probability ``1 - a``; the
whitened innovations ``L^-1 nu`` (``S = L L'``) have no autocorrelation beyond
``+-z / sqrt(n)``. A mean NIS above the band says ``S`` is too small (Q or R too small), below
it too large; autocorrelated innovations say the process noise is too small (the filter
trusts a drifting prediction). The measurement sigma floor is the ``f`` [rad or the unit of
the kind] that, added in quadrature to every ``R``, brings the mean NIS to ``dim``.

The input is the ``updates`` table of :class:`polins.fusion.FusionResult` with its
``innovation`` and ``innovation_var`` columns (:class:`polins.fusion.items.UpdateRecord`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import NDArray
from scipy.optimize import brentq
from scipy.signal import correlate
from scipy.stats import chi2, norm

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class InnovationStats:
    """Innovation statistics of one measurement kind.

    Attributes
    ----------
    kind : str
        ``"yaw"``, ``"sun"``, ``"zupt"`` or ``"nhc"``.
    n : int
        Accepted updates with an innovation (the yaw alignment has none).
    dim : int
        Dimension of each update.
    nis_mean : float
        Mean NIS (``dim`` for a consistent filter).
    nis_band : tuple of float
        The ``prob`` band of the mean NIS of ``n`` consistent updates.
    autocorr : ndarray, (max_lag,)
        Autocorrelation of the whitened innovations at lags ``1 .. max_lag`` (updates).
    autocorr_band : float
        ``z / sqrt(n)``: the ``prob`` band of the autocorrelation of white innovations.
    sigma_floor : float
        The floor added in quadrature to every measurement sigma that makes the mean NIS
        ``dim`` (the kind's unit: [rad] for yaw and sun); 0 if the NIS is already <= ``dim``.
        One step with this run's gains: when ``R`` was much too small the filter followed
        the measurement noise and the floor comes out too large (up to sqrt(2) x);
        :func:`polins.tuning.tune` refits it by maximum likelihood.
    """

    kind: str
    n: int
    dim: int
    nis_mean: float
    nis_band: tuple[float, float]
    autocorr: FloatArray
    autocorr_band: float
    sigma_floor: float

    @property
    def consistent(self) -> bool:
        """The mean NIS lies inside its chi-square band."""
        return self.nis_band[0] <= self.nis_mean <= self.nis_band[1]

    @property
    def white(self) -> bool:
        """The lag-1 autocorrelation lies inside the band of white innovations."""
        return bool(self.autocorr.size == 0 or abs(self.autocorr[0]) <= self.autocorr_band)

    @property
    def verdict(self) -> str:
        """One phrase: consistent, or which way ``S`` is off."""
        if self.nis_mean > self.nis_band[1]:
            return "S too small (Q or R too small)"
        if self.nis_mean < self.nis_band[0]:
            return "S too large (Q or R too large)"
        return "consistent"


def innovation_arrays(
    updates: pd.DataFrame, kind: str
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Times ``(n,)`` [s], innovations ``(n, dim)`` and their covariances ``(n, dim, dim)`` of
    the accepted ``kind`` updates of an ``updates`` table (those without an innovation, such
    as the yaw alignment, are left out)."""
    rows = updates[(updates["name"] == kind) & updates["accepted"].astype(bool)]
    rows = rows[np.array([len(v) > 0 for v in rows["innovation"]], dtype=bool)]
    if rows.empty:
        return np.zeros(0), np.zeros((0, 0)), np.zeros((0, 0, 0))
    dim = int(rows["dim"].iloc[0])
    nu = np.array([list(v) for v in rows["innovation"]], dtype=float).reshape(-1, dim)
    S = np.array([list(v) for v in rows["innovation_var"]], dtype=float).reshape(-1, dim, dim)
    return rows["t"].to_numpy(dtype=float), nu, S


def whitened(nu: FloatArray, S: FloatArray) -> FloatArray:
    """Whitened innovations ``L^-1 nu`` with ``S = L L'`` (Cholesky), ``(n, dim)``."""
    L = np.linalg.cholesky(S)
    return np.linalg.solve(L, nu[..., None])[..., 0]


def autocorrelation(x: FloatArray, max_lag: int) -> FloatArray:
    """Sample autocorrelation of the rows of ``x`` ``(n, dim)`` at lags ``1 .. max_lag``,
    averaged over the components (the biased estimator; zero-mean assumed)."""
    n = x.shape[0]
    out = np.zeros(min(max_lag, max(n - 1, 0)))
    for col in x.T:
        full = correlate(col, col, mode="full", method="fft")[n - 1 :]
        out += full[1 : out.size + 1] / full[0]
    return out / max(x.shape[1], 1)


def sigma_floor(nu: FloatArray, S: FloatArray) -> float:
    """The ``f >= 0`` with mean ``nu' (S + f^2 I)^-1 nu`` equal to ``dim`` (0 if already below)."""
    dim = nu.shape[1]
    w, V = np.linalg.eigh(S)
    proj = np.einsum("nij,ni->nj", V, nu) ** 2  # nu in the eigenbasis of each S

    def excess(f2: float) -> float:
        return float(np.mean(np.sum(proj / (w + f2), axis=1))) - dim

    if excess(0.0) <= 0.0:
        return 0.0
    hi = float(np.max(proj.sum(axis=1)))  # f^2 = max |nu|^2 makes the mean NIS < dim
    return float(np.sqrt(brentq(excess, 0.0, hi, xtol=1e-14 * hi + 1e-300)))


def innovation_stats(
    updates: pd.DataFrame, *, max_lag: int = 10, prob: float = 0.95
) -> dict[str, InnovationStats]:
    """Innovation statistics per measurement kind of a fusion's ``updates`` table.

    Parameters
    ----------
    updates : DataFrame
        ``FusionResult.updates`` (ESKF): ``name, dim, accepted, innovation, innovation_var``.
        A gate truncates the NIS (its rejections are left out): judge the noise model on a
        run without one (``gate_prob=None``).
    max_lag : int
        Largest autocorrelation lag [updates].
    prob : float
        Probability of the chi-square band of the mean NIS and of the whiteness band.

    Returns
    -------
    dict of str to InnovationStats
        One entry per kind with at least one accepted update with an innovation.
    """
    if "innovation" not in updates.columns:
        raise ValueError(
            "the updates table has no innovation column: innovation statistics need the "
            "ESKF backend's update log"
        )
    out: dict[str, InnovationStats] = {}
    for kind in pd.unique(updates["name"]):
        _, nu, S = innovation_arrays(updates, str(kind))
        if nu.shape[0] == 0:
            continue
        n, dim = nu.shape
        nis = np.einsum("ni,ni->n", nu, np.linalg.solve(S, nu[..., None])[..., 0])
        a = 1.0 - prob
        band = chi2.ppf([a / 2, 1 - a / 2], n * dim) / n
        out[str(kind)] = InnovationStats(
            kind=str(kind),
            n=n,
            dim=dim,
            nis_mean=float(nis.mean()),
            nis_band=(float(band[0]), float(band[1])),
            autocorr=autocorrelation(whitened(nu, S), max_lag),
            autocorr_band=float(norm.ppf(1 - a / 2) / np.sqrt(n)),
            sigma_floor=sigma_floor(nu, S),
        )
    return out


def stats_table(stats: dict[str, InnovationStats]) -> pd.DataFrame:
    """The statistics as a table, one row per kind (for printing and reports)."""
    return pd.DataFrame(
        [
            {
                "kind": s.kind,
                "n": s.n,
                "NIS mean": s.nis_mean,
                "NIS band": f"{s.nis_band[0]:.3g} .. {s.nis_band[1]:.3g}",
                "lag-1 autocorr": float(s.autocorr[0]) if s.autocorr.size else np.nan,
                "white band": s.autocorr_band,
                "sigma floor": s.sigma_floor,
                "verdict": s.verdict,
            }
            for s in stats.values()
        ]
    )


__all__ = [
    "InnovationStats",
    "autocorrelation",
    "innovation_arrays",
    "innovation_stats",
    "sigma_floor",
    "stats_table",
    "whitened",
]
