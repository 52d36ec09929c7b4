"""The transition shapes of the flexible rungs: monotone spline and Richards link (known answers)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.special import expit

from comest_bayes.bayes.shapes import (SPLINE_ANCHOR, SPLINE_CHORD, SPLINE_H0, SPLINE_WARP, monotone_spline,
                                       richards_logs, spline_knots)

jax.config.update("jax_enable_x64", True)

K = 44


def test_straight_spline_is_minus_t_everywhere():
    t = jnp.linspace(-30.0, 30.0, 601)
    np.testing.assert_allclose(monotone_spline(t, jnp.zeros(K)), -np.asarray(t), atol=1e-12)


def test_spline_is_anchored_and_monotone_for_any_rates():
    rng = np.random.default_rng(1)
    t = jnp.linspace(-12.0, 15.0, 2701)
    for _ in range(20):
        eta = jnp.asarray(rng.normal(0.0, 1.5, K))
        s = np.asarray(monotone_spline(t, eta))
        assert np.all(np.diff(s) < 0)  # strictly decreasing: the rate exp(eta) is positive
        assert float(monotone_spline(jnp.zeros(1), eta)[0]) == pytest.approx(0.0, abs=1e-12)
        # the chord normalisation: S falls by exactly 2T over [-T, T] whatever the rates, while the
        # slope at the anchor itself is free (a shoulder at m50 has a small one)
        chord = monotone_spline(jnp.asarray([-SPLINE_CHORD, SPLINE_CHORD]), eta)
        assert float(chord[0] - chord[1]) == pytest.approx(2.0 * SPLINE_CHORD, abs=1e-12)


def test_spline_integrates_the_piecewise_linear_rate():
    # S(t) against a fine numerical integral of the rate (trapezoid on 1e5 points): agreement to 1e-8
    rng = np.random.default_rng(2)
    eta = rng.normal(0.0, 0.8, K)
    knots, k0 = spline_knots(K)
    full = np.insert(eta, k0, 0.0)
    # the mean rate over [-T, T] is 1, integrated here numerically (the code integrates exactly)
    win = np.linspace(-SPLINE_CHORD, SPLINE_CHORD, 400001)
    full = full - np.log(np.trapezoid(np.interp(win, knots, np.exp(full)), win) / (2.0 * SPLINE_CHORD))
    for t_end in (-35.0, -9.0, -2.5, 0.3, 4.7, 12.0, 30.0):
        u = np.linspace(0.0, t_end, 100001)
        # the rate is linear between knots in exp(eta), constant beyond the outer knots (as np.interp)
        rate = np.interp(u, knots, np.exp(full))
        numeric = -np.trapezoid(rate, u)  # S(t) = -integral from 0 to t (positive for t < 0)
        assert float(monotone_spline(jnp.asarray([t_end]), jnp.asarray(eta))[0]) == pytest.approx(
            numeric, rel=1e-8, abs=1e-8)


def test_knots_layout():
    knots, k0 = spline_knots(K)
    knots = np.asarray(knots)
    assert k0 == SPLINE_ANCHOR and knots[k0] == 0.0 and len(knots) == K + 1
    # spacing SPLINE_H0 at m50, growing outward, symmetric about the anchor
    assert knots[k0 + 1] - knots[k0] == pytest.approx(SPLINE_WARP * np.sinh(SPLINE_H0 / SPLINE_WARP), rel=1e-12)
    assert np.all(np.diff(np.diff(knots[k0:])) > 0) and np.all(np.diff(np.diff(knots[:k0 + 1])) < 0)
    np.testing.assert_allclose(knots[k0 - 5:k0][::-1], -knots[k0 + 1:k0 + 6], rtol=1e-12)
    # the bright side reaches 40 units of w (a feature 4 mag brighter than a 0.1-mag-wide transition)
    assert knots[0] < -40.0 and knots[-1] > 20.0
    with pytest.raises(ValueError, match="at least 26 free knots .* got 13"):
        spline_knots(13)


def test_richards_with_nu_one_is_the_logistic_and_half_at_zero():
    s = jnp.linspace(-40.0, 40.0, 161)
    log_g, log_1mg = richards_logs(s, 0.0)
    np.testing.assert_allclose(np.exp(log_g), expit(np.asarray(s)), rtol=1e-12, atol=1e-300)
    np.testing.assert_allclose(np.exp(log_1mg), expit(-np.asarray(s)), rtol=1e-10, atol=1e-300)
    for log_nu in (-2.0, -0.5, 0.7, 2.5):
        lg, l1 = richards_logs(jnp.zeros(1), log_nu)
        assert float(np.exp(lg[0])) == pytest.approx(0.5, abs=1e-12)
        assert float(np.exp(lg[0]) + np.exp(l1[0])) == pytest.approx(1.0, abs=1e-12)


def test_richards_logs_are_stable_and_complementary():
    s = jnp.asarray([-800.0, -50.0, -5.0, 0.0, 5.0, 29.0, 31.0, 50.0, 800.0])
    for log_nu in (-3.0, 0.0, 3.0):
        lg, l1 = (np.asarray(a) for a in richards_logs(s, log_nu))
        assert np.all(np.isfinite(lg[1:-1])) and np.all(np.isfinite(l1))
        mid = np.abs(np.asarray(s)) < 40
        np.testing.assert_allclose(np.exp(lg[mid]) + np.exp(l1[mid]), 1.0, atol=1e-12)
        # the far-bright branch (s + c > 30) continues the expm1 branch smoothly
        nu = np.exp(log_nu)
        c = -np.log(np.expm1(np.log(2.0) / nu))
        z = 31.0 + c
        if z > 30:  # 1 - (1 + x)^-nu = -expm1(-nu log1p(x)), x = exp(-z), without cancellation
            exact = np.log(-np.expm1(-nu * np.log1p(np.exp(-z))))
            assert float(richards_logs(jnp.asarray([31.0]), log_nu)[1][0]) == pytest.approx(exact, abs=1e-9)
        g = jax.grad(lambda x: richards_logs(x, log_nu)[1].sum())(s)
        assert np.all(np.isfinite(np.asarray(g)))
