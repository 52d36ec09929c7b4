"""Adaptive injection through the pipeline: batches, recorded designs, resume, and what it leaves unchanged."""

import json

import numpy as np
import pytest
from astropy.table import Table

from comest_bayes.config import load_config
from comest_bayes.sim.demo import MASK_GAP, make_demo_tile, write_demo_tile
from comest_bayes.pipeline.stages import ComputeOptions, ImageOptions, run_pipeline

PILOT = 2


@pytest.fixture(scope="module")
def tile(tmp_path_factory):
    d = tmp_path_factory.mktemp("adaptive_tile")
    return write_demo_tile(make_demo_tile(seed=5, size=700, star_density=6.0), d)


def _options(paths):
    return ImageOptions(path=str(paths["image"]), weight=str(paths["weight"]), mask=str(paths["mask"]),
                        mask_bits=MASK_GAP)


def _config(*extra):
    # the logistic model keeps each refit to a second; the point kind alone keeps the run small
    return load_config(overrides=["injection.kinds=point", "fit.model=logistic", "fit.purity_model=none",
                                  f"adaptive.pilot_nsims={PILOT}", "adaptive.max_nsims=6", *extra], seed=7)


@pytest.fixture(scope="module")
def adaptive_run(tile, tmp_path_factory):
    out = tmp_path_factory.mktemp("adaptive") / "run"
    lines = []
    run_pipeline(_options(tile), _config("adaptive.precision=0.02"), out, log=lines.append,
                 compute=ComputeOptions(executor="serial", progress=False))
    return out, lines


def test_batches_are_designed_recorded_and_summarised(adaptive_run):
    out, lines = adaptive_run
    summary = json.loads((out / "summary.json").read_text())
    ad = summary["adaptive"]["kinds"]["point"]
    batches = ad["batches"]
    assert batches[0]["design"] == "uniform" and batches[0]["realizations"] == [0, PILOT]
    assert all(b["design"] == "m50" for b in batches[1:])
    # batches follow one another without gaps, within the cap, and every design was written before its batch
    ends = [b["realizations"][1] for b in batches]
    assert all(b["realizations"][0] == e for b, e in zip(batches[1:], ends))
    assert ad["realizations"] == ends[-1] <= 6
    for k in range(len(batches)):
        assert (out / "designs" / f"point_batch{k}.json").is_file()
    # either the precision was reached on the last batch, or the cap stopped it, and the summary says which
    assert ad["reached"] == (batches[-1]["halfwidth"] <= 0.02)
    assert ("precision reached" if ad["reached"] else "NOT reached") in "\n".join(lines)
    # the interval the run reports (the fit stage's) is recorded next to the design's, and compared with the target
    m50 = summary["kinds"]["point"]["model"]["m50"]
    rep = ad["reported"]
    assert rep["model"] == summary["kinds"]["point"]["model"]["name"] == "logistic"
    assert rep["m50_halfwidth"] == pytest.approx(0.5 * (m50["hi68"] - m50["lo68"]))
    assert rep["meets_target"] == (rep["m50_halfwidth"] <= 0.02)
    assert (ad["reached"] and not rep["meets_target"]) == any("the reported fit" in line for line in lines)
    # the merged catalogs hold every realization of every batch
    injected = Table.read(out / "catalogs" / "point_injected.fits")
    assert sorted(set(np.asarray(injected["realization"]).tolist())) == list(range(ad["realizations"]))


def test_adaptive_batches_put_their_injections_near_m50(adaptive_run):
    out, _ = adaptive_run
    summary = json.loads((out / "summary.json").read_text())
    if len(summary["adaptive"]["kinds"]["point"]["batches"]) < 2:
        pytest.skip("the pilot alone reached the precision")
    m50 = summary["kinds"]["point"]["m50_binned"]
    t = Table.read(out / "catalogs" / "point_injected.fits")
    near = np.abs(np.asarray(t["mag"]) - m50) < 0.6
    pilot = np.asarray(t["realization"]) < PILOT
    # uniform over a ~6.5 mag range puts ~18% within 0.6 mag of m50; the design (85% on the gain, which sits
    # within a few widths of m50) must put at least twice that fraction there
    assert near[~pilot].mean() > 2 * near[pilot].mean()


