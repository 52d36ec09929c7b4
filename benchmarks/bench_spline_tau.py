"""Benchmark: how the spline rung's smoothness scale tau trades bias against variance.

The spline rung (``models/spline_depth.toml``) shrinks its knot log-rates towards the logistic
with a random-walk prior of scale tau, chosen per fit by the Laplace evidence over
``selection.TAU_GRID``.  This script fits ``spline_depth`` at every tau of a grid to the same
outcome tables and scores each choice of tau (every fixed tau, the evidence's choice, the
evidence-weighted mixture over the grid, the choice of the Laplace leave-one-out score, and two
rules focused on the targeted quantities) against a known truth, on each fit's Laplace draws
(``--draws laplace``, the default) or on those draws importance-resampled (``--draws resampled``, as
the tables of 2026-11-25 were made; their k-hat and effective sample size are printed per tau):

* ``--scene honesty``: a truth of ``comest_bayes.sim.synthetic`` on the honesty benchmark's scene,
  with the honesty benchmark's own seeds (so replicates pair with ``bench_honesty.py``); scores the
  image-average m50, m90 and f at m50 -+ 0.3 mag (bias in units of the posterior sd, 68%
  coverage, RMSE);
* ``--scene analytic``: subsets of the analytic white-noise injection pool written by
  ``bench_speed_accuracy.py --work DIR`` (``DIR/analytic_run``), scoring m50 against the held-out
  pool's m50 (25.3958 for the pool of the 2026-11 runs; pass ``--ref``);
* ``--scene narrow``: a stand-in for that pool with an exact answer and no pool to build: outcomes
  drawn from a logistic of the pool's width (``--width``, 0.045 mag) over the pool's range.

Example::

    python benchmarks/bench_spline_tau.py --scene honesty --truth two_populations --n 3000 --reps 24
    python benchmarks/bench_spline_tau.py --scene analytic --work /tmp/sa4/work --n 10000 --reps 10
    python benchmarks/bench_spline_tau.py --scene narrow --n 10000 --reps 16 [--draws resampled]

``--taus`` sets the grid; ``--dump FILE`` keeps every replicate's per-tau evidence and draws, and
``--combine FILE ...`` scores the best evidence over several such files (the same replicates fitted
under different priors, ``results/spline_tau/prior_variants/``).
"""

from __future__ import annotations

import argparse
import pickle
import sys
import warnings
from collections import defaultdict
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

TAUS = (0.03, 0.1, 0.3, 1.0, 3.0, 10.0)
NDRAWS = 400


def tau_sweep(model, qfn, *, seed: int, taus=TAUS, draws: str = "laplace"):
    """Per tau: the quantities' draws, the log evidence, the Laplace LOO elpd and the draws' PSIS diagnostics.

    ``draws = "laplace"``: the Laplace Gaussian's own draws (unweighted); ``"resampled"``: those draws
    importance-resampled towards the posterior, as the 2026-11-25 tables were made.  With only
    :data:`NDRAWS` draws the resampling degenerates on rough splines (k-hat 1.2-1.6, an effective sample
    size of 2-12 at tau 10 on a narrow logistic): a handful of distinct draws, whose spread understates
    the posterior's.  ``khat`` and ``ess`` of every row say how far the weights can be trusted.
    """
    from comest_bayes.bayes import selection as SEL
    from comest_bayes.bayes.inference import fit_map, laplace
    from comest_bayes.bayes.psis import psis_log_weights

    rows, prev = [], None
    for tau in taus:
        model.tau = tau
        mp = fit_map(model, nstarts=1 if prev is not None else 2, seed=seed, start=prev,
                     method="newton" if prev is not None else "L-BFGS-B")
        prev = mp.theta
        lap = laplace(model, mp.theta)
        theta, lw, rng = SEL._laplace_draws(model, lap, seed=seed, ndraws=NDRAWS)
        lw_s, khat = psis_log_weights(np.where(np.isfinite(lw), lw, -np.inf))
        w = np.exp(lw_s - np.max(lw_s))
        w /= w.sum()
        use = SEL._resample(theta, lw, NDRAWS, rng) if draws == "resampled" else theta
        rows.append({"tau": tau, "q": qfn(model, use), "khat": float(khat), "ess": float(1.0 / np.sum(w * w)),
                     "evidence": SEL.laplace_evidence(model, mp.theta, mp.log_prob),
                     "loo": SEL.loo_laplace(model, mp.theta, lap.cov).elpd})
    return rows


