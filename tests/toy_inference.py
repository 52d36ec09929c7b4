"""A small self-contained JAX completeness model and its simulated data, shared by the inference and selection tests.

:class:`ToyModel` follows the model contract of ``comest_bayes.bayes.model.CompletenessModel`` (names,
ndim, initial, log_prob, value_and_grad, log_prob_batch, hessian, cell_loglik, transform, data.n,
data.k), so the inference code is tested independently of the production likelihood.
:func:`simulate_real` draws outcomes for the production model.  Every draw has a fixed seed.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np


jax.config.update("jax_enable_x64", True)


# --------------------------------------------------------------------------- a contract-following toy model


class ToyModel:
    """Logistic completeness on binomial cells, optionally with a covariate shifting m50.

    ``f = sigmoid((m50_0 + beta * d - m) / w)`` (plateau 1, floor 0).
    theta = ``[m50_0, log_w]`` or ``[m50_0, log_w, beta]`` (``covariate=True``).
    Priors: m50_0 ~ N(median(m), 5), log_w ~ N(log 0.3, 1), beta ~ N(0, 2).

    Parameters
    ----------
    m, d : array, shape (G,)
        Cell magnitudes and covariate.
    n, k : int array, shape (G,)
        Trials and successes per cell.
    covariate : bool
        Fit the slope ``beta`` of ``d``.
    """

    def __init__(self, m, d, n, k, *, covariate: bool = False):
        self.data = SimpleNamespace(n=np.asarray(n, dtype=np.int64), k=np.asarray(k, dtype=np.int64))
        self.covariate = covariate
        self.names = ["m50_0", "log_w"] + (["beta"] if covariate else [])
        self.ndim = len(self.names)
        self.mu = float(np.median(m))
        m_j, d_j = jnp.asarray(m, dtype=jnp.float64), jnp.asarray(d, dtype=jnp.float64)
        n_j, k_j = jnp.asarray(n, dtype=jnp.float64), jnp.asarray(k, dtype=jnp.float64)
        mu = self.mu

        def pairs(t):  # (G, 2): log f, log(1 - f), numerically stable
            beta = t[2] if covariate else 0.0
            z = (t[0] + beta * d_j - m_j) / jnp.exp(t[1])
            return jnp.stack([jax.nn.log_sigmoid(z), jax.nn.log_sigmoid(-z)], axis=-1)

        def log_prob(t):
            p = pairs(t)
            ll = jnp.sum(k_j * p[:, 0] + (n_j - k_j) * p[:, 1])
            lp = -0.5 * ((t[0] - mu) / 5.0) ** 2 - 0.5 * ((t[1] - jnp.log(0.3)) / 1.0) ** 2
            if covariate:
                lp = lp - 0.5 * (t[2] / 2.0) ** 2
            v = ll + lp
            return jnp.where(jnp.isfinite(v), v, -jnp.inf)

        self._lp = jax.jit(log_prob)
        self._vg = jax.jit(jax.value_and_grad(log_prob))
        self._batch = jax.jit(jax.vmap(log_prob))
        self._hess = jax.jit(jax.hessian(log_prob))
        self._cells = jax.jit(jax.vmap(pairs))

    def initial(self):
        return np.array([self.mu, math.log(0.3)] + ([0.0] if self.covariate else []))

    def log_prob(self, theta):
        return float(self._lp(jnp.asarray(theta, dtype=jnp.float64)))

    def value_and_grad(self, theta):
        v, g = self._vg(jnp.asarray(theta, dtype=jnp.float64))
        return float(v), np.asarray(g)

    def log_prob_batch(self, thetas):
        return np.asarray(self._batch(jnp.asarray(thetas, dtype=jnp.float64)))

    def hessian(self, theta):
        return np.asarray(self._hess(jnp.asarray(theta, dtype=jnp.float64)))

    def cell_loglik(self, thetas):
        return np.asarray(self._cells(jnp.asarray(thetas, dtype=jnp.float64)))

    def transform(self, theta):
        t = np.asarray(theta, dtype=np.float64)
        out = {"m50_0": float(t[0]), "w": float(np.exp(t[1]))}
        if self.covariate:
            out["beta"] = float(t[2])
        return out


def simulate(n_inj: int, seed: int, *, m50: float = 24.0, w: float = 0.25, beta: float = 0.0,
             m_range=(22.0, 26.0), d_sd: float = 0.4):
    """Bernoulli outcomes of the ToyModel's completeness at uniform magnitudes and N(0, d_sd) covariate."""
    rng = np.random.default_rng(seed)
    m = rng.uniform(*m_range, n_inj)
    d = rng.normal(0.0, d_sd, n_inj)
    f = 1.0 / (1.0 + np.exp(-(m50 + beta * d - m) / w))
    return m, d, rng.random(n_inj) < f


def compress_toy(m, d, detected, *, dm: float = 0.01, dd: float | None = 0.02):
    """Exact-enough binomial cells on a (m, d) grid; returns m, d, n, k per cell and each injection's cell."""
    im = np.round(m / dm).astype(np.int64)
    idd = np.round(d / dd).astype(np.int64) if dd else np.zeros_like(im)
    keys, inv = np.unique(np.stack([im, idd], axis=1), axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    n = np.bincount(inv)
    k = np.bincount(inv, weights=detected.astype(np.float64)).astype(np.int64)
    return keys[:, 0] * dm, keys[:, 1] * (dd or 0.0), n, k, inv


def toy_model(n_inj, seed, *, covariate=False, beta=0.0, dm=0.01, dd=0.02, **kw):
    m, d, det = simulate(n_inj, seed, beta=beta, **kw)
    mc, dc, n, k, _ = compress_toy(m, d, det, dm=dm, dd=dd if covariate else None)
    return ToyModel(mc, dc, n, k, covariate=covariate)


# --------------------------------------------------------------------------- the production model


def simulate_real(n_inj: int, seed: int, *, beta_depth: float = 1.0, m50: float = 24.5, w: float = 0.2,
                  A: float = 0.97, floor: float = 0.01, depth_sd: float = 0.3):
    """Outcomes of ``floor + (A - floor) sigmoid((m50 + beta_depth d - m) / w)``, m ~ U(22, 27), d ~ N(0, depth_sd)."""
    from comest_bayes.bayes.outcomes import Covariates

    rng = np.random.default_rng(seed)
    m = rng.uniform(22.0, 27.0, n_inj)
    d = rng.normal(0.0, depth_sd, n_inj)
    g = 1.0 / (1.0 + np.exp(-(m50 + beta_depth * d - m) / w))
    return Covariates.make(m, depth=d), rng.random(n_inj) < floor + (A - floor) * g