def test_a_rerun_resumes_without_new_injections_and_the_same_numbers(adaptive_run, tile):
    out, _ = adaptive_run
    before = json.loads((out / "summary.json").read_text())
    lines = []
    run_pipeline(_options(tile), _config("adaptive.precision=0.02"), out, log=lines.append,
                 compute=ComputeOptions(executor="serial", progress=False))
    after = json.loads((out / "summary.json").read_text())
    assert after["adaptive"] == before["adaptive"]
    assert after["kinds"]["point"]["m50_binned"] == before["kinds"]["point"]["m50_binned"]
    assert not any(line.startswith("inject:") and "to run" in line for line in lines)
    n = before["adaptive"]["kinds"]["point"]["realizations"]
    assert any(line.startswith("inject:") and line.endswith(f"({n} done earlier)") for line in lines), lines


def test_the_pilot_is_the_published_design_and_the_transfer_does_not_depend_on_the_design(adaptive_run, tile,
                                                                                           tmp_path):
    out, _ = adaptive_run
    uniform = tmp_path / "uniform"
    run_pipeline(_options(tile), _config(f"injection.nsims={PILOT}"), uniform, log=lambda s: None,
                 compute=ComputeOptions(executor="serial", progress=False))
    a = Table.read(out / "catalogs" / "point_injected.fits")
    u = Table.read(uniform / "catalogs" / "point_injected.fits")
    pilot = np.asarray(a["realization"]) < PILOT
    # same seed: the pilot realizations are the uniform run's, draw for draw
    np.testing.assert_array_equal(np.asarray(a["mag"])[pilot], np.asarray(u["mag"]))
    # the photometric transfer is conditional on the true magnitude: among matched bright injections
    # (true mag < m50 - 0.5, SNR high), the median of measured - true is the same in the pilot and in the designed
    # batches, within 4 standard errors of the difference (1.25 sigma / sqrt(n) each)
    m = Table.read(out / "catalogs" / "point_matched.fits")
    m50 = json.loads((out / "summary.json").read_text())["kinds"]["point"]["m50_binned"]
    true = np.asarray(m["mag"])
    d = np.asarray(m["det_mag_auto"], float) - true
    sel = (true < m50 - 0.5) & np.isfinite(d)
    pil = np.asarray(m["realization"]) < PILOT
    a_, b_ = d[sel & pil], d[sel & ~pil]
    if min(a_.size, b_.size) < 15:
        pytest.skip("too few bright matched injections in one of the groups")
    se = 1.25 * np.hypot(np.std(a_) / np.sqrt(a_.size), np.std(b_) / np.sqrt(b_.size))
    assert abs(np.median(a_) - np.median(b_)) < 4 * se + 0.005


def test_the_report_charts_precision_against_injections(adaptive_run):
    from comest_bayes.report.html import write_report

    out, _ = adaptive_run
    html = write_report(out).read_text()
    assert 'id="adaptive"' in html and "68% half-width" in html
    assert (out / "figures" / "adaptive_precision.png").is_file()
    ad = json.loads((out / "summary.json").read_text())["adaptive"]["kinds"]["point"]
    assert ("precision reached" if ad["reached"] else "precision NOT reached") in html
    assert f"the fit reported above (logistic) has an m50 68% half-width of {ad['reported']['m50_halfwidth']:.4f}" in html