def psis_summary(all_rows) -> str:
    """Median k-hat and ESS of the :data:`NDRAWS` Laplace draws per tau, over the replicates."""
    parts = []
    for j, tau in enumerate(r["tau"] for r in all_rows[0]):
        k = np.median([rows[j]["khat"] for rows in all_rows])
        e = np.median([rows[j]["ess"] for rows in all_rows])
        parts.append(f"tau {tau:g}: k-hat {k:.2f}, ESS {e:.0f}")
    return f"  importance weights of the {NDRAWS} Laplace draws (median over replicates): " + "; ".join(parts)


def focused_choice(rows, how: str) -> int:
    """A tau chosen for the targeted quantities, against the roughest tau as the (noisy) unbiased reference.

    The difference of a smoother fit's estimate from the roughest one's estimates the smoother fit's
    bias, with a noise variance of about ``v_rough - v_smooth`` (the two estimates are nested, so their
    difference is nearly independent of the smoother one, as in a Hausman test).  ``how = "mse"``: the
    focused information criterion of Claeskens & Hjort (2003, JASA 98, 900): the tau of least
    estimated mean squared error, ``v + max(0, d^2 - (v_rough - v))``, summed over the quantities in
    units of the rough variance.  ``how = "bias"``: the smoothest tau whose every difference is within
    a third of its own sd plus one sd of the difference's noise.
    """
    keys = list(rows[0]["q"])
    stats = []
    for r in rows:
        st = {}
        for k in keys:
            v = np.asarray(r["q"][k], float)
            ok = np.isfinite(v)
            st[k] = (float(np.mean(v[ok])), float(np.var(v[ok]))) if ok.mean() >= 0.5 else None
        stats.append(st)
    ref = stats[-1]
    scores, passes = [], []
    for st in stats:
        total, ok_all = 0.0, True
        for k in keys:
            if st[k] is None or ref[k] is None or ref[k][1] <= 0:
                continue
            (mu, var), (mu_r, var_r) = st[k], ref[k]
            noise = max(var_r - var, 0.0)
            total += (var + max(0.0, (mu - mu_r) ** 2 - noise)) / var_r
            ok_all &= abs(mu - mu_r) <= np.sqrt(var) / 3.0 + np.sqrt(noise)
        scores.append(total)
        passes.append(ok_all)
    if how == "mse":
        return int(np.argmin(scores))
    return next(j for j, ok in enumerate(passes) if ok or j == len(passes) - 1)


def rules(rows, rng):
    """Draws of each quantity under each rule for tau: fixed taus, evidence, evidence mixture, LOO."""
    ev = np.array([r["evidence"] for r in rows])
    w = np.exp(ev - ev.max())
    w /= w.sum()
    one = np.eye(len(rows))
    mixes = {"evidence": one[int(np.argmax(ev))], "evidence-mixture": w,
             "loo": one[int(np.argmax([r["loo"] for r in rows]))],
             "focused-mse": one[focused_choice(rows, "mse")], "bias-test": one[focused_choice(rows, "bias")]}
    mixes.update({f"tau={r['tau']:g}": one[j] for j, r in enumerate(rows)})
    out = {}
    for name, mix in mixes.items():
        counts = rng.multinomial(NDRAWS, mix)
        out[name] = {k: np.concatenate([rows[j]["q"][k][:counts[j]] for j in range(len(rows))]) for k in rows[0]["q"]}
    return out


def _dump(a, payload) -> None:
    """Write every replicate's per-tau rows so far to ``--dump`` (rewritten after each replicate)."""
    if a.dump:
        tmp = Path(a.dump).with_suffix(".part")
        with open(tmp, "wb") as fh:
            pickle.dump(payload, fh)
        tmp.replace(a.dump)


def combine(paths, log):
    """Score the evidence's choice over the union of several ``--dump`` files' grids, replicate by replicate.

    Each file holds the same replicates fitted under one prior (for example the prior variants of
    ``results/spline_tau/prior_variants/``); per replicate the (file, tau) of highest Laplace evidence
    is kept, as a selection over both the prior and tau would.
    """
    dumps = []
    for p in paths:
        with open(p, "rb") as fh:
            dumps.append(pickle.load(fh))
    nrep = min(len(d["rows"]) for d in dumps)
    for label, use in [(Path(p).name, [i]) for i, p in enumerate(paths)] + [("best evidence over all", range(len(paths)))]:
        qs = [max(((row["evidence"], row["q"]) for i in use for row in dumps[i]["rows"][r]), key=lambda c: c[0])[1]
              for r in range(nrep)]
        if "ref" in dumps[0]:
            log(f"  {label:<28s} m50 {_m50_line([q['m50'] for q in qs], dumps[0]['ref'])}  (mmag, {nrep} replicates)")
            continue
        log(f"  {label:<28s} " + _score_line(qs, dumps[0]["truth_q"]))


