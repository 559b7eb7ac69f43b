"""Allan deviation of inertial-sensor rate data and the fit of its standard noise terms.

The overlapping Allan deviation (``allantools.oadev``) of a static recording of rate data
(gyro [rad/s] or accelerometer [m/s^2]) is fitted with the three standard noise terms of
IEEE Std 952-1997 (Annex C) and El-Sheimy, Hou & Niu, "Analysis and modeling of inertial
sensors using Allan variance", IEEE Trans. Instrum. Meas. 57 (1), 2008::

    AVAR(tau) = N^2 / tau  +  (2 ln 2 / pi) B^2  +  K^2 tau / 3

- ``N``: white-noise density (angle / velocity random walk) [unit * sqrt(s)], e.g.
  [rad/s * sqrt(s)] = [rad/sqrt(s)], read at ``tau = 1 s`` on the slope -1/2 line;
- ``B``: bias instability (flicker floor, slope 0) [unit], ADEV minimum ~ 0.664 B;
- ``K``: bias (rate) random walk [unit/sqrt(s)], read at ``tau = 3 s`` on the slope +1/2
  line.

The three coefficients ``N^2, B^2, K^2`` enter linearly, so the fit is a non-negative
weighted least-squares fit in the Allan variance (``scipy.optimize.nnls``), iteratively
re-weighted: each point's variance is ``2 AVAR_model^2 / edf`` with Greenhall's equivalent
degrees of freedom (``allantools.edf_greenhall``) for the noise type that dominates the
model at that ``tau``. Weighting by relative error makes it the weighted log-log fit of the
standard slopes. Confidence intervals of the coefficients come from the fit's covariance;
a term whose lower bound is zero is *not identified* by the recording, and only its upper
bound is meaningful.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import allantools
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import nnls
from scipy.stats import norm

from polins.errors import UserInputError

FloatArray = NDArray[np.float64]

FLICKER_FACTOR = np.sqrt(2.0 * np.log(2.0) / np.pi)  # ADEV floor = 0.664 B
CI_LEVEL = 0.95  # confidence level of the fitted coefficients
ERRORBAR_LEVEL = 0.683  # confidence level of the Allan deviation error bars (1 sigma)
_ALPHA = (0, -1, -2)  # power-law alpha of white FM, flicker FM, random-walk FM (N, B, K)
_MIN_SAMPLES = 64


@dataclass(frozen=True)
class AllanCurve:
    """Overlapping Allan deviation of one or several pooled series of rate samples.

    Attributes
    ----------
    tau : ndarray
        Averaging times [s].
    adev : ndarray
        Allan deviation [unit of the data], pooled over the series (Allan variances
        averaged with their degrees of freedom as weights).
    adev_lo, adev_hi : ndarray
        Error bars of ``adev`` at ``ERRORBAR_LEVEL`` (chi-square with ``edf``) [unit].
    edf : ndarray
        Equivalent degrees of freedom of each pooled Allan variance [-].
    n_samples : tuple of int
        Length of each pooled series [samples].
    """

    tau: FloatArray
    adev: FloatArray
    adev_lo: FloatArray
    adev_hi: FloatArray
    edf: FloatArray
    n_samples: tuple[int, ...]


@dataclass(frozen=True)
class NoiseTerms:
    """The three standard noise terms fitted to an Allan deviation, with confidence intervals.

    Units for a gyro / an accelerometer: ``white`` [rad/sqrt(s)] / [m/s/sqrt(s)],
    ``bias_instability`` [rad/s] / [m/s^2], ``random_walk`` [rad/s/sqrt(s)] / [m/s^2/sqrt(s)].
    Each ``*_ci`` is the ``(low, high)`` interval at ``CI_LEVEL``; a low end of 0 means
    the recording does not identify the term (only the high end is informative).
    ``tau_floor`` [s] is where the fitted Allan deviation is smallest (within the data's
    ``tau`` range): the averaging time beyond which the bias starts to wander.
    """

    white: float
    white_ci: tuple[float, float]
    bias_instability: float
    bias_instability_ci: tuple[float, float]
    random_walk: float
    random_walk_ci: tuple[float, float]
    tau_floor: float

    @property
    def identified(self) -> dict[str, bool]:
        """Which terms the recording identifies (lower confidence bound above zero)."""
        return {
            "white": self.white_ci[0] > 0,
            "bias_instability": self.bias_instability_ci[0] > 0,
            "random_walk": self.random_walk_ci[0] > 0,
        }

    def adev(self, tau: FloatArray) -> FloatArray:
        """The fitted model's Allan deviation at ``tau`` [s], in the data's unit."""
        return np.sqrt(self.avar_terms(tau).sum(axis=0))

    def avar_terms(self, tau: FloatArray) -> FloatArray:
        """The model's Allan variance per term, shape ``(3, len(tau))``: white, flicker, RW."""
        tau = np.asarray(tau, dtype=float)
        return np.stack(
            [
                self.white**2 / tau,
                np.full_like(tau, (FLICKER_FACTOR * self.bias_instability) ** 2),
                self.random_walk**2 * tau / 3.0,
            ]
        )


