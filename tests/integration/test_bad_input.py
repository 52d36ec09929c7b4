"""A corpus of bad inputs: every one gets one ``error:`` line, writes nothing and changes no input.

Each case runs the command line in-process (``comest_bayes.cli.main``) and
checks the exit status, the message, that no traceback was printed, that the
output folder was not created (or, when it existed, that nothing in it
changed), and that every input file is byte-identical afterwards.

The inputs are small (128 x 128 pixels), so the whole corpus runs in seconds.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits

from comest_bayes.cli import main
from conftest import make_synthetic_sky, tan_header, write_fits_file

SHAPE = (128, 128)
PIXEL_SCALE = 0.2
ZP = 27.0


def _header(shape=SHAPE, zp=ZP, wcs=True):
    header = tan_header(shape, PIXEL_SCALE) if wcs else fits.Header()
    if zp is not None:
        header["MAGZERO"] = zp
    return header


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> Path:
    """Every bad (and one good) input file, written once."""
    d = tmp_path_factory.mktemp("inputs")
    rng = np.random.default_rng(11)
    sky = make_synthetic_sky(shape=SHAPE, seed=4, fwhm=3.0)
    good = write_fits_file(d / "good.fits", sky.data, _header())
    raw = good.read_bytes()
    (d / "cut_data.fits").write_bytes(raw[: len(raw) - 40000])          # cut in the middle of the data
    (d / "cut_header.fits").write_bytes(raw[:1000])                     # cut inside the header
    (d / "empty.fits").write_bytes(b"")
    (d / "text.fits").write_text("SIMPLE? no, this is a text file\n")
    write_fits_file(d / "nan.fits", np.full(SHAPE, np.nan, np.float32), _header())
    write_fits_file(d / "constant.fits", np.full(SHAPE, 100.0, np.float32), _header())
    write_fits_file(d / "nowcs.fits", sky.data, _header(wcs=False))
    write_fits_file(d / "nozp.fits", sky.data, _header(zp=None))
    write_fits_file(d / "cube.fits", rng.normal(100, 5, (3,) + SHAPE).astype(np.float32), _header())
    write_fits_file(d / "tiny8.fits", rng.normal(100, 5, (8, 8)).astype(np.float32), _header((8, 8)))
    write_fits_file(d / "small20.fits", rng.normal(100, 5, (20, 20)).astype(np.float32), _header((20, 20)))
    write_fits_file(d / "strip.fits", rng.normal(100, 5, (16, 5000)).astype(np.float32), _header((16, 5000)))
    write_fits_file(d / "extension.fits", sky.data, _header(), extension=True)
    fits.BinTableHDU.from_columns([fits.Column(name="a", format="E", array=np.ones(3))]).writeto(d / "table.fits")
    write_fits_file(d / "mask_wrong.fits", np.zeros((64, 128), np.uint8))
    write_fits_file(d / "mask_all.fits", np.ones(SHAPE, np.uint8))
    write_fits_file(d / "weight_wrong.fits", np.ones((128, 64), np.float32))
    write_fits_file(d / "weight_zero.fits", np.zeros(SHAPE, np.float32))
    (d / "weight_cut.fits").write_bytes((d / "good.fits").read_bytes()[:5000])
    (d / "section_value.toml").write_text("detection = 5\n")
    (d / "invalid.toml").write_text("[detection\nthresh = 2\n")
    (d / "unknown_table.toml").write_text("[detektion]\nthresh = 2\n")
    (d / "unknown_key.toml").write_text("[detection]\nthres = 2\n")
    (d / "wrong_type.toml").write_text("[injection]\nnsims = \"many\"\n")
    (d / "binary.toml").write_bytes(bytes(range(256)))
    (d / "conf_dir.toml").mkdir()
    return d


def _checksums(folder: Path) -> dict:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _snapshot(path: Path):
    if not path.exists():
        return None
    if path.is_file():
        return ("file", path.read_bytes())
    return ("dir", {str(p.relative_to(path)): (p.read_bytes() if p.is_file() else None)
                    for p in sorted(path.rglob("*"))})


# ------------------------------------------------------------------------------ the corpus
# (id, arguments after the image, exit status, text the error line holds); {in} is the inputs folder.
RUN = "run"
CASES = [
    # files that are not usable images
    ("cut_data", [RUN, "{in}/cut_data.fits"], 2, "image file '{in}/cut_data.fits' cannot be read as FITS"),
    ("cut_header", [RUN, "{in}/cut_header.fits"], 2, "cut_header.fits' is not a readable FITS file"),
    ("empty_file", [RUN, "{in}/empty.fits"], 2, "empty.fits' is not a readable FITS file"),
    ("text_file", [RUN, "{in}/text.fits"], 2, "text.fits' is not a readable FITS file"),
    ("missing_image", [RUN, "{in}/nothing.fits"], 2, "image file '{in}/nothing.fits' does not exist"),
    ("image_is_folder", [RUN, "{in}/conf_dir.toml"], 2, "is not a file"),
    ("nan_only", [RUN, "{in}/nan.fits"], 2, "every pixel of '{in}/nan.fits' is unusable (100% NaN or infinite in the image)"),
    ("constant", [RUN, "{in}/constant.fits"], 2, "is constant"),
    ("table_only", [RUN, "{in}/table.fits"], 2, "holds no 2-D image"),
    ("cube", [RUN, "{in}/cube.fits"], 2, "3-D"),
    ("hdu_out_of_range", [RUN, "{in}/good.fits", "--hdu", "5"], 2, "has 1 HDUs (0-0); got hdu=5"),
    ("hdu_empty_primary", [RUN, "{in}/extension.fits", "--hdu", "0"], 2, "HDU 0 of image file"),
    ("no_wcs_no_pixel_scale", [RUN, "{in}/nowcs.fits"], 2, "--pixel-scale"),
    ("no_zero_point", [RUN, "{in}/nozp.fits"], 2, "--zp"),
    ("image_8x8", [RUN, "{in}/tiny8.fits"], 2, "only 8x8 pixels"),
    # images too small for any usable injection
    ("image_20x20", [RUN, "{in}/small20.fits"], 2, "too few injections possible"),
    ("image_16x5000", [RUN, "{in}/strip.fits"], 2, "no injection can be usable on this 5000x16 image"),
    ("image_16x5000_fwhm", [RUN, "{in}/strip.fits", "--fwhm", "3"], 2, "stamp (99.5% of its light) is 25x25"),
    ("fwhm_100", [RUN, "{in}/good.fits", "--fwhm", "100"], 2, "(--fwhm is in pixels: is that right?)"),
    ("too_few_injections", [RUN, "{in}/good.fits", "--density", "3", "--nsims", "1"], 2,
     "is 0.5 injections per kind"),
    ("density_1e6_memory", [RUN, "{in}/good.fits", "--density", "1e6", "--fwhm", "3"], 2,
     "the injections would need about"),
    # image facts given wrongly
    ("zp_nan", [RUN, "{in}/good.fits", "--zp", "nan"], 2, "zp=nan must be a finite number"),
    ("zp_inf", [RUN, "{in}/good.fits", "--zp", "inf"], 2, "zp=inf must be a finite number"),
    ("pixel_scale_zero", [RUN, "{in}/nowcs.fits", "--pixel-scale", "0"], 2, "pixel_scale=0.0 must be a positive"),
    ("fwhm_negative", [RUN, "{in}/good.fits", "--fwhm", "-2"], 2, "fwhm=-2.0 must be a positive"),
    ("gain_negative", [RUN, "{in}/good.fits", "--gain", "-1"], 2, "gain=-1.0 must be a positive"),
    ("saturation_zero", [RUN, "{in}/good.fits", "--saturation", "0"], 2, "saturation=0.0 must be a positive"),
    # companions
    ("mask_wrong_shape", [RUN, "{in}/good.fits", "--mask", "{in}/mask_wrong.fits"], 2,
     "has shape (64, 128) but the image"),
    ("mask_everything", [RUN, "{in}/good.fits", "--mask", "{in}/mask_all.fits"], 2,
     "is unusable (100% flagged in the mask)"),
    ("mask_missing", [RUN, "{in}/good.fits", "--mask", "{in}/nomask.fits"], 2, "mask file '{in}/nomask.fits' does "
                                                                               "not exist"),
    ("weight_wrong_shape", [RUN, "{in}/good.fits", "--weight", "{in}/weight_wrong.fits"], 2,
     "has shape (128, 64) but the image"),
    ("weight_all_zero", [RUN, "{in}/good.fits", "--weight", "{in}/weight_zero.fits"], 2,
     "is unusable (100% zero, negative or non-finite in the weight map"),
    ("weight_cut", [RUN, "{in}/good.fits", "--weight", "{in}/weight_cut.fits"], 2, "weight"),
    # configuration
    ("toml_section_is_value", [RUN, "{in}/good.fits", "--config", "{in}/section_value.toml"], 2,
     "'detection' in '{in}/section_value.toml' is a value (5)"),
    ("toml_invalid", [RUN, "{in}/good.fits", "--config", "{in}/invalid.toml"], 2, "is not valid TOML"),
    ("toml_unknown_table", [RUN, "{in}/good.fits", "--config", "{in}/unknown_table.toml"], 2,
     "unknown table(s) ['detektion']"),
    ("toml_unknown_key", [RUN, "{in}/good.fits", "--config", "{in}/unknown_key.toml"], 2,
     "Did you mean 'detection.thresh'"),
    ("toml_wrong_type", [RUN, "{in}/good.fits", "--config", "{in}/wrong_type.toml"], 2,
     "invalid injection.nsims = 'many'"),
    ("toml_binary", [RUN, "{in}/good.fits", "--config", "{in}/binary.toml"], 2, "is not a text file"),
    ("toml_is_folder", [RUN, "{in}/good.fits", "--config", "{in}/conf_dir.toml"], 2, "is a folder, not a file"),
    ("toml_missing", [RUN, "{in}/good.fits", "--config", "{in}/none.toml"], 2, "does not exist"),
    ("set_without_equals", [RUN, "{in}/good.fits", "--set", "detection.thresh"], 2, "write it as section.key=value"),
    ("set_unknown_section", [RUN, "{in}/good.fits", "--set", "detektion.thresh=2"], 2, "unknown section 'detektion'"),
    ("set_not_a_number", [RUN, "{in}/good.fits", "--set", "detection.thresh=abc"], 2, "invalid detection.thresh = 'abc'"),
    ("set_negative_thresh", [RUN, "{in}/good.fits", "--thresh", "-1"], 2, "invalid detection.thresh = -1.0"),
    ("nsims_zero", [RUN, "{in}/good.fits", "--nsims", "0"], 2, "invalid injection.nsims = 0"),
    ("nsims_negative", [RUN, "{in}/good.fits", "--nsims", "-3"], 2, "invalid injection.nsims = -3"),
    # (--density 0 is the automatic density, the default; not a number is refused)
    ("density_nan", [RUN, "{in}/good.fits", "--density", "nan"], 2, "invalid injection.density = nan"),
    ("density_inf", [RUN, "{in}/good.fits", "--density", "inf"], 2, "invalid injection.density = inf"),
    ("density_negative", [RUN, "{in}/good.fits", "--density", "-5"], 2, "invalid injection.density = -5.0"),
    ("unknown_kind", [RUN, "{in}/good.fits", "--kinds", "point,galaxy"], 2, "invalid injection.kinds"),
    ("unknown_model", [RUN, "{in}/good.fits", "--model", "no_such_model"], 2, "no_such_model"),
    ("unknown_purity_model", [RUN, "{in}/good.fits", "--set", "fit.purity_model=no_such_purity"], 2,
     "no_such_purity"),
    ("mag_range_reversed", [RUN, "{in}/good.fits", "--set", "injection.mag_range=[25,20]"], 2,
     "invalid injection.mag_range"),
    ("placement_unknown", [RUN, "{in}/good.fits", "--set", "injection.placement=hex"], 2,
     "invalid injection.placement = 'hex'"),
    ("filter_missing", [RUN, "{in}/good.fits", "--set", "detection.filter=/no/such.conv"], 2, "such.conv"),
    ("psf_file_missing", [RUN, "{in}/good.fits", "--set", "injection.psf=/no/psf.fits"], 2,
     "injection.psf='/no/psf.fits' is neither"),
    ("ncpu_zero", [RUN, "{in}/good.fits", "--ncpu", "0"], 2, "--ncpu 0 must be at least 1"),
    ("seed_negative", [RUN, "{in}/good.fits", "--seed", "-1"], 2, "invalid seed = -1"),
    # the output folder
    ("out_is_a_file", [RUN, "{in}/good.fits"], 2, "is an existing file, not a directory"),
    ("out_is_foreign", [RUN, "{in}/good.fits"], 2, "is not empty and is not a comest-bayes run"),
    ("out_holds_another_run", [RUN, "{in}/good.fits"], 2, "holds a different run"),
    ("out_in_use", [RUN, "{in}/good.fits"], 2, "is in use by another comest-bayes run (process {holder}"),
    ("out_unwritable", [RUN, "{in}/good.fits"], 2, "is not writable"),
    # the other subcommands
    ("demo_size_small", ["demo", "--size", "100"], 2, "--size 100 is too small"),
    ("report_missing_dir", ["report", "{in}/no_run"], 2, "no_run"),
    ("info_missing_dir", ["info", "{in}/no_run"], 2, "run directory '{in}/no_run' does not exist"),
    ("info_not_a_run", ["info", "{in}"], 2, "is not a comest-bayes run directory (no run.json)"),
    ("fit_missing_table", ["fit", "{in}/no_table.fits"], 2, "does not exist"),
]

#: How each "out_*" case prepares --out before the run (and whether --out is given at all).
OUT_SETUP = {"out_is_a_file", "out_is_foreign", "out_holds_another_run", "out_in_use", "out_unwritable"}
NO_OUT = {"report_missing_dir", "info_missing_dir", "info_not_a_run"}


def _prepare_out(case: str, tmp_path: Path) -> tuple[Path, dict]:
    """The --out path of a case, created as the case needs; returns it and the format fields."""
    out = tmp_path / "out"
    fields = {}
    if case == "out_is_a_file":
        out.write_text("a file the user keeps")
    elif case == "out_is_foreign":
        out.mkdir()
        (out / "notes.txt").write_text("precious")
    elif case == "out_holds_another_run":
        from comest_bayes.io.rundir import RunDirectory

        RunDirectory(out, {"input": {}, "config": {"seed": 99}}).open().release()
    elif case == "out_in_use":
        # a live process other than this one holds the lock: the parent of this test process
        out.mkdir()
        holder = os.getppid()
        (out / "run.lock").write_text(json.dumps({"pid": holder, "host": socket.gethostname(), "proc_start": None,
                                                  "started": "2030-01-01T00:00:00+00:00"}))
        fields["holder"] = holder
    elif case == "out_unwritable":
        if os.geteuid() != 0:
            (tmp_path / "ro").mkdir()
            (tmp_path / "ro").chmod(0o500)
            out = tmp_path / "ro" / "out"
        else:
            sysfs = Path("/sys")
            if not sysfs.is_dir():
                pytest.skip("needs a folder root cannot write to (/sys)")
            try:
                (sysfs / "comest-bayes-probe").mkdir()
            except OSError:
                out = sysfs / "comest-bayes-test-out"
            else:
                (sysfs / "comest-bayes-probe").rmdir()
                pytest.skip("root can write to /sys here")
    return out, fields


def _run(argv) -> int:
    try:
        return main(argv)
    except SystemExit as exc:  # argparse
        return exc.code


@pytest.mark.parametrize("case, argv, code, message", CASES, ids=[c[0] for c in CASES])
def test_bad_input_gets_one_error_line_and_writes_nothing(inputs, tmp_path, monkeypatch, capsys, case, argv, code,
                                                          message):
    monkeypatch.setenv("COMEST_BAYES_MEMORY_GB", "4")  # the memory refusal does not depend on this machine
    monkeypatch.chdir(tmp_path)  # anything written by mistake lands where the test looks
    out, fields = _prepare_out(case, tmp_path)
    fields["in"] = str(inputs)
    before_inputs = _checksums(inputs)
    before_out = _snapshot(out)
    before_cwd = sorted(p.name for p in tmp_path.iterdir())
    args = [a.format(**fields) for a in argv]
    if case not in NO_OUT:
        args += ["--out", str(out)]
    got = _run(args)
    captured = capsys.readouterr()
    err_lines = [line for line in captured.err.splitlines() if line.strip()]
    assert got == code, captured.err
    assert len(err_lines) == 1 and err_lines[0].startswith("error: "), captured.err
    assert message.format(**fields) in err_lines[0]
    assert "Traceback" not in captured.err + captured.out
    assert _snapshot(out) == before_out, "the output folder changed"
    assert sorted(p.name for p in tmp_path.iterdir()) == before_cwd, "something was written"
    assert _checksums(inputs) == before_inputs, "an input file changed"


def test_the_corpus_is_large_enough():
    assert len(CASES) >= 40
    assert len({c[0] for c in CASES}) == len(CASES)


def test_argparse_mistakes_exit_2_with_usage(inputs, tmp_path, capsys):
    assert _run(["run", str(inputs / "good.fits"), "--out", str(tmp_path / "o"), "--nsims", "many"]) == 2
    err = capsys.readouterr().err
    assert "error: argument --nsims: invalid int value: 'many'" in err
    assert not (tmp_path / "o").exists()


# ------------------------------------------------------------------------------ operating-system failures

def _unshare_available() -> bool:
    if not sys.platform.startswith("linux") or shutil.which("unshare") is None:
        return False
    probe = subprocess.run(["unshare", "-rm", "true"], capture_output=True)
    return probe.returncode == 0


needs_unshare = pytest.mark.skipif(not _unshare_available(),
                                   reason="needs unshare -rm (a private mount namespace) for a tmpfs of known size")


def _cli_in_namespace(mount_options: str, mountpoint: Path, argv: list[str]) -> subprocess.CompletedProcess:
    """Run the CLI in a private mount namespace with a tmpfs mounted at ``mountpoint``."""
    cli = [sys.executable, "-m", "comest_bayes.cli"] + argv
    script = (f"mount -t tmpfs -o {mount_options} tmpfs {mountpoint} && exec "
              + " ".join(f"'{a}'" for a in cli))
    return subprocess.run(["unshare", "-rm", "sh", "-c", script], capture_output=True, text=True, timeout=300)


@needs_unshare
def test_a_full_disk_is_one_error_line_naming_the_file(inputs, tmp_path):
    disk = tmp_path / "disk"
    disk.mkdir()
    before = _checksums(inputs)
    # 96 kB: run.json and the lock fit, the detection catalog and maps do not
    done = _cli_in_namespace("size=96k", disk, ["run", str(inputs / "good.fits"), "--out", str(disk / "run"),
                                                "--fwhm", "3", "--model", "none", "--quiet"])
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode != 0
    assert len(lines) == 1 and lines[0].startswith("error: could not write '" + str(disk / "run") + "/"), done.stderr
    assert "No space left on device" in lines[0] or "Not enough space on disk" in lines[0]
    assert "Traceback" not in done.stderr
    assert _checksums(inputs) == before


@needs_unshare
def test_a_read_only_out_is_refused_before_any_work(inputs, tmp_path):
    mount = tmp_path / "ro"
    mount.mkdir()
    done = _cli_in_namespace("ro,size=1m", mount, ["run", str(inputs / "good.fits"), "--out", str(mount / "run"),
                                                   "--fwhm", "3"])
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == 2
    assert len(lines) == 1 and "is not writable" in lines[0] and "Read-only file system" in lines[0], done.stderr
    assert "detect:" not in done.stdout  # refused before the detection ran
