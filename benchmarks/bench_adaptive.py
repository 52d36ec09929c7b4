"""Benchmark: injections needed by the adaptive design against the published uniform + binned method.

Outcome-level scenes with a known completeness (:mod:`comest_bayes.sim.synthetic`),
so the truth is exact and thousands of replicates are affordable:

``white``
    a uniform-depth field (no depth gradient, no chip gap) with a logistic
    completeness: the white-noise scene's shape;
``demo``
    the depth gradient and chip gap of the synthetic scene with a skewed
    faint-end truth (``skew_faint``): a demo-tile-like field whose curve is
    no logistic;
``varying``
    the same field with a width that changes across the image
    (``width_varies``): completeness varying over the footprint.

For each scene:

* **uniform + binned** (the published method): magnitudes uniform over the
  range, m50 of the 0.1-mag binned ratio by linear interpolation, the binned
  curve interpolated between bin centres; ``--reps`` replicates at each of a
  geometric ladder of N from 500 to 400,000 injections.
* **adaptive**: :func:`comest_bayes.pipeline.adaptive.run_sequential` with the
  package's default fit (``auto``) after every batch (a uniform pilot of
  ``--pilot`` (1000), then batches of half the injections so far, at least ``--min-batch`` (250), designed for
  ``--target``), ``--reps`` replicates up to ``--cap`` injections; the error of
  the posterior-median m50 and curve is recorded after every batch (the
  batch sizes are the same in every replicate, so RMSEs are taken per step).

The figure of merit is the number of injections each method needs to reach an
m50 RMSE of 0.02 and 0.01 mag and a curve RMSE of 0.01 (over the magnitudes
where the true image-average curve is between 0.1 and 0.9), by log-log
interpolation of RMSE against N; the ratio uniform / adaptive is the saving.
Coverage: over the adaptive replicates, the fraction whose 68% and 95% m50
intervals contain the truth at the first step whose half-width is at most
0.01 mag (the interval a user stopping at ``--precision 0.01`` gets), with
the binomial 99% range of the nominal level.  CPU seconds include every
refit.

Usage::

    python benchmarks/bench_adaptive.py [--scenes white demo varying] [--reps 20] [--cap 40000]
        [--workers 2] [--out benchmarks/results/adaptive]

Results: ``<out>/adaptive.json``, ``<out>/adaptive.png``.  Replicates are
seeded by (scene, replicate) only; raw results are kept in
``<out>/raw.json`` and a rerun skips the replicates already there.

Real outcomes (``--pool RUN_DIR [RUN_DIR ...]``)
------------------------------------------------
Instead of synthetic draws, both methods take the real outcomes of a finished
injection run whose magnitudes are uniform (``--build-pool analytic|demo``
makes one with :mod:`bench_speed_accuracy`'s scenes, ``--build-range auto``
the analytic one over the range a default run draws instead of the fixed
24.0-26.8; several runs of one image may be pooled).  Because the pool is uniform in magnitude and a design
is uniform within each of its bins, taking for every designed magnitude an
unused pool injection from the same design bin (:class:`PoolSampler`) gives
injections distributed exactly as the design asks, each with its real
position and real detection.  Each adaptive replicate owns a disjoint share
of the pool and stops, saying so, when a bin of its share runs dry; the
uniform method takes disjoint slices at each N (at most 200).  A third of
the realizations (0, 3, 6, ...) is held out as the reference (binned at
0.05 mag; its own noise is estimated by a bootstrap over realizations and
taken out of the RMSEs in ``debiased``), and ``--closed-form`` adds the
analytic scene's exact curve (``--primary`` chooses the reference of the
coverage figures).  ``--regions`` also scores both methods on
the footprint's deeper and shallower halves.  CPU seconds count the pool's
own CPU per injection (injection, detection, matching) plus every fit::

    python benchmarks/bench_adaptive.py --pool RUN_DIR [--closed-form] [--regions] --reps 8 --cap 10000
        --precision 0.001 --pilot 250 --min-batch 100 [--out benchmarks/results/adaptive_pool]

Results: ``<out>/adaptive_<scene>.json`` and ``.png``, raw in ``raw_<scene>.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(1, str(HERE))

SCENES = {
    "white": {"truth": "logistic", "gradient": 0.0, "chip_gap": False},
    "demo": {"truth": "skew_faint", "gradient": 0.6, "chip_gap": True},
    "varying": {"truth": "width_varies", "gradient": 0.6, "chip_gap": True},
}
SHAPE = (512, 512)
UNIFORM_N = [500, 1000, 2000, 4000, 8000, 16000, 32000, 64000, 128000, 256000, 400000]
TARGETS = {"m50_0.02": ("m50", 0.02), "m50_0.01": ("m50", 0.01), "curve_0.01": ("curve", 0.01)}
GRID_STEP = 0.01


def _scene(name: str, seed: int):
    from comest_bayes.sim import synthetic as S

    p = SCENES[name]
    return S.make_scene(SHAPE, gradient=p["gradient"], chip_gap=p["chip_gap"], seed=seed)


def _truth_setup(name: str, scene):
    from comest_bayes.sim import synthetic as S

    truth = S.get_truth(SCENES[name]["truth"])
    lo, hi = truth.default_mag_range()
    grid = np.arange(lo, hi + 1e-9, GRID_STEP)
    curve = S.truth_curve(truth, scene, grid)
    window = (curve >= 0.1) & (curve <= 0.9)
    return truth, (lo, hi), grid, curve, window, S.truth_quantities(truth, scene)["m50"]


def uniform_task(task: dict) -> dict:
    """Replicates of the published method at one N: m50 errors and curve RMS errors."""
    from comest_bayes.sim import synthetic as S

    scene = _scene(task["scene"], task["scene_seed"])
    truth, (lo, hi), grid, curve, window, m50 = _truth_setup(task["scene"], scene)
    errs, crms = [], []
    c0 = time.process_time()
    for rep in range(task["reps"]):
        table = S.draw_outcomes(truth, scene, task["n"], seed=task["seed"] + rep)
        b = S.binned_estimate(table, mag_bin=0.1, mag_range=(lo, hi))
        errs.append(np.nan if b.m50 is None or not np.isfinite(b.m50) else b.m50 - m50)
        crms.append(float(np.sqrt(np.nanmean((b.curve(grid[window]) - curve[window]) ** 2))))
    return {"key": task["key"], "n": task["n"], "m50_err": errs, "curve_rms": crms,
            "cpu_binning": time.process_time() - c0}


def adaptive_task(task: dict) -> dict:
    """One adaptive replicate: the error after every batch."""
    from comest_bayes.pipeline import runtime

    runtime.configure(threads=1)
    from comest_bayes.sim import synthetic as S
    from comest_bayes.pipeline.adaptive import AdaptiveSettings, package_fitter, run_sequential

    from comest_bayes.bayes.fit import shared_maps

    scene = _scene(task["scene"], task["scene_seed"])
    truth, (lo, hi), grid, curve, window, m50 = _truth_setup(task["scene"], scene)
    maps = shared_maps(scene.noise, scene.mask, ["auto"])
    fitter = package_fitter(image_shape=scene.shape, noise=scene.noise, mask=scene.mask, lo=lo, hi=hi,
                            seed=task["seed"], most_flexible=task.get("design_model", "flexible") == "flexible",
                            maps=maps)
    steps = []

    def score(m50_draws, fgrid, curves) -> dict:
        med = np.median(curves, axis=0)
        q = _m50_quantiles(m50_draws)
        return {"m50_err": float(q[2] - m50),
                "curve_rms": float(np.sqrt(np.mean((np.interp(grid[window], fgrid, med) - curve[window]) ** 2))),
                "halfwidth": float(0.5 * (q[3] - q[1])), "cover68": bool(q[1] <= m50 <= q[3]),
                "cover95": bool(q[0] <= m50 <= q[4])}

    def fit(table, k):
        c0 = time.process_time()
        view, post = fitter(table, k)
        cpu = time.process_time() - c0
        step = score(np.asarray(view.m50, float), view.grid, view.curves)
        step.update(n=len(table), halfwidth=view.m50_halfwidth, cpu_fit=cpu, model=post[1].name)
        if task.get("final_fit"):
            _, entry, m50_draws, curves, cpu_final = final_fit(
                table, k, image_shape=scene.shape, noise=scene.noise, mask=scene.mask, lo=lo, hi=hi,
                seed=task["seed"], maps=maps, fgrid=view.grid)
            step["final"] = {**score(m50_draws, view.grid, curves), "cpu_fit": cpu_final, "model": entry.name}
        steps.append(step)
        return view, post

    def simulate(mags, k):
        return S.draw_outcomes(truth, scene, seed=task["seed"] * 1000 + k + 1, mags=mags)

    settings = AdaptiveSettings(precision=task["precision"], pilot=task.get("pilot", 1000), growth=0.5,
                                min_batch=task.get("min_batch", 250), max_injections=task["cap"], target=task["target"])
    t0 = time.perf_counter()
    run_sequential(simulate, fit, lo, hi, settings, seed=task["seed"])
    return {"key": task["key"], "steps": steps, "wall": time.perf_counter() - t0}


def _m50_quantiles(m50_draws) -> np.ndarray:
    """The 2.3, 15.9, 50, 84.1 and 97.7 percentiles of the m50 draws (the median and the 68% and 95%
    intervals), or NaN when fewer than half the draws have an m50."""
    d = np.asarray(m50_draws, float)
    ok = np.isfinite(d)
    return np.percentile(d[ok], [2.275, 15.865, 50, 84.135, 97.725]) if ok.mean() >= 0.5 else np.full(5, np.nan)


def final_fit(table, k: int, *, image_shape, noise, mask, lo: float, hi: float, seed: int, maps: dict, fgrid):
    """What a run stopped after this batch reports: the fit stage's own fit of the outcomes so far.

    The run's fit stage selects the simplest adequate rung of ``auto`` on every outcome, from
    scratch, with its default MAP starts (:func:`comest_bayes.pipeline.fits.fit_task`); the design
    fits fit the selection's most flexible rung.  Returns ``(posterior, entry, m50 draws, curves on
    fgrid, CPU seconds)``.
    """
    from comest_bayes.bayes.fit import fit_kind
    from comest_bayes.config import RunConfig
    from comest_bayes.ratios import binned as R
    from comest_bayes.seeding import int_seed_for

    edges = R.magnitude_edges(lo, hi, 0.1)
    c0 = time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        post, entry = fit_kind(table, kind="point", quantity="completeness", requested="auto",
                               config=RunConfig(seed=int_seed_for(seed, "final-fit", k)), image_shape=image_shape,
                               noise=noise, mask=mask, wcs_header=None, mag_range=(lo, hi),
                               mag_centers=0.5 * (edges[:-1] + edges[1:]), footprints=maps["footprints"],
                               noise_grid=maps["noise_grid"], products=False)
        m50_draws = np.asarray(post.magnitudes_at((0.5,), nsamples=1000)[0.5], float)
        curves = post.average_curve(fgrid, nsamples=1000)
    return post, entry, m50_draws, curves, time.process_time() - c0


def _needed(ns, rmse, target: float) -> float | None:
    """Injections from which the RMSE stays at or below ``target`` through the last step (log-log
    interpolation between the step above it and the next).

    Not the *first* crossing: with a few replicates an RMSE that dips below the target once and
    rises above it again (one replicate's miss at a later step) would credit a method with a level
    it does not hold.
    """
    ns, rmse = np.asarray(ns, float), np.asarray(rmse, float)
    ok = np.isfinite(rmse)
    ns, rmse = ns[ok], rmse[ok]
    if ns.size == 0 or rmse[-1] > target:
        return None
    above = np.flatnonzero(rmse > target)
    if above.size == 0:
        return float(ns[0])
    i = int(above[-1]) + 1
    if rmse[i] <= 0:  # an RMSE with the reference's noise taken out can reach 0
        return float(ns[i])
    x0, x1, y0, y1 = np.log(ns[i - 1]), np.log(ns[i]), np.log(rmse[i - 1]), np.log(rmse[i])
    return float(np.exp(x0 + (np.log(target) - y0) * (x1 - x0) / (y1 - y0)))


def _binom99(n: int, p: float) -> list:
    from scipy.stats import binom

    return [float(binom.ppf(0.005, n, p) / n), float(binom.ppf(0.995, n, p) / n)]


def final_view(raw: dict) -> dict:
    """``raw`` with every adaptive step scored on the fit a run stopped there reports (:func:`final_fit`).

    Each step keeps its ``n`` (and ``within06``), its design fit's CPU (``cpu_fit``, summed over
    the steps so far) and half-width (``halfwidth_design``: where a run stops), and takes the rest
    (errors, scores, half-width, coverage flags, model) from its ``final`` entry, whose CPU becomes
    ``cpu_final``.
    """
    view = {**raw, "adaptive": {}}
    for k, r in raw["adaptive"].items():
        steps = []
        for s in r["steps"]:
            f = s["final"]
            steps.append({**f, "n": s["n"], "cpu_fit": s["cpu_fit"], "cpu_final": f["cpu_fit"],
                          "halfwidth_design": s["halfwidth"],
                          **({"within06": s["within06"]} if "within06" in s else {})})
        view["adaptive"][k] = {**r, "steps": steps}
    return view


def summarise(raw: dict, scenes, truths: dict | None = None) -> dict:
    """Per scene: RMSEs against N, injections needed, coverage at the stop (the first step whose design
    half-width is at most 0.01 mag).  On a :func:`final_view` the CPU after a step counts the design
    fits so far and that step's final fit.
    """
    out = {}
    for sc in scenes:
        uni = sorted((r for k, r in raw["uniform"].items() if k.startswith(sc + "|")), key=lambda r: r["n"])
        ada = [r for k, r in raw["adaptive"].items() if k.startswith(sc + "|")]
        if not uni or not ada:
            continue
        u_n = [r["n"] for r in uni]
        u_m50 = [float(np.sqrt(np.nanmean(np.square(r["m50_err"])))) for r in uni]
        u_curve = [float(np.sqrt(np.nanmean(np.square(r["curve_rms"])))) for r in uni]
        nstep = min(len(r["steps"]) for r in ada)
        a_n = [ada[0]["steps"][j]["n"] for j in range(nstep)]
        a_m50 = [float(np.sqrt(np.nanmean([r["steps"][j]["m50_err"] ** 2 for r in ada]))) for j in range(nstep)]
        a_curve = [float(np.sqrt(np.nanmean([r["steps"][j]["curve_rms"] ** 2 for r in ada]))) for j in range(nstep)]
        # rms of error over 68% half-width per step: about 1 for honest intervals
        a_z = [float(np.sqrt(np.nanmean([(r["steps"][j]["m50_err"] / r["steps"][j]["halfwidth"]) ** 2
                                         for r in ada]))) for j in range(nstep)]
        a_cpu = [float(np.mean([sum(s["cpu_fit"] for s in r["steps"][:j + 1])
                                + r["steps"][j].get("cpu_final", 0.0) for r in ada]))
                 for j in range(nstep)]
        needed = {}
        for name, (what, level) in TARGETS.items():
            nu = _needed(u_n, u_m50 if what == "m50" else u_curve, level)
            na = _needed(a_n, a_m50 if what == "m50" else a_curve, level)
            needed[name] = {"uniform_binned": nu, "adaptive": na,
                            "ratio": None if nu is None or na is None else nu / na,
                            # reached at the first adaptive step: the adaptive N is an upper bound, the ratio a
                            # lower bound
                            "at_first_step": na is not None and na <= a_n[0]}
        # coverage at the first step whose half-width reaches 0.01 mag
        hits68, hits95 = [], []
        for r in ada:
            s = next((s for s in r["steps"] if s.get("halfwidth_design", s["halfwidth"]) <= 0.01), None)
            if s is not None:
                hits68.append(s["cover68"])
                hits95.append(s["cover95"])
        nrep = len(hits68)
        out[sc] = {
            "truth": (truths or {}).get(sc) or SCENES[sc]["truth"], "replicates": len(ada),
            "uniform": {"n": u_n, "m50_rmse": u_m50, "curve_rmse": u_curve},
            "adaptive": {"n": a_n, "m50_rmse": a_m50, "curve_rmse": a_curve, "cpu_fit_cumulative": a_cpu,
                         "error_over_halfwidth_rms": a_z, "models": sorted({s["model"] for r in ada for s in r["steps"]}),
                         "scored": "final" if "cpu_final" in ada[0]["steps"][0] else "design"},
            "needed": needed,
            "coverage_at_0.01": {"replicates": nrep,
                                 "cov68": float(np.mean(hits68)) if nrep else None,
                                 "cov95": float(np.mean(hits95)) if nrep else None,
                                 "band68": _binom99(nrep, 0.6827) if nrep else None,
                                 "band95": _binom99(nrep, 0.9545) if nrep else None},
        }
    return out


def chart(summary: dict, path: Path, cpu: bool = False) -> None:
    """RMSE of m50 and of the curve against injections (and, with ``cpu``, m50 RMSE against CPU seconds)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(summary)
    rows = 3 if cpu else 2
    fig, axes = plt.subplots(rows, len(scenes), figsize=(5 * len(scenes), 4 * rows), squeeze=False)
    for j, sc in enumerate(scenes):
        s = summary[sc]
        for i, (key, label, lines) in enumerate((("m50_rmse", "RMSE of m50 (mag)", (0.02, 0.01)),
                                                 ("curve_rmse", "RMSE of f(m), f in [0.1, 0.9]", (0.01,)))):
            ax = axes[i, j]
            ax.loglog(s["uniform"]["n"], s["uniform"][key], "s-", color="0.3", label="uniform + binned (published)")
            ax.loglog(s["adaptive"]["n"], s["adaptive"][key], "o-", color="tab:red", label="adaptive + model (auto)")
            for y in lines:
                ax.axhline(y, color="k", lw=0.6, ls=":")
            ref_sd = s.get("reference", {}).get("m50_sd" if i == 0 else "curve_rms_sd")
            if ref_sd:
                ax.axhline(ref_sd, color="tab:blue", lw=0.8, ls="--", label="the reference's own noise")
            ax.set_xlabel("injections")
            ax.set_ylabel(label)
            ax.grid(alpha=0.3, which="both")
            if i == 0:
                nd = s["needed"]
                ax.set_title(f"{sc} ({s['truth']}): saving x" + ", x".join(
                    "n/a" if nd[k]["ratio"] is None else f"{nd[k]['ratio']:.1f}" for k in nd) + "\n"
                    "(m50 0.02, m50 0.01, curve 0.01)", fontsize=8)
            ax.legend(fontsize=7)
        if cpu:
            ax = axes[2, j]
            ax.loglog(s["uniform"]["cpu"], s["uniform"]["m50_rmse"], "s-", color="0.3", label="uniform + binned")
            ax.loglog(s["adaptive"]["cpu"], s["adaptive"]["m50_rmse"], "o-", color="tab:red",
                      label="adaptive (refits included)")
            for y in (0.02, 0.01):
                ax.axhline(y, color="k", lw=0.6, ls=":")
            ax.set_xlabel("CPU seconds (injection + detection + fits)")
            ax.set_ylabel("RMSE of m50 (mag)")
            ax.grid(alpha=0.3, which="both")
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _run_tasks(tasks, funcs: dict, raw: dict, raw_path: Path, workers: int) -> None:
    """Run ``(kind, task)`` pairs in ``workers`` processes; keep every result in ``raw`` (saved after each)."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = {pool.submit(funcs[kind], t): (kind, t) for kind, t in tasks}
        for i, fut in enumerate(as_completed(futures), 1):
            kind, t = futures[fut]
            res = fut.result()
            raw[kind][t["key"]] = res
            tmp = raw_path.with_name(".tmp-" + raw_path.name)
            tmp.write_text(json.dumps(raw))
            os.replace(tmp, raw_path)
            if kind == "adaptive" and res["steps"]:
                last = res["steps"][-1]
                err = last["m50_err"] if "m50_err" in last else next(iter(last["scores"].values()))["m50_err"]
                print(f"[{i}/{len(tasks)}] adaptive {t['key']}: {last['n']} injections, m50 err "
                      f"{err:+.4f} +- {last['halfwidth']:.4f}, {res['wall']:.0f} s"
                      + (f"; pool share used up: {res['exhausted']}" if res.get("exhausted") else ""), flush=True)
            else:
                print(f"[{i}/{len(tasks)}] uniform {t['key']}", flush=True)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", nargs="+", default=list(SCENES))
    p.add_argument("--reps", type=int, default=20)
    p.add_argument("--cap", type=int, default=40000)
    p.add_argument("--precision", type=float, default=0.004,
                   help="adaptive runs stop at this m50 half-width (small: follow the RMSE down)")
    p.add_argument("--target", default="m50", choices=["m50", "curve"])
    p.add_argument("--design-model", default="flexible", choices=["flexible", "selected"],
                   help="model of the design fits after the first comparison: the selection's most flexible "
                        "candidate (default since 2026-11-28) or the simplest adequate one (before)")
    p.add_argument("--final-fit", action="store_true",
                   help="also fit, after every batch, what a run stopped there reports (the fit stage's "
                        "selection of auto on every outcome so far) and score that (the headline figures); "
                        "the design fits' own scores go to 'design_fit_scores' in the results")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--seed", type=int, default=16)
    p.add_argument("--out", default=None, help="results folder (default results/adaptive, or "
                   "results/adaptive_pool with --pool)")
    g = p.add_argument_group("real outcome pools (--pool)")
    g.add_argument("--pool", default=None, metavar="RUN_DIR", nargs="+",
                   help="finished uniform-magnitude point-source injection runs (several: of the same image, "
                        "pooled): both methods draw their real outcomes instead of synthetic ones (replaces "
                        "--scenes)")
    g.add_argument("--regions", action="store_true",
                   help="also score each method on the footprint's deeper and shallower halves, against "
                        "held-out references taken per half (a scene whose completeness varies)")
    g.add_argument("--pool-name", default=None, help="scene name for the results (default: RUN_DIR's name)")
    g.add_argument("--closed-form", action="store_true",
                   help="the pool is bench_speed_accuracy's analytic white-noise scene: its closed-form curve "
                        "is the primary reference")
    g.add_argument("--primary", choices=["closed-form", "held-out"], default=None,
                   help="the reference of the coverage (default: the closed form with --closed-form, else the "
                        "held-out third)")
    g.add_argument("--no-holdout", action="store_true",
                   help="use the whole pool for replicates (only with --closed-form; no held-out reference)")
    g.add_argument("--pilot", type=int, default=1000, help="uniform pilot of every adaptive run")
    g.add_argument("--min-batch", type=int, default=250, help="smallest adaptive batch")
    g.add_argument("--build-pool", choices=["analytic", "demo"], default=None,
                   help="build a pool under --work with --nsims realizations (bench_speed_accuracy's scenes), "
                        "then run on it")
    g.add_argument("--work", default=None, help="folder for --build-pool")
    g.add_argument("--nsims", type=int, default=40, help="realizations of --build-pool")
    g.add_argument("--build-seed", type=int, default=11,
                   help="injection seed of --build-pool (the image is always made with seed 11)")
    g.add_argument("--build-range", choices=["bench", "auto"], default="bench",
                   help="magnitude range of --build-pool analytic: bench_speed_accuracy's 24.0-26.8 (bench; "
                        "keeps the closed form valid) or the range a default run chooses on that image "
                        "(auto: (m5 - 5, m5 + 1.5) around the 5-sigma depth; 21.63-28.13 here), in "
                        "<work>/analytic_autorange_run")
    a = p.parse_args(argv)
    for name in ("reps", "cap", "pilot", "min_batch", "workers", "nsims"):
        if getattr(a, name) < 1:
            raise SystemExit(f"error: --{name.replace('_', '-')} must be a positive integer, got {getattr(a, name)}.")
    if a.cap < a.pilot:
        raise SystemExit(f"error: --cap {a.cap} is below the pilot of {a.pilot} injections.")
    if a.no_holdout and not a.closed_form:
        raise SystemExit("error: --no-holdout leaves no reference without --closed-form.")
    if a.build_pool:
        if not a.work:
            raise SystemExit("error: --build-pool needs --work DIR.")
        a.pool = [str(build_pool_cli(a.build_pool, Path(a.work), a.nsims, a.workers, a.build_seed,
                                     auto_range=a.build_range == "auto"))]
    if a.pool:
        if a.out is None:
            a.out = str(HERE / "results" / "adaptive_pool")
        return run_pool(a)
    if a.out is None:
        a.out = str(HERE / "results" / "adaptive")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    settings = {"seed": a.seed, "cap": a.cap, "precision": a.precision, "target": a.target}
    if (a.pilot, a.min_batch) != (1000, 250):  # recorded only when not the first runs' (so their raw.json stays valid)
        settings.update(pilot=a.pilot, min_batch=a.min_batch)
    # the design fits' model (recorded since it became "flexible" on 2026-11-28: a raw.json of the
    # earlier "selected" design fits then cannot be extended with the other kind of replicates)
    settings["design_model"] = a.design_model
    if a.final_fit:  # recorded only when set (earlier raw.json files stay valid)
        settings["final_fit"] = True
    raw_path = out / "raw.json"
    raw = {"settings": settings, "uniform": {}, "adaptive": {}}
    if raw_path.exists():
        raw = json.loads(raw_path.read_text())
        if raw["settings"] != settings:
            raise SystemExit(f"{raw_path} holds other settings {raw['settings']}; use another --out.")
    from comest_bayes.seeding import int_seed_for

    tasks = []
    for sc in a.scenes:
        scene_seed = int_seed_for(a.seed, "scene", sc)
        for n in UNIFORM_N:
            key = f"{sc}|{n}"
            if key not in raw["uniform"]:
                tasks.append(("uniform", {"key": key, "scene": sc, "scene_seed": scene_seed, "n": n,
                                          "reps": 200 if n <= 16000 else 50,
                                          "seed": int_seed_for(a.seed, "uniform", sc, n)}))
        for rep in range(a.reps):
            key = f"{sc}|{rep}"
            if key not in raw["adaptive"]:
                tasks.append(("adaptive", {"key": key, "scene": sc, "scene_seed": scene_seed, "cap": a.cap,
                                           "precision": a.precision, "target": a.target,
                                           "pilot": a.pilot, "min_batch": a.min_batch,
                                           "design_model": a.design_model, "final_fit": a.final_fit,
                                           "seed": int_seed_for(a.seed, "adaptive", sc, rep)}))
    t0 = time.perf_counter()
    _run_tasks(tasks, {"uniform": uniform_task, "adaptive": adaptive_task}, raw, raw_path, a.workers)
    summary = summarise(final_view(raw) if a.final_fit else raw, a.scenes)
    report = {"settings": settings, "wall_seconds": time.perf_counter() - t0, "scenes": summary}
    if a.final_fit:
        report["design_fit_scores"] = summarise(raw, a.scenes)
    (out / "adaptive.json").write_text(json.dumps(report, indent=1))
    chart(summary, out / "adaptive.png")
    for label, summ in (("final fit", summary), ("design fit", report.get("design_fit_scores", {}))):
        if a.final_fit:
            print(f"-- scored on the {label}")
        _print_summary(summ)
    print(f"wrote {out / 'adaptive.json'} and {out / 'adaptive.png'}")
    return 0


def _print_summary(summary: dict) -> None:
    for sc, s in summary.items():
        print(f"{sc} ({s['truth']}): injections needed uniform+binned / adaptive: " + "; ".join(
            f"{k}: {_fmt(v['uniform_binned'])} / {_fmt(v['adaptive'])} = x{_fmt(v['ratio'], '.1f')}"
            for k, v in s["needed"].items())
              + f"; coverage at half-width 0.01: 68% {s['coverage_at_0.01']['cov68']}, "
                f"95% {s['coverage_at_0.01']['cov95']} ({s['coverage_at_0.01']['replicates']} replicates)")
        print("   n: " + " ".join(f"{n}" for n in s["adaptive"]["n"]))
        print("   rms(error/half-width): " + " ".join(f"{z:.2f}" for z in s["adaptive"]["error_over_halfwidth_rms"]))


# --------------------------------------------------------------------------- real outcome pools


def build_pool_cli(scene: str, work: Path, nsims: int, workers: int, seed: int, tile_seed: int = 11,
                   auto_range: bool = False) -> Path:
    """Inject and detect a pool with :mod:`bench_speed_accuracy`'s scenes; return its run directory.

    The image is made with ``tile_seed``; the injections use ``seed`` (another seed on the same
    ``work`` adds an independent pool of the same image, in ``<scene>_run_seed<seed>``).
    ``auto_range`` drops the analytic scene's fixed 24.0-26.8 so that the pipeline chooses the
    range as a default run would (``injection.mag_range = []``); the pool goes to
    ``analytic_autorange_run``.
    """
    import bench_speed_accuracy as SA

    work.mkdir(parents=True, exist_ok=True)
    if scene == "analytic":
        sc = SA.analytic_scene(work, size=2048, sigma=1.0, fwhm_pix=3.0, zeropoint=30.0, pixel_scale=0.2,
                               seed=tile_seed)
        density = 50.0
    elif scene == "demo":
        sc = SA.demo_scene(work, size=3000, seed=tile_seed)
        density = 60.0
    else:
        raise SystemExit(f"error: --build-pool takes analytic or demo, not {scene!r}.")
    if auto_range:
        if scene != "analytic":
            raise SystemExit("error: --build-range auto is for --build-pool analytic (the demo's range is already "
                             "the automatic one).")
        sc = {**sc, "overrides": [o for o in sc["overrides"] if not o.startswith("injection.mag_range")]}
        scene = "analytic_autorange"
    run_dir = work / (f"{scene}_run" if seed == tile_seed else f"{scene}_run_seed{seed}")
    pool = SA.build_pool(sc, run_dir, nsims=nsims, density=density, seed=seed, workers=workers,
                         log=lambda s: None)
    print(f"pool of {len(pool['outcomes'])} injections in {run_dir} ({pool['wall']:.0f} s wall)", flush=True)
    return run_dir


POOL_MAX_UNIFORM_REPS = 200
_POOLS: dict = {}


class PoolExhausted(RuntimeError):
    """A design asked for more injections in one magnitude bin than a replicate's share of the pool holds."""


