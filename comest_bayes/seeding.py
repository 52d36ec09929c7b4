"""Every random number of a run derives from one root seed.

A stream is named by a path of keys (strings or integers), for example
``(Stream.SOURCEFREE,)`` or ``(Stream.INJECT, "point", 7)``.  The path is turned into a
:class:`numpy.random.SeedSequence` spawn key, so the numbers of a stream depend
only on the root seed and its name: never on how many processes ran, in what
order tasks finished, or which other streams were used before.

The package's own stream names are the constants of :class:`Stream`; a seed is a :data:`Seed`,
and :func:`seed_sequence` is the one place a seed and a stream name become a SeedSequence
(:func:`rng_for` and :func:`int_seed_for` are built on it).
"""

from __future__ import annotations

import zlib
from typing import Union

import numpy as np

__all__ = ["Seed", "Stream", "seed_sequence", "rng_for", "int_seed_for"]

#: A seed as the package takes it: a non-negative integer (a run's root seed, or a seed derived from
#: it with :func:`int_seed_for`) or a :class:`numpy.random.SeedSequence` (a stream made by
#: :func:`seed_sequence`).  A SeedSequence's names continue its own path:
#: ``seed_sequence(seed_sequence(7, "a"), "b")`` is ``seed_sequence(7, "a", "b")``.
Seed = Union[int, np.integer, np.random.SeedSequence]


class Stream:
    """The names of the package's random streams (the first key of a stream's path), with their users.

    The values are part of the numbers a run draws: changing one changes every number of its
    stream.  Keys after the first (a kind, a realization index) follow in brackets; a stream
    marked *under X* starts from the integer seed of stream X, not from the run's root seed.
    """

    # -- pipeline, from the run's root seed (RunConfig.seed)
    #: ``pipeline.stages``: the sky noise that replaces the detected sources (the source-free image).
    SOURCEFREE = "sourcefree"
    #: ``recover.realization``: what is injected and where (kind, realization index).
    INJECT = "inject"
    #: ``recover.realization`` and ``report.rundata``: the photon noise of the rendered stamps (kind, index).
    RENDER = "render"
    #: ``pipeline.stages``: the seed of one kind's adaptive design fits (kind).
    ADAPTIVE = "adaptive"
    #: ``pipeline.adaptive``, under ADAPTIVE: the magnitudes drawn from a batch's design (batch).
    DESIGN = "design"
    #: ``pipeline.adaptive``, under ADAPTIVE: the root seed of a batch's design fit (batch).
    DESIGN_FIT = "design-fit"
    #: ``bayes.fit``: the seed of one fit (quantity, kind); the streams below start from it.
    FIT = "fit"

    # -- one fit, under FIT
    #: ``bayes.fit``: the sample of unmasked pixels stored with a posterior.
    FOOTPRINT = "footprint"
    #: ``bayes.selection``: the seed of one candidate of the selection (candidate name).
    SELECT = "select"
    #: ``bayes.selection``, under SELECT: the MAP of one value of a spline's smoothness (``repr(tau)``).
    TAU = "tau"
    #: ``bayes.selection``, under SELECT: the Laplace draws that score a candidate.
    LAPLACE_DRAWS = "laplace-draws"
    #: ``bayes.inference``: the random starts of the MAP search.
    MAP_STARTS = "map-starts"
    #: ``bayes.inference``: the initial positions of the emcee walkers.
    WALKERS = "walkers"
    #: ``bayes.inference``: the seed of emcee's own random state.
    EMCEE = "emcee"
    #: ``bayes.inference``: the draws of the importance sampler.
    IMPORTANCE = "importance"
    #: ``bayes.inference``: the draws of its second try, with heavier tails, where the first fails.
    IMPORTANCE_TAILS = "importance-tails"
    #: ``bayes.inference``: the starting points and the random keys of the NUTS chains.
    NUTS = "nuts"

    # -- binned ratios, from the run's root seed
    #: ``ratios.binned``: the drawn curves whose first crossings give the binned m50's spread.
    CROSSING = "crossing"

    # -- number counts (lf), from the seed given to lf.model.fit_counts
    #: ``lf.model``: the starting points of an LF model.
    LF_INITIAL = "lf-initial"
    #: ``lf.model``: the seeds of the LF fits, followed by one of the four keys below.
    LF = "lf"
    #: ``lf.model``, after LF: the fit with completeness and transfer fixed.
    LF_FIXED = "fixed"
    #: ``lf.model``, after LF: the joint fit.
    LF_JOINT = "joint"
    #: ``lf.model``, after LF: the fit of one completeness draw of the marginal mode (draw index).
    LF_MARGINAL = "marginal"
    #: ``lf.model``, after LF: which completeness draws the marginal mode uses.
    LF_MARGINAL_DRAWS = "marginal-draws"
    #: ``lf.model``, after LF: the Poisson replicates of the posterior predictive check of the counts.
    LF_CHECK = "check"

    # -- data with known truths (sim), from the seed given to them
    #: ``sim.analytic``: the white noise of the closed-form detection check.
    ANALYTIC_NOISE = "analytic-noise"
    #: ``sim.demo``: the demo tile, followed by one of the four keys below.
    DEMO = "demo"
    #: ``sim.demo``, after DEMO: the galaxies of the tile.
    DEMO_GALAXIES = "galaxies"
    #: ``sim.demo``, after DEMO: the stars.
    DEMO_STARS = "stars"
    #: ``sim.demo``, after DEMO: the bright (saturated) stars.
    DEMO_BRIGHT_STARS = "bright_stars"
    #: ``sim.demo``, after DEMO: the sky noise.
    DEMO_NOISE = "noise"


def _key(part) -> int:
    if isinstance(part, (int, np.integer)) and not isinstance(part, bool):
        if part < 0:
            raise ValueError(f"stream key {part} must be non-negative")
        return int(part)
    if isinstance(part, str):
        # crc32 is stable across processes and Python versions (unlike hash()).
        return zlib.crc32(part.encode("utf-8")) + (1 << 32)
    raise TypeError(f"stream keys are str or non-negative int, got {part!r}")


def seed_sequence(seed: Seed, *names) -> np.random.SeedSequence:
    """The SeedSequence of the stream ``names`` under ``seed`` (a :data:`Seed`).

    An integer seed is the SeedSequence's entropy and the names its spawn key; a SeedSequence
    seed keeps its entropy and has the names appended to its spawn key.  With no names, the
    integer ``s`` gives ``SeedSequence(s)``: the numbers of ``numpy.random.default_rng(s)``.
    """
    keys = tuple(_key(n) for n in names)
    if isinstance(seed, np.random.SeedSequence):
        return np.random.SeedSequence(seed.entropy, spawn_key=tuple(seed.spawn_key) + keys,
                                      pool_size=seed.pool_size)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"the root seed must be a non-negative integer or a numpy SeedSequence, got {seed!r}")
    return np.random.SeedSequence(int(seed), spawn_key=keys)


def rng_for(seed: Seed, *names) -> np.random.Generator:
    """A NumPy Generator (PCG64) for the stream ``names`` under ``seed``."""
    return np.random.Generator(np.random.PCG64(seed_sequence(seed, *names)))


def int_seed_for(seed: Seed, *names) -> int:
    """A 31-bit integer seed for libraries that take one (GalSim's BaseDeviate, emcee)."""
    return int(seed_sequence(seed, *names).generate_state(1, dtype=np.uint32)[0] & 0x7FFFFFFF) or 1
