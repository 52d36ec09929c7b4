"""Likelihood of the Bayesian completeness model: numerics, compression, covariates, stability."""

from __future__ import annotations

import math
import warnings

import jax
import jax.numpy as jnp
import mpmath
import numpy as np
import pytest
from astropy.table import Table
from scipy import integrate, optimize, special, stats

from comest_bayes.errors import ConfigError, InputError
from comest_bayes.bayes.model import TRACE_COUNT, CompletenessModel
from comest_bayes.bayes.outcomes import Covariates, compress, compress_for, covariates_from_outcomes, uncompressed
from comest_bayes.bayes.links import link_logs, logistic_mixture_logs, mixture_logs
from comest_bayes.bayes.bases import smooth_basis
from comest_bayes.bayes.spec import ModelSpec

LINKS = ("logistic", "probit", "pritchet")


# --------------------------------------------------------------------------- helpers

def synthetic(n, seed, *, m50=24.0, w=0.2, A=0.95, floor=0.01, beta_depth=1.0, c10=0.0, mrange=(20.0, 27.0)):
    """Outcomes drawn from the logistic model with known parameters (depth follows u, plus scatter)."""
    rng = np.random.default_rng(seed)
    m = rng.uniform(*mrange, n)
    u = rng.uniform(-1, 1, n)
    v = rng.uniform(-1, 1, n)
    depth = 0.3 * u - 0.2 * v ** 2 + rng.normal(0.0, 0.05, n)
    cov = Covariates(m, depth, u, v, np.zeros(n))
    field = m50 + beta_depth * depth + c10 * u
    f = floor + (A - floor) * special.expit((field - m) / w)
    return cov, rng.uniform(size=n) < f


def numpy_logistic_loglik(m, y, m50, w, A, floor):
    f = floor + (A - floor) / (1.0 + np.exp(-(m50 - m) / w))
    return float(np.sum(np.where(y, np.log(f), np.log1p(-f))))


def mp_link(z, link):
    """log g and log(1 - g) with 60 digits."""
    mpmath.mp.dps = 60
    z = mpmath.mpf(z)
    if link == "logistic":
        g, h = 1 / (1 + mpmath.exp(-z)), 1 / (1 + mpmath.exp(z))
    elif link == "probit":
        g, h = mpmath.ncdf(z), mpmath.ncdf(-z)
    else:
        r = mpmath.sqrt(1 + z * z)
        g, h = (1 + z / r) / 2, (1 - z / r) / 2
    return float(mpmath.log(g)), float(mpmath.log(h))


# --------------------------------------------------------------------------- links

@pytest.mark.parametrize("link", LINKS)
def test_link_logs_match_60_digit_reference(link):
    zs = [-1e4, -500.0, -40.0, -5.0, -0.3, 0.0, 0.3, 5.0, 40.0, 500.0, 1e4]
    if link == "probit":
        zs = [-1e3 if abs(z) == 1e4 else z for z in zs]
    lg, l1g = link_logs(jnp.array(zs), link)
    for z, a, b in zip(zs, np.asarray(lg), np.asarray(l1g)):
        ra, rb = mp_link(z, link)
        # relative 1e-10 on values down to -1e8; absolute 1e-14 near 0 where logs vanish
        assert a == pytest.approx(ra, rel=1e-10, abs=1e-14), (z, a, ra)
        assert b == pytest.approx(rb, rel=1e-10, abs=1e-14), (z, b, rb)


@pytest.mark.parametrize("link", LINKS)
def test_link_logs_finite_values_and_gradients_at_extremes(link):
    z = jnp.array([-1e300, -1e100, -1e8, -30.0, 0.0, 30.0, 1e8, 1e100, 1e300, jnp.inf, -jnp.inf])
    lg, l1g = link_logs(z, link)
    assert np.all(np.isfinite(lg)) and np.all(np.isfinite(l1g))
    assert np.all(np.asarray(lg) <= 0) and np.all(np.asarray(l1g) <= 0)
    for fn in (lambda x: link_logs(x, link)[0], lambda x: link_logs(x, link)[1]):
        grads = jax.vmap(jax.grad(fn))(z[:-2])
        assert np.all(np.isfinite(grads))


@pytest.mark.parametrize("link", LINKS)
def test_link_is_symmetric_and_sums_to_one(link):
    z = jnp.linspace(-8, 8, 161)
    lg, l1g = link_logs(z, link)
    lg_neg, _ = link_logs(-z, link)
    # XLA's log1p is good to ~10 ulp (5e-15 absolute seen at x = -0.4), hence 2e-14.
    np.testing.assert_allclose(np.exp(lg) + np.exp(l1g), 1.0, rtol=0, atol=2e-14)
    np.testing.assert_allclose(l1g, lg_neg, rtol=0, atol=2e-14)  # 1 - g(z) = g(-z)


