"""Benchmark: the XLA options of the completeness model's programs (``jaxnum.CPU_COMPILER_OPTIONS``).

A user's first fit compiles every program it uses; on the demo those compiles cost more CPU than
the fit's evaluations.  This script measures, each in fresh processes:

* ``demo``: ``comest-bayes demo --ncpu 1`` with an empty compilation cache (a user's first run),
  then ``--warm-runs`` times with the cache it left, once as the package runs (the options on its
  programs but the batched log posterior) and once with XLA's defaults on every program.  Figure
  of merit: ``run.json`` ``fit_cpu / inject_cpu``.
* ``programs``: every program that first demo stored (``<cache>/exports``), compiled with XLA's
  defaults and with the options, in alternating fresh processes: compile CPU seconds and the
  mean wall time of an evaluation (400 calls on inputs of the stored shapes).
* ``honesty`` (``--honesty REPS``): the first REPS replicates of every truth of
  ``bench_honesty.py`` at 3,000 injections, fitted in one process per setting, three alternating
  passes (the first fills the cache): the fits' CPU seconds.
* ``nuts`` (``--nuts``): three honesty-benchmark tables whose fit reaches NUTS, fitted with NUTS's
  programs compiled with XLA's defaults (as the package does) and with the options: the sampler's
  seconds with a warm cache.  The reason the options are not used there.

Usage::

    python benchmarks/bench_compile_options.py [--nuts] [--honesty 3] [--repeats 2] [--out benchmarks/results/compile_options.json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent

# run in a child: with "defaults", every program of the package gets XLA's defaults; with "nuts_options",
# NUTS's two top-level programs get the options too (their nested jax.jit calls cannot take any)
PRELUDE = textwrap.dedent("""
    import sys
    sys.path.insert(0, {root!r})
    import comest_bayes.jaxnum as jn
    mode = {mode!r}
    if mode == "defaults":
        jn.CPU_COMPILER_OPTIONS = {{}}
    elif mode == "nuts_options":
        from comest_bayes.bayes import nuts
        progs = nuts._programs()
        for name in ("warmup", "draws"):
            progs[name] = jn.jax.jit(progs[name].__wrapped__, static_argnums=(0, 1, 2),
                                     compiler_options=dict(jn.CPU_COMPILER_OPTIONS))
""")

DEMO = PRELUDE + textwrap.dedent("""
    from comest_bayes.cli import main
    sys.exit(main(["demo", "--ncpu", "1", "--out", {out!r}, "--no-report", "--quiet"]))
""")

PROGRAMS = textwrap.dedent("""
    import glob, json, os, time
    os.environ["XLA_FLAGS"] = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
    import sys
    sys.path.insert(0, {root!r})
    import numpy as np
    import comest_bayes.jaxnum as jn
    from jax import export
    jax, jnp = jn.jax, jn.jnp
    opts = dict(jn.CPU_COMPILER_OPTIONS) if {with_options!r} else None
    out = {{}}
    for path in sorted(glob.glob(os.path.join({folder!r}, "*.jaxexport"))):
        exp = export.deserialize(bytearray(open(path, "rb").read()))
        rng = np.random.default_rng(1)  # inputs of the stored shapes (values in the range of the model's)
        flat = [jnp.asarray(rng.uniform(0.05, 0.3, a.shape).astype(a.dtype)) for a in exp.in_avals]
        args = jax.tree_util.tree_unflatten(exp.in_tree, flat)[0]
        lowered = jax.jit(exp.call).lower(*args)
        t = time.process_time()
        compiled = lowered.compile(compiler_options=opts) if opts else lowered.compile()
        compile_cpu = time.process_time() - t
        jax.block_until_ready(compiled(*args))
        t = time.perf_counter()
        for _ in range(400):
            res = compiled(*args)
        jax.block_until_ready(res)
        rec = {{"compile_cpu": compile_cpu, "eval_ms": (time.perf_counter() - t) / 400 * 1e3}}
        if opts:  # the outputs against those of XLA's defaults (compiled untimed)
            ref = lowered.compile()(*args)
            rec["max_rel_diff"] = max(
                (float(np.max(np.abs(np.asarray(x) - np.asarray(y)) / np.maximum(np.abs(np.asarray(y)), 1e-300)))
                 if np.asarray(y).size else 0.0)
                for x, y in zip(jax.tree_util.tree_leaves(res), jax.tree_util.tree_leaves(ref)))
        out[os.path.basename(path).split("-")[0] + "-" + os.path.basename(path).split("-")[1][:8]] = rec
    print(json.dumps(out))
