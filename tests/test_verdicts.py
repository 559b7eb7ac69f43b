"""Verdicts of the consistency figures: NIS bands from the effective number of samples and the gate, RMS(err/sigma) bands."""

import numpy as np
import pandas as pd
import pytest
from scipy.signal import lfilter
from scipy.stats import chi2

from polins.evaluation import format_summary, summarize
from polins.evaluation.reference import normalized_error_stats
from polins.tuning.innovations import effective_samples, nis_mean_band, nis_verdict


def _ar1(rng, n, rho, size=()):
    """Unit-variance Gaussian AR(1) series, shape ``(*size, n)``."""
    x = lfilter([np.sqrt(1 - rho**2)], [1, -rho], rng.standard_normal((*size, n)), axis=-1)
    return x


def test_without_a_gate_the_band_is_the_chi_square_band():
    mean, (lo, hi) = nis_mean_band(2, 500.0)
    assert mean == 2.0
    np.testing.assert_allclose([lo, hi], chi2.ppf([0.025, 0.975], 1000) / 500, rtol=1e-12)


@pytest.mark.parametrize("dim", [1, 2])
def test_a_gate_lowers_the_expected_nis_as_a_truncated_chi_square(dim):
    rng = np.random.default_rng(dim)
    nis = chi2.rvs(dim, size=2_000_000, random_state=rng)
    kept = nis[nis <= chi2.ppf(0.9973, dim)]
    mean, (lo, hi) = nis_mean_band(dim, 400.0, gate_prob=0.9973)
    assert mean == pytest.approx(kept.mean(), rel=2e-3) and mean < dim
    # the band of 400 independent accepted updates covers 95 % of their means
    means = kept[: 400 * 2000].reshape(2000, 400).mean(axis=1)
    assert 0.93 < np.mean((means >= lo) & (means <= hi)) < 0.97


def test_effective_samples_of_correlated_innovations():
    rng = np.random.default_rng(3)
    assert effective_samples(rng.standard_normal(20_000) ** 2) > 15_000  # white: about n
    rho, n = 0.9, 20_000
    squares = _ar1(rng, n, rho) ** 2  # corr(x_i^2, x_j^2) = rho^(2|i-j|)
    expected = n * (1 - rho**2) / (1 + rho**2)
    assert effective_samples(squares) == pytest.approx(expected, rel=0.2)


def test_the_band_of_autocorrelated_nis_covers_its_mean():
    """NHC-like innovations (lag-1 autocorrelation 0.9): the n_eff band holds 95 % of the
    means of consistent runs, the band of n independent updates far fewer."""
    rng = np.random.default_rng(4)
    runs = _ar1(rng, 2000, 0.9, size=(300,)) ** 2
    inside = naive = 0
    for nis in runs:
        _, (lo, hi) = nis_mean_band(1, effective_samples(nis))
        inside += lo <= nis.mean() <= hi
        lo, hi = chi2.ppf([0.025, 0.975], nis.size) / nis.size
        naive += lo <= nis.mean() <= hi
    assert 0.88 < inside / len(runs) <= 1.0
    assert naive / len(runs) < 0.75


def test_rms_normalized_verdicts():
    rng = np.random.default_rng(5)
    z = _ar1(rng, 60_000, 0.999)  # a slowly drifting error at the IMU rate
    st = normalized_error_stats(z)
    assert st["n_eff"] < 600 and st["verdict"] == "consistent"
    assert normalized_error_stats(3.0 * z)["verdict"].startswith("optimistic")
    assert normalized_error_stats(0.2 * z)["verdict"].startswith("conservative")


def _measurements(nis):
    n = len(nis)
    return pd.DataFrame({"t": np.arange(n) * 0.2, "ok": True, "accepted": True, "nis": nis,
                         "nis_dof": 1, "reason": "", "update_reason": ""})  # fmt: skip


@pytest.mark.parametrize(("scale", "word"), [(1.0, "consistent"), (0.7, "conservative"),
                                             (1.6, "optimistic")])  # fmt: skip
def test_every_printed_nis_carries_its_verdict(scale, word):
    rng = np.random.default_rng(6)
    nis = scale * chi2.rvs(1, size=1500, random_state=rng)
    nis = nis[nis <= chi2.ppf(0.9973, 1)]  # what the gate lets through
    solution = pd.DataFrame({"t": [0.0], "heading_deg": [0.0]})
    events = pd.DataFrame(columns=["t", "kind", "detail"])
    summary = summarize(solution, _measurements(nis), events, gate_prob=0.9973)
    yaw = summary["nis"]["yaw"]
    assert yaw["verdict"].startswith(word) and yaw["expected"] == pytest.approx(0.973, abs=1e-3)
    text = format_summary(summary)
    line = next(x for x in text.splitlines() if x.startswith("NIS yaw"))
    assert line.endswith(yaw["verdict"]) and f"of {len(nis)})" in line
    assert ("likely cause" in text) == (word != "consistent")


def test_verdict_words():
    assert nis_verdict(1.0, (0.9, 1.1)) == "consistent"
    assert nis_verdict(0.7, (0.9, 1.1)).startswith("conservative")
    assert nis_verdict(1.7, (0.9, 1.1)).startswith("optimistic")


def test_innovation_stats_count_the_independent_updates():
    """Innovations with lag-1 autocorrelation 0.9 (an NHC at the IMU rate): n_eff from their
    whitened autocorrelation, n (1 - rho^2) / (1 + rho^2), and a consistent verdict."""
    from polins.tuning import innovation_stats

    rng = np.random.default_rng(8)
    n, rho = 6000, 0.9
    nu = 0.02 * _ar1(rng, n, rho)
    updates = pd.DataFrame({"t": np.arange(n) * 0.005, "name": "nhc", "dim": 1,
                            "accepted": True, "innovation": [[v] for v in nu],
                            "innovation_var": [[0.02**2]] * n})  # fmt: skip
    st = innovation_stats(updates)["nhc"]
    assert st.n == n and st.n_eff == pytest.approx(n * (1 - rho**2) / (1 + rho**2), rel=0.25)
    assert st.verdict == "consistent" and st.cause == ""
    assert not st.white and st.autocorr[0] == pytest.approx(rho, abs=0.03)
