"""What a new user met on the JWST cutout: a run whose stars and header give no seeing takes the FWHM of the
injection PSF image the user gave (``injection.psf``) instead of asking for ``--fwhm``; its error map read
with the default ``--weight-type ivar`` is flagged."""

import json

import pytest

from comest_bayes.cli import main
from comest_bayes.config import InjectionConfig
from comest_bayes.inject.psfmodel import psf_image_fwhm_pix


def test_the_jwst_cutout_runs_with_its_psf_image_and_no_fwhm(shared_data, tmp_path, capsys):
    jwst = shared_data / "jwst"
    psf = jwst / "jwst_nircam_f200w_webbpsf.fits"
    argv = ["run", str(jwst / "jwst_nircam_f200w_a2744_glass_sci.fits"), "--out", str(tmp_path / "run"),
            "--weight", str(jwst / "jwst_nircam_f200w_a2744_glass_err.fits"), "--weight-type", "rms",
            "--kinds", "point", "--nsims", "2", "--model", "none", "--no-report", "--ncpu", "1", "--quiet"]
    # without the PSF image the run cannot know the seeing (no stars fit, no header keyword): a clear error
    assert main(argv[:-1] + ["--out", str(tmp_path / "nopsf"), "--quiet"]) == 2
    assert "cannot determine the seeing FWHM" in capsys.readouterr().err
    assert main(argv + ["--set", f"injection.psf={psf}"]) == 0
    state = json.loads((tmp_path / "run" / "run.json").read_text())
    seeing = state["image"]
    expected = psf_image_fwhm_pix(InjectionConfig(psf=str(psf)), 0.0308)
    assert 1.8 < expected < 2.6  # the detector-sampled WebbPSF F200W model: about 2 pixels of 0.031"
    assert seeing["fwhm_pix"] == pytest.approx(expected, rel=0.02)  # the image's scale is 0.03078", not 0.0308
    assert "the FWHM of the injection PSF image" in state["psf"]["fwhm_source"]


def test_an_error_map_read_as_inverse_variance_is_flagged(shared_data, tmp_path, capsys):
    jwst = shared_data / "jwst"
    argv = ["run", str(jwst / "jwst_nircam_f200w_a2744_glass_sci.fits"),
            "--weight", str(jwst / "jwst_nircam_f200w_a2744_glass_err.fits"), "--fwhm", "2.46", "--kinds", "point",
            "--nsims", "2", "--model", "none", "--no-report", "--ncpu", "1"]
    assert main(argv + ["--out", str(tmp_path / "ivar")]) == 0  # the default --weight-type ivar
    out = capsys.readouterr().out
    assert "warning: weight map: the noise it implies as ivar falls where" in out and "--weight-type rms" in out
    state = json.loads((tmp_path / "ivar" / "run.json").read_text())
    agree = state["stages"]["detect"]["meta"]["weight_agreement"]
    assert agree["spearman"] < -0.5 and agree["meshes"] == 100  # measured -0.68 over the 10x10 meshes
    assert main(argv + ["--out", str(tmp_path / "rms"), "--weight-type", "rms"]) == 0
    assert "warning: weight map" not in capsys.readouterr().out
    state = json.loads((tmp_path / "rms" / "run.json").read_text())
    assert state["stages"]["detect"]["meta"]["weight_agreement"]["spearman"] == pytest.approx(-agree["spearman"])
