"""The injected PSF through the pipeline (issue 13): it is the PSF the image has, and says so.

* On a synthetic image whose stars are Moffat profiles of beta 2.5 (drawn with
  :func:`comest_bayes.detect.psf.moffat_image`, integrated over the pixels), a run
  fits the seeing, injects the fitted Moffat (its beta, integrated over the
  pixel), and its own diagnostic finds the injected point sources as large as
  the stars; with beta forced to 3 the same diagnostic finds them too small.
* An image without stars takes the seeing from a header keyword, records
  which one and why, and stops with every attempt listed when there is none.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from comest_bayes.config import load_config
from comest_bayes.errors import InputError
from comest_bayes.pipeline.stages import ComputeOptions, ImageOptions, run_pipeline
from comest_bayes.detect.psf import moffat_image
from conftest import jittered_grid, tan_header, write_fits_file

SERIAL = ComputeOptions(executor="serial")
SHAPE = (500, 500)
PIXEL_SCALE = 0.2
ZP = 27.0
SKY, SIGMA = 100.0, 5.0
FWHM, BETA = 3.5, 2.5
# 40 point sources per arcmin^2 (about 110 per realization on 2.8 arcmin^2), 6 realizations: a few
# hundred detected above SNR 20.  Much denser injections (150 / arcmin^2, 14 px apart) measured 2 %
# smaller sizes from their neighbours' light alone.
OVERRIDES = ["fit.model=none", "fit.purity_model=none", "injection.kinds=point", "injection.nsims=6",
             "injection.density=40", "injection.mag_range=[16,21]"]


@pytest.fixture(scope="module")
def beta25_image(tmp_path_factory) -> Path:
    """64 stars (SNR ~50-2000) of a pixel-integrated Moffat, FWHM 3.5 px, beta 2.5, on white noise."""
    d = tmp_path_factory.mktemp("beta25")
    rng = np.random.default_rng(11)
    x, y = jittered_grid(SHAPE, 60.0, 30.0, rng)
    flux = 10 ** rng.uniform(4.0, 5.5, x.size)
    model = np.zeros(SHAPE)
    h = 40  # 99.9 % of a beta 2.5 Moffat's light lies within 11.5 FWHM = 40 px
    for xi, yi, fi in zip(x, y, flux):
        ix, iy = int(round(xi)), int(round(yi))
        x0, y0, x1, y1 = max(ix - h, 0), max(iy - h, 0), min(ix + h + 1, SHAPE[1]), min(iy + h + 1, SHAPE[0])
        model[y0:y1, x0:x1] += moffat_image((y1 - y0, x1 - x0), xi - x0, yi - y0, fi, FWHM, BETA, oversample=7)
    data = (SKY + model + rng.normal(0.0, SIGMA, SHAPE)).astype(np.float32)
    header = tan_header(SHAPE, PIXEL_SCALE)
    header["MAGZERO"] = ZP
    return write_fits_file(d / "stars_beta25.fits", data, header)


def test_injected_point_sources_are_as_large_as_the_stars(beta25_image, tmp_path):
    lines = []
    result = run_pipeline(ImageOptions(path=str(beta25_image)), load_config(overrides=OVERRIDES, seed=5),
                          tmp_path / "run", log=lines.append, compute=SERIAL)
    state = json.loads((tmp_path / "run" / "run.json").read_text())
    psf = state["psf"]
    # the fit finds the stars' profile (FWHM within 1 %, beta within 0.1) and the injections use it
    assert psf["model"] == "moffat" and psf["pixel_integrated"] is True
    assert psf["fwhm_pix"] == pytest.approx(FWHM, rel=0.01) and psf["beta"] == pytest.approx(BETA, abs=0.1)
    assert psf["fwhm_source"].startswith("fitted from ") and psf["beta_source"].startswith("fitted from ")
    assert psf["warnings"] == [] and result.summary["psf"] == psf
    assert any(s.startswith("psf: injecting a Moffat") and "integrated over the pixel" in s for s in lines), lines
    # the run's own diagnostic: median flux_radius of detected injections (SNR >= 20) against the stars'.
    # Measured: ratio 0.985 +- 0.002 (the injections span fainter magnitudes, where SEP's flux_radius is
    # ~1.5 % smaller); the stated tolerance is 5 %.
    check = result.summary["kinds"]["point"]["size_check"]
    assert check["nstars"] == state["stages"]["fwhm"]["estimate"]["nstars"] >= 50  # the fitted stars
    assert check["ninjected"] >= 200
    assert check["status"] == "agree" and abs(check["ratio"] - 1.0) < 0.05, check
    assert any(s.startswith("psf check: point:") and "agree within 5%" in s for s in lines), lines

    # the report shows where the PSF came from and the size check
    from comest_bayes.report.html import write_report

    html = write_report(tmp_path / "run").read_text()
    assert "injected PSF" in html and "fitted from" in html and "point-source size check" in html


def test_the_size_check_catches_injections_of_the_wrong_beta(beta25_image, tmp_path):
    # beta 3 instead of the stars' 2.5, same FWHM: measured ratio 0.938 +- 0.002
    lines = []
    result = run_pipeline(ImageOptions(path=str(beta25_image)),
                          load_config(overrides=OVERRIDES + ["injection.moffat_beta=3"], seed=5),
                          tmp_path / "run", log=lines.append, compute=SERIAL)
    assert result.summary["psf"]["beta"] == 3.0 and "configuration" in result.summary["psf"]["beta_source"]
    check = result.summary["kinds"]["point"]["size_check"]
    assert check["status"] == "disagree" and check["ratio"] < 0.95, check
    assert any(s.startswith("warning: psf check: point:") for s in lines), lines


STARLESS = ["fit.model=none", "fit.purity_model=none", "injection.kinds=point", "injection.nsims=2",
            "injection.density=60", "injection.mag_range=[18,24]"]


def _starless_image(tmp_path, **keywords) -> Path:
    """Flat noise, no source: the seeing cannot be measured on it."""
    shape = (400, 400)
    header = tan_header(shape, PIXEL_SCALE)
    header["MAGZERO"] = ZP
    for key, value in keywords.items():
        header[key] = value
    data = (SKY + np.random.default_rng(2).normal(0.0, SIGMA, shape)).astype(np.float32)
    return write_fits_file(tmp_path / "starless.fits", data, header)


def test_without_stars_the_header_seeing_is_used_and_recorded(tmp_path):
    path = _starless_image(tmp_path, FWHM=(3.2, "Median FWHM in pixels"))
    lines = []
    config = load_config(overrides=STARLESS, seed=1)
    result = run_pipeline(ImageOptions(path=str(path)), config, tmp_path / "run", log=lines.append, compute=SERIAL)
    state = json.loads((tmp_path / "run" / "run.json").read_text())
    assert state["image"]["fwhm_pix"] == 3.2
    assert "header keyword FWHM = 3.2 (pixels, as its comment says)" in state["image"]["provenance"]["fwhm"]
    psf = state["psf"]
    assert psf["fwhm_source"] == "header keyword FWHM = 3.2 (pixels, as its comment says)"
    assert psf["beta"] == 3.0 and psf["beta_source"].startswith("default 3: not measured (only 0 star candidates")
    assert psf["pixel_integrated"] is False  # a header FWHM is the effective PSF's
    seeing = state["stages"]["fwhm"]["estimate"]
    assert seeing["source"] == "header" and len(seeing["tried"]) == 2
    assert any(s.startswith("fwhm: 3.20 px") and "header keyword FWHM" in s for s in lines), lines
    assert result.summary["kinds"]["point"]["counts"]["usable"] > 0


def test_without_stars_or_header_seeing_the_error_lists_every_attempt(tmp_path):
    path = _starless_image(tmp_path, SEEING=(0.8, "seeing"))  # no unit: refused
    config = load_config(overrides=STARLESS, seed=1)
    with pytest.raises(InputError) as err:
        run_pipeline(ImageOptions(path=str(path)), config, tmp_path / "run", log=lambda s: None, compute=SERIAL)
    message = str(err.value)
    assert "star candidates found" in message and "SEEING = 0.8 / seeing: refused, its comment names no unit" in message
    assert "FWHM: absent" in message and "--fwhm" in message
    assert not (tmp_path / "run").exists()  # nothing is written before the seeing is known