def test_pritchet_tail_is_a_power_law():
    # 1 - g(z) = 0.5 (1 - z / sqrt(1 + z^2)) -> 1 / (4 z^2) for large z
    for z in (1e6, 1e9, 1e50):  # relative correction to 1/(4 z^2) is O(1/z^2)
        _, l1g = link_logs(jnp.array(z), "pritchet")
        assert float(l1g) == pytest.approx(-math.log(4 * z * z), rel=1e-9)


@pytest.mark.parametrize("A, floor", [(0.95, 0.01), (0.5, 0.49), (1 - 1e-12, 1e-12), (0.9999, 0.3)])
def test_logistic_fast_path_equals_generic_mixture(A, floor):
    z = jnp.concatenate([jnp.linspace(-700, 700, 1401), jnp.linspace(-3, 3, 601), jnp.array([0.0])])
    logs = dict(log_A=jnp.log(A), log_1mA=jnp.log1p(-A), log_floor=jnp.log(floor), log_1mfloor=jnp.log1p(-floor))
    fast = logistic_mixture_logs(z, **logs)
    slow = mixture_logs(*link_logs(z, "logistic"), **logs)
    for a, b in zip(fast, slow):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-13)
    # fixed plateau and/or floor (None) too
    for kw in (dict(log_A=None, log_1mA=None), dict(log_floor=None, log_1mfloor=None),
               dict(log_A=None, log_1mA=None, log_floor=None, log_1mfloor=None)):
        logs2 = {**logs, **kw}
        for a, b in zip(logistic_mixture_logs(z, **logs2), mixture_logs(*link_logs(z, "logistic"), **logs2)):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-13)


@pytest.mark.parametrize("link", LINKS)
def test_link_derivatives_match_analytic_ones_including_z_zero(link):
    z = jnp.array([-30.0, -2.0, -0.1, 0.0, 0.1, 2.0, 30.0])
    dg = jax.vmap(jax.grad(lambda x: link_logs(x, link)[0]))(z)
    d1g = jax.vmap(jax.grad(lambda x: link_logs(x, link)[1]))(z)
    zz = np.asarray(z)
    if link == "logistic":
        g, h, pdf = special.expit(zz), special.expit(-zz), special.expit(zz) * special.expit(-zz)
    elif link == "probit":
        g, h, pdf = special.ndtr(zz), special.ndtr(-zz), stats.norm.pdf(zz)
    else:
        r = np.sqrt(1 + zz ** 2)
        g, h, pdf = 0.5 * (1 + zz / r), 0.5 * (1 - zz / r), 0.5 * r ** -3
    # atol: the logistic's log(1 - g) = log g - z has derivative (1 - g) - 1, exact to ~1e-16 absolute
    np.testing.assert_allclose(dg, pdf / g, rtol=1e-9, atol=1e-15)  # jax log_ndtr tail series: ~2e-10
    np.testing.assert_allclose(d1g, -pdf / h, rtol=1e-9, atol=1e-15)


def test_logistic_fast_path_gradients_including_z_zero():
    logs = dict(log_A=jnp.log(0.9), log_1mA=jnp.log(0.1), log_floor=jnp.log(0.05), log_1mfloor=jnp.log(0.95))
    z = jnp.array([-40.0, -1.0, 0.0, 1e-9, 1.0, 40.0])
    for i in (0, 1):
        fast = jax.vmap(jax.grad(lambda x: logistic_mixture_logs(x, **logs)[i]))(z)
        slow = jax.vmap(jax.grad(lambda x: mixture_logs(*link_logs(x, "logistic"), **logs)[i]))(z)
        np.testing.assert_allclose(fast, slow, rtol=1e-12, atol=1e-15)
    # analytic at z = 0: d log f / dz = (A - floor) g'(0) / f = 0.85 * 0.25 / 0.475
    d0 = jax.grad(lambda x: logistic_mixture_logs(x, **logs)[0])(0.0)
    assert float(d0) == pytest.approx(0.85 * 0.25 / 0.475, rel=1e-13)


def test_mixture_with_numeric_minus_inf_has_no_nan():
    # floor = 0 and A = 1 passed as numbers: log 0 = -inf must not give NaN, nor NaN gradients.
    def total(z):
        lf, l1f = mixture_logs(*link_logs(z, "logistic"), log_A=0.0, log_1mA=-jnp.inf,
                               log_floor=-jnp.inf, log_1mfloor=0.0)
        return jnp.sum(lf) + jnp.sum(l1f)

    z = jnp.array([-50.0, -1.0, 0.0, 2.0, 60.0])
    lf, l1f = mixture_logs(*link_logs(z, "logistic"), log_A=0.0, log_1mA=-jnp.inf, log_floor=-jnp.inf,
                           log_1mfloor=0.0)
    ref = link_logs(z, "logistic")
    np.testing.assert_allclose(lf, ref[0], rtol=1e-14)
    np.testing.assert_allclose(l1f, ref[1], rtol=1e-14)
    g = jax.grad(total)(z)
    assert np.all(np.isfinite(g))
    # d/dz [log s + log(1 - s)] = 1 - 2 s
    np.testing.assert_allclose(g, 1 - 2 * special.expit(np.asarray(z)), atol=1e-12)


