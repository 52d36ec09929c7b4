"""A detection catalog with a known population, shared by the observed-population and injection tests."""

import numpy as np
from astropy.table import Table

from comest_bayes.inject.population import draw_magnitudes


def synthetic_catalog(n=6000, slope=0.32, m50=25.0, seed=4):
    """Detections from a known power law, thinned by a logistic completeness, with sizes and SNRs.

    Counts ~ 10**(slope m) on 17-27 mag; completeness 1 / (1 + exp((m - m50) / 0.25)); SNR = 10 at
    m = m50 - 0.3 (so the well-detected range ends well before the turnover); true size relation
    log10 r = 0.6 - 0.12 (m - 22) with 0.08 dex scatter; some rows flagged (saturated, edge).
    """
    rng = np.random.default_rng(seed)
    m = draw_magnitudes(4 * n, (17.0, 27.0), rng, slope=slope)
    keep = rng.uniform(size=m.size) < 1.0 / (1.0 + np.exp((m - m50) / 0.25))
    m = m[keep][:n]
    k = m.size
    logr = 0.6 - 0.12 * (m - 22.0) + 0.08 * rng.standard_normal(k)
    r = 10 ** logr
    q = rng.uniform(0.3, 1.0, k)
    a = r * 1.2 / np.sqrt(q)
    b = r * 1.2 * np.sqrt(q)
    snr = 10.0 * 10 ** (-0.4 * (m - (m50 - 0.3)))
    flags = np.where(rng.uniform(size=k) < 0.03, 4, 0) | np.where(rng.uniform(size=k) < 0.03, 8, 0)
    mag = m + 0.02 * rng.standard_normal(k)
    return Table({"mag_auto": mag, "flux_radius": r, "snr_auto": snr, "flags": flags, "a": a, "b": b})
