"""kill -9 during the merge and during the fits, then the same command again: the same results, no leftovers.

Each case runs the CLI in a child process on a 256x256 demo tile (2 realizations per kind, the
logistic model, one process) and stops it with SIGKILL at a known point.  The point is made
certain, not raced for: the child is this package with one function wrapped so that, at that
point, it writes a marker file and waits (the package itself has no test hooks).  The test then
kills it, runs the same command in this process, and compares with an uninterrupted run: the
merged catalogs and maps byte for byte, the posterior draws exactly, summary.json key by key
(leaving out wall and CPU times), and not one ``.tmp-*`` file left anywhere.
"""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from comest_bayes.cli import main
from comest_bayes.sim.demo import MASK_GAP, make_demo_tile, write_demo_tile

#: The child: install the hang for the case named in argv[1], then run the CLI with argv[3:].
DRIVER = r'''
import os, sys, time
from pathlib import Path

case, marker, args = sys.argv[1], Path(sys.argv[2]), sys.argv[3:]

from comest_bayes.bayes import posterior
from comest_bayes.pipeline import fits as fitting
from comest_bayes.io import rundir

def hang():
    import comest_bayes
    part = marker.with_name(marker.name + ".part")  # whole or absent: the test reads it as soon as it exists
    part.write_text(f"{os.getpid()}\n{Path(comest_bayes.__file__).resolve()}")
    os.replace(part, marker)
    while True:
        time.sleep(60)

if case == "merge":  # while the second kind's first catalog is being written
    write_table = rundir.RunDirectory.write_table
    def wrapped(self, name, table, extname=None):
        if name == "catalogs/buldisk_injected.fits":
            with rundir.atomic_path(self.file(name)) as tmp:
                table.write(tmp, format="fits")
                hang()
        return write_table(self, name, table, extname)
    rundir.RunDirectory.write_table = wrapped
elif case == "fit":  # in the middle of the second completeness fit
    fit_task = fitting.fit_task
    def wrapped(task):
        if task["kind"] == "buldisk" and task["quantity"] == "completeness":
            hang()
        return fit_task(task)
    fitting.fit_task = wrapped
elif case == "posterior":  # while the first fit's posterior is being written
    save = posterior.CompletenessPosterior.save
    def wrapped(self, path):
        if Path(path).name == "point_completeness.npz":
            with rundir.atomic_path(Path(path)) as tmp:
                Path(tmp).write_bytes(b"half a posterior")
                hang()
        return save(self, path)
    posterior.CompletenessPosterior.save = wrapped

from comest_bayes.cli import main
sys.exit(main(args))
'''


@pytest.fixture(scope="module")
def tile(tmp_path_factory):
    return write_demo_tile(make_demo_tile(seed=4, size=256), tmp_path_factory.mktemp("tile"))


def _args(tile, out) -> list:
    return ["run", str(tile["image"]), "--weight", str(tile["weight"]), "--mask", str(tile["mask"]),
            "--mask-bits", str(MASK_GAP), "--out", str(out), "--nsims", "2", "--model", "logistic",
            "--ncpu", "1", "--no-report", "--seed", "7"]


@pytest.fixture(scope="module")
def reference(tile, tmp_path_factory):
    """The same run, never interrupted."""
    out = tmp_path_factory.mktemp("reference") / "run"
    assert main(_args(tile, out) + ["--quiet"]) == 0
    return out


