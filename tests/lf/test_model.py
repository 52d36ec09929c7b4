"""The luminosity-function forward model and its fit (comest_bayes.lf.model): closed forms (identity transfer,
the Eddington factor of a power law), the effective area, a known slope, the joint model against the
completeness model's own link, and clear errors.
"""

import math

import numpy as np
import pytest

from comest_bayes.lf.counts import CountModel
from comest_bayes.errors import InputError
from comest_bayes.lf.model import LFModel, LFWarning, build_inputs, counts_check, effective_area, fit_counts
from comest_bayes.bayes.spec import load_spec
from comest_bayes.bayes.posterior import CompletenessPosterior
from comest_bayes.recover.transfer import PhotometricTransfer, measure_transfer
from lf_truths import mock_catalog, sample_powerlaw, synthetic_posterior


LN10 = math.log(10.0)


def _gaussian_transfer(bias, sigma, lo=15.0, hi=32.0):
    """An exact Gaussian kernel (same at every true magnitude), tabulated."""
    from scipy.stats import norm

    dm = np.arange(-2.0, 2.0 + 1e-9, 0.002)
    nodes = np.array([lo, hi])
    dens = np.tile(norm.pdf(dm, bias, sigma), (2, 1))
    cdf = np.tile(norm.cdf(dm, bias, sigma), (2, 1))
    return PhotometricTransfer(nodes=nodes, dm=dm, density=dens, cdf=cdf, finite_fraction=np.ones(2),
                               n_eff=np.full(2, 1e6), bandwidth=np.zeros(2), meta={"true_range": [lo, hi]})


# --------------------------------------------------------------------------- analytic


def test_identity_transfer_and_unit_completeness_integrate_phi():
    counts = CountModel("powerlaw")
    inputs = build_inputs([21.0, 22.5], area_deg2=0.7, mag_range=(20.0, 24.0), transfer=None)
    model = LFModel(counts, inputs, f_obj=np.ones((1, inputs.grid.size)), f_bar=np.ones(inputs.grid.size))
    log_n, slope = 4.1, 0.35
    exact = 0.7 * 10**log_n * (10 ** (slope * 1.0) - 10 ** (slope * -3.0)) / (slope * LN10)
    # trapezoid-like sums on dt = 0.02 of an exponential: relative error ~ (b dt)^2 / 12 ~ 5e-6
    assert model.expected_number([log_n, slope]) == pytest.approx(exact, rel=1e-4)
    # ln L = sum ln(A phi(m_i)) - Lambda
    ll = model.log_likelihood(np.array([log_n, slope]))
    direct = sum(math.log(0.7) + LN10 * (log_n + slope * (m - 23.0)) for m in (21.0, 22.5)) - exact
    assert ll == pytest.approx(direct, rel=1e-4)


def test_gaussian_transfer_gives_the_eddington_factor_of_a_power_law():
    # A power law 10^(b m) convolved with N(bias, sigma) is the same power law shifted by bias and
    # multiplied by exp((b ln10 sigma)^2 / 2) (Eddington 1913): analytic expected number and intensity.
    counts = CountModel("powerlaw")
    bias, sigma, slope, log_n = 0.05, 0.15, 0.4, 4.0
    inputs = build_inputs([22.0], area_deg2=1.0, mag_range=(20.0, 24.0), transfer=_gaussian_transfer(bias, sigma))
    model = LFModel(counts, inputs, f_obj=np.ones((1, inputs.grid.size)), f_bar=np.ones(inputs.grid.size))
    factor = math.exp(0.5 * (slope * LN10 * sigma) ** 2)
    b = slope * LN10
    exact = 10**log_n * factor * (math.exp(b * (24 - bias - 23)) - math.exp(b * (20 - bias - 23))) / b
    assert model.expected_number([log_n, slope]) == pytest.approx(exact, rel=1e-3)
    lam = math.exp(model.log_likelihood(np.array([log_n, slope])) + exact)
    assert lam == pytest.approx(10 ** (log_n + slope * (22.0 - bias - 23.0)) * factor, rel=1e-3)


