"""The fits around the numerics (comest_bayes.pipeline.fits): the fit stage's worker task reading a run
directory, and ``comest-bayes fit`` on an outcome table with known truth (the CLI itself: tests/test_cli.py)."""

import json

import numpy as np
import pytest
from astropy.table import Table

from comest_bayes.config import load_config
from comest_bayes.io import layout
from comest_bayes.errors import InputError
from comest_bayes.pipeline.fits import OUTCOME_COLUMNS, fit_outcome_file, fit_task, noise_at_positions


def _logistic_outcomes(n=3000, seed=3, m50=24.0, w=0.25):
    rng = np.random.default_rng(seed)
    mag = rng.uniform(21.0, 27.0, n)
    return Table({"mag": mag, "detected": rng.uniform(size=n) < 1.0 / (1.0 + np.exp((mag - m50) / w)),
                  "x": rng.uniform(0, 199, n), "y": rng.uniform(0, 99, n), "noise": np.ones(n)})


def test_an_outcome_file_is_fitted_and_every_product_is_written(tmp_path):
    path = tmp_path / "outcomes.fits"
    _logistic_outcomes().write(path)
    assert set(OUTCOME_COLUMNS) == {"mag", "detected", "x", "y", "noise"}
    summary = fit_outcome_file(path, tmp_path / "out", kind="stars", model="logistic", image_shape=(100, 200),
                               noise_map=None, mask=None, seed=1)
    entry = summary["kinds"]["stars"]["model"]
    # truth 24.0; 3000 outcomes on a 0.25-mag logistic give a posterior sd of ~0.012 mag: within 4 sd
    sd = 0.5 * (entry["m50"]["hi68"] - entry["m50"]["lo68"])
    assert 0.004 < sd < 0.03 and abs(entry["m50"]["median"] - 24.0) < 4 * sd
    out = tmp_path / "out"
    assert json.loads((out / layout.SUMMARY).read_text())["kinds"]["stars"]["model"]["name"] == "logistic"
    assert (out / layout.posterior("stars")).is_file() and entry["posterior_file"] == layout.posterior("stars")
    assert (out / layout.FIGURES_DIR / "stars_completeness.png").is_file()
    binned = summary["kinds"]["stars"]["completeness"]
    assert sum(binned["n"]) == 3000
    # the published binned m50 and its spread, as a run's summary.json has them: 3000 injections over
    # 6 mag in 0.1-mag bins give ~50 per bin and a binned m50 within ~0.05 mag of the truth
    m50_binned, m50_binned_sd = summary["kinds"]["stars"]["m50_binned"], summary["kinds"]["stars"]["m50_binned_sd"]
    assert 0.005 < m50_binned_sd < 0.1 and abs(m50_binned - 24.0) < 4 * m50_binned_sd


def test_the_noise_map_is_read_at_each_position_as_a_run_records_it():
    """Nearest pixel (floor(x + 0.5)), NaN for a non-finite position, and a clear error for a position
    outside the map (a 1-based catalogue, say) instead of a clipped, wrong noise."""
    noise = np.arange(12.0).reshape(3, 4)  # noise[iy, ix] = 4 iy + ix
    got = noise_at_positions(noise, [0.0, 0.49, 0.51, 3.4, np.nan, -0.5], [0.0, 1.2, 1.6, 2.49, 1.0, 0.0], what="t")
    assert np.array_equal(got[[0, 1, 2, 3, 5]], [0.0, 4.0, 9.0, 11.0, 0.0]) and np.isnan(got[4])
    with pytest.raises(InputError, match=r"1 of 2 positions lie outside the noise map \(3 x 4 pixels.*X_IMAGE"):
        noise_at_positions(noise, [1.0, 3.6], [1.0, 1.0], what="t")


