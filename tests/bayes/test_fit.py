"""The fit stage: outcome tables to posteriors and summary entries, on known truths."""

import json
import warnings

import numpy as np
import pytest
from astropy.table import Table

from comest_bayes.bayes.fit import purity_outcomes
from outcome_truths import SHAPE, depth_split_outcomes, fit_depth_split


def test_depth_model_recovers_the_truth_and_reports_intervals():
    table, noise_map = depth_split_outcomes(20000)
    post, entry = fit_depth_split(table, noise_map, "logistic_depth")
    par = entry.parameters
    # 20000 outcomes constrain m50_0 and beta_depth to ~0.01 and ~0.03: 4 posterior sd of tolerance
    for name, truth in (("m50_0", 24.0), ("beta_depth", 1.0), ("w", 0.15), ("A", 0.98)):
        sd = 0.5 * (par[name]["hi68"] - par[name]["lo68"])
        assert abs(par[name]["median"] - truth) < 4 * sd + 1e-3, (name, par[name], truth)
    assert entry.diagnostics["converged"]
    assert np.min(entry.diagnostics["ess"]) >= 300
    # the completeness query at a position in the shallow half is lower than in the deep half
    deep = post.completeness(24.0, 100.0, 200.0).mean()
    shallow = post.completeness(24.0, 500.0, 200.0).mean()
    assert deep == pytest.approx(0.98 / 2, abs=0.04)
    assert shallow == pytest.approx(0.98 / (1 + np.exp(0.5 / 0.15)), abs=0.03)
    # m50 of the image-average curve lies between the two halves' m50
    assert 23.5 < entry.magnitudes["m50"]["median"] < 24.0
    assert entry.magnitudes["m50"]["lo68"] <= entry.magnitudes["m50"]["median"] <= entry.magnitudes["m50"]["hi68"]
    json.dumps(entry.to_dict())  # JSON-ready
    # the JSON form has the keys (and order) summary.json has had for a fit, the covariate check after the shape's
    d = entry.to_dict()
    assert list(d) == ["name", "requested", "selection", "m50", "m80", "m90", "parameters", "curve", "diagnostics",
                       "tau", "shape_check", "covariate_check", "warnings", "n_outcomes", "n_cells", "seconds"]
    assert d["m50"] == entry.magnitudes["m50"] and d["shape_check"] == entry.shape_check.to_dict()
    assert d["covariate_check"] == entry.covariate_check.to_dict()
    assert d["warnings"] == list(entry.warnings) and d["n_cells"] == entry.n_cells


def test_auto_selection_prefers_the_depth_model_when_depth_varies():
    table, noise_map = depth_split_outcomes(6000, seed=1)
    post, entry = fit_depth_split(table, noise_map, "auto", min_ess=100)
    # the truth is a logistic whose m50 follows the depth: that rung agrees with the spline on every
    # targeted quantity (adequate) and is the simplest within the LOO margin; the logistic without
    # depth is ~180 nats worse: outside the margin, so its adequacy is never checked (no draws, no quantities)
    assert entry.selection["chosen"] == "logistic_depth"
    rows = {row["name"]: row for row in entry.selection["table"]}
    assert list(rows)[0] == "logistic" and list(rows)[-1] == "spline_depth"
    assert rows["logistic"]["delta_elpd"] < -50
    assert rows["logistic"]["adequate"] is None and rows["logistic"]["quantities"] == {}
    assert rows["logistic_depth"]["adequate"] is True and rows["spline_depth"]["adequate"] is True
    # the chosen rung was compared with the spline on every targeted quantity; the rung above it was not checked
    assert set(rows["logistic_depth"]["quantities"]) == {"m50", "m90", "f_bright", "f_faint"}
    assert all(q["diff_over_sd"] <= 1.0 / 3.0 for q in rows["logistic_depth"]["quantities"].values())
    if "richards_depth" in rows:
        assert rows["richards_depth"]["adequate"] is None
    # the width does not vary over the image: the score test of the chosen rung does not escalate
    assert entry.selection["width_test"]["escalated"] is False
    assert entry.selection["width_test"]["p_value"] > 1e-3


def _width_grows_along_y(n=6000):
    """The depth-split truth with a width growing from 0.1 mag (y = 0) to 0.35 mag (top), independent of depth."""
    table, noise_map = depth_split_outcomes(n, seed=21)
    rng = np.random.default_rng(1021)  # not depth_split_outcomes' seed: its first draws are the positions
    w = 0.1 + 0.25 * np.asarray(table["y"]) / (SHAPE[0] - 1)
    mu = 24.0 - 2.5 * np.log10(np.asarray(table["noise"]))
    table["detected"] = rng.random(n) < 0.98 / (1.0 + np.exp(-(mu - np.asarray(table["mag"])) / w))
    return table, noise_map


def _logistic_selection(tmp_path) -> str:
    """A selection spec with the logistic rungs of auto and its logistic width rung (fast to fit)."""
    spec = tmp_path / "auto_logistic.toml"
    spec.write_text('name = "auto_logistic"\ncandidates = ["logistic", "logistic_depth"]\n'
                    'width_candidates = ["logistic_depth_width_uv"]\n')
    return str(spec)


