"""Every random number of a run derives from one root seed.

A stream is named by a path of keys (strings or integers), for example
``("sourcefree",)`` or ``("inject", "point", 7)``.  The path is turned into a
:class:`numpy.random.SeedSequence` spawn key, so the numbers of a stream depend
only on the root seed and its name: never on how many processes ran, in what
order tasks finished, or which other streams were used before.
"""

from __future__ import annotations

import zlib

import numpy as np

__all__ = ["seed_sequence", "rng_for", "int_seed_for"]


def _key(part) -> int:
    if isinstance(part, (int, np.integer)) and not isinstance(part, bool):
        if part < 0:
            raise ValueError(f"stream key {part} must be non-negative")
        return int(part)
    if isinstance(part, str):
        # crc32 is stable across processes and Python versions (unlike hash()).
        return zlib.crc32(part.encode("utf-8")) + (1 << 32)
    raise TypeError(f"stream keys are str or non-negative int, got {part!r}")


def seed_sequence(root_seed: int, *names) -> np.random.SeedSequence:
    """The SeedSequence of the stream ``names`` under ``root_seed``."""
    if isinstance(root_seed, bool) or not isinstance(root_seed, (int, np.integer)) or root_seed < 0:
        raise ValueError(f"the root seed must be a non-negative integer, got {root_seed!r}")
    return np.random.SeedSequence(int(root_seed), spawn_key=tuple(_key(n) for n in names))


def rng_for(root_seed: int, *names) -> np.random.Generator:
    """A NumPy Generator for the stream ``names``."""
    return np.random.Generator(np.random.PCG64(seed_sequence(root_seed, *names)))


def int_seed_for(root_seed: int, *names) -> int:
    """A 31-bit integer seed for libraries that take one (GalSim's BaseDeviate, emcee)."""
    return int(seed_sequence(root_seed, *names).generate_state(1, dtype=np.uint32)[0] & 0x7FFFFFFF) or 1
