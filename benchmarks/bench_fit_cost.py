"""Benchmark: what the completeness fit costs, as a ratio to the injection it models.

Three measurements, each in fresh processes launched as a user would launch them:

* ``demo``: ``comest-bayes demo`` with its defaults (point + buldisk, completeness and purity
  fits, ``--model auto``).  The run records the CPU seconds that the injection-recovery workers
  and the fit workers spent (``run.json`` timings ``inject_cpu`` and ``fit_cpu``); the ratio
  ``fit_cpu / inject_cpu`` is the figure of merit (target <= 0.2).  Run twice into fresh
  folders: the first with an empty JAX compilation cache (a user's first run), the second with
  the cache the first left.
* ``demo_2048_ncpu1``: the same demo on a 2048 x 2048 tile (point + buldisk, 10 realizations)
  with ``--ncpu 1`` and the warm cache: the issue's "no more than the injection's CPU time" case.
  Its data sizes differ from the 3000 x 3000 demo's, so it is run twice: the first run
  (``demo_2048_ncpu1_first_run``) compiles its programs, the second is the warm-cache figure.
* ``million``: 10^6 outcomes of a skewed truth (``synthetic`` ``skew_faint``) fitted by
  ``fitting.fit_kind`` with ``auto`` (selection of every rung, then the chosen model's
  posterior), wall time in a fresh process with the warm cache (target <= 10 s on 2 cores).
* ``adaptive``: ``comest-bayes demo --precision 0.01`` (twice; the second with the warm cache): the
  CPU of the design fits (``run.json`` ``design_fit_cpu``) against the injection's, issue #16's
  "a refit costs a small fraction of a batch".
* ``threads``: the largest number of threads of a process running that fit after
  ``runtime.configure(threads=1)`` (what ``--ncpu 1`` gives), read from ``/proc/self/task``.

Usage::

    python benchmarks/bench_fit_cost.py [--skip-demo] [--demo-size 3000] [--out benchmarks/results/fit_cost.json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent

MILLION = textwrap.dedent("""
    import json, os, sys, threading, time, warnings
    sys.path.insert(0, {root!r})
    from comest_bayes.pipeline import runtime
    runtime.configure(threads=1)
    import numpy as np
    from comest_bayes.sim import synthetic as S
    from comest_bayes.config import RunConfig
    from comest_bayes.bayes.fit import fit_kind
    from comest_bayes.ratios.binned import magnitude_edges
    peak = {{"threads": 0}}
    def watch():
        while True:
            peak["threads"] = max(peak["threads"], len(os.listdir("/proc/self/task")))
            time.sleep(0.05)
    threading.Thread(target=watch, daemon=True).start()
    scene = S.make_scene((512, 512), seed=1)
    truth = S.get_truth("skew_faint")
    lo, hi = truth.default_mag_range()
    table = S.draw_outcomes(truth, scene, {n}, seed=2)
    edges = magnitude_edges(lo, hi, 0.1)
    warnings.simplefilter("ignore")
    t0, c0 = time.perf_counter(), time.process_time()
    post, entry = fit_kind(table, kind="point", quantity="completeness", requested="auto", config=RunConfig(seed=3),
                           image_shape=scene.shape, noise=scene.noise, mask=scene.mask, wcs_header=None,
                           mag_range=(lo, hi), mag_centers=0.5 * (edges[:-1] + edges[1:]))
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    entry = entry.to_dict()
    q = S.truth_quantities(truth, scene)
    print(json.dumps({{"n": {n}, "wall": wall, "cpu": cpu, "threads": peak["threads"], "model": entry["name"],
                      "m50": entry["m50"], "m50_truth": q["m50"], "cells": entry["n_cells"],
                      "sampler": entry["diagnostics"].get("method"), "khat": entry["diagnostics"].get("khat")}}))