# --------------------------------------------------------------------------- model: known answers

@pytest.fixture(scope="module")
def tiny():
    m = np.array([21.0, 23.5, 24.0, 24.2, 25.0, 26.5])
    y = np.array([True, True, False, True, False, False])
    depth = np.array([0.1, -0.2, 0.0, 0.3, -0.1, 0.2])
    u = np.array([-1.0, -0.5, 0.0, 0.25, 0.5, 1.0])
    v = np.array([0.5, -1.0, 0.75, 0.0, -0.25, 1.0])
    return Covariates(m, depth, u, v, np.zeros(6)), y


def test_tiny_dataset_matches_hand_computation(tiny):
    cov, y = tiny
    model = CompletenessModel("logistic_depth", uncompressed(cov, y))
    assert model.names == ["m50_0", "log_w", "logit_A", "logit_floor", "beta_depth"]
    p = dict(m50_0=24.1, w=0.3, A=0.9, floor=0.05, beta_depth=0.7)
    theta = model.inverse_transform(p)
    ll = numpy_logistic_loglik(cov.m, y, p["m50_0"] + p["beta_depth"] * cov.depth, p["w"], p["A"], p["floor"])
    assert model.log_likelihood(theta) == pytest.approx(ll, rel=1e-13)
    # the prior in theta space: densities of the documented priors times the Jacobians of the logits
    r = p["floor"] / p["A"]
    lp = (stats.norm(25, 5).logpdf(24.1) + stats.norm(math.log(0.2), 1).logpdf(math.log(0.3))
          + stats.beta(20, 1).logpdf(0.9) + math.log(0.9 * 0.1)
          + stats.beta(1, 50).logpdf(r) + math.log(r * (1 - r))
          + stats.norm(1, 1).logpdf(0.7))
    assert model.log_prior(theta) == pytest.approx(lp, rel=1e-12)
    assert model.log_prob(theta) == pytest.approx(lp + ll, rel=1e-12)
    back = model.transform(theta)
    for key, value in p.items():
        assert back[key] == pytest.approx(value, rel=1e-12)


@pytest.mark.parametrize("link", LINKS)
def test_prob_at_m50_is_halfway_between_floor_and_plateau(link):
    cov, y = synthetic(50, 1)
    model = CompletenessModel(ModelSpec(name=link, link=link, spatial="depth"), uncompressed(cov, y))
    p = dict(m50_0=23.0, w=0.25, A=0.93, floor=0.04, beta_depth=0.8)
    theta = model.inverse_transform(p)
    d = np.array([-0.4, 0.0, 0.5])
    at = Covariates.make(p["m50_0"] + p["beta_depth"] * d, depth=d)
    np.testing.assert_allclose(model.prob(theta, at), 0.04 + (0.93 - 0.04) / 2, rtol=1e-12)
    # far bright -> plateau, far faint -> floor (|z| = 1e5: even the Pritchet tail 1/(4 z^2) is negligible)
    ends = Covariates.make(np.array([23.0 - 2.5e4, 23.0 + 2.5e4]))
    np.testing.assert_allclose(model.prob(theta, ends), [0.93, 0.04], rtol=1e-9)


def test_depth_slope_shifts_the_m50_field():
    cov, y = synthetic(50, 2)
    model = CompletenessModel("logistic_depth_smooth", uncompressed(cov, y))
    theta = model.inverse_transform(dict(m50_0=24.0, w=0.2, beta_depth=1.3, c_10=0.2, c_02=-0.1))
    d = np.linspace(-0.5, 0.5, 11)
    u = np.linspace(-1, 1, 11)
    v = np.linspace(1, -1, 11)
    with_d = model.m50(theta, Covariates.make(20.0, depth=d, u=u, v=v))
    without = model.m50(theta, Covariates.make(20.0, depth=0.0, u=u, v=v))
    np.testing.assert_allclose(with_d - without, 1.3 * d, atol=1e-12)
    # smooth term: Legendre P1(u) and P2(v) = (3 v^2 - 1) / 2
    np.testing.assert_allclose(without, 24.0 + 0.2 * u - 0.1 * (3 * v ** 2 - 1) / 2, atol=1e-12)


