"""How much the binned method's m50 error depends on where its bin grid falls (rescoring).

The published binned method fixes 0.1-mag bins and reads m50 by linear interpolation between
the two bin centres around the 0.5 crossing.  When the transition is narrower than a bin, the
error of that interpolation depends on the grid's *phase*: where the nearest bin edge falls
relative to the true m50.  A user does not know m50 when choosing a grid, so the phase is
effectively random; ``bench_speed_accuracy.py`` scores one fixed grid (edges at the injected
range's bright end plus multiples of 0.1).

This script takes a pool and a per-replicate trace written by ``bench_speed_accuracy.py``,
rebuilds exactly the replicates' subsets (``replicate_subsets``; the benchmark's own grid must
reproduce the trace's binned m50 to 1e-9 mag, or the script stops), recomputes the binned m50 on
grids shifted by ``k * 0.1 / phases`` mag, and scores them and the trace's ``auto`` m50 against
the held-out pool's reference (``bench_speed_accuracy.pool_reference``: its local-likelihood m50,
which replaced the 0.05-mag binned m50 on 2026-11-28; ``bench_reference_m50.py``).  No model is
refitted.  Because the reference's own error is common to every replicate and method, the
efficiencies are also printed with the reference moved by -1 and +1 of its sd.

Printed per budget: the RMSE of the model and of the binned m50 at every phase, the efficiency
(RMSE_binned / RMSE_auto)^2 at the benchmark's phase and averaged over phases (mean squared
error over phases), its range over phases, and a bootstrap 68% interval of the phase-averaged
efficiency over replicates (the replicate noise of the figure).

    python benchmarks/bench_binned_phase.py --run WORK/analytic_run \\
        --trace benchmarks/results/speed_accuracy_traces/analytic_2026-11-28_final_code.jsonl.gz \\
        --out benchmarks/results/binned_phase_analytic.json
"""
from __future__ import annotations

import argparse
import gzip
import json
import sys
from pathlib import Path

import numpy as np
from astropy.table import Table

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_speed_accuracy import (BIN_PHASES, BIN_WIDTH, REF_BIN_WIDTH, binned_m50_at_phase,  # noqa: E402
                                  phase_edges, pool_reference, replicate_subsets)

from comest_bayes.ratios import binned as R  # noqa: E402


def read_trace(path: Path) -> list[dict]:
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "rt") as f:
        return [json.loads(line) for line in f if line.strip()]


