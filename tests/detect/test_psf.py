"""Tests of comest_bayes.detect.psf: seeing FWHM from the stars of an image.

The synthetic images are drawn with GalSim (pixel scale 1, so sizes are in
pixels): stars of a known PSF on a jittered grid, extended exponential
galaxies convolved with the same PSF at random positions, a flat sky and
Gaussian noise.  Detection is the package's own SEP detector.
"""

from __future__ import annotations

import json

import galsim
import numpy as np
import pytest

from comest_bayes.detect.catalog import FLAG_SATURATED
from comest_bayes.detect.sep_backend import detect_array
from comest_bayes.errors import InputError
from comest_bayes.detect.psf import (BETA_RANGE, FwhmEstimate, estimate_fwhm, fit_moffat, injection_psf, measure_seeing, moffat_image, point_size_check, seeing_from_header, select_stars)

SKY = 100.0
SIGMA = 1.0


def _psf(kind: str, fwhm: float) -> galsim.GSObject:
    if kind == "moffat":
        return galsim.Moffat(beta=3.0, fwhm=fwhm)
    return galsim.Gaussian(fwhm=fwhm)


def _add(image: galsim.ImageF, prof: galsim.GSObject, x: float, y: float, size: int) -> None:
    """Draw ``prof`` centred on the 0-based pixel position (x, y)."""
    ix, iy = int(np.floor(x)), int(np.floor(y))
    stamp = prof.drawImage(nx=size, ny=size, scale=1.0, offset=(x - ix - 0.5, y - iy - 0.5))
    stamp.setCenter(ix + 1, iy + 1)  # GalSim images are 1-based
    overlap = stamp.bounds & image.bounds
    if overlap.isDefined():
        image[overlap] += stamp[overlap]


def make_field(kind: str, fwhm: float, seed: int, *, n: int = 512, stars: bool = True, ngal: int = 60,
               gal_hlr_fwhm=(0.5, 2.0)) -> np.ndarray:
    """Stars on a 7x7 jittered grid (if ``stars``) plus ``ngal`` galaxies; sky SKY, noise SIGMA."""
    rng = np.random.default_rng(seed)
    psf = _psf(kind, fwhm)
    image = galsim.ImageF(n, n, scale=1.0)
    if stars:
        grid = np.linspace(30, n - 30, 7)
        for gx in grid:
            for gy in grid:
                flux = 10 ** rng.uniform(2.5, 4.5)  # SNR ~ 40 to 4000
                _add(image, psf.withFlux(flux), gx + rng.uniform(-8, 8), gy + rng.uniform(-8, 8), 64)
    for _ in range(ngal):
        flux = 10 ** rng.uniform(2.7, 4.5)
        hlr = rng.uniform(*gal_hlr_fwhm) * fwhm
        disk = galsim.Exponential(half_light_radius=hlr).shear(q=rng.uniform(0.3, 1.0),
                                                               beta=rng.uniform(0, np.pi) * galsim.radians)
        _add(image, galsim.Convolve(disk, psf).withFlux(flux), *rng.uniform(10, n - 10, 2), 96)
    data = image.array + SKY + SIGMA * rng.standard_normal((n, n))
    return data.astype(np.float32)


def _measure(data, **kwargs) -> FwhmEstimate:
    det = detect_array(data, zeropoint=30.0)
    return estimate_fwhm(data - det.background, det.catalog, **kwargs)


@pytest.mark.parametrize("kind", ["moffat", "gaussian"])
@pytest.mark.parametrize("fwhm", [2.5, 3.5, 5.0])
def test_fwhm_recovered_within_ten_percent(kind, fwhm):
    # The requirement is 10 %.  The fits are pixel-integrated Moffats, so on
    # these images the error is far smaller: we measured +0.3 % for the Moffat (beta=3)
    # and -0.2 % for the Gaussian stars at all three FWHMs (15-34 stars, standard
    # errors 0.1-0.3 %); 3 % is asserted as a tighter guard.
    est = _measure(make_field(kind, fwhm, seed=11))
    assert est.nstars >= 5
    assert abs(est.fwhm / fwhm - 1.0) < 0.10
    assert abs(est.fwhm / fwhm - 1.0) < 0.03
    assert 0.0 <= est.fwhm_err < 0.05 * fwhm
    if kind == "moffat":
        # the drawn beta is 3; at these SNRs the median fitted beta is within 10 %
        assert abs(est.beta - 3.0) < 0.3
    assert "Moffat" in est.method and f"{est.nstars} stars" in est.method


