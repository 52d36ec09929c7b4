"""The luminosity-function stage on a run directory (comest_bayes.lf.fit.run_lf) and its command line: results,
figures and summary entry on a run made from known truths, bad input refused before any work, the README's
example, and a rendered mock that recovers its power law.
"""

import json
import math

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table

from comest_bayes.errors import ConfigError, InputError, InputFileError
from comest_bayes.lf.model import LFWarning
from comest_bayes.lf.result import LFResult
from comest_bayes.lf.fit import run_lf
from lf_truths import logistic, mock_catalog, synthetic_posterior
from conftest import REPO_ROOT




# --------------------------------------------------------------------------- run directory


@pytest.fixture(scope="module")
def fake_run(tmp_path_factory):
    """A run directory with the files run_lf reads, made from known truths (no image)."""
    d = tmp_path_factory.mktemp("run")
    rng = np.random.default_rng(30)
    post = synthetic_posterior(sd_m50=0.03, sd_logw=0.05)
    (d / "posterior").mkdir()
    post.save(d / "posterior" / "point_completeness.npz")
    (d / "catalogs").mkdir()
    n = 6000
    inj = Table({"mag": rng.uniform(19.0, 26.0, n), "x": rng.uniform(0, 199, n), "y": rng.uniform(0, 199, n)})
    inj["detected"] = rng.random(n) < logistic(np.asarray(inj["mag"]), 23.0, 0.3)
    inj["det_mag_auto"] = np.where(inj["detected"], inj["mag"] + 0.03 + 0.08 * rng.standard_normal(n), np.nan)
    inj.write(d / "catalogs" / "point_outcomes.fits")
    mask = np.zeros((200, 200), np.uint8)
    mask[:, 150:] = 1
    fits.PrimaryHDU(mask).writeto(d / "mask.fits")
    (d / "run.json").write_text(json.dumps({"image": {"pixel_scale_arcsec": 2.0},
                                            "stages": {"baseline": {"mag_range": [19.0, 26.0]}}}))
    (d / "summary.json").write_text(json.dumps({"format": 1, "kinds": {"point": {}}}))
    area_all = (200 * 2.0 / 3600) ** 2
    obs = mock_catalog(rng, area=area_all)
    cat = Table({"mag_auto": obs, "xwin": rng.uniform(0, 199, obs.size), "ywin": rng.uniform(0, 199, obs.size)})
    cat.write(d / "detection.fits")
    return d


def test_run_lf_writes_results_figures_and_summary_entry(fake_run):
    res = run_lf(fake_run, kind="point", model="powerlaw", mode="fixed", mag_range=(20.0, 23.5), seed=4,
                 min_ess=200)
    out = fake_run / "lf" / "point_powerlaw_fixed"
    for name in ("lf_posterior.npz", "lf.json", "counts.png", "corner.png"):
        assert (out / name).is_file(), name
    # only the unmasked three quarters count, objects on masked pixels are dropped
    assert res.area_deg2 == pytest.approx(200 * 150 * (2.0 / 3600) ** 2)
    summary = json.loads((fake_run / "summary.json").read_text())
    assert summary["format"] == 1 and "point" in summary["kinds"]
    entry = summary["lf"]["point_powerlaw_fixed"]
    assert entry["mode"] == "fixed" and entry["n_objects"] == res.n_objects
    s = entry["parameters"]
    # truth within 3 posterior sd (a calibrated posterior fails this ~0.3% of the time per parameter)
    assert abs(s["slope"]["median"] - 0.3) < 3 * s["slope"]["sd"]
    assert abs(s["log_n"]["median"] - 4.3) < 3 * s["log_n"]["sd"]
    # the counts figure's legend lies under both panels, over none of their points
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from comest_bayes.report.plots.lf import counts_figure

    fig = counts_figure(res)
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    renderer = canvas.get_renderer()
    lower = fig.axes[1]
    assert lower.get_legend().get_window_extent(renderer).y1 < lower.get_window_extent(renderer).y0
    assert fig.axes[0].get_legend() is None
    back = LFResult.load(out)
    np.testing.assert_array_equal(back.samples, res.samples)
    np.testing.assert_array_equal(back.transfer.density, res.transfer.density)
    assert back.parameter_summary() == res.parameter_summary()
    from comest_bayes.report.html import lf_figures

    figs = lf_figures(fake_run / "lf")
    assert [t.split(":")[0] for t, _ in figs] == ["Number counts point_powerlaw_fixed"] * 2


