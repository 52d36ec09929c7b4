"""Truth tables and rendering of injected sources."""

import warnings

import galsim
import numpy as np
import pytest
from astropy.table import Table, vstack
from astropy.wcs import WCS

from comest_bayes.config import InjectionConfig
from comest_bayes.errors import InputError
from comest_bayes.inject.render import (FLAG_DRAW_ERROR, FLAG_MASKED, FLAG_OFF_IMAGE, TRUTH_COLUMNS, StampRenderer, local_jacobians, make_truth, psf_enclosed_radius_pix, render_truth)
from comest_bayes.inject.cosmos import load_cosmos
from comest_bayes.inject.psfmodel import make_psf
from comest_bayes.inject.profiles import sersic_index_grid

from conftest import tan_header
from observed_catalog import synthetic_catalog

ZP = 30.0
SCALE = 0.2
FWHM = 3.5  # pixels


def truth_for(kind, xs, ys, mags, *, shape=(128, 128), cosmos=None, **columns):
    """A truth table with the given sources (drawn with make_truth, then overridden).

    Drawn on a canvas large enough for every galaxy's stamp (galaxies are placed where their stamps
    fit; the positions are replaced anyway).
    """
    cfg = InjectionConfig(min_sep=0.0)
    canvas = (max(shape[0], 2048), max(shape[1], 2048))
    t = make_truth(kind, shape=canvas, pixel_scale=SCALE, fwhm_pix=FWHM, config=cfg, mag_range=(20.0, 21.0),
                   rng=np.random.default_rng(0), zeropoint=ZP, n=len(xs), cosmos=cosmos)
    t["x"] = np.asarray(xs, dtype=float)
    t["y"] = np.asarray(ys, dtype=float)
    t["mag"] = np.asarray(mags, dtype=float)
    t["flux"] = 10 ** (-0.4 * (t["mag"] - ZP))
    for name, value in columns.items():
        t[name] = value
    return t


def render(truth, shape=(128, 128), *, psf_name="moffat", gain=None, seed=1, photon_noise=False, **kw):
    cfg = InjectionConfig(psf=psf_name, photon_noise=photon_noise)
    psf = make_psf(cfg, FWHM, SCALE)
    return render_truth(np.zeros(shape, np.float32), truth, psf=psf, config=cfg, pixel_scale=SCALE,
                        zeropoint=ZP, gain=gain, rng_seed=seed, **kw)


# --------------------------------------------------------------------------- truth table


def test_truth_columns_units_ids_and_fluxes():
    cfg = InjectionConfig(density=60.0, min_sep=2.0)
    t = make_truth("buldisk", shape=(300, 400), pixel_scale=SCALE, fwhm_pix=FWHM, config=cfg,
                   mag_range=(21.0, 25.0), rng=np.random.default_rng(4), zeropoint=ZP)
    assert t.colnames == list(TRUTH_COLUMNS)
    # Poisson mean 60 * (300*400*0.04/3600) = 80; P(|N-80| > 40) ~ 1e-5
    assert 40 < len(t) < 120
    np.testing.assert_array_equal(t["injection_id"], np.arange(len(t)))
    np.testing.assert_allclose(t["flux"], 10 ** (-0.4 * (t["mag"] - ZP)))
    assert str(t["x"].unit) == "pix" and str(t["hlr_arcsec"].unit) == "arcsec"
    assert np.all(np.isnan(t["ra"])) and np.all(t["cosmos_index"] == -1)
    assert t.meta["n_placed"] == len(t) and t.meta["placement_complete"]
    assert all(np.isscalar(v) for v in t.meta.values())


def test_same_seed_same_truth_other_seed_different():
    cfg = InjectionConfig(density=40.0)
    kw = dict(shape=(200, 200), pixel_scale=SCALE, fwhm_pix=FWHM, config=cfg, mag_range=(21.0, 25.0),
              zeropoint=ZP)
    a = make_truth("sersic", rng=np.random.default_rng(7), **kw)
    b = make_truth("sersic", rng=np.random.default_rng(7), **kw)
    c = make_truth("sersic", rng=np.random.default_rng(8), **kw)
    for name in TRUTH_COLUMNS:
        np.testing.assert_array_equal(a[name], b[name])
    assert len(a) != len(c) or not np.allclose(a["x"], c["x"])


