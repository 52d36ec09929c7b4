"""End to end: the CLI and the pipeline on small synthetic images."""

import json

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table

from comest_bayes.cli import main
from comest_bayes.config import load_config as _load_config
from comest_bayes.sim.demo import MASK_GAP, make_demo_tile, write_demo_tile
from comest_bayes.pipeline.stages import ImageOptions, run_pipeline


@pytest.fixture(scope="module")
def small_tile(tmp_path_factory):
    """A 700x700 demo tile written to disk (image, weight, mask, truth)."""
    d = tmp_path_factory.mktemp("tile")
    tile = make_demo_tile(seed=3, size=700, star_density=6.0)
    paths = write_demo_tile(tile, d)
    return tile, paths


def load_config(**kw):
    """Two realizations per kind keep these end-to-end tests fast."""
    return _load_config(overrides=["injection.nsims=2", "fit.model=none", "fit.purity_model=none"], **kw)


def _options(paths, **kw):
    return ImageOptions(path=str(paths["image"]), weight=str(paths["weight"]), mask=str(paths["mask"]),
                        mask_bits=MASK_GAP, **kw)


def test_pipeline_writes_every_product_with_the_input_wcs(small_tile, tmp_path):
    tile, paths = small_tile
    out = tmp_path / "run"
    result = run_pipeline(_options(paths), load_config(seed=5), out, log=lambda s: None)
    for name in ("detection.fits", "segmentation.fits", "background.fits", "rms.fits", "noise.fits",
                 "sfi.fits", "bnb.fits", "run.json"):
        assert (out / name).is_file(), name
    state = json.loads((out / "run.json").read_text())
    assert state["fingerprint"]["config"]["seed"] == 5
    assert state["fingerprint"]["config"]["detection"]["thresh"] == 1.5
    assert state["versions"]["sep"]
    assert set(state["stages"]) >= {"detect", "fwhm", "sourcefree"}
    # the image facts and where each came from
    facts = state["image"]
    assert facts["zeropoint"] == tile.header["MAGZERO"]
    assert facts["provenance"]["zeropoint"] == "image header MAGZERO"
    assert facts["pixel_scale_arcsec"] == pytest.approx(0.26, rel=1e-3)
    # the measured seeing is the demo's 0.9" within the 10% the FWHM estimator promises
    assert facts["fwhm_pix"] * 0.26 == pytest.approx(0.9, rel=0.10)
    assert "Moffat" in facts["provenance"]["fwhm"]
    # outputs carry the input WCS: same sky position for the same pixel
    from astropy.wcs import WCS

    w_in = WCS(tile.header)
    w_out = WCS(fits.getheader(out / "sfi.fits"))
    np.testing.assert_allclose(w_out.all_pix2world([[10.0, 500.0]], 0), w_in.all_pix2world([[10.0, 500.0]], 0),
                               atol=1e-9)
    # the detections are real: bright isolated stars of the truth are found
    cat = result.detection.catalog
    stars = tile.truth[(tile.truth["kind"] == "star") & (tile.truth["mag"] < 22) & ~tile.truth["saturated"]]
    d = np.hypot(cat["xwin"][None, :] - np.asarray(stars["x"])[:, None],
                 cat["ywin"][None, :] - np.asarray(stars["y"])[:, None]).min(axis=1)
    assert len(stars) >= 3 and np.median(d) < 0.3


def test_rerun_resumes_without_redoing_stages(small_tile, tmp_path):
    _, paths = small_tile
    out = tmp_path / "run"
    run_pipeline(_options(paths), load_config(), out, log=lambda s: None)
    sfi_before = (out / "sfi.fits").stat().st_mtime_ns
    lines = []
    result = run_pipeline(_options(paths), load_config(), out, log=lines.append)
    assert result.resumed
    assert any("detect: done earlier" in s for s in lines)
    assert any("sourcefree: done earlier" in s for s in lines)
    assert (out / "sfi.fits").stat().st_mtime_ns == sfi_before


def _crash_writing_sfi(monkeypatch):
    """The run dies as it writes sfi.fits (the source-free image is built and judged before anything is written)."""
    from comest_bayes.io.rundir import RunDirectory

    write_image = RunDirectory.write_image

    def boom(self, name, *a, **k):
        if name == "sfi.fits":
            raise RuntimeError("simulated crash")
        return write_image(self, name, *a, **k)

    monkeypatch.setattr(RunDirectory, "write_image", boom)


