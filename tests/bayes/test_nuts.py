"""Tests of comest_bayes.bayes.nuts: NUTS draws against analytic posteriors, and its place in ``fit``.

The targets are small JAX densities with known moments, given through the ``log_density`` contract of
:meth:`comest_bayes.bayes.model.CompletenessModel.log_density`; the last tests use the real model.
Every random draw has a fixed seed.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import digamma, polygamma

from comest_bayes.bayes import inference
from comest_bayes.bayes.inference import LaplaceResult, fit, importance_posterior
from comest_bayes.bayes.nuts import RHAT_MAX, nuts_posterior, supports_nuts
from comest_bayes.errors import InputError
from comest_bayes.jaxnum import jnp


def _gaussian(static, theta, mean, prec):
    d = theta - mean
    return -0.5 * d @ prec @ d


def _log_gamma(static, theta, shape):
    """log density of theta = log X with X ~ Gamma(shape, 1), plus an independent N(0, 1) coordinate."""
    return shape * theta[0] - jnp.exp(theta[0]) - 0.5 * theta[1] ** 2


class Target:
    """A model-like target: names and log_density only (all NUTS needs)."""

    def __init__(self, fn, args, names):
        self._fn, self._args, self.names = fn, args, list(names)
        self.ndim = len(names)

    def log_density(self):
        return self._fn, "target", self._args


@pytest.fixture(scope="module")
def correlated():
    mean = np.array([1.0, -2.0, 0.5])
    sd = np.array([0.1, 2.0, 1.0])
    corr = np.array([[1.0, 0.9, 0.0], [0.9, 1.0, -0.3], [0.0, -0.3, 1.0]])  # positive definite (det 0.1)
    cov = corr * np.outer(sd, sd)
    target = Target(_gaussian, (jnp.asarray(mean), jnp.asarray(np.linalg.inv(cov))), ["a", "b", "c"])
    # a wrong guess (shifted by 1 sd, covariance doubled and decorrelated): the sampler must not lean on it
    guess = LaplaceResult(mean=mean + sd, cov=np.diag(2.0 * sd ** 2), ok=True, message="guess")
    return target, mean, cov, guess


def test_nuts_recovers_a_correlated_gaussian_from_a_wrong_guess(correlated):
    # ESS >= 400 per parameter: a mean's Monte Carlo error is <= 0.05 sd and an sd's <= 3.5%; tolerances 0.2 sd
    # and 12% are ~4 such errors.
    target, mean, cov, guess = correlated
    post = nuts_posterior(target, guess, seed=3, min_ess=400)
    d = post.diagnostics
    assert d.converged and d.divergences == 0 and d.rhat.max() <= RHAT_MAX and d.ess.min() >= 400
    sd = np.sqrt(np.diag(cov))
    assert np.all(np.abs(post.samples.mean(axis=0) - mean) < 0.2 * sd)
    np.testing.assert_allclose(post.samples.std(axis=0), sd, rtol=0.12)
    np.testing.assert_allclose(np.corrcoef(post.samples.T)[0, 1], 0.9, atol=0.03)
    # layout: (draws, chains, D) chain, step-major flattened samples, log posterior of every kept draw
    assert post.chain.shape == (d.ndraws, d.nchains, 3)
    np.testing.assert_array_equal(post.samples[: d.nchains], post.chain[0])
    lp = np.array([float(_gaussian(None, jnp.asarray(x), *target._args)) for x in post.chain[:3, 0]])
    np.testing.assert_allclose(post.log_prob[:3, 0], lp, rtol=1e-10, atol=1e-10)
    assert d.to_dict()["method"] == "nuts"


def test_nuts_is_reproducible_from_its_seed(correlated):
    target, _, _, guess = correlated
    kw = dict(min_ess=100, nwarmup=100, ndraws=50, max_draws=100)  # the short test's compiled programs
    a = nuts_posterior(target, guess, seed=8, **kw)
    b = nuts_posterior(target, guess, seed=8, **kw)
    c = nuts_posterior(target, guess, seed=9, **kw)
    np.testing.assert_array_equal(a.samples, b.samples)
    assert not np.array_equal(a.samples, c.samples)


def test_nuts_follows_a_skewed_posterior_the_laplace_fit_misses():
    # log of a Gamma(2, 1) variable: skewness -0.78, mean digamma(2) = 0.4228 and variance trigamma(2) = 0.6449,
    # while the Laplace fit at the mode (log 2 = 0.693, variance 1/2) is off by 0.34 sd in mean and 12% in sd.
    # Against the exact moments and the 16/50/84% quantiles: at ESS >= 1000 a mean's Monte Carlo error is 0.03 sd,
    # an sd's 2%, and these quantiles' at most 0.06 sd (sqrt(p (1 - p) / ESS) / density); the tolerances are 3-4 of
    # them.  (The 2.5% quantile would carry 0.13 sd of Monte Carlo error in the exponential left tail.)
    shape = 2.0
    target = Target(_log_gamma, (jnp.asarray(shape),), ["log_x", "z"])
    lap = LaplaceResult(mean=np.array([math.log(shape), 0.0]), cov=np.diag([1.0 / shape, 1.0]), ok=True, message="")
    post = nuts_posterior(target, lap, seed=4, min_ess=1000)
    assert post.diagnostics.converged and post.diagnostics.ess.min() >= 1000
    x = post.samples[:, 0]
    sd = math.sqrt(polygamma(1, shape))
    assert abs(x.mean() - digamma(shape)) < 0.1 * sd
    assert abs(x.std() / sd - 1.0) < 0.08
    rng = np.random.default_rng(0)
    exact = np.percentile(np.log(rng.gamma(shape, size=400_000)), [16, 50, 84])
    np.testing.assert_allclose(np.percentile(x, [16, 50, 84]), exact, atol=0.2 * sd)


def test_nuts_reports_a_run_that_falls_short(correlated):
    # 4 chains x 50 draws cannot reach an ESS of 5000: the run must say so, with its numbers, not pass silently
    target, _, _, guess = correlated
    post = nuts_posterior(target, guess, seed=2, min_ess=5000, nwarmup=100, ndraws=50, max_draws=50)
    d = post.diagnostics
    assert not d.converged and d.ndraws == 50 and post.samples.shape == (200, 3)
    assert d.warnings and "NUTS did not converge" in d.warnings[0] and "wanted >= 5000" in d.warnings[0]
    assert d.ess.max() < 5000


def test_nuts_rejects_what_it_cannot_sample(correlated):
    target, _, _, guess = correlated

    class NoDensity:
        names = ["a"]

    assert supports_nuts(target) and not supports_nuts(NoDensity())
    with pytest.raises(InputError, match="log_density"):
        nuts_posterior(NoDensity(), guess, seed=1)
    with pytest.raises(InputError, match="nchains"):
        nuts_posterior(target, guess, seed=1, nchains=1)


# --------------------------------------------------------------------------- with the real model


@pytest.fixture(scope="module")
def real_model():
    from comest_bayes.bayes.model import CompletenessModel
    from comest_bayes.bayes.outcomes import compress_for
    from toy_inference import simulate_real

    cov, det = simulate_real(6000, seed=12)
    data = compress_for("logistic_depth", cov, det, dm=0.02, ddepth=0.05)
    return CompletenessModel("logistic_depth", data)


def test_the_model_density_is_its_log_prob(real_model):
    fn, static, args = real_model.log_density()
    theta = real_model.initial()
    assert float(fn(static, jnp.asarray(theta), *args)) == pytest.approx(real_model.log_prob(theta), rel=1e-12)


def _importance_made_to_fail(first_only: bool, calls: list | None = None):
    """:func:`importance_posterior` whose result fails (k-hat replaced by 0.9): every call, or only the first
    try's (no ``df`` given); ``calls`` collects each call's (df, stream)."""
    def failing(model, lap, **kw):
        if calls is not None:
            calls.append((kw.get("df", 5.0), kw.get("stream", inference.Stream.IMPORTANCE)))
        post = importance_posterior(model, lap, **kw)
        if not (first_only and "df" in kw):
            post.diagnostics.khat, post.diagnostics.converged = 0.9, False
            post.diagnostics.warnings.append("importance sampling from the Laplace approximation: Pareto k-hat = 0.90")
        return post
    return failing


def test_fit_falls_back_from_importance_sampling_to_nuts(real_model, monkeypatch):
    # Importance sampling made to fail (its k-hat replaced by 0.9): fit(sampler="auto") must sample with NUTS,
    # name the failure first in the diagnostics' warnings, and give the importance sampler's intervals (0.15 sd:
    # both Monte Carlo errors are ~0.05 sd at ESS >= 400).
    reference = fit(real_model, seed=5, sampler="importance", min_ess=1000)
    monkeypatch.setattr(inference, "importance_posterior", _importance_made_to_fail(first_only=False))
    res = fit(real_model, seed=5, sampler="auto", min_ess=1000)
    d = res.posterior.diagnostics
    assert d.method == "nuts" and d.converged and d.min_ess == 400
    assert "k-hat = 0.90" in d.warnings[0] and "NUTS" in d.warnings[0]
    # sampler="nuts" asks NUTS directly, to the full min_ess, with no note of a failed importance sampler
    direct = fit(real_model, seed=5, sampler="nuts", min_ess=600)
    assert direct.posterior.diagnostics.min_ess == 600 and direct.posterior.diagnostics.converged
    assert not direct.posterior.diagnostics.warnings
    for post in (res.posterior, direct.posterior):
        for j in range(real_model.ndim):
            sd = reference.posterior.samples[:, j].std()
            np.testing.assert_allclose(np.percentile(post.samples[:, j], [16, 50, 84]),
                                       np.percentile(reference.posterior.samples[:, j], [16, 50, 84]),
                                       atol=0.15 * sd)


def test_fit_tries_heavier_tails_before_nuts(real_model, monkeypatch):
    # The first importance sampler (t with 5 degrees of freedom) made to fail: fit(sampler="auto") must try a t
    # with IS_RETRY_DF degrees of freedom from its own random stream, keep it when it passes (no NUTS), say so
    # first in the warnings, and give the first sampler's intervals (0.15 sd, as above).
    reference = fit(real_model, seed=5, sampler="importance", min_ess=1000)
    seen = []
    monkeypatch.setattr(inference, "importance_posterior", _importance_made_to_fail(first_only=True, calls=seen))
    res = fit(real_model, seed=5, sampler="auto", min_ess=1000)
    d = res.posterior.diagnostics
    assert seen == [(5.0, "importance"), (inference.IS_RETRY_DF, "importance-tails")]
    assert d.method == "importance" and d.converged and d.df == inference.IS_RETRY_DF
    assert "k-hat = 0.90" in d.warnings[0] and "sampled again" in d.warnings[0]
    assert not np.array_equal(res.posterior.samples, reference.posterior.samples)  # other draws
    for j in range(real_model.ndim):
        sd = reference.posterior.samples[:, j].std()
        np.testing.assert_allclose(np.percentile(res.posterior.samples[:, j], [16, 50, 84]),
                                   np.percentile(reference.posterior.samples[:, j], [16, 50, 84]), atol=0.15 * sd)


def test_a_model_without_a_traceable_density_falls_back_to_emcee(monkeypatch):
    from toy_inference import toy_model

    model = toy_model(4000, seed=2)
    assert not supports_nuts(model)

    monkeypatch.setattr(inference, "importance_posterior", _importance_made_to_fail(first_only=False))
    res = fit(model, seed=5, sampler="auto", min_ess=200, chunk=250)
    assert res.posterior.diagnostics.to_dict()["method"] == "emcee"
    assert "emcee instead" in res.posterior.diagnostics.warnings[0]
