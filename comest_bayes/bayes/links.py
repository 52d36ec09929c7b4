"""Link functions of the completeness model: ``log f`` and ``log(1 - f)`` of
``f = floor + (A - floor) g(z)`` for the logistic, probit and Pritchet forms, in log space
(never the log of a difference; see ``docs/bayesian.md``).
"""

from __future__ import annotations

from comest_bayes.jaxnum import jnp
from jax.scipy.special import log_ndtr
from comest_bayes.errors import ConfigError
from comest_bayes.bayes.shapes import logaddexp, softplus

__all__ = ['link_logs', 'mixture_logs', 'logistic_mixture_logs', 'Z_CLIP']

#: |z| is clipped to this value before the link, so that absurd parameters give
#: finite or -inf log-probabilities, never NaN (z^2 stays representable).
Z_CLIP = 1e100


# ---------------------------------------------------------------------------
# Link functions and the floor/plateau mixture (JAX, elementwise)
# ---------------------------------------------------------------------------

# The branch selections below use jnp.where rather than jnp.maximum / jnp.abs:
# JAX gives max(x, 0) and |x| a zero derivative at the kink, which would make
# the derivative of softplus wrong at exactly 0; with where, each branch is a
# smooth formula valid on its side, so derivatives are right everywhere.

softplus = softplus
safe_logaddexp = logaddexp


def link_logs(z, link: str):
    """``log g(z)`` and ``log(1 - g(z))`` of a link, stable for any z.

    Parameters
    ----------
    z : array_like
        Standardised distance ``(m50 - m) / w`` (positive = brighter than m50).
        Clipped to ``[-Z_CLIP, Z_CLIP]``.
    link : {"logistic", "probit", "pritchet"}
        The transition shape.

    Returns
    -------
    log_g, log_1mg : jax arrays, shape of z
    """
    z = jnp.clip(jnp.asarray(z, dtype=jnp.float64), -Z_CLIP, Z_CLIP)
    if link == "logistic":
        log_g = -softplus(-z)
        return log_g, log_g - z
    if link == "probit":
        return log_ndtr(z), log_ndtr(-z)
    if link == "pritchet":
        # g = 0.5 (1 + z / r), r = sqrt(1 + z^2).  The smaller of g and 1 - g is
        # q = 0.5 (1 - |z| / r) = 0.5 / (r (r + |z|)), without cancellation.
        a = jnp.where(z >= 0, z, -z)  # |z| whose derivative at 0 matches the z >= 0 branch
        # With |z| <= Z_CLIP = 1e100, r (r + |z|) <= 2e200: neither overflows nor underflows.
        r = jnp.sqrt(1.0 + a * a)
        q = 0.5 / (r * (r + a))
        log_q = jnp.log(q)
        log_1mq = jnp.log1p(-q)
        return jnp.where(z >= 0, log_1mq, log_q), jnp.where(z >= 0, log_q, log_1mq)
    raise ConfigError(f"unknown link {link!r}; valid links: logistic, probit, pritchet.")


def mixture_logs(log_g, log_1mg, *, log_A=None, log_1mA=None, log_floor=None, log_1mfloor=None):
    """``log f`` and ``log(1 - f)`` for ``f = floor + (A - floor) g``.

    ``1 - f = (1 - A) g + (1 - floor)(1 - g)``.  ``log_A=None`` means a fixed
    plateau ``A = 1`` and ``log_floor=None`` a fixed ``floor = 0``; the
    vanishing terms are then left out.  Numeric ``-inf`` arguments (for
    example ``log_floor = log 0``) are also safe: they give the same values
    and no NaN in values or gradients.

    Parameters
    ----------
    log_g, log_1mg : arrays
        From :func:`link_logs`.
    log_A, log_1mA : scalar or None
        ``log A`` and ``log(1 - A)``.
    log_floor, log_1mfloor : scalar or None
        ``log floor`` and ``log(1 - floor)``.
    """
    if log_floor is None:
        if log_A is None:
            return log_g, log_1mg
        return log_A + log_g, safe_logaddexp(log_1mA + log_g, log_1mg)
    la = 0.0 if log_A is None else log_A
    log_f = safe_logaddexp(log_floor + log_1mg, la + log_g)
    if log_A is None:
        return log_f, log_1mfloor + log_1mg
    return log_f, safe_logaddexp(log_1mA + log_g, log_1mfloor + log_1mg)


def _safe_log(x):
    """log(x) for x >= 0 whose gradient at x = 0 is 0 instead of NaN (the value is -inf)."""
    ok = x > 0
    return jnp.where(ok, jnp.log(jnp.where(ok, x, 1.0)), -jnp.inf)


def logistic_mixture_logs(z, *, log_A=None, log_1mA=None, log_floor=None, log_1mfloor=None):
    """:func:`mixture_logs` of :func:`link_logs` for the logistic link, in fewer operations.

    With ``e = exp(-|z|)``, ``L = log(1 + e)``, ``r = floor / A`` and
    ``q = (1 - A) / (1 - floor)`` (both in [0, 1) because floor < A)::

        log f       = log A       - L + log(1 + r e)   (z >= 0),   log(r + e)   (z < 0)
        log(1 - f)  = log(1-floor) - L + log(e + q)     (z >= 0),   log(1 + q e) (z < 0)

    which follow from ``(1 - g) / g = exp(-z)``: every sum is of non-negative
    terms (no cancellation) and the cost is one exp, one log1p and two logs
    per cell instead of a softplus and two log-add-exps.  ``None`` arguments mean ``A = 1``
    or ``floor = 0`` as in :func:`mixture_logs`, with which the result agrees
    to rounding (see the tests); only when ``r`` or ``q`` underflows to 0
    *and* ``|z| > 745`` (parameters far outside any posterior) does it give
    ``-inf`` where the log-add-exp form stays finite.
    """
    z = jnp.clip(jnp.asarray(z, dtype=jnp.float64), -Z_CLIP, Z_CLIP)
    pos = z >= 0
    a = jnp.where(pos, z, -z)  # |z|, with the derivative of the branch in use at z = 0
    e = jnp.exp(-a)
    big_l = jnp.log1p(e)
    if log_floor is None:
        log_f = -big_l - jnp.where(pos, 0.0, a)  # log g
    else:
        r = jnp.exp(log_floor if log_A is None else log_floor - log_A)
        log_f = -big_l + _safe_log(jnp.where(pos, 1.0 + r * e, r + e))
    if log_A is not None:
        log_f = log_f + log_A
    if log_A is None:
        log_1mf = -big_l - jnp.where(pos, a, 0.0)  # log(1 - g)
    else:
        q = jnp.exp(log_1mA if log_1mfloor is None else log_1mA - log_1mfloor)
        log_1mf = -big_l + _safe_log(jnp.where(pos, e + q, 1.0 + q * e))
    if log_1mfloor is not None:
        log_1mf = log_1mf + log_1mfloor
    return log_f, log_1mf
