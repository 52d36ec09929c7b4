"""Transition shapes of the flexible completeness rungs (pure JAX, float64, elementwise).

:func:`monotone_spline` (the spline rung's monotone transition) and :func:`richards_logs` (the
generalised logistic), written for ``jax.jit`` and ``jax.grad`` with no NaN in a gradient.
Formulas: ``docs/bayesian.md`` ("Transition shapes of the flexible rungs").
"""

from __future__ import annotations

import jax.numpy as jnp

__all__ = ["SPLINE_T0", "SPLINE_H", "spline_knots", "monotone_spline", "richards_logs", "softplus", "logaddexp"]

#: First knot of the monotone spline in standardised magnitude t = (m - m50) / w.
SPLINE_T0 = -6.0
#: Knot spacing in t (half the chord width: features half as wide as the transition are followed);
#: the anchor knot (eta = 0) sits at t = 0.
SPLINE_H = 0.5


def spline_knots(n_free: int):
    """Knot positions (numpy-free tuple) and the anchor index for ``n_free`` free knot parameters.

    The knots are ``SPLINE_T0 + k SPLINE_H`` for ``k = 0 .. n_free``; the one at
    ``t = 0`` (index ``-SPLINE_T0 / SPLINE_H``) is the anchor.
    """
    k0 = int(round(-SPLINE_T0 / SPLINE_H))
    if n_free < k0 + 1:
        raise ValueError(f"a monotone spline needs at least {k0 + 1} free knots (the anchor sits at index {k0}), "
                         f"got {n_free}")
    return tuple(SPLINE_T0 + k * SPLINE_H for k in range(n_free + 1)), k0


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
        Log-rates at the knots other than the anchor (``K >= 13``).

    Returns
    -------
    array, shape of t
        Decreasing in t, ``S(0) = 0``, ``S(-h) - S(h) = 2 h`` (``h = SPLINE_H``); ``S(t) = -t`` when
        ``eta_free = 0``.
    """
    n_free = eta_free.shape[0]
    k0 = int(round(-SPLINE_T0 / SPLINE_H))
    eta = full_eta(eta_free, k0)                                 # (K + 1,)
    # the chord normalisation: the mean rate over [-h, h] is 1, so S(-h) - S(h) = 2 h whatever the
    # shape, and w is the transition's chord width there, not the inverse of its slope at m50 alone
    # (a transition with a shoulder at m50 has a small slope there and steep flanks on both sides)
    log_c = logaddexp(logaddexp(eta[k0 - 1], eta[k0 + 1]), jnp.log(2.0) + eta[k0]) - jnp.log(4.0)
    rate = jnp.exp(eta - log_c)
    seg = 0.5 * SPLINE_H * (rate[:-1] + rate[1:])                 # integral over each knot interval
    cum = jnp.concatenate([jnp.zeros(1, dtype=rate.dtype), jnp.cumsum(seg)])  # I(t_k) from t_0
    t_last = SPLINE_T0 + n_free * SPLINE_H
    pos = (t - SPLINE_T0) / SPLINE_H
    idx = jnp.clip(jnp.floor(pos).astype(jnp.int32), 0, n_free - 1)
    u = t - (SPLINE_T0 + idx * SPLINE_H)  # in [0, h) inside; not clipped (a clip halves the slope at knots)
    r0 = rate[idx]
    r1 = rate[idx + 1]
    inside = cum[idx] + r0 * u + (r1 - r0) * u * u / (2.0 * SPLINE_H)
    below = rate[0] * (t - SPLINE_T0)                             # t < t_0: constant rate
    above = cum[-1] + rate[-1] * (t - t_last)                     # t > t_last
    integral = jnp.where(t < SPLINE_T0, below, jnp.where(t > t_last, above, inside))
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
