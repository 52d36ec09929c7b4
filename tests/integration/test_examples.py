"""The example scripts run, with tiny arguments, and produce sensible numbers."""

from __future__ import annotations

import importlib.util
import json

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table
from scipy import ndimage

from conftest import REPO_ROOT


def _load_example(name: str):
    path = REPO_ROOT / "examples" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"example_{name}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def published(tmp_path_factory):
    """The published-workflow example on a 600 px tile, one realization per kind."""
    out = tmp_path_factory.mktemp("published") / "out"
    example = _load_example("published_workflow")
    code = example.main(["--out", str(out), "--size", "600", "--nsims", "1", "--seed", "3", "--density", "40",
                         "--quiet"])
    return out, code


def _summary(out, run: str) -> dict:
    return json.loads((out / run / "summary.json").read_text())


@pytest.mark.slow
def test_published_workflow_writes_both_runs_and_the_table(published, capsys):
    out, code = published
    assert code == 0
    for run, kind in (("buldisk_bnb", "buldisk"), ("point_sfi", "point")):
        s = _summary(out, run)
        assert list(s["kinds"]) == [kind]
        c = s["kinds"][kind]["counts"]
        # 40 / arcmin^2 on the 6.8 arcmin^2 tile less its chip gap: ~250 injections
        assert c["realizations"] == 1 and 150 < c["usable"] < 350
        state = json.loads((out / run / "run.json").read_text())["fingerprint"]["config"]
        assert state["injection"]["on"] == run.split("_")[1]
        assert state["sourcefree"]["bnb_area_min"] == 350
        assert state["injection"]["bulge_fraction_range"] == [0.5, 0.9]
    # the seeing is given as published (0.9"), in pixels of the 0.26"/px tile
    image = _summary(out, "point_sfi")["image"]
    assert image["fwhm_pix"] == pytest.approx(0.9 / 0.26, rel=1e-3)
    # the table on disk holds a row per magnitude bin of each kind
    text = (out / "table.txt").read_text()
    assert "buldisk on the BnB" in text and "point on the SFI" in text
    for run, kind in (("buldisk_bnb", "buldisk"), ("point_sfi", "point")):
        nbins = len(_summary(out, run)["kinds"][kind]["binned"]["mag_centers"])
        block = text.split(f"{kind} on the")[1].split("\n\n")[0].strip().splitlines()
        assert len(block) == 2 + nbins


@pytest.mark.slow
def test_published_workflow_numbers_are_sensible(published):
    out, _ = published
    for run, kind in (("buldisk_bnb", "buldisk"), ("point_sfi", "point")):
        b = _summary(out, run)["kinds"][kind]["binned"]
        for name in ("completeness", "purity"):
            for r, lo, hi, n, k in zip(b[name], b[f"{name}_lower"], b[f"{name}_upper"], b[f"{name}_n"],
                                       b[f"{name}_k"]):
                if n == 0:
                    assert r is None
                else:
                    assert 0 <= k <= n and r == pytest.approx(k / n)
                    eps = 1e-12  # float round-off of the interval ends at k = 0 and k = n
                    assert -eps <= lo <= r + eps and r - eps <= hi <= 1.0 + eps
        # faintest bin: far below the 5-sigma depth (m5 + 1.5 at the end of the automatic range)
        assert b["completeness"][-1] < 0.2

    # Point sources on the source-free image: nothing to blend with, so every injection at least
    # 1 mag brighter than the 5-sigma depth of the tile's noisiest part is found (SNR > 12 there).
    s = _summary(out, "point_sfi")
    m5 = s["depth"]["point_source_5sigma"]
    b = s["kinds"]["point"]["binned"]
    edges = np.asarray(b["mag_edges"])
    bright = edges[1:] <= m5 - 1.5  # the tile's noise sigma varies by a factor of ~2 (0.75 mag)
    assert bright.sum() >= 3
    np.testing.assert_array_equal(np.asarray(b["completeness"])[bright], 1.0)
    # Bright detections are injections, except where a source centred in the masked chip gap (left
    # out of completeness, but drawn) spills light over the gap's edge: that detection misses the
    # 1.5 mag tolerance (part of its flux is masked) and counts as false.  So every bright false
    # detection must sit within 2 FWHM of a masked pixel.
    run = out / "point_sfi"
    fwhm = s["image"]["fwhm_pix"]
    near_mask = ndimage.distance_transform_edt(fits.getdata(run / "mask.fits") == 0) <= 2 * fwhm
    false = Table.read(run / "catalogs" / "point_false.fits", mask_invalid=False)
    false = false[np.asarray(false["mag_auto"]) < m5 - 1.5]
    fx = np.floor(np.asarray(false["xwin"]) + 0.5).astype(int)
    fy = np.floor(np.asarray(false["ywin"]) + 0.5).astype(int)
    assert np.all(near_mask[fy, fx])
    m50 = s["kinds"]["point"]["m50_binned"]
    assert m5 - 1.5 < m50 < m5 + 1.0
    assert 0.0 < s["kinds"]["point"]["m50_binned_sd"] < 0.2  # the spread of its first crossing, mag

    # Bulge+disk galaxies on the BnB image: bright ones are lost only where a kept bright-and-big
    # source sits (pixels where the BnB image differs from the SFI, grown by 1 FWHM).  "Bright" is
    # 3 mag above the point-source depth: a galaxy of half-light radius up to 0.75" spreads its light
    # over several times the PSF's noise area, costing up to ~1.5 mag of SNR against a point source.
    run = out / "buldisk_bnb"
    kept = fits.getdata(run / "bnb.fits") != fits.getdata(run / "sfi.fits")
    assert kept.any()
    fwhm = _summary(out, "buldisk_bnb")["image"]["fwhm_pix"]
    near_kept = ndimage.distance_transform_edt(~kept) <= fwhm
    t = Table.read(run / "catalogs" / "buldisk_outcomes.fits", mask_invalid=False)
    ix = np.clip(np.floor(np.asarray(t["x"]) + 0.5).astype(int), 0, kept.shape[1] - 1)
    iy = np.clip(np.floor(np.asarray(t["y"]) + 0.5).astype(int), 0, kept.shape[0] - 1)
    bright = np.asarray(t["mag"]) < m5 - 3.0
    free = bright & ~near_kept[iy, ix]
    assert free.sum() >= 30
    assert np.all(np.asarray(t["detected"])[free])
