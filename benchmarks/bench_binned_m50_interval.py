"""Benchmark: does the binned m50's uncertainty (``ratios.binned.magnitude_at_sd``) cover the truth at every N?

Draws outcome tables from a known completeness (a logistic with plateau and floor, injections uniform over
a magnitude range, as a run's are), bins them in 0.1-mag bins, and counts how often ``|m50 - truth| <= sd``
for the package's spread of the first crossing and for the delta method on the two bins interpolated (the
rule before 2026-11-29, computed here).  Nominal: 0.68.  Prints per N the RMSE of the binned m50, the
median of each sd and each coverage.

Usage::

    python benchmarks/bench_binned_m50_interval.py [--sizes 50 150 500 1500 5000 20000] [--reps 300]
        [--out benchmarks/results/binned_m50_interval.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def delta_sd(ratio, level=0.5) -> float:
    """The former rule: first-order propagation of the two interpolated bins' binomial noise."""
    from comest_bayes.ratios.binned import _crossing_points

    ok = ratio.n > 0
    c, f, n = ratio.centers[ok], ratio.ratio[ok], ratio.n[ok].astype(float)
    rows, i_, j_ = _crossing_points(f[None, :], level)
    if rows.size == 0:
        return float("nan")
    i, j = int(i_[0]), int(j_[0])
    span, gap = c[j] - c[i], f[i] - f[j]
    grad = np.array([span * (level - f[j]), span * (f[i] - level)]) / gap ** 2
    fb, nb = f[[i, j]], n[[i, j]]
    pq = fb * (1.0 - fb)
    return float(np.sqrt(np.sum(grad ** 2 * np.where(pq > 0, pq, 1.0 / nb) / nb)))


def main(argv=None) -> int:
    from scipy import special

    from comest_bayes.ratios import binned as R

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", nargs="+", type=int, default=[50, 150, 500, 1500, 5000, 20000])
    p.add_argument("--reps", type=int, default=300)
    p.add_argument("--m50", type=float, default=24.0)
    p.add_argument("--width", type=float, default=0.15, help="logistic width, mag")
    p.add_argument("--plateau", type=float, default=0.97)
    p.add_argument("--floor", type=float, default=0.01)
    p.add_argument("--range", nargs=2, type=float, default=[21.0, 26.0], help="injected magnitudes")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--out", default=None)
    a = p.parse_args(argv)

    lo, hi = a.range
    edges = R.magnitude_edges(lo, hi, 0.1)
    truth = a.m50 + a.width * np.log((a.plateau - 0.5) / (0.5 - a.floor))  # where f = 1/2
    rng = np.random.default_rng(a.seed)
    rows = []
    print(f"logistic m50 {a.m50}, w {a.width}, plateau {a.plateau}, floor {a.floor}; injections uniform over "
          f"[{lo}, {hi}], 0.1-mag bins; {a.reps} tables per N; truth m50 {truth:.4f}")
    for n in a.sizes:
        t0 = time.process_time()
        est, new, old = [], [], []
        for rep in range(a.reps):
            m = rng.uniform(lo, hi, n)
            det = rng.random(n) < a.floor + (a.plateau - a.floor) * special.expit((a.m50 - m) / a.width)
            res = R.completeness(m, det, edges)
            est.append(R.magnitude_at(res, 0.5))
            new.append(R.magnitude_at_sd(res, 0.5, seed=rep))
            old.append(delta_sd(res, 0.5))
        est, new, old = map(np.asarray, (est, new, old))
        err = np.abs(est - truth)
        row = {"n": n, "reps": a.reps, "defined": float(np.mean(np.isfinite(est))),
               "rmse": float(np.sqrt(np.nanmean(err ** 2))),
               "sd_median": float(np.nanmedian(new)), "coverage": float(np.mean(err[np.isfinite(new)] <= new[np.isfinite(new)])),
               "delta_sd_median": float(np.nanmedian(old)),
               "delta_coverage": float(np.mean(err[np.isfinite(old)] <= old[np.isfinite(old)])),
               "cpu_seconds_per_table": (time.process_time() - t0) / a.reps}
        rows.append(row)
        print(f"N {n:6d}: m50 RMSE {1000 * row['rmse']:7.1f} mmag | spread of the first crossing: median "
              f"{1000 * row['sd_median']:7.1f} mmag, coverage {row['coverage']:.2f} | delta method: median "
              f"{1000 * row['delta_sd_median']:6.1f} mmag, coverage {row['delta_coverage']:.2f} | "
              f"{1000 * row['cpu_seconds_per_table']:.1f} ms per table", flush=True)
    if a.out:
        Path(a.out).write_text(json.dumps({"settings": vars(a), "truth_m50": truth, "rows": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
