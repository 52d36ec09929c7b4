"""Every random number of a run derives from one root seed (comest_bayes.seeding): streams depend only on the
root seed and their name, as NumPy SeedSequence spawn keys.
"""

import ast
import zlib
from pathlib import Path

import numpy as np
import pytest

import comest_bayes
from comest_bayes.seeding import Stream, int_seed_for, rng_for, seed_sequence


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
    ("7", (), ValueError, "non-negative integer or a numpy SeedSequence"),
    (3, (-1,), ValueError, "stream key -1 must be non-negative"),
    (3, (True,), TypeError, "stream keys are str or non-negative int"),
    (3, (2.0,), TypeError, "stream keys are str or non-negative int"),
])
def test_bad_seeds_and_keys_are_refused(root, names, error, message):
    with pytest.raises(error, match=message):
        seed_sequence(root, *names)


#: The stream names as the runs published so far drew them: a changed value changes every number of its
#: stream, so this table changes only with a deliberate break of reproducibility.
PUBLISHED_STREAMS = {
    "SOURCEFREE": "sourcefree", "INJECT": "inject", "RENDER": "render", "ADAPTIVE": "adaptive", "DESIGN": "design",
    "DESIGN_FIT": "design-fit", "FIT": "fit", "FOOTPRINT": "footprint", "SELECT": "select", "TAU": "tau",
    "LAPLACE_DRAWS": "laplace-draws", "MAP_STARTS": "map-starts", "WALKERS": "walkers", "EMCEE": "emcee",
    "IMPORTANCE": "importance", "IMPORTANCE_TAILS": "importance-tails", "NUTS": "nuts", "CROSSING": "crossing", "LF_INITIAL": "lf-initial", "LF": "lf", "LF_FIXED": "fixed", "LF_JOINT": "joint",
    "LF_MARGINAL": "marginal", "LF_MARGINAL_DRAWS": "marginal-draws", "LF_CHECK": "check", "ANALYTIC_NOISE": "analytic-noise",
    "DEMO": "demo", "DEMO_GALAXIES": "galaxies", "DEMO_STARS": "stars", "DEMO_BRIGHT_STARS": "bright_stars",
    "DEMO_NOISE": "noise",
}


def test_the_stream_names_are_the_published_ones():
    names = {k: v for k, v in vars(Stream).items() if k.isupper()}
    assert names == PUBLISHED_STREAMS


def test_a_stream_constant_draws_the_numbers_of_its_published_name():
    # the values below were drawn with the string literals before the constants existed (commit e5c9ed9)
    assert int_seed_for(0, Stream.FIT, "completeness", "point") == 667092187
    assert int_seed_for(2024, Stream.SELECT, "spline_depth") == 666481000
    assert int_seed_for(5, Stream.LF, Stream.LF_MARGINAL, 3) == 150866458
    assert rng_for(7, Stream.DEMO, Stream.DEMO_GALAXIES).random() == 0.07292515357810947
    # the same constant twice, the same numbers; another stream, others
    a = rng_for(7, Stream.INJECT, "buldisk", 2).random(3)
    assert a[0] == 0.37413998850091434
    np.testing.assert_array_equal(a, rng_for(7, Stream.INJECT, "buldisk", 2).random(3))
    assert not np.array_equal(a, rng_for(7, Stream.RENDER, "buldisk", 2).random(3))


def test_a_seed_sequence_seed_continues_its_path():
    # seed_sequence(seed_sequence(7, a), b) is seed_sequence(7, a, b): a stage handed a stream can name sub-streams
    inner = seed_sequence(7, Stream.INJECT, "point")
    assert seed_sequence(inner, 3).spawn_key == seed_sequence(7, Stream.INJECT, "point", 3).spawn_key
    np.testing.assert_array_equal(rng_for(inner, 3).random(4), rng_for(7, Stream.INJECT, "point", 3).random(4))
    assert int_seed_for(inner, 3) == int_seed_for(7, Stream.INJECT, "point", 3)
    # with no names, a seed draws what numpy.random.default_rng draws from it (sourcefree, render rely on it)
    np.testing.assert_array_equal(rng_for(11).random(4), np.random.default_rng(11).random(4))
    np.testing.assert_array_equal(rng_for(inner).random(4), np.random.default_rng(inner).random(4))


def _stream_literals(path: Path) -> list[str]:
    """``file:line`` of every call of seed_sequence / rng_for / int_seed_for naming a stream by a string literal."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Call):
            fn = node.func.id if isinstance(node.func, ast.Name) else getattr(node.func, "attr", None)
            if fn in ("seed_sequence", "rng_for", "int_seed_for") and any(
                    isinstance(a, ast.Constant) and isinstance(a.value, str) for a in node.args[1:]):
                out.append(f"{path.name}:{node.lineno}")
    return out


def test_the_package_names_its_streams_only_by_the_constants():
    root = Path(comest_bayes.__file__).resolve().parent
    found = [hit for path in sorted(root.rglob("*.py")) for hit in _stream_literals(path)]
    assert found == []
    # the scan sees a literal where there is one
    probe = Path(__file__).resolve()
    assert _stream_literals(probe)  # this file calls rng_for(7, "inject", "point", 3)


def _direct_generators(path: Path) -> list[str]:
    """``file:line`` of every ``default_rng(...)`` call and ``RandomState(...)`` not seeded by ``int_seed_for``."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Call):
            fn = node.func.id if isinstance(node.func, ast.Name) else getattr(node.func, "attr", None)
            seeded = (node.args and isinstance(node.args[0], ast.Call)
                      and getattr(node.args[0].func, "id", None) == "int_seed_for")
            # emcee takes a legacy RandomState: allowed when its seed is a stream's (int_seed_for)
            if fn == "default_rng" or (fn == "RandomState" and not seeded):
                out.append(f"{path.name}:{node.lineno}")
    return out


def test_every_generator_of_the_package_comes_from_seeding():
    # one home for random numbers: a generator made directly (np.random.default_rng) would escape the
    # root seed's streams; rng_for(s) gives the numbers default_rng(s) gives, so nothing needs it
    root = Path(comest_bayes.__file__).resolve().parent
    found = [hit for path in sorted(root.rglob("*.py")) if path.name != "seeding.py"
             for hit in _direct_generators(path)]
    assert found == []
    assert _direct_generators(Path(__file__).resolve())  # the scan sees one where there is one
    np.testing.assert_array_equal(rng_for(11).random(4), np.random.default_rng(11).random(4))
