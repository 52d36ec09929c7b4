"""Checks 1 and 2 (no fit): the truth's image-average m50 by brute force against truth_quantities, and the
rung's image-average m50 at the TRUE parameters through the fit's footprint cells against every pixel."""
import time
from common import *

for name in ("width_logplane", "logistic", "width_varies"):
    truth = TRUTHS[name]
    q = S.truth_quantities(truth, SCENE)
    iy, ix = np.nonzero(~SCENE.mask)
    d = SCENE.depth[iy, ix]; u, v = SCENE.uv(ix, iy)
    brute = brentq(lambda m: truth.prob(np.full(d.size, m), d, u, v).mean() - 0.5, 22, 26, xtol=1e-10)
    print(f"{name}: truth_quantities m50 {q['m50']:.6f}  brute {brute:.6f}  diff {1e3*(q['m50']-brute):+.4f} mmag")
    if name == "width_varies":
        continue
    tab = table(truth, 300000, 0)
    cov, det, meta = covariates_from_outcomes(tab, image_shape=SCENE.shape)
    data = compress_for(MODEL, cov, det, meta=meta)
    model = CompletenessModel(MODEL, data)
    th = true_theta(model, truth, meta["sigma_ref"])
    print("  sigma_ref fit/scene", meta["sigma_ref"] / SCENE.sigma_ref, dict(zip(model.names, np.round(th, 5))))
    pc = pixel_cells(meta["sigma_ref"])
    fc = cells_of(meta["sigma_ref"])
    mp = crossing(model, th, pc); mf = crossing(model, th, fc)
    print(f"  model at true theta: per-pixel m50 {mp:.6f} (vs truth {1e3*(mp-q['m50']):+.4f} mmag); "
          f"fit cells ({len(fc)}) {mf:.6f} (vs per-pixel {1e3*(mf-mp):+.4f} mmag)")
    # and the package's own crossing routine (xtol as magnitudes_at uses it)
    from comest_bayes.bayes.posterior import average_crossings
    for xt in (1e-3, 1e-6):
        c = average_crossings(model, th[None, :], fc, (0.5,), 20.0, 27.0, xtol=xt)[0.5][0]
        print(f"  average_crossings xtol {xt}: {c:.6f} (vs brentq on the same cells {1e3*(c-mf):+.4f} mmag)")