def test_effective_area_counts_unmasked_pixels():
    mask = np.zeros((100, 200), bool)
    mask[:, :50] = True
    assert effective_area(mask, 0.36) == pytest.approx(15000 * 1e-8)
    with pytest.raises(InputError, match="no unmasked pixel"):
        effective_area(np.ones((3, 3), bool), 0.2)


# --------------------------------------------------------------------------- estimator


def test_extended_poisson_fit_recovers_a_known_slope():
    rng = np.random.default_rng(12)
    log_n, slope, area = 4.0, 0.3, 0.05
    mags = sample_powerlaw(rng, log_n, slope, area, 19.0, 24.0)  # ~2000 sources
    inputs = build_inputs(mags, area_deg2=area, mag_range=(19.0, 24.0), transfer=None)
    g = inputs.grid.size
    res = fit_counts(inputs, "powerlaw", mode="fixed", f_fixed=(np.ones((1, g)), np.ones(g)), seed=3, min_ess=300)
    summ = res.parameter_summary()
    # Seeded sample; the Fisher sd of the slope is ~0.01 here.  The truth must lie within 3 posterior sd
    # (fails with probability ~0.3% for a correct estimator) and the sd must match the Fisher value to 30%.
    for name, truth in (("log_n", log_n), ("slope", slope)):
        assert abs(summ[name]["median"] - truth) < 3 * summ[name]["sd"]
    # Fisher information of the slope (normalisation free) for events with density ~ 10^(slope m) on a
    # fixed interval: N Var(m) ln10^2, Var(m) estimated from the sample itself
    fisher_sd_slope = 1.0 / math.sqrt(len(mags) * np.var(mags) * LN10**2)
    assert summ["slope"]["sd"] == pytest.approx(fisher_sd_slope, rel=0.3)


def _depth_posterior(nsamples=400, seed=0):
    """A logistic_depth posterior on a 200 x 200 image whose noise rises 2x from left to right (depth
    +0.38 to -0.38 mag), m50 = 23 + depth, with known Gaussian draws."""
    spec = load_spec("logistic_depth")
    step = 20
    noise = np.tile(np.geomspace(0.7, 1.4, 10), (10, 1))
    names = ["m50_0", "log_w", "logit_A", "logit_floor", "beta_depth"]
    post = CompletenessPosterior(spec=spec, samples=np.zeros((1, 5)), names=names,
                                 meta={"sigma_ref": 1.0, "hlr_ref": None, "image_shape": (200, 200),
                                       "mag_range": [18.0, 27.0], "kind": "point", "quantity": "completeness"},
                                 noise_grid=noise, grid_step=step,
                                 footprint=np.column_stack([np.arange(5, 200, 10.0), np.full(20, 100.0)]))
    centre = post.model.inverse_transform({"m50_0": 23.0, "w": 0.3, "A": 0.995, "floor": 1e-4, "beta_depth": 1.0})
    rng = np.random.default_rng(seed)
    post.samples = centre + np.array([0.03, 0.05, 0.0, 0.0, 0.05]) * rng.standard_normal((nsamples, 5))
    return post


def test_joint_model_uses_the_completeness_models_own_link_at_its_free_parameters():
    # The joint mode samples the completeness posterior's free parameters; the link needs the full layout
    # (pinned slots such as w_depth, beta_size).  Fed the free vector, JAX clamped the out-of-range slots to the
    # last free value (here w_depth = beta_depth = 1): the completeness, and the counts, were wrong.
    from comest_bayes.lf.model import completeness_arrays

    rng = np.random.default_rng(41)
    post = _depth_posterior()
    n = 300
    inputs = build_inputs(rng.uniform(20.0, 23.5, n), area_deg2=0.003, mag_range=(20.0, 23.5),
                          transfer=_gaussian_transfer(0.02, 0.08), x=rng.uniform(0, 199, n), y=rng.uniform(0, 199, n))
    counts = CountModel("powerlaw")
    c = post.samples[3]
    f_obj, f_bar = completeness_arrays(post, c[None, :], inputs)
    fixed = LFModel(counts, inputs, f_obj=f_obj[0], f_bar=f_bar[0])
    joint = LFModel(counts, inputs, post=post, prior_mean=post.samples.mean(axis=0),
                    prior_cov=np.cov(post.samples, rowvar=False), depth_nodes=None)
    t = np.array([5.5, 0.3])
    full = np.concatenate([t, c])
    assert joint.expected_number(full) == pytest.approx(fixed.expected_number(t), rel=1e-9)
    assert joint.log_likelihood(full) == pytest.approx(fixed.log_likelihood(t), rel=1e-9)