def test_masked_injections_are_flagged():
    shape = (200, 200)
    mask = np.zeros(shape, dtype=bool)
    mask[:, :80] = True
    cfg = InjectionConfig(density=300.0, min_sep=1.0)
    t = make_truth("point", shape=shape, mask=mask, pixel_scale=SCALE, fwhm_pix=FWHM, config=cfg,
                   mag_range=(21.0, 25.0), rng=np.random.default_rng(1), zeropoint=ZP)
    ix = np.floor(np.asarray(t["x"]) + 0.5).astype(int)
    iy = np.floor(np.asarray(t["y"]) + 0.5).astype(int)
    np.testing.assert_array_equal(t["masked"], mask[iy, ix])
    np.testing.assert_array_equal((t["flag"] & FLAG_MASKED) != 0, mask[iy, ix])
    assert 0 < t["masked"].sum() < len(t)
    _, rendered = render(t, shape)
    np.testing.assert_array_equal((rendered["flag"] & FLAG_MASKED) != 0, mask[iy, ix])  # kept by rendering


def test_sky_positions_and_local_noise():
    shape = (150, 150)
    wcs = WCS(tan_header(shape, SCALE, rotation_deg=20.0))
    noise = np.arange(150 * 150, dtype=float).reshape(shape)
    t = make_truth("point", shape=shape, pixel_scale=SCALE, fwhm_pix=FWHM, config=InjectionConfig(density=50.0),
                   mag_range=(21.0, 25.0), rng=np.random.default_rng(2), zeropoint=ZP, wcs=wcs, noise=noise)
    x, y = wcs.all_world2pix(t["ra"], t["dec"], 0)
    np.testing.assert_allclose(x, t["x"], atol=1e-6)
    np.testing.assert_allclose(y, t["y"], atol=1e-6)
    ix = np.floor(np.asarray(t["x"]) + 0.5).astype(int)
    iy = np.floor(np.asarray(t["y"]) + 0.5).astype(int)
    np.testing.assert_array_equal(t["local_noise"], noise[iy, ix])


def test_observed_kind_follows_the_catalog():
    cfg = InjectionConfig(density=200.0, min_sep=0.5, sersic_n_range=(0.5, 2.0))
    t = make_truth("observed", shape=(300, 300), pixel_scale=SCALE, fwhm_pix=FWHM, config=cfg,
                   mag_range=(20.0, 27.0), rng=np.random.default_rng(3), zeropoint=ZP,
                   observed_catalog=synthetic_catalog())
    assert t.meta["obs_slope"] == pytest.approx(0.32, abs=0.04)  # the catalog's known slope
    assert np.all(t["hlr_arcsec"] > 0) and np.all((t["q"] > 0) & (t["q"] <= 1))
    assert set(np.unique(t["sersic_n"])) <= set(sersic_index_grid((0.5, 2.0)))
    # the size relation shrinks with magnitude: faint injections are smaller on the median
    bright = np.median(t["hlr_arcsec"][t["mag"] < 23.0])
    faint = np.median(t["hlr_arcsec"][t["mag"] > 25.0])
    assert faint < bright
    img, rendered = render(t, (300, 300))
    assert rendered.meta["n_draw_errors"] == 0


def test_missing_inputs_are_clear_errors():
    kw = dict(shape=(50, 50), pixel_scale=SCALE, fwhm_pix=FWHM, config=InjectionConfig(),
              rng=np.random.default_rng(0), zeropoint=ZP)
    with pytest.raises(InputError, match="mag_range"):
        make_truth("point", **kw)
    with pytest.raises(InputError, match="observed_catalog"):
        make_truth("observed", mag_range=(20, 25), **kw)
    with pytest.raises(InputError, match="load_cosmos"):
        make_truth("cosmos", mag_range=(20, 25), **kw)
    with pytest.raises(InputError, match="unknown source kind"):
        make_truth("galaxy", mag_range=(20, 25), **kw)
    t = truth_for("point", [10.0], [10.0], [22.0], shape=(50, 50))
    with pytest.raises(InputError, match="zero point"):
        render_truth(np.zeros((50, 50)), t, psf=make_psf(InjectionConfig(), FWHM, SCALE),
                     config=InjectionConfig(), pixel_scale=SCALE, zeropoint=ZP + 1.0, rng_seed=0)


# --------------------------------------------------------------------------- rendering: flux and shape


@pytest.mark.parametrize("kind,columns", [
    ("point", {}),
    ("buldisk", dict(hlr_arcsec=[0.6], q=[0.5], pa_deg=[30.0], bulge_fraction=[0.8])),
    ("sersic", dict(hlr_arcsec=[0.5], q=[0.7], pa_deg=[80.0], sersic_n=[4.0])),
    ("sersic", dict(hlr_arcsec=[0.4], q=[1.0], pa_deg=[0.0], sersic_n=[1.0])),
])
def test_drawn_flux_equals_requested_flux(kind, columns):
    shape = (256, 256)
    t = truth_for(kind, [128.3], [127.6], [22.0], shape=shape, **columns)
    flux = float(t["flux"][0])
    big, info = render(t, shape, flux_fraction=0.9999)
    assert info["flag"][0] == 0
    assert big.sum(dtype=float) / flux == pytest.approx(1.0, abs=0.005)
    # default stamps are sized for 99.5% of the light; measured: the stamp footprint holds >= 99.8%
    # of the light of the large-stamp drawing (point source; more for galaxies), and the light beyond
    # it that the FFT wraps back onto the stamp edges is < 0.2% of the flux
    small, info = render(t, shape)
    assert info.meta["flux_fraction"] == 0.995
    footprint = small != 0
    assert big[footprint].sum(dtype=float) / flux > 0.995
    assert small.sum(dtype=float) / flux == pytest.approx(1.0, abs=0.005)
    assert np.abs(small.astype(float) - big).max() < 1e-3 * big.max()


