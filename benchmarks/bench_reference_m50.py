"""How accurate is the held-out pool's reference m50?  (bias and scatter on stand-in truths)

``bench_speed_accuracy.py`` scores every estimate of m50 against a reference taken from a third of
its injection pool, held out from the budgets.  Its error is common to every method scored, so a
reference that leans the way one method leans flatters that method.  This script measures the two
references the benchmark has used on truths of each pool's own shape:

* ``binned``: the 0.05-mag binned ratio, m50 by linear interpolation between bin centres (the
  benchmark's reference until 2026-11-28);
* ``local``: ``bench_speed_accuracy.local_m50``, a degree-4 polynomial in logit f fitted by maximum
  likelihood to the unbinned outcomes within (m10 - m90) of the binned m50 (the reference since
  then).  Its delta-method sd is checked too (the fraction of simulated pools whose
  reference lies within 1 sd of the truth).

Stand-in truths, for each pool (``--run``, a pool's run directory):

* ``flux probit``: ``A * Phi((F / F50 - 1) / s)`` with ``F = 10^(-0.4 m)``, fitted to the held-out
  pool: the transition of a noisy flux threshold, the shape SEP has on white noise;
* ``pool curve``: a monotone PCHIP through the whole pool's 0.05-mag binned curve, whatever
  shape the pool has (it carries the bins' own smoothing, which does not matter for a truth).

Each simulated pool draws detections at the held-out pool's own magnitudes from the truth.  The
noise-free bias of each reference is printed too: for the binned one from the truth's bin averages
(quadrature), for the local one from the fit to the truth's own probabilities at the held-out
magnitudes (the limit of infinitely many pools).

    python benchmarks/bench_reference_m50.py --run /work/pools/sa_narrow_big/analytic_run --reps 100
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from astropy.table import Table
from scipy.integrate import quad
from scipy.interpolate import PchipInterpolator
from scipy.optimize import brentq, minimize
from scipy.special import expit, log_ndtr, ndtr

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_speed_accuracy import REF_BIN_WIDTH, local_m50, pool_reference  # noqa: E402

from comest_bayes.ratios import binned as R  # noqa: E402


def read_pool(run: Path):
    cat = next((run / "catalogs").glob("*_outcomes.fits"))
    out = Table.read(cat)
    mag_range = tuple(json.loads((run / "run.json").read_text())["stages"]["baseline"]["mag_range"])
    held = np.asarray(out["realization"]) % 3 == 0
    return np.asarray(out["mag"], float), np.asarray(out["detected"], bool), held, mag_range


def flux_probit_truth(mag, det, m50_guess: float):
    """Maximum-likelihood ``A * Phi((10^(-0.4 (m - m50)) - 1) / s)``; returns the curve as a function."""
    def nll(p):
        m50, log_s, logit_a = p
        z = (10 ** (-0.4 * (mag - m50)) - 1.0) / np.exp(log_s)
        log_a = -np.logaddexp(0.0, -logit_a)
        lp = log_a + log_ndtr(z)
        return -np.sum(np.where(det, lp, np.log1p(-np.exp(lp) + 1e-300)))
    best = minimize(nll, [m50_guess, np.log(0.1), 5.0], method="Nelder-Mead",
                    options={"xatol": 1e-7, "fatol": 1e-4, "maxiter": 4000}).x
    m50, log_s, logit_a = best
    return lambda m: expit(logit_a) * ndtr((10 ** (-0.4 * (np.asarray(m) - m50)) - 1.0) / np.exp(log_s))


def pool_curve_truth(mag, det, mag_range):
    """A monotone PCHIP through the whole pool's 0.05-mag binned curve (running minimum made monotone)."""
    edges = R.magnitude_edges(mag_range[0], mag_range[1], REF_BIN_WIDTH)
    br = R.binned_ratio(mag, det, edges)
    ok = np.asarray(br.n) > 0
    x = (0.5 * (edges[:-1] + edges[1:]))[ok]
    y = np.minimum.accumulate(np.asarray(br.ratio, float)[ok])
    f = PchipInterpolator(x, y, extrapolate=False)
    return lambda m: np.clip(np.nan_to_num(f(np.clip(m, x[0], x[-1]))), 0.0, 1.0)