def test_a_selection_escalates_to_a_positional_width_when_the_width_varies_across_the_image(tmp_path):
    # the depth-split truth, but the width grows from 0.1 mag (y = 0) to 0.35 mag (top), independent of
    # depth; a selection spec with the logistic rungs of auto and its logistic width rung keeps the test fast
    # (auto's spline rungs select the same way: the honesty benchmark, benchmarks/README.md)
    table, noise_map = _width_grows_along_y()
    post, entry = fit_depth_split(table, noise_map, _logistic_selection(tmp_path), min_ess=100)
    test = entry.selection["width_test"]
    assert test["escalated"] and test["p_value"] < 1e-6
    # the escalated selection compares the first selection's choice with the positional-width rung, on
    # cells that resolve position, and keeps the latter: the single width misses the image average
    assert test["first_selection"]["chosen"] == "logistic_depth"
    assert [row["name"] for row in entry.selection["table"]] == ["logistic_depth", "logistic_depth_width_uv"]
    assert entry.name == "logistic_depth_width_uv"
    # log w rises along v: from log 0.1 to log 0.35 over the image height, a plane slope of ~0.6 per unit
    # v (the truth is linear in w, not in log w); 6000 injections give it to ~0.07
    assert 0.4 < entry.parameters["w_01"]["median"] < 0.8
    assert abs(entry.parameters["w_10"]["median"]) < 0.2


def test_the_most_flexible_fit_of_a_selection_compares_no_simpler_rung_and_still_escalates(tmp_path):
    # most_flexible (the adaptive design's fits): only the last candidate is fitted, with the same width test,
    # and when it fires only the last positional-width rung.  The same width-varying table as above, with
    # a selection spec whose last candidate is logistic_depth (fast); the full selection chose it too.
    table, noise_map = _width_grows_along_y()
    post, entry = fit_depth_split(table, noise_map, _logistic_selection(tmp_path), min_ess=100, most_flexible=True)
    test = entry.selection["width_test"]
    assert test["escalated"] and test["p_value"] < 1e-6
    assert [row["name"] for row in test["first_selection"]["table"]] == ["logistic_depth"]
    assert [row["name"] for row in entry.selection["table"]] == ["logistic_depth_width_uv"]
    assert entry.name == "logistic_depth_width_uv"
    assert 0.4 < entry.parameters["w_01"]["median"] < 0.8
    # a flat width: the last candidate alone, no escalation (the full selection would keep logistic_depth too,
    # test_auto_selection_prefers_the_depth_model_when_depth_varies)
    table, noise_map = depth_split_outcomes(6000, seed=1)
    post, entry = fit_depth_split(table, noise_map, _logistic_selection(tmp_path), min_ess=100, most_flexible=True)
    assert [row["name"] for row in entry.selection["table"]] == ["logistic_depth"]
    assert entry.name == "logistic_depth" and not entry.selection["width_test"]["escalated"]
    # one candidate has nothing to be compared with: no adequacy quantities or shape check are computed for it
    row = entry.selection["table"][0]
    assert row["adequate"] and row["quantities"] == {} and row["shape_p"] is None


def test_auto_selection_keeps_the_simple_model_on_uniform_depth():
    table, noise_map = depth_split_outcomes(6000, depth_slope=0.0, seed=2)
    table["noise"] = 1.0
    post, entry = fit_depth_split(table, np.ones(SHAPE), "auto", min_ess=100)
    assert entry.selection["chosen"] == "logistic"


@pytest.mark.parametrize("case", ["all", "none", "few"])
def test_degenerate_outcomes_give_a_finite_posterior_and_a_warning(case):
    table, noise_map = depth_split_outcomes(3000, seed=4)
    if case == "all":
        table["detected"] = True
    elif case == "none":
        table["detected"] = False
    else:
        table = table[:15]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        post, entry = fit_depth_split(table, noise_map, "logistic", min_ess=100)
    # the warning names the case: every outcome positive / negative, or too few outcomes for the data to lead
    expected = {"all": "every point outcome is positive", "none": "every point outcome is negative",
                "few": "only 15 outcomes: the posterior of the point completeness is dominated by the priors"}[case]
    assert any(expected in str(w.message) for w in caught), [str(w.message) for w in caught]
    assert any(expected in w for w in entry.warnings)
    assert np.all(np.isfinite(post.samples))
    curve = entry.curve
    assert all(0.0 <= v <= 1.0 for v in curve["median"])


def test_purity_outcomes_stack_matched_and_false_detections():
    matched = Table({"det_xwin": [1.0, 2.0], "det_ywin": [3.0, 4.0], "det_mag_auto": [20.0, 21.0]})
    false = Table({"xwin": [5.0], "ywin": [6.0], "mag_auto": [25.0]})
    t = purity_outcomes(matched, false)
    assert list(t["real"]) == [True, True, False]
    assert list(t["mag"]) == [20.0, 21.0, 25.0] and list(t["x"]) == [1.0, 2.0, 5.0]