def test_cosmos_galaxies_have_the_requested_flux(shared_data):
    sample = load_cosmos(InjectionConfig(cosmos_dir=str(shared_data / "cosmos" / "btk_26_extension")))
    shape = (200, 200)
    t = truth_for("cosmos", [60.2, 140.7], [70.4, 130.1], [21.0, 23.0], shape=shape, cosmos=sample,
                  cosmos_index=[3, 40], pa_deg=[10.0, 250.0])
    img, info = render(t, shape, cosmos=sample, flux_fraction=0.9999)
    assert np.all(info["flag"] == 0)
    assert img.sum(dtype=float) / t["flux"].sum() == pytest.approx(1.0, abs=0.005)
    img2, _ = render(t, shape, cosmos=sample)
    assert img2.sum(dtype=float) / t["flux"].sum() > 0.99


def test_rendering_agrees_with_galsim_drawimage():
    # the PSF transform is cached and reused: the stamp must equal GalSim's own convolution
    shape = (80, 80)
    t = truth_for("buldisk", [40.37], [38.81], [21.0], shape=shape, hlr_arcsec=[0.5], q=[0.6],
                  pa_deg=[25.0], bulge_fraction=[0.5])
    ours, _ = render(t, shape, flux_fraction=0.9999)
    cfg = InjectionConfig()
    psf = make_psf(cfg, FWHM, SCALE)
    bulge = galsim.DeVaucouleurs(half_light_radius=0.5, trunc=4.0, flux_untruncated=False)
    disk = galsim.Exponential(half_light_radius=0.5)
    gal = (0.5 * bulge + 0.5 * disk).shear(q=0.6, beta=25.0 * galsim.degrees).withFlux(float(t["flux"][0]))
    image = galsim.ImageD(80, 80, scale=SCALE)  # GalSim pixel (1, 1) is numpy [0, 0]
    ref = galsim.Convolve(gal, psf).drawImage(image=image, method="no_pixel",
                                              center=galsim.PositionD(40.37 + 1, 38.81 + 1)).array
    assert np.abs(ours - ref).max() < 1e-3 * ref.max()


def test_rendering_with_a_rotated_wcs_agrees_with_galsim():
    shape = (80, 80)
    header = tan_header(shape, SCALE, rotation_deg=35.0)
    wcs = WCS(header)
    t = truth_for("sersic", [39.6], [41.2], [21.0], shape=shape, hlr_arcsec=[0.5], q=[0.4], pa_deg=[10.0],
                  sersic_n=[1.0])
    ours, _ = render(t, shape, wcs=wcs, flux_fraction=0.9999)
    gwcs = galsim.GSFitsWCS(header=galsim.FitsHeader(header=header))
    pos = galsim.PositionD(39.6 + 1, 41.2 + 1)
    local = gwcs.local(image_pos=pos)
    psf_world = local.toWorld(galsim.PixelScale(SCALE).toImage(make_psf(InjectionConfig(), FWHM, SCALE)))
    gal = galsim.Exponential(half_light_radius=0.5, flux=float(t["flux"][0])).shear(q=0.4, beta=10 * galsim.degrees)
    image = galsim.ImageD(80, 80, wcs=gwcs)
    ref = galsim.Convolve(gal, psf_world).drawImage(image=image, method="no_pixel", center=pos).array
    assert np.abs(ours - ref).max() < 1e-3 * ref.max()
    assert ours.sum() / t["flux"][0] == pytest.approx(1.0, abs=0.003)  # flux kept through the Jacobian


def test_local_jacobian_of_a_rotated_tan_wcs():
    wcs = WCS(tan_header((100, 100), 0.25, rotation_deg=30.0))
    jac = local_jacobians([50.0, 10.0], [50.0, 90.0], wcs=wcs, pixel_scale=0.0)
    c, s = np.cos(np.deg2rad(30.0)), np.sin(np.deg2rad(30.0))
    for j in jac:  # u = west, v = north: a rotation by 30 degrees times the scale
        np.testing.assert_allclose(j, 0.25 * np.array([[c, -s], [s, c]]), atol=2e-6)
    np.testing.assert_allclose(local_jacobians([3.0], [4.0], pixel_scale=0.3)[0], 0.3 * np.eye(2))