def noise_free_binned_m50(truth, mag_range) -> float:
    edges = R.magnitude_edges(mag_range[0], mag_range[1], REF_BIN_WIDTH)
    vals = np.array([quad(truth, a, b)[0] / (b - a) for a, b in zip(edges[:-1], edges[1:])])
    return float(R.first_crossing(0.5 * (edges[:-1] + edges[1:]), vals, 0.5))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--run", nargs="+", required=True, help="pool run directories (bench_speed_accuracy's <work>/<scene>_run)")
    p.add_argument("--reps", type=int, default=100, help="simulated pools per truth")
    p.add_argument("--seed", type=int, default=2026)
    p.add_argument("--out", default=None, help="JSON file for the figures")
    a = p.parse_args(argv)
    rng = np.random.default_rng(a.seed)
    report = {"reps": a.reps, "seed": a.seed, "pools": {}}
    for run in map(Path, a.run):
        mag, det, held, mag_range = read_pool(run)
        mh, dh = mag[held], det[held]
        ref = pool_reference(mh, dh, mag_range)
        print(f"{run}: {held.sum()} held-out injections; reference m50 binned {ref['m50_binned']:.5f}, "
              f"local {ref['m50']:.5f} +- {ref['m50_sd']:.5f} (window {ref['local_half_width']:.3f} mag)")
        rows = {}
        truths = {"flux probit": flux_probit_truth(mh, dh, ref["m50"]),
                  "pool curve": pool_curve_truth(mag, det, mag_range)}
        for name, truth in truths.items():
            m50_true = brentq(lambda m: float(truth(m)) - 0.5, ref["m50"] - 0.5, ref["m50"] + 0.5)
            bias_nf = noise_free_binned_m50(truth, mag_range) - m50_true
            pt = truth(mh)
            bias_nf_local = local_m50(mh, pt, m50_true, half_width=ref["local_half_width"])[0] - m50_true
            err = {"binned": [], "local": []}
            within = []
            for _ in range(a.reps):
                d = rng.random(len(mh)) < pt
                r = pool_reference(mh, d, mag_range)
                err["binned"].append(r["m50_binned"] - m50_true)
                err["local"].append(r["m50"] - m50_true)
                within.append(abs(r["m50"] - m50_true) <= r["m50_sd"])
            row = {"m50_true": m50_true, "binned_noise_free_bias": bias_nf, "local_noise_free_bias": bias_nf_local,
                   "local_within_1sd": float(np.mean(within))}
            print(f"  truth {name}: m50 {m50_true:.5f}; noise-free bias: binned reference {1e3 * bias_nf:+.2f}, "
                  f"local {1e3 * bias_nf_local:+.2f} mmag")
            for k, v in err.items():
                v = np.asarray(v)
                row[k] = {"bias": float(v.mean()), "bias_se": float(v.std(ddof=1) / np.sqrt(len(v))),
                          "sd": float(v.std(ddof=1)), "rmse": float(np.sqrt(np.mean(v ** 2)))}
                print(f"    {k:7s} bias {1e3 * v.mean():+.2f} +- {1e3 * v.std(ddof=1) / np.sqrt(len(v)):.2f}  "
                      f"sd {1e3 * v.std(ddof=1):.2f}  RMSE {1e3 * np.sqrt(np.mean(v ** 2)):.2f} mmag")
            print(f"    local reference within its 1-sd of the truth in {np.mean(within):.2f} of pools (0.68 nominal)")
            rows[name] = row
        report["pools"][str(run)] = {"held_out": int(held.sum()), "reference": {k: v for k, v in ref.items()
                                                                               if k not in ("grid", "curve")},
                                     "truths": rows}
    if a.out:
        Path(a.out).write_text(json.dumps(report, indent=1))
        print(f"written {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
