"""The run directory: atomic writes, resume of the same run, refusal of another."""

import json
import os

import numpy as np
import pytest
from astropy.table import Table

from comest_bayes.errors import RunDirectoryError
from comest_bayes.rundir import RunDirectory, atomic_path, file_checksum
from comest_bayes.seeding import int_seed_for, rng_for, seed_sequence


def test_new_run_writes_run_json_with_fingerprint_and_versions(tmp_path):
    run = RunDirectory(tmp_path / "r", {"config": {"a": 1}, "seed": 3}).open()
    state = json.loads((tmp_path / "r" / "run.json").read_text())
    assert state["fingerprint"] == {"config": {"a": 1}, "seed": 3}
    assert state["versions"]["numpy"] == np.__version__
    assert not run.resumed


def test_same_fingerprint_resumes_and_keeps_finished_stages(tmp_path):
    run = RunDirectory(tmp_path, {"x": 1}).open()
    name = run.write_table("t.fits", Table({"a": [1, 2]}))
    run.record_stage("detect", files=[name], seconds=1.5, nsources=2)
    again = RunDirectory(tmp_path, {"x": 1}).open()
    assert again.resumed
    assert again.stage_done("detect")
    assert again.stage_info("detect")["nsources"] == 2


def test_stage_with_missing_file_is_not_done(tmp_path):
    run = RunDirectory(tmp_path, {"x": 1}).open()
    run.write_json("a.json", {"v": 1})
    run.record_stage("s", files=["a.json"])
    (tmp_path / "a.json").unlink()
    assert not RunDirectory(tmp_path, {"x": 1}).open().stage_done("s")


def test_different_fingerprint_is_refused_and_names_the_difference(tmp_path):
    RunDirectory(tmp_path, {"config": {"thresh": 1.5}, "seed": 0}).open()
    before = (tmp_path / "run.json").read_bytes()
    with pytest.raises(RunDirectoryError, match=r"differs in: config\.thresh.*another --out"):
        RunDirectory(tmp_path, {"config": {"thresh": 2.0}, "seed": 0}).open()
    assert (tmp_path / "run.json").read_bytes() == before


def test_non_empty_foreign_directory_is_refused(tmp_path):
    (tmp_path / "image.fits").write_bytes(b"precious")
    with pytest.raises(RunDirectoryError, match="not empty and is not a comest-bayes run"):
        RunDirectory(tmp_path, {}).open()
    assert (tmp_path / "image.fits").read_bytes() == b"precious"


def test_out_that_is_a_file_is_refused(tmp_path):
    f = tmp_path / "f"
    f.write_text("x")
    with pytest.raises(RunDirectoryError, match="is an existing file"):
        RunDirectory(f, {}).open()


def test_atomic_path_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.txt"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("crash mid-write")
    assert not target.exists()
    assert list(tmp_path.iterdir()) == []


def test_stale_temporary_files_are_cleaned_on_resume(tmp_path):
    RunDirectory(tmp_path, {"x": 1}).open()
    (tmp_path / ".tmp-999-sfi.fits").write_text("partial")
    RunDirectory(tmp_path, {"x": 1}).open()
    assert not (tmp_path / ".tmp-999-sfi.fits").exists()


def test_file_checksum_is_sha256(tmp_path):
    import hashlib

    p = tmp_path / "b"
    p.write_bytes(os.urandom(1000))
    assert file_checksum(p) == hashlib.sha256(p.read_bytes()).hexdigest()


def test_seed_streams_depend_only_on_root_and_name():
    a = rng_for(7, "inject", "point", 3).normal(size=5)
    # drawing from other streams first must not change this one
    rng_for(7, "inject", "point", 2).normal(size=100)
    b = rng_for(7, "inject", "point", 3).normal(size=5)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, rng_for(8, "inject", "point", 3).normal(size=5))
    assert not np.array_equal(a, rng_for(7, "inject", "buldisk", 3).normal(size=5))
    assert int_seed_for(7, "x") == int_seed_for(7, "x") > 0
    with pytest.raises(ValueError, match="non-negative"):
        seed_sequence(-1)
