"""The posterior predictive shape check: silent when the model's form is right, loud when it is not."""

import warnings

import numpy as np
import pytest

from comest_bayes.bayes.checks import (P_WARN, ShapeBin, ShapeCheck, covariate_check, covariate_warning, shape_check,
                                      shape_warning)
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


# --------------------------------------------------------------------------- the covariate check

def _fit_logistic_depth(m, depth, det, seed=0):
    """logistic_depth fitted to uncompressed-in-position cells, as auto's rungs are, with Laplace draws."""
    cov = Covariates.make(m, depth=depth)
    model = CompletenessModel("logistic_depth", compress(cov, det, nuv=None, dsize=None))
    mp = fit_map(model, seed=seed)
    lap = laplace(model, mp.theta)
    draws = np.random.default_rng(seed).multivariate_normal(lap.mean, lap.cov, size=200)
    return model, draws


def _scene(n, seed):
    """Positions over a 1000^2 image and a depth that runs 0.6 mag along y (as a gradient in the noise)."""
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(0, 999, n), rng.uniform(0, 999, n)
    u, v = 2 * x / 999 - 1, 2 * y / 999 - 1
    depth = 0.3 * v
    m = rng.uniform(21.0, 26.0, n)
    return rng, m, u, v, depth


def test_the_covariate_check_is_silent_when_m50_follows_the_depth_as_modelled():
    # 30000 outcomes from logistic_depth's own family: every group's residual is binomial noise, and the
    # fitted parameters only shrink the chi-squares, so p < 1e-3 would be rarer than once in a thousand
    # seeds (this one is fixed)
    rng, m, u, v, depth = _scene(30000, 3)
    det = rng.random(m.size) < _logistic(m, 24.0 + depth, 0.15)
    model, draws = _fit_logistic_depth(m, depth, det)
    check = covariate_check(model, draws, u=u, v=v, depth=depth, detected=det, image_shape=(1000, 1000))
    assert check.position.dof >= 40 and check.depth.dof >= 20
    assert check.position.p_value > 0.01 and check.depth.p_value > 0.01
    assert check.p_value == pytest.approx(min(1.0, 2 * min(check.position.p_value, check.depth.p_value)))
    assert covariate_warning(check, name="logistic_depth", kind="point", quantity="completeness") is None
    # the groups add up to the data: the worst group's counts are a share of it
    assert 0 < check.position.worst["n"] < m.size


def test_an_m50_patch_the_noise_does_not_explain_is_found_and_located():
    # m50 0.5 mag brighter inside a disc (scattered light, a crowded cluster) that the depth does not
    # carry: the magnitude bins average it into a slightly broader transition, the tiles do not
    rng, m, u, v, depth = _scene(20000, 4)
    x, y = (u + 1) * 499.5, (v + 1) * 499.5
    patch = (x - 700) ** 2 + (y - 250) ** 2 < 200 ** 2
    det = rng.random(m.size) < _logistic(m, 24.0 + depth - 0.5 * patch, 0.15)
    model, draws = _fit_logistic_depth(m, depth, det)
    check = covariate_check(model, draws, u=u, v=v, depth=depth, detected=det, image_shape=(1000, 1000))
    assert check.position.p_value < 1e-10
    w = check.position.worst
    # the worst group is a tile the disc covers (tiles are 250 pixels; the disc centre is at 700, 250),
    # with fewer detections than predicted
    assert abs(w["x"] - 700) <= 250 and abs(w["y"] - 250) <= 250 and w["z"] < -4
    msg = covariate_warning(check, name="logistic_depth", kind="point", quantity="completeness")
    assert msg is not None and "across the image" in msg and "auto_smooth" in msg


def test_an_m50_that_saturates_with_depth_fails_the_depth_part():
    # m50 = 24 + 0.3 tanh(d / 0.05): it follows the depth near the reference and stops beyond it, which a
    # line in d cannot follow at both ends
    rng, m, u, v, depth = _scene(30000, 5)
    det = rng.random(m.size) < _logistic(m, 24.0 + 0.3 * np.tanh(depth / 0.05), 0.1)
    model, draws = _fit_logistic_depth(m, depth, det)
    check = covariate_check(model, draws, depth=depth, detected=det)
    assert check.position is None  # no positions given: that part does not apply
    assert check.depth.p_value < 1e-6 and check.p_value == check.depth.p_value
    msg = covariate_warning(check, name="logistic_depth", kind="point", quantity="completeness")
    assert msg is not None and "with the local depth" in msg and "noise map" in msg
    # the purity model has no more flexible rung to point to: the remedy is its binned ratios
    msg = covariate_warning(check, name="purity", kind="point", quantity="purity")
    assert msg.startswith("the purity curve of point") and "binned purity ratios per depth range" in msg


def test_the_covariate_check_needs_the_cells_of_the_injections():
    rng, m, u, v, depth = _scene(2000, 6)
    det = rng.random(m.size) < _logistic(m, 24.0, 0.15)
    model, draws = _fit_logistic_depth(m, depth, det)
    with pytest.raises(ValueError, match="index"):
        covariate_check(model, draws, depth=depth, detected=det[:-1])
    # a depth that does not vary and no positions: nothing to check, no verdict
    flat = covariate_check(model, draws, depth=np.zeros(m.size), detected=det)
    assert flat.position is None and flat.depth is None and flat.p_value is None
    assert covariate_warning(flat, name="logistic_depth", kind="point", quantity="completeness") is None


def test_fit_kind_runs_the_covariate_check_and_warns_with_the_place(tmp_path):
    """End to end: an outcome table whose m50 is 0.5 mag brighter in a disc the noise map does not show.
    The fit's magnitude shape check passes (the patch averages into a broader transition) and the covariate
    check warns, names the tile and lands in the JSON form."""
    from astropy.table import Table

    from comest_bayes.bayes.fit import fit_kind
    from comest_bayes.config import load_config

    rng = np.random.default_rng(8)
    ny = nx = 400
    yy = np.arange(ny)[:, None] * np.ones((1, nx))
    noise_map = 10.0 ** (0.4 * 0.3 * (2 * yy / (ny - 1) - 1))       # 0.6 mag of depth along y
    n = 20000
    x, y = rng.uniform(-0.5, nx - 0.5, n), rng.uniform(-0.5, ny - 0.5, n)
    noise = noise_map[np.floor(y + 0.5).astype(int), np.floor(x + 0.5).astype(int)]
    depth = -2.5 * np.log10(noise / np.median(noise))
    m = rng.uniform(21.0, 26.0, n)
    patch = (x - 100) ** 2 + (y - 300) ** 2 < 80 ** 2
    det = rng.random(n) < _logistic(m, 24.0 + depth - 0.5 * patch, 0.15)
    table = Table({"mag": m, "detected": det, "x": x, "y": y, "noise": noise})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        post, entry = fit_kind(table, kind="point", quantity="completeness", requested="logistic_depth",
                               config=load_config(overrides=["fit.min_ess=100"], seed=3), image_shape=(ny, nx),
                               noise=noise_map, mask=np.zeros((ny, nx), bool), wcs_header=None, mag_range=(21.0, 26.0),
                               mag_centers=np.arange(21.05, 26.0, 0.1))
    assert entry.shape_check.p_value > P_WARN
    check = entry.covariate_check
    assert check.position.p_value < 1e-6 and check.p_value < P_WARN
    w = check.position.worst
    assert abs(w["x"] - 100) <= 100 and abs(w["y"] - 300) <= 100  # tiles of 100 pixels around the disc
    assert any("across the image" in text for text in entry.warnings)
    assert entry.to_dict()["covariate_check"]["position"]["worst"] == w