def test_independent_of_image_units():
    # Real images come in any unit (KiDS coadds in maggies, ~1e-9).  Scaling the image
    # must not change the FWHM: the fit works in units of each stamp's flux.
    data = make_field("moffat", 3.5, seed=3)
    det = detect_array(data, zeropoint=30.0)
    sub = data - det.background
    ref = estimate_fwhm(sub, det.catalog)
    scaled_cat = det.catalog.copy()
    for name in ("peak", "flux_auto", "fluxerr_auto"):
        scaled_cat[name] = scaled_cat[name] * 1e-9
    tiny = estimate_fwhm(sub * 1e-9, scaled_cat)
    assert tiny.nstars == ref.nstars
    assert tiny.fwhm == pytest.approx(ref.fwhm, rel=1e-3)


def test_no_stars_pure_noise_raises_clear_error():
    rng = np.random.default_rng(5)
    data = (SKY + SIGMA * rng.standard_normal((300, 300))).astype(np.float32)
    with pytest.raises(InputError, match="--fwhm"):
        _measure(data)


def test_only_galaxies_raises_clear_error():
    # Extended galaxies with a broad size range (half-light radius 0.5-2 FWHM) and no
    # stars.  Rejection is statistical (FWHM agreement and common-shape checks): in
    # our checks 18 of 20 such star-free fields raised, all at FWHM 3.5 and 5 px.
    data = make_field("moffat", 3.5, seed=1, stars=False, ngal=150)
    with pytest.raises(InputError, match="--fwhm"):
        _measure(data)


def test_flagged_sources_are_not_used():
    # The same stars marked saturated are unusable: no candidates remain.
    data = make_field("moffat", 3.5, seed=2, ngal=0)
    det = detect_array(data, zeropoint=30.0)
    cat = det.catalog.copy()
    est = estimate_fwhm(data - det.background, cat)
    assert est.nstars >= 5
    cat["flags"] = cat["flags"] | FLAG_SATURATED
    with pytest.raises(InputError, match="only 0 star candidates"):
        estimate_fwhm(data - det.background, cat)


def test_unknown_saturation_skips_highest_peaks():
    data = make_field("moffat", 3.5, seed=4, ngal=0)
    det = detect_array(data, zeropoint=30.0)
    peak = np.asarray(det.catalog["peak"])
    trusted = select_stars(det.catalog, shape=data.shape, saturation_flagged=True)
    untrusted = select_stars(det.catalog, shape=data.shape, saturation_flagged=False)
    brightest = int(np.argmax(peak))
    assert brightest in trusted.index
    assert brightest not in untrusted.index
    assert np.all(peak[untrusted.index] < 0.7 * peak.max())


def test_too_few_stars_message_names_the_count():
    data = make_field("moffat", 3.5, seed=6, ngal=0)
    det = detect_array(data, zeropoint=30.0)
    with pytest.raises(InputError, match=r"need 500"):
        estimate_fwhm(data - det.background, det.catalog, min_stars=500)


def test_moffat_image_analytic_values():
    # Point-sampled (oversample=1) at pixel centres: the value at r = FWHM/2 is half the
    # central value, and a large stamp holds the total flux up to the analytic wing
    # fraction (1 + R^2/alpha^2)^(1 - beta) outside radius R (here < 1e-5).
    fwhm, beta, flux = 4.0, 2.5, 1000.0
    img = moffat_image((201, 201), 100.0, 100.0, flux, fwhm, beta, oversample=1)
    assert img[100, 102] == pytest.approx(0.5 * img[100, 100], rel=1e-12)
    assert img[102, 100] == pytest.approx(0.5 * img[100, 100], rel=1e-12)
    alpha = fwhm / (2 * np.sqrt(2 ** (1 / beta) - 1))
    assert img[100, 100] == pytest.approx(flux * (beta - 1) / (np.pi * alpha**2), rel=1e-12)
    assert img.sum() == pytest.approx(flux, rel=1e-4)
    # Pixel integration conserves the flux too.
    assert moffat_image((201, 201), 100.3, 99.6, flux, fwhm, beta, oversample=5).sum() == \
        pytest.approx(flux, rel=1e-4)


