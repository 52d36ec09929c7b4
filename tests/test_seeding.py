"""Every random number of a run derives from one root seed (comest_bayes.seeding): streams depend only on the
root seed and their name, as NumPy SeedSequence spawn keys.
"""

import zlib

import numpy as np
import pytest

from comest_bayes.seeding import int_seed_for, rng_for, seed_sequence


def test_seed_streams_depend_only_on_root_and_name():
    a = rng_for(7, "inject", "point", 3).normal(size=5)
    # drawing from other streams first must not change this one
    rng_for(7, "inject", "point", 2).normal(size=100)
    b = rng_for(7, "inject", "point", 3).normal(size=5)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, rng_for(8, "inject", "point", 3).normal(size=5))
    assert not np.array_equal(a, rng_for(7, "inject", "buldisk", 3).normal(size=5))
    assert int_seed_for(7, "x") == int_seed_for(7, "x") > 0
    with pytest.raises(ValueError, match="non-negative"):
        seed_sequence(-1)


def test_the_spawn_key_is_the_stream_name():
    # integers are themselves, strings their CRC-32 plus 2^32 (so "3" and 3 are different streams)
    seq = seed_sequence(7, "inject", np.int64(3))
    assert seq.entropy == 7 and seq.spawn_key == (zlib.crc32(b"inject") + 2 ** 32, 3)
    assert seed_sequence(7, "3").spawn_key != seed_sequence(7, 3).spawn_key
    # rng_for is PCG64 on that sequence: the numbers are fixed for good, across processes and versions
    expected = np.random.Generator(np.random.PCG64(np.random.SeedSequence(7, spawn_key=seq.spawn_key))).random(4)
    np.testing.assert_array_equal(rng_for(7, "inject", 3).random(4), expected)


def test_integer_seeds_are_positive_31_bit_numbers_of_the_stream():
    seeds = {int_seed_for(11, "emcee", i) for i in range(200)}
    assert len(seeds) == 200 and all(1 <= s < 2 ** 31 for s in seeds)
    state = seed_sequence(11, "emcee", 0).generate_state(1, dtype=np.uint32)[0]
    assert int_seed_for(11, "emcee", 0) == (int(state) & 0x7FFFFFFF or 1)


@pytest.mark.parametrize("root, names, error, message", [
    (True, (), ValueError, "non-negative integer"),
    (1.5, (), ValueError, "non-negative integer"),
    (3, (-1,), ValueError, "stream key -1 must be non-negative"),
    (3, (True,), TypeError, "stream keys are str or non-negative int"),
    (3, (2.0,), TypeError, "stream keys are str or non-negative int"),
])
def test_bad_seeds_and_keys_are_refused(root, names, error, message):
    with pytest.raises(error, match=message):
        seed_sequence(root, *names)