def _depth_gradient_outcomes(n=6000, seed=2):
    """A logistic of width 0.2 whose m50 follows the depth of a noise map rising 2.5x across the image."""
    rng = np.random.default_rng(seed)
    xx = np.mgrid[0:60, 0:80][1]
    noise = (1.0 + 1.5 * xx / 80.0).astype(np.float32)
    mag = rng.uniform(21.0, 27.0, n)
    x, y = rng.uniform(0, 79, n), rng.uniform(0, 59, n)
    sig = noise[np.floor(y + 0.5).astype(int), np.floor(x + 0.5).astype(int)]
    det = rng.uniform(size=n) < 1.0 / (1.0 + np.exp((mag - (24.0 - 2.5 * np.log10(sig))) / 0.2))
    return Table({"mag": mag, "detected": det, "x": x, "y": y}), sig, noise


def test_with_positions_and_a_noise_map_the_noise_column_is_read_from_the_map(tmp_path):
    """Balrog-like outcomes (positions, no noise) with the image's noise map fit exactly as the same table
    with the noise column a run would have written: same depth covariate, same posterior."""
    from astropy.io import fits as afits

    table, sig, noise = _depth_gradient_outcomes()
    afits.writeto(tmp_path / "noise.fits", noise)
    table.write(tmp_path / "nonoise.fits")
    with_noise = table.copy()
    with_noise["noise"] = sig
    with_noise.write(tmp_path / "noise_col.fits")
    logs = []
    a = fit_outcome_file(tmp_path / "nonoise.fits", tmp_path / "a", model="logistic_depth",
                         noise_map=tmp_path / "noise.fits", seed=4, log=logs.append)
    b = fit_outcome_file(tmp_path / "noise_col.fits", tmp_path / "b", model="logistic_depth",
                         noise_map=tmp_path / "noise.fits", seed=4)
    ma, mb = a["kinds"]["injections"]["model"], b["kinds"]["injections"]["model"]
    assert ma["m50"] == mb["m50"] and ma["parameters"] == mb["parameters"]
    assert any("read from the noise map at its position" in line for line in logs)
    # the depth slope is measured, not the prior's: m50 moves by -2.5 log10(sigma) (slope -1 per unit of
    # the depth covariate d = -2.5 log10(sigma / sigma_ref), i.e. +1 per magnitude of depth)
    beta = ma["parameters"]["beta_depth"]
    sd = 0.5 * (beta["hi68"] - beta["lo68"])
    assert abs(beta["median"] - 1.0) < 4 * sd and sd < 0.1


def test_without_any_noise_the_depth_terms_are_inert_and_not_a_warning(tmp_path, recwarn):
    """No noise column and no noise map: a depth rung's depth is 0 for every injection and footprint pixel,
    so it changes nothing; the fit says so once in its log and warns about nothing."""
    table, _, _ = _depth_gradient_outcomes(n=3000)
    table.remove_columns(["x", "y"])
    table.write(tmp_path / "magonly.fits")
    logs = []
    summary = fit_outcome_file(tmp_path / "magonly.fits", tmp_path / "out", model="logistic_depth", seed=1,
                               log=logs.append)
    entry = summary["kinds"]["injections"]["model"]
    assert not [str(w.message) for w in recwarn if "depth" in str(w.message)]
    assert not [w for w in entry["warnings"] if "depth" in w]
    assert sum("depth terms are inert" in line for line in logs) == 1


def test_the_worker_task_skips_a_purity_fit_with_too_few_false_detections(tmp_path):
    # a run directory holding only what the purity task reads: matched pairs and 3 false detections
    (tmp_path / layout.CATALOG_DIR).mkdir()
    rng = np.random.default_rng(0)
    Table({"det_mag_auto": rng.uniform(20, 25, 40), "det_xwin": rng.uniform(0, 99, 40),
           "det_ywin": rng.uniform(0, 99, 40)}).write(tmp_path / layout.catalog("point", "matched"))
    Table({"mag_auto": [24.0, 24.5, 25.0], "xwin": [1.0, 2.0, 3.0],
           "ywin": [1.0, 2.0, 3.0]}).write(tmp_path / layout.catalog("point", "false"))
    post, entry = fit_task({"run_dir": str(tmp_path), "kind": "point", "quantity": "purity", "requested": "purity",
                            "config": load_config(), "image_shape": (100, 100), "wcs_header": None,
                            "mag_range": (20.0, 25.0), "mag_centers": np.arange(20.05, 25.0, 0.1)})
    assert post is None and entry.name is None
    assert entry.to_dict() == {"name": None, "requested": "purity", "cpu_seconds": 0.0, "skipped": entry.skipped}
    assert entry.skipped.startswith("40 real and 3 false detections: a purity model needs at least 25 of each")


