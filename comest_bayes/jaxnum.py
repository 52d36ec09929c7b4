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

__all__ = ["jax", "jnp", "jit", "stored_jit", "export_folder", "compiler_options"]

#: XLA options of most of the completeness model's programs (:class:`stored_jit`) on the CPU.  These
#: programs are small and a fit calls most of them a few hundred times, so on a machine's first run
#: their compiles cost more than their evaluations.  On the demo's fit, XLA's default fusion
#: emitters spent 5.3 CPU-s compiling its ten programs and the older emitters
#: (``xla_cpu_use_fusion_emitters`` False) 3.5 CPU-s; a user's first ``comest-bayes demo`` fitted in
#: 8.1-9.0 CPU-s instead of 10.4-10.7, and later runs as fast as before.  Two kinds of program keep
#: XLA's defaults, which run them faster: the batched log posterior (20-30% faster at 768 cells),
#: which emcee's walkers call at every step, and NUTS's (12-37% faster).  The numbers are the same:
#: every program gave bit-identical outputs but the per-cell Jacobian (LOO, the width test), which
#: differed by at most 7e-16 relative.  Measured by ``benchmarks/bench_compile_options.py``.
CPU_COMPILER_OPTIONS = {"xla_cpu_use_fusion_emitters": False}
_OPTIONS: list = []


_FOLDERS: dict = {}
#: False once serialization turned out to be unavailable in this process (then stored_jit is jax.jit).
_EXPORT_WORKS = [True]


def compiler_options() -> dict:
    """The XLA options :func:`jit` compiles with: :data:`CPU_COMPILER_OPTIONS` on the CPU, if this jaxlib has them.

    Tried once per process on a one-line program; a jaxlib that does not know an option (an older or
    a newer one) or another backend gets no options, i.e. XLA's defaults.
    """
    if not _OPTIONS:
        opts = dict(CPU_COMPILER_OPTIONS) if jax.default_backend() == "cpu" else {}
        if opts:
            try:
                jax.jit(lambda x: x + 1.0, compiler_options=opts).lower(1.0).compile()
            except Exception:  # TypeError: a jax.jit without compiler_options; XlaRuntimeError: an unknown option
                opts = {}
        _OPTIONS.append(opts)
    return _OPTIONS[0]


def jit(fn, **kwargs):
    """``jax.jit`` with :func:`compiler_options`: for programs that compile for longer than they run."""
    opts = compiler_options()
    return jax.jit(fn, compiler_options=opts, **kwargs) if opts else jax.jit(fn, **kwargs)


def export_folder():
    """Where :class:`stored_jit` keeps programs: ``exports`` in the compilation cache, None when that is off."""
    cache = jax.config.jax_compilation_cache_dir
    if cache not in _FOLDERS:
        from pathlib import Path

        _FOLDERS[cache] = Path(cache) / "exports" if cache else None
    return _FOLDERS[cache]


