"""The injection PSF (comest_bayes.inject.psfmodel): analytic PSFs at the image's FWHM, PSF files, errors."""

import numpy as np
import pytest
from astropy.io import fits

from comest_bayes.config import InjectionConfig
from comest_bayes.errors import InputError, InputFileError
from comest_bayes.inject.psfmodel import make_psf, psf_half_light_radius_pix, psf_image_fwhm_pix


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


def test_the_fwhm_of_a_psf_image_in_image_pixels(tmp_path):
    # a Gaussian of sigma 3 PSF pixels of 0.01" (PIXELSCL): FWHM 2.3548 x 0.03" = 2.3548 pixels of 0.03"
    yy, xx = np.mgrid[0:41, 0:41]
    path = tmp_path / "webbpsf_like.fits"
    fits.writeto(path, np.exp(-((xx - 20.0) ** 2 + (yy - 20.0) ** 2) / (2 * 3.0 ** 2)), fits.Header({"PIXELSCL": 0.01}))
    assert psf_image_fwhm_pix(InjectionConfig(psf=str(path)), 0.03) == pytest.approx(2.3548, rel=0.02)
    assert psf_image_fwhm_pix(InjectionConfig(psf=str(path)), 0.06) == pytest.approx(2.3548 / 2, rel=0.02)
    assert psf_image_fwhm_pix(InjectionConfig(psf="moffat"), 0.03) is None  # an analytic PSF has the image's seeing


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


def test_make_psf_rejects_a_bad_pixel_scale():
    with pytest.raises(InputError, match="pixel scale"):
        make_psf(InjectionConfig(), 3.0, 0.0)
