"""Transition shapes of the flexible completeness rungs (pure JAX, float64, elementwise).

:func:`monotone_spline` (the spline rung's monotone transition) and :func:`richards_logs` (the
generalised logistic), written for ``jax.jit`` and ``jax.grad`` with no NaN in a gradient.
Formulas: ``docs/bayesian.md`` ("Transition shapes of the flexible rungs").
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

__all__ = ["SPLINE_H0", "SPLINE_WARP", "SPLINE_ANCHOR", "SPLINE_CHORD", "spline_knots", "monotone_spline", "richards_logs", "softplus", "logaddexp"]

#: Knot spacing of the monotone spline at t = 0, in standardised magnitude t = (m - m50) / w.
SPLINE_H0 = 0.25
#: Scale of the knot warp: the knots sit at ``t = SPLINE_WARP sinh(s / SPLINE_WARP)`` for ``s`` on a
#: uniform grid of step ``SPLINE_H0``, fine near m50 and wider (exponentially) far from it.
SPLINE_WARP = 1.5
#: Index of the anchor knot (``t = 0``, ``eta = 0``): 24 knots on the bright side reach ``t = -41``.
SPLINE_ANCHOR = 24
#: Half-width of the chord window: the rate's mean over ``[-SPLINE_CHORD, SPLINE_CHORD]`` is 1.
SPLINE_CHORD = 2.0


def spline_knots(n_free: int):
    """Knot positions (tuple of floats) and the anchor index for ``n_free`` free knot log-rates.

    Knot ``k`` (``k = 0 .. n_free``) sits at ``SPLINE_WARP sinh((k - k0) SPLINE_H0 / SPLINE_WARP)``
    with ``k0 = SPLINE_ANCHOR`` the anchor at ``t = 0``.
    """
    k0 = SPLINE_ANCHOR
    if n_free < k0 + 2:
        raise ValueError(f"a monotone spline needs at least {k0 + 2} free knots (the anchor sits at index {k0} "
                         f"and the faint side needs two), got {n_free}")
    s = (np.arange(n_free + 1) - k0) * SPLINE_H0
    knots = SPLINE_WARP * np.sinh(s / SPLINE_WARP)
    return tuple(float(x) for x in knots), k0


def _window_weights(knots: np.ndarray, half: float) -> np.ndarray:
    """Weights ``c_k`` with ``sum_k c_k r_k`` the integral over ``[-half, half]`` of the rate that is
    linear between the knots (exact for any window end inside a knot interval)."""
    c = np.zeros(knots.size)
    for j in range(knots.size - 1):
        a, b = max(knots[j], -half), min(knots[j + 1], half)
        if b <= a:
            continue
        h = knots[j + 1] - knots[j]
        # integral over [a, b] of the hat functions of knots j and j + 1
        ua, ub = (a - knots[j]) / h, (b - knots[j]) / h
        c[j] += h * ((ub - ua) - 0.5 * (ub ** 2 - ua ** 2))
        c[j + 1] += h * 0.5 * (ub ** 2 - ua ** 2)
    return c


def softplus(x):
    """log(1 + exp(x)), stable, with the right derivative everywhere."""
    pos = x > 0
    return jnp.where(pos, x, 0.0) + jnp.log1p(jnp.exp(jnp.where(pos, -x, x)))


def logaddexp(a, b):
    """log(exp(a) + exp(b)); -inf (not NaN) with finite gradients when a term is -inf."""
    first = a >= b
    m = jnp.where(first, a, b)
    ok = m > -jnp.inf
    d = jnp.where(ok, jnp.where(first, b - a, a - b), 0.0)
    return jnp.where(ok, m + jnp.log1p(jnp.exp(d)), -jnp.inf)


def full_eta(eta_free, k0: int):
    """The knot log-rates with the anchor's 0 inserted at index ``k0``."""
    return jnp.concatenate([eta_free[:k0], jnp.zeros(1, dtype=eta_free.dtype), eta_free[k0:]])


def monotone_spline(t, eta_free):
    """``S(t)``: minus the integral from 0 to t of a positive piecewise-linear rate.

    Parameters
    ----------
    t : array
        Standardised magnitudes (any shape).
    eta_free : array, shape (K,)
        Log-rates at the knots other than the anchor (``K >= SPLINE_ANCHOR + 2``).

    Returns
    -------
    array, shape of t
        Decreasing in t, ``S(0) = 0``, ``S(-T) - S(T) = 2 T`` (``T = SPLINE_CHORD``); ``S(t) = -t`` when
        ``eta_free = 0``.
    """
    n_free = eta_free.shape[0]
    knots_t, k0 = spline_knots(n_free)
    knots = np.asarray(knots_t)
    dk = np.diff(knots)
    weights = _window_weights(knots, SPLINE_CHORD)
    eta = full_eta(eta_free, k0)                                 # (K + 1,)
    # the chord normalisation: the mean rate over [-T, T] is 1, so S(-T) - S(T) = 2 T whatever the
    # shape, and w is the chord width of the whole transition, not the inverse of its slope at m50
    # alone (a transition with a shoulder at m50 has a small slope there and steep flanks on both sides)
    top = jnp.max(eta)
    log_c = top + jnp.log(jnp.sum(jnp.asarray(weights) * jnp.exp(eta - top))) - math.log(2.0 * SPLINE_CHORD)
    rate = jnp.exp(eta - log_c)
    seg = 0.5 * jnp.asarray(dk) * (rate[:-1] + rate[1:])        # integral over each knot interval
    cum = jnp.concatenate([jnp.zeros(1, dtype=rate.dtype), jnp.cumsum(seg)])  # I(t_k) from t_0
    t0, t_last = float(knots[0]), float(knots[-1])
    idx = jnp.clip(jnp.searchsorted(jnp.asarray(knots), t, side="right") - 1, 0, n_free - 1)
    left = jnp.asarray(knots)[idx]
    h = jnp.asarray(dk)[idx]
    u = t - left  # in [0, h) inside; not clipped (a clip halves the slope at knots)
    r0 = rate[idx]
    r1 = rate[idx + 1]
    inside = cum[idx] + r0 * u + (r1 - r0) * u * u / (2.0 * h)
    below = rate[0] * (t - t0)                                   # t < t_0: constant rate
    above = cum[-1] + rate[-1] * (t - t_last)                    # t > t_last
    integral = jnp.where(t < t0, below, jnp.where(t > t_last, above, inside))
    return -(integral - cum[k0])


def richards_logs(s, log_nu):
    """``log g`` and ``log(1 - g)`` of ``g = (1 + exp(-(s + c)))^(-nu)``, ``c = -log(2^(1/nu) - 1)``.

    Parameters
    ----------
    s : array
        Shape value (positive = brighter than m50).
    log_nu : scalar
        ``log nu``; 0 is the logistic.

    Notes
    -----
    ``log(1 - g) = log(-expm1(log g))`` except far on the bright side
    (``s + c > 30``), where it is ``log nu - (s + c)`` to relative accuracy
    ``(nu + 1) exp(-(s + c)) / 2`` (the expm1 form would round ``log g`` to 0).
    """
    nu = jnp.exp(log_nu)
    c = -jnp.log(jnp.expm1(jnp.log(2.0) / nu))
    z = s + c
    log_g = -nu * softplus(-z)
    far = z > 30.0
    safe = jnp.where(far, -1.0, log_g)
    log_1mg = jnp.where(far, log_nu - z, jnp.log(-jnp.expm1(safe)))
    return log_g, log_1mg
