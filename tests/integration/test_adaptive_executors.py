"""An adaptive run gives the same numbers whichever executor runs its batches (issue #16).

The design of batch ``k`` depends only on the root seed and the outcomes of the batches before it,
so serial, local-process and Dask runs of the same command must write the same designs, the same
merged outcome catalogs and the same m50s, to the last bit.  The run is as small as still shows it:
a 500-pixel tile, the point kind, a pilot of two realizations and one designed batch of two (each
batch's two realizations run side by side on two workers), and a precision no batch reaches, so the
cap, not a coin-flip at the threshold, ends every run.
"""

import json

import numpy as np
import pytest
from astropy.table import Table

from comest_bayes.config import load_config
from comest_bayes.sim.demo import MASK_GAP, make_demo_tile, write_demo_tile
from comest_bayes.pipeline.stages import ComputeOptions, ImageOptions, run_pipeline

pytestmark = pytest.mark.slow

SETTINGS = ["injection.kinds=point", "fit.model=logistic", "fit.purity_model=none", "adaptive.precision=0.001",
            "adaptive.pilot_nsims=2", "adaptive.growth=1.0", "adaptive.max_nsims=4"]


@pytest.fixture(scope="module")
def tile(tmp_path_factory):
    return write_demo_tile(make_demo_tile(seed=5, size=500, star_density=6.0), tmp_path_factory.mktemp("tile"))


def _run(tile, out, executor):
    options = ImageOptions(path=str(tile["image"]), weight=str(tile["weight"]), mask=str(tile["mask"]),
                           mask_bits=MASK_GAP)
    run_pipeline(options, load_config(overrides=SETTINGS, seed=11), out, log=lambda s: None,
                 compute=ComputeOptions(executor=executor, workers=2, progress=False))
    return out


@pytest.fixture(scope="module")
def serial(tile, tmp_path_factory):
    return _run(tile, tmp_path_factory.mktemp("serial") / "run", "serial")


def _m50s(summary: dict) -> dict:
    point = summary["kinds"]["point"]
    return {"binned": point["m50_binned"], "model": point["model"]["m50"],
            "batches": [(b["m50"], b["halfwidth"]) for b in summary["adaptive"]["kinds"]["point"]["batches"]]}


def test_the_serial_run_is_a_two_batch_adaptive_run(serial):
    ad = json.loads((serial / "summary.json").read_text())["adaptive"]["kinds"]["point"]
    assert [b["realizations"] for b in ad["batches"]] == [[0, 2], [2, 4]]
    assert [b["design"] for b in ad["batches"]] == ["uniform", "m50"]
    assert not ad["reached"] and "cap" in ad["reason"]


@pytest.mark.parametrize("executor", ["processes", "dask"])
def test_executors_give_identical_designs_catalogs_and_m50s(executor, serial, tile, tmp_path):
    if executor == "dask":
        pytest.importorskip("distributed", reason="the Dask executor needs dask.distributed (pip install "
                                                  "'dask[distributed]')")
    other = _run(tile, tmp_path / executor, executor)
    designs = sorted(p.name for p in (serial / "designs").glob("*.json"))
    assert designs == ["point_batch0.json", "point_batch1.json"]
    assert sorted(p.name for p in (other / "designs").glob("*.json")) == designs
    for name in designs:
        assert (other / "designs" / name).read_text() == (serial / "designs" / name).read_text(), name
    for name in ("outcomes", "injected", "matched"):
        a = Table.read(serial / "catalogs" / f"point_{name}.fits")
        b = Table.read(other / "catalogs" / f"point_{name}.fits")
        assert a.colnames == b.colnames and len(a) == len(b) > 0, name
        for col in a.colnames:
            np.testing.assert_array_equal(np.asarray(a[col]), np.asarray(b[col]), err_msg=f"{name}.{col}")
    s, o = (json.loads((d / "summary.json").read_text()) for d in (serial, other))
    assert _m50s(o) == _m50s(s)
    assert o["adaptive"] == s["adaptive"]
