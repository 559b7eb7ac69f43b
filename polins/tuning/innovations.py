"""Innovation statistics of a fusion run: NIS against its chi-square band, whiteness, a measurement sigma floor.

A consistent Kalman filter's innovations ``nu`` are zero-mean, white, with covariance ``S``
(docs/tuning.md): the normalized innovation squared ``NIS = nu' S^-1 nu`` of a ``dim``-
dimensional update is chi-square with ``dim`` degrees of freedom, so the mean NIS of ``n``
updates lies in ``chi2.ppf([a/2, 1 - a/2], n dim) / n`` with probability ``1 - a``; the
whitened innovations ``L^-1 nu`` (``S = L L'``) have no autocorrelation beyond
``+-z / sqrt(n)``. A mean NIS above the band says ``S`` is too small (Q or R too small), below
it too large; autocorrelated innovations say the process noise is too small (the filter
trusts a drifting prediction).

Autocorrelated innovations (the NHC and ZUPT pseudo-measurements at the IMU rate, whose
innovations follow the slowly varying velocity error) carry fewer independent samples than
updates: the band of the mean NIS uses the effective number ``n_eff = n / (1 + 2 sum_k
rho_k)`` of the NIS series' autocorrelation ``rho_k`` (summed while it exceeds the white
band), as the variance of a mean of correlated samples; with the innovations at hand, the
smaller of that and ``n / (1 + 2 sum_k rho_k^2)`` of the whitened innovations. A gate that
rejects ``NIS > c`` truncates the chi-square, so the accepted updates' expected mean is ``dim F_{dim+2}(c) /
F_dim(c)``, below ``dim``; the band is that truncated mean's (a scaled chi-square with the
truncated variance). Each kind gets a verdict: consistent, conservative (``S`` too large:
the errors are smaller than the filter thinks) or optimistic (``S`` too small), with the
likely cause for its kind (:func:`likely_cause`). The measurement sigma floor is the ``f`` [rad or the unit of
the kind] that, added in quadrature to every ``R``, brings the mean NIS to ``dim``.

The input is the ``updates`` table of :class:`polins.fusion.FusionResult` with its
``innovation`` and ``innovation_var`` columns (:class:`polins.fusion.items.UpdateRecord`).
"""

from __future__ import annotations