@pytest.mark.parametrize("kwargs, error, message", [
    ({"kind": "buldisk"}, InputFileError, "no completeness posterior for kind 'buldisk'"),
    ({"model": "powerlow"}, ConfigError, "Did you mean 'powerlaw'"),
    ({"mode": "exact"}, ConfigError, r"mode \(--mode\) must be one of"),
    ({"mode": "marginal", "ncomp": 0}, ConfigError, "ncomp, the completeness draws of the marginal mode, must be a "
                                                    "positive integer"),
    ({"name": "../../escape"}, ConfigError, r"name \(--name\) is the folder lf/<name> of the run"),
    ({"mag_range": (24.0, 23.0)}, InputError, "LO < HI"),
    ({"mag_range": (30.0, 31.0)}, InputError, "no catalog object has a magnitude in"),
    ({"mag_column": "mag_iso"}, InputError, "has no column 'mag_iso'"),
])
def test_run_lf_bad_input_is_refused_before_any_work(fake_run, kwargs, error, message):
    with pytest.raises(error, match=message):
        run_lf(fake_run, **{"kind": "point", **kwargs})


def test_run_lf_empty_catalog_is_a_clear_error(fake_run, tmp_path):
    empty = tmp_path / "empty.fits"
    Table({"mag_auto": np.zeros(0)}).write(empty)
    with pytest.raises(InputError, match="is empty"):
        run_lf(fake_run, kind="point", catalog=empty)


