"""The front door: ``import comest_bayes`` stays cheap, the README's Python example runs, bad options are refused."""

from __future__ import annotations

import dataclasses
import json
import re
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from astropy.table import Table

import comest_bayes as cb
from comest_bayes import api
from comest_bayes.cli import _config_from_args, build_parser
from comest_bayes.sim.demo import make_demo_tile, write_demo_tile
from comest_bayes.errors import ComestError, ConfigError, InputError, InputFileError, RunDirectoryError

from conftest import REPO_ROOT

HEAVY = ("jax", "galsim", "matplotlib")


def _fresh_python(code: str) -> dict:
    """Run ``code`` in a new interpreter; it prints one JSON line, returned here."""
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=120,
                         cwd=REPO_ROOT)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


# --------------------------------------------------------------------------- the package's names


def test_import_pulls_in_neither_jax_nor_galsim_nor_matplotlib():
    got = _fresh_python(f"""
        import json, sys
        import comest_bayes as cb
        after_import = [m for m in {HEAVY!r} if m in sys.modules]
        cb.run, cb.Run, cb.fit_completeness, cb.load_config, cb.InputError  # the light names
        after_light = [m for m in {HEAVY!r} if m in sys.modules]
        print(json.dumps({{"import": after_import, "light": after_light, "numpy": "numpy" in sys.modules}}))
    """)
    assert got == {"import": [], "light": [], "numpy": False}


def test_every_exported_name_is_the_object_of_its_module():
    from comest_bayes import config
    from comest_bayes import errors
    from comest_bayes.lf import fit as lf
    from comest_bayes.bayes import posterior
    from comest_bayes.report import html as report

    expected = {"run": api.run, "fit_completeness": api.fit_completeness, "Run": api.Run,
                "KindSummary": api.KindSummary, "ModelSummary": api.ModelSummary, "Interval": api.Interval,
                "CompletenessFit": api.CompletenessFit, "CompletenessPosterior": posterior.CompletenessPosterior,
                "load_config": config.load_config, "write_report": report.write_report, "fit_lf": lf.run_lf,
                "ComestError": errors.ComestError, "InputError": errors.InputError,
                "ConfigError": errors.ConfigError}
    assert set(cb.__all__) == set(expected) | {"__version__"}
    for name, obj in expected.items():
        assert getattr(cb, name) is obj, name
    assert set(cb.__all__) <= set(dir(cb))
    with pytest.raises(AttributeError, match="no attribute 'runn'"):
        cb.runn


# --------------------------------------------------------------------------- options -> configuration


def test_python_options_give_the_command_lines_configuration():
    argv = ["run", "x.fits", "--out", "y", "--kinds", "point,buldisk", "--nsims", "3", "--thresh", "2.5",
            "--set", "detection.minarea=7", "--precision", "0.02", "--precision-at", "23.5,24.0", "--no-bnb",
            "--seed", "11", "--model", "logistic"]
    from_cli = _config_from_args(build_parser().parse_args(argv))
    from_python = api.config_from_options(kinds=["point", "buldisk"], nsims=3, thresh=2.5,
                                          overrides={"detection.minarea": 7}, precision=0.02,
                                          precision_at=[23.5, 24.0], no_bnb=True, seed=11, model="logistic")
    assert from_python == from_cli
    # and the values arrived where the options say
    assert from_python.injection.kinds == ("point", "buldisk") and from_python.injection.nsims == 3
    assert from_python.detection.thresh == 2.5 and from_python.detection.minarea == 7
    assert from_python.sourcefree.bnb is False and from_python.seed == 11 and from_python.fit.model == "logistic"
    assert from_python.adaptive.target == "f" and from_python.adaptive.magnitudes == (23.5, 24.0)


@pytest.mark.parametrize("options, error, message", [
    ({"thres": 2.0}, ConfigError, r"unknown option\(s\) of comest_bayes.run: 'thres' \(did you mean 'thresh'\?\)"),
    ({"thresh": "deep"}, ConfigError, r"invalid detection.thresh = 'deep'"),
    ({"overrides": ["detection.thresh"]}, ConfigError, r"write it as section.key=value"),
    ({"ncpu": 0}, ConfigError, r"--ncpu 0 must be at least 1"),
    ({"ncpu": 1.5}, ConfigError, r"ncpu=1.5 must be an integer"),
    ({"executor": "gpu"}, ConfigError, r"executor 'gpu' is not one of"),
    ({"weight_type": "sigma"}, InputError, r"weight_type='sigma' is not one of"),
])
def test_bad_options_are_refused_before_anything_is_written(tmp_path, synthetic_fits, options, error, message):
    image = synthetic_fits("image.fits")
    out = tmp_path / "run"
    with pytest.raises(error, match=message):
        cb.run(image.path, out=out, quiet=True, **options)
    assert not out.exists()