def test_fit_moffat_recovers_noiseless_parameters():
    truth = dict(x0=15.3, y0=14.6, flux=5000.0, fwhm=3.0, beta=2.5, sky=0.0)
    stamp = moffat_image((31, 31), *truth.values(), oversample=5)
    fit = fit_moffat(stamp, 15.0, 15.0, 3.5, oversample=5)
    assert fit.ok
    assert fit.fwhm == pytest.approx(3.0, rel=1e-4)
    assert fit.beta == pytest.approx(2.5, rel=1e-3)
    assert (fit.x, fit.y) == pytest.approx((15.3, 14.6), abs=1e-4)
    assert fit.flux == pytest.approx(5000.0, rel=1e-3)
    # A round profile sampled off-centre on square pixels has weighted moments round to ~1e-5.
    assert abs(fit.ellipticity) < 1e-3


def test_as_dict_is_plain_json():
    est = FwhmEstimate(fwhm=3.2, fwhm_err=0.05, nstars=12, method="test", beta=float("nan"))
    d = est.as_dict()
    assert json.loads(json.dumps(d)) == {"fwhm": 3.2, "fwhm_err": 0.05, "nstars": 12, "method": "test",
                                         "beta": None, "beta_at_bound": 0, "star_flux_radius": None,
                                         "star_rows": []}


def test_input_validation():
    data = make_field("moffat", 3.5, seed=7, ngal=0)
    det = detect_array(data, zeropoint=30.0)
    with pytest.raises(InputError, match="mask has shape"):
        estimate_fwhm(data - det.background, det.catalog, mask=np.zeros((3, 3), bool))
    with pytest.raises(InputError, match="lacks the columns"):
        estimate_fwhm(data - det.background, det.catalog[["id", "x"]])


# --------------------------------------------------------------------------- header seeing (issue 13)


def _header(cards=(), **keywords):
    """A FITS header from (keyword, value, comment) cards and keyword=value pairs."""
    from astropy.io import fits

    header = fits.Header()
    for key, value, comment in cards:
        header["HIERARCH " + key if len(key) > 8 else key] = (value, comment)
    for key, value in keywords.items():
        header[key] = value
    return header


@pytest.mark.parametrize("cards, extra, expected", [
    # DECam community pipeline: pixels, as the comment says
    ([("FWHM", 4.027092, "Median FWHM in pixels")], {}, 4.027092),
    # UKIDSS (CASU): SEEING in pixels, with or without the unit in the comment
    ([("SEEING", 2.1, "[pixels] Average FWHM")], {"INSTRUME": "WFCAM"}, 2.1),
    ([("SEEING", 2.1, "Average FWHM")], {"TELESCOP": "UKIRT"}, 2.1),
    # SEEING in arcsec where the comment says so: 0.9" at 0.25"/px
    ([("SEEING", 0.9, "Seeing FWHM [arcsec]")], {}, 3.6),
    ([("PSF_FWHM", 0.8, "PSF FWHM in arcsec")], {}, 3.2),
    # SExtractor's names and units
    ([("FWHM_IMAGE", 3.3, "")], {}, 3.3),
    ([("FWHM_WORLD", 2.5e-4, "")], {}, 3.6),
])
def test_header_seeing_reads_the_keyword_in_its_unit(cards, extra, expected):
    got = seeing_from_header([_header(cards, **extra)], 0.25)
    assert got.fwhm == pytest.approx(expected, rel=1e-9)
    assert got.keyword == cards[0][0] and got.keyword in got.source and got.tried[-1].endswith("used")


def test_header_seeing_refuses_what_it_cannot_trust_and_says_why():
    header = _header([("FWHM", 0.2, "Median FWHM in pixels"),   # too small to be a seeing
                      ("SEEING", 0.9, "seeing"),                  # no unit, not CASU data
                      ("PSF_FWHM", "n/a", "")])                   # not a number
    got = seeing_from_header([header], 0.2)
    assert got.fwhm is None
    said = "\n".join(got.tried)
    assert "FWHM = 0.2" in said and "outside the 0.7-100 pixels" in said
    assert "SEEING = 0.9" in said and "names no unit" in said
    assert "PSF_FWHM" in said and "not a positive number" in said
    assert "FWHM_IMAGE: absent" in said and "FWHM_WORLD: absent" in said


def test_header_seeing_takes_the_image_header_before_the_primary():
    image = _header([("SEEING", 2.0, "[pixels]")])
    primary = _header([("FWHM", 5.0, "Median FWHM in pixels"), ("SEEING", 9.0, "[pixels]")])
    got = seeing_from_header([image, primary], 0.2)
    assert (got.keyword, got.fwhm) == ("FWHM", 5.0)  # FWHM comes first in the order of keywords ...
    got = seeing_from_header([_header([("SEEING", 2.0, "[pixels]")]), primary], 0.2, catalog=None)
    assert got.fwhm == 5.0
    del primary["FWHM"]
    assert seeing_from_header([image, primary], 0.2).fwhm == 2.0  # ... and the image HDU's SEEING wins


