"""Decisions taken before any injection (comest_bayes.pipeline.preflight): the automatic injection density,
against the background mesh, the target, the published density and what the placement holds.
"""

import numpy as np
import pytest


# --------------------------------------------------------------------------- the automatic density
# comest_bayes.pipeline.preflight.choose_density: known image sizes give known counts per realization.

def _choice(kind, shape, pixel_scale, fwhm_pix, back_size=64, **injection):
    from comest_bayes.config import InjectionConfig
    from comest_bayes.pipeline.preflight import choose_density

    return choose_density(kind, shape=shape, pixel_scale=pixel_scale, fwhm_pix=fwhm_pix,
                          injection=InjectionConfig(**injection), back_size=back_size)


def _half_jamming(npix, sep_pix):
    # half of random sequential packing (54.7% covered by discs of diameter sep_pix)
    return 0.5 * 0.547 * npix / (np.pi * sep_pix ** 2 / 4.0)


def test_auto_density_raises_a_small_fine_pixel_field_to_a_quarter_injection_per_background_mesh():
    # The shared JWST cutout: 640x640 at 0.0308"/px is 0.1079 arcmin^2, 1.6 injections per
    # realization at 15 per arcmin^2.  Point sources (FWHM 2.46 px, 9.84 px apart) are raised to
    # a quarter per 64x64 background mesh, 25 (the target is 100, the placement holds 1473).
    c = _choice("point", (640, 640), 0.0308, 2.46)
    area = 640 * 640 * (0.0308 / 60) ** 2
    assert c.source == "automatic" and c.rule == "raised"
    assert c.published == pytest.approx(15 * area)
    assert c.mesh_cap == pytest.approx(0.25 * 100) and c.per_realization == pytest.approx(25.0)
    assert c.density == pytest.approx(25.0 / area)  # 231.6 per arcmin^2
    assert c.hold_cap == pytest.approx(_half_jamming(640 * 640, 4 * 2.46))
    assert "0.25 per 64x64 background mesh" in c.reason
    # Galaxies (hlr 0.35-0.75" = 11-24 px) keep max(2 FWHM, 4 hlr) each from each other and their whole
    # 99.5% stamps (radius 94-300 px) on the image: the placement keeps 95% of 3 per realization, every
    # one usable.  (The old single separation, 8 x 0.75" = 194.8 px, asked for 3.8 of which about 30%
    # had their stamps on the image.)
    g = _choice("buldisk", (640, 640), 0.0308, 2.46)
    assert g.per_realization == 3.0 and g.hold_cap == 3.0 and g.rule == "raised"
    assert g.min_sep_pix == pytest.approx(6.0 / 0.0308)  # the pair of the largest galaxies
    assert g.sizing["per_source"] and "4 hlr" in g.sizing["separation"]
    assert "held by the placement" in g.reason
    # smaller meshes (detection.back_size 32) allow four times as many
    assert _choice("point", (640, 640), 0.0308, 2.46, back_size=32).per_realization == pytest.approx(100.0)


def test_auto_density_stops_at_the_target():
    # 1400x1400 at 0.05"/px: 20.4 per realization at 15 per arcmin^2, room for 119.6 at a quarter per
    # mesh: the target, 100
    c = _choice("point", (1400, 1400), 0.05, 3.0)
    assert c.published == pytest.approx(15 * (1400 * 0.05 / 60) ** 2) and c.mesh_cap == pytest.approx(0.25 * 1400 ** 2 / 4096)
    assert c.rule == "raised" and c.per_realization == pytest.approx(100.0)


def test_auto_density_keeps_the_published_density_where_it_is_enough():
    # the 3000x3000 demo tile at 0.26"/px: 2535 per realization >= the target
    c = _choice("point", (3000, 3000), 0.26, 3.5)
    assert c.rule == "published" and c.density == 15.0 and c.per_realization == pytest.approx(15 * 13.0 ** 2)
    # a 200x200 DECam cutout at 0.262"/px: 11.4 per realization, already more than one per mesh (9.8)
    d = _choice("point", (200, 200), 0.262, 4.0)
    assert d.rule == "published" and d.density == 15.0
    assert d.per_realization == pytest.approx(15 * (200 * 0.262 / 60) ** 2) and d.mesh_cap < d.per_realization


