"""Benchmark: number-count recovery, interval coverage, and the shortcuts it replaces.

Replicate mocks (fast path, no images)
--------------------------------------
Each replicate draws everything from known truths instead of rendering images.
Detection and photometry share their noise, as they do on an image: a source
is detected when a latent standard normal ``z`` falls below
``Phi^-1(f(m))``, and its measured magnitude is
``m + 0.02 + sigma(m) (rho z + sqrt(1 - rho^2) e)`` with ``rho = 0.7`` and
``e`` an independent normal.  So the completeness is exactly
``f(m) = 0.995 / (1 + exp((m - 23) / 0.3))`` in true magnitude, and the sources
detected near the limit are the ones whose noise made them look brighter
(flux boosting), as near-threshold detections do on real images.
``sigma(m) = 0.02 + 0.25 x 10**(0.4 (m - 23.5))`` (capped at 0.6) and 3% of the
detections are blends measured 0.75 mag too bright.

* injections: ``--ninj`` true magnitudes uniform in [19, 26], detected and
  measured that way; the completeness model ``logistic`` is fitted to their
  outcomes with the package's own machinery (:func:`comest_bayes.bayes.inference.fit`),
  giving a real :class:`~comest_bayes.bayes.posterior.CompletenessPosterior`, and the
  photometric transfer is measured from the detected ones
  (:mod:`comest_bayes.recover.transfer`);
* population: a power law ``log_n = 4.3`` (deg^-2 mag^-1 at m = 23),
  ``slope = 0.3`` over 17-28 on ``--area`` deg^2, detected and measured the same way.

Fitted on ``[20, 24)`` (measured; f(24) ~ 0.03, so the range reaches the detection limit) with:

``joint``      the full forward model, completeness sampled jointly;
``fixed``      the full forward model with the completeness held at its posterior median;
``no_transfer`` multiply the model by the completeness, ignore the photometric transfer;
``binned``     divide the binned counts (0.25 mag, measured magnitudes) by the binned
               completeness and fit a straight line to log10 of the corrected counts
               (weighted least squares, Poisson weights; Gaussian intervals).

Reported per method: mean bias of the slope and of log_n with its standard
error, mean posterior sd against the scatter of the medians, and the fraction
of replicates whose 68% and 95% intervals hold the truth (binomial standard
error ``sqrt(p (1 - p) / R)``).  The defaults (1000 injections against about
1,400 catalog objects in range; 1,361 on average in the last run) make the completeness uncertainty comparable to
the Poisson noise of the counts, which is where holding it fixed matters.
Replicates run in ``--workers`` processes; each is seeded from its index, so
the numbers do not depend on the worker count.

Rendered mock (end to end)
--------------------------
One demo tile (1000 x 1000 px) whose point sources follow the same power law
(``make_demo_tile(star_counts=(2e4, 0.3, 23))``, no galaxies), run through the
pipeline (4 point-source realizations, ``logistic`` completeness), then
:func:`comest_bayes.lf.fit.run_lf` in joint and fixed mode.

Usage::

    python benchmarks/bench_lf.py               # 48 replicates + the rendered mock, ~16 min on 2 cores
    python benchmarks/bench_lf.py --replicates 4 --no-render   # quick check

Writes ``benchmarks/results/lf.json`` and ``benchmarks/results/lf.png``.
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

TRUTH = {"log_n": 4.3, "slope": 0.3}
AREA = 0.05
RHO = 0.7
RANGE = (20.0, 24.0)
M50, W, A = 23.0, 0.3, 0.995
METHODS = ("joint", "fixed", "no_transfer", "binned")


def completeness(m):
    return A / (1.0 + np.exp((np.asarray(m) - M50) / W))


def detect_and_measure(rng, true):
    """Detection flags and measured magnitudes with shared noise (see the module docstring).

    The measured magnitude of an undetected source is NaN.
    """
    from scipy.special import ndtri

    z = rng.standard_normal(true.size)
    det = z < ndtri(completeness(true))
    sigma = np.minimum(0.02 + 0.25 * 10 ** (0.4 * (true - 23.5)), 0.6)
    noise = RHO * z + math.sqrt(1.0 - RHO**2) * rng.standard_normal(true.size)
    obs = true + 0.02 + sigma * noise
    blend = rng.random(true.size) < 0.03
    obs[blend] -= 0.75
    obs[~det] = np.nan
    return det, obs


def sample_powerlaw(rng, log_n, slope, area, lo, hi, m_ref=23.0):
    b = slope * math.log(10.0)
    expected = area * 10**log_n * (math.exp(b * (hi - m_ref)) - math.exp(b * (lo - m_ref))) / b
    u = rng.random(rng.poisson(expected))
    return lo + np.log1p(u * (math.exp(b * (hi - lo)) - 1.0)) / b


def fit_completeness(rng, ninj, seed):
    from comest_bayes.bayes.inference import fit
    from comest_bayes.bayes.model import CompletenessModel
    from comest_bayes.bayes.outcomes import compress_for, covariates_from_outcomes
    from comest_bayes.bayes.spec import load_spec
    from comest_bayes.bayes.posterior import CompletenessPosterior

    true = rng.uniform(19.0, 26.0, ninj)
    det, obs = detect_and_measure(rng, true)
    spec = load_spec("logistic")
    cov, outcome, meta = covariates_from_outcomes({"mag": true, "detected": det}, image_shape=None)
    data = compress_for(spec, cov, outcome, meta=meta)
    model = CompletenessModel(spec, data)
    res = fit(model, seed=seed, min_ess=300)
    post = CompletenessPosterior(spec=spec, samples=res.draws(), names=list(model.names),
                                 meta={"sigma_ref": None, "hlr_ref": None, "image_shape": (100, 100),
                                       "mag_range": [19.0, 26.0], "kind": "point", "quantity": "completeness"},
                                 footprint=np.array([[50.0, 50.0]]))
    return post, true[det], obs[det]


def binned_shortcut(obs, post, lo, hi, width=0.25, area=AREA):
    edges = np.arange(lo, hi + 1e-9, width)
    c = 0.5 * (edges[:-1] + edges[1:])
    n = np.histogram(obs, edges)[0].astype(float)
    f = np.median(post.average_curve(c, nsamples=300), axis=0)
    ok = n > 0
    y = np.log10(n[ok] / (f[ok] * area * width))
    sig = 1.0 / (math.log(10.0) * np.sqrt(n[ok]))
    x = c[ok] - 23.0
    wts = 1.0 / sig**2
    design = np.column_stack([np.ones_like(x), x])
    cov = np.linalg.inv(design.T @ (design * wts[:, None]))
    beta = cov @ design.T @ (wts * y)
    sd = np.sqrt(np.diag(cov))
    return {"log_n": (beta[0], sd[0]), "slope": (beta[1], sd[1])}


def replicate(r, ninj, min_ess, area=AREA):
    from comest_bayes.lf.model import build_inputs, fit_counts
    from comest_bayes.seeding import int_seed_for, rng_for
    from comest_bayes.recover.transfer import measure_transfer

    rng = rng_for(2024, "bench_lf", r)
    post, t_det, o_det = fit_completeness(rng, ninj, int_seed_for(2024, "bench_lf", "comp", r))
    tr = measure_transfer(t_det, o_det)
    pop = sample_powerlaw(rng, TRUTH["log_n"], TRUTH["slope"], area, 17.0, 28.0)
    det, obs = detect_and_measure(rng, pop)
    obs = obs[det]
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for method in ("joint", "fixed", "no_transfer"):
            inputs = build_inputs(obs, area_deg2=area, mag_range=RANGE,
                                  transfer=None if method == "no_transfer" else tr)
            mode = "joint" if method == "joint" else "fixed"
            res = fit_counts(inputs, "powerlaw", mode=mode, post=post, seed=r, min_ess=min_ess)
            s = res.parameter_summary()
            out[method] = {k: {q: s[k][q] for q in ("median", "sd", "lo68", "hi68", "lo95", "hi95")} for k in TRUTH}
        b = binned_shortcut(obs, post, *RANGE, area=area)
        out["binned"] = {k: {"median": float(v), "sd": float(s_), "lo68": float(v - s_), "hi68": float(v + s_),
                             "lo95": float(v - 1.96 * s_), "hi95": float(v + 1.96 * s_)} for k, (v, s_) in b.items()}
    out["n_objects"] = int(((obs >= RANGE[0]) & (obs < RANGE[1])).sum())
    return out


def summarise(reps):
    table = {}
    nrep = len(reps)
    for method in METHODS:
        row = {}
        for k, truth in TRUTH.items():
            med = np.array([r[method][k]["median"] for r in reps])
            sd = np.array([r[method][k]["sd"] for r in reps])
            c68 = np.mean([r[method][k]["lo68"] <= truth <= r[method][k]["hi68"] for r in reps])
            c95 = np.mean([r[method][k]["lo95"] <= truth <= r[method][k]["hi95"] for r in reps])
            row[k] = {"bias": float(med.mean() - truth), "rmse": float(np.sqrt(np.mean((med - truth) ** 2))), "bias_se": float(med.std(ddof=1) / math.sqrt(nrep))
                      if nrep > 1 else None, "mean_sd": float(sd.mean()), "scatter_of_medians": float(med.std(ddof=1))
                      if nrep > 1 else None, "coverage68": float(c68), "coverage95": float(c95),
                      "coverage_se68": float(math.sqrt(0.6827 * 0.3173 / nrep)),
                      "coverage_se95": float(math.sqrt(0.9545 * 0.0455 / nrep))}
        table[method] = row
    return table


def rendered_mock(workdir: Path, min_ess):
    from comest_bayes.config import load_config
    from comest_bayes.sim.demo import MASK_GAP, make_demo_tile, write_demo_tile
    from comest_bayes.lf.fit import run_lf
    from comest_bayes.pipeline.stages import ComputeOptions, ImageOptions, run_pipeline

    t0 = time.perf_counter()
    tile = make_demo_tile(seed=11, size=1000, galaxy_density=0.0, n_saturated_stars=0, star_counts=(2.0e4, 0.3, 23.0))
    paths = write_demo_tile(tile, workdir / "tile")
    cfg = load_config(overrides=["injection.nsims=4", "injection.kinds=point", "fit.model=logistic",
                                 "fit.purity_model=none", "fit.min_ess=300", "injection.mag_range=[19.0,26.5]"], seed=1)
    opts = ImageOptions(path=str(paths["image"]), weight=str(paths["weight"]), mask=str(paths["mask"]),
                        mask_bits=MASK_GAP, fwhm=0.9 / 0.26)
    run_pipeline(opts, cfg, workdir / "run", log=lambda s: None, compute=ComputeOptions(executor="serial"))
    out = {"truth": {"log_n": math.log10(2.0e4), "slope": 0.3}}
    for mode in ("joint", "fixed"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = run_lf(workdir / "run", kind="point", model="powerlaw", mode=mode, mag_range=(20.0, 24.5),
                         seed=2, min_ess=min_ess, figures=False)
        out[mode] = res.parameter_summary()
        out["n_objects"] = res.n_objects
        out["area_deg2"] = res.area_deg2
    out["seconds"] = round(time.perf_counter() - t0, 1)
    return out


def figure(reps, table, path, ninj, area):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(13, 4.4), layout="constrained")
    ax1, ax2, ax3 = fig.subplots(1, 3)
    colors = {"joint": "#0072B2", "fixed": "#009E73", "no_transfer": "#D55E00", "binned": "#CC79A7"}
    labels = {"joint": "forward model, joint completeness", "fixed": "forward model, completeness fixed",
              "no_transfer": "phi x f, no transfer", "binned": "binned counts / binned f"}
    nrep = len(reps)
    # bias of each parameter in units of the truth's scale, with the standard error of the mean
    for i, method in enumerate(METHODS):
        for j, key in enumerate(TRUTH):
            row = table[method][key]
            ax1.errorbar(j + 0.18 * (i - 1.5), row["bias"], yerr=row["bias_se"], fmt="o", color=colors[method],
                         label=labels[method] if j == 0 else None)
    ax1.axhline(0.0, color="k", lw=1)
    ax1.set_xticks([0, 1], ["log_n (dex)", "slope (dex/mag)"])
    ax1.set_xlim(-0.6, 1.6)
    ax1.set_ylabel("mean bias of the posterior median (+- 1 s.e.)")
    ax1.set_title(f"bias over {nrep} replicate mocks", fontsize=9)
    ax1.legend(fontsize=7, loc="best")
    # reported width against the true scatter
    w = 0.2
    for i, method in enumerate(METHODS):
        for j, key in enumerate(TRUTH):
            row = table[method][key]
            ratio = row["mean_sd"] / row["rmse"] if row["rmse"] else np.nan
            ax2.bar(j + w * (i - 1.5), ratio, width=w, color=colors[method])
    ax2.axhline(1.0, color="k", lw=1, ls="--")
    ax2.set_xticks([0, 1], ["log_n", "slope"])
    ax2.set_ylabel("mean reported sd / RMS error of the median")
    ax2.set_title("honest intervals sit at 1", fontsize=9)
    for i, method in enumerate(METHODS):
        for j, key in enumerate(("coverage68", "coverage95")):
            vals = [table[method][p][key] for p in TRUTH]
            ax3.bar(np.arange(2) + 2.3 * j + w * (i - 1.5), vals, width=w, color=colors[method])
    for j, nominal in enumerate((0.6827, 0.9545)):
        band = 2 * math.sqrt(nominal * (1 - nominal) / nrep)
        ax3.axhspan(nominal - band, nominal + band, xmin=(2.3 * j + 0.1) / 4.4, xmax=(2.3 * j + 2.1) / 4.4,
                    color="0.85", zorder=0)
        ax3.hlines(nominal, 2.3 * j - 0.5, 2.3 * j + 1.5, color="k", lw=1, ls="--")
    ax3.set_xlim(-0.6, 3.8)
    ax3.set_xticks([0, 1, 2.3, 3.3], ["log_n 68%", "slope 68%", "log_n 95%", "slope 95%"])
    ax3.set_ylabel("fraction of intervals holding the truth")
    ax3.set_ylim(0, 1.05)
    ax3.set_title("coverage (grey: nominal +- 2 binomial s.e.)", fontsize=9)
    fig.suptitle(f"power-law counts through a measured completeness: {ninj} injections, {area} deg^2, "
                 f"fitted range {RANGE[0]}-{RANGE[1]} (measured mag; f = 0.03 at the faint end)", fontsize=10)
    fig.savefig(path, dpi=120)


def _replicate_job(args):
    r, ninj, min_ess, area = args
    return r, replicate(r, ninj, min_ess, area)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--replicates", type=int, default=48)
    ap.add_argument("--ninj", type=int, default=1000)
    ap.add_argument("--area", type=float, default=AREA, help="catalog area, deg^2")
    ap.add_argument("--min-ess", type=float, default=300)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--no-render", action="store_true")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results"))
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    jobs = [(r, args.ninj, args.min_ess, args.area) for r in range(args.replicates)]
    done = {}

    def report(r, rep):
        done[r] = rep
        print(f"replicate {r}: N = {rep['n_objects']}, slope " +
              ", ".join(f"{m} {rep[m]['slope']['median']:.3f}+-{rep[m]['slope']['sd']:.3f}" for m in METHODS),
              flush=True)

    if args.workers > 1:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        # spawn: JAX is not fork-safe once initialised
        with ProcessPoolExecutor(args.workers, mp_context=mp.get_context("spawn")) as pool:
            for r, rep in pool.map(_replicate_job, jobs):
                report(r, rep)
    else:
        for job in jobs:
            report(*_replicate_job(job))
    reps = [done[r] for r in range(args.replicates)]
    table = summarise(reps)
    result = {"truth": TRUTH, "area_deg2": args.area, "mag_range": RANGE, "replicates": args.replicates,
              "ninj": args.ninj, "rho": RHO, "summary": table, "per_replicate": reps,
              "seconds_replicates": round(time.perf_counter() - t0, 1), "workers": args.workers}
    if not args.no_render:
        with tempfile.TemporaryDirectory() as tmp:
            result["rendered_mock"] = rendered_mock(Path(tmp), args.min_ess)
    result["seconds_total"] = round(time.perf_counter() - t0, 1)
    (out / "lf.json").write_text(json.dumps(result, indent=2))
    figure(reps, table, out / "lf.png", args.ninj, args.area)
    for method in METHODS:
        for key in TRUTH:
            s = table[method][key]
            print(f"{method:12s} {key:6s} bias {s['bias']:+.4f} +- {s['bias_se']:.4f}  mean sd {s['mean_sd']:.4f}  "
                  f"rmse {s['rmse']:.4f}  coverage 68% {s['coverage68']:.2f}  95% {s['coverage95']:.2f}")
    print(f"wrote {out / 'lf.json'} and {out / 'lf.png'} in {result['seconds_total']:.0f} s")


if __name__ == "__main__":
    main()
