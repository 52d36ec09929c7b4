"""What a run directory holds (comest_bayes.io.info, comest_bayes.io.run): run_info and format_info on finished, partial and running
run directories made by hand, through `comest-bayes info` and directly, and clear errors on what is no run.
"""

import json

import numpy as np
import pytest

from comest_bayes.cli import main


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
                                   "m50_binned": 23.97, "m50_binned_sd": 0.0071, "mag_range": [19.2, 25.8],
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
    assert "3 realizations per kind; 15 per arcmin^2; detector sep; model auto; seed 7" in out
    assert "point: 700/900 usable injections detected in 3 realizations, 3 false detections" in out
    # the sd where the summary has one (point), none where it does not (buldisk: a run before the sd existed)
    assert "m50 binned: 23.97 +- 0.007 (spread of the first crossing under the bins' binomial noise)" in out
    assert "m50 binned: 23.26\n" in out
    assert "completeness model: spline_depth (chosen among logistic, spline_depth)" in out
    assert "m50: 23.957 [68%: 23.949, 23.964] [95%: 23.942, 23.971]" in out
    assert "purity model: skipped (too few false detections)" in out
    assert "5-sigma point-source depth: 24.18 mag" in out
    assert "buldisk completeness: the shape check fails at 22.9 mag" in out
    assert "realization buldisk #2 failed" in out
    assert "sims/" in out and "(6 files)" in out and "summary.json" in out
    assert _tree(finished_run) == before


def test_an_automatic_density_is_shown_as_the_density_each_kind_got(finished_run, capsys):
    """density = 0 in the config means automatic: info names the density the run chose per kind, not "0.0"."""
    state = json.loads((finished_run / "run.json").read_text())  # as a run with --density 0 leaves it
    state["fingerprint"]["config"]["injection"]["density"] = 0.0
    state["injection_density"] = {"point": {"density": 15.0, "source": "automatic"},
                                  "buldisk": {"density": 7.25, "source": "automatic"}}
    (finished_run / "run.json").write_text(json.dumps(state))
    assert main(["info", str(finished_run)]) == 0
    out = capsys.readouterr().out
    assert "3 realizations per kind; density automatic (point 15, buldisk 7.25 per arcmin^2); detector sep; model auto" in out


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


# ---------------------------------------------------------------------------------------- run_info directly


def test_run_info_orders_stages_by_the_data_flow_and_warns_about_what_went_wrong(tmp_path):
    from comest_bayes.io.info import format_info
    from comest_bayes.io.run import run_info
    from comest_bayes.io.rundir import RunDirectory

    out = tmp_path / "run"
    run = RunDirectory(out, {"config": {"injection": {"kinds": ["point", "sersic"], "nsims": 2}}}).open()
    # recorded out of order: info lists detect, fwhm, sourcefree, baseline, then inject and ratios, then fits
    run.record_stage("fit_completeness_point", seconds=5.0)
    run.record_stage("sourcefree", seconds=2.0)
    run.record_stage("detect", seconds=1.0)
    run.update(timings={"ratios": 4.0, "inject": 3.0})
    unconverged = _entry("logistic", 24.0, 23.9, 24.1, 23.8, 24.2)
    unconverged["diagnostics"] = {"method": "emcee", "converged": False}
    run.write_json("summary.json", {"kinds": {
        "point": {"counts": {"usable": 10, "detected": 5}, "model": unconverged},
        "sersic": {"counts": {"usable": 0}, "model": None}}})
    run.release()
    info = run_info(out)
    assert list(info["stages"]) == ["detect", "sourcefree", "inject", "ratios", "fit_completeness_point"]
    assert info["status"] == "finished" and info["realizations"] == {"point": 0, "sersic": 0}
    assert info["warnings"] == ["point completeness: the emcee sampler did not converge", "sersic: no usable injection"]
    assert info["kinds"]["sersic"]["model"] is None
    assert "the emcee sampler did not converge" in format_info(info)
    json.dumps(info)  # JSON-ready


def test_model_facts_of_a_full_a_skipped_and_a_missing_entry():
    from comest_bayes.io.run import model_facts

    facts = model_facts(_entry("spline_depth", 23.9, 23.8, 24.0, 23.7, 24.1))
    assert facts["name"] == "spline_depth" and facts["candidates"] == ["logistic", "spline_depth"]
    assert facts["m50"] == {"median": 23.9, "lo68": 23.8, "hi68": 24.0, "lo95": 23.7, "hi95": 24.1,
                            "extrapolated": False}
    assert facts["m80"]["median"] == pytest.approx(23.7) and facts["sampler"] == "importance"
    assert model_facts({"name": None, "requested": "purity", "skipped": "too few"}) == \
        {"name": None, "requested": "purity", "skipped": "too few"}
    assert model_facts(None) is None and model_facts({}) is None
    # emcee's diagnostics name their sampler (a run before 2026-11-29 did not: its walkers say it)
    from comest_bayes.bayes.inference import PosteriorDiagnostics

    diag = PosteriorDiagnostics(names=["m50_0"], tau=np.array([30.0]), ess=np.array([500.0]), acceptance_mean=0.3,
                                acceptance_min=0.2, nsteps=2000, burn=60, nwalkers=16, min_ess=400.0,
                                converged=False, warnings=[], seconds=1.0).to_dict()
    assert diag["method"] == "emcee"
    for stored in (diag, {k: v for k, v in diag.items() if k != "method"}):
        entry = {**_entry("spline_depth", 23.9, 23.8, 24.0, 23.7, 24.1), "diagnostics": stored}
        assert model_facts(entry)["sampler"] == "emcee" and model_facts(entry)["converged"] is False
    assert model_facts({"name": "x", "m50": {"median": None}})["m50"] is None


def test_what_is_no_run_is_refused_clearly(tmp_path):
    from comest_bayes.errors import InputFileError, RunDirectoryError
    from comest_bayes.io.run import run_info

    with pytest.raises(InputFileError, match="does not exist"):
        run_info(tmp_path / "nowhere")
    with pytest.raises(RunDirectoryError, match=r"not a comest-bayes run directory \(no run.json\)"):
        run_info(tmp_path)
    (tmp_path / "run.json").write_text("{not json")
    with pytest.raises(RunDirectoryError, match="cannot be read"):
        run_info(tmp_path)
    (tmp_path / "run.json").write_text("[1, 2]")
    with pytest.raises(RunDirectoryError, match="is not a comest-bayes record"):
        run_info(tmp_path)
