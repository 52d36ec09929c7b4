"""Orchestration of the stages into a run directory.

Modules: ``stages`` (the run, stage by stage), ``adaptive`` (sequential batches to a precision
target), ``preflight`` (checks before the first byte), ``executors`` (serial, processes, Dask),
``runtime`` (JAX/XLA threads, compilation cache), ``progress`` (what a run says as it works).
"""