def load_pools(run_dirs) -> dict:
    """One pool from one or more finished runs on the same image (realizations renumbered run by run)."""
    dirs = [run_dirs] if isinstance(run_dirs, (str, Path)) else list(run_dirs)
    key = tuple(str(Path(d).resolve()) for d in dirs)
    if key in _POOLS:
        return _POOLS[key]
    pools = [load_pool(d) for d in dirs]
    first = pools[0]
    for p in pools[1:]:
        if (p["lo"], p["hi"]) != (first["lo"], first["hi"]) or p["noise"].shape != first["noise"].shape \
                or not np.array_equal(p["mask"], first["mask"]):
            raise SystemExit(f"error: {p['run_dir']} is not a pool of the same image and range as {first['run_dir']}.")
    if len(pools) == 1:
        merged = first
    else:
        cols = {c: np.concatenate([p["cols"][c] for p in pools]) for c in first["cols"]}
        cols["realization"] = np.concatenate([p["cols"]["realization"] + 100_000 * i for i, p in enumerate(pools)])
        n = [p["cols"]["mag"].size for p in pools]
        merged = {**first, "cols": cols, "run_dir": ", ".join(p["run_dir"] for p in pools),
                  "cpu_per_injection": float(np.average([p["cpu_per_injection"] for p in pools], weights=n))}
    _POOLS[key] = merged
    return merged


