"""Diagnostic (h-width2; run as `python diag.py N REPS MODEL TRUTHS`, e.g. `300000 5 logistic_depth_width_uv width_varies,width_logplane`): is the 300k m50 bias of the order-2 width rung the width form, or compression / image average?
Fit logistic_depth_width_uv (order 2) directly to (a) width_varies (w linear in u) and (b) the same truth with
log w a plane in u (inside the rung's family; same end widths), 300k injections, same draw seeds as bench_honesty."""
import sys, json, math, time
from dataclasses import dataclass
sys.path.insert(0, "/work/wt-width2")
from comest_bayes.pipeline import runtime
runtime.configure(threads=1)
import numpy as np
from comest_bayes.sim import synthetic as S
from comest_bayes.seeding import int_seed_for
from comest_bayes.config import RunConfig
from comest_bayes.bayes.fit import fit_kind
from comest_bayes.ratios import binned as R

@dataclass(frozen=True)
class LogPlaneWidth(S.VaryingWidthTruth):
    name: str = "width_logplane"
    description: str = "width_varies with log w a plane in u (0.1 at u=-1, 0.35 at u=+1)"
    def width(self, u):
        u = np.clip(np.asarray(u, float), -1.0, 1.0)
        return self.w_left * np.exp(math.log(self.w_right / self.w_left) * 0.5 * (u + 1.0))

scene = S.make_scene((512, 512), gradient=0.6, chip_gap=True, seed=int_seed_for(12, "honesty", "scene"))
n = int(sys.argv[1]); reps = int(sys.argv[2]); model = sys.argv[3] if len(sys.argv) > 3 else "logistic_depth_width_uv"
out = {}
TR = {"width_varies": S.get_truth("width_varies"), "width_logplane": LogPlaneWidth(), "logistic": S.get_truth("logistic")}
for truth in [TR[t] for t in sys.argv[4].split(",")]:
    q = S.truth_quantities(truth, scene)
    lo, hi = truth.default_mag_range()
    edges = R.magnitude_edges(lo, hi, 0.1); centers = 0.5 * (edges[:-1] + edges[1:])
    res = []
    for rep in range(reps):
        table = S.draw_outcomes(truth, scene, n, mag_range=(lo, hi),
                                seed=int_seed_for(12, "honesty", "width_varies", n, rep, "draw"))
        c0 = time.process_time()
        post, entry = fit_kind(table, kind="point", quantity="completeness", requested=model,
                               config=RunConfig(seed=int_seed_for(12, "honesty", "width_varies", n, rep, "fit")),
                               image_shape=scene.shape, noise=scene.noise, mask=scene.mask, wcs_header=None,
                               mag_range=(lo, hi), mag_centers=centers)
        lv = {round(float(k), 6): np.asarray(v) for k, v in post.magnitudes_at((0.5, 0.9)).items()}
        row = {"rep": rep, "cpu": time.process_time() - c0,
               "m50": float(np.nanmedian(lv[0.5]) - q["m50"]), "m50_sd": float(np.nanstd(lv[0.5])),
               "m90": float(np.nanmedian(lv[0.9]) - q["m90"]), "m90_sd": float(np.nanstd(lv[0.9])),
               "params": {k: v.get("median") for k, v in entry.to_dict().get("parameters", {}).items()
                          if k.startswith("w") or k.startswith("log_w")}}
        res.append(row)
        print(truth.name, json.dumps(row), flush=True)
    b = np.array([r["m50"] for r in res]); s = np.array([r["m50_sd"] for r in res])
    b9 = np.array([r["m90"] for r in res]); s9 = np.array([r["m90_sd"] for r in res])
    print(f"== {truth.name} {model} n={n}: m50 bias {1e3*b.mean():+.2f} +- {1e3*b.std(ddof=1)/math.sqrt(len(b)):.2f} mmag "
          f"(sd {1e3*s.mean():.2f}, |b|/sd {abs(b.mean())/s.mean():.2f}); m90 bias {1e3*b9.mean():+.2f} +- "
          f"{1e3*b9.std(ddof=1)/math.sqrt(len(b9)):.2f} (sd {1e3*s9.mean():.2f})", flush=True)
    out[truth.name] = res
json.dump(out, open(f"/tmp/width2/diag/diag_{n}_{model}_{sys.argv[4]}.json", "w"), indent=1)
