"""Injection and recovery through the whole pipeline, against known answers.

Three small images are used, each run once per module:

* a *clean* image: flat sky plus white Gaussian noise of known sigma, no real
  source, a TAN WCS and a zero point.  Every detection on a realization is an
  injection or noise, so completeness, positions and magnitudes have analytic
  expectations (the matched-filter SNR of a Moffat point source, the Moffat
  growth curve);
* a clean image with a masked block and a rotated WCS, for the exclusion of
  masked injections and the orientation of the maps;
* a small demo tile (galaxies, stars, chip gap, weight map), for the
  executor independence and the resumption of interrupted runs.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table
from astropy.wcs import WCS

from comest_bayes.recover import realization as recovery
from comest_bayes.config import load_config
from comest_bayes.io import layout

# These tests are about injection and recovery; the Bayesian fit has its own tests.
NOFIT = ["fit.model=none", "fit.purity_model=none"]
from comest_bayes.sim.demo import MASK_GAP, make_demo_tile, write_demo_tile
from comest_bayes.pipeline.stages import ComputeOptions, ImageOptions, run_pipeline
from comest_bayes.ratios.binned import magnitude_edges
from comest_bayes.recover.realization import OUTCOME_COLUMNS, merge_realizations, realization_file
from conftest import make_synthetic_sky, matched_snr, render_point_sources, tan_header, write_fits_file

# ---------------------------------------------------------------- the clean image
SHAPE = (800, 800)
PIXEL_SCALE = 0.2  # arcsec / pixel
ZP = 27.0
SKY = 100.0
SIGMA = 5.0  # white noise sigma, image units
FWHM = 3.0  # pixels, given to the pipeline (a clean image has no star to measure it on)
BETA = 3.0  # injection.moffat_beta default
MAG_RANGE = (17.0, 25.5)
MAG_BIN = 0.5
SERIAL = ComputeOptions(executor="serial")


def _quiet(_line: str) -> None:
    pass


def _read(path) -> Table:
    """A FITS table as written: NaN stays NaN (astropy would otherwise mask it)."""
    return Table.read(path, mask_invalid=False)


def _mag_of_snr(snr: float) -> float:
    """Magnitude of a point source of matched-filter SNR ``snr`` on the clean image."""
    unit = float(matched_snr(1.0, FWHM, SIGMA, psf="moffat", beta=BETA))
    return ZP - 2.5 * np.log10(snr / unit)


def _moffat_enclosed(radius_pix, fwhm: float = FWHM, beta: float = BETA):
    """Fraction of a Moffat profile's flux inside a circle of ``radius_pix``.

    ``1 - (1 + R^2/alpha^2)^(1 - beta)`` with ``alpha = fwhm / (2 sqrt(2^(1/beta) - 1))``
    (Moffat 1969; e.g. Trujillo et al. 2001, MNRAS 328, 977, eq. 8 and 20).
    """
    alpha = fwhm / (2.0 * np.sqrt(2.0 ** (1.0 / beta) - 1.0))
    return 1.0 - (1.0 + (np.asarray(radius_pix, float) / alpha) ** 2) ** (1.0 - beta)


@pytest.fixture(scope="module")
def clean_run(tmp_path_factory):
    """Point and bulge+disk injections on a source-free flat-noise image (3 realizations each)."""
    d = tmp_path_factory.mktemp("clean")
    rng = np.random.default_rng(20240611)
    data = (SKY + rng.normal(0.0, SIGMA, SHAPE)).astype(np.float32)
    header = tan_header(SHAPE, PIXEL_SCALE)
    header["MAGZERO"] = ZP
    path = write_fits_file(d / "clean.fits", data, header)
    # density 40 / arcmin^2 on 7.1 arcmin^2: ~285 injections per realization, ~50 per 0.5-mag bin
    config = load_config(overrides=NOFIT + ["injection.kinds=point,buldisk", "injection.nsims=3", "injection.density=40",
                                    f"injection.mag_range=[{MAG_RANGE[0]},{MAG_RANGE[1]}]",
                                    f"ratios.mag_bin={MAG_BIN}"], seed=8)
    out = d / "run"
    result = run_pipeline(ImageOptions(path=str(path), fwhm=FWHM), config, out, log=_quiet, compute=SERIAL)
    return SimpleNamespace(out=out, result=result, config=config, header=header,
                           summary=json.loads((out / "summary.json").read_text()))


def _bins(summary: dict, kind: str) -> dict:
    b = summary["kinds"][kind]["binned"]
    return {k: (np.array([np.nan if v is None else v for v in vals], float) if isinstance(vals, list) else vals)
            for k, vals in b.items()}


# ---------------------------------------------------------------- known-answer completeness


def test_point_completeness_is_one_far_above_and_zero_far_below_the_noise(clean_run):
    b = _bins(clean_run.summary, "point")
    lo, hi = b["mag_edges"][:-1], b["mag_edges"][1:]
    bright = hi <= _mag_of_snr(100.0)  # whole bin at matched SNR > 100 (about mag < 18.34)
    faint = lo >= _mag_of_snr(0.5)  # whole bin at matched SNR < 0.5 (about mag > 24.09)
    assert bright.sum() >= 2 and faint.sum() >= 2
    assert np.all(b["completeness_n"][bright | faint] >= 20)
    # every bright injection is found; the interval contains the true value 1
    np.testing.assert_array_equal(b["completeness"][bright], 1.0)
    assert np.all(b["completeness_lower"][bright] < 1.0) and np.all(b["completeness_upper"][bright] >= 1.0 - 1e-12)
    # none far below the noise is: a chance noise peak within 1 FWHM and 1.5 mag of the truth is the
    # only way, and the bare image has no detection at all (baseline); the interval contains 0
    np.testing.assert_array_equal(b["completeness"][faint], 0.0)
    assert np.all(b["completeness_lower"][faint] < 1e-12) and np.all(b["completeness_upper"][faint] > 0.0)
    # every interval holds its estimate
    ok = b["completeness_n"] > 0
    assert np.all(b["completeness_lower"][ok] <= b["completeness"][ok] + 1e-12)  # float round-off of k=0
    assert np.all(b["completeness"][ok] <= b["completeness_upper"][ok] + 1e-12)
    # the 50% point lies between matched SNR 12 and 3: a 1.5-sigma-per-pixel threshold on the
    # 3x3-filtered image with 5 connected pixels puts it near SNR 5-6 for this PSF; the wide bracket
    # only catches gross errors (a zero point or flux unit off by > 0.7 mag, a wrong threshold)
    m50 = clean_run.summary["kinds"]["point"]["m50_binned"]
    assert _mag_of_snr(12.0) < m50 < _mag_of_snr(3.0)


def test_bright_isolated_buldisk_completeness_is_one(clean_run):
    b = _bins(clean_run.summary, "buldisk")
    # galaxies of hlr <= 0.75" spread their light over ~10x the PSF's noise area, so SNR > 30 here
    bright = b["mag_edges"][1:] <= _mag_of_snr(100.0)
    assert bright.sum() >= 2 and np.all(b["completeness_n"][bright] >= 20)
    np.testing.assert_array_equal(b["completeness"][bright], 1.0)
    assert np.all(b["completeness_lower"][bright] < 1.0) and np.all(b["completeness_upper"][bright] >= 1.0 - 1e-12)
    # and they are found where they were put: within a third of the PSF FWHM
    t = _read(clean_run.out / "catalogs" / "buldisk_matched.fits")
    sel = (t["mag"] < _mag_of_snr(100.0)) & (t["flag"] == 0)
    assert np.median(t["separation"][sel]) < FWHM / 3


def test_bright_point_source_position_and_mag_auto(clean_run):
    t = _read(clean_run.out / "catalogs" / "point_injected.fits")
    sel = (np.asarray(t["mag"]) < _mag_of_snr(100.0)) & (np.asarray(t["flag"]) == 0)
    assert sel.sum() >= 60
    b = t[sel]
    assert np.all(b["detected"])
    b = b[np.asarray(b["det_flags"]) == 0]
    assert len(b) >= 60
    # Position: the centroid error at SNR > 100 is ~FWHM / (2.35 SNR) < 0.013 px per axis, so a
    # 0.05 px median separation leaves room for noise but not for a convention error (0.5 px,
    # 1 px) between where GalSim draws and where SEP measures.
    assert np.median(b["separation"]) < 0.05
    assert abs(np.median(b["det_xwin"] - b["x"])) < 0.02
    assert abs(np.median(b["det_ywin"] - b["y"])) < 0.02
    # MAG_AUTO: the Kron aperture misses the Moffat wings beyond it.  The aperture of each detection
    # is a circle of radius kron_radius * sqrt(a b) for these round sources; the expected magnitude is
    # mag - 2.5 log10(enclosed fraction) from the Moffat growth curve, and the residual in units of
    # MAGERR_AUTO must be a standard normal.  Tolerances (n ~ 100): |median| < 0.5 (its standard
    # error is 1.25/sqrt(n) ~ 0.13), 0.7 < std < 1.4 (the aperture itself is noisy), none beyond 5.
    merged = merge_realizations(clean_run.out / "sims", "point", range(3))
    det = merged.detections
    row = {(int(r), int(i)): k for k, (r, i) in enumerate(zip(det["realization"], det["id"]))}
    assert len(row) == len(det)  # (realization, id) identifies a detection
    k = np.array([row[(int(r), int(i))] for r, i in zip(b["realization"], b["det_id"])])
    radius = np.asarray(det["kron_radius"])[k] * np.sqrt(np.asarray(det["a"])[k] * np.asarray(det["b"])[k])
    expected = np.asarray(b["mag"]) - 2.5 * np.log10(_moffat_enclosed(radius))
    z = (np.asarray(b["det_mag_auto"]) - expected) / np.asarray(b["det_magerr_auto"])
    assert abs(np.median(z)) < 0.5
    assert 0.7 < np.std(z) < 1.4
    assert np.max(np.abs(z)) < 5.0
    # the loss itself is a few per cent (Kron factor 2.5, minimum radius 3.5): 0.01-0.15 mag
    assert 0.01 < np.median(np.asarray(b["det_mag_auto"]) - np.asarray(b["mag"])) < 0.15


# ---------------------------------------------------------------- summary and outcome table


def test_summary_json_has_the_documented_keys_and_consistent_counts(clean_run):
    s = clean_run.summary
    assert s["format"] == 1
    assert set(s) >= {"format", "image", "depth", "kinds", "failed_realizations"}
    assert s["failed_realizations"] == []
    assert set(s["depth"]) >= {"point_source_5sigma", "aperture_5sigma", "aperture_diameter_pix", "histogram"}
    # the documented 5-sigma depth: SNR 5 of optimal photometry of a *Gaussian* PSF of the image FWHM
    # on the white noise; 0.03 mag allows the few per cent error of the measured noise median
    unit_snr = float(matched_snr(1.0, FWHM, SIGMA, psf="gaussian"))
    assert s["depth"]["point_source_5sigma_gaussian"] == pytest.approx(ZP - 2.5 * np.log10(5.0 / unit_snr), abs=0.03)
    # with the injection PSF (Moffat beta=3), the optimal-photometry depth from its noise-equivalent area
    unit_snr_moffat = float(matched_snr(1.0, FWHM, SIGMA, psf="moffat", beta=3.0))
    assert s["depth"]["point_source_5sigma"] == pytest.approx(ZP - 2.5 * np.log10(5.0 / unit_snr_moffat), abs=0.03)
    assert s["depth"]["noise_median"] == pytest.approx(SIGMA, rel=0.03)
    assert set(s["kinds"]) == {"point", "buldisk"}
    edges = magnitude_edges(MAG_RANGE[0], MAG_RANGE[1], MAG_BIN)
    for kind, entry in s["kinds"].items():
        assert set(entry) >= {"counts", "mag_range", "binned", "m50_binned", "maps"}
        c = entry["counts"]
        assert set(c) == {"realizations", "injected", "usable", "detected", "false", "preexisting", "near_unusable"}
        b = entry["binned"]
        assert set(b) >= {"mag_edges", "mag_centers", "completeness", "completeness_lower", "completeness_upper",
                          "completeness_n", "completeness_k", "purity", "purity_lower", "purity_upper", "purity_n",
                          "purity_k", "detection_rate", "detection_rate_lower", "detection_rate_upper",
                          "confidence", "interval"}
        np.testing.assert_allclose(b["mag_edges"], edges)
        nb = len(edges) - 1
        for key in ("mag_centers", "completeness", "completeness_n", "purity", "purity_n", "detection_rate"):
            assert len(b[key]) == nb, key
        assert set(entry["maps"]) == {"file", "mag_edges", "bin_arcmin"}
        assert (clean_run.out / entry["maps"]["file"]).is_file()
        # counts agree with the catalogs on disk
        injected = _read(clean_run.out / "catalogs" / f"{kind}_injected.fits")
        outcomes = _read(clean_run.out / "catalogs" / f"{kind}_outcomes.fits")
        false = _read(clean_run.out / "catalogs" / f"{kind}_false.fits")
        assert c["realizations"] == 3
        assert c["injected"] == len(injected) and c["usable"] == len(outcomes)
        assert c["detected"] == int(np.sum(outcomes["detected"])) and c["false"] == len(false)
        # every usable injection lies in the magnitude range, so the bins count all of them
        assert sum(b["completeness_n"]) == c["usable"] and sum(b["completeness_k"]) == c["detected"]
        # purity is a fraction of counted detections; none is pre-existing on a clean image
        assert c["preexisting"] == 0
        for k, n, p in zip(b["purity_k"], b["purity_n"], b["purity"]):
            assert 0 <= k <= n and (p is None if n == 0 else 0.0 <= p <= 1.0)
        # bright detections on a clean image are all injections
        bright = np.asarray(edges[1:]) <= _mag_of_snr(100.0)
        assert all(p == 1.0 for p, is_b in zip(b["purity"], bright) if is_b and p is not None)


def test_outcome_table_has_one_row_per_usable_injection(clean_run):
    for kind in ("point", "buldisk"):
        injected = _read(clean_run.out / "catalogs" / f"{kind}_injected.fits")
        out = _read(clean_run.out / "catalogs" / f"{kind}_outcomes.fits")
        assert out.colnames == list(OUTCOME_COLUMNS)
        usable = injected[np.asarray(injected["usable"], bool)]
        assert len(out) == len(usable) > 500
        np.testing.assert_array_equal(out["realization"], usable["realization"])
        np.testing.assert_array_equal(out["injection_id"], usable["injection_id"])
        np.testing.assert_array_equal(out["mag"], usable["mag"])
        det = np.asarray(out["detected"], bool)
        assert 0 < det.sum() < len(out)
        # measured columns are filled exactly for the detected ones
        assert np.all(np.isfinite(out["det_mag_auto"][det])) and np.all(np.isnan(out["det_mag_auto"][~det]))
        assert np.all(np.isfinite(out["separation"][det])) and np.all(np.isnan(out["separation"][~det]))
        assert np.all(out["det_flags"][~det] == -1) and np.all(out["det_flags"][det] >= 0)
        # a match lies within the matching radius (1 FWHM)
        assert np.all(out["separation"][det] <= FWHM + 1e-9)
        # the detection noise at the position is the image's white-noise sigma (background RMS
        # map: few-per-cent estimation error over 64-pixel meshes)
        np.testing.assert_allclose(np.median(out["noise"]), SIGMA, rtol=0.03)
        assert np.all(np.abs(out["noise"] / SIGMA - 1) < 0.1)
        # sizes: NaN for the PSF, inside the configured range for galaxies
        hlr = np.asarray(out["hlr_arcsec"])
        if kind == "point":
            assert np.all(np.isnan(hlr))
        else:
            lo, hi = clean_run.config.injection.hlr_range
            assert np.all((hlr >= lo) & (hlr <= hi))
        # sky positions are the WCS of the pixel positions
        sky = WCS(clean_run.header).all_pix2world(np.c_[out["x"], out["y"]], 0)
        np.testing.assert_allclose(out["ra"], sky[:, 0], atol=1e-9)
        np.testing.assert_allclose(out["dec"], sky[:, 1], atol=1e-9)


# ---------------------------------------------------------------- masked injections and maps

MASKED_SHAPE = (600, 600)
BLOCK = (slice(0, 300), slice(300, 600))  # y < 300 and x >= 300 are bad pixels


@pytest.fixture(scope="module")
def masked_run(tmp_path_factory):
    """A clean image with a dead, masked quarter and a rotated WCS; points only, one realization."""
    d = tmp_path_factory.mktemp("masked")
    rng = np.random.default_rng(77)
    data = (SKY + rng.normal(0.0, SIGMA, MASKED_SHAPE)).astype(np.float32)
    data[BLOCK] = 0.0  # dead pixels: garbage that only the mask keeps out
    header = tan_header(MASKED_SHAPE, PIXEL_SCALE, rotation_deg=25.0)
    header["MAGZERO"] = ZP
    mask = np.zeros(MASKED_SHAPE, np.uint8)
    mask[BLOCK] = 1
    image = write_fits_file(d / "image.fits", data, header)
    mask_path = write_fits_file(d / "mask.fits", mask, header)
    # 60 / arcmin^2 on 4 arcmin^2: ~240 injections, a quarter of them masked; maps of 0.5' = 150 px
    config = load_config(overrides=NOFIT + ["injection.kinds=point", "injection.nsims=1", "injection.density=60",
                                    "injection.min_sep=2.4", "injection.mag_range=[17,25]",
                                    "ratios.map_bin_arcmin=0.5", "ratios.map_mag_edges=[17,21,25]"], seed=21)
    out = d / "run"
    run_pipeline(ImageOptions(path=str(image), mask=str(mask_path), fwhm=FWHM), config, out, log=_quiet,
                 compute=SERIAL)
    return SimpleNamespace(out=out, header=header, summary=json.loads((out / "summary.json").read_text()))


def test_masked_injections_are_excluded(masked_run):
    injected = _read(masked_run.out / "catalogs" / "point_injected.fits")
    outcomes = _read(masked_run.out / "catalogs" / "point_outcomes.fits")
    x, y = np.asarray(injected["x"]), np.asarray(injected["y"])
    ix, iy = np.floor(x + 0.5).astype(int), np.floor(y + 0.5).astype(int)
    in_block = (iy < 300) & (ix >= 300)
    assert 30 <= in_block.sum() <= len(injected) - 100
    np.testing.assert_array_equal(injected["masked"], in_block)
    assert np.all(injected["flag"][in_block] & 1) and not np.any(injected["flag"][~in_block] & 1)
    # usable: centre not masked and drawn whole (flag 2: the stamp runs off the image edge)
    np.testing.assert_array_equal(injected["usable"], ~in_block & (injected["flag"] == 0))
    usable = np.asarray(injected["usable"], bool)
    # absent from the outcome table, absent from the completeness counts
    assert len(outcomes) == usable.sum()
    np.testing.assert_array_equal(outcomes["injection_id"], injected["injection_id"][usable])
    b = masked_run.summary["kinds"]["point"]["binned"]
    counts = masked_run.summary["kinds"]["point"]["counts"]
    assert counts["usable"] == usable.sum() and counts["injected"] == len(injected)
    n_expected, _ = np.histogram(injected["mag"][usable], bins=b["mag_edges"])
    np.testing.assert_array_equal(b["completeness_n"], n_expected)
    # and nothing is detected on the dead pixels
    false = _read(masked_run.out / "catalogs" / "point_false.fits")
    matched = _read(masked_run.out / "catalogs" / "point_matched.fits")
    for t, xc, yc in ((false, "xwin", "ywin"), (matched, "det_xwin", "det_ywin")):
        fx, fy = np.floor(np.asarray(t[xc]) + 0.5), np.floor(np.asarray(t[yc]) + 0.5)
        assert not np.any((fy < 299) & (fx > 300))


def test_maps_carry_a_wcs_matching_the_image_and_the_mask(masked_run):
    entry = masked_run.summary["kinds"]["point"]["maps"]
    with fits.open(masked_run.out / entry["file"]) as hdul:
        names = [h.name for h in hdul[1:]]
        assert names == ["COMPLETENESS", "COMPLETENESS_N", "COMPLETENESS_LO", "COMPLETENESS_HI", "PURITY",
                         "PURITY_N", "MAG_EDGES"]
        hdr = hdul["COMPLETENESS"].header
        comp_n = hdul["COMPLETENESS_N"].data
        comp = hdul["COMPLETENESS"].data
    bpix = hdr["BINPIX"]
    assert bpix == pytest.approx(0.5 * 60 / PIXEL_SCALE)
    assert comp_n.shape == (2, 4, 4)  # (mag planes, y bins, x bins)
    assert [hdr["MAGLO0"], hdr["MAGHI0"], hdr["MAGHI1"]] == [17.0, 21.0, 25.0]
    # bin centres: map pixel (i, j) is the image position ((i + 0.5) b - 0.5, (j + 0.5) b - 0.5)
    mwcs = WCS(hdr, naxis=2)
    iw = WCS(masked_run.header)
    i, j = np.meshgrid(np.arange(4.0), np.arange(4.0))
    i, j = i.ravel(), j.ravel()
    sky_map = mwcs.all_pix2world(np.c_[i, j], 0)
    sky_img = iw.all_pix2world(np.c_[(i + 0.5) * bpix - 0.5, (j + 0.5) * bpix - 0.5], 0)
    np.testing.assert_allclose(sky_map, sky_img, atol=1e-6 / 3600)  # 1 micro-arcsec
    # the masked quarter (y < 300, x >= 300) is the 2x2 block of bins y 0-1, x 2-3: no usable injection
    assert np.all(comp_n[:, :2, 2:] == 0) and np.all(np.isnan(comp[:, :2, 2:]))
    assert np.all(comp_n.sum(axis=0)[2:, :] > 0) and np.all(comp_n.sum(axis=0)[:, :2] > 0)
    # the bright plane is complete wherever it has injections
    bright = comp[0][comp_n[0] > 0]
    np.testing.assert_array_equal(bright, 1.0)


# ---------------------------------------------------------------- executors and resumption

DEMO_OVERRIDES = NOFIT + ["injection.nsims=3", "injection.density=40"]
DEMO_SEED = 11
KINDS = ("point", "buldisk")


def _demo_options(paths) -> ImageOptions:
    return ImageOptions(path=str(paths["image"]), weight=str(paths["weight"]), mask=str(paths["mask"]),
                        mask_bits=MASK_GAP)


def _run_demo(paths, out, compute=SERIAL, log=_quiet):
    config = load_config(overrides=DEMO_OVERRIDES, seed=DEMO_SEED)
    return run_pipeline(_demo_options(paths), config, out, log=log, compute=compute)


@pytest.fixture(scope="module")
def demo_paths(tmp_path_factory):
    d = tmp_path_factory.mktemp("demo")
    tile = make_demo_tile(seed=5, size=640, star_density=6.0)
    return write_demo_tile(tile, d)


@pytest.fixture(scope="module")
def reference(demo_paths, tmp_path_factory):
    """An uninterrupted serial run of the demo tile."""
    out = tmp_path_factory.mktemp("reference") / "run"
    _run_demo(demo_paths, out)
    return out


def _assert_tables_identical(a: Table, b: Table, what: str) -> None:
    assert a.colnames == b.colnames, what
    assert len(a) == len(b), what
    for name in a.colnames:
        x, y = np.asarray(a[name]), np.asarray(b[name])
        assert x.dtype == y.dtype, f"{what}: {name}"
        np.testing.assert_array_equal(x, y, err_msg=f"{what}: column {name}")  # NaN == NaN here


def _assert_same_results(run_a: Path, run_b: Path) -> None:
    for kind in KINDS:
        for name in ("injected", "false", "outcomes"):
            a = _read(run_a / "catalogs" / f"{kind}_{name}.fits")
            b = _read(run_b / "catalogs" / f"{kind}_{name}.fits")
            _assert_tables_identical(a, b, f"{kind}_{name}")
    sa = json.loads((run_a / "summary.json").read_text())
    sb = json.loads((run_b / "summary.json").read_text())
    for kind in KINDS:
        for key in ("counts", "binned", "m50_binned", "mag_range"):
            assert sa["kinds"][kind][key] == sb["kinds"][kind][key], (kind, key)
    assert sb["failed_realizations"] == []


def test_reference_run_is_not_trivial(reference):
    s = json.loads((reference / "summary.json").read_text())
    for kind in KINDS:
        c = s["kinds"][kind]["counts"]
        assert c["realizations"] == 3 and c["usable"] > 500 and 0 < c["detected"] < c["usable"]
        assert sorted(set(_read(reference / "catalogs" / f"{kind}_injected.fits")["realization"])) == [0, 1, 2]


@pytest.mark.slow
@pytest.mark.parametrize("executor", ["processes", "dask"])
def test_executors_give_identical_catalogs(executor, demo_paths, reference, tmp_path):
    if executor == "dask":
        pytest.importorskip("distributed", reason="the Dask executor needs dask.distributed (pip install "
                                                  "'dask[distributed]')")
    out = tmp_path / executor
    _run_demo(demo_paths, out, compute=ComputeOptions(executor=executor, workers=2))
    _assert_same_results(reference, out)


def test_failed_realizations_warn_are_left_out_and_are_retried(demo_paths, reference, tmp_path, monkeypatch):
    real = recovery._run_realization

    def flaky(task):
        if task.kind == "point" and task.index in (0, 2):
            raise RuntimeError(f"simulated failure of {task.kind} #{task.index}")
        return real(task)

    monkeypatch.setattr(recovery, "_run_realization", flaky)
    out = tmp_path / "run"
    lines = []
    _run_demo(demo_paths, out, log=lines.append)
    # a warning per failure, and the run carries on to the summary
    warnings = [s for s in lines if s.startswith("warning: realization point")]
    assert len(warnings) == 2 and all("simulated failure" in s for s in warnings)
    s = json.loads((out / "summary.json").read_text())
    assert s["failed_realizations"] == ["point #0", "point #2"]
    assert s["kinds"]["point"]["counts"]["realizations"] == 1
    assert s["kinds"]["buldisk"]["counts"]["realizations"] == 3
    injected = _read(out / "catalogs" / "point_injected.fits")
    assert set(injected["realization"]) == {1}
    assert not realization_file(out / "sims", "point", 0).exists()
    # the surviving realization is the reference's realization 1
    ref = _read(reference / "catalogs" / "point_injected.fits")
    _assert_tables_identical(injected, ref[ref["realization"] == 1], "point realization 1")

    # rerun without the failure: only the two failed realizations run, and the results are the
    # uninterrupted run's
    monkeypatch.undo()
    lines = []
    _run_demo(demo_paths, out, log=lines.append)
    assert any("2 realizations to run (4 done earlier)" in s for s in lines)
    # no warning but the one every start repeats: the test's 40 per arcmin^2 is 3.1 per background mesh
    warned = [s for s in lines if s.startswith("warning")]
    assert len(warned) == len(KINDS) and all(
        s.startswith(f"warning: density: {k}: 40 per arcmin^2 puts 3.1 injections in each 64x64 background mesh")
        for k, s in zip(KINDS, warned))
    _assert_same_results(reference, out)


def test_deleted_realizations_are_rerun_identically(reference, demo_paths, tmp_path):
    out = tmp_path / "run"
    shutil.copytree(reference, out)
    for kind, index in (("point", 1), ("buldisk", 2)):
        realization_file(out / "sims", kind, index).unlink()
    (out / "summary.json").unlink()
    shutil.rmtree(out / "catalogs")
    lines = []
    _run_demo(demo_paths, out, log=lines.append)
    assert any("2 realizations to run (4 done earlier)" in s for s in lines)
    for kind, index in (("point", 1), ("buldisk", 2)):
        with fits.open(realization_file(out / "sims", kind, index)) as new, \
                fits.open(realization_file(reference / "sims", kind, index)) as old:
            for hdu in ("TRUTH", "DETECTIONS"):
                _assert_tables_identical(Table(new[hdu].data), Table(old[hdu].data), f"{kind} #{index} {hdu}")
    _assert_same_results(reference, out)


@pytest.mark.slow
def test_killed_run_resumes_to_identical_results(reference, demo_paths, tmp_path):
    """SIGKILL a CLI run (two worker processes) once its first realization is written, then resume."""
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "comest_bayes.cli", "run", str(demo_paths["image"]),
           "--weight", str(demo_paths["weight"]), "--mask", str(demo_paths["mask"]), "--mask-bits", str(MASK_GAP),
           "--seed", str(DEMO_SEED), "--ncpu", "2", "--executor", "processes", "--out", str(out), "--quiet"]
    for item in DEMO_OVERRIDES:
        cmd += ["--set", item]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    sims = out / "sims"
    deadline = time.monotonic() + 120
    try:
        while not list(sims.glob("*/r*.fits")):
            if proc.poll() is not None:
                pytest.fail(f"the run ended before it could be killed: {proc.stderr.read().decode()[-2000:]}")
            if time.monotonic() > deadline:
                pytest.fail("no realization was written within 120 s")
            time.sleep(0.01)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)  # the run and its worker processes (its own session)
        proc.wait()
        proc.stderr.close()
    done = len(list(sims.glob("*/r*.fits")))
    assert 1 <= done < 2 * 3, "the kill must land in the middle of the realizations"
    assert not (out / "summary.json").exists()
    lines = []
    _run_demo(demo_paths, out, log=lines.append)
    assert any("resuming" in s for s in lines)
    assert any(f"{6 - done} realizations to run ({done} done earlier)" in s for s in lines)
    _assert_same_results(reference, out)


def test_a_new_run_in_a_recreated_directory_reads_its_own_images(tmp_path):
    """Realization inputs are cached per process; a rewritten file under the same path is read again."""
    config = load_config(overrides=NOFIT + ["injection.kinds=point", "injection.nsims=1", "injection.density=60",
                                    "injection.min_sep=2.4", "injection.mag_range=[17,25]"], seed=4)
    shape = (300, 300)
    header = tan_header(shape, PIXEL_SCALE)
    header["MAGZERO"] = ZP
    images = {}
    for name, sigma in (("quiet", SIGMA), ("noisy", 10 * SIGMA)):
        data = (SKY + np.random.default_rng(5).normal(0.0, sigma, shape)).astype(np.float32)
        images[name] = ImageOptions(path=str(write_fits_file(tmp_path / f"{name}.fits", data, header)), fwhm=FWHM)
    out = tmp_path / "run"
    run_pipeline(images["quiet"], config, out, log=_quiet, compute=SERIAL)
    quiet = _read(out / "catalogs" / "point_injected.fits")
    shutil.rmtree(out)
    run_pipeline(images["noisy"], config, out, log=_quiet, compute=SERIAL)  # same paths, new content
    run_pipeline(images["noisy"], config, tmp_path / "fresh", log=_quiet, compute=SERIAL)
    noisy = _read(out / "catalogs" / "point_injected.fits")
    _assert_tables_identical(noisy, _read(tmp_path / "fresh" / "catalogs" / "point_injected.fits"), "noisy")
    # same seed, same positions and magnitudes, but 10x the noise: 2.5 mag shallower
    np.testing.assert_array_equal(noisy["mag"], quiet["mag"])
    assert noisy["detected"].sum() < quiet["detected"].sum()


# ---------------------------------------------------------------- one realization, directly


def _small_context(tmp_path, *, noise_mode="background", nan_at=None, mask_block=True):
    """A SimContext on a 256^2 flat-noise base image written as the pipeline writes its inputs."""
    from comest_bayes.config import DetectionConfig, InjectionConfig, MatchingConfig
    from comest_bayes.detect.sep_backend import detect_array

    shape = (256, 256)
    rng = np.random.default_rng(31)
    sigma = np.where(np.arange(shape[1])[None, :] < 128, SIGMA, 2 * SIGMA) * np.ones((shape[0], 1))
    base = (SKY + rng.normal(0.0, 1.0, shape) * sigma).astype(np.float32)
    mask = np.zeros(shape, np.uint8)
    if mask_block:
        mask[100:140, 30:90] = 1
        base[mask == 1] = np.nan  # masked pixels may hold anything
    if nan_at is not None:
        base[nan_at] = np.nan
    paths = {name: tmp_path / f"{name}.fits" for name in ("base", "mask", "noise", "baseline")}
    header = tan_header(shape, PIXEL_SCALE)
    base_header = header.copy()
    base_header["BUNIT"] = "adu"  # as the run's sfi.fits carries the image's unit
    fits.PrimaryHDU(base, header=base_header).writeto(paths["base"])
    fits.PrimaryHDU(mask).writeto(paths["mask"])
    fits.PrimaryHDU(sigma.astype(np.float32)).writeto(paths["noise"])
    detection = DetectionConfig(back_size=32)
    clean = np.where(mask == 1, SKY, np.nan_to_num(base, nan=SKY))
    detect_array(clean, mask=mask.astype(bool), zeropoint=ZP, config=detection).catalog.write(paths["baseline"])
    ctx = recovery.SimContext(
        base_path=str(paths["base"]), mask_path=str(paths["mask"]), noise_path=str(paths["noise"]),
        baseline_path=str(paths["baseline"]), detection_path=str(paths["baseline"]), shape=shape,
        wcs_header=WCS(header).to_header().tostring(), zeropoint=ZP, gain=2.0, saturation=None,
        pixel_scale=PIXEL_SCALE, fwhm=FWHM, mag_range=(18.0, 23.0), noise_mode=noise_mode, detection=detection,
        injection=InjectionConfig(kinds=("buldisk",), density=300.0, min_sep=2.0, mag_range=(18.0, 23.0)),
        matching=MatchingConfig(), root_seed=77)
    return ctx, base, mask.astype(bool), sigma.astype(np.float32)


@pytest.mark.parametrize("noise_mode", ["background", "weight"])
def test_a_realization_detects_exactly_as_the_default_detection_path(tmp_path, noise_mode):
    # run_realization re-detects on its private rendered copy with the fast path (no segmentation map,
    # background subtracted in place, no per-realization finiteness check); redoing the realization by
    # hand with the default detect_array must give the same detections.
    from comest_bayes.detect.sep_backend import detect_array
    from comest_bayes.inject.render import make_truth, render_truth
    from comest_bayes.seeding import int_seed_for, rng_for

    ctx, base, mask, sigma = _small_context(tmp_path, noise_mode=noise_mode)
    ctx = dataclasses.replace(ctx, image_dir=str(tmp_path / "images"))  # injection.write_images
    result = recovery.run_realization(recovery.RealizationTask(ctx, "buldisk", 3))
    assert result.error is None, result.error
    truth = make_truth("buldisk", shape=base.shape, mask=mask, pixel_scale=ctx.pixel_scale, fwhm_pix=ctx.fwhm,
                       config=ctx.injection, mag_range=ctx.mag_range, rng=rng_for(ctx.root_seed, "inject", "buldisk", 3),
                       wcs=ctx.wcs, zeropoint=ctx.zeropoint)
    image, _ = render_truth(base, truth, psf=recovery._psf(ctx.injection, ctx.fwhm, ctx.pixel_scale),
                            config=ctx.injection, pixel_scale=ctx.pixel_scale, gain=ctx.gain, zeropoint=ctx.zeropoint,
                            rng_seed=int_seed_for(ctx.root_seed, "render", "buldisk", 3), wcs=ctx.wcs)
    ref = detect_array(image, mask=mask, weight_noise=sigma if noise_mode == "weight" else None,
                       zeropoint=ctx.zeropoint, gain=ctx.gain, wcs=ctx.wcs, config=ctx.detection).catalog
    dets = result.detections
    assert len(truth) > 60 and len(ref) > 40 and dets["matched"].sum() > 30  # premise: a real realization
    assert len(dets) == len(ref)
    for name in ("xwin", "ywin", "flux_auto", "mag_auto", "flux_radius", "noise", "background", "flags"):
        np.testing.assert_allclose(np.asarray(dets[name], float), np.asarray(ref[name], float), rtol=1e-6, atol=0,
                                   equal_nan=True, err_msg=name)
    assert set(result.seconds) == {"make", "render", "image", "detect", "match", "cpu"}
    # the image written for the user is the rendered one, not the background-subtracted work array
    written, header = fits.getdata(tmp_path / "images" / "buldisk" / "image_r00003.fits", header=True)
    np.testing.assert_array_equal(written, image)
    # with the base image's header (WCS, BUNIT, zero point: what the pixels are) and what it holds
    base_header = fits.getheader(ctx.base_path)
    assert header["INJKIND"] == "buldisk" and header["INJREAL"] == 3 and header["BUNIT"] == "adu"
    assert header["CTYPE1"] == "RA---TAN"
    for key in base_header:
        if key not in ("SIMPLE", "BITPIX", "NAXIS", "NAXIS1", "NAXIS2", "EXTEND", "COMMENT", "HISTORY", ""):
            assert header[key] == base_header[key], key


def test_a_base_image_with_nan_in_unmasked_pixels_fails_the_realization_clearly(tmp_path):
    ctx, *_ = _small_context(tmp_path, nan_at=(10, 200))
    result = recovery.run_realization(recovery.RealizationTask(ctx, "buldisk", 0))
    assert result.truth is None and "NaN or infinite values in unmasked pixels" in result.error
    assert "base.fits" in result.error


# ---------------------------------------------------------------- realizations without injections


def test_matching_an_empty_truth_table_makes_every_detection_false(tmp_path):
    # A small field at a low density can draw zero injections; the detections of such a realization
    # (here: noise peaks and sources of an image) must all come out unmatched and false, not crash.
    from comest_bayes.config import InjectionConfig
    from comest_bayes.detect.sep_backend import detect_array
    from comest_bayes.inject.render import make_truth
    from comest_bayes.seeding import rng_for

    ctx, base, mask, sigma = _small_context(tmp_path)
    truth = make_truth("point", shape=base.shape, mask=mask, pixel_scale=ctx.pixel_scale, fwhm_pix=ctx.fwhm,
                       config=InjectionConfig(kinds=("point",), density=1e-6), mag_range=(18.0, 23.0),
                       rng=rng_for(1, "inject", "point", 0), wcs=ctx.wcs, zeropoint=ctx.zeropoint)
    assert len(truth) == 0  # premise: 1e-6 per arcmin^2 on 0.7 arcmin^2 draws nothing with this seed
    sky = make_synthetic_sky(shape=base.shape, seed=3)
    catalog = detect_array(sky.data, zeropoint=ZP).catalog
    assert len(catalog) > 20
    out, dets = recovery.match_realization(truth, catalog, catalog[:0], sigma, ctx)
    assert len(out) == 0 and {"usable", "detected", "separation", "noise", "det_mag_auto"} <= set(out.colnames)
    assert len(dets) == len(catalog)
    assert not dets["matched"].any() and dets["false"].all() and not dets["preexisting"].any()
    assert dets["injection_id"].dtype.kind == "i" and (dets["injection_id"] == -1).all()
    # ... and the pair of tables is a valid realization file, merged as zero outcomes
    out["realization"] = np.zeros(0, np.int32)
    dets["realization"] = np.zeros(len(dets), np.int32)
    recovery.write_realization(recovery.RealizationResult("point", 0, out, dets), tmp_path / "sims")
    merged = merge_realizations(tmp_path / "sims", "point", [0])
    assert len(merged.injected) == len(merged.outcomes) == 0 and len(merged.false) == len(catalog)
    assert list(merged.outcomes.colnames) == list(OUTCOME_COLUMNS)
    # the catalogs written as files are named as in the layout; the detections and timings are no catalog file
    assert [len(merged.table(name)) for name in layout.CATALOGS] == [0, 0, 0, len(catalog), 0]
    with pytest.raises(KeyError, match="no merged catalog 'detections'"):
        merged.table("detections")


def test_realizations_without_injections_are_recorded_and_not_rerun(tmp_path):
    # 2.5 injections per arcmin^2 on a 200x200 image of 0.2" pixels: 1.1 per realization, so a third of
    # the 12 realizations draw none, while the three stars kept on the bright-and-big image are detected
    # in every one of them (pre-existing sources): before the fix, each of those realizations failed with
    # an IndexError, and again on every resume.
    shape = (200, 200)
    header = tan_header(shape, PIXEL_SCALE)
    header["MAGZERO"] = ZP
    stars = render_point_sources(shape, [50.0, 150.0, 100.0], [60.0, 140.0, 100.0], [3e5, 2e5, 1e5], fwhm=FWHM)
    data = (SKY + stars + np.random.default_rng(5).normal(0.0, SIGMA, shape)).astype(np.float32)
    image = ImageOptions(path=str(write_fits_file(tmp_path / "image.fits", data, header)), fwhm=FWHM)
    nsims = 12
    config = load_config(overrides=NOFIT + ["injection.kinds=point", f"injection.nsims={nsims}",
                                            "injection.density=2.5", "injection.mag_range=[18,22]",
                                            "injection.on=bnb", "sourcefree.bnb_area_min=5"], seed=3)
    out = tmp_path / "run"
    lines = []
    result = run_pipeline(image, config, out, log=lines.append, compute=SERIAL)
    assert not any(s.startswith("warning: realization") for s in lines), lines
    assert result.summary["failed_realizations"] == []
    counts = result.summary["kinds"]["point"]["counts"]
    assert counts["realizations"] == nsims and counts["preexisting"] == 3 * nsims
    empty = []
    for i in range(nsims):
        with fits.open(realization_file(out / "sims", "point", i)) as hdul:
            assert len(hdul["DETECTIONS"].data) >= 3  # the kept stars, at least
            if len(hdul["TRUTH"].data) == 0:
                empty.append(i)
    assert 2 <= len(empty) <= nsims - 2  # premise: a mix (with this seed)
    assert any(f"{len(empty)} of {nsims} realizations held no injection" in s for s in lines), lines
    injected = _read(out / "catalogs" / "point_injected.fits")
    assert counts["injected"] == len(injected) and not set(injected["realization"]) & set(empty)
    # a rerun resumes: nothing is left to inject
    lines = []
    run_pipeline(image, config, out, log=lines.append, compute=SERIAL)
    assert any(f"inject: all {nsims} realizations done earlier" in s for s in lines), lines


@pytest.mark.parametrize("noise_mode", ["background", "weight"])
def test_observed_noise_level_thresholds_every_realization_at_the_observed_noise_map(tmp_path, noise_mode):
    # detection.noise_level = "observed": the realization's threshold sigma is the run's noise map
    # (noise.fits, here SIGMA left and 2 SIGMA right) as it is, whatever the injections add to the
    # image's measured RMS.  Every detection's noise is then one of the two levels exactly; re-measured
    # per image ("per_image"), the weight map is rescaled by this image's RMS and the levels move.
    ctx, base, mask, sigma = _small_context(tmp_path, noise_mode=noise_mode)
    levels = np.float32([SIGMA, 2 * SIGMA])
    fixed = dataclasses.replace(ctx, detection=dataclasses.replace(ctx.detection, noise_level="observed"))
    result = recovery.run_realization(recovery.RealizationTask(fixed, "buldisk", 3))
    assert result.error is None, result.error
    noise = np.asarray(result.detections["noise"], np.float32)
    assert len(noise) > 40  # premise: a real realization
    assert np.all(np.isin(noise, levels)), np.unique(noise)[:8]
    per_image = recovery.run_realization(recovery.RealizationTask(ctx, "buldisk", 3))
    moved = np.asarray(per_image.detections["noise"], np.float32)
    assert not np.all(np.isin(moved, levels))  # premise: the per-image level differs from the given one
