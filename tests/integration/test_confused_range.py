"""The automatic magnitude range on a confused field: it starts brighter, and its injections keep apart."""

import json

import numpy as np
import pytest
from astropy.table import Table

from comest_bayes.cli import main
from comest_bayes.pipeline.preflight import CONFUSION_COVER, CONFUSION_MAX_SHIFT, CONFUSION_RISE
from comest_bayes.sim.starfield import star_field


def _field(tmp_path, density, seed=3):
    # 320x320 px at 0.5"/px (7.1 arcmin^2), Gaussian stars of 3 px FWHM on white noise, m5 = 24.1
    path = tmp_path / f"stars_{density:g}.fits"
    hdu, facts = star_field((320, 320), density, seed=seed)
    hdu.writeto(path)
    return path, facts


def _run(image, out, *extra):
    return main(["run", str(image), "--fwhm", "3", "--nsims", "1", "--model", "none", "--ncpu", "1", "--seed", "2",
                 "--no-report", "--set", "injection.on=observed", "--out", str(out), *extra])


def _ran(image, out, capsys, *extra):
    """Run, then the log, run.json and its injection_range."""
    assert _run(image, out, *extra) == 0
    state = json.loads((out / "run.json").read_text())
    return capsys.readouterr().out, state, state["injection_range"]


def _closest_pair(table):
    """Smallest distance (pixels) between two injections of the same realization."""
    best = np.inf
    for r in np.unique(table["realization"]):
        sel = table["realization"] == r
        x, y = np.asarray(table["x"][sel], float), np.asarray(table["y"][sel], float)
        if x.size > 1:
            d = np.hypot(x[:, None] - x[None, :], y[:, None] - y[None, :])
            best = min(best, d[np.triu_indices(x.size, 1)].min())
    return best


def test_a_confused_field_starts_its_range_brighter_and_keeps_its_injections_apart(tmp_path, capsys):
    # 300 stars per arcmin^2 brighter than m5 (8,300 stars down to m5 + 2): the sources SEP finds in the usual
    # range's first 2 mag cover about 11% of the image
    image, _ = _field(tmp_path, 300.0)
    out = tmp_path / "confused"
    log, state, rec = _ran(image, out, capsys, "--kinds", "point,buldisk")
    assert rec["rule"] == "confused" and rec["confusion_rise"] > CONFUSION_RISE
    lo, hi = rec["mag_range"]
    # the start moves brighter, by at most CONFUSION_MAX_SHIFT, to where brighter sources cover at most 5%
    assert rec["usual_bright"] - CONFUSION_MAX_SHIFT <= lo < rec["usual_bright"] - 0.5
    assert rec["usual_bright"] == pytest.approx(round(rec["m5"] - 5.0, 2)) and hi == pytest.approx(round(rec["m5"] + 1.5, 2))
    assert rec["cover_bright"] <= CONFUSION_COVER
    assert f"range: a confused field: the sources detected at {rec['usual_bright']:.2f}-" in log
    assert f"the injections start at {lo:.2f} mag instead" in log
    assert f"injections span {lo:.2f}-{hi:.2f} mag" in log
    assert state["stages"]["baseline"]["mag_range"] == [lo, hi]
    assert state["stages"]["baseline"]["range"]["rule"] == "confused"
    # the brightest injection's reach keeps every kind apart: far more than 4 FWHM (12 px) for the point sources,
    # and the galaxies never closer than that
    dens = state["injection_density"]
    sep_point = dens["point"]["min_sep_arcsec"] / 0.5
    assert sep_point > 12.0 * 1.2
    assert dens["buldisk"]["min_sep_arcsec"] >= dens["point"]["min_sep_arcsec"]
    assert "instead of 4 FWHM" in log and "instead of each pair's size-based separation" in log
    injected = Table.read(out / "catalogs" / "point_injected.fits")
    assert injected["mag"].min() >= lo and _closest_pair(injected) >= sep_point - 1e-6
    galaxies = Table.read(out / "catalogs" / "buldisk_injected.fits")
    assert _closest_pair(galaxies) >= dens["buldisk"]["min_sep_arcsec"] / 0.5 - 1e-6

    # the report's table of decisions says it, with the log line's reason
    from html import escape

    from comest_bayes.report.html import write_report

    assert rec["reason"].startswith("a confused field: the sources detected at")
    assert f"range: {rec['reason']}" in log
    html = write_report(out).read_text()
    assert "injected magnitudes" in html and escape(rec["reason"]) in html
    # `info` says where the range came from
    assert main(["info", str(out)]) == 0
    assert (f"injected magnitudes: {lo:.2f}-{hi:.2f} (automatic, a confused field: from where brighter sources "
            f"cover {100 * rec['cover_bright']:.0f}% of the image, instead of m5 - 5 = {rec['usual_bright']:.2f})"
            in capsys.readouterr().out.splitlines())

    # resumed, the run keeps the range it chose
    assert _run(image, out, "--kinds", "point,buldisk") == 0
    assert json.loads((out / "run.json").read_text())["injection_range"]["mag_range"] == [lo, hi]