def noise_free_bias(m50: float, scale: float, mag_range, phases) -> list[float]:
    """The binned m50's error on a logistic ``1 / (1 + exp((m - m50) / scale))`` without noise.

    Every bin's ratio is the curve's exact average over the bin (closed form through the
    softplus), as infinitely many uniform injections would give; m50 is then interpolated as
    ``ratios.binned.magnitude_at`` does (``first_crossing``).  What is left is the interpolation's
    bias alone.
    """
    out = []
    for phase in phases:
        edges = phase_edges(mag_range, phase)
        a, b = edges[:-1], edges[1:]
        # integral of the curve over [a, b] = scale * (softplus((m50 - a) / scale) - softplus((m50 - b) / scale))
        ratio = scale * (np.logaddexp(0, (m50 - a) / scale) - np.logaddexp(0, (m50 - b) / scale)) / (b - a)
        out.append(float(R.first_crossing(0.5 * (a + b), ratio, 0.5)) - m50)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--run", required=True, help="the pool's run directory (bench_speed_accuracy's <work>/<scene>_run)")
    p.add_argument("--trace", required=True, help="bench_speed_accuracy's per-replicate trace (.jsonl or .jsonl.gz)")
    p.add_argument("--seed", type=int, default=11, help="the benchmark's --seed (draws the subsets)")
    p.add_argument("--phases", type=int, default=BIN_PHASES, help="grid phases, evenly spaced over one bin")
    p.add_argument("--bootstrap", type=int, default=2000)
    p.add_argument("--logistic-scale", type=float, default=0.045,
                   help="also print the interpolation bias alone, on a noise-free logistic of this scale (mag) "
                        "centred on the reference m50 (0.045: the narrow scene's fitted width; 0 to skip)")
    p.add_argument("--out", default=None, help="JSON file for the figures")
    a = p.parse_args(argv)

    run = Path(a.run)
    out = Table.read(run / "catalogs" / "point_outcomes.fits")
    mag_range = tuple(json.loads((run / "run.json").read_text())["stages"]["baseline"]["mag_range"])
    mag = np.asarray(out["mag"], float)
    det = np.asarray(out["detected"], bool)
    held = np.asarray(out["realization"]) % 3 == 0
    ref_info = pool_reference(mag[held], det[held], mag_range)
    ref, ref_sd = ref_info["m50"], ref_info["m50_sd"]
    # the reference's own dependence on its grid's phase (0.05-mag bins, 1/3 of the pool)
    ref_spread = [binned_m50_at_phase(mag[held], det[held], mag_range, k * REF_BIN_WIDTH / 5, REF_BIN_WIDTH)
                  for k in range(5)]
    phases = [k * BIN_WIDTH / a.phases for k in range(a.phases)]
    trace = read_trace(Path(a.trace))
    budgets = sorted({t["budget"] for t in trace})
    rng = np.random.default_rng(a.seed)
    print(f"pool {len(mag)} injections, {int(held.sum())} held out; reference m50 {ref:.5f} +- {ref_sd:.5f} "
          f"(local likelihood); the held-out pool's binned m50 is {ref_info['m50_binned']:.5f}, and its grid's "
          f"phase moves it over {1e3 * (max(ref_spread) - min(ref_spread)):.1f} mmag")
    print(f"phases (mag): {', '.join(f'{v:.3f}' for v in phases)}")
    bias0 = []
    if a.logistic_scale > 0:
        bias0 = noise_free_bias(ref, a.logistic_scale, mag_range, phases)
        print(f"noise-free logistic of scale {a.logistic_scale} mag: binned m50 - m50 per phase (mmag): "
              + " ".join(f"{1e3 * v:+.2f}" for v in bias0))
    print("budget reps | auto RMSE | binned RMSE per phase (mmag) | eff at phase 0 | phase-averaged "
          "[bootstrap 68%] | min-max over phases | eff at phase 0 / averaged with the reference moved by "
          "-1 sd, +1 sd")
    report = {"run": str(run), "trace": str(a.trace), "reference_m50": ref, "reference_m50_sd": ref_sd,
              "reference_m50_binned": ref_info["m50_binned"], "reference_source": ref_info["source"],
              "reference_phase_m50s": ref_spread,
              "phases": phases, "bin_width": BIN_WIDTH, "logistic_scale": a.logistic_scale,
              "noise_free_logistic_bias_per_phase": bias0, "budgets": {}}
    for budget in budgets:
        rows = sorted((t for t in trace if t["budget"] == budget), key=lambda t: t["replicate"])
        subsets = replicate_subsets(len(mag), held, seed=a.seed, budget=budget, max_replicates=len(rows))
        if len(subsets) != len(rows):
            raise SystemExit(f"budget {budget}: the trace has {len(rows)} replicates, the pool gives "
                             f"{len(subsets)}; wrong --run or --seed?")
        err_b = np.empty((len(rows), len(phases)))
        for r, (t, sub) in enumerate(zip(rows, subsets)):
            for k, ph in enumerate(phases):
                err_b[r, k] = binned_m50_at_phase(mag[sub], det[sub], mag_range, ph) - ref
            if abs(err_b[r, 0] + ref - t["binned_m50"]) > 1e-9:
                raise SystemExit(f"budget {budget} replicate {t['replicate']}: binned m50 {err_b[r, 0] + ref:.6f} "
                                 f"differs from the trace's {t['binned_m50']:.6f}; not the benchmark's subsets")
        err_a = np.array([t["auto_m50"] for t in rows]) - ref
        ok = np.isfinite(err_a) & np.all(np.isfinite(err_b), axis=1)
        err_a, err_b = err_a[ok], err_b[ok]
        mse_a = np.mean(err_a ** 2)
        mse_b = np.mean(err_b ** 2, axis=0)
        eff = mse_b / mse_a
        eff_avg = float(np.mean(mse_b) / mse_a)
        boot = []
        for _ in range(a.bootstrap):
            i = rng.integers(0, len(err_a), len(err_a))
            boot.append(np.mean(err_b[i] ** 2) / np.mean(err_a[i] ** 2))
        lo68, hi68 = np.percentile(boot, [15.87, 84.13])
        # the reference's own error is common to every replicate and method: move it by its sd
        shifted = {}
        for tag, dr in (("minus_1sd", -ref_sd), ("plus_1sd", ref_sd)):
            ma, mb = np.mean((err_a - dr) ** 2), np.mean((err_b - dr) ** 2, axis=0)
            shifted[tag] = [float(mb[0] / ma), float(np.mean(mb) / ma)]
        print(f"{budget:>7d} {len(err_a):>3d} | {1e3 * np.sqrt(mse_a):5.2f} | "
              + " ".join(f"{1e3 * np.sqrt(v):5.2f}" for v in mse_b)
              + f" | {eff[0]:5.2f} | {eff_avg:5.2f} [{lo68:.2f}, {hi68:.2f}] | {eff.min():.2f}-{eff.max():.2f}"
              + f" | {shifted['minus_1sd'][0]:.2f} / {shifted['minus_1sd'][1]:.2f}, "
                f"{shifted['plus_1sd'][0]:.2f} / {shifted['plus_1sd'][1]:.2f}")
        report["budgets"][str(budget)] = {
            "replicates": int(len(err_a)), "auto_rmse": float(np.sqrt(mse_a)),
            "binned_rmse_per_phase": [float(np.sqrt(v)) for v in mse_b],
            "efficiency_per_phase": [float(v) for v in eff], "efficiency_phase_averaged": eff_avg,
            "efficiency_phase_averaged_bootstrap68": [float(lo68), float(hi68)],
            "efficiency_phase0_and_averaged_reference_shifted": shifted}
    if a.out:
        Path(a.out).write_text(json.dumps(report, indent=1))
        print(f"written {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
