"""Benchmark: does NUTS give emcee's intervals where importance sampling fails?

A fit samples its chosen model by importance sampling from the Laplace approximation and, where
the Pareto k-hat says that fails, by NUTS (``comest_bayes.bayes.nuts``).  About 3% of the honesty
benchmark's small fits fail importance sampling: their spline posteriors have a curved ridge.
Until 2026-11-29 these fell back to emcee, which stopped at 5000 steps short of its convergence
rule.  This script refits such outcome tables (those of ``bench_honesty.py``, drawn from the same
seeds) with

* ``auto``: the package default (importance sampling, then NUTS);
* ``emcee``: emcee alone, to ESS ``--ref-ess`` within ``--ref-steps`` steps per walker (the
  reference; the sampler the package used before NUTS, now run long enough to converge);
* ``fallback``: emcee as the fallback ran it before NUTS (ESS 400, at most 5000 steps);

and compares the posterior of the image-average m50, m90 and f at m50 -/+ 0.3 mag: the
difference of the medians and of the 68% and 95% interval ends in units of the reference's
posterior sd, and each fit's CPU time.  Both fits of a table make the same model selection (the
sampler runs only on the chosen model), so the differences are the samplers' alone.

Usage::

    python benchmarks/bench_samplers.py --out benchmarks/results/samplers     # the default tables
    python benchmarks/bench_samplers.py --tables two_populations:3000:2 long_tail:3000:13 --out DIR

Results go to ``<out>/raw.json`` as they arrive (a rerun skips the fits already there) and the
table to ``<out>/summary.txt``.  One process, one thread: about 5 minutes per table, most of it the
emcee reference (an hour for the 11 default tables).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

#: Tables whose importance sampling failed in the honesty benchmark of 2026-11-29 (main 79891da),
#: as truth:N:replicate; their emcee fallbacks all stopped at 5000 steps unconverged.
DEFAULT_TABLES = ("two_populations:3000:2", "two_populations:3000:12", "two_populations:3000:15",
                  "two_populations:3000:21", "long_tail:3000:13", "long_tail:3000:25", "long_tail:3000:30",
                  "skew_faint:3000:21", "two_populations:30000:0", "skew_bright:30000:2", "long_tail:30000:3")

QUANTITIES = ("m50", "m90", "f_bright", "f_faint")
ENDS = ("median", "lo68", "hi68", "lo95", "hi95")


def _sd_units(rec: dict, ref: dict, q: str) -> dict:
    """Differences of the interval ends of ``rec`` from ``ref`` for quantity ``q``, in units of ``ref``'s sd."""
    a, b = rec["posterior"][q], ref["posterior"][q]
    sd = b.get("sd")
    if not sd or "median" not in a or "median" not in b:
        return {}
    return {e: (a[e] - b[e]) / sd for e in ENDS}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tables", nargs="+", default=list(DEFAULT_TABLES), help="truth:N:replicate of bench_honesty")
    p.add_argument("--seed", type=int, default=12, help="bench_honesty's root seed")
    p.add_argument("--ref-ess", type=float, default=2000.0, help="ESS of the emcee reference (default 2000)")
    p.add_argument("--ref-steps", type=int, default=60000, help="most emcee steps of the reference")
    p.add_argument("--no-fallback", action="store_true", help="skip the 5000-step emcee fallback of old")
    p.add_argument("--out", default=str(HERE / "results" / "samplers"))
    a = p.parse_args(argv)

    from comest_bayes.pipeline import runtime

    runtime.configure(threads=1)  # one XLA/BLAS thread and the compilation cache, before jax is first imported
    import bench_honesty as B
    from comest_bayes.seeding import int_seed_for
    from comest_bayes.sim import synthetic as S

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    raw_path = out / "raw.json"
    settings = {"seed": a.seed, "ref_ess": a.ref_ess, "ref_steps": a.ref_steps}
    raw = {"settings": settings, "records": {}}
    if raw_path.exists():
        raw = json.loads(raw_path.read_text())
        if raw.get("settings") != settings:
            raise SystemExit(f"{raw_path} was written with other settings; use another --out")
    scene_params = {**B.SCENE, "seed": int_seed_for(a.seed, "honesty", "scene")}
    scene = S.make_scene(tuple(B.SCENE["shape"]), gradient=B.SCENE["gradient"], chip_gap=B.SCENE["chip_gap"],
                         seed=scene_params["seed"])
    runs = {"auto": {}, "emcee": {"sampler": "emcee", "min_ess": a.ref_ess, "max_steps": a.ref_steps}}
    if not a.no_fallback:
        runs["fallback"] = {"sampler": "emcee", "min_ess": 400.0, "max_steps": 5000}
    for spec in a.tables:
        name, n, rep = spec.split(":")
        truths = B.truth_setup([name], scene)
        for label, kw in runs.items():
            key = f"{spec}|{label}"
            if key in raw["records"]:
                continue
            task = B.make_task(truths, name, int(n), int(rep), seed=a.seed, scene_params=scene_params, model="auto",
                               **kw)
            t0 = time.perf_counter()
            rec = B.run_replicate(task)
            raw["records"][key] = rec
            tmp = raw_path.with_name(raw_path.name + ".tmp")
            tmp.write_text(json.dumps(raw, indent=1))
            tmp.replace(raw_path)
            print(f"{key}: {rec['model']}, sampler {rec.get('sampler')}, converged {rec['converged']}, "
                  f"{rec['cpu_seconds']:.1f} CPU-s ({time.perf_counter() - t0:.0f} s)", flush=True)

    lines = [f"$ python benchmarks/bench_samplers.py {' '.join(sys.argv[1:])}", "",
             "differences from the emcee reference in units of its posterior sd (median; worst 68% and 95% end)",
             f"{'table':<26s} {'run':<9s} {'model':<14s} {'sampler':<10s} {'conv':<5s} {'CPU-s':>6s}  " +
             "  ".join(f"{q:>17s}" for q in QUANTITIES)]
    worst = {"auto": 0.0, "fallback": 0.0}
    for spec in a.tables:
        ref = raw["records"].get(f"{spec}|emcee")
        for label in runs:
            rec = raw["records"].get(f"{spec}|{label}")
            if rec is None or ref is None:
                continue
            cells = []
            for q in QUANTITIES:
                d = _sd_units(rec, ref, q)
                if not d:
                    cells.append(f"{'n/a':>17s}")
                    continue
                w68 = max(abs(d["lo68"]), abs(d["hi68"]))
                w95 = max(abs(d["lo95"]), abs(d["hi95"]))
                if label in worst:
                    worst[label] = max(worst[label], abs(d["median"]), w68, w95)
                cells.append(f"{d['median']:+5.2f} {w68:5.2f} {w95:5.2f}")
            lines.append(f"{spec:<26s} {label:<9s} {rec['model']:<14s} {str(rec.get('sampler')):<10s} "
                         f"{str(rec['converged']):<5s} {rec['cpu_seconds']:6.1f}  " + "  ".join(cells))
    cpu = {label: [raw["records"][f"{s}|{label}"]["cpu_seconds"] for s in a.tables
                   if f"{s}|{label}" in raw["records"]] for label in runs}
    lines.append("")
    lines.append("CPU-s per fit (mean, max): " + "; ".join(
        f"{label} {sum(v) / len(v):.1f}, {max(v):.1f}" for label, v in cpu.items() if v))
    lines.append("largest |difference| from the reference over every quantity and interval end (sd): " +
                 "; ".join(f"{k} {v:.2f}" for k, v in worst.items() if math.isfinite(v)))
    text = "\n".join(lines)
    (out / "summary.txt").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
