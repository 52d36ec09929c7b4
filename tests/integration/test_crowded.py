"""A crowded field through the pipeline: the source-free image that would replace most of it.

The fields are Gaussian stars (FWHM 3 px) on a flat sky of 100 with noise 10, dN/dm ~ 10^(0.3 m)
(:func:`conftest.crowded_field`):

* 1250 stars of 14-22 mag on 256^2 pixels, the density of the issue's 20,000 stars on 1024^2: their
  grown segments cover 99.98% of the pixels, and the run must be refused before anything is written,
  offering the observed image (Balrog's way) and the bright-and-big image;
* 600 stars of 16-24 mag: 85% replaced, a run with a warning recorded in run.json and summary.json.
"""

import json

import numpy as np
import pytest
from astropy.io import fits

from conftest import crowded_field, tan_header, write_fits_file

from comest_bayes.cli import main

COMMON = ["--fwhm", "3", "--density", "200", "--nsims", "1", "--kinds", "point", "--model", "none",
          "--set", "fit.purity_model=none", "--no-report", "--executor", "serial"]


def _write(path, data):
    header = tan_header(data.shape, 0.2)
    header["MAGZERO"] = 30.0
    header["BUNIT"] = "ADU"
    return write_fits_file(path, data, header)


@pytest.fixture(scope="module")
def packed(tmp_path_factory):
    return _write(tmp_path_factory.mktemp("packed") / "packed.fits",
                  crowded_field(nstars=1250, mags=(14.0, 22.0), seed=2))


def test_a_source_free_image_of_sky_draws_is_refused_before_anything_is_written(packed, tmp_path, capsys):
    before = packed.read_bytes()
    out = tmp_path / "run"
    assert main(["run", str(packed), "--out", str(out), *COMMON]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: the source-free image replaces 99.9")
    for phrase in ("sourcefree.max_replaced = 90%", "--set injection.on=observed", "as Balrog does",
                   "(--set injection.on=bnb)", "--set sourcefree.max_replaced=1", "Nothing was written."):
        assert phrase in err[0], phrase
    assert not out.exists() and packed.read_bytes() == before


def test_the_observed_image_is_the_honest_alternative(packed, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", str(packed), "--out", str(out), *COMMON, "--set", "injection.on=observed"]) == 0
    printed = capsys.readouterr().out
    assert "injecting on observed.fits" in printed and "warning: sourcefree" not in printed
    # the injections were drawn on the image as observed, its real sources counted as pre-existing
    np.testing.assert_array_equal(fits.getdata(out / "observed.fits"), fits.getdata(packed))
    state = json.loads((out / "run.json").read_text())
    assert state["stages"]["baseline"]["base"] == "observed.fits"
    assert state["stages"]["baseline"]["nsources"] == state["stages"]["detect"]["nsources"]
    summary = json.loads((out / "summary.json").read_text())
    record = summary["sourcefree"]
    assert record == state["stages"]["sourcefree"]["replacement"]
    assert record["injected_on"] == "observed" and record["fraction_replaced"] == 0.0
    assert record["sfi_fraction_replaced"] > 0.999 and record["refusal"] is None
    assert summary["kinds"]["point"]["counts"]["usable"] > 50


def test_a_mostly_replaced_image_warns_and_records_the_fraction(tmp_path, capsys):
    image = _write(tmp_path / "crowded.fits", crowded_field(nstars=600, mags=(16.0, 24.0), seed=1))
    out = tmp_path / "run"
    assert main(["run", str(image), "--out", str(out), *COMMON]) == 0
    printed = capsys.readouterr().out
    warned = [s for s in printed.splitlines() if s.startswith("warning: sourcefree:")]
    # the fraction, and (most meshes being mostly sources) that the sky under them could not be measured again
    assert len(warned) == 2 and "more than sourcefree.warn_replaced = 50%" in warned[0]
    assert "the sky under the removed sources could not be measured again" in warned[1]
    record = json.loads((out / "summary.json").read_text())["sourcefree"]
    assert record["injected_on"] == "sfi" and 0.5 < record["fraction_replaced"] <= 0.9
    assert record["warnings"] == [w.removeprefix("warning: sourcefree: ") for w in warned]
    # the same run resumed says it again: the fraction is a fact of the run, not of the stage's first pass
    assert main(["run", str(image), "--out", str(out), *COMMON]) == 0
    assert warned[0] in capsys.readouterr().out.splitlines()
    # and so does a look at the finished run
    assert main(["info", str(out)]) == 0
    assert f"  - source-free image: {record['warnings'][0]}" in capsys.readouterr().out.splitlines()
