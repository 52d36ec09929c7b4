"""The speed-accuracy benchmark's reference m50 (``benchmarks/bench_speed_accuracy.local_m50``).

Every m50 the benchmark scores is compared with this one number, so it is tested against known
answers: exact on a logistic, negligible bias on the skewed transition of a noisy flux threshold,
an error bar that matches its scatter, and a binned reference that does not have these properties.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import brentq
from scipy.special import expit, ndtr

from conftest import load_benchmark


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("bench_speed_accuracy")


M50 = 25.3941


def flux_probit(m, s=0.077):
    """A noisy flux threshold: Phi((F / F50 - 1) / s), skewed in magnitude (the narrow pool's s)."""
    return ndtr((10 ** (-0.4 * (np.asarray(m) - M50)) - 1.0) / s)


def test_exact_on_a_logistic_and_unbiased_on_a_skewed_transition(bench):
    """Fitted to a curve's own probabilities (the limit of infinite data) the local fit returns m50:
    exactly for a logistic (linear in logit, inside every degree), and within 0.05 mmag for the skewed
    flux-threshold shape, where the 0.05-mag binned m50 of the same curve is off by about 0.5 mmag."""
    m = np.linspace(24.0, 26.8, 280_001)
    logistic = expit(-(m - M50) / 0.045)
    got, _ = bench.local_m50(m, logistic, 25.39, half_width=0.2)
    assert got == pytest.approx(M50, abs=1e-7)

    p = flux_probit(m)
    truth = brentq(lambda x: float(flux_probit(x)) - 0.5, 25.3, 25.5)
    got, _ = bench.local_m50(m, p, 25.395, half_width=0.224)
    assert abs(got - truth) < 5e-5
    # the binned reference of the same curve: bin averages (fine sampling), linear interpolation
    from comest_bayes.ratios import binned as R
    edges = R.magnitude_edges(24.0, 26.8, 0.05)
    idx = np.clip(np.searchsorted(edges, m, side="right") - 1, 0, len(edges) - 2)
    avg = np.bincount(idx, weights=p, minlength=len(edges) - 1) / np.bincount(idx, minlength=len(edges) - 1)
    binned = float(R.first_crossing(0.5 * (edges[:-1] + edges[1:]), avg, 0.5))
    assert 3e-4 < binned - truth < 7e-4


def test_its_error_bar_matches_its_scatter(bench):
    """Over 40 seeded pools of 100,000 outcomes of the flux threshold the delta-method sd agrees with the
    empirical scatter to 25% (the sd of a 40-sample sd is about 11%, so this is over 2 sigma), the mean
    error is within 3 standard errors of zero, and every error is within 4 of its own sd."""
    rng = np.random.default_rng(20261128)
    truth = brentq(lambda x: float(flux_probit(x)) - 0.5, 25.3, 25.5)
    errs, sds = [], []
    for _ in range(40):
        m = rng.uniform(24.0, 26.8, 100_000)
        d = rng.random(m.size) < flux_probit(m)
        got, sd = bench.local_m50(m, d, 25.395, half_width=0.224)
        errs.append(got - truth)
        sds.append(sd)
    errs, sds = np.array(errs), np.array(sds)
    assert np.all(np.abs(errs) < 4 * sds)
    assert abs(errs.mean()) < 3 * errs.std(ddof=1) / np.sqrt(errs.size)
    assert np.std(errs, ddof=1) == pytest.approx(np.median(sds), rel=0.25)


def test_degenerate_windows_give_nan_not_a_number_that_looks_right(bench):
    """All detected, too few outcomes in the window, or outcomes perfectly separated (the likelihood
    has no maximum): no root to report."""
    m = np.linspace(25.2, 25.6, 1000)
    assert np.isnan(bench.local_m50(m, np.ones(m.size, bool), 25.4, half_width=0.1)[0])
    assert np.isnan(bench.local_m50(m[:20], np.arange(20) % 2 == 0, 25.4, half_width=0.1)[0])
    with np.errstate(all="ignore"):
        assert np.isnan(bench.local_m50(m, m < 25.41, 25.4, half_width=0.1)[0])