def _m50_line(draws, ref: float) -> str:
    """RMSE of the replicates' posterior-mean m50 against ``ref`` and their median posterior sd, mmag."""
    mean = np.array([np.mean(x) for x in draws])
    return (f"rmse {1e3 * np.sqrt(np.mean((mean - ref) ** 2)):5.2f}  "
            f"sd {1e3 * np.median([np.std(x) for x in draws]):5.2f}")


def _score_line(reps, truth) -> str:
    """Per quantity with a truth: bias / median posterior sd, 68% coverage and RMSE x 1000 over the replicates."""
    parts = []
    for k in reps[0]:
        if truth.get(k) is None:
            continue
        v = [np.asarray(r[k], float) for r in reps]
        mean = np.array([np.nanmean(x) for x in v])
        sd = np.median([np.nanstd(x) for x in v])
        cov68 = np.mean([np.nanpercentile(x, 16) <= truth[k] <= np.nanpercentile(x, 84) for x in v])
        parts.append(f"{k} {(mean.mean() - truth[k]) / sd:+.2f} {cov68:.2f} "
                     f"{1e3 * np.sqrt(np.mean((mean - truth[k]) ** 2)):5.1f}")
    return " | ".join(parts)


def honesty(a, log):
    import bench_honesty as H
    from comest_bayes.bayes.fit import targeted_quantities
    from comest_bayes.bayes.model import CompletenessModel
    from comest_bayes.bayes.outcomes import compress_for, covariates_from_outcomes
    from comest_bayes.bayes.posterior import Footprint, FootprintHistogram
    from comest_bayes.bayes.spec import load_spec
    from comest_bayes.seeding import int_seed_for
    from comest_bayes.sim import synthetic as S

    sp = {**H.SCENE, "seed": int_seed_for(a.seed, "honesty", "scene")}
    scene = S.make_scene(tuple(sp["shape"]), gradient=sp["gradient"], chip_gap=sp["chip_gap"], seed=sp["seed"])
    truth = S.get_truth(a.truth)
    setup = H.truth_setup([a.truth], scene)[a.truth]
    lo, hi = setup["mag_range"]
    q = setup["quantities"]
    spec = load_spec("spline_depth")
    hist = FootprintHistogram.from_maps(scene.noise, scene.mask, ddepth=0.01, nuv=1)
    scores, all_rows = defaultdict(list), []
    for rep in range(a.reps):
        table = S.draw_outcomes(truth, scene, a.n, mag_range=(lo, hi),
                                seed=int_seed_for(a.seed, "honesty", a.truth, a.n, rep, "draw"))
        cov, out, meta = covariates_from_outcomes(table, image_shape=scene.shape)
        model = CompletenessModel(spec, compress_for(spec, cov, out, meta=meta))
        qfn = targeted_quantities(Footprint.from_histogram(hist, meta.get("sigma_ref")),
                                  [q["mag_bright"], q["mag_faint"]], lo, hi)
        rows = tau_sweep(model, qfn, seed=int_seed_for(a.seed, "honesty", a.truth, a.n, rep, "fit"), draws=a.draws,
                         taus=a.taus)
        all_rows.append(rows)
        _dump(a, {"truth_q": q, "rows": all_rows})
        for name, qd in rules(rows, np.random.default_rng(rep)).items():
            scores[name].append(qd)
        log(f"  replicate {rep}: evidence picks tau {rows[int(np.argmax([r['evidence'] for r in rows]))]['tau']:g}, "
            f"LOO picks {rows[int(np.argmax([r['loo'] for r in rows]))]['tau']:g}")
    log(f"{a.truth}, N = {a.n}, {a.reps} replicates, {a.draws} draws: bias / posterior sd, 68% coverage, RMSE x 1000")
    log(psis_summary(all_rows))
    for name, reps in scores.items():
        log(f"  {name:<17s} " + _score_line(reps, q))


