"""Checks 3 and 4 on the same tables: MAP m50 from the compressed cells against the unbinned (one cell per
injection) likelihood, and the posterior median (importance sampling, as fit_kind) against the MAP.
argv: truth rep0 reps [n]"""
import json, time, warnings
from common import *
from comest_bayes.bayes.inference import fit_map, fit
from comest_bayes.bayes.posterior import average_crossings
warnings.simplefilter("ignore")
name = sys.argv[1]; r0 = int(sys.argv[2]); reps = int(sys.argv[3]); n = int(sys.argv[4]) if len(sys.argv) > 4 else 300000
truth = TRUTHS[name]
q = S.truth_quantities(truth, SCENE)
for rep in range(r0, r0 + reps):
    tab = table(truth, n, rep)
    cov, det, meta = covariates_from_outcomes(tab, image_shape=SCENE.shape)
    fc = cells_of(meta["sigma_ref"])
    row = {"truth": name, "rep": rep}
    c0 = time.process_time()
    data = compress_for(MODEL, cov, det, meta=meta)
    model = CompletenessModel(MODEL, data)
    seed = int_seed_for(12, "honesty", "width_varies", n, rep, "fit")
    res = fit(model, seed=seed, sampler="importance", min_ess=400)
    th_c = res.map.theta
    row["ncells"] = int(data.ncells)
    row["map_c"] = 1e3 * (crossing(model, th_c, fc) - q["m50"])
    draws = res.draws()
    m = average_crossings(model, draws, fc, (0.5,), 20.0, 27.0, xtol=1e-6)[0.5]
    row["post_med_c"] = 1e3 * (float(np.nanmedian(m)) - q["m50"]); row["post_mean_c"] = 1e3 * (float(np.nanmean(m)) - q["m50"])
    row["post_sd"] = 1e3 * float(np.nanstd(m))
    row["cpu_c"] = time.process_time() - c0
    c0 = time.process_time()
    data_u = uncompressed(cov, det, meta=meta)
    model_u = CompletenessModel(MODEL, data_u)
    mp_u = fit_map(model_u, nstarts=1, seed=seed, method="newton", start=th_c)
    row["map_u"] = 1e3 * (crossing(model_u, mp_u.theta, fc) - q["m50"])
    row["cpu_u"] = time.process_time() - c0
    row["theta_c"] = dict(zip(model.names, np.round(th_c, 5).tolist()))
    row["theta_u"] = dict(zip(model.names, np.round(mp_u.theta, 5).tolist()))
    if name in ("width_logplane", "logistic"):
        tt = true_theta(model, truth, meta["sigma_ref"])
        row["lp_true_minus_map_c"] = float(model.log_prob(tt) - model.log_prob(th_c))
        row["lp_true_minus_map_u"] = float(model_u.log_prob(tt) - model_u.log_prob(mp_u.theta))
    print(json.dumps(row), flush=True)