def test_joint_depth_nodes_match_the_exact_per_object_likelihood_and_batches_match_single_calls():
    # Joint mode with a depth-dependent completeness: f from 25 depth nodes, linear in between, instead of at
    # each of the N objects (N x M link values per walker: minutes and gigabytes on a demo tile).
    rng = np.random.default_rng(40)
    post = _depth_posterior()
    n = 1500
    x, y = rng.uniform(0, 199, n), rng.uniform(0, 199, n)
    mags = rng.uniform(20.0, 23.5, n)
    inputs = build_inputs(mags, area_deg2=0.003, mag_range=(20.0, 23.5), transfer=_gaussian_transfer(0.02, 0.08),
                          x=x, y=y)
    counts = CountModel("powerlaw")
    mu, cov = post.samples.mean(axis=0), np.cov(post.samples, rowvar=False)
    exact = LFModel(counts, inputs, post=post, prior_mean=mu, prior_cov=cov, depth_nodes=None)
    nodes = LFModel(counts, inputs, post=post, prior_mean=mu, prior_cov=cov)
    assert exact.depth_nodes is None and nodes.depth_nodes.size == 49
    assert nodes.depth_nodes[0] == pytest.approx(-2.5 * math.log10(1.4), abs=1e-9)
    thetas = np.column_stack([np.full(6, 5.5), np.linspace(0.25, 0.35, 6), post.samples[:6]])
    a = np.array([exact.log_likelihood(t) for t in thetas])
    b = np.array([nodes.log_likelihood(t) for t in thetas])
    # linear interpolation over 0.75 mag of depth in 48 steps (0.016 mag of m50 each, w = 0.3) puts a
    # relative error ~(0.016/0.3)^2/8 ~ 4e-4 on f near m50; over 1500 objects, most in the transition, that is
    # ~0.015 nats (measured 0.000-0.013 here; 25 nodes gave up to 0.053), and what the posterior sees, its
    # change between parameters, is as small
    assert np.all(np.abs(b - a) < 0.03)
    assert np.ptp(b - a) < 0.03
    # batches are evaluated in fixed-size blocks (memory): the same numbers as one call per row
    many = np.repeat(thetas, 12, axis=0)[:70]
    assert nodes.chunk < len(many)  # two blocks, the second one padded
    np.testing.assert_allclose(nodes.log_prob_batch(many), [nodes.log_prob(t) for t in many], rtol=1e-10)


@pytest.mark.slow
def test_joint_and_marginal_intervals_are_wider_than_fixed():
    rng = np.random.default_rng(21)
    # an uncertain completeness (sd 0.08 mag in m50) and a range reaching into the transition
    post = synthetic_posterior(sd_m50=0.08)
    obs = mock_catalog(rng)
    truth_true = rng.uniform(19, 27, 20000)
    tr = measure_transfer(truth_true, truth_true + 0.03 + 0.08 * rng.standard_normal(truth_true.size))
    inputs = build_inputs(obs, area_deg2=0.0123, mag_range=(20.0, 23.5), transfer=tr)
    fixed = fit_counts(inputs, "powerlaw", mode="fixed", post=post, seed=1, min_ess=300)
    joint = fit_counts(inputs, "powerlaw", mode="joint", post=post, seed=1, min_ess=300)
    marg = fit_counts(inputs, "powerlaw", mode="marginal", post=post, seed=1, min_ess=300, ncomp=12)
    sd = {r.mode: r.parameter_summary()["slope"]["sd"] for r in (fixed, joint, marg)}
    # The completeness uncertainty adds variance: with sd(m50) = 0.08 mag the slope sd grows by well over
    # 10% (joint 0.036 against fixed 0.029 here); ESS >= 300 gives sd estimates good to ~5%, so 10% is a
    # safe margin.  The marginal mode estimates the between-draw variance from ncomp draws: with a few (6)
    # it is too noisy for this check, hence 12.
    assert sd["joint"] > 1.1 * sd["fixed"]
    assert sd["marginal"] > 1.1 * sd["fixed"]
    for r in (fixed, joint, marg):
        s = r.parameter_summary()
        # within 3 posterior sd of the truth (a correct, calibrated posterior fails this ~0.3% of the time;
        # 30 replicates of this set-up gave z-scores of mean 0.1 and sd 0.9)
        assert abs(s["slope"]["median"] - 0.3) < 3 * s["slope"]["sd"], r.mode
        assert np.all(np.isfinite(r.expected_bands))
    assert joint.comp_samples.shape == (len(joint.samples), 4)


