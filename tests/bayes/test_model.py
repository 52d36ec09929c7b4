"""The JAX density of the completeness model (comest_bayes.bayes.model): known answers on a tiny data set, m50
and its covariates, gradients and Hessians, priors, MAP recovery, degenerate data, compilation and batches.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate, optimize, special, stats

from comest_bayes.errors import InputError
from comest_bayes.bayes.model import TRACE_COUNT, CompletenessModel
from comest_bayes.bayes.outcomes import Covariates, compress, compress_for, uncompressed
from comest_bayes.bayes.spec import ModelSpec
from outcome_truths import synthetic


LINKS = ("logistic", "probit", "pritchet")


# --------------------------------------------------------------------------- helpers


def numpy_logistic_loglik(m, y, m50, w, A, floor):
    f = floor + (A - floor) / (1.0 + np.exp(-(m50 - m) / w))
    return float(np.sum(np.where(y, np.log(f), np.log1p(-f))))


# --------------------------------------------------------------------------- model: known answers

@pytest.fixture(scope="module")
def tiny():
    m = np.array([21.0, 23.5, 24.0, 24.2, 25.0, 26.5])
    y = np.array([True, True, False, True, False, False])
    depth = np.array([0.1, -0.2, 0.0, 0.3, -0.1, 0.2])
    u = np.array([-1.0, -0.5, 0.0, 0.25, 0.5, 1.0])
    v = np.array([0.5, -1.0, 0.75, 0.0, -0.25, 1.0])
    return Covariates(m, depth, u, v, np.zeros(6)), y


def test_tiny_dataset_matches_hand_computation(tiny):
    cov, y = tiny
    model = CompletenessModel("logistic_depth", uncompressed(cov, y))
    assert model.names == ["m50_0", "log_w", "logit_A", "logit_floor", "beta_depth"]
    p = dict(m50_0=24.1, w=0.3, A=0.9, floor=0.05, beta_depth=0.7)
    theta = model.inverse_transform(p)
    ll = numpy_logistic_loglik(cov.m, y, p["m50_0"] + p["beta_depth"] * cov.depth, p["w"], p["A"], p["floor"])
    assert model.log_likelihood(theta) == pytest.approx(ll, rel=1e-13)
    # the prior in theta space: densities of the documented priors times the Jacobians of the logits
    r = p["floor"] / p["A"]
    lp = (stats.norm(25, 5).logpdf(24.1) + stats.norm(math.log(0.2), 1).logpdf(math.log(0.3))
          + stats.beta(20, 1).logpdf(0.9) + math.log(0.9 * 0.1)
          + stats.beta(1, 50).logpdf(r) + math.log(r * (1 - r))
          + stats.norm(1, 1).logpdf(0.7))
    assert model.log_prior(theta) == pytest.approx(lp, rel=1e-12)
    assert model.log_prob(theta) == pytest.approx(lp + ll, rel=1e-12)
    back = model.transform(theta)
    for key, value in p.items():
        assert back[key] == pytest.approx(value, rel=1e-12)


@pytest.mark.parametrize("link", LINKS)
def test_prob_at_m50_is_halfway_between_floor_and_plateau(link):
    cov, y = synthetic(50, 1)
    model = CompletenessModel(ModelSpec(name=link, link=link, spatial="depth"), uncompressed(cov, y))
    p = dict(m50_0=23.0, w=0.25, A=0.93, floor=0.04, beta_depth=0.8)
    theta = model.inverse_transform(p)
    d = np.array([-0.4, 0.0, 0.5])
    at = Covariates.make(p["m50_0"] + p["beta_depth"] * d, depth=d)
    np.testing.assert_allclose(model.prob(theta, at), 0.04 + (0.93 - 0.04) / 2, rtol=1e-12)
    # far bright -> plateau, far faint -> floor (|z| = 1e5: even the Pritchet tail 1/(4 z^2) is negligible)
    ends = Covariates.make(np.array([23.0 - 2.5e4, 23.0 + 2.5e4]))
    np.testing.assert_allclose(model.prob(theta, ends), [0.93, 0.04], rtol=1e-9)


def test_depth_slope_shifts_the_m50_field():
    cov, y = synthetic(50, 2)
    model = CompletenessModel("logistic_depth_smooth", uncompressed(cov, y))
    theta = model.inverse_transform(dict(m50_0=24.0, w=0.2, beta_depth=1.3, c_10=0.2, c_02=-0.1))
    d = np.linspace(-0.5, 0.5, 11)
    u = np.linspace(-1, 1, 11)
    v = np.linspace(1, -1, 11)
    with_d = model.m50(theta, Covariates.make(20.0, depth=d, u=u, v=v))
    without = model.m50(theta, Covariates.make(20.0, depth=0.0, u=u, v=v))
    np.testing.assert_allclose(with_d - without, 1.3 * d, atol=1e-12)
    # smooth term: Legendre P1(u) and P2(v) = (3 v^2 - 1) / 2
    np.testing.assert_allclose(without, 24.0 + 0.2 * u - 0.1 * (3 * v ** 2 - 1) / 2, atol=1e-12)


def test_size_covariate_and_width_depth_enter_as_documented():
    cov, y = synthetic(40, 3)
    spec = ModelSpec(name="s", spatial="depth", width_depth=True, size_covariate=True)
    model = CompletenessModel(spec, uncompressed(cov, y))
    assert model.names[-3:] == ["beta_depth", "w_depth", "beta_size"]
    theta = model.inverse_transform(dict(m50_0=24.0, w=0.2, A=0.9, floor=0.02, beta_depth=1.0, w_depth=0.5,
                                         beta_size=-3.0))
    d, s = 0.4, 0.2
    m50 = 24.0 + 1.0 * d - 3.0 * s
    w = 0.2 * math.exp(0.5 * d)
    m = m50 + w  # z = -1
    f = model.prob(theta, Covariates.make(m, depth=d, size=s))
    assert f[0] == pytest.approx(0.02 + 0.88 * special.expit(-1.0), rel=1e-12)


@pytest.mark.parametrize("spec", ["logistic_depth_smooth", ModelSpec(name="p", link="probit", spatial="depth",
                                                                      width_depth=True),
                                  ModelSpec(name="q", link="pritchet", spatial="smooth", smooth_basis="bspline",
                                            smooth_order=4)])
def test_gradient_and_hessian_match_finite_differences(spec):
    cov, y = synthetic(3000, 4)
    model = CompletenessModel(spec, compress(cov, y, dm=0.05, ddepth=0.05, nuv=8))
    rng = np.random.default_rng(5)
    theta = model.initial() + rng.normal(0, 0.1, model.ndim)
    value, grad = model.value_and_grad(theta)
    assert value == pytest.approx(model.log_prob(theta), rel=1e-14)
    h = 1e-5
    fd = np.array([(model.log_prob(theta + h * e) - model.log_prob(theta - h * e)) / (2 * h)
                   for e in np.eye(model.ndim)])
    # central differences: truncation ~ h^2 f''' and rounding ~ 1e-16 |f| / h ~ 1e-8 here
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-4)
    hess = model.hessian(theta)
    fdh = np.array([(model.value_and_grad(theta + h * e)[1] - model.value_and_grad(theta - h * e)[1]) / (2 * h)
                    for e in np.eye(model.ndim)])
    np.testing.assert_allclose(hess, fdh, rtol=1e-4, atol=1e-2)
    np.testing.assert_allclose(hess, hess.T, rtol=1e-10, atol=1e-8)


@pytest.mark.parametrize("spec", ["logistic_depth_smooth", "richards_depth", "spline_depth_width_uv"])
def test_difference_hessian_matches_the_exact_one(spec):
    """The Hessian is forward differences of the compiled gradient; compare it with ``jax.hessian``.

    Tolerance: ``HESSIAN_STEP = 1e-7`` gave a largest error of 1.9e-6 in units of
    ``sqrt(|H_ii H_jj|)`` on these rungs (truncation, 19 x the step); 2e-5 allows a tenfold margin
    and still fails for a wrong column, a missing symmetrisation or a step of the wrong sign.
    """
    from comest_bayes.bayes import model as model_module
    from comest_bayes.jaxnum import jax

    cov, y = synthetic(3000, 4)
    model = CompletenessModel(spec, compress_for(spec, cov, y, dm=0.05, ddepth=0.05))
    rng = np.random.default_rng(8)
    theta = model.initial() + rng.normal(0, 0.1, model.ndim)
    full = model.full(theta)
    exact = jax.hessian(model_module._log_prob, argnums=1)(model._st, full, model._data, model._prior)
    free = model._free_idx
    exact = np.asarray(exact)[np.ix_(free, free)]
    scale = np.sqrt(np.outer(np.abs(np.diag(exact)), np.abs(np.diag(exact))))
    hess = model.hessian(theta)
    assert np.max(np.abs(hess - exact) / scale) < 2e-5
    np.testing.assert_array_equal(hess, hess.T)


def test_difference_hessian_is_nan_where_the_posterior_is_not_finite():
    cov, y = synthetic(500, 4)
    model = CompletenessModel("logistic_depth", compress_for("logistic_depth", cov, y, dm=0.05, ddepth=0.05))
    outside = model.initial()
    outside[0] = 2e4  # beyond the parameter box: log_prob is -inf
    assert model.log_prob(outside) == -np.inf
    assert np.all(np.isnan(model.hessian(outside)))


def test_prior_is_normalised_with_its_jacobians():
    cov, y = synthetic(20, 6)
    model = CompletenessModel("logistic", uncompressed(cov, y))
    base = model.inverse_transform(dict(m50_0=24.0, w=0.2, A=0.9, floor=0.05))
    i_a, i_f = model.names.index("logit_A"), model.names.index("logit_floor")
    lp0 = model.log_prior(base)

    def density(i, t):
        th = base.copy()
        th[i] = t
        return math.exp(model.log_prior(th) - lp0)

    # Beta(20, 1) on A = sigmoid(t): integral of the theta-space density over t is the density's
    # normalisation 1 / p_t(t0); its mean of A is 20 / 21.  Same for r = floor / A ~ Beta(1, 50).
    for i, (a, b) in ((i_a, (20.0, 1.0)), (i_f, (1.0, 50.0))):
        s0 = special.expit(base[i])
        p_t0 = stats.beta(a, b).pdf(s0) * s0 * (1 - s0)
        norm, _ = integrate.quad(lambda t: density(i, t), -60, 60, limit=200, points=[base[i]])
        mean, _ = integrate.quad(lambda t: special.expit(t) * density(i, t), -60, 60, limit=200, points=[base[i]])
        assert norm * p_t0 == pytest.approx(1.0, rel=1e-6)
        assert mean / norm == pytest.approx(a / (a + b), rel=1e-6)


def test_floor_stays_below_plateau_for_any_theta():
    cov, y = synthetic(20, 7)
    model = CompletenessModel("logistic", uncompressed(cov, y))
    thetas = np.random.default_rng(8).normal(0, 30, (2000, model.ndim))
    p = model.transform(thetas)
    assert np.all(p["floor"] <= p["A"]) and np.all(p["A"] <= 1) and np.all(p["floor"] >= 0)
    fixed = CompletenessModel(ModelSpec(name="f", plateau="fixed"), uncompressed(cov, y))
    assert fixed.names == ["m50_0", "log_w", "logit_floor"]
    assert fixed.transform(np.array([24.0, -1.6, -3.0]))["A"] == 1.0


def test_map_recovers_known_parameters():
    # 20000 outcomes from logistic_depth with known truth; the MAP must lie within 4 Laplace sigma
    # of the truth in every parameter (a 4-sigma miss has probability ~6e-5 per parameter).
    truth = dict(m50_0=24.0, w=0.2, A=0.95, floor=0.01, beta_depth=1.0)
    cov, y = synthetic(20000, 9, **{("m50" if k == "m50_0" else k): v for k, v in truth.items()})
    model = CompletenessModel("logistic_depth", compress_for("logistic_depth", cov, y))
    res = optimize.minimize(lambda t: tuple(-x for x in model.value_and_grad(t)), model.initial(), jac=True,
                            method="L-BFGS-B")
    assert res.success
    sd = np.sqrt(np.diag(np.linalg.inv(-model.hessian(res.x))))
    t_true = model.inverse_transform(truth)
    assert np.all(np.abs(res.x - t_true) < 4 * sd), (res.x, t_true, sd)


# --------------------------------------------------------------------------- stability

def _cases():
    rng = np.random.default_rng(17)
    m = rng.uniform(20, 27, 200)
    u = rng.uniform(-1, 1, 200)
    v = rng.uniform(-1, 1, 200)
    d = rng.normal(0, 0.1, 200)
    spread = Covariates(m, d, u, v, np.zeros(200))
    one_cell = Covariates(m, np.full(200, 0.05), np.full(200, 0.3), np.full(200, -0.2), np.zeros(200))
    few = spread.take(np.arange(12))
    return {
        "all detected": (spread, np.ones(200, bool)),
        "none detected": (spread, np.zeros(200, bool)),
        "separated": (spread, m < 23.5),
        "12 injections": (few, few.m < 24.0),
        "one spatial cell": (one_cell, rng.uniform(size=200) < special.expit((24 - m) / 0.2)),
    }


@pytest.mark.parametrize("spec", ["logistic", "logistic_depth_smooth", "probit", "pritchet",
                                  ModelSpec(name="fixed", plateau="fixed", floor="fixed", spatial="depth")])
def test_degenerate_data_give_finite_posteriors(spec):
    # uncompressed: the cases share one cell count (200), so each function compiles once per spec
    for label, (cov, y) in _cases().items():
        model = CompletenessModel(spec, uncompressed(cov, y))
        theta = model.initial()
        value, grad = model.value_and_grad(theta)
        assert np.isfinite(value) and np.all(np.isfinite(grad)), label
        if len(cov) == 200:  # (the Hessian is compiled for one data shape only, to keep the test fast)
            assert np.all(np.isfinite(model.hessian(theta))), label
        f = model.prob(theta, cov)
        assert np.all((f >= 0) & (f <= 1)), label
        for absurd in (np.full(model.ndim, 1e6), np.full(model.ndim, -1e6), np.full(model.ndim, 1e300),
                       np.full(model.ndim, np.nan), np.where(np.arange(model.ndim) % 2 == 0, 1e6, -1e6)):
            lp = model.log_prob(absurd)
            assert not np.isnan(lp) and lp < value, (label, absurd[:2], lp)
            v2, g2 = model.value_and_grad(absurd)
            assert not np.isnan(v2) and not np.any(np.isnan(g2)), label
        if len(cov) == 200:
            batch = model.log_prob_batch(np.stack([theta, np.full(model.ndim, np.nan)]))
            assert batch[0] == pytest.approx(value, rel=1e-12) and batch[1] == -np.inf


def test_initial_lands_near_the_transition():
    cov, y = synthetic(5000, 18)
    model = CompletenessModel("logistic", compress_for("logistic", cov, y))
    p = model.transform(model.initial())
    assert abs(p["m50_0"] - 24.0) < 0.3 and 0.05 < p["w"] < 0.5  # grid step of m50 is ~0.1 mag


# --------------------------------------------------------------------------- jit, batches, pointwise

def test_compiled_once_per_model_and_batches_agree():
    cov, y = synthetic(700, 19)
    model = CompletenessModel(ModelSpec(name="jit", spatial="depth", width_depth=True),
                              compress(cov, y, dm=0.01))
    theta = model.initial()
    model.log_prob(theta)
    model.value_and_grad(theta)
    before = TRACE_COUNT["log_prob"]
    rng = np.random.default_rng(20)
    thetas = theta + rng.normal(0, 0.05, (7, model.ndim))
    values = [model.log_prob(t) for t in thetas]
    for t in thetas:
        model.value_and_grad(list(t))  # a list converts to the same float64 (D,) array
    assert TRACE_COUNT["log_prob"] == before
    np.testing.assert_allclose(model.log_prob_batch(thetas), values, rtol=1e-13)
    with pytest.raises(InputError, match="shape"):
        model.log_prob(theta[:-1])


def test_cell_loglik_reproduces_the_likelihood_in_chunks():
    cov, y = synthetic(2000, 21)
    data = compress(cov, y, dm=0.02, ddepth=0.05, nuv=4)
    model = CompletenessModel("logistic_depth_smooth", data)
    rng = np.random.default_rng(22)
    thetas = model.initial() + rng.normal(0, 0.05, (5, model.ndim))
    cl = model.cell_loglik(thetas, max_elements=3 * 2 * data.ncells)  # chunks of 3 samples, last one padded
    assert cl.shape == (5, data.ncells, 2)
    total = (cl[..., 0] * data.k + cl[..., 1] * (data.n - data.k)).sum(axis=1)
    np.testing.assert_allclose(total, [model.log_likelihood(t) for t in thetas], rtol=1e-12)
    np.testing.assert_allclose(np.exp(cl[..., 0]) + np.exp(cl[..., 1]), 1.0, atol=1e-14)
    f = model.prob(thetas, data.cov)
    assert f.shape == (5, data.ncells)
    np.testing.assert_allclose(f, np.exp(cl[..., 0]), rtol=1e-12)


def test_predictions_run_through_few_padded_shapes_and_equal_each_draw_alone(monkeypatch):
    """prob / m50 pad the draws (blocks of PREDICT_DRAWS, fewer to a power of two) and the rows
    (padded_size): a shape check's 200 draws and an m50 map's 500 draws of 729 cells call one compiled
    shape, and every value equals the draw and row computed alone (the analytic logistic)."""
    from comest_bayes.bayes import model as M

    cov, y = synthetic(300, 23)
    model = CompletenessModel("logistic_depth", uncompressed(cov, y))
    shapes = []
    inner = M._jit_prob_m50_batch

    def recording(st, thetas, *args):
        shapes.append((thetas.shape[0], args[0].shape[0]))  # (draws, rows) of the full vectors
        return inner(st, thetas, *args)

    monkeypatch.setattr(M, "_jit_prob_m50_batch", recording)
    rng = np.random.default_rng(24)
    p = dict(m50_0=24.0, w=0.2, A=0.95, floor=0.03, beta_depth=0.8)
    base = model.inverse_transform(p)
    thetas = base + rng.normal(0, 0.02, (500, model.ndim))
    thetas[:, 0] = 24.0 + rng.normal(0, 0.05, 500)  # m50_0 varies from draw to draw
    d = rng.normal(0, 0.2, 729)
    at = Covariates.make(rng.uniform(22.5, 25.5, 729), depth=d)
    f = model.prob(thetas, at)
    f200 = model.prob(thetas[:200], Covariates.make(at.m[:700], depth=d[:700]))
    m50 = model.m50(thetas[:3], at)
    assert f.shape == (500, 729) and f200.shape == (200, 700) and m50.shape == (3, 729)
    assert shapes[:3] == [(256, 768)] * 3  # 500 draws: two blocks; 200 draws: one
    assert shapes[3] == (4, 768)            # 3 draws: a block of 4
    tr = model.transform(thetas)
    m50_true = tr["m50_0"][:, None] + tr["beta_depth"][:, None] * d[None, :]
    z = (m50_true - at.m[None, :]) / tr["w"][:, None]
    want = tr["floor"][:, None] + (tr["A"] - tr["floor"])[:, None] * special.expit(z)
    np.testing.assert_allclose(f, want, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(f200, want[:200, :700], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(m50, m50_true[:3], rtol=1e-14)
    one = model.prob(thetas[7], Covariates.make(at.m[5:6], depth=d[5:6]))
    assert one.shape == (1,) and one[0] == pytest.approx(want[7, 5], rel=1e-12)
    assert model.prob(thetas[:2], Covariates.make(np.array([]))).shape == (2, 0)


def test_footprint_args_are_reused_for_the_same_cells_and_rebuilt_for_new_ones():
    """The averaging programs get the footprint's device arrays once per footprint, and a new
    footprint (other arrays) is never served the previous one's cells."""
    from comest_bayes.bayes.outcomes import Covariates, compress_for
    from comest_bayes.bayes.model import CompletenessModel

    rng = np.random.default_rng(3)
    m = rng.uniform(20.0, 26.0, 3000)
    depth = rng.normal(0.0, 0.2, 3000)
    det = rng.random(3000) < 1.0 / (1.0 + np.exp((m - 23.0 - depth) / 0.2))
    model = CompletenessModel("logistic_depth", compress_for("logistic_depth", Covariates.make(m=m, depth=depth), det))
    theta = np.array([23.0, np.log(0.2), 4.0, -5.0, 1.0])[:model.ndim]
    d1, z1, w1 = np.array([-0.2, 0.3]), np.zeros(2), np.array([0.5, 0.5])
    a = model._footprint_args(d1, z1, z1, w1)
    assert model._footprint_args(d1, z1, z1, w1) is a
    d2 = np.array([0.4, 0.4])
    f2 = model.average_prob_at(theta[None, :], np.array([23.2]), d2, z1, z1, w1)
    f1 = model.average_prob_at(theta[None, :], np.array([23.2]), d1, z1, z1, w1)
    direct2 = model.prob(theta, Covariates.make(m=np.array([23.2]), depth=np.array([0.4])))
    direct1 = 0.5 * np.sum(model.prob(theta, Covariates.make(m=np.full(2, 23.2), depth=d1)))
    np.testing.assert_allclose(f2, direct2, rtol=1e-12)
    np.testing.assert_allclose(f1, direct1, rtol=1e-12)