def test_a_map_that_is_no_image_is_refused(tmp_path):
    path = tmp_path / "outcomes.fits"
    _logistic_outcomes(200).write(path)
    Table({"a": [1.0]}).write(tmp_path / "table.fits")
    with pytest.raises(Exception, match="holds no 2-D image HDU"):
        fit_outcome_file(path, tmp_path / "out", model="logistic", noise_map=tmp_path / "table.fits",
                         image_shape=(100, 200))


def test_fit_tasks_returns_the_fits_before_a_failure_with_it(monkeypatch):
    from comest_bayes.pipeline import fits as fitting

    def fake(task):
        if task == "bad":
            raise ValueError("this fit fails")
        return task.upper()

    monkeypatch.setattr(fitting, "fit_task", fake)
    assert fitting.fit_tasks(["a", "b"]) == ["A", "B"]
    out = fitting.fit_tasks(["a", "bad", "c"])  # the one after the failure is not run
    assert out[0] == "A" and len(out) == 2 and isinstance(out[1], fitting.FitFailure)
    assert "this fit fails" in str(out[1].exc) and "Traceback" in out[1].exc.__notes__[0]


def test_an_escalated_width_selection_in_a_run_averages_over_the_noise_map(tmp_path, monkeypatch):
    # Regression: the fit stage hands the workers the footprint cells of the requested selection
    # (depth only) and no noise map; a selection escalated to a positional width then built its
    # position-resolved cells without the map, which put every pixel at the reference depth and moved
    # the image-average m50 (by 0.034 mag on a 2048^2 run).  The task must give the same posterior as
    # a fit handed the noise map itself.
    from comest_bayes.bayes import fit as bfit
    from comest_bayes.bayes.fit import fit_kind, shared_maps
    from astropy.io import fits

    shape = (96, 128)
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    noise = (1.0 + 1.5 * xx / shape[1]).astype(np.float32)  # 0.9 mag of depth across the image
    mask = np.zeros(shape, bool)
    mask[:, 60:64] = True  # a chip gap
    rng = np.random.default_rng(11)
    n = 4000
    x, y = rng.uniform(0, shape[1] - 1, n), rng.uniform(0, shape[0] - 1, n)
    sig = noise[y.astype(int), x.astype(int)].astype(float)
    mag = rng.uniform(22.0, 27.0, n)
    m50 = 24.5 - 2.5 * np.log10(sig / np.median(sig))
    p = 0.97 / (1.0 + np.exp((mag - m50) / 0.3))
    table = Table({"mag": mag, "detected": rng.uniform(size=n) < p, "x": x, "y": y, "noise": sig})
    (tmp_path / layout.CATALOG_DIR).mkdir()
    table.write(tmp_path / layout.catalog("point", "outcomes"))
    fits.writeto(tmp_path / layout.NOISE, noise)
    fits.writeto(tmp_path / layout.MASK, mask.astype(np.uint8))
    spec = tmp_path / "select.toml"
    spec.write_text('name = "select"\ndescription = "test"\ncandidates = ["logistic_depth"]\n'
                    'width_candidates = ["logistic_depth_width_uv"]\n')
    monkeypatch.setattr(bfit, "WIDTH_TEST_P", 1.01)  # every width test escalates
    config = load_config()
    edges = np.arange(22.0, 27.01, 0.1)
    common = dict(kind="point", quantity="completeness", requested=str(spec), config=config, image_shape=shape,
                  wcs_header=None, mag_range=(22.0, 27.0), mag_centers=0.5 * (edges[:-1] + edges[1:]))
    maps = shared_maps(noise, mask, [str(spec)])
    assert bfit.footprint_grid(True) not in maps["footprints"]  # the run does not pay for position upfront
    post, entry = fit_task({"run_dir": str(tmp_path), "shared_maps": maps, **common})
    ref_post, ref_entry = fit_kind(table, noise=noise, mask=mask, **common)
    assert entry.selection["width_test"]["escalated"]
    assert entry.name == ref_entry.name
    # the same outcomes, cells and seed: the same numbers
    assert entry.magnitudes["m50"]["median"] == pytest.approx(ref_entry.magnitudes["m50"]["median"], abs=1e-9)
    # and a fit without the map refuses rather than averaging at the reference depth (fresh maps: a fit
    # keeps the histograms it computes in the dict it was handed)
    fresh = shared_maps(noise, mask, [str(spec)])
    with pytest.raises(Exception, match="needs the footprint cells"):
        fit_kind(table, noise=None, mask=mask, footprints=fresh["footprints"], noise_grid=fresh["noise_grid"],
                 **common)