def test_info_tells_how_the_adaptive_injection_ended(adaptive_run, capsys):
    from comest_bayes.cli import main

    out, _ = adaptive_run
    assert main(["info", str(out)]) == 0
    text = capsys.readouterr().out
    ad = json.loads((out / "summary.json").read_text())["adaptive"]["kinds"]["point"]
    assert "adaptive injection: target m50 half-width 0.02" in text
    assert f"point: {'reached' if ad['reached'] else 'NOT reached'} in {len(ad['batches'])} batches" in text
    assert f"reported fit logistic: m50 half-width {ad['reported']['m50_halfwidth']:.4f}" in text
    # found by a new user: a finished adaptive run read as incomplete (its unused nsims as the whole)
    n = ad["realizations"]
    assert "adaptive batches of at most 6 realizations per kind" in text and "realizations per kind; " in text
    assert f"realizations on disk: point {n} (adaptive; at most 6 per kind)" in text
    assert json.loads((out / "summary.json").read_text())["adaptive"]["max_nsims"] == 6



def _noisy(real):
    """A realization that warns: alike in every realization (logged once), and of its own in designed batches."""
    import warnings

    def noisy(task):
        warnings.warn("stamp of injection 7 clipped at the image edge", UserWarning)
        if task.design is not None:
            warnings.warn(f"designed realization {task.index} drew no magnitude above the range", UserWarning)
        return real(task)

    return noisy


@pytest.fixture(scope="module")
def f_run(tile, tmp_path_factory):
    """An adaptive run aimed at f at 23.5 and 24.0 mag (a target it cannot reach in 3 realizations), whose
    realizations warn."""
    import comest_bayes.recover.realization as recovery

    out = tmp_path_factory.mktemp("adaptive_f") / "run"
    lines = []
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(recovery, "_run_realization", _noisy(recovery._run_realization))
        run_pipeline(_options(tile), _config("adaptive.precision=0.001", "adaptive.max_nsims=3", "adaptive.target=f",
                                             "adaptive.magnitudes=[23.5, 24.0]"),
                     out, log=lines.append, compute=ComputeOptions(executor="serial", progress=False))
    return out, lines


def test_the_workers_warnings_reach_the_log_once_each(f_run):
    _, lines = f_run
    said = [s for s in lines if s.startswith("warning: realization point")]
    assert said == ["warning: realization point #0 (adaptive batch 0): stamp of injection 7 clipped at the image edge",
                    "warning: realization point #2 (adaptive batch 1): designed realization 2 drew no magnitude "
                    "above the range"], said