def test_warm_start_without_the_grid_search_equals_the_one_with_it():
    """A rung warm-started from another that supplies m50_0, log_w and the plateau/floor logits starts
    where the grid-searched start overridden by them would (the search is skipped, not changed)."""
    rng = np.random.default_rng(5)
    m = rng.uniform(20.0, 26.0, 2000)
    depth = rng.normal(0.0, 0.2, 2000)
    det = rng.random(2000) < 0.97 / (1.0 + np.exp((m - 23.0 - depth) / 0.2))
    data = compress_for("spline_depth", Covariates.make(m=m, depth=depth), det)
    model = CompletenessModel("spline_depth", data)
    names = ["m50_0", "log_w", "logit_A", "logit_floor"]
    theta = np.array([23.1, math.log(0.25), 3.0, -4.0])
    fast = model.warm_start(names, theta)
    slow = model.initial()
    for i, name in enumerate(model.names):
        if name in names:
            slow[i] = theta[names.index(name)]
    np.testing.assert_array_equal(fast, slow)
    # a rung that lacks one of them still gets the searched start for it
    partial = model.warm_start(names[:2], theta[:2])
    j = model.names.index("logit_A")
    assert partial[j] == model.initial()[j]


# --------------------------------------------------------------------------- work shared or remembered


def test_padded_sizes_hold_the_cells_and_waste_at_most_a_third():
    from comest_bayes.bayes.model import padded_size

    assert [padded_size(g) for g in (1, 256, 257, 385, 673, 731, 769, 1025, 1537)] == \
        [256, 256, 384, 512, 768, 768, 1024, 1536, 2048]
    # from 4096 on, quarter steps: a position-resolved fit's 6145 cells take 7168, not 8192
    assert [padded_size(g) for g in (4096, 4097, 6145, 8193, 16385)] == [4096, 5120, 7168, 10240, 20480]
    for g in range(257, 40000, 7):
        size = padded_size(g)
        assert g <= size <= 1.5 * g  # above 256 the steps are x1.5 and x4/3
        assert g <= 4096 or size <= 1.25 * g  # above 4096 at most a fifth of the cells are padding
        assert padded_size(size) == size