""")


def run_million(n: int, cache: str) -> dict:
    env = dict(os.environ, COMEST_BAYES_CACHE=cache)
    out = subprocess.run([sys.executable, "-c", MILLION.format(root=str(ROOT), n=n)], env=env, capture_output=True,
                         text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def run_demo(folder: Path, cache: str, size: int, ncpu: int | None = None, precision: float | None = None) -> dict:
    env = dict(os.environ, COMEST_BAYES_CACHE=cache)
    t0 = time.perf_counter()
    extra = [] if ncpu is None else ["--ncpu", str(ncpu)]
    if precision:
        extra += ["--precision", str(precision)]
    subprocess.run([sys.executable, "-m", "comest_bayes.cli", "demo", "--out", str(folder), "--size", str(size),
                    "--no-report", "--quiet", *extra], env=env, check=True, cwd=str(ROOT))
    wall = time.perf_counter() - t0
    state = json.loads((folder / "run.json").read_text())
    t = state.get("timings", {})
    out = {"wall": wall, "timings": t, "ratio_cpu": t.get("fit_cpu", float("nan")) / t.get("inject_cpu", float("nan")),
           "ratio_wall": t.get("fit", float("nan")) / t.get("inject", float("nan"))}
    if "design_fit_cpu" in t:  # an adaptive run: the design fits against the injection they steer
        out["design_ratio_cpu"] = t["design_fit_cpu"] / t.get("inject_cpu", float("nan"))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--skip-demo", action="store_true")
    p.add_argument("--demo-size", type=int, default=3000)
    p.add_argument("--small-size", type=int, default=2048,
                   help="also a demo of this size on one core (--ncpu 1), warm cache; 0 skips it")
    p.add_argument("--sizes", nargs="+", type=int, default=[30_000, 1_000_000])
    p.add_argument("--precision", type=float, default=0.01,
                   help="also the adaptive demo (--precision) twice, warm cache the second time: its design fits' CPU "
                        "against its injection's (run.json design_fit_cpu / inject_cpu); 0 skips it")
    p.add_argument("--out", default=str(HERE / "results" / "fit_cost.json"))
    a = p.parse_args(argv)
    result = {"machine": {"cpus": os.cpu_count(), "python": sys.version.split()[0]}}
    with tempfile.TemporaryDirectory() as tmp:
        cache = str(Path(tmp) / "jax-cache")
        if not a.skip_demo:
            result["demo_cold"] = run_demo(Path(tmp) / "demo1", cache, a.demo_size)
            print("demo, empty compilation cache:", json.dumps(result["demo_cold"]), flush=True)
            result["demo_warm"] = run_demo(Path(tmp) / "demo2", cache, a.demo_size)
            print("demo, warm compilation cache:", json.dumps(result["demo_warm"]), flush=True)
            if a.small_size:
                key = f"demo_{a.small_size}_ncpu1"
                # its data sizes (padded cell counts, footprint) differ from the larger demo's: a first run fills
                # the cache with their programs (reported as ..._first_run), the second is the warm-cache case
                result[key + "_first_run"] = run_demo(Path(tmp) / "demo3", cache, a.small_size, ncpu=1)
                print(f"demo {a.small_size}^2 on one core, first run of its sizes:",
                      json.dumps(result[key + "_first_run"]), flush=True)
                result[key] = run_demo(Path(tmp) / "demo4", cache, a.small_size, ncpu=1)
                print(f"demo {a.small_size}^2 on one core, warm cache:", json.dumps(result[key]), flush=True)
        if not a.skip_demo and a.precision:
            for key, folder in (("adaptive_first_run", "demo5"), ("adaptive", "demo6")):
                result[key] = run_demo(Path(tmp) / folder, cache, a.demo_size, precision=a.precision)
                print(f"adaptive demo (--precision {a.precision:g}), {key}:", json.dumps(result[key]), flush=True)
        for n in a.sizes:
            run_million(n, cache)  # fills the cache for this padded size
            result[f"fit_{n}"] = run_million(n, cache)
            print(f"{n} outcomes, warm cache:", json.dumps(result[f"fit_{n}"]), flush=True)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
