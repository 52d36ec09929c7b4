"""The command line: every subcommand's --help, and `comest-bayes fit` on outcome tables from elsewhere."""

import json

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table

from comest_bayes.sim import synthetic as S
from comest_bayes.cli import build_parser, main

SUBCOMMANDS = ("run", "demo", "report", "lf", "fit", "info")


def test_every_subcommand_has_a_help_that_prints(capsys):
    parser = build_parser()
    choices = parser._subparsers._group_actions[0].choices
    # the list is the parser's own: a new subcommand is covered here, or this fails
    assert set(choices) == set(SUBCOMMANDS)
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    top = capsys.readouterr().out
    assert top.startswith("usage: comest-bayes")
    for name in SUBCOMMANDS:
        assert name in top
        with pytest.raises(SystemExit) as exc:
            main([name, "--help"])
        assert exc.value.code == 0
        captured = capsys.readouterr()
        out = captured.out
        assert out.startswith("usage: comest-bayes " + name) and len(out) > 200 and not captured.err
        # every option of the subcommand is listed with its help text (a bare % in a help string crashed lf)
        for action in choices[name]._actions:
            for flag in action.option_strings:
                assert flag in out, (name, flag)
            if action.option_strings and action.help:
                first = action.help.split("%")[0].split()[:3]
                assert " ".join(first) in " ".join(out.split()), (name, action.option_strings, first)


@pytest.fixture(scope="module")
def outcome_files(tmp_path_factory):
    """A skewed truth (outside every logistic rung) on a small scene, written as a foreign pipeline would."""
    root = tmp_path_factory.mktemp("foreign")
    scene = S.make_scene((160, 200), seed=3)
    truth = S.get_truth("skew_faint")
    table = S.draw_outcomes(truth, scene, 12000, seed=4)
    foreign = Table({"TRUE_MAG": table["mag"], "FOUND": table["detected"].astype(np.int16),
                     "XIMAGE": table["x"], "YIMAGE": table["y"], "SKYRMS": table["noise"]})
    foreign.write(root / "balrog_like.fits")
    fits.writeto(root / "noise.fits", scene.noise.astype(np.float32))
    fits.writeto(root / "mask.fits", scene.mask.astype(np.uint8))
    return root, S.truth_quantities(truth, scene)


def test_fit_runs_the_selection_on_a_foreign_outcome_table(outcome_files, tmp_path):
    root, truth = outcome_files
    out = tmp_path / "fit"
    argv = ["fit", str(root / "balrog_like.fits"), "--out", str(out), "--kind", "stars", "--mag-column", "TRUE_MAG",
            "--detected-column", "FOUND", "--x-column", "XIMAGE", "--y-column", "YIMAGE", "--noise-column", "SKYRMS",
            "--noise-map", str(root / "noise.fits"), "--mask", str(root / "mask.fits"), "--quiet"]
    assert main(argv) == 0
    summary = json.loads((out / "summary.json").read_text())
    entry = summary["kinds"]["stars"]["model"]
    assert entry["footprint"] == "maps" and (out / entry["posterior_file"]).is_file()
    assert (out / "figures" / "stars_completeness.png").is_file()
    assert sum(summary["kinds"]["stars"]["completeness"]["n"]) == 12000
    # the truth's image-average m50 lies within 3 posterior sd (a seeded draw: measured 0.3 sd)
    m50 = entry["m50"]
    sd = 0.5 * (m50["hi68"] - m50["lo68"])
    assert abs(m50["median"] - truth["m50"]) < 3 * sd
    # a second run into the same folder is refused, and nothing in it changes
    before = (out / "summary.json").read_bytes()
    assert main(argv) == 2
    assert (out / "summary.json").read_bytes() == before


