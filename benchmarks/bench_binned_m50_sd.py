"""Benchmark: is the binned m50's standard deviation (``ratios.binned.magnitude_at_sd``) calibrated?

Draws disjoint subsets of N injections from the narrow-range white-noise pool of
``bench_speed_accuracy.py --work DIR`` (``DIR/analytic_run``; realizations not held out), bins
each subset's completeness in 0.1-mag bins over the pool's range as a run does, and compares
``(m50_binned - reference) / m50_binned_sd`` with a unit normal.  The reference is the m50 of the
held-out third of the pool (``--ref``; 25.3958 for the pools of the 2026-11 runs).  Prints, per N,
the fraction of |z| <= 1 and <= 2, the rms of z and the median sd, and how often the crossings of the
pointwise 68% Wilson bands (an interval not used) hold the reference.

Usage::

    python benchmarks/bench_binned_m50_sd.py --work /tmp/sa/work [--sizes 1000 3000 10000 30000] [--reps 60]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main(argv=None) -> int:
    from astropy.table import Table

    from comest_bayes.ratios import binned as R

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_speed_accuracy import phase_edges

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--work", required=True, help="bench_speed_accuracy.py --work directory")
    p.add_argument("--ref", type=float, default=25.3958, help="m50 of the held-out third of the pool")
    p.add_argument("--sizes", nargs="+", type=int, default=[1000, 3000, 10000, 30000])
    p.add_argument("--reps", type=int, default=60, help="at most this many disjoint subsets per size")
    p.add_argument("--bin", type=float, default=0.1, help="bin width, mag")
    p.add_argument("--phases", nargs="+", type=float, default=[0.0],
                   help="offsets of the bin grid (mag, 0 <= phase < --bin): the edges sit at the pool's brightest "
                        "magnitude + phase + k * bin; 0 is a run's grid.  On a transition narrower than a bin the "
                        "interpolated m50 is biased by an amount that depends on the phase, which the sd omits")
    a = p.parse_args(argv)

    o = Table.read(Path(a.work) / "analytic_run" / "catalogs" / "point_outcomes.fits")
    mag = np.asarray(o["mag"], float)
    det = np.asarray(o["detected"], bool)
    pool = np.random.default_rng(7).permutation(np.flatnonzero(np.asarray(o["realization"]) % 3 != 0))
    print(f"pool of {pool.size} injections (held out: {mag.size - pool.size}); reference m50 {a.ref:.4f}; "
          f"{a.bin:g}-mag bins")
    for phase in a.phases:
        if not 0 <= phase < a.bin:
            raise SystemExit(f"--phases: {phase} is outside [0, {a.bin})")
        edges = phase_edges((float(mag.min()), float(mag.max())), phase, a.bin)
        if len(a.phases) > 1 or phase > 0:
            print(f" grid phase {phase:.3f} mag (edges at {edges[0]:.3f} + k * {a.bin:g})")
        _score_sizes(R, mag, det, pool, edges, a)
    return 0


def _score_sizes(R, mag, det, pool, edges, a) -> None:
    for n in a.sizes:
        reps = min(a.reps, pool.size // n)
        z, sds, bands = [], [], []
        for r in range(reps):
            s = pool[r * n:(r + 1) * n]
            c = R.completeness(mag[s], det[s], edges)
            sd = R.magnitude_at_sd(c, 0.5)
            z.append((R.magnitude_at(c, 0.5) - a.ref) / sd)
            sds.append(sd)
            # the alternative not used: the crossings of the pointwise 68% Wilson bands as an interval
            bands.append(R.first_crossing(c.centers, c.lower, 0.5) <= a.ref <= R.first_crossing(c.centers, c.upper, 0.5))
        z = np.asarray(z)
        print(f"  N {n:6d}, {reps:3d} subsets: |z| <= 1 in {np.mean(np.abs(z) <= 1):.2f}, |z| <= 2 in "
              f"{np.mean(np.abs(z) <= 2):.2f}, rms z {np.sqrt(np.mean(z * z)):.2f}, mean z {np.mean(z):+.2f}, "
              f"median sd {1e3 * np.median(sds):.1f} mmag; 68% band crossings cover {np.mean(bands):.2f}")


if __name__ == "__main__":
    raise SystemExit(main())