@pytest.mark.parametrize("rotation", [0.0, 40.0])
def test_position_angle_is_counter_clockwise_from_west(rotation):
    shape = (96, 96)
    wcs = WCS(tan_header(shape, SCALE, rotation_deg=rotation))
    t = truth_for("sersic", [48.0], [48.0], [19.0], shape=shape, hlr_arcsec=[0.8], q=[0.3], pa_deg=[30.0],
                  sersic_n=[1.0])
    img, _ = render(t, shape, psf_name="gaussian", wcs=wcs)
    yy, xx = np.mgrid[0:96, 0:96]
    w = img / img.sum()
    mx, my = (w * xx).sum(), (w * yy).sum()
    mxx, myy, mxy = (w * (xx - mx) ** 2).sum(), (w * (yy - my) ** 2).sum(), (w * (xx - mx) * (yy - my)).sum()
    angle = 0.5 * np.degrees(np.arctan2(2 * mxy, mxx - myy))
    # tan_header's "rotation" turns the sky frame by +rotation relative to the pixel frame
    expected = (30.0 - rotation + 90.0) % 180.0 - 90.0
    assert angle == pytest.approx(expected, abs=1.0)


@pytest.mark.parametrize("psf_name", ["gaussian", "moffat"])
def test_sub_pixel_position_is_the_light_centroid(psf_name):
    shape = (64, 64)
    rng = np.random.default_rng(5)
    for _ in range(4):
        x, y = 32 + rng.uniform(-0.5, 0.5), 31 + rng.uniform(-0.5, 0.5)
        t = truth_for("point", [x], [y], [18.0], shape=shape)
        img, _ = render(t, shape, psf_name=psf_name)
        yy, xx = np.mgrid[0:64, 0:64]
        assert (img * xx).sum() / img.sum() == pytest.approx(x, abs=0.01)
        assert (img * yy).sum() / img.sum() == pytest.approx(y, abs=0.01)


def test_point_source_fwhm_is_the_image_fwhm():
    # the PSF is the effective PSF: no second pixel convolution broadens it
    shape = (64, 64)
    t = truth_for("point", [32.0], [32.0], [18.0], shape=shape)
    img, _ = render(t, shape, psf_name="gaussian")
    yy, xx = np.mgrid[0:64, 0:64]
    w = img / img.sum(dtype=float)
    var_x = (w * (xx - 32.0) ** 2).sum()
    # sampled at pixel centres, the variance is sigma^2 = (FWHM / 2.3548)^2 = 2.209 px^2; integrating
    # over the pixel again would add 1/12 px^2 (+3.8%)
    assert var_x == pytest.approx((FWHM / 2.3548200450309493) ** 2, rel=0.01)


# --------------------------------------------------------------------------- rendering: edges, errors, noise


def test_stamps_at_the_edge_are_flagged_and_clipped():
    shape = (100, 100)
    t = truth_for("buldisk", [0.2, 99.4, 50.0, -300.0], [50.0, 98.0, 50.0, 50.0], [21.0, 21.0, 21.0, 21.0],
                  shape=shape, hlr_arcsec=[0.5] * 4, q=[0.8] * 4, pa_deg=[0.0] * 4, bulge_fraction=[0.5] * 4)
    img, info = render(t, shape)
    np.testing.assert_array_equal(info["flag"] & FLAG_OFF_IMAGE, [2, 2, 0, 2])
    assert np.all(np.isfinite(img))
    assert info.meta["n_drawn"] == 3 and info.meta["n_off_image"] == 3
    # the edge sources lost about half their light; the fully-off one added nothing
    alone, _ = render(t[2:3], shape)
    edge_light = img.sum(dtype=float) - alone.sum(dtype=float)
    assert 0.3 * t["flux"][0] < edge_light < 1.3 * t["flux"][0]


def test_fully_off_image_source_leaves_the_image_unchanged():
    t = truth_for("point", [-500.0], [20.0], [20.0], shape=(40, 40))
    img, info = render(t, (40, 40))
    assert info["flag"][0] == FLAG_OFF_IMAGE and not img.any()


def test_a_failing_source_is_flagged_and_the_others_drawn():
    shape = (100, 100)
    t = truth_for("sersic", [30.0, 70.0], [50.0, 50.0], [21.0, 21.0], shape=shape, hlr_arcsec=[0.4, 0.4],
                  q=[1.0, 1.0], pa_deg=[0.0, 0.0], sersic_n=[4.0, 9.0])  # GalSim refuses n > 6.2
    img, info = render(t, shape)
    np.testing.assert_array_equal(info["flag"], [0, FLAG_DRAW_ERROR])
    assert info.meta["n_draw_errors"] == 1 and "1:" in info.meta["draw_errors"]
    assert img.sum(dtype=float) == pytest.approx(t["flux"][0], rel=0.01)


