"""Count models: analytic forms, integrals and the declarative specifications."""

import math

import numpy as np
import pytest
from scipy.special import gamma

from comest_bayes.lf.counts import CountModel, list_count_specs, load_count_spec
from comest_bayes.errors import ConfigError


def _trapz(y, x):
    return float(np.sum(0.5 * (y[1:] + y[:-1]) * np.diff(x)))


def test_shipped_specs_load_with_their_forms():
    names = list_count_specs()
    assert {"powerlaw", "schechter", "double_powerlaw"} <= set(names)
    for name in names:
        spec = load_count_spec(name)
        assert spec.form == name
        assert set(spec.priors) == set(spec.params)


def test_powerlaw_integral_matches_the_closed_form():
    model = CountModel("powerlaw")
    log_n, slope = 4.3, 0.31
    m = np.linspace(20.0, 25.0, 20001)
    phi = model.phi([log_n, slope], m)
    # int 10^(log_n + b (m - m_ref)) dm = 10^log_n (10^(b (hi - m_ref)) - 10^(b (lo - m_ref))) / (b ln 10)
    exact = 10**log_n * (10 ** (slope * (25 - 23)) - 10 ** (slope * (20 - 23))) / (slope * math.log(10))
    assert _trapz(phi, m) == pytest.approx(exact, rel=1e-7)
    assert phi[np.searchsorted(m, 23.0)] == pytest.approx(10**log_n, rel=1e-9)


def test_schechter_total_is_phi_star_gamma_alpha_plus_one():
    model = CountModel("schechter")
    log_phi_star, m_star, alpha = 3.0, 20.0, -0.5
    m = np.linspace(5.0, 60.0, 400001)
    total = _trapz(model.phi([log_phi_star, m_star, alpha], m), m)
    # with x = 10^(0.4 (m* - m)): int phi dm = phi* int x^alpha e^-x dx = phi* Gamma(alpha + 1)
    assert total == pytest.approx(10**log_phi_star * gamma(alpha + 1.0), rel=1e-5)


def test_double_powerlaw_tends_to_its_two_slopes_and_passes_the_break():
    model = CountModel("double_powerlaw")
    p = [4.0, 22.0, 0.6, 0.25]
    assert model.phi(p, [22.0])[0] == pytest.approx(1e4, rel=1e-12)
    lg = lambda m: np.log10(model.phi(p, np.array([m]))[0])  # noqa: E731
    assert (lg(12.1) - lg(12.0)) / 0.1 == pytest.approx(0.6, abs=1e-3)
    assert (lg(32.1) - lg(32.0)) / 0.1 == pytest.approx(0.25, abs=1e-3)


def test_priors_are_normalised_and_uniform_bounds_give_minus_inf():
    model = CountModel("powerlaw")
    lo, hi = model.prior_box()
    assert lo[0] == -2.0 and hi[0] == 9.0 and np.isinf(lo[1])
    # log_n uniform on [-2, 9] (density 1/11), slope Normal(0.3, 0.5) at its mean
    expected = -math.log(11.0) - math.log(0.5) - 0.5 * math.log(2 * math.pi)
    assert float(model.log_prior(np.array([4.0, 0.3]))) == pytest.approx(expected, rel=1e-12)
    assert float(model.log_prior(np.array([9.5, 0.3]))) == -np.inf
    draws = model.prior_draws(2000, np.random.default_rng(1))
    assert draws.shape == (2000, 2) and draws[:, 0].min() >= -2 and draws[:, 0].max() <= 9


def test_user_spec_from_a_file(tmp_path):
    path = tmp_path / "mine.toml"
    path.write_text('form = "powerlaw"\n[constants]\nm_ref = 20.0\n'
                    '[priors]\nlog_n = {dist = "normal", mu = 3.0, sigma = 1.0}\n'
                    'slope = {dist = "uniform", lo = 0.0, hi = 1.0}\n')
    spec = load_count_spec(str(path))
    assert spec.name == "mine" and spec.constants == {"m_ref": 20.0}
    assert CountModel(spec).phi([3.0, 0.5], [20.0])[0] == pytest.approx(1e3)


@pytest.mark.parametrize("text, message", [
    ('form = "__import__(\'os\').system(\'true\')"\n', "registry"),
    ('form = "powerlaw"\n[priors]\nlog_n = {dist = "normal", mu = 3.0, sigma = 1.0}\n', "no prior for parameter"),
    ('form = "powerlaw"\n[priors]\nlog_n = {dist = "cauchy", mu = 3.0, sigma = 1.0}\n'
     'slope = {dist = "normal", mu = 0.3, sigma = 0.1}\n', "dist"),
    ('form = "powerlaw"\n[priors]\nlog_n = {dist = "uniform", lo = 3.0, hi = 1.0}\n'
     'slope = {dist = "normal", mu = 0.3, sigma = 0.1}\n', "hi > lo"),
    ('form = "powerlaw"\nslopes = 1\n', "unknown key"),
])
def test_invalid_user_specs_are_refused_with_the_reason(tmp_path, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message):
        load_count_spec(path)


def test_unknown_name_suggests_the_closest():
    with pytest.raises(ConfigError, match="Did you mean 'schechter'"):
        load_count_spec("schecter")


def test_a_spec_can_ask_auto_for_emcee_and_the_double_power_law_does(tmp_path, monkeypatch):
    """--sampler auto importance-sampled the double power law's Laplace approximation and accepted one mode of
    a multimodal posterior (k-hat 0.685, a 95% interval 5x too narrow). Its spec now asks auto for emcee;
    other samplers given explicitly are kept, and specs without the key keep the default rule."""
    import comest_bayes.lf.model as M
    from comest_bayes.lf.model import build_inputs, fit_counts

    assert load_count_spec("double_powerlaw").sampler == "emcee"
    assert load_count_spec("powerlaw").sampler == ""
    bad = tmp_path / "bad.toml"
    bad.write_text('form = "powerlaw"\nsampler = "nuts"\n[priors]\nlog_n = { dist = "uniform", lo = 0.0, hi = 8.0 }\n'
                   'slope = { dist = "normal", mu = 0.6, sigma = 0.1 }\n')
    with pytest.raises(ConfigError, match="invalid sampler = 'nuts'"):
        load_count_spec(bad)

    used = []

    class Stop(Exception):
        pass

    def spy(model, *, sampler, **kw):
        used.append(sampler)
        raise Stop

    monkeypatch.setattr(M, "fit", spy)
    rng = np.random.default_rng(2)
    inputs = build_inputs(rng.uniform(20.0, 23.0, 300), area_deg2=0.01, mag_range=(20.0, 23.0), transfer=None)
    f_fixed = (np.ones(inputs.grid.size), np.ones(inputs.grid.size))
    for model, sampler, expected in (("double_powerlaw", "auto", "emcee"), ("double_powerlaw", "importance",
                                                                           "importance"), ("powerlaw", "auto", "auto")):
        with pytest.raises(Stop):
            fit_counts(inputs, model, mode="fixed", f_fixed=f_fixed, sampler=sampler)
        assert used[-1] == expected
