"""Stage 6: the Bayesian completeness (and purity) model.

Modules: ``spec`` (declarative model specifications in ``models/``), ``likelihood``, ``shapes``
(transition shapes), ``inference`` (MAP, Laplace, importance sampling, emcee), ``psis``,
``selection`` (the ladder of rungs), ``checks`` (posterior predictive shape check),
``posterior`` (curves, maps, queries), ``fit`` (one kind's fit, end to end).
"""
