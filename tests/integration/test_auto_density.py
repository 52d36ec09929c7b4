"""The automatic injection density in a whole run: chosen from the image, logged, recorded, used per kind."""

import json

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table

from comest_bayes.cli import main


@pytest.fixture()
def fine_small_image(tmp_path):
    # 640x640 white noise at 0.05"/px: 0.284 arcmin^2, 4.3 injections per realization at the published
    # 15 per arcmin^2; 100 background meshes of 64x64 pixels.
    rng = np.random.default_rng(5)
    path = tmp_path / "fine.fits"
    fits.writeto(path, rng.normal(0.0, 1.0, (640, 640)).astype(np.float32))
    return path


def _run(image, out, *extra):
    return main(["run", str(image), "--pixel-scale", "0.05", "--zp", "25", "--fwhm", "3", "--kinds", "point",
                 "--nsims", "3", "--model", "none", "--ncpu", "1", "--seed", "1", "--no-report", "--out", str(out),
                 *extra])


def test_a_small_fine_pixel_image_gets_a_quarter_injection_per_background_mesh(fine_small_image, tmp_path, capsys):
    out = tmp_path / "auto"
    assert _run(fine_small_image, out) == 0
    log = capsys.readouterr().out
    state = json.loads((out / "run.json").read_text())
    choice = state["injection_density"]["point"]
    area = 640 * 640 * (0.05 / 60) ** 2
    assert choice["source"] == "automatic" and choice["rule"] == "raised"
    assert choice["per_realization"] == pytest.approx(25.0) and choice["density"] == pytest.approx(25.0 / area)
    assert "density: point: " in log and "0.25 per 64x64 background mesh" in log
    # 3 x 25 = 75 expected, fewer usable (stamps must lie on the image): the run warns
    assert "warning: density: only about" in log and "usable point injections" in log
    # ... and after the run, with the number it got
    assert "warning: ratios: point: only " in log and "usable injections: its completeness and m50 are loose" in log
    injected = Table.read(out / "catalogs" / "point_injected.fits")
    # Poisson(25) per realization, 3 realizations: 75 +- 8.7 in all (3.5 sd); the published density
    # would have drawn about 13
    assert abs(len(injected) - 75) <= 30


def test_a_density_given_by_the_user_is_kept(fine_small_image, tmp_path, capsys):
    out = tmp_path / "user"
    assert _run(fine_small_image, out, "--density", "2000") == 0
    log = capsys.readouterr().out
    choice = json.loads((out / "run.json").read_text())["injection_density"]["point"]
    area = 640 * 640 * (0.05 / 60) ** 2
    assert choice["source"] == "user" and choice["density"] == 2000.0
    assert "2000 per arcmin^2 as given" in log
    # 569 per realization on 100 background meshes: kept, with a warning that says what it risks
    assert choice["warning"].startswith("2000 per arcmin^2 puts 5.7 injections in each 64x64 background mesh")
    assert f"warning: density: point: {choice['warning']}" in log
    assert main(["info", str(out)]) == 0
    assert f"  - density (point): {choice['warning']}" in capsys.readouterr().out.splitlines()
    injected = Table.read(out / "catalogs" / "point_injected.fits")
    mean = 3 * 2000.0 * area  # 1707
    assert abs(len(injected) - mean) <= 3.5 * np.sqrt(mean)


def test_coarse_pixels_get_at_most_one_and_a_quarter_injections_per_background_mesh(fine_small_image, tmp_path,
                                                                                   capsys):
    # The same 640x640 pixels read as 2"/px: 455 arcmin^2, 6827 per realization at 15 per arcmin^2,
    # 990 held by the placement (12 px apart); 100 meshes hold 125 at the ceiling of 1.25 per mesh.
    out = tmp_path / "coarse"
    assert main(["run", str(fine_small_image), "--pixel-scale", "2", "--zp", "25", "--fwhm", "3", "--kinds", "point",
                 "--nsims", "2", "--model", "none", "--ncpu", "1", "--seed", "1", "--no-report",
                 "--out", str(out)]) == 0
    log = capsys.readouterr().out
    choice = json.loads((out / "run.json").read_text())["injection_density"]["point"]
    assert choice["source"] == "automatic" and choice["rule"] == "background cap"
    assert choice["per_realization"] == pytest.approx(125.0) and choice["warning"] is None
    assert "lowered further to 125, 1.25 per 64x64 background mesh" in log and "warning: density" not in log
    injected = Table.read(out / "catalogs" / "point_injected.fits")
    assert abs(len(injected) - 250) <= 3.5 * np.sqrt(250)  # Poisson(125) twice; the placement would give ~2000