def test_auto_density_is_lowered_to_a_background_ceiling_on_coarse_pixels():
    # the 2MASS field: 720x721 at 5"/px is 3605 arcmin^2, 54075 per realization at 15 per arcmin^2;
    # point sources of FWHM 1.5 px, 6 px apart: half of random packing is 5021, 40 per 64x64 mesh,
    # about as many as the sources the field has.  The ceiling of 1.25 per mesh (126.7 meshes) binds.
    c = _choice("point", (721, 720), 5.0, 1.5)
    assert c.hold_cap == pytest.approx(_half_jamming(721 * 720, 6.0)) and 5000 < c.hold_cap < 5050
    assert c.rule == "background cap" and c.warning is None
    assert c.per_realization == pytest.approx(1.25 * 721 * 720 / 64 ** 2)  # 158.4
    assert c.density == pytest.approx(c.per_realization / (721 * 720 * (5.0 / 60) ** 2))
    assert "lowered to the 5021" in c.reason and "lowered further to 158, 1.25 per 64x64 background mesh" in c.reason
    # larger meshes hold more (the ceiling counts meshes of detection.back_size)
    assert _choice("point", (721, 720), 5.0, 1.5, back_size=128).per_realization == pytest.approx(c.per_realization / 4)
    # the ceiling is the published density's load at ground-based pixel scales: it leaves those alone
    assert _choice("point", (3000, 3000), 0.26, 3.5).rule == "published"  # 1.15 per mesh
    assert _choice("point", (2600, 2600), 0.2, 4.0).rule == "published"  # KiDS, 0.68 per mesh
    # at the SDSS pixel (0.396"/px) the published density is 2.6 per mesh: lowered to the ceiling
    sdss = _choice("point", (2048, 1489), 0.396, 3.5)
    assert sdss.rule == "background cap" and sdss.per_realization == pytest.approx(1.25 * 2048 * 1489 / 4096)


def test_a_user_density_above_the_background_ceiling_is_kept_with_a_warning():
    c = _choice("point", (721, 720), 5.0, 1.5, density=1.0)
    assert c.source == "user" and c.density == 1.0 and c.per_realization == pytest.approx(721 * 720 * (5 / 60) ** 2)
    assert c.warning.startswith("1 per arcmin^2 puts 28.4 injections in each 64x64 background mesh (more than 1.25)")
    assert "0.0439 per arcmin^2 (158 per realization) or less" in c.warning and "--nsims" in c.warning
    assert _choice("point", (640, 640), 0.0308, 2.46, density=100.0).warning is None  # 0.11 per mesh


def test_a_density_the_user_sets_is_kept():
    c = _choice("point", (640, 640), 0.0308, 2.46, density=400.0)
    assert c.source == "user" and c.rule == "user" and c.density == 400.0
    assert c.per_realization == pytest.approx(400.0 * 640 * 640 * (0.0308 / 60) ** 2)


# --------------------------------------------------------------------------- galaxies placed source by source
# comest_bayes.pipeline.preflight.sized_capacity: what the per-source placement holds, against counts known
# from geometry.

def test_sized_capacity_counts_the_galaxies_a_fine_pixel_field_holds():
    # Equal galaxies: hlr 0.5" on 0.05"/px is 10 px, separation radius 4 hlr = 40 px, stamp radius
    # (99.5% of an exponential disk, 4.43 hlr, + the PSF + margins) about 49 px.  On a 300x300 image the
    # centres must lie in the central 300 - 2 x 49 = 202 px square, 80 px apart.  4 always fit (the
    # corners are 202 px apart) and 9 only on a lattice (spacing 101 px), which random placement does
    # not find: the count it keeps 95% of lies in [4, 8] (6 with these seeds).
    from comest_bayes.config import InjectionConfig
    from comest_bayes.pipeline.preflight import sized_capacity

    inj = InjectionConfig(kinds=("buldisk",), hlr_range=(0.5, 0.5), bulge_fraction_range=(0.0, 0.0),
                          q_range=(1.0, 1.0))
    n, full = sized_capacity("buldisk", shape=(300, 300), pixel_scale=0.05, fwhm_pix=3.0, injection=inj,
                             wanted=100)
    assert full and 4 <= n <= 8
    # a field ten times wider holds the 100 asked for (area 100x, about 450 such galaxies at half packing)
    n, full = sized_capacity("buldisk", shape=(3000, 3000), pixel_scale=0.05, fwhm_pix=3.0, injection=inj,
                             wanted=100)
    assert not full and n == 100


