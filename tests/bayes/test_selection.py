"""Tests of comest_bayes.bayes.selection: grouped PSIS-LOO and model selection.

The toy model of ``tests/toy_inference.py`` (a JAX model following the
CompletenessModel contract) is reused; the last tests use the real
``comest_bayes.bayes.model.CompletenessModel``.  Every random draw has a fixed seed.
"""

from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest

from comest_bayes.bayes.inference import fit_map, laplace
from comest_bayes.bayes.selection import LooResult, LooWarning, apply_rule, compare_loo, loo_grouped, select_model
from toy_inference import ToyModel, compress_toy, simulate


def _arviz():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        import arviz as az
    return az


def _laplace_draws(model, nsamples, seed, widen=1.0):
    mp = fit_map(model, seed=0)
    lap = laplace(model, mp.theta)
    rng = np.random.default_rng(seed)
    return rng.multivariate_normal(lap.mean, lap.cov * widen**2, nsamples)


def _expanded_loglik(model, draws, inv, detected):
    """The (S, N) per-injection log-likelihood matrix: column i = log f or log(1-f) of injection i's cell."""
    ll = model.cell_loglik(draws)
    return ll[:, inv, np.where(detected, 0, 1)]


@pytest.mark.parametrize("covariate, reff", [(False, 1.0), (True, 0.6)])
def test_grouped_loo_equals_arviz_loo_on_expanded_data(covariate, reff):
    # 400 injections in 0.1-mag (x 0.5 in d) cells (several injections per (cell, outcome) group): the grouped estimate
    # must equal arviz.loo on the 400-column matrix to rounding (same PSIS per identical column).
    m, d, det = simulate(400, seed=31, beta=0.8 if covariate else 0.0)
    mc, dc, n, k, inv = compress_toy(m, d, det, dm=0.1, dd=0.5 if covariate else None)
    assert n.size < 200  # grouping is really exercised
    model = ToyModel(mc, dc, n, k, covariate=covariate)
    draws = _laplace_draws(model, 1500, seed=4)
    got = loo_grouped(model, draws, reff=reff)

    az = _arviz()
    idata = az.from_dict(log_likelihood={"y": _expanded_loglik(model, draws, inv, det)[None]})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        ref = az.loo(idata, reff=reff, pointwise=True)
    assert got.n == 400 and got.nsamples == 1500
    assert got.elpd == pytest.approx(float(ref.elpd_loo), rel=1e-10)
    assert got.se == pytest.approx(float(ref.se), rel=1e-8)
    assert got.p_loo == pytest.approx(float(ref.p_loo), rel=1e-8)
    khat_inj = got.khat_groups[inv, np.where(det, 0, 1)]
    np.testing.assert_allclose(khat_inj, np.asarray(ref.pareto_k), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(got.elpd_groups[inv, np.where(det, 0, 1)], np.asarray(ref.loo_i), rtol=1e-10)
    # Contract's mapping access and JSON form.
    assert got["elpd"] == got.elpd and got["n_bad_k"] == 0
    json.dumps(got.to_dict(), allow_nan=False)


def test_loo_flags_large_khat_and_counts_injections():
    # Draws 30x wider than the posterior make the importance ratios heavy-tailed (k-hat > 0.7) for the cells
    # the model is sure about; n_bad_k must count the injections in those groups and a LooWarning must say so.
    m, d, det = simulate(600, seed=5)
    mc, dc, n, k, _ = compress_toy(m, d, det, dm=0.05, dd=None)
    model = ToyModel(mc, dc, n, k)
    draws = _laplace_draws(model, 1000, seed=6, widen=30.0)
    with pytest.warns(LooWarning, match="k-hat > 0.7"):
        res = loo_grouped(model, draws)
    bad = res.khat_groups > 0.7
    assert res.khat_max > 0.7
    assert res.n_bad_k == int(res.counts[bad].sum()) > 0


def test_loo_max_draws_thins_evenly():
    m, d, det = simulate(300, seed=7)
    mc, dc, n, k, _ = compress_toy(m, d, det, dm=0.05, dd=None)
    model = ToyModel(mc, dc, n, k)
    draws = _laplace_draws(model, 2998, seed=8)
    a = loo_grouped(model, draws, max_draws=1000)
    b = loo_grouped(model, draws[::3])  # linspace(0, 2997, 1000) is rows 0, 3, ..., 2997
    assert a.nsamples == 1000
    assert a.elpd == pytest.approx(b.elpd, rel=1e-6)


def _toy_factory(spec, data):
    m, d, n, k = data
    return ToyModel(m, d, n, k, covariate=spec.covariate)


class _Spec:
    def __init__(self, name, covariate):
        self.name, self.covariate = name, covariate


CANDIDATES = [_Spec("plain", False), _Spec("covariate", True)]


def _toy_data(beta, seed, n_inj=4000):
    m, d, det = simulate(n_inj, seed=seed, beta=beta)
    mc, dc, n, k, _ = compress_toy(m, d, det, dm=0.02, dd=0.1)
    return mc, dc, n, k


@pytest.mark.parametrize("beta, expected", [(0.0, "plain"), (1.0, "covariate")])
def test_selection_picks_the_simple_model_unless_the_covariate_matters(beta, expected):
    # 4000 injections; d ~ N(0, 0.4), so beta = 1 moves m50 by +-0.4 mag against w = 0.25: the covariate model
    # wins by hundreds of nats.  With beta = 0 the extra parameter can gain at most ~1 nat (p_loo +1), far
    # inside the 4-nat margin.
    data = _toy_data(beta, seed=41)
    res = select_model(data, CANDIDATES, seed=2, min_ess=200, chunk=200, model_factory=_toy_factory,
                       loo_draws=1000, scoring="emcee")
    assert res.chosen == expected
    rows = {r["name"]: r for r in res.table}
    assert [r["name"] for r in res.table] == ["plain", "covariate"]
    assert rows["plain"]["nparams"] == 2 and rows["covariate"]["nparams"] == 3
    assert rows[res.best]["delta_elpd"] == 0.0 and rows[res.best]["se_delta"] == 0.0
    assert sum(r["chosen"] for r in res.table) == 1
    other = "plain" if res.best == "covariate" else "covariate"
    if beta == 0.0:
        assert abs(rows[other]["delta_elpd"]) < 4.0
        assert 1.0 < rows["plain"]["p_loo"] < 3.5 and 2.0 < rows["covariate"]["p_loo"] < 4.5
    else:
        assert res.best == "covariate"
        assert rows["plain"]["delta_elpd"] < -max(4.0, 2.0 * rows["plain"]["se_delta"])
        assert rows["plain"]["delta_elpd"] < -100
    for r in res.table:
        assert r["khat_max"] < 0.7 and r["se"] > 0
        assert res.fits[r["name"]].posterior.diagnostics.ess.min() >= 200
    json.dumps(res.to_dict(), allow_nan=False)
    assert res.chosen in res.format_table()
    # With no margin at all the best model is taken.
    assert compare_loo(res.loo, margin=0.0, margin_se=0.0)[1] == res.best


def _fake_loo(elpd_groups, counts):
    elpd_groups, counts = np.asarray(elpd_groups, float), np.asarray(counts)
    total = float(np.sum(counts * elpd_groups))
    return LooResult(elpd=total, se=1.0, p_loo=1.0, lppd=total + 1.0, khat_max=0.1, n_bad_k=0, khat_threshold=0.7,
                     n=int(counts.sum()), nsamples=100, reff=1.0, elpd_groups=elpd_groups, khat_groups=0 * elpd_groups,
                     counts=counts)


def test_compare_loo_paired_differences_and_rule():
    # Two cells x 2 outcomes, 10 injections.  Per-injection differences (simple - complex) are -1 for the 4
    # injections of group (0, 0) and 0 for the 6 others: delta = -4, mean -0.4, population variance
    # 0.4 * 0.6 = 0.24, so se_delta = sqrt(10 * 0.24) = sqrt(2.4).
    counts = np.array([[4, 1], [2, 3]])
    complex_ = _fake_loo([[-0.1, -2.0], [-0.3, -0.5]], counts)
    simple = _fake_loo([[-1.1, -2.0], [-0.3, -0.5]], counts)
    rows, chosen, best = compare_loo({"simple": simple, "complex": complex_})
    assert best == "complex"
    assert rows[0]["delta_elpd"] == pytest.approx(-4.0) and rows[0]["se_delta"] == pytest.approx(math.sqrt(2.4))
    assert rows[1]["delta_elpd"] == 0.0 and rows[1]["se_delta"] == 0.0
    assert chosen == "simple"  # -4 >= -max(4, 2 * 1.55): within the margin
    assert compare_loo({"simple": simple, "complex": complex_}, margin=3.9)[1] == "complex"
    assert compare_loo({"simple": simple, "complex": complex_}, margin=0.0, margin_se=2.6)[1] == "simple"
    assert compare_loo({"simple": simple, "complex": complex_}, margin=0.0, margin_se=2.5)[1] == "complex"
    assert [r["chosen"] for r in rows] == [True, False]
    # Different cells cannot be compared.
    other = _fake_loo([[-0.1, -2.0], [-0.3, -0.5]], np.array([[4, 1], [3, 2]]))
    with pytest.raises(ValueError, match="different cells"):
        compare_loo({"simple": simple, "other": other})


@pytest.mark.slow
@pytest.mark.parametrize("beta_depth, expected", [(0.0, "logistic"), (1.0, "logistic_depth")])
def test_select_model_with_completeness_model(beta_depth, expected):
    # The production model and the shipped specs: 5000 injections, depth d ~ N(0, 0.3), compressed on a
    # 0.04 mag x 0.1 mag grid.  With beta_depth = 1 m50 moves by +-0.3 mag against w = 0.2 (~150 nats in
    # favour of the depth model); with beta_depth = 0 the slope is worth ~1 nat at most, inside the 4-nat margin.
    from comest_bayes.bayes.outcomes import compress_for
    from toy_inference import simulate_real

    cov, det = simulate_real(5000, seed=17, beta_depth=beta_depth)
    candidates = ["logistic", "logistic_depth"]
    data = compress_for(candidates, cov, det, dm=0.04, ddepth=0.1)
    res = select_model(data, candidates, seed=4, min_ess=200, chunk=200, loo_draws=1000)
    assert res.chosen == expected, res.format_table()
    rows = {r["name"]: r for r in res.table}
    assert rows["logistic"]["nparams"] == 4 and rows["logistic_depth"]["nparams"] == 5
    if beta_depth:
        assert rows["logistic"]["delta_elpd"] < -50
    else:
        assert abs(rows["logistic_depth"]["delta_elpd"]) < 4.0


@pytest.mark.slow
def test_auto_selection_picks_a_smooth_term_for_variation_not_in_the_weight_map():
    # m50 varies smoothly across the field (m50 = 24 + 0.4 u + 0.2 v^2, e.g. vignetting or a PSF trend that the
    # weight map does not know), while the depth covariate is uniform (noise map flat): the depth model cannot
    # explain the trend, a smooth term can.  5000 injections, w = 0.2: the trend moves m50 by +-0.4 mag, worth
    # hundreds of nats, far beyond the 4-nat margin of the rule.
    from comest_bayes.bayes.outcomes import Covariates, compress_for

    rng = np.random.default_rng(23)
    n = 5000
    u, v = rng.uniform(-1, 1, n), rng.uniform(-1, 1, n)
    m = rng.uniform(22.0, 26.5, n)
    m50 = 24.0 + 0.4 * u + 0.2 * v**2
    det = rng.random(n) < 0.97 / (1.0 + np.exp(-(m50 - m) / 0.2))
    cov = Covariates.make(m, depth=0.0, u=u, v=v)
    candidates = ["logistic", "logistic_depth", "logistic_smooth", "logistic_depth_smooth"]
    data = compress_for(candidates, cov, det, dm=0.04)
    res = select_model(data, candidates, seed=6)
    assert res.chosen == "logistic_smooth", res.format_table()
    rows = {r["name"]: r for r in res.table}
    assert rows["logistic"]["delta_elpd"] < -50 and rows["logistic_depth"]["delta_elpd"] < -50
    # the smooth field found is the truth: c_10 (the P1(u) coefficient) ~ 0.4 mag
    fit = res.fits["logistic_smooth"]
    model = res.models["logistic_smooth"]
    c10 = fit.map.theta[model.names.index("c_10")]
    assert c10 == pytest.approx(0.4, abs=0.08)  # posterior sd ~0.02 at 5000 injections: 4 sd


def test_laplace_loo_agrees_with_psis_loo_on_posterior_draws():
    # The infinitesimal-jackknife LOO of selection.loo_laplace against PSIS-LOO on importance-sampled posterior
    # draws of the same model and data (5000 injections, logistic_depth): they differ by O(1/N) terms, measured
    # 0.1-0.3 nat in elpd; required within 1 nat, and their model differences within 1 nat too.
    from comest_bayes.bayes.inference import fit
    from comest_bayes.bayes.model import CompletenessModel
    from comest_bayes.bayes.outcomes import Covariates, compress_for
    from comest_bayes.bayes.selection import loo_laplace

    rng = np.random.default_rng(31)
    n = 5000
    m = rng.uniform(22.0, 26.0, n)
    d = rng.normal(0.0, 0.25, n)
    det = rng.random(n) < 0.01 + 0.96 / (1.0 + np.exp(-(24.0 + d - m) / 0.2))
    data = compress_for(["logistic", "logistic_depth"], Covariates.make(m, depth=d), det)
    out = {}
    for name in ("logistic", "logistic_depth"):
        model = CompletenessModel(name, data)
        res = fit(model, seed=4, sampler="importance", min_ess=1000)
        out[name] = (loo_laplace(model, res.map.theta, res.laplace.cov),
                     loo_grouped(model, res.posterior.samples, warn=False))
        lap, psis = out[name]
        assert lap.elpd == pytest.approx(psis.elpd, abs=1.0)
        assert lap.p_loo == pytest.approx(psis.p_loo, abs=1.0)
    d_lap = out["logistic_depth"][0].elpd - out["logistic"][0].elpd
    d_psis = out["logistic_depth"][1].elpd - out["logistic"][1].elpd
    assert d_lap == pytest.approx(d_psis, abs=1.0) and d_lap > 20


def test_a_level_no_candidate_reaches_does_not_make_the_simple_candidates_inadequate():
    # A purity-like curve: f = 0.995 over the whole injected range, so the image-average f of no candidate falls
    # to one half within [lo - 1, hi + 1] in most draws: m50 is undefined in every candidate.  Both the
    # candidate and the reference (the spline) then agree that the crossing is beyond the data, and that
    # quantity must not decide (it made every simpler rung inadequate and sent the demo's buldisk purity fit
    # to a 21-parameter spline sampled by emcee for 22 s).  The other quantities still decide.
    from comest_bayes.bayes.checks import P_WARN
    from comest_bayes.bayes.fit import targeted_quantities
    from comest_bayes.bayes.outcomes import Covariates, compress_for
    from comest_bayes.bayes.posterior import Footprint

    rng = np.random.default_rng(31)
    n = 3000
    m = rng.uniform(18.0, 25.0, n)
    det = rng.random(n) < 0.995
    cov = Covariates.make(m, depth=0.0)
    candidates = ["logistic_depth", "spline_depth"]
    data = compress_for(candidates, cov, det, dm=0.04)
    cells = Footprint(depth=np.zeros(1), u=np.zeros(1), v=np.zeros(1), weight=np.ones(1), npix=1)
    quantities = targeted_quantities(cells, (20.0, 23.0), 18.0, 25.0)
    res = select_model(data, candidates, seed=8, quantities=quantities)
    rows = {r["name"]: r for r in res.table}
    for name in candidates:
        assert rows[name]["quantities"]["m50"].get("undefined") is True, res.format_table()
    simple = rows["logistic_depth"]
    others = [q for k, q in simple["quantities"].items() if k != "m50"]
    expected = all(q.get("undefined") or q["diff_over_sd"] <= 1.0 / 3.0 for q in others) and (simple["shape_p"] is None
                                                                       or simple["shape_p"] >= P_WARN)
    assert simple["adequate"] == expected
    # on this plateau the simple rung's other quantities lie near the spline's: well inside one sd (whether
    # within the third that makes it adequate is up to the 200 importance draws' noise, ~0.1 sd)
    assert all(q.get("undefined") or q["diff_over_sd"] < 1.0 for q in others), res.format_table()
    assert res.chosen == ("logistic_depth" if expected else "spline_depth")


def test_a_smoothness_handed_in_is_kept_and_a_same_model_start_is_refined():
    # An escalated selection refits the first selection's chosen spline rung on finer cells of the same
    # outcomes: it hands in the smoothness already chosen by the evidence (`taus`) and that rung's MAP
    # (`start`).  The rung must keep that tau (no evidence search: an empty tau table) and reach the same
    # optimum as a search from scratch at that tau (log posterior within 1e-3 nats, the optimizer's tolerance).
    from comest_bayes.bayes.model import CompletenessModel
    from comest_bayes.bayes.outcomes import Covariates, compress_for
    from comest_bayes.bayes.spec import load_spec

    rng = np.random.default_rng(41)
    n = 2000
    m = rng.uniform(21.0, 26.0, n)
    det = rng.random(n) < 1.0 / (1.0 + np.exp((m - 23.5) / 0.25)) ** 0.5  # skewed: a Richards-like truth
    cov = Covariates.make(m, depth=0.0)
    coarse = compress_for(["spline_depth"], cov, det, dm=0.1)
    fine = compress_for(["spline_depth"], cov, det, dm=0.02)
    first = select_model(coarse, ["spline_depth"], seed=3)
    tau = first.table[0]["tau"]
    assert len(first.table[0]["tau_table"]) > 1  # the first selection searched the scales
    warm = (list(first.models["spline_depth"].names), first.fits["spline_depth"].map.theta)
    res = select_model(fine, ["spline_depth"], seed=3, start=warm, taus={"spline_depth": tau})
    row = res.table[0]
    assert row["tau"] == tau and row["tau_table"] == []
    assert res.models["spline_depth"].tau == tau
    ref = CompletenessModel(load_spec("spline_depth"), fine)
    ref.tau = tau
    scratch = fit_map(ref, seed=3, nstarts=2)
    assert abs(res.fits["spline_depth"].map.log_prob - scratch.log_prob) < 1e-3


def _rule_rows(elpds, ses):
    """LOO rows of :func:`compare_loo`'s shape from elpd values and paired SEs (simplest first)."""
    best = max(elpds)
    return [{"name": f"c{i}", "elpd_loo": e, "delta_elpd": e - best, "se_delta": se}
            for i, (e, se) in enumerate(zip(elpds, ses))]


def _eager_rule(rows, ok, margin=4.0, margin_se=2.0):
    """The rule with every candidate's adequacy known in advance (what the selection computed before)."""
    for r in rows:
        if ok[r["name"]] and r["delta_elpd"] >= -max(margin, margin_se * r["se_delta"]):
            return r["name"]
    return max((r for r in rows if ok[r["name"]]), key=lambda r: r["elpd_loo"])["name"]


@pytest.mark.parametrize("elpds, ses, ok, expect_checked", [
    # the simplest candidate 200 nats out, the next within the margin and adequate: only that one is checked
    ([-1700.0, -1486.0, -1485.0, -1484.0], [20.0, 3.3, 2.5, 0.0], [False, True, True, True], ["c1"]),
    # 7 nats out with a paired SE of 3.3 (margin 6.6) is outside: the rung above is the first checked
    ([-1700.0, -1491.0, -1487.0, -1484.0], [20.0, 3.3, 2.5, 0.0], [False, True, True, True], ["c2"]),
    # the first within the margin inadequate, the next adequate: those two, not the one outside nor the top
    ([-1700.0, -1490.0, -1486.0, -1484.0], [20.0, 3.0, 2.0, 0.0], [True, False, True, True], ["c1", "c2"]),
    # nothing but the reference within the margin: no check at all (the reference is adequate by definition)
    ([-1700.0, -1600.0, -1550.0, -1484.0], [20.0, 9.0, 8.0, 0.0], [True, True, True, True], ["c3"]),
    # the reference outside the margin and the only candidate within it inadequate: the adequate one of highest
    # elpd, checked in order of elpd
    ([-1490.0, -1480.0, -1470.0, -1500.0], [5.0, 2.0, 0.0, 3.0], [True, True, False, True], ["c2", "c1"]),
])
def test_the_rule_checks_adequacy_only_where_it_needs_it_and_chooses_as_if_it_knew_all(elpds, ses, ok, expect_checked):
    rows = _rule_rows(elpds, ses)
    truth = {f"c{i}": v for i, v in enumerate(ok)}
    checked = []

    def adequate(name):  # the selection computes a candidate's checks once; record the first call only
        if name not in checked:
            checked.append(name)
        return truth[name]

    chosen, how = apply_rule(rows, adequate)
    assert chosen == _eager_rule(rows, truth)
    assert checked == expect_checked
    assert ("no adequate candidate" in how) == (elpds == [-1490.0, -1480.0, -1470.0, -1500.0])
