"""The posterior draws every sampler returns (:class:`PosteriorSamples`), apart from the samplers themselves.

:mod:`comest_bayes.bayes.inference` (importance sampling, emcee) and :mod:`comest_bayes.bayes.nuts` both
return it; it lives here so that neither sampler module imports the other's.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the annotations only: the configuration imports SAMPLERS, and `import comest_bayes` no numpy
    import numpy as np

__all__ = ["PosteriorSamples", "SAMPLERS"]

#: The posterior samplers of :func:`comest_bayes.bayes.inference.fit` and ``fit.sampler`` (named here, where
#: the configuration can read them without importing JAX).
SAMPLERS = ("auto", "importance", "nuts", "emcee")


@dataclass
class PosteriorSamples:
    """Posterior draws of a sampler (emcee's :func:`~comest_bayes.bayes.inference.sample_posterior`,
    :func:`~comest_bayes.bayes.inference.importance_posterior`, :func:`~comest_bayes.bayes.nuts.nuts_posterior`).

    Attributes
    ----------
    samples : ndarray, shape (S, D)
        Equal-weight draws of the unconstrained ``theta``.  emcee's are the post-burn-in steps, flattened
        step-major (row ``s * nwalkers + w`` is walker ``w`` at kept step ``s``); NUTS's likewise with its
        chains for walkers; importance sampling's are resampled from its weighted proposal draws.
    chain : ndarray, shape (steps, walkers, D)
        emcee's whole chain, burn-in included; NUTS's kept draws (draws, chains, D); importance sampling's
        proposal draws (N, 1, D).
    log_prob : ndarray, shape (steps, walkers)
        Log posterior of every ``chain`` position.
    diagnostics : PosteriorDiagnostics, ImportanceDiagnostics or NutsDiagnostics
        The sampler's own; each has ``converged``, ``warnings`` and ``to_dict()`` (with ``method``).
    """

    samples: np.ndarray
    chain: np.ndarray
    log_prob: np.ndarray
    diagnostics: object
