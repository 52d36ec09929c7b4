"""How the injection density changes the completeness measured on a crowded field.

Runs point-source injections on the shared 2MASS Galactic-centre frame (injected on the observed
image, ``--model none``) at several densities, and prints the binned completeness per 0.5-mag bin
of each, with the binomial standard error.  On a crowded field the injections add to the crowding
they measure, and they lift the background meshes of each realization's detection: the
completeness falls with their number.  This is the measurement behind
``comest_bayes.pipeline.preflight.MAX_PER_BACKGROUND_MESH``.

    python benchmarks/bench_crowded_density.py --work /tmp/crowded_density
    python benchmarks/bench_crowded_density.py --runs RUN_DIR [RUN_DIR ...]   # tabulate existing runs

Each run directory resumes, so an interrupted benchmark continues where it stopped.  The default
densities are 1.393 per arcmin^2 (5021 per realization: what the placement holds, the automatic
density before the ceiling; 40 per 64-pixel mesh), 0.14 (505; 4 per mesh), 0.0444 (160; the
ceiling of 1.25 per mesh) and 0.0148 (53), with 4, 40, 100 and 300 realizations (about 20,000,
20,000, 16,000 and 16,000 injections; about 70 min on two cores, nearly all of it the 400
detections of the last two).
"""

from __future__ import annotations

import argparse
import glob
import json
import sys
from pathlib import Path

import numpy as np
from astropy.io import fits

IMAGE = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "crowded" / "2mass_k_galactic_center_720px.fits"
RUNS = ((1.393, 4), (0.14, 40), (0.0444, 100), (0.0148, 300))  # (per arcmin^2, realizations)
MESHES = 721 * 720 / 64 ** 2


def run_one(work: Path, image: Path, density: float, nsims: int, ncpu: int) -> Path:
    from comest_bayes.cli import main

    out = work / f"density_{density:g}"
    # the range and separation pinned to those these runs were measured with (m5 - 5 to m5 + 1.5, 4 FWHM = 6 px):
    # the automatic range now starts at 4.4 mag on this confused field, with a wider separation
    # (docs/injection.md, "The range on a confused field")
    args = ["run", str(image), "--fwhm", "1.5", "--set", "injection.on=observed", "--density", str(density),
            "--set", "injection.mag_range=[8.61,15.11]", "--set", "injection.min_sep=30",
            "--nsims", str(nsims), "--kinds", "point", "--model", "none", "--no-report", "--ncpu", str(ncpu),
            "--quiet", "--out", str(out)]
    if main(args) != 0:
        raise SystemExit(f"the run at density {density} failed: comest-bayes {' '.join(args)}")
    return out


def outcomes(run: Path):
    """(mag, detected, per realization) of a run's usable point injections, from its realization files."""
    mags, det = [], []
    files = sorted(glob.glob(str(run / "sims" / "point" / "*.fits")))
    for f in files:
        t = fits.getdata(f, "TRUTH")
        use = np.asarray(t["usable"], bool)
        mags.append(np.asarray(t["mag"], float)[use])
        det.append(np.asarray(t["detected"], bool)[use])
    if not files:
        raise SystemExit(f"{run}: no point realizations under sims/point")
    return np.concatenate(mags), np.concatenate(det), sum(len(m) for m in mags) / len(files)


def table(runs: list[Path], edges) -> str:
    data = [outcomes(r) for r in runs]
    head = "mag      " + "  ".join(f"{r.name[-22:]:>22s}" for r in runs)
    sub = "         " + "  ".join(f"{f'{per:.0f}/real., {per / MESHES:.2f}/mesh':>22s}" for _, _, per in data)
    lines = [head, sub]
    for lo, hi in zip(edges[:-1], edges[1:]):
        row = []
        for m, d, _ in data:
            s = (m >= lo) & (m < hi)
            n = int(s.sum())
            if n == 0:
                row.append(" " * 22)
                continue
            f = d[s].mean()
            row.append(f"{f:6.3f} +- {np.sqrt(max(f * (1 - f), 0.25 / n) / n):5.3f} ({n:5d})")
        lines.append(f"{lo:4.1f}-{hi:4.1f} " + "  ".join(row))
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, help="directory for the run directories (resumed when present)")
    ap.add_argument("--runs", type=Path, nargs="+", help="tabulate these existing run directories instead")
    ap.add_argument("--image", type=Path, default=IMAGE)
    ap.add_argument("--ncpu", type=int, default=2)
    ap.add_argument("--out", type=Path, help="also write the table to this text file")
    a = ap.parse_args(argv)
    if a.runs:
        runs = a.runs
    elif a.work:
        if not a.image.is_file():
            raise SystemExit(f"{a.image} not found: this benchmark needs ../shared/data (or --image)")
        a.work.mkdir(parents=True, exist_ok=True)
        runs = [run_one(a.work, a.image, d, n, a.ncpu) for d, n in RUNS]
    else:
        ap.error("give --work (run the benchmark) or --runs (tabulate runs)")
    text = table(runs, np.arange(8.6, 15.11, 0.5))  # the pinned range, 8.61-15.11
    for r in runs:
        state = json.loads((r / "run.json").read_text())
        choice = (state.get("injection_density") or {}).get("point", {})
        text += f"\n{r}: {choice.get('reason', '?')}"
    print(text)
    if a.out:
        a.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
