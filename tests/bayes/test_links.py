"""The link functions and the plateau/floor mixture (comest_bayes.bayes.links): 60-digit references, symmetry,
tails, extremes, and the logistic fast path against the generic mixture, with gradients.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import mpmath
import numpy as np
import pytest
from scipy import special, stats

from comest_bayes.bayes.links import link_logs, logistic_mixture_logs, mixture_logs


LINKS = ("logistic", "probit", "pritchet")


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