def test_remembered_hessian_follows_theta_and_tau():
    """The Hessian memo returns the value a fresh model computes, for the theta and tau asked now:
    changing tau (the spline's smoothness) or theta never serves an earlier Hessian."""
    cov, y = synthetic(3000, 31)
    data = compress_for("spline_depth", cov, y)
    model = CompletenessModel("spline_depth", data)
    theta = model.initial()
    h1 = model.hessian(theta)
    h1[0, 0] = 0.0  # the caller's copy: the memo is not changed through it
    np.testing.assert_array_equal(model.hessian(theta), CompletenessModel("spline_depth", data).hessian(theta))
    model.tau = 1.0
    fresh = CompletenessModel("spline_depth", data)
    fresh.tau = 1.0
    h_tau = model.hessian(theta)
    np.testing.assert_array_equal(h_tau, fresh.hessian(theta))
    assert not np.allclose(h_tau, CompletenessModel("spline_depth", data).hessian(theta))  # tau matters
    other = theta + 0.01
    np.testing.assert_array_equal(model.hessian(other), fresh.hessian(other))
    # the log posterior follows tau as well (its prior arrays are kept per tau)
    assert model.log_prob(theta) == fresh.log_prob(theta)
    model.tau = 0.3
    assert model.log_prob(theta) == CompletenessModel("spline_depth", data).log_prob(theta)


