"""Process-wide runtime settings (comest_bayes.pipeline.runtime): thread limits, the compilation cache folder,
and pinning to one core.  What changes the process for good runs in a fresh Python."""

import json
import os
import subprocess
import sys

import pytest

from comest_bayes.pipeline import runtime
from conftest import REPO_ROOT

THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _fresh_python(code: str, env: dict) -> dict:
    """Run ``code`` (which prints one JSON line) in a new interpreter that imports this checkout."""
    full = {k: v for k, v in os.environ.items() if not k.startswith("JAX_")}  # no cache setting inherited
    full.update(env, PYTHONPATH=str(REPO_ROOT))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=full, timeout=120)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_cache_dir_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("COMEST_BAYES_CACHE", str(tmp_path / "c"))
    assert runtime.cache_dir() == tmp_path / "c"
    monkeypatch.delenv("COMEST_BAYES_CACHE")
    monkeypatch.setenv("HOME", str(tmp_path))
    assert runtime.cache_dir() == tmp_path / ".cache" / "comest-bayes" / "jax"


def test_one_thread_sets_xla_and_blas_limits_and_keeps_the_users_choices(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_dump_to=/tmp/x")
    monkeypatch.setenv("MKL_NUM_THREADS", "3")  # the user's own setting stays
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        monkeypatch.delenv(var, raising=False)
    runtime.configure(threads=1, cache=False)
    flags = os.environ["XLA_FLAGS"]
    assert flags.startswith("--xla_dump_to=/tmp/x ") and "intra_op_parallelism_threads=1" in flags
    assert "--xla_cpu_multi_thread_eigen=false" in flags
    assert (os.environ["OMP_NUM_THREADS"], os.environ["OPENBLAS_NUM_THREADS"], os.environ["MKL_NUM_THREADS"]) == \
        ("1", "1", "3")
    runtime.configure(threads=1, cache=False)  # a second call adds nothing
    assert os.environ["XLA_FLAGS"] == flags


def test_threads_none_leaves_the_environment_alone(monkeypatch):
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    for var in THREAD_VARS:
        monkeypatch.delenv(var, raising=False)
    runtime.configure(threads=None, cache=False)
    assert "XLA_FLAGS" not in os.environ and not any(var in os.environ for var in THREAD_VARS)


def test_the_cache_folder_is_created_and_handed_to_jax(tmp_path):
    code = ("import json, os, sys; from comest_bayes.pipeline import runtime; runtime.configure(threads=None); "
            "print(json.dumps({'dir': os.environ.get('JAX_COMPILATION_CACHE_DIR'), "
            "'min': os.environ.get('JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS'), 'jax': 'jax' in sys.modules}))")
    got = _fresh_python(code, {"COMEST_BAYES_CACHE": str(tmp_path / "cache")})
    assert got == {"dir": str(tmp_path / "cache"), "min": "0", "jax": False}  # configuring does not import JAX
    assert (tmp_path / "cache").is_dir()
    # a folder that cannot be created (under a file) is skipped silently: no cache, no error
    blocker = tmp_path / "file"
    blocker.write_text("")
    got = _fresh_python(code, {"COMEST_BAYES_CACHE": str(blocker / "cache")})
    assert got == {"dir": None, "min": None, "jax": False}


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="CPU affinity is Linux only")
def test_one_core_inside_the_block_and_the_former_cores_after():
    before = os.sched_getaffinity(0)
    with runtime.one_core():
        inside = os.sched_getaffinity(0)
        assert len(inside) == 1 and inside <= before
    assert os.sched_getaffinity(0) == before


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="CPU affinity is Linux only")
def test_pin_to_one_core_takes_the_index_modulo_the_cores():
    code = ("import json, os; from comest_bayes.pipeline import runtime; cores = sorted(os.sched_getaffinity(0)); "
            "core = runtime.pin_to_one_core(len(cores) + 1); "
            "print(json.dumps({'cores': cores, 'core': core, 'after': sorted(os.sched_getaffinity(0))}))")
    got = _fresh_python(code, {})
    cores = got["cores"]
    assert got["core"] == cores[1 % len(cores)]
    assert got["after"] == ([got["core"]] if len(cores) > 1 else cores)