def test_header_seeing_is_checked_against_the_bright_detections():
    # Measured (../shared/data/misc, a CTIO Mosaic2 cutout): FWHM = 1.69 "Median FWHM in pixels", while
    # the bright unflagged detections have flux_radius 2.5-5 px; a point source of FWHM 1.69 px has at most
    # 0.8 x 1.69 = 1.35 px.  A catalog of such sizes refuses the keyword; one of point sources accepts it.
    from astropy.table import Table

    header = _header([("FWHM", 1.69, "Median FWHM in pixels")])
    big = Table({"flux_radius": np.linspace(2.5, 5.5, 12), "snr_auto": np.full(12, 50.0),
                 "flags": np.zeros(12, np.int64)})
    got = seeing_from_header([header], 0.26, catalog=big)
    assert got.fwhm is None and "does not describe this image" in got.tried[0]
    small = Table({"flux_radius": np.full(12, 1.0), "snr_auto": np.full(12, 50.0), "flags": np.zeros(12, np.int64)})
    assert seeing_from_header([header], 0.26, catalog=small).fwhm == 1.69
    assert seeing_from_header([header], 0.26, catalog=big[:4]).fwhm == 1.69  # too few to judge


def test_measure_seeing_falls_back_on_the_header_and_lists_everything_it_tried():
    data = make_field("moffat", 3.5, seed=3, stars=False, ngal=0)  # noise only: no star to fit
    det = detect_array(data, zeropoint=30.0)
    sub = data - det.background
    header = _header([("FWHM", 3.4, "Median FWHM in pixels")])
    got = measure_seeing(sub, det.catalog, headers=[header], pixel_scale=0.2)
    assert got["source"] == "header" and got["fwhm"] == 3.4 and got["beta"] is None
    assert "header keyword FWHM = 3.4 (pixels, as its comment says)" in got["fwhm_source"]
    assert "star candidates found" in got["stars"]
    with pytest.raises(InputError) as err:
        measure_seeing(sub, det.catalog, headers=[_header()], pixel_scale=0.2)
    message = str(err.value)
    assert message.startswith("cannot determine the seeing FWHM")
    for said in ("(1) Moffat fits to the image's stars: only 0 star candidates", "(2) header keywords: FWHM: absent",
                 "SEEING: absent", "PSF_FWHM: absent", "FWHM_IMAGE: absent", "FWHM_WORLD: absent", "--fwhm"):
        assert said in message, said
    got = measure_seeing(sub, det.catalog, headers=[_header()], pixel_scale=0.2, fallback=(3.0, "the demo's seeing"))
    assert (got["source"], got["fwhm"], got["fwhm_source"]) == ("fallback", 3.0, "the demo's seeing")


def test_measure_seeing_fits_the_stars_for_their_beta_even_when_the_fwhm_is_given():
    data = make_field("moffat", 3.5, seed=7, ngal=0)  # GalSim Moffat beta 3 stars
    det = detect_array(data, zeropoint=30.0)
    fitted = measure_seeing(data - det.background, det.catalog)
    assert fitted["source"] == "fitted" and fitted["fwhm_source"] == f"fitted from {fitted['nstars']} stars"
    assert fitted["fwhm"] == pytest.approx(3.5, rel=0.1) and fitted["beta"] == pytest.approx(3.0, rel=0.15)
    # the stars' flux_radius, measured by the detector on the stars that entered the fit
    assert 0.5 * 3.5 < fitted["star_flux_radius"] < 0.8 * 3.5
    assert len(fitted["star_rows"]) == fitted["nstars"]
    assert np.median(det.catalog["flux_radius"][fitted["star_rows"]]) == fitted["star_flux_radius"]
    given = measure_seeing(data - det.background, det.catalog, user_fwhm=4.0)
    assert (given["source"], given["fwhm"], given["fwhm_source"]) == ("user", 4.0, "user --fwhm")
    assert given["beta"] == fitted["beta"]


# --------------------------------------------------------------------------- the injected PSF (issue 13)


def _seeing(**kw):
    out = {"fwhm": 3.2, "source": "fitted", "fwhm_source": "fitted from 40 stars", "nstars": 40, "beta": 2.4,
           "beta_at_bound": 0, "stars": "fitted"}
    out.update(kw)
    return out