def test_size_covariate_and_width_depth_enter_as_documented():
    cov, y = synthetic(40, 3)
    spec = ModelSpec(name="s", spatial="depth", width_depth=True, size_covariate=True)
    model = CompletenessModel(spec, uncompressed(cov, y))
    assert model.names[-3:] == ["beta_depth", "w_depth", "beta_size"]
    theta = model.inverse_transform(dict(m50_0=24.0, w=0.2, A=0.9, floor=0.02, beta_depth=1.0, w_depth=0.5,
                                         beta_size=-3.0))
    d, s = 0.4, 0.2
    m50 = 24.0 + 1.0 * d - 3.0 * s
    w = 0.2 * math.exp(0.5 * d)
    m = m50 + w  # z = -1
    f = model.prob(theta, Covariates.make(m, depth=d, size=s))
    assert f[0] == pytest.approx(0.02 + 0.88 * special.expit(-1.0), rel=1e-12)


@pytest.mark.parametrize("spec", ["logistic_depth_smooth", ModelSpec(name="p", link="probit", spatial="depth",
                                                                      width_depth=True),
                                  ModelSpec(name="q", link="pritchet", spatial="smooth", smooth_basis="bspline",
                                            smooth_order=4)])
def test_gradient_and_hessian_match_finite_differences(spec):
    cov, y = synthetic(3000, 4)
    model = CompletenessModel(spec, compress(cov, y, dm=0.05, ddepth=0.05, nuv=8))
    rng = np.random.default_rng(5)
    theta = model.initial() + rng.normal(0, 0.1, model.ndim)
    value, grad = model.value_and_grad(theta)
    assert value == pytest.approx(model.log_prob(theta), rel=1e-14)
    h = 1e-5
    fd = np.array([(model.log_prob(theta + h * e) - model.log_prob(theta - h * e)) / (2 * h)
                   for e in np.eye(model.ndim)])
    # central differences: truncation ~ h^2 f''' and rounding ~ 1e-16 |f| / h ~ 1e-8 here
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-4)
    hess = model.hessian(theta)
    fdh = np.array([(model.value_and_grad(theta + h * e)[1] - model.value_and_grad(theta - h * e)[1]) / (2 * h)
                    for e in np.eye(model.ndim)])
    np.testing.assert_allclose(hess, fdh, rtol=1e-4, atol=1e-2)
    np.testing.assert_allclose(hess, hess.T, rtol=1e-10, atol=1e-8)


def test_prior_is_normalised_with_its_jacobians():
    cov, y = synthetic(20, 6)
    model = CompletenessModel("logistic", uncompressed(cov, y))
    base = model.inverse_transform(dict(m50_0=24.0, w=0.2, A=0.9, floor=0.05))
    i_a, i_f = model.names.index("logit_A"), model.names.index("logit_floor")
    lp0 = model.log_prior(base)

    def density(i, t):
        th = base.copy()
        th[i] = t
        return math.exp(model.log_prior(th) - lp0)

    # Beta(20, 1) on A = sigmoid(t): integral of the theta-space density over t is the density's
    # normalisation 1 / p_t(t0); its mean of A is 20 / 21.  Same for r = floor / A ~ Beta(1, 50).
    for i, (a, b) in ((i_a, (20.0, 1.0)), (i_f, (1.0, 50.0))):
        s0 = special.expit(base[i])
        p_t0 = stats.beta(a, b).pdf(s0) * s0 * (1 - s0)
        norm, _ = integrate.quad(lambda t: density(i, t), -60, 60, limit=200, points=[base[i]])
        mean, _ = integrate.quad(lambda t: special.expit(t) * density(i, t), -60, 60, limit=200, points=[base[i]])
        assert norm * p_t0 == pytest.approx(1.0, rel=1e-6)
        assert mean / norm == pytest.approx(a / (a + b), rel=1e-6)


def test_floor_stays_below_plateau_for_any_theta():
    cov, y = synthetic(20, 7)
    model = CompletenessModel("logistic", uncompressed(cov, y))
    thetas = np.random.default_rng(8).normal(0, 30, (2000, model.ndim))
    p = model.transform(thetas)
    assert np.all(p["floor"] <= p["A"]) and np.all(p["A"] <= 1) and np.all(p["floor"] >= 0)
    fixed = CompletenessModel(ModelSpec(name="f", plateau="fixed"), uncompressed(cov, y))
    assert fixed.names == ["m50_0", "log_w", "logit_floor"]
    assert fixed.transform(np.array([24.0, -1.6, -3.0]))["A"] == 1.0