def test_the_f_target_is_designed_recorded_reported_and_shown(f_run, capsys):
    from comest_bayes.cli import main
    from comest_bayes.report.html import write_report

    out, lines = f_run
    ad = json.loads((out / "summary.json").read_text())["adaptive"]
    assert ad["target"] == "f" and ad["magnitudes"] == [23.5, 24.0] and ad["precision"] == 0.001
    point = ad["kinds"]["point"]
    assert [b["design"] for b in point["batches"]] == ["uniform", "f"]
    assert json.loads((out / "designs" / "point_batch1.json").read_text())["target"] == "f"
    for b in point["batches"]:
        # f at 23.5 mag (above m50 ~ 23.95) is higher than at 24.0, both are probabilities, and their sds are
        # positive and above the unreachable target
        assert len(b["f"]) == len(b["f_sd"]) == 2 and 1 > b["f"][0] > b["f"][1] > 0
        assert all(0.001 < v < 0.5 for v in b["f_sd"])
    assert not point["reached"] and "sd of f at 23.50, 24.00" in point["reason"]
    assert any("until the posterior sd of f at 23.50, 24.00 mag is <= 0.001" in s for s in lines)
    assert main(["info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "adaptive injection: target sd of f 0.001 at 23.50, 24.00 mag" in text
    last = point["batches"][-1]["f_sd"]
    assert "point: NOT reached in 2 batches, 3 realizations" in text and f"(sd of f {last[0]:.4f}, {last[1]:.4f})" in text
    html = write_report(out).read_text()
    assert "largest posterior sd of the image-average f at 23.50, 24.00 mag" in html
    assert "sd of f at 23.50, 24.00" in html and (out / "figures" / "adaptive_precision.png").is_file()


def test_f_target_magnitudes_outside_the_injected_range_are_refused_before_anything_is_written(tile, tmp_path):
    # found by a new user: the check ran in the adaptive stage, after the run had written its first stages, and
    # the corrected command was then refused as another run in the same folder
    from comest_bayes.errors import ConfigError

    out = tmp_path / "run"
    with pytest.raises(ConfigError, match=r"adaptive.magnitudes \[30.0\] \(--precision-at\) must lie inside"):
        run_pipeline(_options(tile), _config("adaptive.precision=0.01", "adaptive.target=f", "adaptive.magnitudes=30"),
                     out, log=lambda s: None, compute=ComputeOptions(executor="serial", progress=False))
    assert not out.exists() or not any(out.iterdir())


def test_adaptive_settings_without_a_precision_or_with_an_infinite_one_are_refused():
    from comest_bayes.api import config_from_options
    from comest_bayes.errors import ConfigError

    with pytest.raises(ConfigError, match=r"--precision-at given without --precision \(adaptive.precision\)"):
        config_from_options(precision_at=[23.5])
    with pytest.raises(ConfigError, match=r"--max-nsims given without --precision"):
        config_from_options(max_nsims=5)
    with pytest.raises(ConfigError, match=r"invalid adaptive.precision = inf"):
        config_from_options(precision=float("inf"))
    assert config_from_options(precision=0.02, max_nsims=5).adaptive.max_nsims == 5


def test_precision_at_on_the_command_line_sets_the_f_target():
    from comest_bayes import cli

    args = cli.build_parser().parse_args(["run", "image.fits", "--out", "o", "--precision", "0.02",
                                          "--precision-at", "23.5,24"])
    ad = cli._config_from_args(args).adaptive
    assert (ad.target, ad.magnitudes, ad.precision) == ("f", (23.5, 24.0), 0.02)


def test_a_reported_interval_wider_than_the_target_is_recorded_and_logged():
    """The batches stop on the design fits; the fit stage's own model may give a wider interval, and the
    summary and the log say so (and stay quiet when it is within the target, or the target is on f)."""
    from comest_bayes.pipeline.stages import _adaptive_reported

    def summary(target="m50"):
        return {"precision": 0.01, "target": target, "kinds": {"point": {"reached": True},
                                                               "buldisk": {"reached": True}}}
    kinds = {"point": {"model": {"name": "logistic", "m50": {"lo68": 24.990, "hi68": 25.014}}},
             "buldisk": {"model": {"name": "spline_depth", "m50": {"lo68": 24.500, "hi68": 24.518}}}}
    lines = []
    ad = summary()
    _adaptive_reported(ad, kinds, lines.append)
    assert ad["kinds"]["point"]["reported"] == {"model": "logistic", "m50_halfwidth": pytest.approx(0.012),
                                                "meets_target": False}
    assert ad["kinds"]["buldisk"]["reported"]["meets_target"] is True
    assert len(lines) == 1 and "point" in lines[0] and "0.0120" in lines[0]
    # a kind whose design did not reach the target already says so: its wider reported interval is recorded, not logged
    lines = []
    ad = summary()
    ad["kinds"]["point"]["reached"] = False
    _adaptive_reported(ad, kinds, lines.append)
    assert ad["kinds"]["point"]["reported"]["meets_target"] is False and not lines
    # a target on f: the half-width is recorded, not judged
    lines = []
    ad = summary("f")
    _adaptive_reported(ad, kinds, lines.append)
    assert ad["kinds"]["point"]["reported"]["meets_target"] is None and not lines
    # a kind without a model fit (fit.model = none): nothing to compare
    ad = summary()
    _adaptive_reported(ad, {"point": {}, "buldisk": {}}, lines.append)
    assert ad["kinds"]["point"]["reported"] == {"model": None, "m50_halfwidth": None, "meets_target": None}
