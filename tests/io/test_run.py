"""Reading a run directory (comest_bayes.io.run.Run): its records, its configuration, and clear errors on what
is no run.  Runs made by the pipeline are read in tests/test_api.py and tests/io/test_info.py."""

import json

import pytest

from comest_bayes.errors import InputError, InputFileError, RunDirectoryError
from comest_bayes.io import layout
from comest_bayes.io.run import Run

SUMMARY = {"kinds": {"sersic": {"m50_binned": 23.4, "counts": {"usable": 20}}, "point": {}}}


def _write_run(path, summary=None, state=None):
    path.mkdir(parents=True, exist_ok=True)
    state = state if state is not None else {
        "fingerprint": {"config": {"seed": 5, "injection": {"nsims": 3}}},
        "image": {"shape": [100, 200], "zeropoint": 30.0}}
    (path / layout.RUN).write_text(json.dumps(state))
    if summary is not None:
        (path / layout.SUMMARY).write_text(json.dumps(summary))
    return path


def test_open_reads_the_records_and_the_run_configuration(tmp_path):
    run = Run.open(_write_run(tmp_path / "run", SUMMARY))
    assert run.kind_names == ["sersic", "point"]  # in the order of summary.json
    assert run.image_facts == {"shape": [100, 200], "zeropoint": 30.0}  # from run.json: summary has none
    assert run.config.seed == 5 and run.config.injection.nsims == 3
    assert run.kind_entry("buldisk") == {} and run.kind_entry("sersic")["m50_binned"] == 23.4
    assert run.file(layout.SUMMARY).is_file() and run.summary_json() == SUMMARY
    assert run.status == "finished" and run.summary("sersic").m50_binned == 23.4
    assert run.summary("sersic").m50_binned_sd is None  # a summary written before the sd existed
    partial = Run.open(_write_run(tmp_path / "partial"))
    assert partial.summary_record is None and partial.kind_names == [] and partial.status == "partial"
    with pytest.raises(InputFileError, match="does not exist; the run is partial"):
        partial.summary_json()


def test_a_copy_of_summary_json_is_handed_out(tmp_path):
    run = Run.open(_write_run(tmp_path / "run", SUMMARY))
    copy = run.summary_json()
    copy["kinds"]["sersic"]["m50_binned"] = 0.0
    assert run.summary_json()["kinds"]["sersic"]["m50_binned"] == 23.4


@pytest.mark.parametrize("make, error, message", [
    (lambda p: p / "missing", InputFileError, "does not exist"),
    (lambda p: (p / "a_file").write_text("x") and p / "a_file", RunDirectoryError, "is a file, not a run directory"),
    (lambda p: p, RunDirectoryError, r"not a comest-bayes run directory \(no run.json\)"),
    (lambda p: _write_run(p, state=["no", "record"]), RunDirectoryError, "is not a comest-bayes record"),
])
def test_what_is_no_run_is_refused(tmp_path, make, error, message):
    with pytest.raises(error, match=message):
        Run.open(make(tmp_path))


def test_a_record_without_fingerprint_has_no_configuration(tmp_path):
    run = Run.open(_write_run(tmp_path / "run", state={"image": {}}))
    with pytest.raises(RunDirectoryError, match=r"not a comest-bayes run record \(no fingerprint\)"):
        run.config


def test_file_names_a_file_of_the_run_or_refuses(tmp_path):
    run = Run.open(_write_run(tmp_path / "run", SUMMARY))
    assert run.file(layout.SUMMARY) == tmp_path / "run" / "summary.json"
    assert run.file(layout.posterior("point")) == tmp_path / "run" / "posterior" / "point_completeness.npz"
    for bad in ("nonexistent", "../outside.fits", "/etc/passwd", "posterior/../../x"):
        with pytest.raises(InputError, match="is not a file of a comest-bayes run"):
            run.file(bad)


def test_a_missing_posterior_says_why(tmp_path):
    summary = {"kinds": {"point": {"model": {"name": None, "requested": "auto", "skipped": "too few outcomes"},
                                   "purity_model": None}}}
    run = Run.open(_write_run(tmp_path / "run", summary))
    with pytest.raises(InputFileError, match=r"no completeness posterior for kind 'point': the model was skipped "
                                             r"\(too few outcomes\)\.$"):
        run.posterior("point")
    with pytest.raises(InputFileError, match=r"no purity posterior .* it was run without one \(fit.purity_model"):
        run.posterior("point", "purity")