def test_all_injections_in_one_bin_warn_that_the_shape_is_unconstrained():
    # every injection within 0.05 mag of 23.6: the data say f ~ 0.8 there and nothing about the width, m80 or
    # m90 (the case: m80 came out 0.4 mag off with no warning)
    table, noise_map = depth_split_outcomes(3000, seed=6)
    table["mag"] = 23.6 + 0.09 * (np.asarray(table["mag"]) - 21.0) / 5.5 - 0.045
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        post, entry = fit_depth_split(table, noise_map, "logistic_depth", min_ess=100)
    assert any("less than two" in w and "not constrained" in w for w in entry.warnings)
    # and a magnitude outside the injected range is flagged as extrapolated
    assert post.extrapolated(24.5) and not post.extrapolated(23.6)


def test_fit_records_the_cpu_it_spent_and_the_injected_range(tmp_path):
    table, noise_map = depth_split_outcomes(3000, seed=7)
    post, entry = fit_depth_split(table, noise_map, "logistic_depth", min_ess=100)
    lo, hi = post.meta["injected_range"]
    assert lo == pytest.approx(float(np.min(table["mag"]))) and hi == pytest.approx(float(np.max(table["mag"])))
    assert entry.magnitudes["m50"]["extrapolated"] is False and entry.magnitudes["m50"]["lo95"] < entry.magnitudes["m50"]["lo68"]


def test_a_warm_refit_equals_a_cold_fit_of_the_same_model():
    # The adaptive design refits the chosen model after every batch from the previous posterior (Newton steps
    # from its median).  With the same data and seed, the warm refit must land on the cold fit's posterior:
    # medians and 68% intervals of m50 within 0.15 posterior sd (both have ESS >= 400: Monte Carlo ~0.05 sd).
    from comest_bayes.bayes.fit import warm_state
    from comest_bayes.errors import InputError

    first, noise_map = depth_split_outcomes(3000, seed=5)
    more, _ = depth_split_outcomes(9000, seed=6)
    post1, _ = fit_depth_split(first, noise_map, "logistic_depth")
    warm = warm_state(post1)
    assert warm["model"] == "logistic_depth" and len(warm["theta"]) == len(warm["names"])
    cold, e_cold = fit_depth_split(more, noise_map, "logistic_depth")
    hot, e_hot = fit_depth_split(more, noise_map, "logistic_depth", warm=warm)
    sd = 0.5 * (e_cold.magnitudes["m50"]["hi68"] - e_cold.magnitudes["m50"]["lo68"])
    for key in ("median", "lo68", "hi68"):
        assert abs(e_hot.magnitudes["m50"][key] - e_cold.magnitudes["m50"][key]) < 0.15 * sd, (key, e_hot.magnitudes["m50"], e_cold.magnitudes["m50"])
    with pytest.raises(InputError, match="warm refit needs one model"):
        fit_depth_split(more, noise_map, "auto", warm=warm)


def test_a_fit_entry_is_frozen_and_its_json_form_gains_only_the_keys_that_were_set():
    from dataclasses import FrozenInstanceError, replace

    from comest_bayes.bayes.fit import FitEntry

    entry = FitEntry(name="logistic", requested="auto", magnitudes={"m50": {"median": 24.0}}, warnings=("w",),
                     n_outcomes=10, n_cells=4, seconds=1.5)
    with pytest.raises(FrozenInstanceError):
        entry.name = "other"
    d = entry.to_dict()
    assert "cpu_seconds" not in d and "warm_refit" not in d and "skipped" not in d
    assert d["m50"] == {"median": 24.0} and d["warnings"] == ["w"] and d["shape_check"] is None
    # the fit stage adds its CPU time, the adaptive design whether the fit was warm: each last, as before
    assert list(replace(entry, cpu_seconds=2.0).to_dict())[-1] == "cpu_seconds"
    assert replace(entry, warm_refit=False).to_dict()["warm_refit"] is False
    # a fit not run keeps the four keys of a skipped entry
    skipped = FitEntry(name=None, requested="purity", cpu_seconds=0.0, skipped="too few")
    assert skipped.to_dict() == {"name": None, "requested": "purity", "cpu_seconds": 0.0, "skipped": "too few"}


def test_a_fit_without_products_has_the_same_posterior_and_an_entry_without_summaries():
    # The adaptive design's refits query the posterior themselves (products=False): the posterior must be the one
    # a full fit makes (same draws, same seed), and the entry must not carry summaries that were never computed.
    table, noise_map = depth_split_outcomes(3000, seed=5)
    full, e_full = fit_depth_split(table, noise_map, "logistic_depth")
    bare, e_bare = fit_depth_split(table, noise_map, "logistic_depth", products=False)
    np.testing.assert_array_equal(bare.samples, full.samples)
    assert e_full.magnitudes["m50"] and e_full.curve and e_full.shape_check is not None
    assert e_bare.magnitudes == {} and e_bare.curve == {} and e_bare.shape_check is None
    assert e_bare.name == e_full.name and e_bare.n_cells == e_full.n_cells
    assert "m50" not in e_bare.to_dict() and "m50" in e_full.to_dict()