def test_empty_truth_returns_a_float32_copy():
    base = np.ones((20, 30))
    t = truth_for("point", [], [], [], shape=(20, 30))
    img, info = render_truth(base, t, psf=make_psf(InjectionConfig(), FWHM, SCALE), config=InjectionConfig(),
                             pixel_scale=SCALE, rng_seed=0)
    assert img.dtype == np.float32 and np.array_equal(img, base) and img is not base
    assert len(info) == 0


def test_base_image_is_not_modified_and_sources_are_added():
    base = np.random.default_rng(0).normal(0, 1, (64, 64)).astype(np.float32)
    keep = base.copy()
    t = truth_for("point", [32.0], [32.0], [20.0], shape=(64, 64))
    cfg = InjectionConfig()
    img, _ = render_truth(base, t, psf=make_psf(cfg, FWHM, SCALE), config=cfg, pixel_scale=SCALE, rng_seed=0)
    np.testing.assert_array_equal(base, keep)
    assert (img - base).sum(dtype=float) == pytest.approx(t["flux"][0], rel=0.01)


def test_photon_noise_has_zero_mean_and_variance_flux_over_gain():
    shape = (64, 64)
    gain = 4.0
    t = truth_for("sersic", [32.0], [32.0], [17.0], shape=shape, hlr_arcsec=[0.6], q=[1.0], pa_deg=[0.0],
                  sersic_n=[1.0])  # flux 1e5 image units = 4e5 electrons
    clean, _ = render(t, shape)
    noisy, info = render(t, shape, gain=gain, photon_noise=True, seed=3)
    assert info.meta["photon_noise"]
    diff = noisy.astype(float) - clean
    sel = clean * gain > 100.0  # Poisson ~ Gaussian there
    z = diff[sel] / np.sqrt(clean[sel] / gain)
    # ~500 pixels: sd of the mean of z is ~0.045 and of its variance ~0.06; tolerances > 4 sd
    assert sel.sum() > 300
    assert abs(z.mean()) < 0.2
    assert z.var() == pytest.approx(1.0, abs=0.25)
    # total: sum of the noise has variance flux / gain = 25000 -> sd 158 (vs flux 1e5)
    sums = np.array([render(t, shape, gain=gain, photon_noise=True, seed=s)[0].sum(dtype=float)
                     for s in range(60)]) - clean.sum(dtype=float)
    # 60 realisations: the sd of the sample variance is ~18%; tolerance 60%. The mean: sd 20, tolerance 100.
    assert abs(sums.mean()) < 100.0
    assert sums.var(ddof=1) / (t["flux"][0] / gain) == pytest.approx(1.0, abs=0.6)


def test_same_seed_same_image_other_seed_different():
    shape = (96, 96)
    cfg = InjectionConfig(density=400.0, min_sep=1.0)
    t = make_truth("buldisk", shape=shape, pixel_scale=SCALE, fwhm_pix=FWHM, config=cfg, mag_range=(19.0, 22.0),
                   rng=np.random.default_rng(2), zeropoint=ZP)
    a, _ = render(t, shape, gain=2.0, photon_noise=True, seed=10)
    b, _ = render(t, shape, gain=2.0, photon_noise=True, seed=10)
    c, _ = render(t, shape, gain=2.0, photon_noise=True, seed=11)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    d, info = render(t, shape, gain=None, photon_noise=True, seed=10)  # no gain: no photon noise
    assert not info.meta["photon_noise"]
    e, _ = render(t, shape, gain=None, photon_noise=True, seed=99)
    np.testing.assert_array_equal(d, e)


def test_psf_with_extreme_wings_warns_and_caps_the_stamps():
    # Moffat beta=1.5: 99.5% of the light lies within ~200 scale radii, far beyond the 256 px cap
    shape = (64, 64)
    t = truth_for("point", [32.0], [32.0], [20.0], shape=shape)
    cfg = InjectionConfig(moffat_beta=1.5)
    with pytest.warns(UserWarning, match="wings"):
        img, info = render_truth(np.zeros(shape), t, psf=make_psf(cfg, FWHM, SCALE), config=cfg,
                                 pixel_scale=SCALE, rng_seed=0)
    assert info.meta["psf_radius_pix"] == 256.0
    assert 0.95 < info.meta["psf_enclosed_fraction"] < 0.995


def _moffat_radius(fwhm, beta, fraction):
    """Radius enclosing ``fraction`` of a Moffat's flux: ``1 - (1 + R^2/alpha^2)^(1 - beta) = fraction``."""
    alpha = fwhm / (2.0 * np.sqrt(2.0 ** (1.0 / beta) - 1.0))
    return alpha * np.sqrt((1.0 - fraction) ** (1.0 / (1.0 - beta)) - 1.0)


