"""The point-source stamp decision recorded in run.json (psf.stamp): known answers for Moffat PSFs."""

import math

import galsim
import pytest

from comest_bayes.config import InjectionConfig
from comest_bayes.inject.render import MAX_PSF_RADIUS_PIX, point_stamp_size
from comest_bayes.detect.psf import injection_psf


def _moffat_radius(fwhm, beta, fraction=0.995):
    """Radius (pixels) outside which a Moffat leaves 1 - fraction of its light: (1 + (R/a)^2)^(1-beta)."""
    alpha = fwhm / (2.0 * math.sqrt(2.0 ** (1.0 / beta) - 1.0))
    return alpha * math.sqrt((1.0 - fraction) ** (1.0 / (1.0 - beta)) - 1.0), alpha


@pytest.mark.parametrize("fwhm, beta", [(3.0, 3.0), (2.0, 2.5), (4.0, 4.5)])
def test_point_stamp_encloses_the_requested_light_of_a_moffat(fwhm, beta):
    scale = 0.2
    stamp = point_stamp_size(galsim.Moffat(beta=beta, fwhm=fwhm * scale), scale)
    radius, _ = _moffat_radius(fwhm, beta)  # 10.67, 10.19 and 9.23 px
    assert stamp["psf_radius_pix"] == pytest.approx(radius, rel=0.02)
    assert stamp["half_size_pix"] == math.ceil(stamp["psf_radius_pix"] + 1.0)
    assert stamp["enclosed_fraction"] == pytest.approx(0.995, abs=1e-3) and not stamp["capped"]


def test_heavy_wings_are_capped_and_say_so():
    # beta 1.5: 99.5% needs R = 200 alpha = 392 px for FWHM 3 px, beyond the 256 px cap; within 256 px
    # the Moffat holds 1 - (1 + (256/alpha)^2)^(-1/2) = 0.9924
    radius, alpha = _moffat_radius(3.0, 1.5)
    assert radius > MAX_PSF_RADIUS_PIX
    stamp = point_stamp_size(galsim.Moffat(beta=1.5, fwhm=0.6), 0.2)
    assert stamp["capped"] and stamp["psf_radius_pix"] == pytest.approx(MAX_PSF_RADIUS_PIX)
    expected = 1.0 - (1.0 + (MAX_PSF_RADIUS_PIX / alpha) ** 2) ** -0.5
    assert stamp["enclosed_fraction"] == pytest.approx(expected, abs=2e-3)
    assert "capped at 256 px" in stamp["source"]


def test_injection_psf_records_the_stamp_and_names_it():
    seeing = {"fwhm": 3.0, "source": "user", "fwhm_source": "user --fwhm", "beta": None, "stars": "not fitted"}
    choice = injection_psf(InjectionConfig(), seeing, pixel_scale=0.2)
    stamp = choice["stamp"]
    radius, _ = _moffat_radius(3.0, 3.0)
    assert stamp["psf_radius_pix"] == pytest.approx(radius, rel=0.02) and stamp["half_size_pix"] == 12
    assert "point-source stamps 25x25 px (99.5% of the light)" in choice["description"]
    assert choice["warnings"] == []
    assert "stamp" not in injection_psf(InjectionConfig(), seeing)  # without a pixel scale: not decided here
    heavy = injection_psf(InjectionConfig(moffat_beta=1.5), seeing, pixel_scale=0.2)
    width = 2 * heavy["stamp"]["half_size_pix"] + 1  # 515 px: the 256 px cap plus a pixel each side
    assert heavy["stamp"]["capped"] and any(f"wider than {width} px" in w for w in heavy["warnings"])
