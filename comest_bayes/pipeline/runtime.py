"""Process-wide settings of the numerical runtime (JAX/XLA threads, compilation cache).

The command line calls :func:`configure` once, before any JAX computation, and the worker
processes inherit its environment; Python users who import the package are not affected unless
they call it.  Threads, core pinning and the cache: ``docs/compute.md``.
"""

from __future__ import annotations

import os
from pathlib import Path
import sys

__all__ = ["configure", "cache_dir", "pin_to_one_core", "one_core"]

_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
_XLA_ONE_THREAD = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"


def cache_dir() -> Path:
    """Folder of the persistent JAX compilation cache."""
    env = os.environ.get("COMEST_BAYES_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "comest-bayes" / "jax"


def configure(threads: int | None = 1, *, cache: bool = True) -> None:
    """Limit the numerical threads of this process (and its future children) and enable the cache.

    Parameters
    ----------
    threads : int or None
        1 pins XLA and BLAS to one thread per process; None leaves them alone.
    cache : bool
        Use the persistent compilation cache (:func:`cache_dir`); silently
        skipped when the folder cannot be created (a read-only home).
    """
    if threads == 1:
        flags = os.environ.get("XLA_FLAGS", "")
        if "intra_op_parallelism_threads" not in flags:
            os.environ["XLA_FLAGS"] = (flags + " " + _XLA_ONE_THREAD).strip()
        for var in _THREAD_VARS:
            os.environ.setdefault(var, "1")
    if cache:
        path = cache_dir()
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError:
            return
        os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(path))
        os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")

        if "jax" in sys.modules:  # already imported: set the options directly
            import jax

            jax.config.update("jax_compilation_cache_dir", str(path))
            jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)


def pin_to_one_core(index: int = 0) -> int | None:
    """Restrict this process to one of the cores it may use (``index`` modulo their number).

    Returns the core, or None where affinity cannot be set (not Linux).
    """
    try:
        cores = sorted(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return None
    if not cores:  # pragma: no cover
        return None
    core = cores[int(index) % len(cores)]
    if len(cores) > 1:
        try:
            os.sched_setaffinity(0, {core})
        except OSError:  # pragma: no cover - a sandbox that forbids it
            return None
    return core


class one_core:
    """Context manager: this process on one core inside the block, its former cores restored after."""

    def __enter__(self):
        try:
            self._before = os.sched_getaffinity(0)
        except AttributeError:  # pragma: no cover - not Linux
            self._before = None
        if self._before is not None:
            pin_to_one_core(0)
        return self

    def __exit__(self, *exc):
        if self._before is not None:
            try:
                os.sched_setaffinity(0, self._before)
            except OSError:  # pragma: no cover
                pass
        return False