def test_map_recovers_known_parameters():
    # 20000 outcomes from logistic_depth with known truth; the MAP must lie within 4 Laplace sigma
    # of the truth in every parameter (a 4-sigma miss has probability ~6e-5 per parameter).
    truth = dict(m50_0=24.0, w=0.2, A=0.95, floor=0.01, beta_depth=1.0)
    cov, y = synthetic(20000, 9, **{("m50" if k == "m50_0" else k): v for k, v in truth.items()})
    model = CompletenessModel("logistic_depth", compress_for("logistic_depth", cov, y))
    res = optimize.minimize(lambda t: tuple(-x for x in model.value_and_grad(t)), model.initial(), jac=True,
                            method="L-BFGS-B")
    assert res.success
    sd = np.sqrt(np.diag(np.linalg.inv(-model.hessian(res.x))))
    t_true = model.inverse_transform(truth)
    assert np.all(np.abs(res.x - t_true) < 4 * sd), (res.x, t_true, sd)


# --------------------------------------------------------------------------- compression

def test_compression_is_exact_for_shared_covariates():
    rng = np.random.default_rng(10)
    base = Covariates(rng.uniform(22, 26, 50), rng.normal(0, 0.2, 50), rng.uniform(-1, 1, 50),
                      rng.uniform(-1, 1, 50), np.zeros(50))
    rep = rng.integers(1, 30, 50)
    cov = base.take(np.repeat(np.arange(50), rep))
    y = rng.uniform(size=len(cov)) < 0.5
    comp = compress(cov, y)
    assert comp.ncells <= 100 and comp.ntotal == len(cov) == comp.meta["N"]
    np.testing.assert_array_equal(np.bincount(comp.index), comp.n)
    assert comp.k.sum() == y.sum()
    for spec in ("logistic_depth_smooth", ModelSpec(name="p", link="pritchet", spatial="depth")):
        mc, mu = CompletenessModel(spec, comp), CompletenessModel(spec, uncompressed(cov, y))
        theta = mu.initial() + 0.05
        assert mc.log_likelihood(theta) == pytest.approx(mu.log_likelihood(theta), rel=1e-12)