def load_pool(run_dir) -> dict:
    """A finished injection run's point outcomes, noise map, mask, range and CPU per injection (cached)."""
    from astropy.io import fits
    from astropy.table import Table

    run_dir = Path(run_dir)
    key = str(run_dir.resolve())
    if key in _POOLS:
        return _POOLS[key]
    need = [run_dir / "catalogs" / "point_outcomes.fits", run_dir / "run.json", run_dir / "summary.json",
            run_dir / "noise.fits", run_dir / "mask.fits"]
    missing = [str(f) for f in need if not f.exists()]
    if missing:
        raise SystemExit(f"error: {run_dir} is not a finished point-source injection run: missing "
                         + ", ".join(missing) + " (build one with --build-pool analytic|demo).")
    t = Table.read(need[0])
    state = json.loads(need[1].read_text())
    summary = json.loads(need[2].read_text())
    point = summary["kinds"]["point"]
    lo, hi = (float(v) for v in state["stages"]["baseline"]["mag_range"])
    cols = {c: np.asarray(t[c]) for c in ("mag", "detected", "x", "y", "noise", "realization")}
    cols["detected"] = cols["detected"].astype(bool)
    pool = {"run_dir": str(run_dir), "cols": cols, "lo": lo, "hi": hi,
            "noise": fits.getdata(need[3]).astype(np.float32), "mask": fits.getdata(need[4]).astype(bool),
            # CPU seconds of a realization (process time of inject + detect + match) per usable injection
            "cpu_per_injection": float(point["seconds"]["cpu"]) / max(int(point["counts"]["usable"]), 1),
            "state": state, "summary": summary}
    _POOLS[key] = pool
    return pool