@pytest.mark.parametrize("fwhm", [1.0, 1.4, 1.8, 3.0])
@pytest.mark.parametrize("beta", [2.5, 3.0])
@pytest.mark.parametrize("pixel_integrated", [False, True])
def test_undersampled_psf_gets_a_small_stamp_radius_and_no_warning(fwhm, beta, pixel_integrated):
    # A Moffat narrower than a pixel sampled at pixel centres does not sum to its flux (FWHM 1.4 px:
    # 98.7 %), which once sized its stamps at the 256 px cap with a false "extended wings" warning.
    # The radius is the continuous profile's: for the Moffat itself known in closed form (0.5 %
    # tolerance: the growth curve steps from one sample radius to the next, 1/k pixel apart, k >= 2
    # here); convolving with the pixel widens it by less than half a pixel diagonal.
    cfg = InjectionConfig(moffat_beta=beta)
    psf = make_psf(cfg, fwhm, SCALE, pixel_integrated=pixel_integrated)
    radius, enclosed = psf_enclosed_radius_pix(galsim.PixelScale(SCALE).toImage(psf), 0.995)
    exact = _moffat_radius(fwhm, beta, 0.995)
    if pixel_integrated:
        assert exact * (1 - 5e-3) <= radius <= exact + 0.71
    else:
        assert radius == pytest.approx(exact, rel=5e-3)
    assert radius < 6.0 * fwhm
    assert enclosed == pytest.approx(0.995, abs=2e-4)
    shape = (64, 64)
    for x, y in ((32.0, 32.0), (32.3, 31.6), (32.5, 32.5)):
        t = truth_for("point", [x], [y], [20.0], shape=shape)
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # no warning about the wings
            img, info = render_truth(np.zeros(shape, np.float32), t, psf=psf, config=cfg, pixel_scale=SCALE,
                                     zeropoint=ZP, rng_seed=0)
        assert info.meta["psf_radius_pix"] == radius and info.meta["psf_enclosed_fraction"] >= 0.995 - 1e-6
        if pixel_integrated:
            # the pixel's transform vanishes at every alias of k = 0, so the samples of a pixel-integrated
            # profile sum to its flux wherever it sits in the pixel (stamps hold it to ~0.2 %)
            assert img.sum() == pytest.approx(float(t["flux"][0]), rel=3e-3)


def test_enclosed_radius_of_heavy_wings_matches_the_moffat_growth_curve():
    # beta 1.5: the radius (131 px at FWHM 1 px) lies beyond the fine core grid, in the pixel-sampled wings;
    # at FWHM 3 px it lies beyond the 256 px cap, where the enclosed fraction is that of the profile.
    radius, enclosed = psf_enclosed_radius_pix(galsim.Moffat(beta=1.5, fwhm=1.0), 0.995)
    assert radius == pytest.approx(_moffat_radius(1.0, 1.5, 0.995), rel=5e-3)
    radius, enclosed = psf_enclosed_radius_pix(galsim.Moffat(beta=1.5, fwhm=3.0), 0.995)
    alpha = 3.0 / (2.0 * np.sqrt(2.0 ** (1.0 / 1.5) - 1.0))
    assert radius == 256.0 and enclosed == pytest.approx(1.0 - (1.0 + (256.0 / alpha) ** 2) ** -0.5, abs=1e-5)


def test_stamp_renderer_with_an_undersampled_psf_keeps_the_flux():
    # FWHM 1.2 px: the PSF has power beyond the Nyquist frequency, so the k grid is extended and wrapped
    psf = galsim.Gaussian(fwhm=1.2)
    r = StampRenderer(psf)
    stamp = r.draw(None, 10.0, 0.3, -0.2, 8)
    ref = galsim.Convolve(galsim.DeltaFunction(flux=10.0), psf).drawImage(
        galsim.ImageD(galsim.BoundsI(-8, 8, -8, 8), scale=1.0), method="no_pixel", offset=(0.3, -0.2),
        use_true_center=False).array
    assert np.abs(stamp - ref).max() < 1e-4 * ref.max()
    assert stamp.sum() == pytest.approx(10.0, rel=1e-4)


def test_truth_read_back_from_fits_renders_identically(tmp_path):
    shape = (120, 120)
    cfg = InjectionConfig(density=300.0, min_sep=1.0)
    t = make_truth("buldisk", shape=shape, pixel_scale=SCALE, fwhm_pix=FWHM, config=cfg, mag_range=(20.0, 23.0),
                   rng=np.random.default_rng(6), zeropoint=ZP)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # long meta keys become HIERARCH cards
        t.write(tmp_path / "truth.fits")
    back = Table.read(tmp_path / "truth.fits")
    a, _ = render(t, shape, gain=1.0, photon_noise=True, seed=4)
    b, _ = render(back, shape, gain=1.0, photon_noise=True, seed=4)
    np.testing.assert_array_equal(a, b)