def _kill_at(case: str, tile, out: Path, tmp_path: Path, sig=signal.SIGKILL) -> str:
    """Run the CLI in a child until it reaches ``case``'s point, then send it ``sig`` (SIGKILL); its stderr."""
    driver = tmp_path / "driver.py"
    driver.write_text(DRIVER)
    marker = tmp_path / f"{case}.reached"
    # the child must run the package this process imported, not another copy on its path (an installed
    # wheel beside a checkout once made the two runs differ in every draw)
    import comest_bayes

    root = str(Path(comest_bayes.__file__).resolve().parent.parent)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([root, os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)}
    child = subprocess.Popen([sys.executable, str(driver), case, str(marker), *_args(tile, out), "--quiet"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    try:
        deadline = time.monotonic() + 120.0
        while not marker.exists():
            if child.poll() is not None:
                pytest.fail(f"the run ended (status {child.returncode}) before the {case} point: "
                            f"{child.stderr.read().decode()[-2000:]}")
            assert time.monotonic() < deadline, f"the run did not reach the {case} point in 120 s"
            time.sleep(0.05)
        pid, package = marker.read_text().split("\n")
        assert int(pid) == child.pid
        assert package == str(Path(comest_bayes.__file__).resolve()), "the child imported another copy of the package"
    finally:
        os.kill(child.pid, sig)
        try:
            child.wait(timeout=60)
        except subprocess.TimeoutExpired:
            os.kill(child.pid, signal.SIGKILL)
            child.wait()
        err = child.stderr.read().decode()
        child.stderr.close()
    if sig == signal.SIGKILL:
        assert child.returncode == -signal.SIGKILL
    return err


def _stages(out: Path) -> dict:
    return {k: v for k, v in json.loads((out / "run.json").read_text())["stages"].items() if v["status"] == "done"}


def _without_times(obj):
    """summary.json with wall and CPU times left out (everything else must be equal)."""
    if isinstance(obj, dict):
        return {k: _without_times(v) for k, v in obj.items() if "seconds" not in k and k != "timings"}
    if isinstance(obj, list):
        return [_without_times(v) for v in obj]
    return obj


def _assert_same_results(out: Path, reference: Path) -> None:
    assert not list(out.rglob(".tmp-*")), "a temporary file survived the resume"
    assert not (out / "run.lock").exists()
    names = sorted(p.name for p in (reference / "catalogs").glob("*.fits"))
    assert len(names) == 10 and names == sorted(p.name for p in (out / "catalogs").glob("*.fits"))
    for name in names:  # bit for bit
        assert (out / "catalogs" / name).read_bytes() == (reference / "catalogs" / name).read_bytes(), name
    for kind in ("point", "buldisk"):
        maps = f"maps/{kind}_maps.fits"
        assert (out / maps).read_bytes() == (reference / maps).read_bytes(), maps
        with np.load(out / "posterior" / f"{kind}_completeness.npz") as a, \
                np.load(reference / "posterior" / f"{kind}_completeness.npz") as b:
            np.testing.assert_array_equal(a["samples"], b["samples"])
    summary = json.loads((out / "summary.json").read_text())
    expected = json.loads((reference / "summary.json").read_text())
    assert _without_times(summary) == _without_times(expected)
    assert summary["kinds"]["buldisk"]["model"]["m50"] == expected["kinds"]["buldisk"]["model"]["m50"]


def test_kill_during_the_merge_then_resume(tile, reference, tmp_path, capsys):
    out = tmp_path / "run"
    _kill_at("merge", tile, out, tmp_path)
    # killed with the point catalogs written and the buldisk one half-written under a temporary name
    assert (out / "catalogs" / "point_outcomes.fits").exists()
    assert not (out / "catalogs" / "buldisk_injected.fits").exists()
    assert [p.name.startswith(".tmp-") for p in (out / "catalogs").iterdir() if "buldisk" in p.name] == [True]
    assert not any(name.startswith("fit_") for name in _stages(out))
    capsys.readouterr()
    assert main(_args(tile, out)) == 0
    printed = capsys.readouterr().out
    assert "took over the lock of process" in printed and "all 4 realizations done earlier" in printed
    _assert_same_results(out, reference)


@pytest.mark.parametrize("case", ["fit", "posterior"])
def test_kill_during_the_fits_then_resume_redoes_only_unfinished_fits(case, tile, reference, tmp_path, capsys):
    out = tmp_path / "run"
    _kill_at(case, tile, out, tmp_path)
    done = _stages(out)
    if case == "fit":
        # the point fits finished and were recorded, each on its own; the buldisk ones were not
        assert {"fit_completeness_point", "fit_purity_point"} <= set(done)
        assert (out / done["fit_completeness_point"]["files"][0]).is_file()
        todo = ["buldisk completeness", "buldisk purity"]
    else:
        # killed as the first posterior was written: nothing of the fits was recorded
        assert not any(name.startswith("fit_") for name in done)
        assert [p.name for p in (out / "posterior").iterdir()][0].startswith(".tmp-")
        todo = ["point completeness", "point purity", "buldisk completeness", "buldisk purity"]
    capsys.readouterr()
    assert main(_args(tile, out)) == 0
    printed = capsys.readouterr().out.splitlines()
    # only the unfinished fits run again, each announced with what it does
    assert f"fit: {len(todo)} model fits ({', '.join(todo)}) on 1 process" in printed
    started = [s.split(":")[1].strip() for s in printed if s.startswith("fit: ") and ": started: " in s]
    assert started == todo
    assert any(s.startswith("fit: buldisk completeness: started: logistic (MAP + Laplace), then importance "
                            "sampling") for s in printed)
    _assert_same_results(out, reference)


def test_sigterm_while_a_posterior_is_written_leaves_no_temporary_file_and_the_run_resumes(tile, reference, tmp_path,
                                                                                           capsys):
    # SIGTERM is what a batch scheduler sends at a time limit: the run unwinds as on Ctrl-C (found by a new user
    # with SExtractor's working folder, 47 MB, left behind), removing what it had half written
    out = tmp_path / "run"
    err = _kill_at("posterior", tile, out, tmp_path, sig=signal.SIGTERM)
    assert "terminated: rerun the same command to resume where it stopped." in err and "Traceback" not in err
    assert not list(out.rglob(".tmp-*")) and not (out / "run.lock").exists()
    capsys.readouterr()
    assert main(_args(tile, out)) == 0
    _assert_same_results(out, reference)


def test_a_realization_that_failed_and_then_ran_gets_its_kind_refitted(tile, reference, tmp_path, capsys,
                                                                      monkeypatch):
    import comest_bayes.recover.realization as recovery

    run_realization = recovery.run_realization

    def flaky(task):
        if task.kind == "buldisk" and task.index == 1:
            return recovery.RealizationResult(task.kind, task.index, None, None, error="simulated failure\n")
        return run_realization(task)

    out = tmp_path / "run"
    monkeypatch.setattr(recovery, "run_realization", flaky)
    assert main(_args(tile, out)) == 0
    first = json.loads((out / "summary.json").read_text())
    assert first["failed_realizations"] == ["buldisk #1"]
    assert first["kinds"]["buldisk"]["counts"]["realizations"] == 1
    monkeypatch.undo()
    capsys.readouterr()
    assert main(_args(tile, out)) == 0  # the failed realization runs now, and the buldisk fits see it
    printed = capsys.readouterr().out.splitlines()
    assert "fit: 2 model fits (buldisk completeness, buldisk purity) on 1 process" in printed
    _assert_same_results(out, reference)