def pool_split(pool: dict, seed: int, holdout: bool):
    """``(held, uniform_order, adaptive_order)``: the held-out third (realizations 0, 3, 6, ...) when
    ``holdout``, and two seeded permutations of the rest from which replicates take disjoint slices."""
    from comest_bayes.seeding import rng_for

    real = pool["cols"]["realization"]
    held = (real % 3 == 0) if holdout else np.zeros(real.size, bool)
    rest = np.flatnonzero(~held)
    return (held, rng_for(seed, "pool", "uniform").permutation(rest),
            rng_for(seed, "pool", "adaptive").permutation(rest))


class PoolSampler:
    """Outcomes for designed magnitudes taken from a uniform-magnitude pool, without reuse.

    A design is piecewise constant on its bins and uniform within each, and so
    is a pool of uniform magnitudes; so for each requested magnitude an unused
    pool injection from the same design bin, taken in a seeded random order,
    has exactly the design's distribution, with its real position and real
    detection outcome.  The requested magnitude's position inside the bin (an
    independent uniform draw) is replaced by the pool injection's own.
    """

    def __init__(self, mags, indices, edges, seed: int):
        from comest_bayes.seeding import rng_for

        self.edges = np.asarray(edges, float)
        idx = np.asarray(indices)
        b = np.clip(np.searchsorted(self.edges, mags[idx], side="right") - 1, 0, self.edges.size - 2)
        rng = rng_for(seed, "pool-sampler")
        self.queues = [rng.permutation(idx[b == j]) for j in range(self.edges.size - 1)]
        self.used = np.zeros(self.edges.size - 1, int)

    def take(self, mags) -> np.ndarray:
        b = np.clip(np.searchsorted(self.edges, np.asarray(mags, float), side="right") - 1, 0, self.edges.size - 2)
        want = np.bincount(b, minlength=self.used.size)
        have = np.array([q.size for q in self.queues])
        short = np.flatnonzero(self.used + want > have)
        if short.size:
            j = int(short[0])
            raise PoolExhausted(f"bin {self.edges[j]:.3f}-{self.edges[j + 1]:.3f} mag needs {self.used[j] + want[j]} "
                                f"pool injections, the replicate's share holds {have[j]}")
        out = np.empty(b.size, int)
        for j in np.flatnonzero(want):
            where = np.flatnonzero(b == j)
            out[where] = self.queues[j][self.used[j]:self.used[j] + want[j]]
            self.used[j] += want[j]
        return out