def test_a_fit_reads_the_noise_map_only_when_it_must():
    # fit_kind takes the noise map as a loader and calls it only for footprint cells or a noise grid it is
    # not handed: a run's fits that get the shared maps never read noise.fits, a fit without them reads it once
    from comest_bayes.bayes.fit import fit_kind, shared_maps

    shape = (100, 200)
    noise_map, mask = np.ones(shape, np.float32), np.zeros(shape, bool)
    calls = []

    def loader():
        calls.append(1)
        return noise_map

    edges = np.arange(21.0, 27.01, 0.1)
    common = dict(kind="point", quantity="completeness", requested="logistic", config=load_config(),
                  image_shape=shape, wcs_header=None, mag_range=(21.0, 27.0),
                  mag_centers=0.5 * (edges[:-1] + edges[1:]), mask=mask)
    maps = shared_maps(noise_map, mask, ["logistic"])
    _, given = fit_kind(_logistic_outcomes(600), noise=loader, footprints=maps["footprints"],
                        noise_grid=maps["noise_grid"], **common)
    assert calls == []
    _, read = fit_kind(_logistic_outcomes(600), noise=loader, **common)
    assert calls == [1]  # the histogram and the grid share one read
    assert given.magnitudes["m50"]["median"] == read.magnitudes["m50"]["median"]


def test_masked_entries_are_missing_values_not_their_fill(tmp_path):
    """A masked magnitude is dropped like a NaN one (with the warning that counts them), not read as its fill
    value 0.0; a masked outcome is refused by name instead of being read as its fill value."""
    from astropy.table import MaskedColumn

    table = _logistic_outcomes(n=2000, seed=5)
    hidden = np.arange(2000) < 300
    table["mag"] = MaskedColumn(np.where(hidden, 0.0, table["mag"]), mask=hidden)
    table.write(tmp_path / "masked_mag.ecsv")
    with pytest.warns(UserWarning, match="dropped 300 of 2000 outcome rows"):
        summary = fit_outcome_file(tmp_path / "masked_mag.ecsv", tmp_path / "a", model="logistic",
                                   image_shape=(100, 200), seed=1)
    binned = summary["kinds"]["injections"]["completeness"]
    assert sum(binned["n"]) == 1700 and binned["edges"][0] >= 21.0  # no bin at 0 mag
    det = _logistic_outcomes(n=500, seed=6)
    det["detected"] = MaskedColumn(det["detected"].astype(np.int16), mask=np.arange(500) < 7)
    det.write(tmp_path / "masked_det.fits")
    with pytest.raises(InputError, match="'detected' has 7 masked \\(missing\\) entries of 500"):
        fit_outcome_file(tmp_path / "masked_det.fits", tmp_path / "b", model="logistic", image_shape=(100, 200))
    assert not (tmp_path / "b").exists()