def test_injection_psf_uses_the_fitted_beta_integrated_over_the_pixel():
    from comest_bayes.config import InjectionConfig

    psf = injection_psf(InjectionConfig(), _seeing())
    assert (psf["model"], psf["fwhm_pix"], psf["beta"], psf["pixel_integrated"]) == ("moffat", 3.2, 2.4, True)
    assert psf["beta_source"] == "fitted from 40 stars (median)" and psf["warnings"] == []
    assert "integrated over the pixel" in psf["description"]
    # a beta set in the configuration wins
    psf = injection_psf(InjectionConfig(moffat_beta=4.5), _seeing())
    assert psf["beta"] == 4.5 and "configuration" in psf["beta_source"]
    # not measured: beta 3, with the reason; a FWHM from the header is the effective PSF's
    psf = injection_psf(InjectionConfig(), _seeing(source="header", fwhm_source="header keyword FWHM = 3.2", beta=None,
                                                   stars="only 0 star candidates found"))
    assert psf["beta"] == 3.0 and psf["beta_source"] == "default 3: not measured (only 0 star candidates found)"
    assert not psf["pixel_integrated"] and psf["fwhm_source"] == "header keyword FWHM = 3.2"
    # a Gaussian has no beta
    psf = injection_psf(InjectionConfig(psf="gaussian"), _seeing())
    assert psf["beta"] is None and psf["beta_source"] is None and psf["pixel_integrated"]


@pytest.mark.parametrize("beta, side", [(BETA_RANGE[0], "lower"), (BETA_RANGE[1], "upper")])
def test_a_fitted_beta_at_a_bound_is_warned_about(beta, side):
    from comest_bayes.config import InjectionConfig

    psf = injection_psf(InjectionConfig(), _seeing(beta=beta, beta_at_bound=31))
    assert psf["beta"] == beta
    assert len(psf["warnings"]) == 1 and f"at the {side} bound" in psf["warnings"][0]
    assert "31 of 40 stars" in psf["warnings"][0]


def test_point_size_check_known_answers():
    rng = np.random.default_rng(4)
    stars = 2.0 * (1.0 + 0.01 * rng.standard_normal(50))
    same = point_size_check(stars, 2.0 * (1.0 + 0.02 * rng.standard_normal(300)))
    assert same["status"] == "agree" and same["ratio"] == pytest.approx(1.0, abs=0.01)
    # 7 % smaller, measured to 0.2 %: a disagreement; 3 % smaller: within the 5 % tolerance
    small = point_size_check(stars, 1.86 * (1.0 + 0.02 * rng.standard_normal(300)))
    assert small["status"] == "disagree" and small["ratio"] == pytest.approx(0.93, abs=0.01)
    assert point_size_check(stars, 1.94 * np.ones(300))["status"] == "agree"
    assert point_size_check(stars[:4], stars)["status"] == "not enough"
    assert point_size_check(stars, [np.nan] * 10)["ninjected"] == 0


@pytest.mark.realdata
def test_real_headers_decam_fwhm_is_used_and_a_contradicted_one_is_refused(shared_data):
    # No star can be fitted on either cutout (measured: 0 star candidates).  DECam's community pipeline
    # writes FWHM = 4.02 "Median FWHM in pixels" in the image HDU (1); the CTIO Mosaic2 cutout says
    # FWHM = 1.69 pixels in its primary header while its 12 bright unflagged detections all exceed 2.5 px
    # (README: seeing about 5.8 px), so the keyword is refused and the error says why.
    import warnings

    from astropy.io import fits

    from comest_bayes.config import DetectionConfig
    from comest_bayes.detect.sep_backend import detect
    from comest_bayes.io.image import load_image

    def seeing(path, **kw):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # TPV/astropy header notes are not what this test is about
            image = load_image(path, **kw)
        det = detect(image, DetectionConfig())
        headers = [image.header] + ([fits.getheader(path, 0)] if image.hdu else [])
        return measure_seeing(image.data - det.background, det.catalog, mask=image.mask, headers=headers,
                              pixel_scale=image.pixel_scale)

    got = seeing(shared_data / "decam" / "decam_r_N6_375x280_ooi.fits", zp=29.3)
    assert got["source"] == "header" and got["fwhm"] == pytest.approx(4.022961)
    assert got["fwhm_source"] == "header keyword FWHM = 4.02296 (pixels, as its comment says)"
    with pytest.raises(InputError, match=r"FWHM = 1\.686972 / Median FWHM in pixels: refused, 1\.69 pixels does "
                                         r"not describe this image"):
        seeing(shared_data / "misc" / "ctio_mosaic2_I_cdfs_512px_tpv.fits", zp=30.0)