def test_a_missing_image_is_an_input_file_error(tmp_path):
    with pytest.raises(InputFileError, match="does not exist"):
        cb.run(tmp_path / "nothing.fits", out=tmp_path / "run", quiet=True)
    assert not (tmp_path / "run").exists()


def test_a_top_level_call_in_a_re_imported_script_is_refused_with_the_fix(tmp_path):
    # what a worker process does with a script that calls run() at its top level (multiprocessing's
    # spawn imports it as __mp_main__): refused before the run starts, naming the remedy
    script = compile(f"import comest_bayes as cb\ncb.run({str(tmp_path / 'image.fits')!r}, out='x')\n",
                     "script.py", "exec")
    with pytest.raises(ComestError, match=r'if __name__ == "__main__":'):
        exec(script, {"__name__": "__mp_main__"})
    # the same call from an ordinary script's top level goes on to look at its inputs
    with pytest.raises(InputFileError, match="image.fits.*does not exist"):
        exec(script, {"__name__": "__main__"})


def test_open_refuses_a_folder_that_is_not_a_run(tmp_path):
    with pytest.raises(RunDirectoryError, match="not a comest-bayes run directory"):
        cb.Run.open(tmp_path)


# --------------------------------------------------------------------------- fit_completeness


def _logistic_outcomes(n: int = 4000, m50: float = 24.0, width: float = 0.25, seed: int = 0) -> Table:
    rng = np.random.default_rng(seed)
    mag = rng.uniform(21.0, 26.0, n)
    p = 1.0 / (1.0 + np.exp((mag - m50) / width))
    return Table({"mag": mag, "detected": rng.random(n) < p})


def test_fit_completeness_finds_a_known_m50_from_a_table_or_a_file(tmp_path):
    table = _logistic_outcomes()
    in_memory = cb.fit_completeness(table, model="logistic", kind="stars")
    path = tmp_path / "outcomes.fits"
    table.write(path)
    on_disk = cb.fit_completeness(path, tmp_path / "fit", model="logistic", kind="stars")
    # one path: the same outcomes and seed give the same posterior, whatever form they came in
    np.testing.assert_array_equal(in_memory.posterior.samples, on_disk.posterior.samples)
    assert in_memory.out is None and on_disk.out == tmp_path / "fit"
    summary = json.loads((tmp_path / "fit" / "summary.json").read_text())
    entry = summary["kinds"]["stars"]["model"]
    assert dict(on_disk.entry) == entry
    fit = in_memory.model
    assert fit.name == "logistic" and fit.m50.median == pytest.approx(entry["m50"]["median"], abs=1e-12)
    # The truth, 24.0, within 4 posterior sd (the 68% half-width) of the median; with 4000 outcomes
    # on a 0.25-mag logistic the sd is ~0.01 mag.  Fixed seed, so the outcome is fixed too.
    sd = 0.5 * (fit.m50.hi68 - fit.m50.lo68)
    assert 0.003 < sd < 0.03
    assert abs(fit.m50.median - 24.0) < 4 * sd
    assert fit.m50.lo95 < fit.m50.lo68 < fit.m50.median < fit.m50.hi68 < fit.m50.hi95
    # a table given in memory is named as such in errors, not by the scratch file it is written to, and the
    # Python way to name a column is given with the command line's
    with pytest.raises(InputError, match=re.escape("the outcome table given has no column(s) ['MAG']")) as err:
        cb.fit_completeness(table, columns={"mag": "MAG"})
    assert "--mag-column (in Python: columns={'mag': ...})" in str(err.value) and "comest-fit-" not in str(err.value)


def test_fit_completeness_refuses_a_table_without_the_columns(tmp_path):
    with pytest.raises(InputError, match=r"has no column\(s\) \['detected'\]"):
        cb.fit_completeness(Table({"mag": [22.0, 23.0]}))
    with pytest.raises(InputError, match="must be a FITS path or a 2-D array"):
        cb.fit_completeness(_logistic_outcomes(100), mask=np.zeros(5))


# --------------------------------------------------------------------------- the README's example


def readme_example() -> str:
    """The Python block between the README's ``python-example`` markers."""
    text = (REPO_ROOT / "README.md").read_text()
    block = re.search(r"<!-- python-example:start[^>]*-->\s*```python\n(.*?)```\s*<!-- python-example:end -->",
                      text, re.S)
    assert block, "README.md has no python-example block"
    return block.group(1)


@pytest.fixture(scope="module")
def readme_run(tmp_path_factory):
    """The README's example, run as a script (worker processes and all) next to a small demo tile."""
    where = tmp_path_factory.mktemp("readme")
    paths = write_demo_tile(make_demo_tile(seed=3, size=700, star_density=6.0), where)
    for role in ("image", "weight", "mask"):
        paths[role].rename(where / f"{role}.fits")
    (where / "example.py").write_text(readme_example())
    done = subprocess.run([sys.executable, "example.py"], cwd=where, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-4000:]
    return where, done.stdout