def test_cli_lf_fits_prints_and_refuses_bad_input_in_one_line(fake_run, capsys):
    from comest_bayes.cli import main

    assert main(["lf", str(fake_run), "--kind", "point", "--mode", "fixed", "--mag-range", "20", "23.5",
                 "--name", "cli_fixed", "--no-report"]) == 0
    out = capsys.readouterr().out
    assert "slope" in out and "cli_fixed done" in out
    entry = json.loads((fake_run / "summary.json").read_text())["lf"]["cli_fixed"]
    assert entry["mode"] == "fixed" and entry["mag_range"] == [20.0, 23.5]
    # a user mistake: one error line, exit status 2, no traceback
    assert main(["lf", str(fake_run), "--model", "powerlow"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and "powerlaw" in err and "Traceback" not in err


def _readme_lf_command():
    """The ``comest-bayes lf ...`` example of the README's luminosity-function section, as an argument list."""
    import re
    import shlex

    text = (REPO_ROOT / "README.md").read_text()
    section = text.split("## Luminosity function", 1)[1].split("\n## ", 1)[0]
    found = re.findall(r"`(comest-bayes lf [^`]+)`", section)
    assert found, "the README's luminosity-function section has no `comest-bayes lf ...` example"
    return shlex.split(found[0])[1:]


def test_readme_lf_example_runs_without_the_faint_limit_warning(fake_run, capsys):
    from comest_bayes.cli import main

    argv = _readme_lf_command()
    assert argv[:2] == ["lf", "comest-demo"]
    # the demo's detections are mostly galaxies: the README counts them with a galaxy kind's completeness
    at = argv.index("--kind")
    assert argv[at + 1] == "buldisk"
    # the README's other options on a run whose completeness is known (m50 = 23, w = 0.3, injected 19-26),
    # of point sources, its only kind
    argv = ["lf", str(fake_run)] + argv[2:at] + ["--kind", "point"] + argv[at + 2:] + ["--name", "readme", "--no-report"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "readme done" in out and "warning" not in out
    entry = json.loads((fake_run / "summary.json").read_text())["lf"]["readme"]
    assert entry["warnings"] == []
    # the default range stops where the completeness falls to 10% (23 + 0.3 ln 9 = 23.66), not below 5%
    assert entry["mag_range"][1] == pytest.approx(23.0 + 0.3 * math.log(9.0), abs=0.03)
    # the range the README used to give reached where the completeness is 0.7%: the tool warns
    with pytest.warns(LFWarning, match="completeness at the faint end") as caught:
        assert main(["lf", str(fake_run), "--mode", "fixed", "--mag-range", "20", "24.5", "--name", "faint",
                     "--no-report"]) == 0
    assert sum("completeness at the faint end" in str(w.message) for w in caught) == 1
    assert "completeness at the faint end" not in capsys.readouterr().out  # said once, as the warning it is


# --------------------------------------------------------------------------- rendered mock

@pytest.mark.slow
def test_rendered_mock_recovers_the_power_law(tmp_path):
    """Point sources drawn from a known power law, rendered, detected; completeness by injection; counts fitted."""
    from comest_bayes.config import load_config
    from comest_bayes.sim.demo import MASK_GAP, make_demo_tile, write_demo_tile
    from comest_bayes.pipeline.stages import ComputeOptions, ImageOptions, run_pipeline

    tile = make_demo_tile(seed=11, size=1000, galaxy_density=0.0, n_saturated_stars=0,
                          star_counts=(2.0e4, 0.3, 23.0))
    paths = write_demo_tile(tile, tmp_path / "tile")
    cfg = load_config(overrides=["injection.nsims=6", "injection.kinds=point", "fit.model=logistic",
                                 "fit.purity_model=none", "fit.min_ess=300", "injection.mag_range=[19.0,26.5]"],
                      seed=1)
    opts = ImageOptions(path=str(paths["image"]), weight=str(paths["weight"]), mask=str(paths["mask"]),
                        mask_bits=MASK_GAP, fwhm=0.9 / 0.26)
    run_pipeline(opts, cfg, tmp_path / "run", log=lambda s: None, compute=ComputeOptions(executor="serial"))
    res = run_lf(tmp_path / "run", kind="point", model="powerlaw", mode="joint", mag_range=(20.0, 24.5), seed=2,
                 min_ess=300)
    s = res.parameter_summary()
    # truth: log10(2e4) = 4.301 and slope 0.3; one seeded realisation: within 3 posterior sd (a calibrated
    # posterior fails this ~0.3% of the time; this seed gave |z| < 1)
    assert abs(s["log_n"]["median"] - math.log10(2.0e4)) < 3 * s["log_n"]["sd"]
    assert abs(s["slope"]["median"] - 0.3) < 3 * s["slope"]["sd"]
    assert res.n_objects > 150


def test_the_lf_seed_is_the_runs_root_seed_unless_one_is_given(fake_run, tmp_path, monkeypatch):
    import shutil

    import comest_bayes.lf.fit as lf_fit

    run = tmp_path / "run"
    shutil.copytree(fake_run, run)
    state = json.loads((run / "run.json").read_text())
    state["fingerprint"] = {"config": {"seed": 17}}
    (run / "run.json").write_text(json.dumps(state))
    seen = []

    class Stop(Exception):
        pass

    def capture(*args, seed, **kwargs):
        seen.append(seed)
        raise Stop

    monkeypatch.setattr(lf_fit, "fit_counts", capture)
    for given in (None, 5):
        with pytest.raises(Stop):
            run_lf(run, kind="point", mode="fixed", mag_range=(20.0, 23.5), seed=given, figures=False)
    assert seen == [17, 5]


def test_objects_off_the_image_or_without_a_magnitude_are_not_counted_and_said(fake_run, tmp_path):
    """A catalog wider than the run's image (a survey's) counted its off-image objects on the image's edge
    pixels and its area: twice the counts for a twice-as-wide catalog, without a word. They are left out now,
    as are non-finite magnitudes, each with a warning; the fit equals the one on the image's own objects.
    The wider catalog comes as CSV with upper-case X, Y (astropy's other readers, SExtractor-like names)."""
    own = Table.read(fake_run / "detection.fits")
    rng = np.random.default_rng(3)
    shifted = own.copy()
    shifted["xwin"] = shifted["xwin"] + 300.0  # the same sky again, beside the 200-pixel image
    blank = own[:25].copy()
    blank["mag_auto"] = np.nan
    blank["xwin"] = rng.uniform(0, 149, len(blank))  # on unmasked pixels: counted, were their magnitudes known
    wide = Table(np.lib.recfunctions.stack_arrays([own.as_array(), shifted.as_array(), blank.as_array()],
                                                  usemask=False, asrecarray=False))
    wide.rename_columns(["xwin", "ywin"], ["X", "Y"])
    wide.write(tmp_path / "wide.csv")
    ref = run_lf(fake_run, kind="point", model="powerlaw", mode="fixed", mag_range=(20.0, 23.5), seed=4,
                 min_ess=200, name="own", figures=False)
    with pytest.warns(LFWarning) as caught:
        got = run_lf(fake_run, kind="point", catalog=tmp_path / "wide.csv", model="powerlaw", mode="fixed",
                     mag_range=(20.0, 23.5), seed=4, min_ess=200, name="wide", figures=False)
    said = [str(w.message) for w in caught]
    assert any(f"{len(own)} of {len(wide)} catalog objects lie outside the run's image" in s for s in said), said
    assert any("25 of" in s and "non-finite mag_auto" in s for s in said), said
    assert got.n_objects == ref.n_objects
    assert got.parameter_summary() == ref.parameter_summary()
    assert any("outside the run's image" in s for s in got.warnings)


def test_objects_without_a_position_are_refused_before_the_fit(fake_run, tmp_path):
    cat = Table.read(fake_run / "detection.fits")
    cat["xwin"][:7] = np.nan
    cat.write(tmp_path / "nanpos.fits")
    with pytest.raises(InputError, match="7 of .* objects have no finite position"):
        run_lf(fake_run, kind="point", catalog=tmp_path / "nanpos.fits", name="nanpos")
    Table.read(fake_run / "detection.fits")[:0].write(tmp_path / "x.fits")
    (tmp_path / "garbage.fits").write_text("not a table\n" * 3)
    with pytest.raises(InputFileError, match=r"cannot be read as a table \(FITS, or a format astropy knows"):
        run_lf(fake_run, kind="point", catalog=tmp_path / "garbage.fits")


def test_a_range_where_almost_nothing_is_detected_is_refused_before_sampling(fake_run):
    # the fake run's completeness is a logistic with m50 23 and w 0.3: 0.018 at 24.2 mag (the catalog reaches 24.6)
    with pytest.raises(InputError, match=r"completeness is below 0.05 over the whole magnitude range 24.20-25.20"):
        run_lf(fake_run, kind="point", mode="joint", mag_range=(24.2, 25.2), name="below_five_percent")
    assert not (fake_run / "lf" / "below_five_percent").exists()