def test_range_where_completeness_vanishes_warns_and_stays_finite():
    rng = np.random.default_rng(22)
    post = synthetic_posterior(m50=22.0, w=0.2, sd_m50=0.02, sd_logw=0.02)
    obs = mock_catalog(rng, m50=22.0, w=0.2)
    inputs = build_inputs(obs, area_deg2=0.0123, mag_range=(19.0, 26.0), transfer=_gaussian_transfer(0.0, 0.05))
    with pytest.warns(LFWarning, match="completeness at the faint end"):
        res = fit_counts(inputs, "powerlaw", mode="fixed", post=post, seed=2, min_ess=200)
    assert np.all(np.isfinite(res.samples)) and np.all(np.isfinite(res.expected_bands))
    s = res.parameter_summary()
    assert abs(s["slope"]["median"] - 0.3) < 3 * s["slope"]["sd"]  # 3 sd: fails ~0.3% for a calibrated fit


def test_empty_range_is_a_clear_error():
    with pytest.raises(InputError, match="no catalog object has a magnitude in"):
        build_inputs([21.0, 22.0], area_deg2=1.0, mag_range=(25.0, 26.0), transfer=None)
    with pytest.raises(InputError, match="lo < hi"):
        build_inputs([21.0], area_deg2=1.0, mag_range=(23.0, 22.0), transfer=None)


def test_counts_check_passes_counts_drawn_from_the_model_and_flags_a_bent_shape():
    """Counts of a power law in 30 bins (20 to 400 per bin) checked against posterior draws scattered around the
    truth as a posterior of 3,000 objects would be.  Drawn from the model: over 200 seeded catalogs the p-value
    is below 0.05 in at most 10% of them (measured 6%; the binomial sd at 200 is 1.5%), and never below
    COUNTS_CHECK_P (measured minimum 0.006).  Drawn from counts 30% lower at the bright end and 30% higher at
    the faint end (a completeness of the wrong kind): p below 1e-3 in every catalog (measured p = 0 in 200 of
    200)."""
    mags = np.linspace(20.0, 23.0, 30)
    truth = 20.0 * 10 ** (0.43 * (mags - 20.0))                     # 20 ... 390 per bin
    rng = np.random.default_rng(20261129)
    low, bent = [], []
    tilt = np.linspace(0.7, 1.3, 30)
    for _ in range(200):
        draws = truth[None, :] * np.exp(rng.normal(0, 0.02, (400, 1)) + rng.normal(0, 0.01, (400, 30)))
        low.append(counts_check(rng.poisson(truth), draws, rng)["p_value"])
        bent.append(counts_check(rng.poisson(truth * tilt), draws, rng)["p_value"])
    low, bent = np.asarray(low), np.asarray(bent)
    assert np.mean(low < 0.05) <= 0.10 and low.min() >= 1e-3
    assert np.all(bent < 1e-3)
    one = counts_check(rng.poisson(truth), truth[None, :].repeat(5, 0), rng, replicates=4)
    assert one["bins"] == 30 and one["replicates"] == 20 and one["deviance"] > 0
