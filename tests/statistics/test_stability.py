"""Stability of the completeness fit where methods usually fail.

Every case must give a finite posterior (or a clear InputError) together with an explicit warning naming
the problem, never a crash or a silent NaN.  The fits run through ``fit_kind`` (the pipeline's fit stage)
with short chains (min_ess 50, max_steps 300): these tests are about what is reported, not about precision.
Each fit compiles the model for its own data shape (~5 s), so the module is marked slow (it still runs in CI).
"""

import json
import warnings

import numpy as np
import pytest
from astropy.table import Table

from comest_bayes.config import load_config
from comest_bayes.errors import InputError
from comest_bayes.bayes.fit import fit_kind
from comest_bayes.bayes.inference import IdentifiabilityWarning

pytestmark = pytest.mark.slow

SHAPE = (300, 400)
SPLIT = 220


def _noise_map():
    return np.where(np.arange(SHAPE[1])[None, :] < SPLIT, 1.0, 10 ** 0.2) * np.ones(SHAPE)


def _outcomes(n, seed, *, m50=24.0, w=0.15):
    """Known truth: logistic completeness, m50 = 24 in the deep part, 0.5 mag brighter in the shallow part."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(0, SHAPE[1] - 1, n)
    y = rng.uniform(0, SHAPE[0] - 1, n)
    m = rng.uniform(22.0, 26.0, n)
    noise = np.where(x < SPLIT, 1.0, 10 ** 0.2)
    p = 0.98 / (1.0 + np.exp(-(m50 - 2.5 * np.log10(noise) - m) / w))
    return Table({"x": x, "y": y, "mag": m, "noise": noise, "hlr_arcsec": np.full(n, np.nan),
                  "detected": rng.random(n) < p})


def _fit(table, model="logistic_depth"):
    config = load_config(overrides=[f"fit.model={model}", "fit.min_ess=50", "fit.max_steps=300"], seed=2)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        post, entry = fit_kind(table, kind="point", quantity="completeness", requested=model, config=config,
                               image_shape=SHAPE, noise=_noise_map(), mask=np.zeros(SHAPE, bool), wcs_header=None,
                               mag_range=(22.0, 26.0), mag_centers=np.arange(22.1, 26.0, 0.2))
    messages = [f"{w.category.__name__}: {w.message}" for w in caught]
    return post, entry, messages


def _assert_finite(post, entry):
    assert np.all(np.isfinite(post.samples))
    for key in ("median", "lo68", "hi68", "lo95", "hi95"):
        values = np.asarray(entry.curve[key])
        assert np.all(np.isfinite(values)) and np.all((values >= 0) & (values <= 1)), key
    for key in ("m50", "m80", "m90"):
        item = entry.magnitudes[key]
        # either a finite interval, or None with the fraction of draws where it is defined
        if item["median"] is None:
            assert 0.0 <= item["defined_fraction"] < 0.5
        else:
            assert np.isfinite([item["median"], item["lo68"], item["hi68"]]).all()
    json.dumps(entry.to_dict())  # JSON-ready, so no NaN sneaks into summary.json


@pytest.mark.parametrize("case", ["all", "none"])
def test_all_or_no_detections_with_a_depth_model(case):
    table = _outcomes(800, 1)
    table["detected"] = case == "all"
    post, entry, messages = _fit(table)
    word = "positive" if case == "all" else "negative"
    assert any(f"every point outcome is {word}" in m for m in messages), messages
    assert any(f"every point outcome is {word}" in m for m in entry.warnings)
    _assert_finite(post, entry)


def test_perfectly_separated_outcomes_at_the_fit_stage():
    table = _outcomes(1500, 2)
    table["detected"] = table["mag"] < 24.0
    post, entry, messages = _fit(table, "logistic")
    assert any(m.startswith("IdentifiabilityWarning") and "separated" in m for m in messages), messages
    _assert_finite(post, entry)
    # the step sits between the brightest undetected and the faintest detected injection
    m = np.asarray(table["mag"])
    lo, hi = m[m < 24.0].max(), m[m >= 24.0].min()
    assert lo - 0.05 < entry.magnitudes["m50"]["median"] < hi + 0.05


def test_fewer_than_twenty_injections():
    table = _outcomes(400, 3)[:12]
    post, entry, messages = _fit(table)
    assert any("only 12 outcomes" in m for m in messages), messages
    _assert_finite(post, entry)
    # 12 injections say little: the 68% interval of m50 is wide (prior-dominated), not a false precision
    if entry.magnitudes["m50"]["median"] is not None:
        assert entry.magnitudes["m50"]["hi68"] - entry.magnitudes["m50"]["lo68"] > 0.1


def test_all_injections_in_one_spatial_cell():
    table = _outcomes(800, 4)
    rng = np.random.default_rng(5)
    table["x"] = 50.0 + rng.uniform(0, 4, len(table))
    table["y"] = 60.0 + rng.uniform(0, 4, len(table))
    table["noise"] = 1.0
    # outcomes of the deep part's truth (m50 = 24) for the new positions
    m = np.asarray(table["mag"])
    table["detected"] = rng.random(len(table)) < 0.98 / (1.0 + np.exp(-(24.0 - m) / 0.15))
    post, entry, messages = _fit(table, "logistic_smooth")
    assert any("one small spatial cell" in m for m in messages), messages
    assert any("one small spatial cell" in m for m in entry.warnings)
    _assert_finite(post, entry)
    med, sd, _ = post.m50_map(100)
    assert np.all(np.isfinite(med)) and np.all(np.isfinite(sd))
    # at the sampled cell the fit knows m50 (truth 24); far away it only has the prior's spread
    here = post.completeness(24.0, 52.0, 62.0).mean()
    assert here == pytest.approx(0.49, abs=0.1)  # 800 injections: m50 there to ~0.02 mag, f(m50) to ~0.06
    assert sd.max() > 2 * sd.min()


def test_depth_model_on_uniform_noise_warns_that_the_slope_is_the_prior():
    table = _outcomes(800, 6)
    table["noise"] = 1.0
    post, entry, messages = _fit(table, "logistic_depth")
    assert any("depth covariate spans only" in m for m in messages), messages
    _assert_finite(post, entry)


def test_nan_covariates_are_dropped_or_neutralised_with_counts():
    table = _outcomes(1500, 7)
    table["mag"][:40] = np.nan
    table["x"][40:50] = np.nan
    table["noise"][50:200] = np.nan
    post, entry, messages = _fit(table)
    assert any("dropped 50 of 1500 outcome rows" in m and "40 with non-finite mag" in m for m in messages), messages
    assert any("150 of 1450 outcome rows have a non-finite or non-positive noise" in m for m in messages), messages
    _assert_finite(post, entry)
    assert entry.n_outcomes == 1450
    # the remaining rows still carry the truth: m50_0 = 24 with w = 0.15 (sd ~0.02 at 1450 injections; 0.1 is 5 sd)
    assert entry.parameters["m50_0"]["median"] == pytest.approx(24.0, abs=0.1)


def test_nan_everywhere_is_a_clear_error():
    table = _outcomes(50, 8)
    table["mag"] = np.nan
    with pytest.raises(InputError, match="all 50 rows"):
        _fit(table)
    with pytest.raises(InputError, match="nothing to fit"):
        _fit(table[:0])


def test_no_usable_noise_column_warns_and_fits():
    table = _outcomes(800, 9)
    table["noise"] = np.nan
    post, entry, messages = _fit(table)
    assert any("no finite positive noise value" in m for m in messages), messages
    _assert_finite(post, entry)


def test_posterior_queries_refuse_nan_inputs():
    table = _outcomes(600, 10)
    post, _, _ = _fit(table, "logistic")
    assert np.all(np.isfinite(post.completeness([23.0, 25.0], 10.0, 10.0)))
    with pytest.raises(InputError, match="non-finite"):
        post.completeness(np.nan, 10.0, 10.0)
    with pytest.raises(InputError, match="non-finite"):
        post.completeness(24.0, np.nan, 10.0)