# --------------------------------------------------------------------------- batched drawing


def _mixed_truth(shape, seed=5):
    """Point sources and bulge+disk galaxies, some cut by the border, one wholly off the image."""
    cfg = InjectionConfig(density=400.0, min_sep=1.0)
    tables = [make_truth(kind, shape=shape, pixel_scale=SCALE, fwhm_pix=FWHM, config=cfg, mag_range=(19.0, 23.0),
                         rng=np.random.default_rng(seed + k), zeropoint=ZP) for k, kind in enumerate(("buldisk", "point"))]
    t = vstack(tables, metadata_conflicts="silent")
    t["injection_id"] = np.arange(len(t))
    t["x"][:3] = [-1.7, shape[1] - 0.6, -40.0]  # cut by the left / right border; wholly off
    t["y"][:3] = [20.3, 55.5, 30.0]
    t["q"][0] = 0.35  # a strongly elongated galaxy at the border
    return t


@pytest.mark.parametrize("rotation", [None, 35.0])
def test_batched_stamps_agree_with_the_per_source_galsim_path(rotation):
    shape = (150, 170)
    wcs = None if rotation is None else WCS(tan_header(shape, SCALE, rotation_deg=rotation))
    t = _mixed_truth(shape)
    kinds = np.asarray(t["kind"])
    assert {"point", "buldisk"} <= set(kinds) and len(t) > 40  # premise: both batched kinds, many overlaps
    fast, info = render(t, shape, wcs=wcs)
    slow, ref = render(t, shape, wcs=wcs, batched=False)
    assert info.meta["n_batched"] == info.meta["n_drawn"] == ref.meta["n_drawn"] == len(t) - 1
    assert ref.meta["n_batched"] == 0
    np.testing.assert_array_equal(info["flag"], ref["flag"])
    assert info["flag"][2] == FLAG_OFF_IMAGE and info["flag"][0] == FLAG_OFF_IMAGE
    # Point sources use the same PSF transform and folding: identical to rounding. Galaxies differ by
    # the bulge's table interpolation (<= 7.6e-6 of the flux in k space, see inject/test_kspace.py): measured
    # 5e-7 of the peak; 1e-5 leaves room for other parameters without hiding a real error (a wrong
    # shear or fold gives > 1e-3).
    assert np.abs(fast - slow).max() < 1e-5 * slow.max()
    assert fast.sum(dtype=float) == pytest.approx(slow.sum(dtype=float), rel=1e-6)
    points = t[kinds == "point"]
    p_fast, _ = render(points, shape, wcs=wcs)
    p_slow, _ = render(points, shape, wcs=wcs, batched=False)
    np.testing.assert_allclose(p_fast, p_slow, rtol=0, atol=1e-6 * p_slow.max())


def test_batched_buldisk_with_a_rotated_wcs_agrees_with_galsim_drawimage():
    shape = (80, 80)
    header = tan_header(shape, SCALE, rotation_deg=-50.0)
    wcs = WCS(header)
    t = truth_for("buldisk", [40.3], [38.6], [21.0], shape=shape, hlr_arcsec=[0.55], q=[0.45], pa_deg=[70.0],
                  bulge_fraction=[0.6])
    ours, info = render(t, shape, wcs=wcs, flux_fraction=0.9999)
    assert info.meta["n_batched"] == 1
    gwcs = galsim.GSFitsWCS(header=galsim.FitsHeader(header=header))
    pos = galsim.PositionD(40.3 + 1, 38.6 + 1)
    psf_world = gwcs.local(image_pos=pos).toWorld(galsim.PixelScale(SCALE).toImage(make_psf(InjectionConfig(), FWHM,
                                                                                            SCALE)))
    bulge = galsim.DeVaucouleurs(half_light_radius=0.55, trunc=8.0 * 0.55, flux_untruncated=False)
    disk = galsim.Exponential(half_light_radius=0.55)
    gal = (0.6 * bulge + 0.4 * disk).shear(q=0.45, beta=70.0 * galsim.degrees).withFlux(float(t["flux"][0]))
    ref = galsim.Convolve(gal, psf_world).drawImage(image=galsim.ImageD(80, 80, wcs=gwcs), method="no_pixel",
                                                    center=pos).array
    assert np.abs(ours - ref).max() < 1e-3 * ref.max()
    assert ours.sum() / t["flux"][0] == pytest.approx(1.0, abs=0.003)