""")

# the honesty benchmark's scene and seeds (bench_honesty.py, root seed 12), in a child after PRELUDE
HONESTY_SETUP = PRELUDE + textwrap.dedent("""
    import json
    sys.path.insert(0, {bench!r})
    import bench_honesty as B
    from comest_bayes.pipeline import runtime
    runtime.configure(threads=1)
    from comest_bayes.seeding import int_seed_for
    seed = 12
    sp = {{"shape": [512, 512], "gradient": 0.6, "chip_gap": True, "seed": int_seed_for(seed, "honesty", "scene")}}
""")

NUTS = HONESTY_SETUP + textwrap.dedent("""
    res = []
    for name, n, rep in {tables!r}:
        truths = B.truth_setup([name], B._scene(sp))
        rec = B.run_replicate(B.make_task(truths, name, n, rep, seed=seed, scene_params=sp, model="auto"))
        res.append({{"table": f"{{name}}:{{n}}:{{rep}}", "sampler": rec["sampler"], "converged": rec["converged"],
                    "cpu_seconds": rec["cpu_seconds"], "sampler_seconds": rec["sampler_seconds"],
                    "m50": rec["posterior"]["m50"]["median"]}})
    print(json.dumps(res))
""")

HONESTY = HONESTY_SETUP + textwrap.dedent("""
    names = ["skew_faint", "skew_bright", "long_tail", "two_populations", "plateau_slow", "width_varies", "logistic"]
    truths = B.truth_setup(names, B._scene(sp))
    res = {{}}
    for rep in range({reps}):
        for name in names:
            rec = B.run_replicate(B.make_task(truths, name, 3000, rep, seed=seed, scene_params=sp, model="auto"))
            res[f"{{name}}:3000:{{rep}}"] = {{"cpu_seconds": rec["cpu_seconds"], "sampler": rec["sampler"],
                                            "m50": rec["posterior"]["m50"]["median"]}}
    print(json.dumps(res))
