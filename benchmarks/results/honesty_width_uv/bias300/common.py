"""Shared set-up of the bias300 diagnostics (issue #12): scene, truths, one 300k table, the rung's model."""
import math, sys
import numpy as np
from scipy.optimize import brentq
from comest_bayes.pipeline import runtime
runtime.configure(threads=1)
from comest_bayes.sim import synthetic as S
from comest_bayes.seeding import int_seed_for
from comest_bayes.bayes.outcomes import covariates_from_outcomes, compress_for, uncompressed
from comest_bayes.bayes.model import CompletenessModel
from comest_bayes.bayes.posterior import Footprint, FootprintHistogram
from comest_bayes.bayes.fit import footprint_grid

MODEL = "logistic_depth_width_uv"


SCENE = S.make_scene((512, 512), gradient=0.6, chip_gap=True, seed=int_seed_for(12, "honesty", "scene"))
TRUTHS = {"width_varies": S.get_truth("width_varies"), "width_logplane": S.LogPlaneWidthTruth(),
          "logistic": S.get_truth("logistic")}


def table(truth, n, rep):
    lo, hi = truth.default_mag_range()
    return S.draw_outcomes(truth, SCENE, n, mag_range=(lo, hi),
                           seed=int_seed_for(12, "honesty", "width_varies", n, rep, "draw"))


def cells_of(sigma_ref, grid=None):
    grid = footprint_grid(True) if grid is None else grid
    return Footprint.from_histogram(FootprintHistogram.from_maps(SCENE.noise, SCENE.mask, ddepth=grid[0], nuv=grid[1]),
                                    sigma_ref)


def pixel_cells(sigma_ref):
    """One cell per unmasked pixel (the exact image average)."""
    iy, ix = np.nonzero(~SCENE.mask)
    return Footprint.from_points(ix.astype(float), iy.astype(float), SCENE.noise[iy, ix], sigma_ref, SCENE.shape,
                                 ddepth=None)


def avg(model, theta, mags, fp, chunk=20000):
    """Footprint average of f at one theta for magnitudes, in numpy chunks over the cells."""
    from comest_bayes.bayes.outcomes import Covariates
    mags = np.atleast_1d(np.asarray(mags, float))
    out = np.zeros(mags.size)
    for s in range(0, len(fp.weight), chunk):
        sl = slice(s, s + chunk)
        P = len(fp.weight[sl])
        cov = Covariates.make(np.repeat(mags, P), np.tile(fp.depth[sl], mags.size), np.tile(fp.u[sl], mags.size),
                              np.tile(fp.v[sl], mags.size))
        f = model.prob(theta, cov).reshape(mags.size, P)
        out += f @ fp.weight[sl]
    return out


def crossing(model, theta, fp, level=0.5, lo=22.0, hi=26.0):
    return brentq(lambda m: avg(model, theta, [m], fp)[0] - level, lo, hi, xtol=1e-9)


def true_theta(model, truth, sigma_ref):
    """The rung's parameters of a truth inside its family (logistic / width_logplane)."""
    m50_0 = truth.m50_0 - 2.5 * math.log10(sigma_ref / SCENE.sigma_ref)
    p = {"m50_0": m50_0, "A": truth.plateau, "floor": truth.floor, "beta_depth": 1.0}
    if isinstance(truth, S.LogPlaneWidthTruth):
        half = 0.5 * math.log(truth.w_right / truth.w_left)
        p["log_w"] = math.log(truth.w_left) + half
        p["w_10"] = half
    else:
        p["log_w"] = math.log(truth.w)
    return model.inverse_transform(p)
