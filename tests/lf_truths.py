"""Known truths shared by the number-count tests (tests/lf/): power-law catalogs, a logistic completeness, a
completeness posterior whose draws are a known Gaussian, and a mock catalog seen through both."""

import math

import numpy as np

from comest_bayes.bayes.posterior import CompletenessPosterior
from comest_bayes.bayes.spec import load_spec

LN10 = math.log(10.0)


def sample_powerlaw(rng, log_n, slope, area, lo, hi, m_ref=23.0):
    b = slope * LN10
    expected = area * 10**log_n * (math.exp(b * (hi - m_ref)) - math.exp(b * (lo - m_ref))) / b
    n = rng.poisson(expected)
    u = rng.random(n)
    return lo + np.log1p(u * (math.exp(b * (hi - lo)) - 1.0)) / b


def logistic(m, m50, w):
    return 1.0 / (1.0 + np.exp((m - m50) / w))


def synthetic_posterior(m50=23.0, w=0.3, sd_m50=0.08, sd_logw=0.1, nsamples=3000, seed=0):
    """A CompletenessPosterior (logistic, no spatial term) whose draws are a known Gaussian around (m50, w)."""
    spec = load_spec("logistic")
    post = CompletenessPosterior(spec=spec, samples=np.zeros((1, 4)), names=["m50_0", "log_w", "logit_A",
                                                                             "logit_floor"],
                                 meta={"sigma_ref": None, "hlr_ref": None, "image_shape": (200, 200),
                                       "mag_range": [18.0, 27.0], "kind": "point", "quantity": "completeness"},
                                 footprint=np.array([[100.0, 100.0]]))
    centre = post.model.inverse_transform({"m50_0": m50, "w": w, "A": 0.995, "floor": 1e-4})
    rng = np.random.default_rng(seed)
    draws = np.tile(centre, (nsamples, 1))
    draws[:, 0] += sd_m50 * rng.standard_normal(nsamples)
    draws[:, 1] += sd_logw * rng.standard_normal(nsamples)
    post.samples = draws
    return post


def mock_catalog(rng, *, log_n=4.3, slope=0.3, area=0.0123, m50=23.0, w=0.3, bias=0.03, sigma=0.08):
    true = sample_powerlaw(rng, log_n, slope, area, 17.0, 28.0)
    det = rng.random(true.size) < 0.995 * logistic(true, m50, w)
    obs = true[det] + bias + sigma * rng.standard_normal(det.sum())
    return obs
