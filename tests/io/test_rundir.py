"""The run directory: atomic writes, resume of the same run, refusal of another."""

import json
import os
from pathlib import Path

import numpy as np
import pytest
from astropy.table import Table

from comest_bayes.errors import OutputWriteError, RunDirectoryError
from comest_bayes.io.rundir import RunDirectory, atomic_path, check_writable, file_checksum


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
    with pytest.raises(RuntimeError, match="crash mid-write"):  # the caller's own error, unchanged
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


# ---------------------------------------------------------------- leftovers, lock, writability, write errors


def test_temporary_files_in_every_subfolder_are_cleaned_on_resume(tmp_path):
    RunDirectory(tmp_path, {"x": 1}).open().release()
    left = [tmp_path / "catalogs" / ".tmp-77-point_matched.fits", tmp_path / "sims" / "point" / ".tmp-77-r00001.fits",
            tmp_path / "maps" / ".tmp-77-point_maps.fits", tmp_path / "inputs" / ".tmp-77-abc-demo_image.fits"]
    for path in left:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("partial")
    kept = tmp_path / "catalogs" / "point_matched.fits"
    kept.write_text("complete")
    RunDirectory(tmp_path, {"x": 1}).open().release()
    assert [p for p in left if p.exists()] == []
    assert kept.read_text() == "complete"


def _hold_lock_in_another_process(path):
    """A second Python process that opens the run and waits; returns it once it holds the lock."""
    import subprocess
    import sys

    code = ("import sys, time\nfrom comest_bayes.io.rundir import RunDirectory\n"
            f"RunDirectory({str(path)!r}, {{'x': 1}}).open()\nprint('ready', flush=True)\ntime.sleep(120)\n")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "ready"
    return proc


def test_a_live_run_holds_the_directory_and_its_lock_is_taken_over_once_it_is_killed(tmp_path):
    import signal
    import socket

    out = tmp_path / "run"
    proc = _hold_lock_in_another_process(out)
    try:
        lock = json.loads((out / "run.lock").read_text())
        assert lock["pid"] == proc.pid and lock["host"] == socket.gethostname()
        before = (out / "run.json").read_bytes()
        with pytest.raises(RunDirectoryError, match=rf"in use by another comest-bayes run \(process {proc.pid} on "
                                                    rf"{socket.gethostname()}"):
            RunDirectory(out, {"x": 1}).open()
        # a run with another fingerprint is told the directory is in use, too; nothing changed
        with pytest.raises(RunDirectoryError, match=f"process {proc.pid}"):
            RunDirectory(out, {"x": 2}).check()
        assert (out / "run.json").read_bytes() == before
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        proc.stdout.close()
    run = RunDirectory(out, {"x": 1}).open()  # the holder is dead: the stale lock is taken over, with a note
    assert run.resumed
    assert f"process {proc.pid}" in run.lock_note and "no longer running" in run.lock_note
    assert json.loads((out / "run.lock").read_text())["pid"] == os.getpid()
    run.release()
    assert not (out / "run.lock").exists()


def test_the_lock_is_reentrant_in_one_process_and_released(tmp_path):
    first = RunDirectory(tmp_path, {"x": 1}).open()
    second = RunDirectory(tmp_path, {"x": 1}).open()  # e.g. a notebook opening the same run again
    assert second.lock_note is None
    second.release()
    assert not (tmp_path / "run.lock").exists()
    first.release()  # already gone: no error


def test_a_lock_left_without_run_json_does_not_make_the_directory_foreign(tmp_path):
    import socket

    (tmp_path / "run.lock").write_text(json.dumps({"pid": 2 ** 22 + 12345, "host": socket.gethostname()}))
    run = RunDirectory(tmp_path, {"x": 1}).open()
    assert not run.resumed and "no longer running" in run.lock_note
    run.release()


def _unwritable_folder(tmp_path):
    if os.geteuid() != 0:
        folder = tmp_path / "ro"
        folder.mkdir()
        folder.chmod(0o500)
        return folder
    sysfs = Path("/sys")
    if sysfs.is_dir():  # root may not create entries in sysfs either
        try:
            (sysfs / "comest-bayes-probe").mkdir()
        except OSError:
            return sysfs
        (sysfs / "comest-bayes-probe").rmdir()
    pytest.skip("no folder this user cannot write to")


def test_an_unwritable_out_is_refused_before_anything_is_written(tmp_path):
    folder = _unwritable_folder(tmp_path)
    before = sorted(p.name for p in folder.iterdir())
    with pytest.raises(RunDirectoryError, match="is not writable.*Nothing was written"):
        RunDirectory(folder / "comest-run" / "deeper", {"x": 1}).check()
    assert sorted(p.name for p in folder.iterdir()) == before


def test_check_writable_leaves_no_probe_behind(tmp_path):
    check_writable(tmp_path / "new" / "run")
    check_writable(tmp_path)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("error, reason", [
    (OSError(28, "No space left on device"), "No space left on device"),
    # astropy reports a full disk without an errno, in several sentences
    (OSError("Not enough space on disk: requested 160000, available 0. Not enough space on disk: requested "
             "160000, available 0. 40000 requested and 15664 written"), "Not enough space on disk: requested 160000"),
])
def test_a_refused_write_names_the_file_and_the_reason_on_one_line(tmp_path, error, reason):
    target = tmp_path / "catalogs" / "point_matched.fits"
    target.parent.mkdir()
    with pytest.raises(OutputWriteError) as info:
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise error
    text = str(info.value)
    assert text.startswith(f"could not write {str(target)!r}: {reason}") and "\n" not in text
    assert isinstance(info.value, OSError)
    assert list(target.parent.iterdir()) == []  # no temporary file left