def test_fit_names_a_missing_column_before_writing_anything(outcome_files, tmp_path, capsys):
    root, _ = outcome_files
    out = tmp_path / "never"
    assert main(["fit", str(root / "balrog_like.fits"), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "no column(s) ['mag', 'detected']" in err and "TRUE_MAG" in err and "--mag-column" in err
    assert not out.exists()
    assert main(["fit", str(root / "nothing.fits"), "--out", str(out)]) == 2
    assert "does not exist" in capsys.readouterr().err and not out.exists()
    assert main(["fit", str(root / "balrog_like.fits"), "--out", str(out), "--mag-column", "TRUE_MAG",
                 "--detected-column", "FOUND", "--image-shape", "12"]) == 2
    assert "NY,NX" in capsys.readouterr().err and not out.exists()


def test_fit_without_maps_averages_over_the_injections_own_footprint(outcome_files, tmp_path):
    # no noise map: the injections (uniform over the unmasked pixels) sample the footprint, so the image average
    # is their own average; the truth's m50 must still lie within 3 posterior sd (measured well inside)
    root, truth = outcome_files
    out = tmp_path / "nomaps"
    assert main(["fit", str(root / "balrog_like.fits"), "--out", str(out), "--mag-column", "TRUE_MAG",
                 "--detected-column", "FOUND", "--x-column", "XIMAGE", "--y-column", "YIMAGE",
                 "--noise-column", "SKYRMS", "--image-shape", "160,200", "--quiet"]) == 0
    entry = json.loads((out / "summary.json").read_text())["kinds"]["injections"]["model"]
    assert entry["footprint"] == "injections"
    m50 = entry["m50"]
    assert abs(m50["median"] - truth["m50"]) < 3 * 0.5 * (m50["hi68"] - m50["lo68"])


# ---------------------------------------------------------------------------------------- comest-bayes info


def _entry(name, m50, lo68, hi68, lo95, hi95, **extra):
    q = {"median": m50, "lo68": lo68, "hi68": hi68, "lo95": lo95, "hi95": hi95, "defined_fraction": 1.0,
         "extrapolated": False}
    entry = {"name": name, "requested": "auto", "m50": q, "m80": dict(q, median=m50 - 0.2), "m90": dict(q, median=m50 - 0.3),
             "diagnostics": {"method": "importance", "converged": True}, "warnings": [],
             "selection": {"table": [{"name": "logistic", "chosen": False}, {"name": name, "chosen": True}]}}
    entry.update(extra)
    return entry


@pytest.fixture
def finished_run(tmp_path):
    """A run directory as a finished run leaves it: run.json with its stages, summary.json, a few files."""
    from comest_bayes.io.rundir import RunDirectory

    out = tmp_path / "run"
    config = {"seed": 7, "injection": {"kinds": ["point", "buldisk"], "nsims": 3, "density": 15.0},
              "fit": {"model": "auto"}}
    run = RunDirectory(out, {"input": {"options": {"path": "/data/img.fits"}}, "config": config}).open()
    run.write_json("detection.json", {})
    run.record_stage("detect", files=["detection.json"], seconds=2.5)
    run.record_stage("sourcefree", seconds=3.25)
    run.record_stage("fit_completeness_point", seconds=4.0)
    for kind in ("point", "buldisk"):
        (out / "sims" / kind).mkdir(parents=True)
        for i in range(3):
            (out / "sims" / kind / f"r{i:05d}.fits").write_bytes(b"x" * 100)
    run.update(image={"path": "/data/img.fits", "shape": [300, 400], "zeropoint": 30.0, "pixel_scale_arcsec": 0.26,
                      "fwhm_pix": 3.47, "provenance": {"zeropoint": "image header MAGZERO", "fwhm": "Moffat fits"}},
               timings={"inject": 12.0, "ratios": 1.0, "fit": 9.0})
    summary = {"image": run.state["image"], "depth": {"point_source_5sigma": 24.18},
               "failed_realizations": ["buldisk #2"],
               "kinds": {"point": {"counts": {"usable": 900, "detected": 700, "false": 3, "realizations": 3},
                                   "m50_binned": 23.97, "mag_range": [19.2, 25.8],
                                   "model": _entry("spline_depth", 23.957, 23.949, 23.964, 23.942, 23.971),
                                   "purity_model": {"name": None, "requested": "purity",
                                                    "skipped": "too few false detections"}},
                         "buldisk": {"counts": {"usable": 800, "detected": 500, "false": 9, "realizations": 2},
                                     "m50_binned": 23.26, "mag_range": [19.2, 25.8],
                                     "model": _entry("logistic_depth", 23.262, 23.253, 23.271, 23.244, 23.278,
                                                     warnings=["the shape check fails at 22.9 mag"]),
                                     "purity_model": None}}}
    run.write_json("summary.json", summary)
    run.release()
    return out


def _tree(path):
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


def test_info_prints_a_finished_runs_results_and_writes_nothing(finished_run, capsys):
    before = _tree(finished_run)
    assert main(["info", str(finished_run)]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"run: {finished_run} (finished")
    assert "400x300 px; zero point 30 (image header MAGZERO)" in out
    assert "stages done: detect (2.5 s), sourcefree (3.2 s), inject (12.0 s), ratios (1.0 s), " \
           "fit_completeness_point (4.0 s)" in out
    assert "realizations on disk: point 3/3, buldisk 3/3" in out
    assert "point: 700/900 usable injections detected in 3 realizations, 3 false detections" in out
    assert "m50 binned: 23.97" in out and "m50 binned: 23.26" in out
    assert "completeness model: spline_depth (chosen among logistic, spline_depth)" in out
    assert "m50: 23.957 [68%: 23.949, 23.964] [95%: 23.942, 23.971]" in out
    assert "purity model: skipped (too few false detections)" in out
    assert "5-sigma point-source depth: 24.18 mag" in out
    assert "buldisk completeness: the shape check fails at 22.9 mag" in out
    assert "realization buldisk #2 failed" in out
    assert "sims/" in out and "(6 files)" in out and "summary.json" in out
    assert _tree(finished_run) == before


def test_info_json_holds_the_same_facts(finished_run, capsys):
    assert main(["info", str(finished_run), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["status"] == "finished" and info["running"] is None
    assert info["kinds"]["point"]["model"]["m50"]["lo95"] == 23.942
    assert info["kinds"]["buldisk"]["model"]["name"] == "logistic_depth"
    assert info["config"]["seed"] == 7 and info["realizations"] == {"point": 3, "buldisk": 3}
    assert len(info["warnings"]) == 2


def test_info_on_a_partial_run_says_what_is_missing(tmp_path, capsys):
    from comest_bayes.io.rundir import RunDirectory

    out = tmp_path / "partial"
    run = RunDirectory(out, {"config": {"injection": {"kinds": ["point"], "nsims": 4}}}).open()
    run.record_stage("detect", seconds=1.0)
    (out / "sims" / "point").mkdir(parents=True)
    (out / "sims" / "point" / "r00000.fits").write_bytes(b"x")
    run.release()
    assert main(["info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "(partial" in text and "stages done: detect (1.0 s)" in text
    assert "realizations on disk: point 1/4" in text and "results: none yet" in text
    # while a live process holds the run's lock, info says the run is going on and who runs it
    import os
    import socket

    (out / "run.lock").write_text(json.dumps({"pid": os.getppid(), "host": socket.gethostname(),
                                              "started": "2030-01-01T00:00:00+00:00"}))
    assert main(["info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "(running" in text and f"in use by process {os.getppid()} on {socket.gethostname()}" in text


def test_a_reader_that_goes_away_is_no_error(finished_run, monkeypatch, capsys):
    # `comest-bayes info DIR | head -1`: printing raises BrokenPipeError once head has exited
    import comest_bayes.io.info as info_module

    def closed_pipe(info):
        raise BrokenPipeError(32, "Broken pipe")

    monkeypatch.setattr(info_module, "format_info", closed_pipe)
    assert main(["info", str(finished_run)]) == 1
    assert capsys.readouterr().err == ""