def pool_regions(pool: dict, regions: bool) -> dict:
    """Boolean selections of pool rows: ``""`` (all) and, with ``regions``, the footprint's deeper and
    shallower halves (noise at the injection below / above the median of the unmasked noise map)."""
    noise = pool["cols"]["noise"]
    out = {"": np.ones(noise.size, bool)}
    if regions:
        thr = float(np.median(pool["noise"][~pool["mask"]]))
        out["deep half"] = np.isfinite(noise) & (noise <= thr)
        out["shallow half"] = ~out["deep half"]
    return out


def pool_references(pool: dict, held: np.ndarray, closed_form: bool, regions: bool = False) -> dict:
    """The references: the held-out pool's binned curve (0.05 mag) and, with ``closed_form``, the analytic one.

    Each is ``{"grid", "curve", "var", "m50", "m50_var", "source"}`` on the comparison grid (``GRID_STEP``):
    ``var`` is the reference's own binomial variance per grid point (0 for the closed form) and ``m50_var``
    the variance of its m50 (bootstrap over the held-out injections), so that reference noise can be
    taken out of a mean squared error (the held-out set is disjoint from every replicate).
    """
    from comest_bayes.ratios import binned as R

    lo, hi = pool["lo"], pool["hi"]
    grid = np.arange(lo, hi + 1e-9, GRID_STEP)
    refs = {}
    for region, sel in (pool_regions(pool, regions).items() if held.any() else ()):
        mag, det = pool["cols"]["mag"][held & sel], pool["cols"]["detected"][held & sel]
        edges = R.magnitude_edges(lo, hi, 0.05)
        br = R.binned_ratio(mag, det, edges)
        n = np.asarray(br.n, float)
        ok = n > 0
        centers = 0.5 * (edges[:-1] + edges[1:])
        f = np.asarray(br.ratio, float)
        var = np.where(ok, f * (1 - f) / np.maximum(n, 1), np.nan)
        # bootstrap over whole realizations: injections of one realization share its image and
        # placement, so resampling single injections could understate the reference's noise
        rng = np.random.default_rng(0)
        real = pool["cols"]["realization"][held & sel]
        ids, inv = np.unique(real, return_inverse=True)
        members = [np.flatnonzero(inv == i) for i in range(ids.size)]
        boot = []
        for _ in range(100):
            pick = np.concatenate([members[i] for i in rng.integers(0, ids.size, ids.size)])
            boot.append(R.magnitude_at(R.binned_ratio(mag[pick], det[pick], edges), 0.5))
        refs["held-out pool" + (f" ({region})" if region else "")] = {
            "grid": grid, "curve": np.interp(grid, centers[ok], f[ok]), "region": region,
            "var": np.interp(grid, centers[ok], var[ok]), "m50": float(R.magnitude_at(br, 0.5)),
            "m50_var": float(np.nanvar(boot, ddof=1)),
            "source": f"binned ratio (0.05 mag) of the {mag.size} held-out injections"
                      + (f" in the {region} of the footprint" if region else "")}
    if closed_form:
        import bench_speed_accuracy as SA

        cfg = pool["state"]["fingerprint"]["config"]["detection"]
        meta = pool["state"]["stages"]["detect"]["meta"]
        facts = {"zeropoint": float(meta["zeropt"]),
                 "fwhm_pix": float(pool["state"]["fingerprint"]["input"]["options"]["fwhm"])}
        det_cfg = type("Detection", (), {"filter": cfg["filter"], "thresh": float(cfg["thresh"])})
        r = SA.analytic_reference(facts, (lo, hi), det_cfg, float(np.median(pool["noise"])))
        refs["closed form"] = {"grid": grid, "curve": np.interp(grid, r["grid"], r["curve"]), "region": "",
                               "var": np.zeros(grid.size), "m50": float(r["m50"]), "m50_var": 0.0,
                               "source": r["source"]}
    return refs


