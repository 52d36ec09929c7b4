"""The products a person reads: the HTML report and the figures.

Modules: ``html`` (the self-contained report), ``rundata`` (reading a run for the figures),
``plots`` (matplotlib figures; no I/O).
"""
