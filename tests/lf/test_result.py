"""The saved result of a count fit (comest_bayes.lf.result.LFResult): parameter summaries against hand-computed
percentiles, the lf.json entry, and an exact save/load round trip."""

import json
import math

import numpy as np
import pytest

from comest_bayes.errors import InputFileError
from comest_bayes.lf.result import LFResult


def _result(comp_samples=None) -> LFResult:
    """A result whose first parameter's draws are 1, 2, ..., 1000 (so every percentile is known by hand)."""
    a = np.arange(1.0, 1001.0)
    b = np.full(1000, 0.3)
    grid = np.linspace(18.0, 25.0, 8)
    bands = np.vstack([np.full(8, v) for v in (1.0, 2.0, 3.0, 4.0, 5.0)])
    edges = np.array([20.0, 21.0, 22.0, 23.0])
    expected = np.array([[9.0, 19.0, 29.0], [10.0, 20.0, 30.0], [11.0, 21.0, 31.0], [12.0, 22.0, 32.0],
                         [13.0, 23.0, 33.0]])
    return LFResult(name="main", kind="point", mode="fixed", spec={"name": "powerlaw"}, names=["log_n", "slope"],
                    samples=np.column_stack([a, b]), comp_samples=comp_samples, grid=grid, phi_bands=bands,
                    obs_edges=edges, observed=np.array([10, 21, 29]), expected_bands=expected,
                    expected_draws=np.ones((4, 3)), fbar_median=np.linspace(1.0, 0.2, 8), area_deg2=0.0123,
                    mag_range=(20.0, 23.0), n_objects=60, diagnostics={"ess": 812.5}, warnings=["a warning"],
                    meta={"seed": 4})


def test_parameter_summary_is_the_percentiles_of_the_draws():
    s = _result().parameter_summary()
    # numpy's linear percentile of 1..1000 at q is 1 + q/100 * 999
    assert s["log_n"]["median"] == pytest.approx(500.5)
    assert s["log_n"]["lo68"] == pytest.approx(1 + 0.16 * 999) and s["log_n"]["hi68"] == pytest.approx(1 + 0.84 * 999)
    assert s["log_n"]["lo95"] == pytest.approx(1 + 0.025 * 999) and s["log_n"]["hi95"] == pytest.approx(1 + 0.975 * 999)
    assert s["log_n"]["mean"] == pytest.approx(500.5)
    assert s["log_n"]["sd"] == pytest.approx(math.sqrt((1000 ** 2 - 1) / 12.0))  # sd of a discrete uniform
    assert s["slope"] == {k: pytest.approx(v) for k, v in
                          {"median": 0.3, "lo68": 0.3, "hi68": 0.3, "lo95": 0.3, "hi95": 0.3, "mean": 0.3, "sd": 0.0}.items()}


def test_json_entry_holds_the_observed_counts_and_the_middle_bands():
    entry = _result().to_json()
    assert entry["n_samples"] == 1000 and entry["n_objects"] == 60 and entry["mag_range"] == [20.0, 23.0]
    assert entry["observed"]["counts"] == [10, 21, 29]
    # bands are 2.5, 16, 50, 84, 97.5 percent: rows 1, 2, 3 are lo68, median, hi68
    assert entry["observed"]["expected_lo68"] == [10.0, 20.0, 30.0]
    assert entry["observed"]["expected_median"] == [11.0, 21.0, 31.0]
    assert entry["observed"]["expected_hi68"] == [12.0, 22.0, 32.0]
    json.dumps(entry)  # JSON-ready as it is


@pytest.mark.parametrize("comp_samples", [None, np.arange(6.0).reshape(3, 2)])
def test_save_and_load_give_back_the_same_result(tmp_path, comp_samples):
    res = _result(comp_samples)
    npz = res.save(tmp_path / "lf")
    assert npz == tmp_path / "lf" / "lf_posterior.npz"
    assert json.loads((tmp_path / "lf" / "lf.json").read_text()) == json.loads(json.dumps(res.to_json()))
    for source in (npz, tmp_path / "lf"):  # the file or its directory
        back = LFResult.load(source)
        for name in ("samples", "grid", "phi_bands", "obs_edges", "observed", "expected_bands", "expected_draws",
                     "fbar_median"):
            np.testing.assert_array_equal(getattr(back, name), getattr(res, name), err_msg=name)
        if comp_samples is None:
            assert back.comp_samples is None
        else:
            np.testing.assert_array_equal(back.comp_samples, comp_samples)
        assert (back.name, back.kind, back.mode, back.names) == ("main", "point", "fixed", ["log_n", "slope"])
        assert back.mag_range == (20.0, 23.0) and back.area_deg2 == 0.0123 and back.n_objects == 60
        assert back.diagnostics == {"ess": 812.5} and back.warnings == ["a warning"] and back.meta == {"seed": 4}
        assert back.transfer is None


def test_loading_a_missing_result_names_the_file(tmp_path):
    with pytest.raises(InputFileError, match="lf_posterior.npz.*does not exist"):
        LFResult.load(tmp_path)
