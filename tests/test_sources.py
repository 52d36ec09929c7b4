"""Source profiles, parameter draws, PSFs, COSMOS loading and the observed population."""

import pickle

import galsim
import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table
from scipy import integrate, stats

from comest_bayes.config import InjectionConfig
from comest_bayes.errors import InputError, InputFileError
from comest_bayes.inject.kspace import DEV_K_STEP, buldisk_k, buldisk_radius_per_hlr, devaucouleurs_k_table, exponential_k, kspace_quadratic_forms, shear_matrices
from comest_bayes.inject.profiles import TRUNC_HLR, bulge_disk_components, sersic_enclosed_radius, sersic_index_grid, sersic_truncation, source_profile
from comest_bayes.inject.population import draw_magnitudes, draw_parameters, fit_count_slope, fit_observed_population
from comest_bayes.inject.cosmos import load_cosmos
from comest_bayes.inject.psfmodel import make_psf, psf_half_light_radius_pix
from observed_catalog import synthetic_catalog


def enclosed_fraction(profile, radius):
    """Flux fraction of a circular profile inside ``radius``, by radial integration of xValue."""
    f = lambda r: 2.0 * np.pi * r * profile.xValue(galsim.PositionD(r, 0.0))  # noqa: E731
    inner, _ = integrate.quad(f, 0.0, radius, limit=400, points=[radius * 1e-3, radius * 1e-2])
    return inner / profile.flux


# --------------------------------------------------------------------------- profiles


def test_bulge_is_a_de_vaucouleurs_sersic_n4_not_a_gaussian():
    hlr = 0.5
    bulge, disk = bulge_disk_components(hlr, 0.4, flux=10.0)
    assert isinstance(bulge.original, galsim.DeVaucouleurs) and bulge.original.n == 4.0
    assert isinstance(disk.original, galsim.Exponential)
    assert bulge.flux == pytest.approx(4.0) and disk.flux == pytest.approx(6.0)
    # ln I is exactly linear in r^(1/4) for a Sersic n=4 profile (inside the truncation) ...
    r = np.linspace(0.1, 3.0, 30) * hlr
    lnI = np.log([bulge.xValue(galsim.PositionD(v, 0.0)) for v in r])
    for power, linear in ((0.25, True), (2.0, False), (1.0, False)):
        coef = np.polyfit(r ** power, lnI, 1)
        resid = np.abs(lnI - np.polyval(coef, r ** power)).max()
        assert (resid < 1e-4) == linear, (power, resid)
    # ... with slope -1 / scale_radius^(1/4) (I ~ exp(-(r / r0)^(1/4)); r0 = hlr / b_4^4 untruncated,
    # a little different here because the truncated profile keeps the requested half-light radius)
    slope = np.polyfit(r ** 0.25, lnI, 1)[0]
    assert -slope * (bulge.original.scale_radius * hlr) ** 0.25 == pytest.approx(1.0, rel=1e-6)
    # the (truncated) bulge, the disk and their sum all have the requested half-light radius
    for prof in (bulge, disk, bulge + disk):
        assert enclosed_fraction(prof, hlr) == pytest.approx(0.5, abs=2e-3)
    assert bulge.original.trunc == pytest.approx(TRUNC_HLR)  # in half-light radii of the unit profile
    assert bulge.original.half_light_radius == pytest.approx(1.0)


def test_truncation_only_where_the_tail_matters():
    assert sersic_truncation(4.0) == TRUNC_HLR
    assert sersic_truncation(2.0) == TRUNC_HLR
    assert sersic_truncation(0.5) == 0.0
    assert sersic_truncation(1.0) == 0.0  # exponential: 2e-5 of the light beyond 8 hlr


def test_sersic_enclosed_radius_matches_the_exponential_formula():
    # exponential: flux inside x scale radii is 1 - (1 + x) exp(-x)
    x = sersic_enclosed_radius(1.0, 1.0, 0.0, 0.995)
    assert 1.0 - (1.0 + x) * np.exp(-x) == pytest.approx(0.995, abs=1e-9)
    # truncated: the radius of the full fraction is the truncation radius
    assert sersic_enclosed_radius(4.0, 0.01, 3.0, 1.0) == pytest.approx(3.0, rel=1e-6)