def test_a_sparse_star_field_keeps_the_range_from_m5(tmp_path, capsys):
    # 3 stars per arcmin^2 brighter than m5: the usual range's first 2 mag hold about 0.1% of the image
    image, _ = _field(tmp_path, 3.0)
    out = tmp_path / "sparse"
    log, state, rec = _ran(image, out, capsys, "--kinds", "point")
    assert rec["rule"] == "m5" and rec["confusion_rise"] < 0.1 * CONFUSION_RISE
    assert rec["mag_range"] == [pytest.approx(round(rec["m5"] - 5.0, 2)), pytest.approx(round(rec["m5"] + 1.5, 2))]
    assert "range: a confused field" not in log
    assert rec["reason"] == f"m5 - 5 to m5 + 1.5 around the 5-sigma point-source depth m5 = {rec['m5']:.2f} of the injection PSF"
    assert state["injection_density"]["point"].get("min_sep_arcsec") is None  # 4 FWHM kept
    assert main(["info", str(out)]) == 0
    lo, hi = rec["mag_range"]
    assert f"injected magnitudes: {lo:.2f}-{hi:.2f} (automatic: m5 - 5 to m5 + 1.5)" in capsys.readouterr().out


def test_a_range_the_user_sets_is_kept_on_a_confused_field(tmp_path, capsys):
    image, _ = _field(tmp_path, 300.0)
    log, _, rec = _ran(image, tmp_path / "user", capsys, "--kinds", "point", "--set", "injection.mag_range=[19.5,24.5]")
    assert rec == {"mag_range": [19.5, 24.5], "rule": "user", "reason": "injection.mag_range as set"}
    assert "range: a confused field" not in log and "injections span 19.50-24.50 mag" in log
    assert main(["info", str(tmp_path / "user")]) == 0
    assert "injected magnitudes: 19.50-24.50 (as set)" in capsys.readouterr().out


@pytest.mark.parametrize("extra, footprints", [((), "segmentation.fits"),
                                               (("--set", "detection.background_level=observed"),
                                                "baseline_segmentation.fits")])
def test_on_the_observed_image_a_detection_in_a_real_sources_footprint_is_that_source(tmp_path, extra, footprints):
    # A realization's re-detection of a crowded field splits, merges and shifts the blends of its real sources
    # by more than the matching radius (1 FWHM): those detections are the real sources, not false ones.
    from astropy.io import fits

    image, _ = _field(tmp_path, 300.0)
    out = tmp_path / "observed"
    assert _run(image, out, "--kinds", "point", "--nsims", "2", *extra) == 0
    state = json.loads((out / "run.json").read_text())
    # the first detection is the baseline when nothing differs; with the observed background map the baseline is
    # detected again and its own segmentation kept
    assert state["stages"]["baseline"]["preexisting_footprints"] == footprints
    seg = fits.getdata(out / footprints)
    dets = Table.read(out / "sims" / "point" / sorted(p.name for p in (out / "sims" / "point").iterdir())[0],
                      "DETECTIONS")
    ix = np.floor(np.asarray(dets["xwin"], float) + 0.5).astype(int)
    iy = np.floor(np.asarray(dets["ywin"], float) + 0.5).astype(int)
    inside = seg[np.clip(iy, 0, seg.shape[0] - 1), np.clip(ix, 0, seg.shape[1] - 1)] > 0
    unmatched = ~np.asarray(dets["matched"], bool)
    preexisting, false = np.asarray(dets["preexisting"], bool), np.asarray(dets["false"], bool)
    # every unmatched detection centred in a real source's footprint is pre-existing, none of them false; some of
    # these lie beyond the matching radius of any real source's position (the ones this rule adds)
    assert (unmatched & inside).sum() >= 20
    assert preexisting[unmatched & inside].all() and not false[inside].any()
    base = Table.read(out / "baseline.fits")
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(np.column_stack([base["xwin"], base["ywin"]])).query(np.column_stack([dets["xwin"], dets["ywin"]]))
    assert (unmatched & inside & (dist > 3.0)).sum() >= 1
    # outside every footprint and far from every real source, an unmatched detection stays false
    assert not preexisting[unmatched & ~inside & (dist > 3.0)].any()