def test_rungs_on_one_data_set_share_the_grid_search_and_start_where_alone():
    """The starting grid search is made once per data set for the rungs whose search is the same (the
    logistic, Richards and spline rungs search the logistic they contain): each rung's start equals the
    one it finds on a fresh copy of the data."""
    from dataclasses import replace as dc_replace

    cov, y = synthetic(4000, 32)
    data = compress_for("auto", cov, y)
    starts = {}
    for name in ("logistic", "logistic_depth", "richards_depth", "spline_depth"):
        starts[name] = CompletenessModel(name, data).initial()
        alone = CompletenessModel(name, dc_replace(data)).initial()
        np.testing.assert_array_equal(starts[name], alone)
    assert len(data.__dict__["_grid_starts"]) == 1
    # the shared part is the same for all: m50_0 and log_w
    for name in starts:
        np.testing.assert_array_equal(starts[name][:2], starts["logistic"][:2])


def test_padding_floor_shares_a_size_within_a_power_of_two_and_changes_no_density():
    """A worker's fits of one model share the largest padded size of the group when it is no larger than
    the power of two above their own count; the padding (empty cells) leaves every density unchanged."""
    from comest_bayes.bayes.model import padded_size, padding_floor

    with padding_floor(1024):
        assert [padded_size(g) for g in (710, 831, 513, 300, 1100)] == [1024, 1024, 1024, 384, 1536]
    with padding_floor(768):
        assert padded_size(673) == padded_size(731) == 768
    assert padded_size(710) == 768  # the floor ends with the block
    cov, y = synthetic(3000, 33)
    data = compress_for("spline_depth", cov, y)
    alone = CompletenessModel("spline_depth", data)
    pow2 = 256 * 2 ** math.ceil(math.log2(data.ncells / 256))
    assert pow2 > padded_size(data.ncells)  # this data set's count lies between the steps (1024, 1536]
    with padding_floor(pow2):
        wide = CompletenessModel("spline_depth", data)
    assert wide._data[0].shape[0] == pow2 > alone._data[0].shape[0]
    theta = alone.initial()
    assert wide.log_prob(theta) == pytest.approx(alone.log_prob(theta), rel=1e-13, abs=1e-9)
    np.testing.assert_allclose(wide.value_and_grad(theta)[1], alone.value_and_grad(theta)[1], rtol=1e-11, atol=1e-9)
