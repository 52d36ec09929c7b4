"""Benchmark: level and power of the positional-width score test (``selection.width_position_test``).

``auto`` escalates a selection to its positional-width rungs (``width_order = 2``: log w a quadratic
Legendre field in the image coordinates) when the score test of the rung it chose fires.  The test
computes two alternatives from one Jacobian: a plane in log w (2 dof) and the rungs' quadratic field
(5 dof).  This script measures, on outcome tables drawn from known truths
(:mod:`comest_bayes.sim.synthetic`), how often each decision rule fires at ``WIDTH_TEST_P``:

* ``plane``: the plane alone (the test before the quadratic was added);
* ``quad5``: the quadratic field alone (5 dof);
* ``bonf``: ``min(1, 2 min(p_plane, p_quad5))`` (the rule the package uses);
* ``bonf_curv``: the plane and the curvature given the plane (``S_5 - S_2``, 3 dof), Bonferroni.

Truths: flat widths (``logistic``, ``skew_faint``: the false-escalation rate, nominal 1e-3) and
widths that vary (``width_logplane``: log w a plane in u; ``width_varies``: w linear in u;
``width_radial``: log w quadratic in the distance from the centre, no plane component).  Each table is
fitted by the MAP of the rung the test would run on (``logistic_depth``; with ``--spline`` also
``spline_depth`` with its smoothness chosen by the evidence, as the selection does) on the cells
``auto`` compresses to (no position), and tested.  One process, seeded by (root seed, truth, N,
replicate) only.

Usage::

    python benchmarks/bench_width_test.py --out benchmarks/results/width_test_quadratic
    #   --null-sizes 1000 5000 --null-reps 40 --power-sizes 1000 3000 10000 --power-reps 20 --spline

Writes ``<out>/raw.json`` (every table's statistics) and ``<out>/summary.txt``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

SCENE = {"shape": [512, 512], "gradient": 0.6, "chip_gap": True}
NULL_TRUTHS = ("logistic", "skew_faint")
POWER_TRUTHS = ("width_logplane", "width_varies", "width_radial")
RULES = ("plane", "quad5", "bonf", "bonf_curv")


def _truth(name):
    from comest_bayes.sim import synthetic as S

    extra = {"width_logplane": S.LogPlaneWidthTruth(), "width_radial": S.RadialWidthTruth()}
    return extra[name] if name in extra else S.get_truth(name)


def run_table(truth_name, n, rep, scene, root_seed, rungs) -> dict:
    import numpy as np

    from comest_bayes.bayes.inference import fit_map
    from comest_bayes.bayes.model import CompletenessModel
    from comest_bayes.bayes.outcomes import compress_for, covariates_from_outcomes
    from comest_bayes.bayes.selection import choose_tau, width_position_test
    from comest_bayes.seeding import int_seed_for
    from comest_bayes.sim import synthetic as S

    table = S.draw_outcomes(_truth(truth_name), scene, n, seed=int_seed_for(root_seed, "width_test", truth_name,
                                                                             n, rep, "draw"))
    cov, det, meta = covariates_from_outcomes(table, image_shape=scene.shape)
    data = compress_for("auto", cov, det, meta=meta)
    fit_seed = int_seed_for(root_seed, "width_test", truth_name, n, rep, "fit")
    out = {"truth": truth_name, "n": int(n), "rep": int(rep), "ncells": int(data.ncells)}
    for rung in rungs:
        t0 = time.process_time()
        model = CompletenessModel(rung, data)
        if model.spec.link == "spline":
            _, mp = choose_tau(model, seed=fit_seed)[:2]
        else:
            mp = fit_map(model, nstarts=2, seed=fit_seed)
        t1 = time.process_time()
        test = width_position_test(model, mp.theta, cov.u, cov.v, det)
        out[rung] = {"plane": test.plane.to_dict(), "quadratic": test.quadratic.to_dict(),
                     "p_value": test.p_value, "alternative": test.alternative,
                     "cpu_fit": t1 - t0, "cpu_test": time.process_time() - t1}
    return out


def rule_p(rec: dict) -> dict:
    """The p-value of every rule from one table's two tests."""
    from scipy.special import chdtrc

    pl, qu = rec["plane"], rec["quadratic"]
    dof_c = qu["dof"] - pl["dof"]
    p_curv = float(chdtrc(dof_c, max(qu["statistic"] - pl["statistic"], 0.0))) if dof_c > 0 else 1.0
    return {"plane": pl["p_value"], "quad5": qu["p_value"], "bonf": min(1.0, 2 * min(pl["p_value"], qu["p_value"])),
            "bonf_curv": min(1.0, 2 * min(pl["p_value"], p_curv))}


