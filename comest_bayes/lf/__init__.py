"""Number counts (luminosity function) forward-modelled through completeness and transfer.

Modules: ``counts`` (count models declared in ``models/counts/``), ``fit``.
"""

#: How the completeness uncertainty enters a count fit (:func:`comest_bayes.lf.fit.run_lf`).
MODES = ("joint", "marginal", "fixed")
#: Samplers of :func:`comest_bayes.bayes.inference.fit` the count fits accept.
SAMPLERS = ("auto", "emcee", "importance")