def test_undersampled_psf_and_out_of_domain_parameters_take_the_galsim_path():
    shape = (90, 90)
    t = truth_for("buldisk", [30.2, 60.7], [45.1, 44.6], [21.0, 21.0], shape=shape, hlr_arcsec=[0.4, 0.4],
                  q=[0.7, 1.3], pa_deg=[10.0, 10.0], bulge_fraction=[0.3, 0.3])
    # q = 1.3 is outside the batched model (0 < q <= 1): drawn by GalSim, which does not shear q >= 1
    img, info = render(t, shape)
    assert info.meta["n_batched"] == 1 and info.meta["n_drawn"] == 2
    slow, _ = render(t, shape, batched=False)
    assert np.abs(img - slow).max() < 1e-5 * slow.max()
    # a PSF with power beyond Nyquist (Gaussian of FWHM 2 px: GalSim's maxk = 4.4 > pi per pixel) needs
    # GalSim's general folding: no batching
    cfg = InjectionConfig()
    sharp = galsim.Gaussian(fwhm=2.0 * SCALE)
    assert galsim.PixelScale(SCALE).toImage(sharp).maxk > np.pi  # premise
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        img, info = render_truth(np.zeros(shape, np.float32), t, psf=sharp, config=cfg, pixel_scale=SCALE,
                                 rng_seed=0)
    assert info.meta["n_batched"] == 0 and info.meta["n_drawn"] == 2
    assert img.sum(dtype=float) / t["flux"].sum() == pytest.approx(1.0, abs=0.005)


def test_batched_photon_noise_is_reproducible_and_has_the_right_variance():
    # same seed, same image; the noise on a bright batched point source has variance flux / gain
    shape = (64, 64)
    t = truth_for("point", [31.6], [32.2], [16.0], shape=shape)
    a, info = render(t, shape, gain=2.0, photon_noise=True, seed=3)
    b, _ = render(t, shape, gain=2.0, photon_noise=True, seed=3)
    np.testing.assert_array_equal(a, b)
    assert info.meta["n_batched"] == 1
    clean, _ = render(t, shape)
    diffs = [render(t, shape, gain=2.0, photon_noise=True, seed=s)[0] - clean for s in range(40)]
    var = np.var(np.stack(diffs), axis=0)
    # per-pixel variance = s / gain; over the 40 x ~2500 pixel draws the summed variance is within a few %
    # (relative error of a variance from 40 draws is sqrt(2/40) = 22% per pixel, averaged over the
    # ~100 bright pixels that carry the sum: ~3%); 10% tolerance
    assert var.sum() == pytest.approx(clean.sum() / 2.0, rel=0.1)


def test_galaxies_on_a_fine_pixel_field_keep_their_sizes_and_their_stamps_on_the_image():
    # 640x640 at 0.03"/px (a JWST-like field): galaxies of hlr 0.35-0.75" (ground-based sizes) stay that
    # size in arcsec; each keeps max(2 FWHM, 4 hlr) from its neighbour's and its whole stamp on the image,
    # so none is flagged off the image.
    from comest_bayes.inject.render import SEPARATION_HLR

    cfg = InjectionConfig(kinds=("buldisk",))
    psf = make_psf(cfg, 2.5, 0.03)
    t = make_truth("buldisk", shape=(640, 640), pixel_scale=0.03, fwhm_pix=2.5, config=cfg, psf=psf,
                   mag_range=(22.0, 26.0), rng=np.random.default_rng(1), zeropoint=ZP, n=3)
    assert t.meta["per_source_separation"] and t.meta["n_unplaced"] == 3 - len(t)
    hlr = np.asarray(t["hlr_arcsec"])
    assert np.all((hlr >= 0.35) & (hlr <= 0.75))
    x, y = np.asarray(t["x"]), np.asarray(t["y"])
    for i in range(len(t)):
        for j in range(i):
            assert np.hypot(x[i] - x[j], y[i] - y[j]) >= SEPARATION_HLR * (hlr[i] + hlr[j]) / 0.03
    _, out = render_truth(np.zeros((640, 640), np.float32), t, psf=psf, config=cfg, pixel_scale=0.03, rng_seed=0)
    assert not np.any(np.asarray(out["flag"]) & FLAG_OFF_IMAGE)


def test_point_sources_keep_the_one_separation_placement():
    # point sources are drawn positions first, as before (the demo's point-source numbers do not move)
    cfg = InjectionConfig(kinds=("point",))
    t = make_truth("point", shape=(200, 200), pixel_scale=0.2, fwhm_pix=4.0, config=cfg,
                   mag_range=(22.0, 26.0), rng=np.random.default_rng(1), zeropoint=ZP, n=20)
    assert not t.meta["per_source_separation"] and t.meta["min_sep_pix"] == pytest.approx(16.0)
