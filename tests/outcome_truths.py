"""Outcome tables drawn from known logistic completeness functions, shared by the model tests (tests/bayes/)."""

import numpy as np
from astropy.table import Table
from scipy import special

from comest_bayes.bayes.fit import fit_kind
from comest_bayes.bayes.outcomes import Covariates
from comest_bayes.config import load_config

#: Image of the depth-split scene; its right part (x >= SPLIT) is 0.5 mag shallower.
SHAPE = (400, 600)
SPLIT = 330  # x where the shallow part starts


def synthetic(n, seed, *, m50=24.0, w=0.2, A=0.95, floor=0.01, beta_depth=1.0, c10=0.0, mrange=(20.0, 27.0)):
    """Outcomes drawn from the logistic model with known parameters (depth follows u, plus scatter)."""
    rng = np.random.default_rng(seed)
    m = rng.uniform(*mrange, n)
    u = rng.uniform(-1, 1, n)
    v = rng.uniform(-1, 1, n)
    depth = 0.3 * u - 0.2 * v ** 2 + rng.normal(0.0, 0.05, n)
    cov = Covariates(m, depth, u, v, np.zeros(n))
    field = m50 + beta_depth * depth + c10 * u
    f = floor + (A - floor) * special.expit((field - m) / w)
    return cov, rng.uniform(size=n) < f


def depth_split_outcomes(n, *, m50=24.0, w=0.15, A=0.98, depth_slope=1.0, seed=0):
    """Outcomes from a known logistic completeness; the right 45% of the image is 0.5 mag shallower.

    The deep part holds most injections, so the model's reference noise (the median) is the deep
    noise and the true m50_0 is ``m50``.
    """
    rng = np.random.default_rng(seed)
    x = rng.uniform(0, SHAPE[1] - 1, n)
    y = rng.uniform(0, SHAPE[0] - 1, n)
    m = rng.uniform(21.0, 26.5, n)
    noise = np.where(x < SPLIT, 1.0, 10 ** (0.4 * 0.5))
    d = -2.5 * np.log10(noise)
    mu = m50 + depth_slope * d
    p = A / (1.0 + np.exp(-(mu - m) / w))
    noise_map = np.where(np.arange(SHAPE[1])[None, :] < SPLIT, 1.0, 10 ** (0.4 * 0.5)) * np.ones(SHAPE)
    return Table({"x": x, "y": y, "mag": m, "noise": noise, "hlr_arcsec": np.full(n, np.nan),
                  "detected": rng.random(n) < p}), noise_map


def fit_depth_split(table, noise_map, model, min_ess=300, **kw):
    config = load_config(overrides=[f"fit.model={model}", f"fit.min_ess={min_ess}"], seed=3)
    return fit_kind(table, kind="point", quantity="completeness", requested=model, config=config,
                    image_shape=SHAPE, noise=noise_map, mask=np.zeros(SHAPE, bool), wcs_header=None,
                    mag_range=(21.0, 26.5), mag_centers=np.arange(21.1, 26.5, 0.2), **kw)