class stored_jit:
    """``jax.jit`` that keeps each traced program on disk and loads it in later processes.

    A process pays for every program it uses the Python trace and the lowering to StableHLO, even
    when JAX's persistent compilation cache holds the compiled code (the cache key is computed from
    the lowered program).  For the completeness likelihood that is about a second per process.  When
    the compilation cache is on (:func:`comest_bayes.runtime.configure`), this wrapper exports the
    program of each (static arguments, argument shapes) with :mod:`jax.export` into
    ``<compilation cache>/exports`` and later processes deserialize it instead of tracing it: the
    same StableHLO, hence the same compiled code and the same numbers.  The file name holds a digest
    of ``sources`` (the files whose code is traced), of the JAX version and of the call's signature,
    so a changed source never loads an old program.  Without the compilation cache it is :func:`jit`
    (``jax.jit`` with ``quick_compile`` False).

    Parameters
    ----------
    fn : callable
        The function to compile; positional arguments only.
    static_argnums : int or tuple of int
        As for ``jax.jit`` (hashable values with a stable ``repr``).
    sources : sequence of path
        Files whose contents determine what ``fn`` computes.
    name : str, optional
        Label of the stored files (default ``fn.__name__``).
    quick_compile : bool
        Compile with :func:`compiler_options` (:func:`jit`); False for XLA's defaults, for a program
        evaluated so often that its speed matters more than its compile.
    """

    def __init__(self, fn, static_argnums=(), *, sources=(), name=None, quick_compile=True):
        self._fn = fn
        self._jit_of = jit if quick_compile else jax.jit
        self._static = (static_argnums,) if isinstance(static_argnums, int) else tuple(static_argnums)
        self._plain = None
        self._sources = tuple(str(s) for s in sources)
        self._name = name or getattr(fn, "__name__", "fn")
        self._calls = {}
        self._digest = None

    @property
    def _jit(self):
        """The program without storage (made on first use: :func:`compiler_options` needs the backend)."""
        if self._plain is None:
            self._plain = self._jit_of(self._fn, static_argnums=self._static)
        return self._plain

    def _source_digest(self) -> str:
        if self._digest is None:
            import hashlib

            h = hashlib.sha256(f"{jax.__version__} x64={jax.config.jax_enable_x64}".encode())
            for path in self._sources:
                with open(path, "rb") as fh:
                    h.update(fh.read())
            self._digest = h.hexdigest()
        return self._digest

    def __call__(self, *args):
        folder = export_folder()
        if folder is None or not _EXPORT_WORKS[0]:
            return self._jit(*args)
        static = tuple(args[i] for i in self._static)
        dyn = [a for i, a in enumerate(args) if i not in self._static]
        leaves, tree = jax.tree_util.tree_flatten(dyn)
        # the signature from attributes (called for every evaluation: jnp.shape / result_type cost 25 us a leaf)
        sig = tuple((x.shape, x.dtype, getattr(x, "weak_type", False)) if hasattr(x, "dtype") else ((), type(x).__name__, True)
                    for x in leaves)
        key = (static, tree, sig)
        call = self._calls.get(key)
        if call is None:
            call = self._calls[key] = self._load_or_export(folder, key, args, dyn)
        return call(*dyn)

    def _load_or_export(self, folder, key, args, dyn):
        import hashlib
        import os

        from jax import export

        static, tree, sig = key
        text = repr((self._source_digest(), self._name, repr(static), str(tree),
                     [(tuple(shape), str(dtype), bool(weak)) for shape, dtype, weak in sig]))
        digest = hashlib.sha256(text.encode()).hexdigest()[:40]
        path = folder / f"{self._name}-{digest}.jaxexport"
        try:
            return self._jit_of(export.deserialize(bytearray(path.read_bytes())).call)
        except Exception:  # not stored yet, or unreadable (a partial or foreign file): trace and store it again
            pass
        positions = [i for i in range(len(args)) if i not in self._static]
        fixed = {i: args[i] for i in self._static}

        def bound(*values):
            full = dict(fixed)
            full.update(zip(positions, values))
            return self._fn(*(full[i] for i in range(len(args))))

        exported = export.export(jax.jit(bound))(*dyn)
        try:
            blob = exported.serialize()
        except ImportError:
            # jax.export serializes with the optional `flatbuffers` package (a dependency of this
            # package; missing only where it was removed): fall back to plain jit for the process
            _EXPORT_WORKS[0] = False

            def unstored(*values):
                full = dict(fixed)
                full.update(zip(positions, values))
                return self._jit(*(full[i] for i in range(len(args))))

            return unstored
        try:
            folder.mkdir(parents=True, exist_ok=True)
            tmp = folder / f".tmp-{os.getpid()}-{path.name}"
            tmp.write_bytes(blob)
            os.replace(tmp, path)
        except OSError:  # a read-only cache: this process still uses the program it traced
            pass
        return self._jit_of(exported.call)