def test_the_python_api_keeps_the_mask_of_a_boolean_outcome():
    import comest_bayes as cb

    table = _logistic_outcomes(n=500, seed=7)
    table["detected"] = np.ma.MaskedArray(np.asarray(table["detected"]), mask=np.arange(500) < 3)
    with pytest.raises(InputError, match="3 masked"):
        cb.fit_completeness(table, model="logistic", image_shape=(100, 200))


def test_outcomes_written_as_the_words_true_and_false_are_read(tmp_path):
    from comest_bayes.bayes.outcomes import outcome_flags

    assert outcome_flags(np.array(["True", "false", " TRUE "])).tolist() == [True, False, True]
    with pytest.raises(InputError, match="boolean, 0/1 or the words True/False.*'yes'"):
        outcome_flags(np.array(["yes", "no"]))


@pytest.mark.parametrize("mags, message", [
    (np.full(50, np.nan), "none of its 50 magnitudes .* is a finite number"),
    (np.full(50, 24.0), "all 50 finite magnitudes equal 24"),
    (np.array([24.0]), "all 1 finite magnitudes equal 24"),
])
def test_tables_with_no_magnitude_range_are_refused_before_anything_is_written(tmp_path, mags, message):
    Table({"mag": mags, "detected": np.arange(mags.size) % 2 == 0}).write(tmp_path / "t.fits")
    with pytest.raises(InputError, match=message):
        fit_outcome_file(tmp_path / "t.fits", tmp_path / "out")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.fits"]


@pytest.mark.parametrize("kind", ["../escaped", "a b/c", "", ".hidden"])
def test_a_kind_that_is_no_plain_name_is_refused(tmp_path, kind):
    _logistic_outcomes(n=200).write(tmp_path / "t.fits")
    with pytest.raises(InputError, match="kind \\(--kind\\) names the files"):
        fit_outcome_file(tmp_path / "t.fits", tmp_path / "out" / "o", kind=kind)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.fits"]


def _two_depth_scene(n=4000, seed=8):
    """Left half 1 mag deeper than the right; a logistic (w 0.15) whose m50 follows the depth."""
    rng = np.random.default_rng(seed)
    noise = np.ones((40, 60), np.float32)
    noise[:, 30:] = 10 ** 0.4
    x, y, mag = rng.uniform(0, 59, n), rng.uniform(0, 39, n), rng.uniform(21.0, 26.0, n)
    sig = noise[np.floor(y + 0.5).astype(int), np.floor(x + 0.5).astype(int)]
    det = rng.uniform(size=n) < 1.0 / (1.0 + np.exp((mag - (24.0 - 2.5 * np.log10(sig))) / 0.15))
    return Table({"mag": mag, "detected": det, "x": x, "y": y, "noise": sig}), noise


def test_unusable_noise_map_pixels_are_masked_not_averaged_at_the_reference_depth(tmp_path):
    """NaN and zero pixels of a noise map are no footprint: the fit equals the one with those pixels masked
    explicitly (same outcomes left out, same image average), and it says so. Before, they counted at the
    reference depth and moved the image-average m50 by ~10 posterior sd without a word."""
    from astropy.io import fits as afits

    table, noise = _two_depth_scene()
    table.remove_column("noise")
    table.write(tmp_path / "t.fits")
    holed = noise.copy()
    holed[:, 40:52] = np.nan
    holed[5:15, 0:10] = 0.0
    afits.writeto(tmp_path / "holed.fits", holed)
    afits.writeto(tmp_path / "noise.fits", noise)
    mask = (~(np.isfinite(holed) & (holed > 0))).astype(np.uint8)
    afits.writeto(tmp_path / "mask.fits", mask)
    with pytest.warns(UserWarning, match=f"{int(mask.sum())} pixels of the noise map are NaN, infinite or <= 0"):
        a = fit_outcome_file(tmp_path / "t.fits", tmp_path / "a", model="logistic_depth", seed=2,
                             noise_map=tmp_path / "holed.fits")
    with pytest.warns(UserWarning, match="injections lie on masked pixels"):
        b = fit_outcome_file(tmp_path / "t.fits", tmp_path / "b", model="logistic_depth", seed=2,
                             noise_map=tmp_path / "noise.fits", mask=tmp_path / "mask.fits")
    ma, mb = a["kinds"]["injections"]["model"], b["kinds"]["injections"]["model"]
    assert ma["m50"] == mb["m50"] and ma["n_outcomes"] == mb["n_outcomes"] < len(table)


