"""JAX in double precision (comest_bayes.jaxnum): importing it, or a module that needs float64, switches JAX
to 64-bit; the front door does not.  Each case runs in a fresh Python, since the switch is per process."""

import json
import os
import subprocess
import sys

import pytest

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