""")

# honesty tables (bench_honesty seed 12) whose first importance sampler and its retry both fail
NUTS_TABLES = [("logistic", 3000, 19), ("two_populations", 3000, 2), ("two_populations", 3000, 15)]


def _child(code: str, cache: str) -> str:
    env = dict(os.environ, COMEST_BAYES_CACHE=cache)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, cwd=str(ROOT))
    if out.returncode:
        raise RuntimeError(out.stderr[-3000:])
    return out.stdout


def demo(mode: str, work: Path, warm_runs: int) -> dict:
    cache = str(work / f"cache-{mode}")
    res = {}
    for run in ["first_run"] + [f"warm{i + 1}" for i in range(warm_runs)]:
        folder = work / f"demo-{mode}-{run}"
        _child(DEMO.format(root=str(ROOT), mode=mode, out=str(folder)), cache)
        t = json.loads((folder / "run.json").read_text())["timings"]
        res[run] = {"fit_cpu": t["fit_cpu"], "inject_cpu": t["inject_cpu"], "ratio": t["fit_cpu"] / t["inject_cpu"]}
        print(f"demo {mode:8s} {run:9s} fit {t['fit_cpu']:6.2f} CPU-s  injection {t['inject_cpu']:6.2f}  "
              f"ratio {res[run]['ratio']:.3f}", flush=True)
    return res


def program_table(result: dict) -> None:
    """Print the per-program table (best of the repeats) and store the compile totals."""
    print(f"\n{'program':28s} {'compile CPU-s (defaults / options)':>36s} {'evaluation ms (defaults / options)':>36s}"
          f"  {'max rel diff':>12s}")
    tot = {"defaults": 0.0, "options": 0.0}
    for name, rec in result["programs"].items():
        c = {k: min(r["compile_cpu"] for r in v) for k, v in rec.items()}
        e = {k: min(r["eval_ms"] for r in v) for k, v in rec.items()}
        for k in tot:
            tot[k] += c[k]
        diff = max(r["max_rel_diff"] for r in rec["options"])
        print(f"{name:28s} {c['defaults']:17.2f} / {c['options']:<16.2f} {e['defaults']:17.3f} / {e['options']:<16.3f}"
              f"  {diff:12.1e}")
    print(f"{'all (best of each)':28s} {tot['defaults']:17.2f} / {tot['options']:<16.2f}")
    result["programs_total_compile_cpu"] = tot


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=2, help="fresh processes per setting for the program table")
    ap.add_argument("--warm-runs", type=int, default=2, help="demo runs with the cache of the first, per setting")
    ap.add_argument("--nuts", action="store_true", help="also time NUTS with and without the options (about 5 min)")
    ap.add_argument("--skip-demo", action="store_true", help="skip the demo runs and the program table")
    ap.add_argument("--honesty", type=int, default=0, metavar="REPS",
                    help="also fit the first REPS replicates of every honesty truth at 3k per setting")
    ap.add_argument("--out", default=str(HERE / "results" / "compile_options.json"))
    args = ap.parse_args(argv)
    from comest_bayes import jaxnum

    result = {"options": jaxnum.CPU_COMPILER_OPTIONS, "demo": {}, "programs": {}, "nuts": {}}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for mode in ("package", "defaults") if not args.skip_demo else ():
            result["demo"][mode] = demo(mode, work, args.warm_runs)
        folder = str(work / "cache-package" / "exports")
        for rep in range(args.repeats if not args.skip_demo else 0):
            for with_options in (False, True):
                key = "options" if with_options else "defaults"
                out = json.loads(_child(PROGRAMS.format(root=str(ROOT), folder=folder, with_options=with_options),
                                        str(work / "unused")).strip().splitlines()[-1])
                for name, rec in out.items():
                    result["programs"].setdefault(name, {}).setdefault(key, []).append(rec)
        if not args.skip_demo:
            program_table(result)
        if args.honesty:
            # the honesty benchmark's first replicates at 3k, each setting in its own process (after one
            # process that fills its cache), alternating: the fits' CPU with a warm cache
            runs = {"package": [], "defaults": []}
            for rep in range(3):
                for mode in ("package", "defaults"):
                    out = json.loads(_child(HONESTY.format(root=str(ROOT), mode=mode, bench=str(HERE),
                                                           reps=args.honesty), str(work / f"hon-{mode}"))
                                     .strip().splitlines()[-1])
                    runs[mode].append(out)
            result["honesty"] = runs
            for mode, rr in runs.items():
                totals = [sum(r["cpu_seconds"] for r in run.values()) for run in rr]
                print(f"honesty {mode:8s} {len(rr[0])} fits at 3k: CPU-s per pass " + ", ".join(f"{t:.1f}" for t in totals)
                      + " (the first pass fills the cache)")
            same = all(runs["package"][0][k]["m50"] == runs["defaults"][0][k]["m50"] for k in runs["package"][0])
            print(f"honesty: every m50 median identical between the settings: {same}")
        if args.nuts:
            for mode in ("package", "nuts_options"):
                cache = str(work / f"nuts-{mode}")
                runs = [json.loads(_child(NUTS.format(root=str(ROOT), mode=mode, bench=str(HERE), tables=NUTS_TABLES),
                                          cache).strip().splitlines()[-1]) for _ in ("cold", "warm")]
                result["nuts"][mode] = {"cold": runs[0], "warm": runs[1]}
                for r in runs[1]:
                    print(f"nuts {mode:12s} {r['table']:24s} sampler {r['sampler']:10s} warm: {r['sampler_seconds']:6.2f} s "
                          f"(fit {r['cpu_seconds']:6.2f} CPU-s)", flush=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1))
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
