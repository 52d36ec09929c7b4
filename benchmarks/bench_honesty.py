"""Benchmark: are the completeness posterior's intervals honest when the truth is in no model's family?

For every known completeness truth of :mod:`comest_bayes.sim.synthetic` (a skewed
faint end, a skewed bright end, a long faint tail, two populations, a low
plateau with a slow roll-off, a width that changes across the image, and a
plain logistic as the control; every one with m50 following the depth one for
one) and every number of injections N (3000, 30000, 300000 by default, with
50, 20 and 8 replicates), the script

1. draws an outcome table (uniform unmasked positions on a fixed synthetic
   512 x 512 scene with a depth gradient, a chip gap and masked blobs;
   magnitudes uniform over the truth's range; detected ~ Bernoulli(f));
2. fits it through the package's own path,
   :func:`comest_bayes.bayes.fit.fit_kind` (``covariates_from_outcomes`` ->
   ``compress_for`` -> model selection / ``inference.fit`` ->
   ``CompletenessPosterior``) with ``--model`` (default ``auto``);
3. reads off the posterior of the image-average m50, m90 and f at the truth's
   m50 -/+ 0.3 mag (``magnitudes_at`` and ``average_curve`` draws; median,
   central 68% and 95% intervals, sd) and the posterior-median image-average
   curve on a 0.05-mag grid over the magnitudes where the true curve is
   between 0.1 and 0.9;
4. computes the published binned estimate (0.1-mag bins; m50, m90 by linear
   interpolation at the first crossing; the curve interpolated between bin
   centres).

Per truth and N it then reports the empirical coverage of the 68% and 95%
intervals against the exact image-average truth, with the binomial 99% range
of the nominal level for that number of replicates; the mean bias and its
standard error (empirical, and ``se_p`` = mean posterior sd / sqrt(R): a few
replicates can scatter far less than a calibrated posterior's sd by chance, and
an empirical se alone then makes a chance mean look resolved); the mean
posterior sd and |bias| / sd; the RMSE of the
posterior median and of the binned estimate (m50 and the curve); and the fit
wall time.  A calibrated posterior has coverages inside the bands at every N;
a model whose form cannot follow the truth shows coverage falling with N while
its RMSE stops falling (bias-dominated), as Issue 12 found.

Each replicate also records, as ``truth_footprint``, the truth averaged over a
2000-pixel sample of the footprint (``cov68_fp`` in the JSON).  It was the
diagnostic that found the 400-pixel image average's error; the posterior now
averages over every unmasked pixel, so the coverage against the full truth is
the one that counts.

Usage::

    python benchmarks/bench_honesty.py                    # everything (hours: 546 fits)
    python benchmarks/bench_honesty.py --truths logistic skew_faint --sizes 3000 --reps 2 \\
        --model logistic_depth --out /tmp/honesty_trial  # a trial
    #   --seed S  --workers W  --min-ess E (override FitConfig.min_ess)  --summarise-only

Replicates run in ``--workers`` spawned processes, each single-threaded (XLA
and OpenMP), seeded by (root seed, truth, N, replicate) only, so the numbers
do not depend on the worker count or completion order.  Raw per-replicate
results go to ``<out>/raw.json`` as they arrive; a rerun with the same
settings skips the replicates already there.  The summary goes to
``<out>/honesty.json`` and the chart to ``<out>/honesty.png``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
# this checkout first: a non-editable install in site-packages may be an older copy
sys.path.insert(0, str(HERE.parent))

# NOTE: nothing here imports jax or comest_bayes at module level: spawned workers import this
# module first, and must set their thread flags before jax is imported (see run_replicate).

DEFAULT_SIZES = (3000, 30000, 300000)
DEFAULT_REPS = (50, 20, 8)
QUANTITIES = ("m50", "m90", "f_bright", "f_faint")
MAG_BIN = 0.1
CURVE_STEP = 0.05
CURVE_LEVELS = (0.1, 0.9)
SCENE = {"shape": [512, 512], "gradient": 0.6, "chip_gap": True}
XLA_FLAGS = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"

_WORKER_STATE: dict = {}


# --------------------------------------------------------------------------- worker

def _scene(params: dict):
    from comest_bayes.sim.synthetic import make_scene

    key = json.dumps(params, sort_keys=True)
    if _WORKER_STATE.get("scene_key") != key:
        _WORKER_STATE["scene"] = make_scene(tuple(params["shape"]), gradient=params["gradient"],
                                            chip_gap=params["chip_gap"], seed=params["seed"])
        _WORKER_STATE["scene_key"] = key
    return _WORKER_STATE["scene"]


def _interval(draws) -> dict:
    import numpy as np

    d = np.asarray(draws, dtype=float).ravel()
    ok = np.isfinite(d)
    frac = float(ok.mean()) if d.size else 0.0
    if frac < 0.5:
        return {"defined_fraction": frac}
    q = np.percentile(d[ok], [2.5, 16.0, 50.0, 84.0, 97.5])
    return {"median": float(q[2]), "lo68": float(q[1]), "hi68": float(q[3]), "lo95": float(q[0]),
            "hi95": float(q[4]), "sd": float(np.std(d[ok], ddof=1)) if ok.sum() > 1 else 0.0,
            "defined_fraction": frac}


def _num(v):
    return None if v is None or not math.isfinite(v) else float(v)


def run_replicate(task: dict) -> dict:
    """Draw, fit and measure one replicate (the worker entry point; picklable task in, JSON-ready dict out)."""
    # single-threaded numerics, set before jax (or a BLAS) is first imported in this process
    from comest_bayes.pipeline import runtime

    runtime.configure(threads=1)  # one XLA/BLAS thread and the compilation cache, before the first jax use
    import inspect
    import warnings

    import numpy as np

    from comest_bayes.ratios import binned as R
    from comest_bayes.sim import synthetic as S
    from comest_bayes.config import FitConfig, RunConfig
    from comest_bayes.bayes.fit import fit_kind

    _WORKER_STATE["ntasks"] = _WORKER_STATE.get("ntasks", 0) + 1
    scene = _scene(task["scene"])
    truth = S.get_truth(task["truth"])
    lo, hi = task["mag_range"]
    table = S.draw_outcomes(truth, scene, task["n"], mag_range=(lo, hi), seed=task["draw_seed"])
    edges = R.magnitude_edges(lo, hi, MAG_BIN)
    centers = 0.5 * (edges[:-1] + edges[1:])
    fit_settings = {k: task[k] for k in ("min_ess", "sampler", "max_steps") if task.get(k) is not None}
    config = RunConfig(seed=task["fit_seed"], fit=FitConfig(**fit_settings))
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    t0, c0 = time.perf_counter(), time.process_time()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        post, entry = fit_kind(table, kind="point", quantity="completeness", requested=task["model"],
                               config=config, image_shape=scene.shape, noise=scene.noise, mask=scene.mask,
                               wcs_header=None, mag_range=(lo, hi), mag_centers=centers)
    seconds, cpu_seconds = time.perf_counter() - t0, time.process_time() - c0

    t1 = time.perf_counter()
    tq = task["truth_q"]
    probes = np.array([tq["mag_bright"], tq["mag_faint"]])
    grid = np.asarray(task["grid"], dtype=float)
    levels = post.magnitudes_at((0.5, 0.9))
    by_level = {round(float(k), 6): v for k, v in levels.items()}
    f_probe = post.average_curve(probes)
    curve = np.median(post.average_curve(grid), axis=0)
    posterior = {"m50": _interval(by_level[0.5]), "m90": _interval(by_level[0.9]),
                 "f_bright": _interval(f_probe[:, 0]), "f_faint": _interval(f_probe[:, 1])}
    query_seconds = time.perf_counter() - t1

    truth_curve = np.asarray(task["grid_truth"], dtype=float)
    binned = S.binned_estimate(table, mag_bin=MAG_BIN, mag_range=(lo, hi), probes=probes)
    binned_curve = binned.curve(grid)

    # the truth averaged over the posterior's own footprint sample (what its image average can see)
    try:
        npos = int(inspect.signature(post.average_curve).parameters["npos"].default)
    except (KeyError, TypeError, ValueError):
        npos = 400
    fp = np.asarray(post.footprint, dtype=float)[:npos]
    tq_fp = S.truth_quantities(truth, scene, positions=fp)

    entry = entry.to_dict()
    diag = entry.get("diagnostics") or {}
    sel = entry.get("selection") or {}
    shape = entry.get("shape_check") or {}
    return {
        "truth": truth.name, "n": int(task["n"]), "rep": int(task["rep"]),
        "draw_seed": int(task["draw_seed"]), "fit_seed": int(task["fit_seed"]),
        "model": entry.get("name"), "rule": sel.get("rule"),
        "width_p": (sel.get("width_test") or {}).get("p_value"),
        "seconds": round(seconds, 3), "cpu_seconds": round(cpu_seconds, 3), "query_seconds": round(query_seconds, 3), "load": load,
        "worker_pid": os.getpid(), "worker_task": _WORKER_STATE["ntasks"],
        "n_detected": int(np.sum(table["detected"])),
        "posterior": posterior,
        "binned": {"m50": _num(binned.m50), "m90": _num(binned.m90), "f_bright": _num(float(binned.f_probe[0])),
                   "f_faint": _num(float(binned.f_probe[1]))},
        "curve_mse": {"model": float(np.mean((curve - truth_curve) ** 2)),
                      "binned": _num(float(np.mean((binned_curve - truth_curve) ** 2)))},
        "truth_footprint": {q: _num(tq_fp[k]) for q, k in (("m50", "m50"), ("m90", "m90"))} | {
            "f_bright": _num(float(S.truth_curve(truth, scene, tq["mag_bright"], positions=fp))),
            "f_faint": _num(float(S.truth_curve(truth, scene, tq["mag_faint"], positions=fp)))},
        "npos": int(len(fp)),
        "converged": diag.get("converged"),
        "sampler": diag.get("method"), "sampler_seconds": diag.get("seconds"),
        "shape_p": shape.get("p_value"),
        "warnings": sorted({str(w.message)[:200] for w in caught})[:10],
    }


# --------------------------------------------------------------------------- main process

def _atomic_write(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def make_task(truths: dict, name: str, n: int, rep: int, *, seed: int, scene_params: dict, model: str,
              min_ess=None, sampler=None, max_steps=None) -> dict:
    """The worker's task for replicate ``rep`` of truth ``name`` at ``n`` injections (``truths``: :func:`truth_setup`).

    ``sampler`` and ``max_steps`` override the package's ``FitConfig`` defaults (``bench_samplers.py``).
    """
    from comest_bayes.seeding import int_seed_for

    t = truths[name]
    return {"key": f"{name}|{n}|{rep}", "truth": name, "n": n, "rep": rep, "model": model,
            "draw_seed": int_seed_for(seed, "honesty", name, n, rep, "draw"),
            "fit_seed": int_seed_for(seed, "honesty", name, n, rep, "fit"),
            "scene": scene_params, "mag_range": t["mag_range"], "truth_q": t["quantities"],
            "grid": t["grid"], "grid_truth": t["grid_truth"], "min_ess": min_ess, "sampler": sampler,
            "max_steps": max_steps}


def truth_setup(names, scene) -> dict:
    """Exact image-average quantities, injection range and curve grid of each truth."""
    import numpy as np

    from comest_bayes.sim import synthetic as S

    out = {}
    for name in names:
        truth = S.get_truth(name)
        lo, hi = truth.default_mag_range()
        q = S.truth_quantities(truth, scene)
        full = np.arange(math.ceil(lo / CURVE_STEP - 1e-9), math.floor(hi / CURVE_STEP + 1e-9) + 1) * CURVE_STEP
        fc = S.truth_curve(truth, scene, full)
        keep = (fc >= CURVE_LEVELS[0]) & (fc <= CURVE_LEVELS[1])
        out[name] = {"description": truth.description, "parameters": truth.to_dict(), "mag_range": [lo, hi],
                     "quantities": {k: _num(v) for k, v in q.items()},
                     "grid": [round(float(v), 6) for v in full[keep]], "grid_truth": [float(v) for v in fc[keep]]}
    return out


def binomial_band(nrep: int, level: float) -> list:
    """The central 99% range of Binomial(nrep, level) / nrep."""
    from scipy import stats

    if nrep <= 0:
        return [None, None]
    lo, hi = stats.binom.ppf([0.005, 0.995], nrep, level) / nrep
    return [float(lo), float(hi)]


def summarise(records: list, truths: dict) -> dict:
    """Coverage, bias, sd, RMSE and time per truth and N from the raw replicate records."""
    from collections import Counter

    import numpy as np

    out: dict = {}
    groups: dict = {}
    for r in records:
        groups.setdefault((r["truth"], int(r["n"])), []).append(r)
    for (name, n), recs in sorted(groups.items(), key=lambda kv: (list(truths).index(kv[0][0])
                                                                  if kv[0][0] in truths else 99, kv[0][1])):
        tq = truths[name]["quantities"]
        row: dict = {"reps": len(recs), "models": dict(Counter(str(r["model"]) for r in recs)),
                     "seconds_mean": float(np.mean([r["seconds"] for r in recs])),
                     "seconds_max": float(np.max([r["seconds"] for r in recs])),
                     "query_seconds_mean": float(np.mean([r.get("query_seconds", 0.0) for r in recs]))}
        for qname in QUANTITIES:
            t = tq.get(qname)
            if t is None:
                row[qname] = {"truth": None, "note": "undefined for this truth",
                              "posterior_defined": int(sum("median" in r["posterior"][qname] for r in recs))}
                continue
            post = [r["posterior"][qname] for r in recs]
            defined = [p for p in post if "median" in p]
            n_rep = len(post)
            res: dict = {"truth": t, "n_defined": len(defined)}
            for lev, tag in ((0.68, "68"), (0.95, "95")):
                # an undefined posterior interval counts as a miss
                hits = [("median" in p) and (p[f"lo{tag}"] <= t <= p[f"hi{tag}"]) for p in post]
                res[f"cov{tag}"] = float(np.mean(hits))
                res[f"band{tag}"] = binomial_band(n_rep, lev)
                fp_hits = []
                for p, r in zip(post, recs):
                    tf = r.get("truth_footprint", {}).get(qname)
                    if tf is not None:
                        fp_hits.append(("median" in p) and (p[f"lo{tag}"] <= tf <= p[f"hi{tag}"]))
                res[f"cov{tag}_fp"] = float(np.mean(fp_hits)) if fp_hits else None
            if defined:
                err = np.array([p["median"] - t for p in defined])
                sd = np.array([p["sd"] for p in defined])
                res["bias"] = float(err.mean())
                res["bias_se"] = float(err.std(ddof=1) / math.sqrt(len(err))) if len(err) > 1 else None
                res["sd_mean"] = float(sd.mean())
                # the se of the mean error if the replicates scatter by the posterior sd (a calibrated
                # posterior's do): the empirical se of a few replicates can be far smaller by chance
                # (results/honesty_width_uv/bias300/: 300k width_varies, replicates 0-7)
                res["bias_se_post"] = float(sd.mean() / math.sqrt(len(err)))
                res["spread_over_sd"] = float(err.std(ddof=1) / sd.mean()) if len(err) > 1 and sd.mean() > 0 else None
                res["abs_bias_over_sd"] = float(abs(err.mean()) / sd.mean()) if sd.mean() > 0 else None
                res["rmse_model"] = float(np.sqrt(np.mean(err ** 2)))
            b = np.array([r["binned"][qname] for r in recs if r["binned"].get(qname) is not None], dtype=float)
            if b.size:
                res["bias_binned"] = float(np.mean(b - t))
                res["rmse_binned"] = float(np.sqrt(np.mean((b - t) ** 2)))
                res["n_binned"] = int(b.size)
            row[qname] = res
        cm = [r["curve_mse"]["model"] for r in recs]
        cb = [r["curve_mse"]["binned"] for r in recs if r["curve_mse"].get("binned") is not None]
        row["curve"] = {"rmse_model": float(np.sqrt(np.mean(cm))),
                        "rmse_binned": float(np.sqrt(np.mean(cb))) if cb else None,
                        "grid": [truths[name]["grid"][0], truths[name]["grid"][-1]] if truths[name]["grid"] else None}
        out.setdefault(name, {})[str(n)] = row
    return out


def _f(v, fmt=".3f", width=6) -> str:
    return f"{'-':>{width}s}" if v is None else f"{v:{width}{fmt}}"


def print_table(summary: dict, log=print) -> None:
    """The summary as plain text: m50 in detail, then the coverage of every quantity."""
    log("\nm50 of the image-average curve (bias, sd, RMSE in mmag; coverage with the binomial 99% range)")
    head = (f"{'truth':<16s} {'N':>7s} {'R':>3s} {'cov68':>6s} {'[99% range]':>13s} {'cov95':>6s} "
            f"{'[99% range]':>13s} {'bias':>7s} {'+-se':>6s} {'se_p':>6s} {'sd':>6s} {'|b|/sd':>6s} {'rmse':>6s} "
            f"{'binned':>6s} {'curve':>6s} {'binned':>6s} {'fit s':>6s}  models")
    log(head)
    log("-" * len(head))
    for name, by_n in summary.items():
        for n, row in by_n.items():
            m = row["m50"]
            if m.get("truth") is None:
                continue
            b68, b95 = m["band68"], m["band95"]
            models = ", ".join(f"{k} x{v}" for k, v in sorted(row["models"].items()))
            mm = lambda v: None if v is None else 1e3 * v  # noqa: E731
            log(f"{name:<16s} {int(n):>7d} {row['reps']:>3d} {m['cov68']:>6.2f} [{b68[0]:.2f}, {b68[1]:.2f}] "
                f"{m['cov95']:>6.2f} [{b95[0]:.2f}, {b95[1]:.2f}] {_f(mm(m.get('bias')), '.1f', 7)} "
                f"{_f(mm(m.get('bias_se')), '.1f')} {_f(mm(m.get('bias_se_post')), '.1f')} {_f(mm(m.get('sd_mean')), '.1f')} "
                f"{_f(m.get('abs_bias_over_sd'), '.2f')} {_f(mm(m.get('rmse_model')), '.1f')} "
                f"{_f(mm(m.get('rmse_binned')), '.1f')} {_f(mm(row['curve']['rmse_model']), '.1f')} "
                f"{_f(mm(row['curve']['rmse_binned']), '.1f')} {row['seconds_mean']:>6.1f}  {models}")
    log("  (curve: RMSE x 1000 of the posterior-median / binned image-average curve where the truth is in "
        "[0.1, 0.9]; +-se: the empirical se of the bias, se_p: sd / sqrt(R), the se if the replicates scatter "
        "by the posterior sd; judge a bias against the larger of the two)")
    log("\ncoverage 68% / 95% of each quantity (* = outside the binomial 99% range)")
    head = f"{'truth':<16s} {'N':>7s} " + " ".join(f"{q:>15s}" for q in QUANTITIES)
    log(head)
    log("-" * len(head))
    for name, by_n in summary.items():
        for n, row in by_n.items():
            cells = []
            for q in QUANTITIES:
                c = row[q]
                if c.get("truth") is None:
                    cells.append(f"{'n/a':>15s}")
                    continue
                s = []
                for tag in ("68", "95"):
                    lo, hi = c[f"band{tag}"]
                    flag = "*" if not (lo <= c[f"cov{tag}"] <= hi) else " "
                    s.append(f"{c[f'cov{tag}']:.2f}{flag}")
                cells.append(f"{' / '.join(s):>15s}")
            log(f"{name:<16s} {int(n):>7d} " + " ".join(cells))


def chart(summary: dict, truths: dict, path: Path) -> None:
    """Coverage per truth and N with binomial bands; RMSE of the model and the binned estimate."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [n for n in truths if n in summary]
    sizes = sorted({int(n) for by_n in summary.values() for n in by_n})
    colors = {n: c for n, c in zip(sizes, ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple"))}
    offs = {n: (i - (len(sizes) - 1) / 2) * 0.22 for i, n in enumerate(sizes)}
    markers = {"m50": "o", "m90": "^", "f_bright": "<", "f_faint": ">"}
    fig, axes = plt.subplots(2, 2, figsize=(13, 8.5))
    for ax, tag, nominal in ((axes[0, 0], "68", 0.68), (axes[0, 1], "95", 0.95)):
        for i, name in enumerate(names):
            for n in sizes:
                row = summary[name].get(str(n))
                if row is None:
                    continue
                x = i + offs[n]
                band = row["m50"].get(f"band{tag}") or binomial_band(row["reps"], nominal)
                ax.plot([x, x], band, color=colors[n], alpha=0.3, lw=7, solid_capstyle="butt")
                for q, mk in markers.items():
                    c = row[q]
                    if c.get("truth") is None:
                        continue
                    dx = {"m50": 0, "m90": -0.04, "f_bright": 0.04, "f_faint": 0.08}[q]
                    ax.plot(x + dx, c[f"cov{tag}"], mk, color=colors[n], ms=7 if q == "m50" else 4,
                            mfc=colors[n] if q == "m50" else "none")
        ax.axhline(nominal, color="k", lw=0.8, ls="--")
        ax.set_xticks(range(len(names)))
        ax.set_xticklabels(names, rotation=25, ha="right", fontsize=8)
        ax.set_ylim(-0.03, 1.03)
        ax.set_ylabel(f"coverage of the central {tag}% interval")
        ax.set_title(f"{tag}% intervals (bars: binomial 99% range; filled o: m50; ^ m90, <> f(m50 -/+ 0.3))",
                     fontsize=9)
    for ax, key, title in ((axes[1, 0], "m50", "RMSE of the image-average m50 (mag)"),
                           (axes[1, 1], "curve", "RMSE of the image-average curve where 0.1 < f < 0.9")):
        ax.plot([], [], "o", color="0.4", label="posterior median")
        ax.plot([], [], "s", color="0.4", mfc="none", label=f"binned ({MAG_BIN} mag)")
        ax.legend(fontsize=8)
        for i, name in enumerate(names):
            for n in sizes:
                row = summary[name].get(str(n))
                if row is None:
                    continue
                x = i + offs[n]
                c = row[key]
                rm = c.get("rmse_model")
                rb = c.get("rmse_binned")
                if rm is not None:
                    ax.plot(x, rm, "o", color=colors[n], ms=7)
                if rb is not None:
                    ax.plot(x, rb, "s", color=colors[n], ms=7, mfc="none")
        ax.set_yscale("log")
        ax.set_xticks(range(len(names)))
        ax.set_xticklabels(names, rotation=25, ha="right", fontsize=8)
        ax.set_title(title, fontsize=9)
    for n in sizes:
        axes[0, 0].plot([], [], "o", color=colors[n], label=f"N = {n}")
    axes[0, 0].legend(fontsize=8, loc="lower left")
    for ax in axes.ravel():
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--truths", nargs="+", default=None, help="truth names (default: all of synthetic.TRUTHS)")
    p.add_argument("--sizes", nargs="+", type=int, default=list(DEFAULT_SIZES), help="numbers of injections N")
    p.add_argument("--reps", nargs="+", type=int, default=None,
                   help="replicates per N: one value for all sizes, or one per size "
                        f"(default {list(DEFAULT_REPS)} for {list(DEFAULT_SIZES)})")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--model", default="auto", help="model spec name/path or selection (default auto)")
    p.add_argument("--seed", type=int, default=12, help="root seed (scene, outcome tables, fits)")
    p.add_argument("--min-ess", type=float, default=None,
                   help="override FitConfig.min_ess (default: the package default)")
    p.add_argument("--out", default=str(HERE / "results" / "honesty"))
    p.add_argument("--summarise-only", action="store_true", help="only rebuild the summary from raw.json")
    a = p.parse_args(argv)

    from comest_bayes.sim import synthetic as S
    from comest_bayes.seeding import int_seed_for

    names = a.truths or list(S.TRUTHS)
    for name in names:
        if name not in S.TRUTHS:
            p.error(f"unknown truth {name!r}; choose from {list(S.TRUTHS)}")
    sizes = [int(n) for n in a.sizes]
    if any(n < 1 for n in sizes):
        p.error("--sizes must be positive")
    if a.reps is None:
        defaults = dict(zip(DEFAULT_SIZES, DEFAULT_REPS))
        reps = [defaults.get(n, DEFAULT_REPS[-1]) for n in sizes]
    elif len(a.reps) == 1:
        reps = a.reps * len(sizes)
    elif len(a.reps) == len(sizes):
        reps = list(a.reps)
    else:
        p.error("--reps takes one value, or one per --sizes value")
    if a.workers < 1 or min(reps) < 1:
        p.error("--workers and --reps must be >= 1")

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    log = lambda s: print(s, flush=True)  # noqa: E731
    scene_params = {**SCENE, "seed": int_seed_for(a.seed, "honesty", "scene")}
    settings = {"seed": a.seed, "model": a.model, "scene": scene_params, "mag_bin": MAG_BIN,
                "min_ess": a.min_ess}
    raw_path = out / "raw.json"
    raw = {"settings": settings, "records": {}}
    if raw_path.exists():
        raw = json.loads(raw_path.read_text())
        if raw.get("settings") != settings:
            raise SystemExit(f"{raw_path} was written with other settings {raw.get('settings')}; "
                             f"use another --out or delete it (now: {settings}).")
        log(f"resuming: {len(raw['records'])} replicates already in {raw_path}")

    t_setup = time.perf_counter()
    scene = S.make_scene(tuple(SCENE["shape"]), gradient=SCENE["gradient"], chip_gap=SCENE["chip_gap"],
                         seed=scene_params["seed"])
    truths = truth_setup(names, scene)
    log(f"scene {scene.shape}, {100 * scene.masked_fraction:.1f}% masked, depth "
        f"{scene.depth[~scene.mask].min():+.2f} .. {scene.depth[~scene.mask].max():+.2f} mag; truths set up in "
        f"{time.perf_counter() - t_setup:.1f} s")
    for name, t in truths.items():
        q = t["quantities"]
        log(f"  {name:<16s} m50 {q['m50']:.4f}  m90 {_f(q['m90'], '.4f', 7).strip()}  "
            f"f(m50-0.3) {q['f_bright']:.4f}  f(m50+0.3) {q['f_faint']:.4f}  range {t['mag_range']}: "
            f"{t['description']}")

    tasks = []
    for n, nrep in zip(sizes, reps):
        for rep in range(nrep):
            for name in names:
                key = f"{name}|{n}|{rep}"
                if key in raw["records"]:
                    continue
                tasks.append(make_task(truths, name, n, rep, seed=a.seed, scene_params=scene_params, model=a.model,
                                       min_ess=a.min_ess))
    failures = []
    if tasks and not a.summarise_only:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed

        log(f"{len(tasks)} replicate fits on {a.workers} spawned worker(s), model {a.model!r}")
        t_all = time.perf_counter()
        with ProcessPoolExecutor(max_workers=a.workers, mp_context=multiprocessing.get_context("spawn")) as pool:
            futures = {pool.submit(run_replicate, t): t for t in tasks}
            for done, fut in enumerate(as_completed(futures), 1):
                task = futures[fut]
                try:
                    rec = fut.result()
                except Exception as exc:  # noqa: BLE001 - a failed fit is reported, not fatal
                    failures.append({"key": task["key"], "error": f"{type(exc).__name__}: {exc}"})
                    log(f"[{done}/{len(tasks)}] {task['key']}: FAILED {type(exc).__name__}: {exc}")
                    continue
                raw["records"][task["key"]] = rec
                _atomic_write(raw_path, json.dumps(raw, indent=0))
                m = rec["posterior"]["m50"]
                tq = task["truth_q"]
                med = m.get("median")
                log(f"[{done}/{len(tasks)}] {task['key']}: {rec['model']} in {rec['seconds']:.1f} s "
                    f"({rec['cpu_seconds']:.1f} CPU-s; +{rec['query_seconds']:.1f} s queries); m50 "
                    + (f"{med:.4f} [{m['lo68']:.4f}, {m['hi68']:.4f}]" if med is not None else "undefined")
                    + f" truth {tq['m50']:.4f}, binned {_f(rec['binned']['m50'], '.4f', 7).strip()}")
        log(f"fits done in {time.perf_counter() - t_all:.0f} s wall")

    wanted = {f"{name}|{n}|{rep}" for n, nrep in zip(sizes, reps) for rep in range(nrep) for name in names}
    records = [r for k, r in raw["records"].items() if k in wanted]
    summary = summarise(records, truths)
    report = {
        "command": " ".join([Path(sys.argv[0]).name, *(argv if argv is not None else sys.argv[1:])]),
        "settings": settings, "sizes": sizes, "reps": reps,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
        "definitions": {
            "truth": "exact average of f over every unmasked pixel of the scene (comest_bayes.sim.synthetic)",
            "posterior": "fit_kind(...) -> CompletenessPosterior; m50/m90 from magnitudes_at, f from "
                         "average_curve (the package's footprint-sample image average); central 68%/95% "
                         "intervals of the draws; a posterior with < 50% defined draws counts as a miss",
            "binned": f"{MAG_BIN}-mag bins; m50/m90 by ratios.magnitude_at; curve interpolated between centres",
            "band": "central 99% range of Binomial(R, nominal) / R",
            "curve_rmse": f"over a {CURVE_STEP}-mag grid where the truth is in {list(CURVE_LEVELS)}",
            "cov_fp": "coverage against the truth averaged over the posterior's own footprint sample"},
        "truths": {k: {kk: vv for kk, vv in v.items() if kk != "grid_truth"} for k, v in truths.items()},
        "summary": summary,
        "failures": failures,
        "raw_file": str(raw_path),
    }
    _atomic_write(out / "honesty.json", json.dumps(report, indent=1))
    if summary:
        print_table(summary, log)
        chart(summary, truths, out / "honesty.png")
        log(f"\nwrote {out / 'honesty.json'}, {out / 'honesty.png'} and {raw_path}")
    if failures:
        log(f"{len(failures)} replicate(s) failed: " + "; ".join(f"{f['key']}: {f['error']}" for f in failures[:5]))
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