def test_crash_after_detection_resumes_from_the_next_stage(small_tile, tmp_path, monkeypatch):
    _, paths = small_tile
    out = tmp_path / "run"
    _crash_writing_sfi(monkeypatch)
    with pytest.raises(RuntimeError, match="simulated crash"):
        run_pipeline(_options(paths), load_config(), out, log=lambda s: None)
    assert (out / "detection.fits").exists() and not (out / "sfi.fits").exists()
    assert not list(out.glob(".tmp-*"))
    monkeypatch.undo()
    lines = []
    run_pipeline(_options(paths), load_config(), out, log=lines.append)
    assert any("detect: done earlier" in s for s in lines)
    assert (out / "sfi.fits").exists()


def test_same_seed_gives_identical_source_free_image(small_tile, tmp_path):
    _, paths = small_tile
    a = run_pipeline(_options(paths), load_config(seed=1), tmp_path / "a", log=lambda s: None)
    b = run_pipeline(_options(paths), load_config(seed=1), tmp_path / "b", log=lambda s: None)
    c = run_pipeline(_options(paths), load_config(seed=2), tmp_path / "c", log=lambda s: None)
    sa, sb, sc = (fits.getdata(r.out_dir / "sfi.fits") for r in (a, b, c))
    np.testing.assert_array_equal(sa, sb)
    assert not np.array_equal(sa, sc)


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--zp", "nan"], "zp=nan must be a finite number"),
        (["--weight", "missing.fits"], "weight file 'missing.fits' does not exist"),
        (["--set", "detection.thres=2"], "Did you mean 'detection.thresh'"),
        (["--set", "detection.back_filtersize=2"], "back_filtersize"),
        (["--pixel-scale", "-1"], "pixel_scale=-1.0 must be a positive"),
    ],
)
def test_cli_bad_input_gives_one_error_line_and_writes_nothing(small_tile, tmp_path, capsys, extra, message):
    _, paths = small_tile
    out = tmp_path / "never"
    code = main(["run", str(paths["image"]), "--out", str(out), *extra])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("error: ") and message in err
    assert "Traceback" not in err
    assert not out.exists()


def test_cli_shape_mismatch_is_reported_before_any_output(small_tile, tmp_path, capsys):
    _, paths = small_tile
    wrong = tmp_path / "w.fits"
    fits.PrimaryHDU(np.ones((10, 20), np.float32)).writeto(wrong)
    out = tmp_path / "never"
    assert main(["run", str(paths["image"]), "--weight", str(wrong), "--out", str(out)]) == 2
    assert "has shape (10, 20) but the image" in capsys.readouterr().err
    assert not out.exists()


def test_cli_debug_shows_the_traceback(small_tile, tmp_path):
    _, paths = small_tile
    from comest_bayes.errors import InputError

    with pytest.raises(InputError):
        main(["run", str(paths["image"]), "--zp", "nan", "--out", str(tmp_path / "x"), "--debug"])


def test_cli_run_refuses_a_directory_with_another_run(small_tile, tmp_path, capsys):
    _, paths = small_tile
    out = tmp_path / "run"
    args = ["run", str(paths["image"]), "--weight", str(paths["weight"]), "--out", str(out), "--quiet",
            "--nsims", "1", "--model", "none", "--set", "fit.purity_model=none"]
    assert main(args) == 0
    before = (out / "run.json").read_text()
    assert main(args + ["--thresh", "3"]) == 2
    assert "holds a different run" in capsys.readouterr().err
    assert (out / "run.json").read_text() == before


@pytest.mark.slow
def test_cli_demo_small_runs_every_stage_and_resumes(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--size", "1000", "--seed", "4", "--nsims", "2",
                 "--model", "none", "--set", "fit.purity_model=none"]) == 0
    printed = capsys.readouterr().out
    assert "detect:" in printed and "sourcefree:" in printed
    assert (out / "inputs" / "demo_image.fits").exists() and (out / "sfi.fits").exists()
    assert main(["demo", "--out", str(out), "--size", "1000", "--seed", "4", "--nsims", "2",
                 "--model", "none", "--set", "fit.purity_model=none"]) == 0
    assert "resuming" in capsys.readouterr().out
    # another seed in the same directory is refused
    assert main(["demo", "--out", str(out), "--size", "1000", "--seed", "5", "--nsims", "2",
                 "--model", "none", "--set", "fit.purity_model=none"]) == 2