@pytest.mark.parametrize("kind,kw", [
    ("buldisk", dict(hlr_arcsec=0.6, q=0.5, pa_deg=20.0, bulge_fraction=0.7)),
    ("sersic", dict(hlr_arcsec=0.4, q=0.8, pa_deg=100.0, sersic_n=3.0)),
    ("observed", dict(hlr_arcsec=0.3, q=0.6, pa_deg=45.0, sersic_n=1.5)),
])
def test_source_profile_flux_and_radius(kind, kw):
    sp = source_profile(kind, flux=123.0, fraction=0.995, **kw)
    assert sp.profile.flux == pytest.approx(123.0)
    # the radius encloses >= 99.5% of the light: draw finely and sum inside the ellipse's circumcircle
    scale = 0.02
    n = int(2 * (sp.radius_arcsec * 1.6) / scale) + 1
    img = sp.profile.drawImage(nx=n, ny=n, scale=scale, method="no_pixel").array
    c = (n - 1) / 2.0
    yy, xx = np.mgrid[0:n, 0:n]
    inside = np.hypot(xx - c, yy - c) * scale <= sp.radius_arcsec
    assert img[inside].sum() / 123.0 >= 0.995 - 2e-3  # pixelisation of the cusp costs < 0.2%


# --------------------------------------------------------------------------- Fourier transforms (batched drawing)


def _kvalues(profile, kx, ky):
    return np.array([profile.kValue(galsim.PositionD(a, b)) for a, b in zip(kx, ky)])


@pytest.mark.parametrize("bulge_fraction", [0.0, 0.35, 1.0])
def test_buldisk_transform_matches_galsim(bulge_fraction):
    bulge, disk = bulge_disk_components(1.0, bulge_fraction, flux=1.0)
    k = np.linspace(0.0, 40.0, 801)
    ref = _kvalues(bulge + disk, k, np.zeros_like(k))
    assert np.abs(ref.imag).max() == 0.0  # real and radial, as the batched drawing assumes
    ours = buldisk_k(k ** 2, bulge_fraction)
    # the disk is analytic (agrees to rounding); the bulge is a linear interpolation of GalSim's own
    # values with step DEV_K_STEP = 0.0025, whose error h^2 |F''| / 8 measured at most 7.6e-6 of F(0) = 1
    tol = 1e-12 if bulge_fraction == 0.0 else 2e-5
    np.testing.assert_allclose(ours, ref.real, rtol=0, atol=tol)
    np.testing.assert_allclose(exponential_k(k ** 2), _kvalues(disk.original, k, 0 * k).real, rtol=1e-12, atol=0)


def test_devaucouleurs_table_is_galsims_values_on_its_grid_and_grows_on_demand():
    small = devaucouleurs_k_table()
    assert small.step == DEV_K_STEP and small.kmax >= 64.0
    bulge = bulge_disk_components(1.0, 1.0)[0]
    idx = np.array([0, 1, 17, 4000, small.values.size - 1])
    np.testing.assert_allclose(small.values[idx], _kvalues(bulge, idx * DEV_K_STEP, 0 * idx).real, rtol=1e-10, atol=0)
    assert small(np.array([0.0]))[0] == pytest.approx(1.0, abs=1e-15)
    big = devaucouleurs_k_table(300.0)
    assert big.kmax >= 300.0 and big.kmax < 2 * 300.0 + 64
    assert devaucouleurs_k_table(10.0) is small  # built once per process


def test_shear_matrices_are_galsims():
    q = np.array([0.3, 0.55, 1.0, 0.9])
    pa = np.array([0.0, 37.0, 120.0, 179.0])
    for m, qi, pi in zip(shear_matrices(q, pa), q, pa):
        np.testing.assert_allclose(m, galsim.Shear(q=qi, beta=pi * galsim.degrees).getMatrix(), rtol=0, atol=1e-15)


def test_quadratic_forms_reproduce_galsims_transformed_profiles():
    # An exponential disk sheared, dilated and mapped to pixels by a rotated, skewed WCS Jacobian:
    # GalSim's transform at pixel wavenumber k must equal flux * F_exp(k^T Q k).
    rng = np.random.default_rng(3)
    hlr, q, pa = np.array([0.4, 0.7]), np.array([0.45, 0.9]), np.array([25.0, 140.0])
    jac = np.array([[[-0.18, 0.05], [0.04, 0.19]], [[0.26, 0.0], [0.0, 0.26]]])
    quad = kspace_quadratic_forms(hlr, q, pa, jac)
    unit = bulge_disk_components(1.0, 0.0)[1].original
    for i in range(2):
        world = unit.dilate(hlr[i]).shear(q=q[i], beta=pa[i] * galsim.degrees).withFlux(3.0)
        prof = galsim.JacobianWCS(*jac[i].ravel()).toImage(world)
        k = rng.uniform(-np.pi, np.pi, (40, 2))
        ref = _kvalues(prof, k[:, 0], k[:, 1])
        ksq = np.einsum("ni,ij,nj->n", k, quad[i], k)
        np.testing.assert_allclose(3.0 * exponential_k(ksq), ref.real, rtol=1e-10, atol=1e-14)
        assert np.abs(ref.imag).max() < 1e-14