def test_sized_galaxies_are_budgeted_as_all_usable():
    from comest_bayes.config import InjectionConfig
    from comest_bayes.pipeline.preflight import injection_budget

    inj = InjectionConfig(kinds=("buldisk",))
    b = injection_budget("buldisk", shape=(640, 640), mask=None, pixel_scale=0.0308, fwhm_pix=2.46, injection=inj,
                         density=3.0 / (640 * 640 * (0.0308 / 60) ** 2))
    assert b.sized and b.inner_fraction == 1.0
    assert b.usable_per_realization == pytest.approx(3.0)


def test_too_few_usable_injections_names_the_limit_that_binds_and_the_realizations_that_would_do():
    from comest_bayes.config import InjectionConfig
    from comest_bayes.errors import InputError
    from comest_bayes.pipeline.preflight import check_injection_count

    # the JWST cutout's geometry: the automatic density is already what the placement holds (3 galaxies per
    # realization), so only more realizations help: 10 usable need ceil(10 / 3) = 4
    inj = InjectionConfig(kinds=("buldisk",), nsims=3)
    with pytest.raises(InputError) as err:
        check_injection_count(shape=(640, 640), mask=None, pixel_scale=0.0308, fwhm_pix=2.46, injection=inj)
    msg = str(err.value)
    assert "only about 3.0 fit" in msg and "the automatic density is already that" in msg
    assert "Raise --nsims to 4 or more; a higher --density cannot help." in msg
    assert "stamp" in msg and "edges" not in msg  # every pixel is usable: no word on stamps and edges
    check_injection_count(shape=(640, 640), mask=None, pixel_scale=0.0308, fwhm_pix=2.46,
                          injection=InjectionConfig(kinds=("buldisk",), nsims=4))
    # a density the user set low on a small image: 4 point sources per realization on 0.36 arcmin^2, of which
    # the stamps of about 80% lie inside the edges: 9.7 usable over 3 realizations; --density helps too
    inj = InjectionConfig(kinds=("point",), nsims=3, density=4.0 / 0.36)
    with pytest.raises(InputError) as err:
        check_injection_count(shape=(180, 180), mask=None, pixel_scale=0.2, fwhm_pix=3.0, injection=inj)
    msg = str(err.value)
    assert "4.0 are asked for per realization" in msg and "px from the edges" in msg
    assert msg.endswith("Raise --nsims to 4 or more or --density, or use a larger image.")


JWST = "/work/shared/data/jwst/jwst_nircam_f200w_a2744_glass_sci.fits"


