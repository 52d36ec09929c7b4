"""Magnitude and parameter draws, and the population fitted to an observed catalog (comest_bayes.inject.population)."""

import numpy as np
import pytest
from astropy.table import Table
from scipy import stats

from comest_bayes.config import InjectionConfig
from comest_bayes.errors import InputError
from comest_bayes.inject.profiles import sersic_index_grid
from comest_bayes.inject.population import draw_magnitudes, draw_parameters, fit_count_slope, fit_observed_population
from observed_catalog import synthetic_catalog


# --------------------------------------------------------------------------- parameter draws


def test_uniform_magnitudes():
    m = draw_magnitudes(5000, (20.0, 25.0), np.random.default_rng(1))
    assert m.min() >= 20.0 and m.max() <= 25.0
    assert stats.kstest(m, stats.uniform(loc=20, scale=5).cdf).pvalue > 1e-3


def test_power_law_magnitudes_recover_their_slope():
    m = draw_magnitudes(20000, (18.0, 26.0), np.random.default_rng(2), slope=0.35)
    slope, err = fit_count_slope(m, 18.0, 26.0)
    # sd of the ML slope for 20000 objects over 8 mag is ~0.003 (err); tolerance 5 sd
    assert err < 0.005
    assert abs(slope - 0.35) < 5 * err
    with pytest.raises(InputError, match="mag_range"):
        draw_magnitudes(3, (25.0, 20.0), np.random.default_rng(0))


@pytest.mark.parametrize("kind", ["point", "buldisk", "sersic", "observed"])
def test_draw_parameters_ranges_and_nans(kind):
    cfg = InjectionConfig(hlr_range=(0.3, 0.6), q_range=(0.5, 0.9), bulge_fraction_range=(0.2, 0.4),
                          sersic_n_range=(1.0, 2.0))
    pop = fit_observed_population(synthetic_catalog(), psf_hlr_pix=1.5, psf_sigma_pix=1.2) \
        if kind == "observed" else None
    p = draw_parameters(kind, 500, config=cfg, mag_range=(21.0, 24.0), rng=np.random.default_rng(0),
                        pixel_scale=0.2, population=pop)
    assert np.all((p["mag"] >= 21.0) & (p["mag"] <= 24.0))
    assert np.all(p["cosmos_index"] == -1)
    if kind == "point":
        for name in ("hlr_arcsec", "q", "pa_deg", "bulge_fraction", "sersic_n"):
            assert np.all(np.isnan(p[name]))
        return
    assert np.all((p["pa_deg"] >= 0) & (p["pa_deg"] < 180))
    assert np.all((p["q"] >= 0.5) & (p["q"] <= 1.0))
    if kind in ("buldisk", "sersic"):
        assert np.all((p["hlr_arcsec"] >= 0.3) & (p["hlr_arcsec"] <= 0.6))
        assert np.all(p["q"] <= 0.9)
    if kind == "buldisk":
        assert np.all((p["bulge_fraction"] >= 0.2) & (p["bulge_fraction"] <= 0.4))
        assert np.all(np.isnan(p["sersic_n"]))
    else:
        assert set(np.unique(p["sersic_n"])) <= set(sersic_index_grid((1.0, 2.0)))
        assert np.all(np.isnan(p["bulge_fraction"]))


# --------------------------------------------------------------------------- observed population


def test_observed_population_recovers_the_count_slope_and_size_relation():
    cat = synthetic_catalog()
    pop = fit_observed_population(cat, psf_hlr_pix=1.0, psf_sigma_pix=0.8)
    # the fit stops short of the incompleteness: completeness at fit_mag_hi is > 90%
    assert pop.fit_mag_hi <= 25.0 - 0.25 * np.log(9)
    assert pop.n_fit > 1500
    # statistical sd ~0.01 (pop.slope_err); residual incompleteness bias < 0.01; tolerance 0.04
    assert abs(pop.slope - 0.32) < 0.04
    assert pop.slope_err < 0.015
    # size relation: slope -0.12 dex/mag; scatter 0.08 dex (sd of these estimates ~0.005)
    assert pop.size_slope == pytest.approx(-0.12, abs=0.02)
    assert pop.size_scatter_dex == pytest.approx(0.08, abs=0.015)
    assert pop.observed_radius_pix(22.0) == pytest.approx(10 ** 0.6, rel=0.05)
    # drawn magnitudes follow the fitted slope, extrapolated to the faint limit
    rng = np.random.default_rng(9)
    m = draw_magnitudes(20000, (20.0, 27.0), rng, slope=pop.slope)
    s, e = fit_count_slope(m, 20.0, 27.0)
    assert abs(s - pop.slope) < 5 * e
    hlr, q = pop.draw_shapes(m, rng, q_range=(0.2, 1.0))
    assert np.all(hlr >= 0.1 * pop.psf_hlr_pix) and np.all((q >= 0.2) & (q <= 1.0))
    # deconvolution: at a bright magnitude, hlr^2 ~ r_obs^2 - r_psf^2 on the median
    bright = np.full(4000, 21.0)
    hlr_b, _ = pop.draw_shapes(bright, np.random.default_rng(1))
    r_obs = pop.observed_radius_pix(21.0)
    assert np.median(hlr_b) == pytest.approx(np.sqrt(r_obs ** 2 - 1.0), rel=0.03)


def test_observed_population_refuses_tiny_or_wrong_catalogs():
    cat = synthetic_catalog(n=20)
    with pytest.raises(InputError, match="at least 30"):
        fit_observed_population(cat, psf_hlr_pix=1.0, psf_sigma_pix=0.8)
    with pytest.raises(InputError, match="missing"):
        fit_observed_population(Table({"mag_auto": [20.0]}), psf_hlr_pix=1.0, psf_sigma_pix=0.8)