@pytest.mark.slow
def test_the_readme_example_prints_the_numbers_of_summary_json(readme_run):
    where, printed = readme_run
    summary = json.loads((where / "run1" / "summary.json").read_text())["kinds"]["point"]
    model = summary["model"]
    line = re.search(r"point: binned m50 ([\d.]+) \+- ([\d.]+); (\w+) m50 ([\d.]+) \[([\d.]+), ([\d.]+)\] \(68%\)",
                     printed)
    assert line, printed
    assert float(line.group(1)) == pytest.approx(summary["m50_binned"], abs=0.0051)
    assert float(line.group(2)) == pytest.approx(summary["m50_binned_sd"], abs=0.0051)
    assert line.group(3) == model["name"] == "logistic_depth"
    for i, key in ((4, "median"), (5, "lo68"), (6, "hi68")):
        assert float(line.group(i)) == pytest.approx(model["m50"][key], abs=0.0051)
    counts = re.search(r"(\d+) of (\d+) injections detected", printed)
    assert (int(counts.group(1)), int(counts.group(2))) == (summary["counts"]["detected"], summary["counts"]["usable"])
    # f(23) and f(24) lie between the summary curve's neighbouring grid values (it falls with magnitude)
    f = [float(v) for v in re.search(r"completeness at 23 and 24 mag: ([\d.]+), ([\d.]+)", printed).groups()]
    grid, median = np.asarray(model["curve"]["mag"]), np.asarray(model["curve"]["median"])
    for m, value in zip((23.0, 24.0), f):
        k = np.searchsorted(grid, m) - 1
        assert median[k + 1] - 0.005 <= value <= median[k] + 0.005, (m, value, grid[k:k + 2], median[k:k + 2])
    assert f[0] > 0.9 and f[1] < f[0]
    assert (where / "run1" / "report.html").is_file()  # run writes the report, as the CLI does


@pytest.mark.slow
def test_the_run_object_holds_summary_json_and_reads_the_run(readme_run):
    where, _ = readme_run
    run = cb.Run.open(where / "run1")
    raw = run.summary_json()
    entry = raw["kinds"]["point"]
    assert run.status == "finished" and list(run.kinds) == ["point"] == list(raw["kinds"])
    point = run.summary("point")
    assert point.m50_binned == entry["m50_binned"] and point.m50_binned_sd == entry["m50_binned_sd"] > 0
    assert point.model.name == entry["model"]["name"] and point.model.requested == "logistic_depth"
    for key in ("median", "lo68", "hi68", "lo95", "hi95"):
        assert getattr(point.m50_model, key) == entry["model"]["m50"][key]
    assert point.model.m90.median == entry["model"]["m90"]["median"]
    assert dict(point.counts) == entry["counts"] and point.mag_range == tuple(entry["mag_range"])
    assert point.purity_model is not None  # skipped or fitted, it is recorded
    from comest_bayes.io.run import run_info

    assert run.warnings == tuple(run_info(where / "run1")["warnings"])
    # catalogs: every injection is matched or not; the outcome table holds the usable ones
    n = {name: len(run.catalog("point", name)) for name in ("injected", "matched", "unmatched", "outcomes")}
    assert n["matched"] + n["unmatched"] == n["injected"] == entry["counts"]["injected"]
    assert n["outcomes"] == entry["counts"]["usable"]
    post = run.posterior("point")
    assert post.spec.name == entry["model"]["name"]
    # frozen, and a wrong kind or catalog names what exists
    with pytest.raises(dataclasses.FrozenInstanceError):
        run.status = "partial"
    with pytest.raises(InputError, match=r"no results for kind 'pointt'; did you mean 'point'\?"):
        run.summary("pointt")
    with pytest.raises(InputError, match="unknown catalog 'pairs'"):
        run.catalog("point", "pairs")


def test_weight_and_mask_options_without_their_map_are_refused(tmp_path):
    # found by a new user: weight_type="rms" without weight= was ignored, and a full run followed
    import comest_bayes as cb
    from comest_bayes.cli import main

    for kwargs, said in (({"weight_type": "rms"}, "weight_type (--weight-type) given without a weight map"),
                         ({"mask_hdu": 1, "mask_bits": 4}, "mask_hdu (--mask-hdu), mask_bits (--mask-bits) given "
                                                          "without a mask map")):
        with pytest.raises(cb.ConfigError, match=re.escape(said)):
            cb.run(tmp_path / "image.fits", out=tmp_path / "r", **kwargs)
    assert main(["run", str(tmp_path / "image.fits"), "--out", str(tmp_path / "r"), "--weight-type", "var"]) == 2
    assert not (tmp_path / "r").exists()