def _m_values(n: int, points_per_decade: int) -> NDArray[np.int_]:
    """Cluster sizes from 1 to n // 4, log-spaced (at least 3 clusters of independent data)."""
    m_max = max(n // 4, 1)
    m = np.round(np.logspace(0, np.log10(m_max), int(np.log10(m_max) * points_per_decade) + 1))
    return np.unique(m.astype(int))


def _check_series(series: Sequence[FloatArray]) -> list[FloatArray]:
    out = [np.asarray(s, dtype=float) for s in series]
    if not out:
        raise UserInputError("no data series given for the Allan deviation")
    for s in out:
        if s.ndim != 1 or len(s) < _MIN_SAMPLES:
            raise UserInputError(
                f"each static series needs at least {_MIN_SAMPLES} samples in one column"
                f" (got shape {s.shape})"
            )
        if not np.all(np.isfinite(s)):
            raise UserInputError("the static recording holds NaN or infinite samples")
    return out


def _edf(alpha: FloatArray, m: int, n: int) -> float:
    return float(allantools.edf_greenhall(alpha=int(alpha), d=2, m=m, N=n + 1, overlapping=True))


def allan_deviation(
    series: Sequence[FloatArray],
    rate_hz: float,
    *,
    points_per_decade: int = 5,
    alpha: Sequence[int] | NDArray[np.int_] | None = None,
) -> AllanCurve:
    """Overlapping Allan deviation of rate samples, pooled over independent series.

    Parameters
    ----------
    series : sequence of ndarray
        One or more 1-D series of rate samples [unit], e.g. the three axes of a sensor or
        several static segments; each is analysed on its own (no jump between segments
        enters) and their Allan variances are averaged with their degrees of freedom.
    rate_hz : float
        Sample rate [Hz], the same for all series.
    points_per_decade : int
        Density of the log-spaced averaging times (``tau = m / rate_hz``).
    alpha : sequence of int, optional
        Power-law noise type per averaging time for the degrees of freedom (0 white,
        -1 flicker, -2 random walk of the rate); default white.

    Returns
    -------
    AllanCurve
    """
    data = _check_series(series)
    if not rate_hz > 0:
        raise UserInputError(f"sample rate must be positive, got {rate_hz} Hz")
    m_all = _m_values(max(len(s) for s in data), points_per_decade)
    alphas = np.zeros(len(m_all)) if alpha is None else np.asarray(alpha, dtype=float)
    if alphas.shape != m_all.shape:
        raise UserInputError(f"alpha needs {len(m_all)} values, one per averaging time")
    sum_w = np.zeros(len(m_all))
    sum_wv = np.zeros(len(m_all))
    for s in data:
        usable = m_all <= len(s) // 4
        taus = m_all[usable] / rate_hz
        tau_out, dev, _, _ = allantools.oadev(s, rate=rate_hz, data_type="freq", taus=taus)
        m_out = np.round(np.asarray(tau_out) * rate_hz).astype(int)
        for mi, d in zip(m_out, dev, strict=True):
            k = int(np.searchsorted(m_all, mi))
            w = _edf(alphas[k], int(mi), len(s))
            sum_w[k] += w
            sum_wv[k] += w * d**2
    keep = sum_w > 0
    tau = m_all[keep] / rate_hz
    edf = sum_w[keep]
    avar = sum_wv[keep] / edf
    adev = np.sqrt(avar)
    bars = np.array(
        [
            allantools.confidence_interval(d, e, ci=ERRORBAR_LEVEL)
            for d, e in zip(adev, edf, strict=True)
        ]
    )
    return AllanCurve(
        tau=tau,
        adev=adev,
        adev_lo=bars[:, 0],
        adev_hi=bars[:, 1],
        edf=edf,
        n_samples=tuple(len(s) for s in data),
    )


def _weighted_nnls(
    design: FloatArray, avar: FloatArray, edf: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Iteratively re-weighted NNLS of ``avar ~ design @ c``; returns c and its covariance."""
    model = avar.copy()
    coef = np.zeros(design.shape[1])
    for _ in range(8):
        w = np.sqrt(edf / 2.0) / np.maximum(model, 1e-300)  # 1 / std of each AVAR estimate
        fitted, _ = nnls(design * w[:, None], avar * w)
        coef = np.asarray(fitted, dtype=float)
        new = design @ coef
        if np.allclose(new, model, rtol=1e-6):
            break
        model = np.maximum(new, 1e-3 * avar)
    w = np.sqrt(edf / 2.0) / np.maximum(design @ coef, 1e-300)
    weighted = design * w[:, None]
    cov = np.asarray(np.linalg.pinv(weighted.T @ weighted), dtype=float)
    return coef, cov


def _interval(c: float, sigma: float, z: float) -> tuple[float, float]:
    """Interval of sqrt(c) from c +- z sigma (c a variance coefficient), clipped at 0."""
    return (float(np.sqrt(max(c - z * sigma, 0.0))), float(np.sqrt(max(c + z * sigma, 0.0))))


def fit_noise_terms(curve: AllanCurve, *, points_per_decade: int = 5) -> NoiseTerms:
    """Fit white noise, bias instability and random walk to an Allan deviation.

    Parameters
    ----------
    curve : AllanCurve
        From :func:`allan_deviation` (its ``edf`` weights the fit).
    points_per_decade : int
        Density of the curve's averaging times. Averaging times closer than about half a
        decade share data, so their errors correlate; the covariance of the fit is scaled
        as if two points per decade were independent (``sqrt(points_per_decade / 2)`` on
        the standard errors; checked by Monte Carlo in ``tests/test_tuning.py``).

    Returns
    -------
    NoiseTerms
        Point estimates (non-negative least squares) with ``CI_LEVEL`` intervals from the
        covariance of the fit of all three terms.
    """
    tau = curve.tau
    design = np.column_stack([1.0 / tau, np.full_like(tau, FLICKER_FACTOR**2), tau / 3.0])
    coef, cov = _weighted_nnls(design, curve.adev**2, curve.edf)
    sigma = np.sqrt(np.clip(np.diag(cov), 0.0, None) * max(points_per_decade / 2.0, 1.0))
    z = float(norm.ppf(0.5 + CI_LEVEL / 2.0))
    n, b, k = np.sqrt(coef)
    fitted = NoiseTerms(
        white=float(n),
        white_ci=_interval(coef[0], sigma[0], z),
        bias_instability=float(b),
        bias_instability_ci=_interval(coef[1], sigma[1], z),
        random_walk=float(k),
        random_walk_ci=_interval(coef[2], sigma[2], z),
        tau_floor=0.0,
    )
    grid = np.geomspace(tau[0], tau[-1], 400)
    tau_floor = float(grid[np.argmin(fitted.adev(grid))])
    return NoiseTerms(**{**fitted.__dict__, "tau_floor": tau_floor})


def fit_allan(
    series: Sequence[FloatArray], rate_hz: float, *, points_per_decade: int = 5
) -> tuple[AllanCurve, NoiseTerms]:
    """Allan deviation of pooled series and its noise-term fit, with noise-aware error bars.

    A first fit with white-noise degrees of freedom finds which term dominates at each
    ``tau``; the Allan deviation's degrees of freedom are then recomputed for that noise
    type (Greenhall) and the terms refitted.

    Parameters
    ----------
    series : sequence of ndarray
        Rate samples [unit], see :func:`allan_deviation`.
    rate_hz : float
        Sample rate [Hz].
    points_per_decade : int
        Density of the averaging times.

    Returns
    -------
    curve : AllanCurve
    terms : NoiseTerms
    """
    curve = allan_deviation(series, rate_hz, points_per_decade=points_per_decade)
    terms = fit_noise_terms(curve, points_per_decade=points_per_decade)
    dominant = np.argmax(terms.avar_terms(curve.tau), axis=0)
    m_all = _m_values(max(curve.n_samples), points_per_decade)
    alpha = np.zeros(len(m_all), dtype=int)
    idx = np.searchsorted(m_all, np.round(curve.tau * rate_hz).astype(int))
    alpha[idx] = np.asarray(_ALPHA)[dominant]
    if len(idx) < len(m_all):  # averaging times no series reached: keep the last type
        alpha[idx[-1] + 1 :] = alpha[idx[-1]]
    curve = allan_deviation(series, rate_hz, points_per_decade=points_per_decade, alpha=alpha)
    return curve, fit_noise_terms(curve, points_per_decade=points_per_decade)


__all__ = [
    "CI_LEVEL",
    "ERRORBAR_LEVEL",
    "FLICKER_FACTOR",
    "AllanCurve",
    "NoiseTerms",
    "allan_deviation",
    "fit_allan",
    "fit_noise_terms",
]