def test_a_mask_applies_when_the_noise_comes_from_the_table(tmp_path):
    """--mask with a noise column and no noise map: the injections on masked pixels are left out of the fit
    and of the footprint the injections sample (as a run never counts them); before, the mask was ignored."""
    from astropy.io import fits as afits

    table, noise = _two_depth_scene(seed=9)
    mask = np.zeros(noise.shape, np.uint8)
    mask[:, 35:] = 1  # most of the shallow half
    afits.writeto(tmp_path / "mask.fits", mask)
    table.write(tmp_path / "all.fits")
    keep = mask[np.floor(table["y"] + 0.5).astype(int), np.floor(table["x"] + 0.5).astype(int)] == 0
    table[keep].write(tmp_path / "kept.fits")
    with pytest.warns(UserWarning, match=f"{int((~keep).sum())} of {len(table)} injections lie on masked pixels"):
        a = fit_outcome_file(tmp_path / "all.fits", tmp_path / "a", model="logistic_depth", seed=3,
                             mask=tmp_path / "mask.fits")
    b = fit_outcome_file(tmp_path / "kept.fits", tmp_path / "b", model="logistic_depth", seed=3,
                         image_shape=noise.shape)
    ma, mb = a["kinds"]["injections"]["model"], b["kinds"]["injections"]["model"]
    assert ma["footprint"] == mb["footprint"] == "injections"
    assert ma["m50"] == mb["m50"]


def test_a_folder_filled_while_the_fit_ran_is_not_overwritten(tmp_path, monkeypatch):
    """The fit writes a hidden sibling folder and renames it onto --out: a second fit that filled the same
    new folder first keeps its files, this one is refused, and no staging folder is left behind."""
    import comest_bayes.pipeline.fits as F

    _logistic_outcomes(n=500).write(tmp_path / "t.fits")
    out = tmp_path / "runs" / "out"
    real = F.save_figure

    def racing(fig, path):
        real(fig, path)
        out.mkdir(parents=True, exist_ok=True)
        (out / "summary.json").write_text("{\"other\": true}\n")

    monkeypatch.setattr(F, "save_figure", racing)
    with pytest.raises(InputError, match="filled by another process while this fit ran; nothing was overwritten"):
        fit_outcome_file(tmp_path / "t.fits", out, model="logistic", image_shape=(100, 200))
    assert json.loads((out / "summary.json").read_text()) == {"other": True}
    assert sorted(p.name for p in out.parent.iterdir()) == ["out"]


def test_a_posterior_fitted_without_positions_refuses_positional_queries(tmp_path):
    table = _logistic_outcomes(n=1500)
    table.remove_columns(["x", "y", "noise"])
    table.write(tmp_path / "t.fits")
    fit_outcome_file(tmp_path / "t.fits", tmp_path / "out", model="logistic", seed=1)
    from comest_bayes.bayes.posterior import CompletenessPosterior

    post = CompletenessPosterior.load(tmp_path / "out" / layout.posterior("injections"))
    assert post.completeness(24.0).shape == (post.samples.shape[0],)
    with pytest.raises(InputError, match="fitted to outcomes without positions"):
        post.completeness(24.0, x=10.0, y=10.0)
    with pytest.raises(InputError, match="fitted to outcomes without positions"):
        post.m50_map()


def test_rows_repeated_exactly_are_warned_about(tmp_path):
    from astropy.table import vstack

    table = _logistic_outcomes(n=600, seed=11)
    vstack([table, table[:40]]).write(tmp_path / "t.fits")
    with pytest.warns(UserWarning, match="40 of 640 rows repeat another row's magnitude and position exactly"):
        fit_outcome_file(tmp_path / "t.fits", tmp_path / "out", model="logistic", image_shape=(100, 200))
