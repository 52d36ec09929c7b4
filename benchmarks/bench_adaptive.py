"""Benchmark: injections needed by the adaptive design against the published uniform + binned method.

Outcome-level scenes with a known completeness (:mod:`comest_bayes.synthetic`),
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
* **adaptive**: :func:`comest_bayes.adaptive.run_sequential` with the
  package's default fit (``auto``) after every batch (a uniform pilot of
  1000, then batches of half the injections so far, designed for
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
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

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
    from comest_bayes import synthetic as S

    p = SCENES[name]
    return S.make_scene(SHAPE, gradient=p["gradient"], chip_gap=p["chip_gap"], seed=seed)


def _truth_setup(name: str, scene):
    from comest_bayes import synthetic as S

    truth = S.get_truth(SCENES[name]["truth"])
    lo, hi = truth.default_mag_range()
    grid = np.arange(lo, hi + 1e-9, GRID_STEP)
    curve = S.truth_curve(truth, scene, grid)
    window = (curve >= 0.1) & (curve <= 0.9)
    return truth, (lo, hi), grid, curve, window, S.truth_quantities(truth, scene)["m50"]


def uniform_task(task: dict) -> dict:
    """Replicates of the published method at one N: m50 errors and curve RMS errors."""
    from comest_bayes import synthetic as S

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
    from comest_bayes import runtime

    runtime.configure(threads=1)
    from comest_bayes import synthetic as S
    from comest_bayes.adaptive import AdaptiveSettings, package_fitter, run_sequential

    scene = _scene(task["scene"], task["scene_seed"])
    truth, (lo, hi), grid, curve, window, m50 = _truth_setup(task["scene"], scene)
    fitter = package_fitter(image_shape=scene.shape, noise=scene.noise, mask=scene.mask, lo=lo, hi=hi,
                            seed=task["seed"])
    steps = []

    def fit(table, k):
        c0 = time.process_time()
        view, post = fitter(table, k)
        cpu = time.process_time() - c0
        med = np.median(view.curves, axis=0)
        ok = np.isfinite(view.m50)
        q = np.percentile(view.m50[ok], [2.275, 15.865, 50, 84.135, 97.725]) if ok.mean() >= 0.5 else [np.nan] * 5
        steps.append({"n": len(table), "m50_err": float(q[2] - m50),
                      "curve_rms": float(np.sqrt(np.mean((np.interp(grid[window], view.grid, med)
                                                          - curve[window]) ** 2))),
                      "halfwidth": view.m50_halfwidth, "cover68": bool(q[1] <= m50 <= q[3]),
                      "cover95": bool(q[0] <= m50 <= q[4]), "cpu_fit": cpu, "model": post[1]["name"]})
        return view, post

    def simulate(mags, k):
        return S.draw_outcomes(truth, scene, seed=task["seed"] * 1000 + k + 1, mags=mags)

    settings = AdaptiveSettings(precision=task["precision"], pilot=1000, growth=0.5, min_batch=250,
                                max_injections=task["cap"], target=task["target"])
    t0 = time.perf_counter()
    run_sequential(simulate, fit, lo, hi, settings, seed=task["seed"])
    return {"key": task["key"], "steps": steps, "wall": time.perf_counter() - t0}


def _needed(ns, rmse, target: float) -> float | None:
    """Injections where RMSE first falls to ``target`` (log-log interpolation between the bracketing N)."""
    ns, rmse = np.asarray(ns, float), np.asarray(rmse, float)
    ok = np.isfinite(rmse)
    ns, rmse = ns[ok], rmse[ok]
    below = np.flatnonzero(rmse <= target)
    if below.size == 0:
        return None
    i = int(below[0])
    if i == 0:
        return float(ns[0])
    x0, x1, y0, y1 = np.log(ns[i - 1]), np.log(ns[i]), np.log(rmse[i - 1]), np.log(rmse[i])
    return float(np.exp(x0 + (np.log(target) - y0) * (x1 - x0) / (y1 - y0)))


def _binom99(n: int, p: float) -> list:
    from scipy.stats import binom

    return [float(binom.ppf(0.005, n, p) / n), float(binom.ppf(0.995, n, p) / n)]


def summarise(raw: dict, scenes) -> dict:
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
        a_cpu = [float(np.mean([sum(s["cpu_fit"] for s in r["steps"][:j + 1]) for r in ada])) for j in range(nstep)]
        needed = {}
        for name, (what, level) in TARGETS.items():
            nu = _needed(u_n, u_m50 if what == "m50" else u_curve, level)
            na = _needed(a_n, a_m50 if what == "m50" else a_curve, level)
            needed[name] = {"uniform_binned": nu, "adaptive": na,
                            "ratio": None if nu is None or na is None else nu / na}
        # coverage at the first step whose half-width reaches 0.01 mag
        hits68, hits95 = [], []
        for r in ada:
            s = next((s for s in r["steps"] if s["halfwidth"] <= 0.01), None)
            if s is not None:
                hits68.append(s["cover68"])
                hits95.append(s["cover95"])
        nrep = len(hits68)
        out[sc] = {
            "truth": SCENES[sc]["truth"], "replicates": len(ada),
            "uniform": {"n": u_n, "m50_rmse": u_m50, "curve_rmse": u_curve},
            "adaptive": {"n": a_n, "m50_rmse": a_m50, "curve_rmse": a_curve, "cpu_fit_cumulative": a_cpu,
                         "models": sorted({s["model"] for r in ada for s in r["steps"]})},
            "needed": needed,
            "coverage_at_0.01": {"replicates": nrep,
                                 "cov68": float(np.mean(hits68)) if nrep else None,
                                 "cov95": float(np.mean(hits95)) if nrep else None,
                                 "band68": _binom99(nrep, 0.6827) if nrep else None,
                                 "band95": _binom99(nrep, 0.9545) if nrep else None},
        }
    return out


def chart(summary: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(summary)
    fig, axes = plt.subplots(2, len(scenes), figsize=(5 * len(scenes), 8), squeeze=False)
    for j, sc in enumerate(scenes):
        s = summary[sc]
        for i, (key, label, lines) in enumerate((("m50_rmse", "RMSE of m50 (mag)", (0.02, 0.01)),
                                                 ("curve_rmse", "RMSE of f(m), f in [0.1, 0.9]", (0.01,)))):
            ax = axes[i, j]
            ax.loglog(s["uniform"]["n"], s["uniform"][key], "s-", color="0.3", label="uniform + binned (published)")
            ax.loglog(s["adaptive"]["n"], s["adaptive"][key], "o-", color="tab:red", label="adaptive + model (auto)")
            for y in lines:
                ax.axhline(y, color="k", lw=0.6, ls=":")
            ax.set_xlabel("injections")
            ax.set_ylabel(label)
            ax.grid(alpha=0.3, which="both")
            if i == 0:
                nd = s["needed"]
                ax.set_title(f"{sc} ({s['truth']}): saving x" + ", x".join(
                    "n/a" if nd[k]["ratio"] is None else f"{nd[k]['ratio']:.1f}" for k in nd) + "\n"
                    "(m50 0.02, m50 0.01, curve 0.01)", fontsize=9)
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", nargs="+", default=list(SCENES))
    p.add_argument("--reps", type=int, default=20)
    p.add_argument("--cap", type=int, default=40000)
    p.add_argument("--precision", type=float, default=0.004,
                   help="adaptive runs stop at this m50 half-width (small: follow the RMSE down)")
    p.add_argument("--target", default="m50", choices=["m50", "curve"])
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--seed", type=int, default=16)
    p.add_argument("--out", default=str(HERE / "results" / "adaptive"))
    a = p.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    settings = {"seed": a.seed, "cap": a.cap, "precision": a.precision, "target": a.target}
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
                                           "seed": int_seed_for(a.seed, "adaptive", sc, rep)}))
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=a.workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = {pool.submit(uniform_task if kind == "uniform" else adaptive_task, t): (kind, t)
                   for kind, t in tasks}
        for i, fut in enumerate(as_completed(futures), 1):
            kind, t = futures[fut]
            res = fut.result()
            raw[kind][t["key"]] = res
            tmp = raw_path.with_name(".tmp-" + raw_path.name)
            tmp.write_text(json.dumps(raw))
            os.replace(tmp, raw_path)
            if kind == "adaptive":
                last = res["steps"][-1]
                print(f"[{i}/{len(tasks)}] adaptive {t['key']}: {last['n']} injections, m50 err "
                      f"{last['m50_err']:+.4f} +- {last['halfwidth']:.4f}, {res['wall']:.0f} s", flush=True)
            else:
                print(f"[{i}/{len(tasks)}] uniform {t['key']}", flush=True)
    summary = summarise(raw, a.scenes)
    report = {"settings": settings, "wall_seconds": time.perf_counter() - t0, "scenes": summary}
    (out / "adaptive.json").write_text(json.dumps(report, indent=1))
    chart(summary, out / "adaptive.png")
    for sc, s in summary.items():
        print(f"{sc} ({s['truth']}): injections needed uniform+binned / adaptive: " + "; ".join(
            f"{k}: {_fmt(v['uniform_binned'])} / {_fmt(v['adaptive'])} = x{_fmt(v['ratio'], '.1f')}"
            for k, v in s["needed"].items())
              + f"; coverage at half-width 0.01: 68% {s['coverage_at_0.01']['cov68']}, "
                f"95% {s['coverage_at_0.01']['cov95']} ({s['coverage_at_0.01']['replicates']} replicates)")
    print(f"wrote {out / 'adaptive.json'} and {out / 'adaptive.png'}")
    return 0


def _fmt(v, spec: str = ".0f") -> str:
    return "n/a" if v is None else format(v, spec)


if __name__ == "__main__":
    raise SystemExit(main())