def test_compression_cells_hold_member_means():
    cov, y = synthetic(5000, 11)
    comp = compress(cov, y, dm=0.1, ddepth=0.1, nuv=4)
    idx = comp.index
    for c in (0, comp.ncells // 2, comp.ncells - 1):
        members = idx == c
        assert comp.n[c] == members.sum() and comp.k[c] == y[members].sum()
        assert comp.cov.m[c] == pytest.approx(cov.m[members].mean(), rel=1e-13)
        assert comp.cov.u[c] == pytest.approx(cov.u[members].mean(), abs=1e-13)
        assert np.all(y[members] == y[members][0])  # split_outcomes: one outcome per cell
    assert np.all(np.abs(np.diff(cov.m[idx == 0])) < 0.1 + 1e-12) or comp.n[0] == 1


@pytest.fixture(scope="module")
def big():
    return synthetic(200_000, 12)


@pytest.mark.parametrize("spec", ["logistic", "logistic_depth"])
def test_compressed_likelihood_agrees_with_unbinned(big, spec):
    cov, y = big
    full = CompletenessModel(spec, uncompressed(cov, y))
    comp_data = compress_for(spec, cov, y)
    comp = CompletenessModel(spec, comp_data)
    theta_true = full.inverse_transform(dict(m50_0=24.0, w=0.2, A=0.95, floor=0.01, beta_depth=1.0))
    # The binning error is second order in the steps: about -1/2 sum g(1-g) (dm^2 + (beta - 1)^2
    # ddepth^2) / (12 w^2) over the ~2e4 outcomes in the transition, ~1.7 nat for the default
    # magnitude step 0.02 (the depth grid, laid along m - depth, adds little).  An offset that is
    # nearly the same at every theta does not move the posterior; required: below 3 nat at the truth
    # and several posterior sigmas away.
    tol = 3.0
    for shift in (0.0, 0.03):
        theta = theta_true + shift
        assert abs(comp.log_likelihood(theta) - full.log_likelihood(theta)) < tol
    # MAP-relevant: the gradient difference moves the optimum by H^-1 dg; require < 0.02 posterior sigma
    # at 200,000 injections (measured 0.012 and 0.014 sigma, on log w).
    _, g_full = full.value_and_grad(theta_true)
    _, g_comp = comp.value_and_grad(theta_true)
    hess = full.hessian(theta_true)
    cov_post = np.linalg.inv(-hess)
    shift = cov_post @ (g_comp - g_full)
    assert np.all(np.abs(shift) / np.sqrt(np.diag(cov_post)) < 0.02)
    if spec == "logistic":
        assert comp_data.ncells <= 2 * 351  # 7 mag / 0.02 = 350 magnitude bins, times 2 outcomes at most


def test_cell_count_is_bounded_independently_of_n():
    # 7 mag range / dm = 0.02 -> at most 350 bins, each split by outcome -> 700 cells (fewer: the step
    # grows to dm_max on the plateau and the floor), whatever N.
    small = compress_for("logistic", *synthetic(10_000, 13))
    large = compress_for("logistic", *synthetic(1_000_000, 14))
    assert large.ncells <= 2 * 351 and small.ncells <= 2 * 351
    assert large.ntotal == 1_000_000
    # with depth resolved too, cells are bounded by the occupied (m - depth, depth) grid, not by N
    cov14 = synthetic(1_000_000, 14)[0]
    lo, hi = cov14.depth.min(), cov14.depth.max()
    span = (cov14.m - cov14.depth).max() - (cov14.m - cov14.depth).min()
    large_d = compress_for("logistic_depth", *synthetic(1_000_000, 14))
    assert large_d.ncells <= 2 * (math.ceil(span / 0.02) + 1) * (math.ceil((hi - lo) / 0.1) + 1)
    assert set(large_d.meta["binned"]) == {"m", "depth"}


def test_magnitude_step_grows_where_outcomes_do_not_mix():
    # Truth: m50 = 24 (+ depth), w = 0.2, plateau 0.95, floor 0.01, injected over 20-27 mag; the magnitude grid
    # alone (no depth resolved).  The step is dm sqrt(0.25 / p(1 - p)) of the local detected fraction p,
    # within [dm, dm_max]: ~0.046 mag on the plateau (p = 0.95), the full 0.1 on the floor (p = 0.01), and
    # dm = 0.02 through the transition.  Measured as the span of each cell's members (one outcome class per
    # cell, split_outcomes), so a cell spans at most its step.
    cov, y = synthetic(200_000, 21)
    fine = compress(cov, y, dm=0.02, ddepth=None, nuv=None, dsize=None)
    grown = compress(cov, y, dm=0.02, ddepth=None, nuv=None, dsize=None, dm_max=0.1)
    assert grown.meta["dm_max"] == 0.1 and grown.ntotal == fine.ntotal == 200_000
    assert grown.ncells < 0.5 * fine.ncells

    def spans(data, lo, hi):
        sel = (cov.m >= lo) & (cov.m < hi)
        idx, m = data.index[sel], cov.m[sel]
        return np.array([np.ptp(m[idx == c]) for c in np.unique(idx)])

    # the transition keeps the fine step (a cell across a coarse-bin edge takes a little of the next step)
    assert spans(grown, 23.9, 24.1).max() <= 1.05 * 0.02
    plateau = spans(grown, 20.5, 22.5)
    assert plateau.max() <= 0.1 + 1e-9 and np.median(plateau) > 0.035
    floor = spans(grown, 25.8, 26.8)
    assert floor.max() <= 0.1 + 1e-9 and np.median(floor) > 0.08
    with pytest.raises(InputError, match="dm_max"):
        compress(cov, y, dm_max=-1.0)


def test_compression_arguments_are_checked():
    cov, y = synthetic(100, 15)
    with pytest.raises(InputError, match="dm"):
        compress(cov, y, dm=None)
    with pytest.raises(InputError, match="nuv"):
        compress(cov, y, nuv=0)
    with pytest.raises(InputError, match="detected"):
        compress(cov, y[:-1])
    coarse = compress(cov, y, nuv=None)
    with pytest.raises(InputError, match="uv"):
        CompletenessModel("logistic_smooth", coarse)
    with pytest.raises(ConfigError, match="selection spec"):
        CompletenessModel("auto", coarse)


# --------------------------------------------------------------------------- covariates from the outcome table

def outcome_table(n=200, seed=16, shape=(100, 300)):
    rng = np.random.default_rng(seed)
    ny, nx = shape
    return Table({"x": rng.uniform(0, nx - 1, n), "y": rng.uniform(0, ny - 1, n), "mag": rng.uniform(20, 26, n),
                  "noise": rng.uniform(1.0, 3.0, n), "hlr_arcsec": rng.uniform(0.2, 1.0, n),
                  "detected": rng.uniform(size=n) < 0.5})


def test_covariates_from_outcomes_known_values():
    t = outcome_table()
    t["x"][:2] = [0.0, 299.0]
    t["y"][:2] = [99.0, 0.0]
    cov, det, meta = covariates_from_outcomes(t, image_shape=(100, 300), sigma_ref=2.0, hlr_ref=0.5)
    np.testing.assert_allclose(cov.u[:2], [-1.0, 1.0])
    np.testing.assert_allclose(cov.v[:2], [1.0, -1.0])
    np.testing.assert_allclose(cov.depth, -2.5 * np.log10(np.asarray(t["noise"]) / 2.0))
    np.testing.assert_allclose(cov.size, np.log10(np.asarray(t["hlr_arcsec"]) / 0.5))
    np.testing.assert_array_equal(det, np.asarray(t["detected"]))
    assert meta["N"] == 200 and meta["image_shape"] == (100, 300)
    assert set(meta["available"]) == {"m", "uv", "depth", "size"}
    _, _, meta2 = covariates_from_outcomes(t, image_shape=(100, 300))
    assert meta2["sigma_ref"] == pytest.approx(np.median(t["noise"]))


def test_nan_positions_and_magnitudes_are_dropped_with_a_count():
    t = outcome_table()
    t["x"][3] = np.nan
    t["mag"][[5, 7]] = np.nan
    with pytest.warns(UserWarning, match="dropped 3 of 200"):
        cov, det, meta = covariates_from_outcomes(t, image_shape=(100, 300))
    assert len(cov) == 197 and det.shape == (197,)
    np.testing.assert_array_equal(meta["dropped_rows"], [3, 5, 7])
    t["mag"][:] = np.nan
    with pytest.raises(InputError, match="all 200 rows"):
        covariates_from_outcomes(t, image_shape=(100, 300))


def test_nan_noise_gives_reference_depth_with_a_warning():
    t = outcome_table()
    t["noise"][[1, 2]] = [np.nan, 0.0]
    with pytest.warns(UserWarning, match="2 of 200 outcome rows have a non-finite or non-positive noise"):
        cov, _, _ = covariates_from_outcomes(t, image_shape=(100, 300))
    assert cov.depth[1] == 0.0 and cov.depth[2] == 0.0
    assert np.all(np.isfinite(cov.depth))


def test_point_sources_get_size_zero_without_nan():
    t = outcome_table()
    t["hlr_arcsec"] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cov, _, meta = covariates_from_outcomes(t, image_shape=(100, 300))
    assert np.all(cov.size == 0) and "size" not in meta["available"]
    with pytest.warns(UserWarning, match="size"):
        CompletenessModel("logistic_depth_size", compress_for("logistic_depth_size", cov, _, meta=meta))


def test_outcome_table_errors_are_clear():
    t = outcome_table()
    with pytest.raises(InputError, match="outside the image"):
        covariates_from_outcomes(t, image_shape=(300, 100))  # transposed
    with pytest.raises(InputError, match="image_shape"):
        covariates_from_outcomes(t, image_shape=None)
    with pytest.raises(InputError, match="no column 'detected'"):
        covariates_from_outcomes(Table({"mag": [1.0]}), image_shape=None)
    bad = outcome_table()
    bad["detected"] = np.where(bad["detected"], 2, 0)
    with pytest.raises(InputError, match="0/1"):
        covariates_from_outcomes(bad, image_shape=(100, 300))
    with pytest.raises(InputError, match="non-finite"):
        Covariates.make([1.0, np.nan])
    # purity: measured magnitude, real-or-false outcome, no positions needed
    pur = Table({"det_mag_auto": [20.0, 21.0, 25.0], "real": [1, 1, 0]})
    cov, real, meta = covariates_from_outcomes(pur, image_shape=None, mag_column="det_mag_auto",
                                               outcome_column="real")
    np.testing.assert_array_equal(real, [True, True, False])
    assert meta["available"] == ("m",)


# --------------------------------------------------------------------------- stability

def _cases():
    rng = np.random.default_rng(17)
    m = rng.uniform(20, 27, 200)
    u = rng.uniform(-1, 1, 200)
    v = rng.uniform(-1, 1, 200)
    d = rng.normal(0, 0.1, 200)
    spread = Covariates(m, d, u, v, np.zeros(200))
    one_cell = Covariates(m, np.full(200, 0.05), np.full(200, 0.3), np.full(200, -0.2), np.zeros(200))
    few = spread.take(np.arange(12))
    return {
        "all detected": (spread, np.ones(200, bool)),
        "none detected": (spread, np.zeros(200, bool)),
        "separated": (spread, m < 23.5),
        "12 injections": (few, few.m < 24.0),
        "one spatial cell": (one_cell, rng.uniform(size=200) < special.expit((24 - m) / 0.2)),
    }


@pytest.mark.parametrize("spec", ["logistic", "logistic_depth_smooth", "probit", "pritchet",
                                  ModelSpec(name="fixed", plateau="fixed", floor="fixed", spatial="depth")])
def test_degenerate_data_give_finite_posteriors(spec):
    # uncompressed: the cases share one cell count (200), so each function compiles once per spec
    for label, (cov, y) in _cases().items():
        model = CompletenessModel(spec, uncompressed(cov, y))
        theta = model.initial()
        value, grad = model.value_and_grad(theta)
        assert np.isfinite(value) and np.all(np.isfinite(grad)), label
        if len(cov) == 200:  # (the Hessian is compiled for one data shape only, to keep the test fast)
            assert np.all(np.isfinite(model.hessian(theta))), label
        f = model.prob(theta, cov)
        assert np.all((f >= 0) & (f <= 1)), label
        for absurd in (np.full(model.ndim, 1e6), np.full(model.ndim, -1e6), np.full(model.ndim, 1e300),
                       np.full(model.ndim, np.nan), np.where(np.arange(model.ndim) % 2 == 0, 1e6, -1e6)):
            lp = model.log_prob(absurd)
            assert not np.isnan(lp) and lp < value, (label, absurd[:2], lp)
            v2, g2 = model.value_and_grad(absurd)
            assert not np.isnan(v2) and not np.any(np.isnan(g2)), label
        if len(cov) == 200:
            batch = model.log_prob_batch(np.stack([theta, np.full(model.ndim, np.nan)]))
            assert batch[0] == pytest.approx(value, rel=1e-12) and batch[1] == -np.inf


def test_initial_lands_near_the_transition():
    cov, y = synthetic(5000, 18)
    model = CompletenessModel("logistic", compress_for("logistic", cov, y))
    p = model.transform(model.initial())
    assert abs(p["m50_0"] - 24.0) < 0.3 and 0.05 < p["w"] < 0.5  # grid step of m50 is ~0.1 mag


# --------------------------------------------------------------------------- jit, batches, pointwise

def test_compiled_once_per_model_and_batches_agree():
    cov, y = synthetic(700, 19)
    model = CompletenessModel(ModelSpec(name="jit", spatial="depth", width_depth=True),
                              compress(cov, y, dm=0.01))
    theta = model.initial()
    model.log_prob(theta)
    model.value_and_grad(theta)
    before = TRACE_COUNT["log_prob"]
    rng = np.random.default_rng(20)
    thetas = theta + rng.normal(0, 0.05, (7, model.ndim))
    values = [model.log_prob(t) for t in thetas]
    for t in thetas:
        model.value_and_grad(list(t))  # a list converts to the same float64 (D,) array
    assert TRACE_COUNT["log_prob"] == before
    np.testing.assert_allclose(model.log_prob_batch(thetas), values, rtol=1e-13)
    with pytest.raises(InputError, match="shape"):
        model.log_prob(theta[:-1])


def test_cell_loglik_reproduces_the_likelihood_in_chunks():
    cov, y = synthetic(2000, 21)
    data = compress(cov, y, dm=0.02, ddepth=0.05, nuv=4)
    model = CompletenessModel("logistic_depth_smooth", data)
    rng = np.random.default_rng(22)
    thetas = model.initial() + rng.normal(0, 0.05, (5, model.ndim))
    cl = model.cell_loglik(thetas, max_elements=3 * 2 * data.ncells)  # chunks of 3 samples, last one padded
    assert cl.shape == (5, data.ncells, 2)
    total = (cl[..., 0] * data.k + cl[..., 1] * (data.n - data.k)).sum(axis=1)
    np.testing.assert_allclose(total, [model.log_likelihood(t) for t in thetas], rtol=1e-12)
    np.testing.assert_allclose(np.exp(cl[..., 0]) + np.exp(cl[..., 1]), 1.0, atol=1e-14)
    f = model.prob(thetas, data.cov)
    assert f.shape == (5, data.ncells)
    np.testing.assert_allclose(f, np.exp(cl[..., 0]), rtol=1e-12)


# --------------------------------------------------------------------------- smooth bases

def test_smooth_bases_have_zero_field_average():
    # Composite Gauss-Legendre, 4 nodes on each of 12 equal sub-intervals per axis: exact for the
    # polynomials and for the piecewise-cubic B-splines (whose knots, spacing 2 or 2/3, fall on
    # sub-interval edges), so the field averages must vanish to rounding.
    nodes, weights = np.polynomial.legendre.leggauss(4)
    edges = np.linspace(-1, 1, 13)
    half = 0.5 * (edges[1] - edges[0])
    x = (edges[:-1, None] + half * (nodes[None, :] + 1)).ravel()
    wx = np.tile(weights * half, 12)
    uu, vv = np.meshgrid(x, x)
    ww = np.outer(wx, wx).ravel() / 4.0  # mean over the square [-1, 1]^2
    assert ww.sum() == pytest.approx(1.0, rel=1e-14)
    for basis, order, ncol in (("poly", 2, 5), ("poly", 3, 9), ("bspline", 4, 15), ("bspline", 6, 35)):
        b = smooth_basis(uu.ravel(), vv.ravel(), basis, order)
        assert b.shape[1] == ncol
        np.testing.assert_allclose(ww @ b, 0.0, atol=1e-13)
        assert np.linalg.matrix_rank(b) == ncol  # no column is a combination of the others
    # the 1-D B-splines behind the tensor basis are a partition of unity
    from comest_bayes.bayes.bases import _bspline_1d
    np.testing.assert_allclose(_bspline_1d(np.linspace(-1, 1, 101), 6).sum(axis=1), 1.0, atol=1e-14)
