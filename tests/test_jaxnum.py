"""comest_bayes.jaxnum: importing it, or a module that needs float64, switches JAX to 64-bit (the front door
does not; each such case runs in a fresh Python, since the switch is per process); stored_jit traces a
program once, stores it with jax.export, and later processes load it with the same numbers."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from comest_bayes import jaxnum
from comest_bayes.jaxnum import jax, jnp, stored_jit
from conftest import REPO_ROOT

CODE = """
import json, sys
{before}
import jax.numpy as jnp
print(json.dumps({{"dtype": str(jnp.ones(1).dtype), "jax": "jax" in sys.modules}}))
"""


def _run(before: str) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    env["PYTHONPATH"] = str(REPO_ROOT)
    out = subprocess.run([sys.executable, "-c", CODE.format(before=before)], capture_output=True, text=True,
                         env=env, timeout=180)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("before, dtype", [
    ("import jax", "float32"),                                   # JAX's own default: the control
    ("import comest_bayes", "float32"),                          # the front door leaves JAX alone
    ("import comest_bayes.jaxnum", "float64"),
    ("from comest_bayes.jaxnum import jnp as _j", "float64"),
    ("import comest_bayes.bayes.model", "float64"),              # the likelihood needs float64
    ("import comest_bayes.lf.counts", "float64"),                # so does the count model
])
def test_double_precision_is_switched_on_by_the_modules_that_need_it(before, dtype):
    assert _run(before)["dtype"] == dtype


# --------------------------------------------------------------------------- stored_jit

def _counting(counter):
    def f(st, x, pair):
        counter["traces"] += 1  # runs at trace time only
        a, b = pair
        return jnp.sum(jnp.exp(-st * x) * a) + jnp.log1p(b)

    return f


def test_stored_jit_loads_the_stored_program_without_tracing_and_gives_the_same_numbers(tmp_path, monkeypatch):
    x = np.linspace(0.0, 1.0, 7)
    pair = (np.arange(7.0), jnp.asarray(0.5))
    counter = {"traces": 0}
    plain = jax.jit(_counting({"traces": 0}), static_argnums=0)(2.0, x, pair)
    # without a compilation cache folder it is jax.jit
    monkeypatch.setattr(jaxnum, "export_folder", lambda: None)
    assert float(stored_jit(_counting(counter), 0, sources=[__file__])(2.0, x, pair)) == float(plain)
    assert counter["traces"] == 1
    assert not (tmp_path / "exports").exists()
    # with one: the first instance (a process) traces and stores, a second one only loads
    monkeypatch.setattr(jaxnum, "export_folder", lambda: tmp_path / "exports")
    first = stored_jit(_counting(counter), 0, sources=[__file__], name="f")
    assert float(first(2.0, x, pair)) == float(plain)
    assert counter["traces"] == 2
    assert len(list((tmp_path / "exports").glob("f-*.jaxexport"))) == 1
    second = stored_jit(_counting(counter), 0, sources=[__file__], name="f")
    assert float(second(2.0, x, pair)) == float(plain)
    assert counter["traces"] == 2  # loaded, not traced
    # another static value or shape is another program
    assert float(second(3.0, x, pair)) == float(jax.jit(_counting({"traces": 0}), static_argnums=0)(3.0, x, pair))
    second(2.0, x[:5], (pair[0][:5], pair[1]))
    assert counter["traces"] == 4
    assert len(list((tmp_path / "exports").glob("f-*.jaxexport"))) == 3


def test_stored_jit_does_not_load_a_program_of_other_sources(tmp_path, monkeypatch):
    monkeypatch.setattr(jaxnum, "export_folder", lambda: tmp_path / "exports")
    src = tmp_path / "model.py"
    src.write_text("version 1")
    counter = {"traces": 0}
    x, pair = np.ones(3), (np.ones(3), jnp.asarray(0.0))
    stored_jit(_counting(counter), 0, sources=[src], name="g")(1.0, x, pair)
    src.write_text("version 2")  # the traced code changed: its old program must not be used
    stored_jit(_counting(counter), 0, sources=[src], name="g")(1.0, x, pair)
    assert counter["traces"] == 2


def test_stored_jit_without_serialization_is_plain_jit(tmp_path, monkeypatch):
    # jax.export serializes with the `flatbuffers` package; where it is missing (it raises ImportError),
    # stored_jit computes with jax.jit for the rest of the process and stores nothing
    from jax import export

    def no_flatbuffers(self, *args, **kwargs):
        raise ImportError("Please install 'flatbuffers' in order to use Exported serialization")

    monkeypatch.setattr(export.Exported, "serialize", no_flatbuffers)
    monkeypatch.setattr(jaxnum, "export_folder", lambda: tmp_path / "exports")
    monkeypatch.setattr(jaxnum, "_EXPORT_WORKS", [True])
    x = np.linspace(0.0, 1.0, 7)
    pair = (np.arange(7.0), jnp.asarray(0.5))
    plain = float(jax.jit(_counting({"traces": 0}), static_argnums=0)(2.0, x, pair))
    f = stored_jit(_counting({"traces": 0}), 0, sources=[__file__], name="g")
    assert float(f(2.0, x, pair)) == plain and float(f(2.0, x, pair)) == plain
    assert jaxnum._EXPORT_WORKS == [False]
    assert not list((tmp_path / "exports").glob("g-*"))


# --------------------------------------------------------------------------- compiler options

def test_compiler_options_are_the_cpu_options_where_this_jaxlib_knows_them(monkeypatch):
    monkeypatch.setattr(jaxnum, "_OPTIONS", [])
    known = jaxnum.compiler_options()
    if jax.default_backend() != "cpu":
        assert known == {}
        return
    # the probe compiles a one-line program with the options: they are kept exactly when that works
    try:
        jax.jit(lambda v: v * 2.0, compiler_options=jaxnum.CPU_COMPILER_OPTIONS).lower(1.0).compile()
        works = True
    except Exception:
        works = False
    assert known == (jaxnum.CPU_COMPILER_OPTIONS if works else {})
    # a program compiled with them computes what XLA's defaults compute, to rounding
    f = _counting({"traces": 0})
    x = np.linspace(0.0, 1.0, 101)
    pair = (np.arange(101.0), jnp.asarray(0.5))
    fast = float(jaxnum.jit(f, static_argnums=0)(2.0, x, pair))
    assert fast == pytest.approx(float(jax.jit(f, static_argnums=0)(2.0, x, pair)), rel=1e-13)


def test_an_option_this_jaxlib_does_not_know_falls_back_to_xla_defaults(monkeypatch):
    # a future jaxlib may drop the option: the package must then compile as plain jax.jit, not fail
    monkeypatch.setattr(jaxnum, "CPU_COMPILER_OPTIONS", {"xla_comest_bayes_no_such_option": True})
    monkeypatch.setattr(jaxnum, "_OPTIONS", [])
    assert jaxnum.compiler_options() == {}
    f = _counting({"traces": 0})
    x = np.linspace(0.0, 1.0, 7)
    pair = (np.arange(7.0), jnp.asarray(0.5))
    assert float(jaxnum.jit(f, static_argnums=0)(2.0, x, pair)) == float(jax.jit(f, static_argnums=0)(2.0, x, pair))


def test_the_options_reach_xla_through_jit_and_stored_jit_but_not_with_quick_compile_off(tmp_path, monkeypatch):
    # an option XLA rejects, set as if the probe had accepted it: a program that passes it to XLA's compile
    # fails, one that does not (quick_compile=False: XLA's defaults) computes as jax.jit does
    monkeypatch.setattr(jaxnum, "_OPTIONS", [{"xla_comest_bayes_no_such_option": True}])
    x = np.linspace(0.0, 1.0, 7)
    pair = (np.arange(7.0), jnp.asarray(0.5))
    plain = float(jax.jit(_counting({"traces": 0}), static_argnums=0)(2.0, x, pair))
    with pytest.raises(Exception, match="xla_comest_bayes_no_such_option"):
        jaxnum.jit(_counting({"traces": 0}), static_argnums=0)(2.0, x, pair)
    for folder in (None, tmp_path / "exports"):  # the unstored and the stored path
        monkeypatch.setattr(jaxnum, "export_folder", lambda folder=folder: folder)
        with pytest.raises(Exception, match="xla_comest_bayes_no_such_option"):
            stored_jit(_counting({"traces": 0}), 0, sources=[__file__], name="q")(2.0, x, pair)
        f = stored_jit(_counting({"traces": 0}), 0, sources=[__file__], name="d", quick_compile=False)
        assert float(f(2.0, x, pair)) == plain
