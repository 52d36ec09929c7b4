"""Stage 4: recovery of the injected sources.

Modules: ``realization`` (inject, detect, match one realization; merge many), ``matching``
(one-to-one truth-to-detection matching), ``transfer`` (measured given true magnitude).
"""
