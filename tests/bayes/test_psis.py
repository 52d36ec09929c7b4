"""PSIS of one vector of log ratios: against arviz (the reference implementation) and known tails."""

import warnings

import numpy as np
import pytest

from comest_bayes.bayes.psis import gpd_fit, psis_log_weights


@pytest.mark.parametrize("size, scale", [(1000, 0.05), (2000, 0.3), (2000, 1.0), (4000, 2.0), (8000, 1.5)])
def test_matches_arviz(size, scale):
    az = pytest.importorskip("arviz")
    rng = np.random.default_rng(size)
    lw = rng.standard_normal(size) * scale + rng.standard_t(3, size) * scale * 0.3
    lw[::97] = -np.inf  # draws of zero weight count in the tail length, as in arviz
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref, ref_k = az.psislw(lw[None].copy(), reff=1.0)
    ours, k = psis_log_weights(lw)
    ref = np.asarray(ref).ravel()
    assert np.array_equal(np.isfinite(ours), np.isfinite(ref))
    fin = np.isfinite(ref)
    # the same algorithm: equal to rounding
    np.testing.assert_allclose(ours[fin], ref[fin], atol=1e-10)
    assert k == pytest.approx(float(np.ravel(ref_k)[0]), abs=1e-10)
    assert np.logaddexp.reduce(ours[fin]) == pytest.approx(0.0, abs=1e-12)


def test_gpd_fit_recovers_a_known_shape():
    # 4000 draws of a generalized Pareto with shape 0.5, scale 2: the estimate (pulled towards 0.5 by a
    # prior of weight 10, which here cannot bias it) lies within 4 standard errors (~0.02 each) of the truth
    rng = np.random.default_rng(3)
    shape, sigma = 0.5, 2.0
    u = rng.random(4000)
    x = np.sort(sigma * np.expm1(-shape * np.log1p(-u)) / shape)
    k, s = gpd_fit(x)
    assert k == pytest.approx(shape, abs=0.08)
    assert s == pytest.approx(sigma, rel=0.1)


def test_light_tails_have_small_khat_and_heavy_tails_large():
    rng = np.random.default_rng(4)
    _, k_light = psis_log_weights(0.1 * rng.standard_normal(4000))
    _, k_heavy = psis_log_weights(3.0 * rng.standard_normal(4000))  # log-normal weights of sd 3: very heavy
    assert k_light < 0.3
    assert k_heavy > 0.7


def test_too_few_draws_give_infinite_khat_and_plain_weights():
    lw, k = psis_log_weights(np.array([0.0, -1.0, -2.0, -0.5]))
    assert k == np.inf
    np.testing.assert_allclose(np.exp(lw).sum(), 1.0)