@pytest.mark.skipif(not __import__("os").path.exists(JWST), reason="the shared JWST image is absent")
def test_the_shared_jwst_image_gets_usable_galaxies_in_every_realization():
    # The shared JWST F200W cutout (640x640, 0.0308"/px, FWHM 2.46 px, its README): with the old single
    # separation of 194.8 px, 3.8 buldisk galaxies were asked for per realization and 11 of 38 had their
    # stamps on the image over 10 realizations.  Placed source by source, the realizations of the run's own
    # count keep at least 2.5 per realization on average, every one with its stamp on the image.
    import warnings
    from astropy.io import fits
    from comest_bayes.config import InjectionConfig
    from comest_bayes.inject.render import FLAG_OFF_IMAGE, make_truth, render_truth
    from comest_bayes.inject.psfmodel import make_psf
    from comest_bayes.pipeline.preflight import choose_density

    shape = fits.getdata(JWST).shape
    inj = InjectionConfig(kinds=("buldisk",))
    choice = choose_density("buldisk", shape=shape, pixel_scale=0.0308, fwhm_pix=2.46, injection=inj)
    assert choice.per_realization >= 3.0  # was 3.758 asked, about 1.1 usable
    cfg = InjectionConfig(kinds=("buldisk",), density=choice.density)
    psf = make_psf(cfg, 2.46, 0.0308)
    usable, asked = 0, 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        for seed in range(20):
            t = make_truth("buldisk", shape=shape, pixel_scale=0.0308, fwhm_pix=2.46, config=cfg, psf=psf,
                           mag_range=(24.0, 28.0), rng=np.random.default_rng(seed), zeropoint=28.03)
            _, t = render_truth(np.zeros(shape, np.float32), t, psf=psf, config=cfg, pixel_scale=0.0308, rng_seed=seed)
            assert not np.any(np.asarray(t["flag"]) & FLAG_OFF_IMAGE)
            usable += len(t)
            asked += t.meta["n_requested"]
    # 20 Poisson draws of mean 3: 60 +- 8 asked; at least 90% of them placed
    assert usable / 20 >= 2.5 and usable >= 0.9 * asked


# --------------------------------------------------------------------------- bright injections and their neighbours

def test_isophote_radius_of_a_gaussian_matches_its_analytic_value():
    # An unfiltered circular Gaussian of sigma s and flux F exceeds t * sigma_noise inside
    # r^2 = 2 s^2 ln(F / (2 pi s^2 t sigma_noise)); the pixel count of a 4-px Gaussian on a fine grid is
    # pi r^2 to within the pixelisation (a fraction of a pixel in radius).
    from comest_bayes.ratios.depth import isophote_radius_pix

    s = 4.0
    y, x = np.mgrid[-100:101, -100:101]
    psf = np.exp(-0.5 * (x ** 2 + y ** 2) / s ** 2)
    flux = np.array([1e3, 1e4, 1e5])
    expected = np.sqrt(2 * s ** 2 * np.log(flux / (2 * np.pi * s ** 2 * 1.5 * 1.0)))
    got = isophote_radius_pix(psf, flux, 1.0, 1.5)
    np.testing.assert_allclose(got, expected, atol=0.3)
    # a source whose peak stays under the threshold has no isophote; a scalar flux gives a float
    assert isophote_radius_pix(psf, 10.0, 1.0, 1.5) == 0.0
    # a filter spreads the light: the isophote of a bright source grows
    assert isophote_radius_pix(psf, 1e5, 1.0, 1.5, kernel=np.ones((5, 5))) > got[-1]


def test_bright_neighbours_counts_the_injections_within_a_brighter_ones_reach():
    from comest_bayes.pipeline.preflight import BRIGHT_REACH, bright_neighbours

    # every injection reaches 2 x 8 = 16 px, kept 12 px apart: each has density x pi (16^2 - 12^2)
    # neighbours expected in that ring
    rec = bright_neighbours((20.0, 22.0), 100.0, 1e6, 12.0, lambda m: np.full(np.shape(m), 8.0))
    assert BRIGHT_REACH == 2.0
    assert rec["fraction"] == pytest.approx(100.0 / 1e6 * np.pi * (16.0 ** 2 - 12.0 ** 2))
    assert rec["mag_reach"] == pytest.approx(22.0) and rec["radius_bright"] == 8.0 and rec["reach_bright"] == 16.0
    # reach grows 2 px per magnitude brighter: only the bright half of the range passes the separation
    rec = bright_neighbours((20.0, 24.0), 100.0, 1e6, 12.0, lambda m: 6.0 + (22.0 - np.asarray(m)), nmag=4001)
    m = np.linspace(20.0, 24.0, 4001)
    excess = np.pi * np.clip((2 * (6.0 + 22.0 - m)) ** 2 - 144.0, 0, None)
    assert rec["fraction"] == pytest.approx(1e-4 * excess.mean())
    assert rec["mag_reach"] == pytest.approx(22.0, abs=2e-3)  # the last grid point whose reach passes 12 px
    # nothing reaches past the separation: no neighbour at risk
    quiet = bright_neighbours((20.0, 24.0), 100.0, 1e6, 12.0, lambda m: np.full(np.shape(m), 5.0))
    assert quiet["fraction"] == 0.0 and quiet["mag_reach"] is None