def test_buldisk_radius_per_hlr_encloses_the_fraction():
    # vectorised growth-curve search: the first 0.01-step radius enclosing the fraction, per source
    bf = np.array([0.0, 0.2, 0.5, 0.8, 1.0])
    radii = buldisk_radius_per_hlr(bf, 0.995)
    assert np.all(np.diff(radii) > 0)  # more bulge, more light at large radii
    for b, r in zip(bf, radii):
        bulge, disk = bulge_disk_components(1.0, b)
        prof = bulge + disk if 0 < b < 1 else (disk if b == 0 else bulge)
        assert enclosed_fraction(prof, r) >= 0.995 - 1e-4
        assert enclosed_fraction(prof, r - 0.02) < 0.995
    # and it is what source_profile uses for its stamp radius
    sp = source_profile("buldisk", flux=1.0, hlr_arcsec=0.5, q=1.0, pa_deg=0.0, bulge_fraction=0.5)
    assert sp.radius_arcsec == 0.5 * radii[2]


def test_point_source_has_no_profile():
    sp = source_profile("point", flux=5.0)
    assert sp.profile is None and sp.radius_arcsec == 0.0


def test_sersic_index_grid():
    g = sersic_index_grid((0.5, 4.0))
    assert g[0] == 0.5 and g[-1] == 4.0 and len(g) == 71
    np.testing.assert_allclose(np.diff(g), 0.05)
    wide = sersic_index_grid((0.3, 6.2))  # 119 values at 0.05: the step widens to keep 80
    assert len(wide) == 80 and wide[0] == 0.3 and wide[-1] == 6.2
    np.testing.assert_allclose(sersic_index_grid((1.0, 2.0)), np.arange(1.0, 2.0001, 0.05))
    np.testing.assert_array_equal(sersic_index_grid((2.0, 2.0)), [2.0])


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


# --------------------------------------------------------------------------- PSF


@pytest.mark.parametrize("name", ["moffat", "gaussian", "kolmogorov"])
def test_analytic_psf_has_the_image_fwhm_and_unit_flux(name):
    cfg = InjectionConfig(psf=name, moffat_beta=2.5)
    psf = make_psf(cfg, 3.5, 0.2)
    assert psf.flux == pytest.approx(1.0)
    # FWHM measured on a finely sampled drawing: 3.5 px * 0.2"/px = 0.7"
    img = psf.drawImage(nx=256, ny=256, scale=0.01, method="no_pixel")
    assert img.calculateFWHM() == pytest.approx(0.7, rel=0.01)
    if name == "moffat":
        assert psf.beta == 2.5
    assert psf_half_light_radius_pix(psf, 0.2) == pytest.approx(psf.half_light_radius / 0.2)


def test_fits_psf_is_normalised_recentred_and_scaled(tmp_path):
    # an off-centre Gaussian of sigma 2 px in a 41x41 image, flux 7
    yy, xx = np.mgrid[0:41, 0:41]
    data = 7.0 * np.exp(-((xx - 21.5) ** 2 + (yy - 19.0) ** 2) / (2 * 2.0 ** 2)) / (2 * np.pi * 4.0)
    path = tmp_path / "psf.fits"
    fits.writeto(path, data.astype(np.float32))
    for psf_scale, expected_scale in ((0.0, 0.3), (0.1, 0.1)):
        cfg = InjectionConfig(psf=str(path), psf_pixel_scale=psf_scale)
        psf = make_psf(cfg, None, 0.3)
        assert psf.flux == pytest.approx(1.0, rel=1e-6)
        img = psf.drawImage(nx=101, ny=101, scale=expected_scale / 2, method="no_pixel")
        mom = img.FindAdaptiveMom()
        # recentred: centroid at the image's true centre (GalSim 1-based: 51, 51)
        assert mom.moments_centroid.x == pytest.approx(51.0, abs=0.02)
        assert mom.moments_centroid.y == pytest.approx(51.0, abs=0.02)
        # sigma 2 PSF pixels = 4 drawing pixels
        assert mom.moments_sigma == pytest.approx(4.0, rel=0.02)


def test_fits_psf_pixel_scale_from_the_pixelscl_keyword(tmp_path):
    yy, xx = np.mgrid[0:31, 0:31]
    data = np.exp(-((xx - 15.0) ** 2 + (yy - 15.0) ** 2) / (2 * 3.0 ** 2))
    path = tmp_path / "webbpsf_like.fits"
    fits.writeto(path, data, fits.Header({"PIXELSCL": 0.01}))
    psf = make_psf(InjectionConfig(psf=str(path)), None, 0.03)
    # sigma 3 PSF pixels of 0.01" = 0.03"; a Gaussian's half-light radius is 1.1774 sigma
    assert psf_half_light_radius_pix(psf, 0.03) == pytest.approx(1.1774, rel=0.03)
    psf = make_psf(InjectionConfig(psf=str(path), psf_pixel_scale=0.02), None, 0.03)  # config wins
    assert psf_half_light_radius_pix(psf, 0.03) == pytest.approx(2 * 1.1774, rel=0.03)


