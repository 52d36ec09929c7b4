"""The command line (comest_bayes.cli): every subcommand's --help, argument errors, one-line errors for bad
input, and `comest-bayes fit` on outcome tables from elsewhere.
"""

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
    good = ["fit", str(root / "balrog_like.fits"), "--out", str(out), "--mag-column", "TRUE_MAG",
            "--detected-column", "FOUND"]
    # optional columns are optional only under their default names: a name given must exist
    assert main(good + ["--noise-column", "sigma"]) == 2
    err = capsys.readouterr().err
    assert "no column(s) ['sigma']" in err and "--noise-column" in err and not out.exists()
    assert main(good + ["--x-column", "XIMAGE"]) == 2  # no 'y' column: positions need both
    assert "--y-column" in capsys.readouterr().err and not out.exists()
    # an outcome that is not 0/1 is refused before the output folder is made
    assert main(good[:-1] + ["SKYRMS"]) == 2
    assert "must be boolean or 0/1" in capsys.readouterr().err and not out.exists()


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


# ---------------------------------------------------------------------------------------- argument errors


def test_no_subcommand_prints_the_help_and_returns_two(capsys):
    assert main([]) == 2
    assert capsys.readouterr().out.startswith("usage: comest-bayes")


@pytest.mark.parametrize("argv, message", [
    (["frobnicate"], "invalid choice: 'frobnicate'"),
    (["run"], "the following arguments are required"),
    (["info"], "the following arguments are required"),
    (["lf", "somewhere", "--mode", "sideways"], "invalid choice: 'sideways'"),
])
def test_bad_arguments_are_refused_by_the_parser_with_exit_code_two(argv, message, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


def test_a_missing_run_directory_is_one_error_line(tmp_path, capsys):
    assert main(["info", str(tmp_path / "nowhere")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: run directory") and "does not exist" in err and err.count("\n") == 1
    assert not (tmp_path / "nowhere").exists()
