"""Does the automatic range find a confused field, and does its brighter start reach the plateau?

The automatic injection range runs from m5 - 5 to m5 + 1.5 (m5: the 5-sigma point-source depth).  On
a confused field the completeness falls from far above m5, and that range never sees its plateau.
The run then starts the range brighter (``comest_bayes.pipeline.preflight.confused_bright_end``): when
the detection footprints of the sources in the range's first 2 mag cover more than
``CONFUSION_RISE`` of the image, the range starts where the sources brighter than it cover
``CONFUSION_COVER``.

Three parts:

* ``--images``: the shared real images (../shared/data), each run through detection with one point
  realization (``--model none``); prints the confusion share each gets and the range chosen.
* ``--galaxies``: demo tiles (``comest_bayes.sim.demo``, 1000 x 1000, 0.26"/px, 0.9" Moffat seeing)
  whose galaxy counts are multiplied by ``GALAXY_DENSITIES``; point sources and bulge+disk galaxies
  injected on the observed image, with the automatic range and, on a confused field, the usual one.
  Prints, per kind, the completeness of the brightest 0.5 mag of each range and the binned m50.
* ``--stars``: synthetic star fields (768 x 768, 0.5"/px, Gaussian PSF of 3 px FWHM, white noise, counts
  rising as 10^(0.3 m) up to m5 + 2) at several densities.  Each is run with the automatic range and,
  when that is a confused field's, once more with the usual range (m5 - 5 to m5 + 1.5); point sources,
  injected on the observed image, ``--model none``.  Prints the completeness of the brightest 0.5 mag
  of each range and the binned m50.

    python benchmarks/bench_confusion.py --work /tmp/confusion --images --stars [--out FILE]

    python benchmarks/bench_confusion.py --work /tmp/confusion --galaxies --nsims 10 --ncpu 1

Run directories resume.  ``--images`` and ``--stars`` take about 15 minutes on two cores,
``--galaxies --nsims 10`` about 8 minutes on one.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
from astropy.io import fits
from astropy.table import Table

SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
#: (label, file, extra run options); zero points and seeing from ../shared/data/README.md.
IMAGES = (
    ("2MASS Galactic centre", "crowded/2mass_k_galactic_center_720px.fits",
     ["--fwhm", "1.5", "--set", "injection.on=observed"]),
    ("JWST Abell 2744", "jwst/jwst_nircam_f200w_a2744_glass_sci.fits", ["--fwhm", "2.46"]),
    ("KiDS r", "kids/kidsviking_waves_2600px_r.fits", ["--zp", "0", "--pixel-scale", "0.2", "--fwhm", "3.46"]),
    ("CTIO CDF-S", "misc/ctio_mosaic2_I_cdfs_512px_tpv.fits", ["--zp", "30", "--fwhm", "5.8"]),
    ("DECam N6", "decam/decam_r_N6_375x280_ooi.fits", ["--zp", "29.30", "--fwhm", "4"]),
)
SIZE, SCALE, FWHM, SIGMA, ZP = 768, 0.5, 3.0, 10.0, 30.0
#: Stars per arcmin^2 brighter than m5, one synthetic field each.
DENSITIES = (3.0, 10.0, 30.0, 100.0, 300.0, 1000.0)
SLOPE = 0.3  # d log10 N / dm of the star counts
#: Multipliers of the demo tile's galaxy counts (1 = its own, 106 galaxies per arcmin^2 down to m5 + 2).
GALAXY_DENSITIES = (1.0, 3.0, 10.0, 30.0)
GALAXY_TILE = 1000


def _run(args: list[str]) -> None:
    from comest_bayes.cli import main

    if main(args) != 0:
        raise SystemExit(f"comest-bayes {' '.join(args)} failed")


def write_star_field(path: Path, density: float, seed: int) -> float:
    """Write a synthetic star field (:func:`comest_bayes.sim.starfield.star_field`); returns its m5."""
    from comest_bayes.sim.starfield import star_field

    hdu, facts = star_field((SIZE, SIZE), density, pixel_scale=SCALE, fwhm_pix=FWHM, sigma=SIGMA, zeropoint=ZP,
                            slope=SLOPE, seed=seed)
    hdu.writeto(path, overwrite=True)
    return facts["m5"]


def bright_end(run: Path, width: float = 0.5, kind: str = "point") -> tuple[float, int, float]:
    """(completeness of the brightest ``width`` mag of injections, their number, binned m50) of a run."""
    t = Table.read(run / "catalogs" / f"{kind}_outcomes.fits")
    mag, det = np.asarray(t["mag"], float), np.asarray(t["detected"], bool)
    sel = mag < mag.min() + width
    summary = json.loads((run / "summary.json").read_text())
    m50 = summary["kinds"][kind].get("m50_binned")
    return float(det[sel].mean()), int(sel.sum()), float("nan") if m50 is None else float(m50)


def images_part(work: Path, ncpu: int) -> list[str]:
    lines = ["real images (one point realization each; confusion share = footprints of the sources detected in "
             "the usual range's first 2 mag)",
             f"{'image':24s} {'m5':>7s} {'share':>7s} {'rule':>9s}  range"]
    for label, rel, extra in IMAGES:
        image = SHARED / rel
        if not image.is_file():
            lines.append(f"{label:24s} missing ({image})")
            continue
        out = work / ("image_" + label.split()[0].lower())
        _run(["run", str(image), *extra, "--nsims", "1", "--kinds", "point", "--model", "none", "--no-report",
              "--ncpu", str(ncpu), "--quiet", "--out", str(out)])
        state = json.loads((out / "run.json").read_text())
        rec = state["injection_range"]
        lo, hi = rec["mag_range"]
        lines.append(f"{label:24s} {rec.get('m5', float('nan')):7.2f} {rec.get('confusion_rise', float('nan')):7.4f} "
                     f"{rec['rule']:>9s}  {lo:.2f}-{hi:.2f}")
    return lines


def stars_part(work: Path, ncpu: int, nsims: int) -> list[str]:
    lines = [f"synthetic star fields ({SIZE}^2, {SCALE}\"/px, FWHM {FWHM} px, {nsims} point realizations per run; "
             "completeness of each range's brightest 0.5 mag, +- binomial sd)",
             f"{'stars/arcmin^2 < m5':>20s} {'share':>7s} {'rule':>9s} {'automatic range':>16s} {'f bright':>15s} "
             f"{'m50':>6s} | {'usual range':>12s} {'f bright':>15s} {'m50':>6s}"]
    for i, density in enumerate(DENSITIES):
        image = work / f"stars_{density:g}.fits"
        if not image.is_file():
            write_star_field(image, density, seed=100 + i)
        common = ["--set", "injection.on=observed", "--nsims", str(nsims), "--kinds", "point", "--model", "none",
                  "--no-report", "--ncpu", str(ncpu), "--quiet", "--fwhm", str(FWHM)]
        auto = work / f"stars_{density:g}_auto"
        _run(["run", str(image), *common, "--out", str(auto)])
        rec = json.loads((auto / "run.json").read_text())["injection_range"]
        f_a, n_a, m50_a = bright_end(auto)
        sd_a = math.sqrt(f_a * (1 - f_a) / n_a)
        row = (f"{density:20g} {rec.get('confusion_rise', float('nan')):7.4f} {rec['rule']:>9s} "
               f"{rec['mag_range'][0]:7.2f}-{rec['mag_range'][1]:.2f} {f_a:7.3f} +- {sd_a:.3f} {m50_a:6.2f}")
        if rec["rule"] == "confused":
            usual = work / f"stars_{density:g}_usual"
            rng = f"injection.mag_range=[{rec['usual_bright']},{rec['mag_range'][1]}]"
            _run(["run", str(image), *common, "--set", rng, "--out", str(usual)])
            f_u, n_u, m50_u = bright_end(usual)
            sd_u = math.sqrt(f_u * (1 - f_u) / n_u)
            row += f" | {rec['usual_bright']:5.2f}-{rec['mag_range'][1]:.2f} {f_u:7.3f} +- {sd_u:.3f} {m50_u:6.2f}"
        lines.append(row)
    return lines


def write_galaxy_field(directory: Path, multiplier: float, seed: int) -> Path:
    """Write a demo tile with ``multiplier`` times its galaxy counts; returns the image's path."""
    from comest_bayes.sim.demo import make_demo_tile, write_demo_tile

    paths = write_demo_tile(make_demo_tile(seed=seed, size=GALAXY_TILE, galaxy_density=multiplier), directory)
    return paths["image"]


