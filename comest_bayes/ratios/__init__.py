"""Stage 5: the raw binned ratios of the paper and the depth references.

Modules: ``binned`` (completeness, purity, detection rate and their maps), ``depth``
(depth references), ``summary`` (the binned part of ``summary.json``).
"""
