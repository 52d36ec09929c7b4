"""Number counts (luminosity function) forward-modelled through completeness and transfer.

Modules: ``counts`` (count models declared in ``models/counts/``), ``fit``.
"""