def summarise(raw: list, rungs, threshold: float) -> str:
    import numpy as np

    lines = [f"fraction of tables with p < {threshold:g} (escalations), per rule; median log10 p in brackets",
             f"rules: {', '.join(RULES)}", ""]
    keys = sorted({(r["truth"], r["n"]) for r in raw}, key=lambda k: (k[0] not in NULL_TRUTHS, k[0], k[1]))
    for rung in rungs:
        lines.append(f"rung {rung}")
        lines.append(f"  {'truth':16s} {'N':>6s} {'reps':>4s} " + " ".join(f"{r:>22s}" for r in RULES)
                     + "   min p (bonf)   cpu fit/test s")
        for truth, n in keys:
            recs = [r[rung] for r in raw if r["truth"] == truth and r["n"] == n and rung in r]
            if not recs:
                continue
            ps = [rule_p(rec) for rec in recs]
            cells = []
            for rule in RULES:
                p = np.array([x[rule] for x in ps])
                cells.append(f"{np.sum(p < threshold):3d}/{p.size:<3d} [{np.median(np.log10(np.maximum(p, 1e-300))):7.2f}]")
            pb = min(x["bonf"] for x in ps)
            cpu = (np.mean([r["cpu_fit"] for r in recs]), np.mean([r["cpu_test"] for r in recs]))
            lines.append(f"  {truth:16s} {n:6d} {len(recs):4d} " + " ".join(f"{c:>22s}" for c in cells)
                         + f"   {pb:10.2g}   {cpu[0]:.2f}/{cpu[1]:.3f}")
        lines.append("")
    return "\n".join(lines)


def asymptotic_power(threshold: float, ncps=(10, 15, 20, 30), draws: int = 200_000, seed: int = 0) -> str:
    """Power of every rule from the asymptotic distributions: the plane statistic ``chi2_2(l_p)`` and the
    curvature given the plane ``chi2_3(l_c)``, independent, ``S_5`` their sum; a tilt (``l_c = 0``), a pure
    curvature (``l_p = 0``) and a width degraded towards one side or corner (half of each)."""
    import numpy as np
    from scipy.stats import chi2, ncx2

    from comest_bayes.seeding import rng_for

    rng = rng_for(seed, "width_test", "asymptotic")
    lines = [f"asymptotic power at p < {threshold:g} ({draws} draws per cell; l = total noncentrality)",
             f"  {'l':>4s} {'signal':8s} " + " ".join(f"{r:>10s}" for r in RULES)]
    for lam in ncps:
        for label, frac in (("tilt", 1.0), ("curve", 0.0), ("mixed", 0.5)):
            sp = ncx2.rvs(2, lam * frac, size=draws, random_state=rng) if frac > 0 else chi2.rvs(2, size=draws, random_state=rng)
            sc = (ncx2.rvs(3, lam * (1 - frac), size=draws, random_state=rng) if frac < 1
                  else chi2.rvs(3, size=draws, random_state=rng))
            pp, p5, pc = chi2.sf(sp, 2), chi2.sf(sp + sc, 5), chi2.sf(sc, 3)
            ps = {"plane": pp, "quad5": p5, "bonf": np.minimum(1, 2 * np.minimum(pp, p5)),
                  "bonf_curv": np.minimum(1, 2 * np.minimum(pp, pc))}
            lines.append(f"  {lam:4g} {label:8s} " + " ".join(f"{np.mean(ps[r] < threshold):10.2f}" for r in RULES))
    return "\n".join(lines) + "\n"


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--seed", type=int, default=12)
    p.add_argument("--null-sizes", type=int, nargs="*", default=[1000, 5000])
    p.add_argument("--null-reps", type=int, default=40)
    p.add_argument("--power-sizes", type=int, nargs="*", default=[1000, 3000, 10000])
    p.add_argument("--power-reps", type=int, default=20)
    p.add_argument("--null-truths", nargs="*", default=list(NULL_TRUTHS))
    p.add_argument("--power-truths", nargs="*", default=list(POWER_TRUTHS))
    p.add_argument("--spline", action="store_true", help="also test on spline_depth (tau by the evidence)")
    p.add_argument("--summarise-only", action="store_true")
    a = p.parse_args(argv)

    from comest_bayes.pipeline import runtime

    runtime.configure(threads=1)
    from comest_bayes.bayes.selection import WIDTH_TEST_P
    from comest_bayes.seeding import int_seed_for
    from comest_bayes.sim.synthetic import make_scene

    rungs = ["logistic_depth"] + (["spline_depth"] if a.spline else [])
    a.out.mkdir(parents=True, exist_ok=True)
    raw_path = a.out / "raw.json"
    raw = json.loads(raw_path.read_text()) if raw_path.exists() else []
    if not a.summarise_only:
        scene = make_scene(tuple(SCENE["shape"]), gradient=SCENE["gradient"], chip_gap=SCENE["chip_gap"],
                           seed=int_seed_for(a.seed, "width_test", "scene"))
        done = {(r["truth"], r["n"], r["rep"]) for r in raw if all(g in r for g in rungs)}
        tasks = [(t, n, k) for t in a.null_truths for n in a.null_sizes for k in range(a.null_reps)]
        tasks += [(t, n, k) for t in a.power_truths for n in a.power_sizes for k in range(a.power_reps)]
        t0 = time.process_time()
        for i, (t, n, k) in enumerate(tasks):
            if (t, n, k) in done:
                continue
            rec = run_table(t, n, k, scene, a.seed, rungs)
            raw = [r for r in raw if (r["truth"], r["n"], r["rep"]) != (t, n, k)] + [rec]
            if i % 10 == 9 or i == len(tasks) - 1:
                raw_path.write_text(json.dumps(raw))
                print(f"{i + 1}/{len(tasks)} tables, {time.process_time() - t0:.0f} CPU-s", flush=True)
        raw_path.write_text(json.dumps(raw))
    text = summarise(raw, rungs, WIDTH_TEST_P) + "\n" + asymptotic_power(WIDTH_TEST_P)
    text += f"\nload average {'at this summary' if a.summarise_only else 'after the run'}: {os.getloadavg()}\n"
    (a.out / "summary.txt").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
