"""JAX in double precision: the one place in the package that switches it on.

The completeness model (:mod:`comest_bayes.bayes.model`), the number-counts model (:mod:`comest_bayes.lf.counts`)
and the luminosity-function model (:mod:`comest_bayes.lf.model`) need float64: binomial log-likelihoods
summed over up to 10^6 outcomes, spline integrals and the Hessians of the Laplace approximation lose
their accuracy in float32.  JAX's precision is one switch per process (``jax_enable_x64``).  It is
turned on here, when one of those modules is first imported; ``import comest_bayes`` (the front door)
does not import them and leaves JAX alone.  A program that also runs its own JAX code in float32
should create its arrays with explicit dtypes (docs/bayesian.md, "Precision").
"""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

__all__ = ["jax", "jnp"]
