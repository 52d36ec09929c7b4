"""Benchmark: coverage of the completeness posterior on replicate synthetic data sets.

Every replicate draws N injections (magnitudes uniform in [22.5, 26.5], depth
``d ~ N(0, 0.3)`` mag) with outcomes from a known ``logistic_depth``
completeness (m50_0 = 24.5, w = 0.2, A = 0.97, floor = 0.01, beta_depth = 1),
fits the ``logistic_depth`` model (MAP, Laplace, and with ``--method emcee``
an emcee posterior to ``--min-ess``; with ``--method importance`` the way a run
samples a chosen model: binomial cells from ``compress_for``, then importance
sampling from the Laplace approximation with emcee as the fallback), and checks whether the central 68% and
95% posterior intervals contain the truth for m50 at the reference depth
(``m50_0``), m50 at a depth of +0.3 mag, and f at three magnitudes at that
depth.  The empirical coverage over replicates is compared with the nominal
level; a calibrated posterior gives Binomial(R, level) / R.

Usage::

    python benchmarks/bench_coverage.py [--nrep 200] [--n 1500] [--method emcee|laplace|importance]
        [--min-ess 1000] [--out benchmarks/results/coverage.json]

Writes the JSON and a PNG chart (nominal vs empirical coverage with binomial
99% bands) next to it.  Seeds are fixed: replicate r uses
``rng_for(seed, "coverage", r)``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
import warnings
from pathlib import Path

import numpy as np
from scipy import special, stats

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from comest_bayes.bayes.inference import fit, fit_map, laplace, sample_posterior  # noqa: E402
from comest_bayes.bayes.model import CompletenessModel
from comest_bayes.bayes.outcomes import Covariates, compress_for, uncompressed
from comest_bayes.seeding import int_seed_for, rng_for  # noqa: E402

TRUTH = {"m50_0": 24.5, "w": 0.2, "A": 0.97, "floor": 0.01, "beta_depth": 1.0}
DEPTH_QUERY = 0.3
MAGS = (24.3, 24.8, 25.1)
QUANTITIES = ["m50_0", "m50(d=0.3)"] + [f"f({m}, d=0.3)" for m in MAGS]
LEVELS = (0.5, 0.68, 0.8, 0.9, 0.95)


def true_f(m, d):
    z = (TRUTH["m50_0"] + TRUTH["beta_depth"] * d - m) / TRUTH["w"]
    return TRUTH["floor"] + (TRUTH["A"] - TRUTH["floor"]) * special.expit(z)


def truths() -> np.ndarray:
    return np.array([TRUTH["m50_0"], TRUTH["m50_0"] + TRUTH["beta_depth"] * DEPTH_QUERY,
                     *true_f(np.array(MAGS), DEPTH_QUERY)])


def replicate(seed: int, r: int, n: int):
    rng = rng_for(seed, "coverage", r)
    m = rng.uniform(22.5, 26.5, n)
    d = rng.normal(0.0, 0.3, n)
    return Covariates.make(m, depth=d), rng.random(n) < true_f(m, d)


def posterior_values(model, draws) -> np.ndarray:
    """Draws of the checked quantities, shape (S, 5)."""
    phys = model.transform(draws)
    f = model.prob(draws, Covariates.make(np.array(MAGS), depth=DEPTH_QUERY))
    m50_d = phys["m50_0"] + phys["beta_depth"] * DEPTH_QUERY
    return np.column_stack([phys["m50_0"], m50_d, f])


def fit_replicate(args, cov, det, seed: int):
    """The model, its posterior draws and the sampler's diagnostics (None for Laplace draws)."""
    if args.method == "importance":  # as a run samples its chosen model
        model = CompletenessModel("logistic_depth", compress_for("logistic_depth", cov, det))
        post = fit(model, seed=seed, nstarts=2, sampler="auto", min_ess=args.min_ess).posterior
        return model, post.samples, post.diagnostics
    model = CompletenessModel("logistic_depth", uncompressed(cov, det))
    mp = fit_map(model, seed=seed, nstarts=2)
    lap = laplace(model, mp.theta)
    if args.method == "emcee":
        post = sample_posterior(model, lap, seed=seed, min_ess=args.min_ess, chunk=300)
        return model, post.samples, post.diagnostics
    return model, rng_for(seed, "laplace").multivariate_normal(lap.mean, lap.cov, 4000), None