def _ref_scores(refs: dict, estimates: dict) -> dict:
    """m50 error and curve RMS error (reference between 0.1 and 0.9) against every reference;
    ``estimates`` maps each reference's region to ``(m50, grid, curve)``."""
    out = {}
    for name, r in refs.items():
        m50_hat, grid_hat, curve_hat = estimates[r["region"]]
        win = (r["curve"] >= 0.1) & (r["curve"] <= 0.9)
        est = np.interp(r["grid"][win], grid_hat, curve_hat)
        out[name] = {"m50_err": float(m50_hat - r["m50"]) if np.isfinite(m50_hat) else float("nan"),
                     "curve_rms": float(np.sqrt(np.mean((est - r["curve"][win]) ** 2)))}
    return out


def _pool_context(task: dict):
    key = (tuple(task["pool"]), task["split_seed"], task["holdout"], task["closed_form"], task["regions"])
    if key not in _POOLS:
        pool = load_pools(task["pool"])
        held, perm_u, perm_a = pool_split(pool, task["split_seed"], task["holdout"])
        _POOLS[key] = (pool, perm_u, perm_a, pool_references(pool, held, task["closed_form"], task["regions"]))
    return _POOLS[key]


def pool_uniform_task(task: dict) -> dict:
    """The published method at one N on disjoint slices of the pool: errors against every reference."""
    from comest_bayes.sim import synthetic as S

    pool, perm_u, _, refs = _pool_context(task)
    c = pool["cols"]
    n = task["n"]
    nrep = min(POOL_MAX_UNIFORM_REPS, perm_u.size // n)
    scores, cpu = [], 0.0
    g = refs[next(iter(refs))]["grid"]
    regions = pool_regions(pool, task["regions"])
    for rep in range(nrep):
        sub = perm_u[rep * n:(rep + 1) * n]
        est = {}
        for region, sel in regions.items():
            # the published method per region: the binned ratio of the injections that fell in it
            rows = sub[sel[sub]]
            c0 = time.process_time()
            b = S.binned_estimate({"mag": c["mag"][rows], "detected": c["detected"][rows]}, mag_bin=0.1,
                                  mag_range=(pool["lo"], pool["hi"]))
            if region == "":
                cpu += time.process_time() - c0
            est[region] = (np.nan if b.m50 is None or not np.isfinite(b.m50) else float(b.m50), g, b.curve(g))
        scores.append(_ref_scores(refs, est))
    return {"key": task["key"], "n": n, "replicates": nrep, "scores": scores,
            "cpu_binning": cpu / max(nrep, 1)}


def _region_estimate(post, grid, rule) -> tuple:
    """Posterior-median m50 and curve averaged over the footprint cells of one region.

    ``rule`` is ``("le" | "gt", noise threshold)``; a cell's depth covariate is
    ``-2.5 log10(noise / sigma_ref)``.  A model without a depth term (or a
    posterior whose cells carry no depth) predicts one curve everywhere: its
    image average is its answer for every region.
    """
    from comest_bayes.bayes.posterior import Footprint, average_prob, crossing_magnitudes

    cells = post.cells if post.cells is not None else post.footprint_cells()
    sigma_ref = post.meta.get("sigma_ref")
    keep = np.ones(len(cells), bool)
    if sigma_ref and np.ptp(cells.depth) > 0:
        d_thr = -2.5 * math.log10(rule[1] / float(sigma_ref))
        keep = cells.depth >= d_thr if rule[0] == "le" else cells.depth < d_thr
        if not keep.any():
            keep[:] = True
    w = cells.weight[keep]
    sub = Footprint(depth=cells.depth[keep], u=cells.u[keep], v=cells.v[keep], weight=w / w.sum(),
                    npix=int(keep.sum()))
    thetas = post._draws(1000)
    curves = np.asarray(average_prob(post.model, thetas, grid, sub))
    m50 = crossing_magnitudes(grid, curves, 0.5)
    ok = np.isfinite(m50)
    return (float(np.median(m50[ok])) if ok.mean() >= 0.5 else np.nan, grid, np.median(curves, axis=0))


def pool_adaptive_task(task: dict) -> dict:
    """One adaptive replicate fed by its own disjoint share of the pool: the errors after every batch."""
    from comest_bayes.pipeline import runtime

    runtime.configure(threads=1)
    from astropy.table import Table

    from comest_bayes.pipeline.adaptive import AdaptiveSettings, package_fitter, run_sequential
    from comest_bayes.inject.design import uniform_design

    pool, _, perm_a, refs = _pool_context(task)
    c = pool["cols"]
    lo, hi = pool["lo"], pool["hi"]
    share = perm_a.size // task["reps"]
    part = perm_a[task["rep"] * share:(task["rep"] + 1) * share]
    sampler = PoolSampler(c["mag"], part, uniform_design(lo, hi).edges, task["seed"])
    from comest_bayes.bayes.fit import shared_maps

    maps = shared_maps(pool["noise"], pool["mask"], ["auto"])
    fitter = package_fitter(image_shape=pool["noise"].shape, noise=pool["noise"], mask=pool["mask"], lo=lo, hi=hi,
                            seed=task["seed"], maps=maps)
    steps = []
    primary = task["primary"]
    # the regions as noise thresholds: deep = noise at most the median of the unmasked noise map
    region_depths = {}
    if task["regions"]:
        thr = float(np.median(pool["noise"][~pool["mask"]]))
        region_depths = {"deep half": ("le", thr), "shallow half": ("gt", thr)}

    def scored(post, m50_draws, fgrid, curves) -> dict:
        q = _m50_quantiles(m50_draws)
        est = {"": (q[2], fgrid, np.median(curves, axis=0))}
        for region, thr in region_depths.items():
            est[region] = _region_estimate(post, fgrid, thr)
        m_ref = refs[primary]["m50"]
        return {"scores": _ref_scores(refs, est), "halfwidth": float(0.5 * (q[3] - q[1])),
                "cover68": bool(q[1] <= m_ref <= q[3]), "cover95": bool(q[0] <= m_ref <= q[4])}

    def fit(table, k):
        c0 = time.process_time()
        view, post = fitter(table, k)
        cpu = time.process_time() - c0
        step = scored(post[0], np.asarray(view.m50, float), view.grid, view.curves)
        step.update(n=len(table), halfwidth=view.m50_halfwidth, cpu_fit=cpu, model=post[1].name,
                    within06=float(np.mean(np.abs(np.asarray(table["mag"]) - refs[primary]["m50"]) <= 0.6)))
        if task.get("final_fit"):
            fpost, entry, m50_draws, curves, cpu_final = final_fit(
                table, k, image_shape=pool["noise"].shape, noise=pool["noise"], mask=pool["mask"], lo=lo, hi=hi,
                seed=task["seed"], maps=maps, fgrid=view.grid)
            step["final"] = {**scored(fpost, m50_draws, view.grid, curves), "cpu_fit": cpu_final, "model": entry.name}
        steps.append(step)
        return view, post

    def simulate(mags, k):
        rows = sampler.take(mags)
        return Table({name: c[name][rows] for name in ("mag", "detected", "x", "y", "noise")})

    settings = AdaptiveSettings(precision=task["precision"], pilot=task["pilot"], growth=0.5,
                                min_batch=task["min_batch"], max_injections=task["cap"], target=task["target"])
    t0 = time.perf_counter()
    exhausted = None
    try:
        run_sequential(simulate, fit, lo, hi, settings, seed=task["seed"])
    except PoolExhausted as e:
        exhausted = str(e)
    have = np.array([q.size for q in sampler.queues])
    return {"key": task["key"], "steps": steps, "wall": time.perf_counter() - t0, "exhausted": exhausted,
            "share": int(share), "peak_bin_use": float(np.max(sampler.used / np.maximum(have, 1)))}


def _pool_raw_view(raw: dict, ref: str) -> dict:
    """The pool results against one reference, in the layout :func:`summarise` reads."""
    view = {"uniform": {}, "adaptive": {}}
    for k, r in raw["uniform"].items():
        view["uniform"][k] = {"n": r["n"], "replicates": r["replicates"],
                              "m50_err": [s[ref]["m50_err"] for s in r["scores"]],
                              "curve_rms": [s[ref]["curve_rms"] for s in r["scores"]]}
    for k, r in raw["adaptive"].items():
        view["adaptive"][k] = {"steps": [{**{kk: vv for kk, vv in s.items() if kk != "scores"},
                                          "m50_err": s["scores"][ref]["m50_err"],
                                          "curve_rms": s["scores"][ref]["curve_rms"]} for s in r["steps"]]}
    return view


def summarise_pool(raw: dict, scene: str, refs: dict, cpu_per_injection: float, primary: str = "") -> dict:
    """Per reference: the summary of :func:`summarise` plus CPU per method and, for a noisy reference,
    RMSEs with the reference's own variance taken out."""
    out = {}
    for ref, r in refs.items():
        s = summarise(_pool_raw_view(raw, ref), [scene], truths={scene: "real"}).get(scene)
        if s is None:
            continue
        uni = sorted(raw["uniform"].values(), key=lambda v: v["n"])
        s["uniform"]["replicates"] = [v["replicates"] for v in uni]
        s["uniform"]["cpu"] = [v["n"] * cpu_per_injection + v["cpu_binning"] for v in uni]
        s["adaptive"]["cpu"] = [n * cpu_per_injection + f for n, f in zip(s["adaptive"]["n"],
                                                                            s["adaptive"]["cpu_fit_cumulative"])]
        ada = list(raw["adaptive"].values())
        s["adaptive"]["exhausted"] = sum(a["exhausted"] is not None for a in ada)
        s["adaptive"]["within06"] = [float(np.mean([a["steps"][j]["within06"] for a in ada]))
                                     for j in range(len(s["adaptive"]["n"]))]
        s["reference"] = {"m50": r["m50"], "m50_sd": math.sqrt(r["m50_var"]), "source": r["source"]}
        if ref == primary:
            # the primary reference's coverage at each replicate's last step (where it stopped: precision
            # reached, cap, or its share of the pool ran dry), all replicates counted
            last = [a["steps"][-1] for a in ada if a["steps"]]
            s["coverage_last_step"] = {"replicates": len(last), "n_median": float(np.median([x["n"] for x in last])),
                                       "halfwidth_median": float(np.median([x["halfwidth"] for x in last])),
                                       "cov68": float(np.mean([x["cover68"] for x in last])),
                                       "cov95": float(np.mean([x["cover95"] for x in last])),
                                       "band68": _binom99(len(last), 0.6827), "band95": _binom99(len(last), 0.9545)}
            s["coverage_past_800"] = _coverage_past(ada, 800, r["m50_var"], ref)
        # CPU seconds (injection + detection + every fit) each method needs for each target
        s["cpu_needed"] = {}
        for name, (what, level) in TARGETS.items():
            key = "m50_rmse" if what == "m50" else "curve_rmse"
            cu = _needed(s["uniform"]["cpu"], s["uniform"][key], level)
            ca = _needed(s["adaptive"]["cpu"], s["adaptive"][key], level)
            s["cpu_needed"][name] = {"uniform_binned": cu, "adaptive": ca,
                                     "ratio": None if cu is None or ca is None else cu / ca}
        if r["m50_var"] > 0 or np.any(r["var"] > 0):
            win = (r["curve"] >= 0.1) & (r["curve"] <= 0.9)
            vc = float(np.mean(r["var"][win]))
            s["reference"]["curve_rms_sd"] = math.sqrt(vc)
            deb = lambda v, w: [float(np.sqrt(max(x * x - w, 0.0))) for x in v]
            s["debiased"] = {"uniform": {"m50_rmse": deb(s["uniform"]["m50_rmse"], r["m50_var"]),
                                         "curve_rmse": deb(s["uniform"]["curve_rmse"], vc)},
                             "adaptive": {"m50_rmse": deb(s["adaptive"]["m50_rmse"], r["m50_var"]),
                                          "curve_rmse": deb(s["adaptive"]["curve_rmse"], vc)}}
            nd = {}
            for name, (what, level) in TARGETS.items():
                key = "m50_rmse" if what == "m50" else "curve_rmse"
                nu = _needed(s["uniform"]["n"], s["debiased"]["uniform"][key], level)
                na = _needed(s["adaptive"]["n"], s["debiased"]["adaptive"][key], level)
                nd[name] = {"uniform_binned": nu, "adaptive": na,
                            "ratio": None if nu is None or na is None else nu / na}
            s["debiased"]["needed"] = nd
        out[ref] = s
    return out


def _coverage_past(ada: list, n_min: int, ref_var: float, ref: str) -> dict:
    """Coverage of reference ``ref``'s m50 by every step past ``n_min`` injections of every replicate.

    ``cov68`` / ``cov95`` are the posterior's own central intervals.  A held-out reference has an
    m50 noise of its own (variance ``ref_var``, independent of the replicates), which an interval
    as narrow as that noise misses by itself; ``with_reference_noise`` therefore also counts, with
    a normal approximation of each interval (68% half-width ``h``), ``|error| <= z sqrt(h^2 +
    ref_var)`` for z = 1 and 1.96, beside the same approximation with ``ref_var = 0`` (which shows
    what the approximation alone changes).  Steps of one replicate are correlated, so the binomial
    range (of the number of replicates) is only a guide.
    """
    st = [x for a in ada for x in a["steps"] if x["n"] > n_min and math.isfinite(x["halfwidth"])
          and math.isfinite(x["scores"][ref]["m50_err"])]
    if not st:
        return {"intervals": 0}
    err = np.array([x["scores"][ref]["m50_err"] for x in st])
    h = np.array([x["halfwidth"] for x in st])
    out = {"intervals": len(st), "replicates": len(ada), "halfwidth_median": float(np.median(h)),
           "cov68": float(np.mean([x["cover68"] for x in st])), "cov95": float(np.mean([x["cover95"] for x in st])),
           "band68": _binom99(len(ada), 0.6827), "band95": _binom99(len(ada), 0.9545),
           "error_over_halfwidth": {"mean": float(np.mean(err / h)), "sd": float(np.std(err / h, ddof=1))
                                    if len(st) > 1 else None}}
    for name, v in (("normal_approximation", 0.0), ("with_reference_noise", ref_var)):
        w = np.sqrt(h * h + v)
        out[name] = {"cov68": float(np.mean(np.abs(err) <= w)), "cov95": float(np.mean(np.abs(err) <= 1.96 * w)),
                     "error_over_width_mean": float(np.mean(err / w)),
                     "error_over_width_sd": float(np.std(err / w, ddof=1)) if len(st) > 1 else None}
    return out


def run_pool(a) -> int:
    """``--pool RUN_DIR``: both methods on real injection outcomes (see the module docstring)."""
    dirs = [str(Path(d).resolve()) for d in a.pool]
    pool = load_pools(dirs)
    scene = a.pool_name or Path(dirs[0]).name.removesuffix("_run") + ("_regions" if a.regions else "")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    settings = {"pool": dirs[0] if len(dirs) == 1 else dirs, "seed": a.seed, "cap": a.cap,
                "precision": a.precision, "target": a.target, "reps": a.reps, "pilot": a.pilot,
                "min_batch": a.min_batch, "holdout": not a.no_holdout, "closed_form": a.closed_form}
    if a.regions:
        settings["regions"] = True
    if a.primary is not None:
        settings["primary"] = a.primary
    if a.final_fit:
        settings["final_fit"] = True
    raw_path = out / f"raw_{scene}.json"
    raw = {"settings": settings, "uniform": {}, "adaptive": {}}
    if raw_path.exists():
        raw = json.loads(raw_path.read_text())
        if raw["settings"] != settings:
            raise SystemExit(f"error: {raw_path} holds other settings {raw['settings']}; use another --out.")
    from comest_bayes.seeding import int_seed_for

    held, perm_u, perm_a = pool_split(pool, a.seed, settings["holdout"])
    refs = pool_references(pool, held, a.closed_form, a.regions)
    if not refs:
        raise SystemExit("error: no reference: keep the held-out third or pass --closed-form.")
    primary = ({"held-out": "held-out pool", "closed-form": "closed form"}.get(a.primary)
               or ("closed form" if a.closed_form else "held-out pool"))
    if primary not in refs:
        raise SystemExit(f"error: --primary {a.primary}: no {primary} reference (needs "
                         + ("--closed-form)." if primary == "closed form" else "the held-out third)."))
    print(f"{scene}: pool of {held.size} injections over {pool['lo']:.2f}-{pool['hi']:.2f} mag, {int(held.sum())} "
          f"held out; {perm_a.size // a.reps} per adaptive replicate; CPU {1e3 * pool['cpu_per_injection']:.3f} ms "
          "per injection; reference m50 " + ", ".join(f"{k} {r['m50']:.4f}" for k, r in refs.items()), flush=True)
    base = {"pool": dirs, "split_seed": a.seed, "holdout": settings["holdout"], "closed_form": a.closed_form,
            "regions": a.regions}
    tasks = []
    for n in UNIFORM_N:
        key = f"{scene}|{n}"
        if n <= perm_u.size and key not in raw["uniform"]:
            tasks.append(("uniform", {**base, "key": key, "n": n}))
    for rep in range(a.reps):
        key = f"{scene}|{rep}"
        if key not in raw["adaptive"]:
            tasks.append(("adaptive", {**base, "key": key, "rep": rep, "reps": a.reps, "cap": a.cap,
                                       "precision": a.precision, "target": a.target, "pilot": a.pilot,
                                       "min_batch": a.min_batch, "primary": primary, "final_fit": a.final_fit,
                                       "seed": int_seed_for(a.seed, "adaptive", scene, rep)}))
    _run_tasks(tasks, {"uniform": pool_uniform_task, "adaptive": pool_adaptive_task}, raw, raw_path, a.workers)
    summary = summarise_pool(final_view(raw) if a.final_fit else raw, scene, refs, pool["cpu_per_injection"], primary)
    report = {"settings": settings, "scene": scene, "primary_reference": primary,
              "pool_injections": int(held.size), "held_out": int(held.sum()),
              "mag_range": [pool["lo"], pool["hi"]], "cpu_per_injection": pool["cpu_per_injection"],
              "references": summary}
    if a.final_fit:
        report["design_fit_scores"] = summarise_pool(raw, scene, refs, pool["cpu_per_injection"], primary)
    (out / f"adaptive_{scene}.json").write_text(json.dumps(report, indent=1))
    chart({f"{scene}, vs {k.replace('held-out pool', 'held-out')}": v for k, v in summary.items()},
          out / f"adaptive_{scene}.png", cpu=True)
    for label, summ in (("final fit", summary), ("design fit", report.get("design_fit_scores", {}))):
        if a.final_fit:
            print(f"-- scored on the {label}")
        _print_pool(summ, scene, primary)
    print(f"wrote {out / f'adaptive_{scene}.json'} and {out / f'adaptive_{scene}.png'}")
    return 0


def _print_pool(summary: dict, scene: str, primary: str) -> None:
    for ref, s in summary.items():
        print(f"{scene} vs {ref}: injections needed uniform+binned / adaptive: " + "; ".join(
            f"{k}: {_fmt(v['uniform_binned'])} / {_fmt(v['adaptive'])} = x{_fmt(v['ratio'], '.1f')}"
            for k, v in s["needed"].items()), flush=True)
        print("  CPU seconds needed: " + "; ".join(
            f"{k}: {_fmt(v['uniform_binned'], '.1f')} / {_fmt(v['adaptive'], '.1f')}"
            for k, v in s["cpu_needed"].items()),
              flush=True)
        if "debiased" in s:
            print("  reference noise taken out: " + "; ".join(
                f"{k}: {_fmt(v['uniform_binned'])} / {_fmt(v['adaptive'])} = x{_fmt(v['ratio'], '.1f')}"
                for k, v in s["debiased"]["needed"].items()), flush=True)
    cl = summary.get(primary, {}).get("coverage_last_step")
    if cl:
        print(f"coverage vs {primary} at each replicate's last step ({cl['replicates']} replicates, median "
              f"{cl['n_median']:.0f} injections, half-width {cl['halfwidth_median']:.4f}): 68% {cl['cov68']:.2f} "
              f"(99% range {cl['band68']}), 95% {cl['cov95']:.2f} ({cl['band95']})", flush=True)
    cp = summary.get(primary, {}).get("coverage_past_800")
    if cp and cp.get("intervals"):
        wr = cp["with_reference_noise"]
        print(f"coverage vs {primary} over the {cp['intervals']} steps past 800 injections (median half-width "
              f"{cp['halfwidth_median']:.4f}): 68% {cp['cov68']:.2f}, 95% {cp['cov95']:.2f}; error / half-width "
              f"mean {cp['error_over_halfwidth']['mean']:+.2f} sd {_fmt(cp['error_over_halfwidth']['sd'], '.2f')}; with the "
              f"reference's own noise: 68% {wr['cov68']:.2f}, 95% {wr['cov95']:.2f}", flush=True)


def _fmt(v, spec: str = ".0f") -> str:
    return "n/a" if v is None else format(v, spec)


if __name__ == "__main__":
    raise SystemExit(main())