import math
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
    n_eff : float
        Effective number of independent NIS samples (:func:`effective_samples`).
    nis_expected : float
        Expected mean NIS: ``dim``, less under a gate (:func:`nis_mean_band`).
    """

    kind: str
    n: int
    dim: int
    nis_mean: float
    nis_band: tuple[float, float]
    autocorr: FloatArray
    autocorr_band: float
    sigma_floor: float
    n_eff: float = math.nan
    nis_expected: float = math.nan

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
        return nis_verdict(self.nis_mean, self.nis_band)

    @property
    def cause(self) -> str:
        """The likely cause of an inconsistent mean NIS for this kind ('' when consistent)."""
        return likely_cause(self.kind, self.verdict)


def nis_verdict(nis_mean: float, band: tuple[float, float]) -> str:
    """``consistent``, ``optimistic: S too small ...`` or ``conservative: S too large ...``."""
    if nis_mean > band[1]:
        return "optimistic: S too small (Q or R too small)"
    if nis_mean < band[0]:
        return "conservative: S too large (Q or R too large)"
    return "consistent"


_CAUSES = {
    ("image", "optimistic"): "the measurement sigma or the IMU noise is too small for this log "
    "(polins tune), or the data hold errors the model lacks (units, time base, camera file)",
    ("image", "conservative"): "the measurement sigma or the IMU noise is larger than this "
    "log's errors (polins tune lowers it)",
    ("pseudo", "optimistic"): "the vehicle slips, rolls or vibrates more than the "
    "pseudo-measurement's sigma allows, or the IMU mounting is wrong",
    ("pseudo", "conservative"): "a pseudo-measurement's sigma is an allowance for slip, "
    "vibration and mounting errors larger than this log's (a simulator's no-slip wheels)",
}


def likely_cause(kind: str, verdict: str) -> str:
    """The likely cause of a verdict for a measurement kind (yaw, sun: images; nhc, zupt,
    odometer: pseudo-measurements); '' for a consistent one."""
    side = verdict.split(":")[0]
    if side == "consistent":
        return ""
    return _CAUSES[("image" if kind in ("yaw", "sun") else "pseudo", side)]


def effective_samples(series: FloatArray, *, prob: float = 0.95) -> float:
    """Effective number of independent samples of a series' mean [-].

    ``n / (1 + 2 sum_k rho_k)`` with the sample autocorrelation ``rho_k`` of the centred
    series summed over the lags before it first falls inside the white band
    ``z / sqrt(n)`` (the initial positive sequence); between 1 and ``n``.
    """
    x = np.asarray(series, dtype=float)
    x = x[np.isfinite(x)]
    n = x.size
    if n < 3 or not np.any(x != x[0]):
        return float(max(n, 1))
    x = x - x.mean()
    full = correlate(x, x, mode="full", method="fft")[n - 1 :]
    rho = full[1:] / full[0]
    band = norm.ppf(0.5 + prob / 2) / np.sqrt(n)
    below = np.flatnonzero(rho <= band)
    k = int(below[0]) if below.size else rho.size
    return float(np.clip(n / (1.0 + 2.0 * rho[:k].sum()), 1.0, n))


def _gaussian_n_eff(white_nu: FloatArray, prob: float) -> float:
    """``n / (1 + 2 sum_k rho_k^2)`` from the whitened innovations' autocorrelation ``rho_k``
    (the squares of Gaussians correlated ``rho`` are correlated ``rho^2``), summed while
    ``|rho_k|`` exceeds the white band: robust where a few large NIS hide the correlation
    of the NIS series itself (zero-velocity updates, large at each stop's start)."""
    n = white_nu.shape[0]
    if n < 3:
        return float(max(n, 1))
    rho = autocorrelation(white_nu, n - 1)
    band = norm.ppf(0.5 + prob / 2) / np.sqrt(n)
    below = np.flatnonzero(np.abs(rho) <= band)
    k = int(below[0]) if below.size else rho.size
    return float(np.clip(n / (1.0 + 2.0 * np.sum(rho[:k] ** 2)), 1.0, n))


def nis_mean_band(
    dim: int, n_eff: float, *, prob: float = 0.95, gate_prob: float | None = None
) -> tuple[float, tuple[float, float]]:
    """Expected mean NIS and its ``prob`` band for ``n_eff`` independent updates of ``dim``.

    Under a gate at ``gate_prob`` the accepted NIS follow a chi-square truncated at
    ``c = chi2.ppf(gate_prob, dim)``: mean ``dim F_{dim+2}(c) / F_dim(c)``, second moment
    ``dim (dim + 2) F_{dim+4}(c) / F_dim(c)``; the band is that of a scaled chi-square with
    the same mean and variance (without a gate: ``chi2.ppf(q, n_eff dim) / n_eff``).
    """
    c = np.inf if gate_prob is None else float(chi2.ppf(gate_prob, dim))
    f0 = chi2.cdf(c, dim)
    mean = dim * chi2.cdf(c, dim + 2) / f0
    var = dim * (dim + 2) * chi2.cdf(c, dim + 4) / f0 - mean**2
    k = 2.0 * mean**2 * n_eff / var
    a = 1.0 - prob
    lo, hi = mean * chi2.ppf([a / 2, 1 - a / 2], k) / k
    return float(mean), (float(lo), float(hi))


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
    updates: pd.DataFrame,
    *,
    max_lag: int = 10,
    prob: float = 0.95,
    gate_prob: float | None = None,
) -> dict[str, InnovationStats]:
    """Innovation statistics per measurement kind of a fusion's ``updates`` table.

    Parameters
    ----------
    updates : DataFrame
        ``FusionResult.updates`` (ESKF): ``name, dim, accepted, innovation, innovation_var``.
        A gate truncates the NIS (its rejections are left out): give its ``gate_prob`` so
        the band is the truncated chi-square's, or judge the noise model on a run without
        one.
    max_lag : int
        Largest autocorrelation lag [updates] reported.
    prob : float
        Probability of the band of the mean NIS and of the whiteness band.
    gate_prob : float, optional
        The run's gate probability (None: no gate).

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
        white_nu = whitened(nu, S)
        n_eff = min(effective_samples(nis, prob=prob), _gaussian_n_eff(white_nu, prob))
        expected, band = nis_mean_band(dim, n_eff, prob=prob, gate_prob=gate_prob)
        out[str(kind)] = InnovationStats(
            kind=str(kind),
            n=n,
            dim=dim,
            nis_mean=float(nis.mean()),
            nis_band=band,
            autocorr=autocorrelation(white_nu, max_lag),
            autocorr_band=float(norm.ppf(1 - a / 2) / np.sqrt(n)),
            sigma_floor=sigma_floor(nu, S),
            n_eff=n_eff,
            nis_expected=expected,
        )
    return out


def stats_table(stats: dict[str, InnovationStats]) -> pd.DataFrame:
    """The statistics as a table, one row per kind (for printing and reports)."""
    return pd.DataFrame(
        [
            {
                "kind": s.kind,
                "n": s.n,
                "n_eff": s.n_eff,
                "NIS mean": s.nis_mean,
                "NIS band": f"{s.nis_band[0]:.3g} .. {s.nis_band[1]:.3g}",
                "lag-1 autocorr": float(s.autocorr[0]) if s.autocorr.size else np.nan,
                "white band": s.autocorr_band,
                "sigma floor": s.sigma_floor,
                "verdict": s.verdict,
                "likely cause": s.cause,
            }
            for s in stats.values()
        ]
    )


__all__ = [
    "InnovationStats",
    "autocorrelation",
    "effective_samples",
    "innovation_arrays",
    "innovation_stats",
    "likely_cause",
    "nis_mean_band",
    "nis_verdict",
    "sigma_floor",
    "stats_table",
    "whitened",
]
