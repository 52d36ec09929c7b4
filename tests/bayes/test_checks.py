"""The posterior predictive shape check: silent when the model's form is right, loud when it is not."""

import warnings

import numpy as np
import pytest

from comest_bayes.bayes.checks import P_WARN, ShapeBin, ShapeCheck, shape_check, shape_warning
from comest_bayes.bayes.inference import fit_map, laplace
from comest_bayes.bayes.model import CompletenessModel
from comest_bayes.bayes.outcomes import Covariates, compress

EDGES = np.arange(21.0, 26.01, 0.2)


def _fit_logistic(m, det, seed=0):
    model = CompletenessModel("logistic", compress(Covariates.make(m), det, ddepth=None, nuv=None, dsize=None))
    mp = fit_map(model, seed=seed)
    lap = laplace(model, mp.theta)
    draws = np.random.default_rng(seed).multivariate_normal(lap.mean, lap.cov, size=200)
    return model, draws


def _logistic(m, m50, w, a=0.98):
    return a / (1.0 + np.exp((m - m50) / w))


def test_a_logistic_truth_passes_the_check():
    # 30000 outcomes from the model's own family: chi2 follows (at most) its nominal distribution, so
    # p < 1e-3 would happen once in a thousand seeds; this seed is fixed.
    rng = np.random.default_rng(1)
    m = rng.uniform(21.0, 26.0, 30000)
    det = rng.random(m.size) < _logistic(m, 24.0, 0.2)
    model, draws = _fit_logistic(m, det)
    check = shape_check(model, draws, EDGES)
    assert check.dof >= 8  # the transition bins; plateau bins with A = 0.98 qualify too
    assert check.p_value > P_WARN
    assert shape_warning(check, name="logistic", kind="point", quantity="completeness") is None
    # observed and expected per bin add up to the data
    assert sum(b.observed for b in check.bins) == int(det.sum())
    assert sum(b.n for b in check.bins) == m.size
    assert sum(b.expected for b in check.bins) == pytest.approx(det.sum(), rel=0.01)


def test_a_two_population_truth_fails_the_check_and_says_so():
    # half the injections with m50 = 23.4, half with 24.0 (e.g. crowded and clear positions, no covariate
    # telling them apart): the average is a broad, flat-topped transition no single logistic follows.
    # With 60000 outcomes the misfit is many sigma in the transition bins.
    rng = np.random.default_rng(2)
    m = rng.uniform(21.0, 26.0, 60000)
    m50 = np.where(rng.random(m.size) < 0.5, 23.4, 24.0)
    det = rng.random(m.size) < _logistic(m, m50, 0.08)
    model, draws = _fit_logistic(m, det)
    check = shape_check(model, draws, EDGES)
    assert check.p_value < 1e-6
    assert check.max_abs_z > 4
    assert 23.0 < check.mag_at_max < 24.4
    msg = shape_warning(check, name="logistic", kind="point", quantity="completeness")
    assert msg is not None and "binned ratios" in msg and "logistic" in msg and "--model" in msg
    # the purity model is named like its quantity and has no more flexible rung to point to
    msg = shape_warning(check, name="purity", kind="point", quantity="purity")
    assert msg.startswith("the purity curve of point does not describe")
    assert "binned purity ratios" in msg and "--model" not in msg


def test_certain_bins_are_left_out_and_all_detected_gives_no_verdict():
    # every injection detected: the fitted curve is ~1 everywhere, every bin's predictive variance is far
    # below a quarter detection, so no bin qualifies and the check gives no p-value (and no warning)
    rng = np.random.default_rng(3)
    m = rng.uniform(21.0, 23.0, 500)
    det = np.ones(m.size, bool)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model, draws = _fit_logistic(m, det)
    check = shape_check(model, draws[0], EDGES)  # a single parameter vector is accepted
    assert check.dof == 0 and all(b.z is None for b in check.bins)
    assert check.p_value is None and check.chi2 is None and check.max_abs_z is None
    assert sum(b.observed for b in check.bins) == m.size
    assert shape_warning(check, name="logistic", kind="point", quantity="completeness") is None


@pytest.mark.parametrize("edges", [[24.0], [25.0, 24.0], [[21.0, 22.0]]])
def test_bad_edges_are_refused(edges):
    rng = np.random.default_rng(4)
    m = rng.uniform(21.0, 26.0, 200)
    model = CompletenessModel("logistic", compress(Covariates.make(m), m < 24.0, ddepth=None, nuv=None, dsize=None))
    with pytest.raises(ValueError, match="increasing"):
        shape_check(model, np.zeros((1, model.ndim)), edges)


def test_the_json_form_keeps_the_published_keys_and_reads_back():
    rng = np.random.default_rng(1)
    m = rng.uniform(21.0, 26.0, 3000)
    det = rng.random(m.size) < _logistic(m, 24.0, 0.2)
    model, draws = _fit_logistic(m, det)
    check = shape_check(model, draws, EDGES)
    d = check.to_dict()
    # the keys summary.json has carried under kinds.<kind>.model.shape_check since the check exists
    assert list(d) == ["chi2", "dof", "p_value", "max_abs_z", "mag_at_max", "bins"]
    assert len(d["bins"]) == len(EDGES) - 1
    assert all(list(b) == ["mag", "n", "observed", "expected", "z"] for b in d["bins"])
    assert d["dof"] == check.dof and d["bins"][3]["observed"] == check.bins[3].observed
    assert ShapeCheck.from_dict(d) == check
    # frozen: a stage cannot change the check it was handed
    with pytest.raises(AttributeError):
        check.dof = 0
    assert isinstance(check.bins, tuple) and isinstance(check.bins[0], ShapeBin)