def test_the_same_image_by_another_path_resumes_and_the_lock_is_released(synthetic_fits, tmp_path, monkeypatch,
                                                                           capsys):
    image = synthetic_fits("good.fits", fwhm=3.0)
    (tmp_path / "in").mkdir()
    image.path.rename(tmp_path / "in" / "good.fits")
    monkeypatch.chdir(tmp_path)
    common = ["--out", "run", "--fwhm", "3", "--density", "100", "--nsims", "1", "--kinds", "point", "--model", "none",
              "--set", "fit.purity_model=none", "--no-report", "--executor", "serial"]
    assert main(["run", "./in/good.fits", *common]) == 0
    assert not (tmp_path / "run" / "run.lock").exists()
    capsys.readouterr()
    assert main(["run", str(tmp_path / "in" / "good.fits"), *common]) == 0
    printed = capsys.readouterr().out
    assert "resuming" in printed and "detect: done earlier" in printed
    state = json.loads((tmp_path / "run" / "run.json").read_text())
    assert state["fingerprint"]["input"]["options"]["path"] == "good.fits"  # content and name, not the path
    assert not (tmp_path / "run" / "run.lock").exists()
    # the same file moved to another folder is the same input
    (tmp_path / "moved").mkdir()
    (tmp_path / "in" / "good.fits").rename(tmp_path / "moved" / "good.fits")
    capsys.readouterr()
    assert main(["run", "moved/good.fits", *common]) == 0
    assert "detect: done earlier" in capsys.readouterr().out


def test_a_failed_run_releases_its_lock(small_tile, tmp_path, monkeypatch):
    _, paths = small_tile
    out = tmp_path / "run"
    _crash_writing_sfi(monkeypatch)
    with pytest.raises(RuntimeError, match="simulated crash"):
        run_pipeline(_options(paths), load_config(), out, log=lambda s: None)
    assert (out / "run.json").exists() and not (out / "run.lock").exists()


def test_cli_demo_at_a_small_size_runs(tmp_path, capsys):
    # 512 px hold too few stars to measure the seeing: the demo uses the seeing it drew the tile with
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--size", "512", "--nsims", "2", "--kinds", "point", "--model", "none",
                 "--set", "fit.purity_model=none", "--no-report", "--executor", "serial"]) == 0
    printed = capsys.readouterr().out
    assert "fwhm: 3.46 px = 0.90 arcsec" in printed
    summary = json.loads((out / "summary.json").read_text())
    assert summary["kinds"]["point"]["counts"]["usable"] > 50
    assert not (out / "run.lock").exists()


def test_observed_noise_and_background_levels_are_recorded_and_used(small_tile, tmp_path):
    # detection.noise_level / background_level = "observed" and matching.exclude_clean_zone: run.json
    # records them, and every re-detection of an injected image used the observed noise map as it is
    # (each detection's noise is a value of noise.fits; re-measured per image, the weight map would
    # be rescaled and no value would be).
    _, paths = small_tile
    out = tmp_path / "run"
    config = _load_config(overrides=["injection.nsims=2", "fit.model=none", "fit.purity_model=none",
                                     "injection.kinds=buldisk", "detection.noise_level=observed",
                                     "detection.background_level=observed", "matching.exclude_clean_zone=true"])
    run_pipeline(_options(paths), config, out, log=lambda s: None)
    recorded = json.loads((out / "run.json").read_text())["fingerprint"]["config"]
    assert recorded["detection"]["noise_level"] == "observed"
    assert recorded["detection"]["background_level"] == "observed"
    assert recorded["matching"]["exclude_clean_zone"] is True
    noise = fits.getdata(out / "noise.fits").astype(np.float32)
    from comest_bayes.io import layout
    from comest_bayes.recover.realization import realization_file

    dets = Table.read(realization_file(out / layout.SIMS_DIR, "buldisk", 0), hdu="DETECTIONS")
    assert len(dets) > 20
    assert np.all(np.isin(np.asarray(dets["noise"], np.float32), noise))
    back = fits.getdata(out / "background.fits").astype(np.float32)
    assert np.all(np.isin(np.asarray(dets["background"], np.float32), back))
    # the clean zone left some injections out (flag 8), and only those beside the masked ones
    injected = Table.read(out / "catalogs" / "buldisk_injected.fits")
    zone = (np.asarray(injected["flag"]) & 8) != 0
    assert zone.any() and not np.any(np.asarray(injected["usable"])[zone])