def run(args) -> dict:
    t_all = time.perf_counter()
    tv = truths()
    inside = {lev: np.zeros((args.nrep, tv.size), bool) for lev in LEVELS}
    seconds, converged, ess_min = [], [], []
    for r in range(args.nrep):
        t0 = time.perf_counter()
        cov, det = replicate(args.seed, r, args.n)
        seed = int_seed_for(args.seed, "fit", r)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model, draws, diag = fit_replicate(args, cov, det, seed)
        if diag is not None:
            converged.append(bool(diag.converged))
            ess_min.append(float(np.min(diag.ess)))
        values = posterior_values(model, draws)
        for lev in LEVELS:
            q = np.percentile(values, [50 * (1 - lev), 50 * (1 + lev)], axis=0)
            inside[lev][r] = (q[0] <= tv) & (tv <= q[1])
        seconds.append(time.perf_counter() - t0)
        if (r + 1) % 10 == 0:
            print(f"  {r + 1}/{args.nrep} replicates, {np.mean(seconds):.2f} s each", flush=True)
    table = []
    for lev in LEVELS:
        lo, hi = stats.binom.ppf([0.005, 0.995], args.nrep, lev) / args.nrep
        cover = inside[lev].mean(axis=0)
        table.append({"level": lev, "coverage": dict(zip(QUANTITIES, cover.round(4).tolist())),
                      "binomial_99": [float(lo), float(hi)],
                      "within": dict(zip(QUANTITIES, [bool(lo <= c <= hi) for c in cover]))})
    return {
        "nrep": args.nrep, "n_injections": args.n, "method": args.method, "min_ess": args.min_ess,
        "truth": TRUTH, "depth_query": DEPTH_QUERY, "mags": list(MAGS), "quantities": QUANTITIES,
        "table": table, "seconds_per_replicate": float(np.mean(seconds)),
        "total_seconds": time.perf_counter() - t_all,
        "sampler_converged_fraction": float(np.mean(converged)) if converged else None,
        "sampler_min_ess_median": float(np.median(ess_min)) if ess_min else None,
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count(), "load": os.getloadavg()},
    }


def chart(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    levels = np.array([row["level"] for row in result["table"]])
    fig, ax = plt.subplots(figsize=(5.5, 5))
    lo = np.array([row["binomial_99"][0] for row in result["table"]])
    hi = np.array([row["binomial_99"][1] for row in result["table"]])
    ax.fill_between(levels, lo, hi, color="0.85", label="binomial 99% range")
    ax.plot([0.45, 1.0], [0.45, 1.0], "k:", lw=1)
    for j, name in enumerate(result["quantities"]):
        cov = [row["coverage"][name] for row in result["table"]]
        ax.plot(levels + (j - 2) * 0.004, cov, "o-", ms=4, label=name)
    ax.set_xlabel("nominal coverage of the central interval")
    ax.set_ylabel("empirical coverage")
    ax.set_title(f"{result['nrep']} replicates x {result['n_injections']} injections ({result['method']})")
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--nrep", type=int, default=200)
    p.add_argument("--n", type=int, default=1500, help="injections per replicate")
    p.add_argument("--method", choices=("emcee", "laplace", "importance"), default="emcee")
    p.add_argument("--min-ess", type=float, default=1000)
    p.add_argument("--seed", type=int, default=2024)
    p.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" / "coverage.json"))
    args = p.parse_args(argv)
    result = run(args)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))
    chart(result, out.with_suffix(".png"))
    print(f"{'level':>6s} " + " ".join(f"{q:>15s}" for q in QUANTITIES) + "   binomial 99%")
    for row in result["table"]:
        print(f"{row['level']:>6.2f} " + " ".join(f"{row['coverage'][q]:>15.3f}" for q in QUANTITIES)
              + f"   [{row['binomial_99'][0]:.3f}, {row['binomial_99'][1]:.3f}]")
    print(f"{result['seconds_per_replicate']:.2f} s per replicate, total {result['total_seconds']:.0f} s; "
          f"wrote {out} and {out.with_suffix('.png')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