def test_psf_errors(tmp_path):
    with pytest.raises(InputFileError, match="neither one of"):
        make_psf(InjectionConfig(psf=str(tmp_path / "nope.fits")), 3.0, 0.2)
    with pytest.raises(InputError, match="FWHM"):
        make_psf(InjectionConfig(psf="moffat"), None, 0.2)
    bad = tmp_path / "bad.fits"
    fits.writeto(bad, np.full((5, 5), np.nan, dtype=np.float32))
    with pytest.raises(InputError, match="non-finite"):
        make_psf(InjectionConfig(psf=str(bad)), None, 0.2)


def test_jwst_psf_file(shared_data):
    cfg = InjectionConfig(psf=str(shared_data / "jwst" / "jwst_nircam_f200w_webbpsf.fits"))
    psf = make_psf(cfg, None, 0.0308)
    assert psf.flux == pytest.approx(1.0)
    # detector-sampled WebbPSF model: the half-light radius is of order one pixel (FWHM ~2.5 px)
    assert 0.7 < psf_half_light_radius_pix(psf, 0.0308) < 3.0


# --------------------------------------------------------------------------- COSMOS


def write_fake_cosmos(directory, gal_file="gals.fits", psf_file="psfs.fits"):
    cols = fits.ColDefs([
        fits.Column(name="IDENT", format="J", array=[1, 2]),
        fits.Column(name="GAL_FILENAME", format="20A", array=[gal_file, gal_file]),
        fits.Column(name="PSF_FILENAME", format="20A", array=[psf_file, psf_file]),
        fits.Column(name="GAL_HDU", format="J", array=[0, 1]),
        fits.Column(name="PSF_HDU", format="J", array=[0, 1]),
        fits.Column(name="PIXEL_SCALE", format="D", array=[0.03, 0.03]),
    ])
    fits.BinTableHDU.from_columns(cols).writeto(directory / "cat.fits")


def test_cosmos_missing_image_file_is_named(tmp_path):
    write_fake_cosmos(tmp_path)
    (tmp_path / "psfs.fits").write_bytes(b"")
    with pytest.raises(InputError, match=r"missing: gals\.fits"):
        load_cosmos(directory=str(tmp_path), file_name="cat.fits")


def test_cosmos_configuration_errors(tmp_path):
    with pytest.raises(InputError, match="cosmos_dir"):
        load_cosmos(InjectionConfig())
    with pytest.raises(InputError, match="not a directory"):
        load_cosmos(directory=str(tmp_path / "absent"))
    with pytest.raises(InputError, match="is not in"):
        load_cosmos(directory=str(tmp_path), file_name="cat.fits")


def test_galsim_example_without_images_gives_a_clear_error(shared_data):
    cfg = InjectionConfig(cosmos_dir=str(shared_data / "cosmos" / "galsim_23.5_example"),
                          cosmos_file="real_galaxy_catalog_23.5_example.fits")
    with pytest.raises(InputError, match=r"real_galaxy_images\.fits"):
        load_cosmos(cfg)


def test_cosmos_sample_loads_and_pickles(shared_data):
    cfg = InjectionConfig(cosmos_dir=str(shared_data / "cosmos" / "btk_26_extension"))
    sample = load_cosmos(cfg)
    assert sample.n == 100
    assert sample.probabilities.sum() == pytest.approx(1.0)
    again = pickle.loads(pickle.dumps(sample))
    assert again.galaxy(5).flux == pytest.approx(sample.galaxy(5).flux)
    sp = source_profile("cosmos", flux=42.0, pa_deg=30.0, cosmos_index=5, cosmos=sample)
    assert sp.profile.flux == pytest.approx(42.0)
    with pytest.raises(InputError, match="outside"):
        sample.galaxy(100)
    p = draw_parameters("cosmos", 300, config=cfg, mag_range=(22, 24), rng=np.random.default_rng(0),
                        pixel_scale=0.2, cosmos=sample)
    assert p["cosmos_index"].min() >= 0 and p["cosmos_index"].max() < 100
    assert len(np.unique(p["cosmos_index"])) > 50  # 300 draws from 100 galaxies


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


def test_make_psf_rejects_a_bad_pixel_scale():
    with pytest.raises(InputError, match="pixel scale"):
        make_psf(InjectionConfig(), 3.0, 0.0)