def _m50_rules(a, log, tables, ref: float, lo: float, hi: float, label: str):
    """Fit every tau to each (magnitude, detected) table of a white-noise scene; m50 RMSE and sd per rule."""
    from comest_bayes.bayes.fit import _probe_magnitudes, targeted_quantities
    from comest_bayes.bayes.model import CompletenessModel
    from comest_bayes.bayes.outcomes import compress_for, covariates_from_outcomes
    from comest_bayes.bayes.posterior import Footprint
    from comest_bayes.bayes.spec import load_spec

    spec = load_spec("spline_depth")
    # white noise: the depth covariate is ~0 everywhere, one footprint cell at depth 0
    one_cell = Footprint(depth=np.zeros(1), u=np.zeros(1), v=np.zeros(1), weight=np.ones(1), npix=1)
    scores, all_rows = defaultdict(list), []
    for rep, (mag, det) in enumerate(tables):
        cov, out, meta = covariates_from_outcomes({"mag": mag, "detected": det}, image_shape=None)
        model = CompletenessModel(spec, compress_for(spec, cov, out, meta=meta))
        qfn = targeted_quantities(one_cell, _probe_magnitudes(cov.m, out), lo, hi)
        rows = tau_sweep(model, qfn, seed=1 + rep, draws=a.draws, taus=a.taus)
        all_rows.append(rows)
        _dump(a, {"ref": ref, "rows": all_rows})
        for name, qd in rules(rows, np.random.default_rng(rep)).items():
            scores[name].append(qd["m50"])
        log(f"  replicate {rep}: evidence picks tau {rows[int(np.argmax([r['evidence'] for r in rows]))]['tau']:g}, "
            f"LOO picks {rows[int(np.argmax([r['loo'] for r in rows]))]['tau']:g}, "
            f"bias test picks {rows[focused_choice(rows, 'bias')]['tau']:g}")
    log(f"{label}, N = {a.n}, {len(tables)} replicates, {a.draws} draws: m50 RMSE and median posterior sd (mmag) "
        f"against {ref:.4f}")
    log(psis_summary(all_rows))
    for name, v in scores.items():
        log(f"  {name:<17s} {_m50_line(v, ref)}")


def analytic(a, log):
    from astropy.table import Table

    o = Table.read(Path(a.work) / "analytic_run" / "catalogs" / "point_outcomes.fits")
    mag = np.asarray(o["mag"], float)
    det = np.asarray(o["detected"], bool)
    idx = np.random.default_rng(7).permutation(np.flatnonzero(np.asarray(o["realization"]) % 3 != 0))
    tables = [(mag[idx[r * a.n:(r + 1) * a.n]], det[idx[r * a.n:(r + 1) * a.n]]) for r in range(a.reps)]
    _m50_rules(a, log, tables, a.ref, float(mag.min()), float(mag.max()), "analytic pool")


#: The ``narrow`` scene: a logistic of the white-noise pool's width (0.045 mag, the fit of 10^4 of its
#: outcomes), floor 0.01 and plateau 0.99, m50 25.4, magnitudes uniform over the pool's 24.0-26.8.
NARROW = {"m50": 25.4, "lo": 24.0, "hi": 26.8, "floor": 0.01, "plateau": 0.99}


def narrow(a, log):
    """A stand-in for the analytic pool with an exact m50: outcomes drawn from a narrow logistic."""
    from comest_bayes.seeding import rng_for

    c = NARROW
    tables = []
    for rep in range(a.reps):
        rng = rng_for(a.seed, "spline_tau", "narrow", a.n, rep)
        mag = rng.uniform(c["lo"], c["hi"], a.n)
        f = c["floor"] + (c["plateau"] - c["floor"]) / (1.0 + np.exp((mag - c["m50"]) / a.width))
        tables.append((mag, rng.random(a.n) < f))
    _m50_rules(a, log, tables, c["m50"], c["lo"], c["hi"], f"narrow logistic (w = {a.width:g} mag)")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", choices=("honesty", "analytic", "narrow"))
    p.add_argument("--taus", type=lambda v: tuple(float(x) for x in v.split(",")), default=TAUS,
                   help="comma-separated grid of tau (default %(default)s)")
    p.add_argument("--dump", help="write every replicate's per-tau rows (evidence, draws) to this pickle")
    p.add_argument("--combine", nargs="+", metavar="DUMP",
                   help="instead of fitting: score the best evidence over the union of these --dump files")
    p.add_argument("--truth", default="two_populations", help="honesty truth name")
    p.add_argument("--n", type=int, default=3000)
    p.add_argument("--reps", type=int, default=24)
    p.add_argument("--seed", type=int, default=12, help="the honesty benchmark's root seed")
    p.add_argument("--work", default="/tmp/sa4/work", help="bench_speed_accuracy.py --work directory")
    p.add_argument("--ref", type=float, default=25.3958, help="reference m50 of the analytic pool")
    p.add_argument("--width", type=float, default=0.045, help="logistic width of the narrow scene, mag")
    p.add_argument("--draws", choices=("laplace", "resampled"), default="laplace",
                   help="score each tau on its Laplace draws (default) or on those draws importance-resampled")
    a = p.parse_args(argv)
    log = lambda s: print(s, flush=True)  # noqa: E731
    if a.combine:
        combine(a.combine, log)
        return 0
    if a.scene is None:
        p.error("--scene is required unless --combine is given")
    from comest_bayes.pipeline import runtime

    runtime.configure(threads=1)
    warnings.simplefilter("ignore")
    {"honesty": honesty, "analytic": analytic, "narrow": narrow}[a.scene](a, log)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
