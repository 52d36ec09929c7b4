"""Sampling spread of the compressed MAP's image-average m50 over many tables (MAP only, cheap), against the
posterior sd (~1.9 mmag at 300k).  Same draw seeds as bench_honesty / diag_300k (tag width_varies: the
replicate r of every truth uses the same random numbers).
argv: truth rep0 reps n [models, comma-separated; default logistic_depth_width_uv] [seed tag]
Writes exp3_<truth>_<n>_<rep0>_<reps>_<models>.json."""
import json, time, warnings
from common import *
from comest_bayes.bayes.inference import fit_map
warnings.simplefilter("ignore")
name = sys.argv[1]; r0 = int(sys.argv[2]); reps = int(sys.argv[3]); n = int(sys.argv[4])
models = sys.argv[5].split(",") if len(sys.argv) > 5 else [MODEL]
tag = sys.argv[6] if len(sys.argv) > 6 else "width_varies"
truth = TRUTHS[name]
q = S.truth_quantities(truth, SCENE)
rows = []
for rep in range(r0, r0 + reps):
    lo, hi = truth.default_mag_range()
    tab = S.draw_outcomes(truth, SCENE, n, mag_range=(lo, hi), seed=int_seed_for(12, "honesty", tag, n, rep, "draw"))
    cov, det, meta = covariates_from_outcomes(tab, image_shape=SCENE.shape)
    fc = cells_of(meta["sigma_ref"])
    row = {"rep": rep}
    for mname in models:
        c0 = time.process_time()
        model = CompletenessModel(mname, compress_for(mname, cov, det, meta=meta))
        mp = fit_map(model, nstarts=2, seed=int_seed_for(12, "honesty", tag, n, rep, "fit"))
        row[mname] = {"m50_err": 1e3 * (crossing(model, mp.theta, fc) - q["m50"]), "cpu": time.process_time() - c0,
                      "theta": dict(zip(model.names, np.round(mp.theta, 5).tolist()))}
    rows.append(row)
    print(json.dumps(row), flush=True)
json.dump(rows, open(f"exp3_{name}_{n}_{r0}_{reps}_{'+'.join(models)}.json", "w"), indent=1)
for mname in models:
    e = np.array([r[mname]["m50_err"] for r in rows])
    print(f"== {name} {mname} n={n} reps {r0}-{r0 + reps - 1}: mean {e.mean():+.3f} +- {e.std(ddof=1)/np.sqrt(e.size):.3f} "
          f"mmag, spread (sd) {e.std(ddof=1):.3f}; first 8: {e[:8].mean():+.3f}")
if len(models) == 2:
    dd = np.array([r[models[1]]["m50_err"] - r[models[0]]["m50_err"] for r in rows])
    print(f"== paired {models[1]} - {models[0]}: {dd.mean():+.3f} +- {dd.std(ddof=1)/np.sqrt(dd.size):.3f} mmag")
