"""Benchmark: time of the completeness fit against the number of outcomes.

For N = 1e3 .. 1e6 injections drawn from a known ``logistic_depth``
completeness (magnitudes uniform in [22, 27], depth ``d ~ N(0, 0.3)`` mag),
and for the models ``logistic`` and ``logistic_depth``, measures in one
process per model:

* ``compress``: :func:`comest_bayes.bayes.outcomes.compress_for` (default grid),
  and the number of binomial cells G it gives;
* ``map``: :func:`comest_bayes.bayes.inference.fit_map` (6 starts), JAX compilation
  for the data shape included (it is paid once per fit in the pipeline too);
* ``laplace``: the Hessian and its inverse;
* ``emcee``: :func:`comest_bayes.bayes.inference.sample_posterior` until every
  parameter has ESS >= ``--min-ess`` (default 1000) and the chain is longer
  than 50 autocorrelation times.

Usage::

    python benchmarks/bench_fit.py [--sizes 1000 10000 100000 1000000] [--models logistic logistic_depth]
        [--min-ess 1000] [--out benchmarks/results/fit.json]

Writes the JSON and a PNG chart (seconds against N, one line per stage and
model) next to it.
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
from scipy import special

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from comest_bayes.bayes.inference import fit_map, laplace, sample_posterior  # noqa: E402
from comest_bayes.bayes.model import CompletenessModel
from comest_bayes.bayes.outcomes import Covariates, compress_for
from comest_bayes.seeding import rng_for  # noqa: E402


def simulate(n: int, seed: int):
    rng = rng_for(seed, "bench-fit", n)
    m = rng.uniform(22.0, 27.0, n)
    d = rng.normal(0.0, 0.3, n)
    f = 0.01 + 0.96 * special.expit((24.5 + d - m) / 0.2)
    return Covariates.make(m, depth=d), rng.random(n) < f


def one(model_name: str, n: int, min_ess: float, seed: int) -> dict:
    cov, det = simulate(n, seed)
    t0 = time.perf_counter()
    data = compress_for(model_name, cov, det)
    t1 = time.perf_counter()
    model = CompletenessModel(model_name, data)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mp = fit_map(model, seed=seed)
        t2 = time.perf_counter()
        lap = laplace(model, mp.theta)
        t3 = time.perf_counter()
        post = sample_posterior(model, lap, seed=seed, min_ess=min_ess)
        t4 = time.perf_counter()
    dg = post.diagnostics
    return {"model": model_name, "n": int(n), "cells": int(data.ncells), "compress": t1 - t0, "map": t2 - t1,
            "laplace": t3 - t2, "emcee": t4 - t3, "emcee_steps": int(dg.nsteps), "nwalkers": int(dg.nwalkers),
            "tau_max": float(np.max(dg.tau)), "ess_min": float(np.min(dg.ess)), "converged": bool(dg.converged),
            "m50_0": float(np.median(model.transform(post.samples)["m50_0"]))}


def chart(rows: list, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    styles = {"logistic": "-", "logistic_depth": "--"}
    colours = {"compress": "C0", "map": "C1", "laplace": "C2", "emcee": "C3"}
    for model in sorted({r["model"] for r in rows}):
        sub = sorted((r for r in rows if r["model"] == model), key=lambda r: r["n"])
        n = [r["n"] for r in sub]
        for stage, colour in colours.items():
            ax.loglog(n, [max(r[stage], 1e-3) for r in sub], styles.get(model, ":"), color=colour, marker="o",
                      ms=3, label=f"{stage} ({model})")
    ax.set_xlabel("number of outcomes N")
    ax.set_ylabel("wall time (s)")
    ax.set_title("completeness fit: time per stage")
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 100000, 1000000])
    p.add_argument("--models", nargs="+", default=["logistic", "logistic_depth"])
    p.add_argument("--min-ess", type=float, default=1000)
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" / "fit.json"))
    args = p.parse_args(argv)
    rows = []
    print(f"{'model':<16s} {'N':>8s} {'cells':>6s} {'compress':>9s} {'map':>7s} {'laplace':>8s} {'emcee':>7s} "
          f"{'steps':>6s} {'ESSmin':>7s}")
    for model in args.models:
        for n in args.sizes:
            r = one(model, n, args.min_ess, args.seed)
            rows.append(r)
            print(f"{model:<16s} {n:>8d} {r['cells']:>6d} {r['compress']:>9.3f} {r['map']:>7.2f} "
                  f"{r['laplace']:>8.2f} {r['emcee']:>7.2f} {r['emcee_steps']:>6d} {r['ess_min']:>7.0f}", flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    result = {"rows": rows, "min_ess": args.min_ess,
              "machine": {"python": platform.python_version(), "cpus": os.cpu_count(), "load": os.getloadavg()}}
    out.write_text(json.dumps(result, indent=2))
    chart(rows, out.with_suffix(".png"))
    print(f"wrote {out} and {out.with_suffix('.png')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