def _footprints(mags, sizes, shape=(100, 100)):
    """A segmentation whose source i (id i + 1) covers the next sizes[i] pixels in reading order."""
    seg = np.zeros(shape, np.int32)
    flat = seg.ravel()
    start = 0
    for i, n in enumerate(sizes):
        flat[start:start + n] = i + 1
        start += n
    return seg, np.arange(1, len(mags) + 1), np.asarray(mags, float)


def test_footprint_cover_gives_each_sources_share_of_the_unmasked_area_by_magnitude():
    from comest_bayes.pipeline.preflight import footprint_cover

    seg, ids, mags = _footprints([12.0, 10.0, np.nan, 11.0], [100, 400, 50, 250])
    mag, share = footprint_cover(seg, ids, mags)
    # sorted by magnitude, the NaN-magnitude source left out; 10^4 pixels
    assert mag.tolist() == [10.0, 11.0, 12.0]
    assert share.tolist() == pytest.approx([0.04, 0.025, 0.01])
    # a mask removes its pixels from both the footprints and the area: the first 200 pixels (source 1's
    # 100 and half of source 2's) are masked, 9800 remain
    mask = np.zeros(seg.shape, bool)
    mask.ravel()[:200] = True
    mag, share = footprint_cover(seg, ids, mags, mask)
    assert share.tolist() == pytest.approx([300 / 9800, 250 / 9800, 0.0])
    # nothing detected, or everything masked: nothing covered
    assert footprint_cover(np.zeros((5, 5), int), [], [])[0].size == 0
    assert footprint_cover(seg, ids, mags, np.ones(seg.shape, bool))[1].size == 0


def test_a_field_is_confused_when_the_sources_of_the_ranges_first_two_magnitudes_cover_five_percent():
    from comest_bayes.pipeline.preflight import (CONFUSION_COVER, CONFUSION_MAX_SHIFT, CONFUSION_RISE,
                                                 CONFUSION_SPAN, confused_bright_end)

    assert (CONFUSION_SPAN, CONFUSION_RISE, CONFUSION_COVER, CONFUSION_MAX_SHIFT) == (2.0, 0.05, 0.05, 5.0)
    # sources every 0.1 mag from 10 to 20, each covering 0.2% of the image: 2% per magnitude
    mag = np.round(np.arange(10.0, 20.0, 0.1), 6)
    share = np.full(mag.size, 0.002)
    # the first 2 mag of a range from 16 hold 20 sources: 4% covered, not confused
    quiet = confused_bright_end(mag, share, 16.0)
    assert quiet["rise"] == pytest.approx(0.04) and not quiet["confused"] and quiet["bright"] == 16.0
    assert quiet["cover_bright"] == pytest.approx(0.12)  # the 60 sources of 10.0-15.9
    # twice the share each: 8% covered in the first 2 mag, confused
    dense = confused_bright_end(mag, 2 * share, 16.0)
    assert dense["rise"] == pytest.approx(0.08) and dense["confused"]
    # cumulative cover 0.004 k after k sources: past 0.05 at k = 13, the source at 11.2 mag
    assert dense["bright"] == pytest.approx(11.2)
    assert dense["cover_bright"] == pytest.approx(0.048)  # the 12 sources of 10.0-11.1
    # a very dense field: the cover passes 5% at 10.2 mag, but the start is held to CONFUSION_MAX_SHIFT = 5 mag
    # above the usual bright end of 18
    held = confused_bright_end(mag, 10 * share, 18.0)
    assert held["confused"] and held["bright"] == pytest.approx(13.0)
    # covered everywhere by far brighter sources but nothing in the range's first 2 mag (one large galaxy):
    # not confused, the range is kept
    galaxy = confused_bright_end(np.array([12.0, 18.5]), np.array([0.25, 0.001]), 18.0)
    assert not galaxy["confused"] and galaxy["bright"] == 18.0