def galaxies_part(work: Path, ncpu: int, nsims: int) -> list[str]:
    kinds = ("point", "buldisk")
    lines = [f"demo tiles with more galaxies ({GALAXY_TILE}^2, 0.26\"/px, 0.9\" seeing; {nsims} realizations of "
             "point sources and bulge+disk galaxies on the observed image; completeness of each range's "
             "brightest 0.5 mag, +- binomial sd)",
             f"{'galaxies x':>10s} {'per arcmin^2':>12s} {'share':>7s} {'rule':>9s} {'kind':>8s} {'automatic range':>16s} "
             f"{'f bright':>15s} {'m50':>6s} | {'usual range':>12s} {'f bright':>15s} {'m50':>6s}"]
    for i, mult in enumerate(GALAXY_DENSITIES):
        inputs = work / f"galaxies_{mult:g}"
        image = inputs / "demo_image.fits"
        if not image.is_file():
            write_galaxy_field(inputs, mult, seed=200 + i)
        kind_col = np.char.strip(np.asarray(Table.read(inputs / "demo_truth.fits")["kind"]).astype(str))
        ngal = int(np.count_nonzero(kind_col == "galaxy"))
        area = (GALAXY_TILE * float(fits.getheader(image)["PIXSCALE"]) / 60.0) ** 2  # arcmin^2
        common = ["--weight", str(inputs / "demo_weight.fits"), "--mask", str(inputs / "demo_mask.fits"),
                  "--set", "injection.on=observed", "--nsims", str(nsims), "--kinds", ",".join(kinds),
                  "--fwhm", "3.46", "--model", "none", "--no-report", "--ncpu", str(ncpu), "--quiet"]
        auto = work / f"galaxies_{mult:g}_auto"
        _run(["run", str(image), *common, "--out", str(auto)])
        rec = json.loads((auto / "run.json").read_text())["injection_range"]
        usual = None
        if rec["rule"] == "confused":
            usual = work / f"galaxies_{mult:g}_usual"
            rng = f"injection.mag_range=[{rec['usual_bright']},{rec['mag_range'][1]}]"
            _run(["run", str(image), *common, "--set", rng, "--out", str(usual)])
        for kind in kinds:
            f_a, n_a, m50_a = bright_end(auto, kind=kind)
            row = (f"{mult:10g} {ngal / area:12.0f} {rec.get('confusion_rise', float('nan')):7.4f} {rec['rule']:>9s} "
                   f"{kind:>8s} {rec['mag_range'][0]:7.2f}-{rec['mag_range'][1]:.2f} {f_a:7.3f} +- "
                   f"{math.sqrt(f_a * (1 - f_a) / n_a):.3f} {m50_a:6.2f}")
            if usual is not None:
                f_u, n_u, m50_u = bright_end(usual, kind=kind)
                row += (f" | {rec['usual_bright']:5.2f}-{rec['mag_range'][1]:.2f} {f_u:7.3f} +- "
                        f"{math.sqrt(f_u * (1 - f_u) / n_u):.3f} {m50_u:6.2f}")
            lines.append(row)
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, required=True, help="directory for the images and runs (resumed)")
    ap.add_argument("--images", action="store_true", help="the shared real images")
    ap.add_argument("--stars", action="store_true", help="synthetic star fields")
    ap.add_argument("--galaxies", action="store_true", help="demo tiles with more galaxies")
    ap.add_argument("--nsims", type=int, default=20, help="realizations per star-field or galaxy-field run")
    ap.add_argument("--ncpu", type=int, default=2)
    ap.add_argument("--out", type=Path, help="also write the tables to this text file")
    a = ap.parse_args(argv)
    if not (a.images or a.stars or a.galaxies):
        ap.error("give --images, --stars, --galaxies or several")
    a.work.mkdir(parents=True, exist_ok=True)
    lines = []
    if a.images:
        lines += images_part(a.work, a.ncpu) + [""]
    if a.stars:
        lines += stars_part(a.work, a.ncpu, a.nsims) + [""]
    if a.galaxies:
        lines += galaxies_part(a.work, a.ncpu, a.nsims)
    text = "\n".join(lines)
    print(text)
    if a.out:
        a.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