def test_a_range_far_brighter_than_the_default_keeps_the_bright_injections_reach_apart(
        fine_small_image, tmp_path, capsys):
    from scipy.spatial import cKDTree

    # the default range (m5 - 5 to m5 + 1.5): the brightest injection's isophote (2 FWHM = 6 px) stays
    # within half the 12 px separation, so almost no injection falls within a brighter one's reach
    out = tmp_path / "default"
    assert _run(fine_small_image, out) == 0
    assert "warning: injection:" not in capsys.readouterr().out
    state = json.loads((out / "run.json").read_text())
    quiet = state["stages"]["baseline"]["bright_neighbours"]
    assert quiet["fraction"] < 1e-3 and quiet["radius_bright"] < 0.5 * quiet["min_sep_pix"] + 0.5
    assert state["injection_density"]["point"]["min_sep_arcsec"] is None
    lo, hi = state["stages"]["baseline"]["mag_range"]
    brighter = ["--set", f"injection.mag_range=[{lo - 5:.2f},{hi:.2f}]"]

    # five magnitudes brighter: the brightest spreads over 2.4 x the radius; the run keeps every pair
    # that reach apart (the brightest one's reach: twice its isophote's radius), so none is at risk
    out = tmp_path / "bright"
    assert _run(fine_small_image, out, *brighter) == 0
    log = capsys.readouterr().out
    state = json.loads((out / "run.json").read_text())
    choice = state["injection_density"]["point"]
    rec = state["stages"]["baseline"]["bright_neighbours"]
    assert rec["radius_bright"] > 2 * quiet["radius_bright"] and rec["fraction"] < 1e-6 and rec["warning"] is None
    assert choice["min_sep_arcsec"] == pytest.approx(2 * rec["radius_bright"] * 0.05, abs=1e-4)
    assert choice["min_sep_pix"] == pytest.approx(choice["min_sep_arcsec"] / 0.05)
    assert f'separation {choice["min_sep_arcsec"]:.3g}" ({choice["min_sep_pix"]:.1f} px) instead of 4 FWHM' in log
    assert "warning: injection:" not in log
    truth = Table.read(out / "catalogs" / "point_injected.fits")
    for r in set(truth["realization"]):
        xy = np.c_[truth["x"], truth["y"]][truth["realization"] == r]
        if len(xy) > 1:
            assert cKDTree(xy).query(xy, k=2)[0][:, 1].min() >= choice["min_sep_pix"] - 1e-6

    # a separation the user sets is kept; too small for the range, it gets a warning that says so
    out = tmp_path / "user_sep"
    assert _run(fine_small_image, out, *brighter, "--set", "injection.min_sep=0.6") == 0
    log = capsys.readouterr().out
    state = json.loads((out / "run.json").read_text())
    rec = state["stages"]["baseline"]["bright_neighbours"]
    assert state["injection_density"]["point"]["min_sep_arcsec"] is None and rec["min_sep_pix"] == pytest.approx(12)
    warned = [line for line in log.splitlines() if line.startswith("warning: injection: point injections brighter")]
    assert len(warned) == 1 and rec["fraction"] > 0.01
    assert f"about {100 * rec['fraction']:.0f}% of the injections" in warned[0]
    assert f"--set injection.min_sep={2 * rec['radius_bright'] * 0.05:.3g} (arcsec)" in warned[0]
    # `comest-bayes info` lists it with the run's other warnings
    assert main(["info", str(out)]) == 0
    assert f"  - injection: {warned[0].removeprefix('warning: injection: ')}" in capsys.readouterr().out.splitlines()
