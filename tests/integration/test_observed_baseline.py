"""Injecting on the observed image: the baseline detection reuses the first one, with unchanged numbers."""

import json

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table

from comest_bayes.pipeline import stages as pipeline
from comest_bayes.cli import main


@pytest.fixture()
def starry_image(tmp_path):
    # 256x256 white noise (sigma 1) with 40 Gaussian stars (FWHM 3 px, peaks 5-200 sigma)
    rng = np.random.default_rng(11)
    ny = nx = 256
    data = rng.normal(0.0, 1.0, (ny, nx))
    yy, xx = np.mgrid[0:ny, 0:nx]
    sigma = 3.0 / 2.3548
    for x0, y0, peak in zip(rng.uniform(10, nx - 10, 40), rng.uniform(10, ny - 10, 40), rng.uniform(5, 200, 40)):
        data += peak * np.exp(-((xx - x0) ** 2 + (yy - y0) ** 2) / (2 * sigma ** 2))
    path = tmp_path / "stars.fits"
    fits.writeto(path, data.astype(np.float32))
    return path


def _run(image, out, *extra):
    return main(["run", str(image), "--pixel-scale", "0.2", "--zp", "25", "--fwhm", "3", "--kinds", "point",
                 "--nsims", "2", "--model", "none", "--ncpu", "1", "--seed", "3", "--no-report", "--quiet",
                 "--out", str(out), "--set", "injection.on=observed", *extra])


def _sorted(table):
    return table[np.lexsort((np.asarray(table["ywin"]), np.asarray(table["xwin"])))]


def test_observed_baseline_reuses_the_first_detection_and_changes_no_number(starry_image, tmp_path, monkeypatch):
    reused = tmp_path / "reused"
    assert _run(starry_image, reused) == 0
    stage = json.loads((reused / "run.json").read_text())["stages"]["baseline"]
    assert stage["reused_detection"] is True
    baseline = Table.read(reused / "baseline.fits")
    detection = Table.read(reused / "detection.fits")
    assert len(baseline) == len(detection) >= 30  # the stars (and a few noise peaks)

    # The same run with the baseline detected afresh, as before the reuse: identical tables.
    monkeypatch.setattr(pipeline, "_observed_baseline", lambda *args, **kwargs: None)
    fresh = tmp_path / "fresh"
    assert _run(starry_image, fresh) == 0
    assert json.loads((fresh / "run.json").read_text())["stages"]["baseline"]["reused_detection"] is False
    again = Table.read(fresh / "baseline.fits")
    assert len(again) == len(baseline)
    a, b = _sorted(again), _sorted(baseline)
    for name in ("xwin", "ywin", "flux_auto", "mag_auto", "flux_radius", "flags"):
        np.testing.assert_array_equal(np.asarray(a[name]), np.asarray(b[name]), err_msg=name)
    for name in ("point_outcomes", "point_false"):
        t1 = Table.read(reused / "catalogs" / f"{name}.fits")
        t2 = Table.read(fresh / "catalogs" / f"{name}.fits")
        assert len(t1) == len(t2) and t1.colnames == t2.colnames
        for col in t1.colnames:
            np.testing.assert_array_equal(np.asarray(t1[col]), np.asarray(t2[col]), err_msg=f"{name}.{col}")
    s1 = json.loads((reused / "summary.json").read_text())["kinds"]["point"]
    s2 = json.loads((fresh / "summary.json").read_text())["kinds"]["point"]
    assert s1["m50_binned"] == s2["m50_binned"] and s1["counts"] == s2["counts"]


def test_a_baseline_on_other_pixels_is_detected(starry_image, tmp_path):
    # on the source-free image (the default) the pixels differ from the detection's: no reuse
    out = tmp_path / "sfi"
    assert main(["run", str(starry_image), "--pixel-scale", "0.2", "--zp", "25", "--fwhm", "3", "--kinds", "point",
                 "--nsims", "2", "--model", "none", "--ncpu", "1", "--no-report", "--quiet", "--out", str(out)]) == 0
    assert json.loads((out / "run.json").read_text())["stages"]["baseline"]["reused_detection"] is False
