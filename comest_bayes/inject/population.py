"""The drawn parameters of the synthetic sources: magnitudes and shapes of each kind, and the
``observed`` population fitted to the image's own detection catalog (number-count slope, size-
magnitude relation, axis ratios).  Every draw comes from an explicit generator.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import numpy as np
from scipy.optimize import minimize_scalar
from comest_bayes.config import InjectionConfig, KINDS
from comest_bayes.errors import InputError
from comest_bayes.inject.cosmos import CosmosSample
from comest_bayes.inject.profiles import sersic_index_grid

__all__ = ['draw_magnitudes', 'draw_parameters', 'ObservedPopulation', 'fit_count_slope', 'fit_observed_population']


# --------------------------------------------------------------------------- parameter drawing


def draw_magnitudes(n: int, mag_range, rng: np.random.Generator, slope: float = 0.0) -> np.ndarray:
    """Magnitudes in ``[bright, faint]`` with ``dN/dm ~ 10**(slope * m)``.

    ``slope = 0`` (default) is the uniform distribution.  Inverse-CDF sampling
    of the truncated exponential in ``t = m - bright``.

    Parameters
    ----------
    n : int
        How many.
    mag_range : (float, float)
        Bright and faint limits, bright < faint.
    rng : numpy.random.Generator
    slope : float
        Logarithmic count slope per magnitude.

    Returns
    -------
    ndarray, shape (n,)
    """
    lo, hi = _check_mag_range(mag_range)
    u = rng.uniform(0.0, 1.0, int(n))
    beta = slope * np.log(10.0)
    width = hi - lo
    if abs(beta * width) < 1e-8:
        return lo + width * u
    # CDF(t) = expm1(beta t) / expm1(beta width)
    return lo + np.log1p(u * np.expm1(beta * width)) / beta


def _check_mag_range(mag_range) -> tuple[float, float]:
    if mag_range is None or len(mag_range) != 2 or not np.all(np.isfinite(mag_range)) \
            or not mag_range[0] < mag_range[1]:
        raise InputError(f"mag_range must be (bright, faint) with bright < faint, got {mag_range!r}; "
                         f"set injection.mag_range or let the pipeline derive it from the image depth.")
    return float(mag_range[0]), float(mag_range[1])


def draw_parameters(kind: str, n: int, *, config: InjectionConfig, mag_range, rng: np.random.Generator,
                    pixel_scale: float, cosmos: "CosmosSample | None" = None,
                    population: "ObservedPopulation | None" = None, mag_design=None) -> dict:
    """Magnitudes and shape parameters of ``n`` sources of one kind.

    The random draws happen in a fixed order (magnitudes, then sizes, axis
    ratios, angles, then the kind's own parameters), so the result depends
    only on the generator's state and the arguments.

    Parameters
    ----------
    kind : str
        Source kind (see ``docs/sources.md``).
    n : int
        Number of sources.
    config : InjectionConfig
        Ranges ``hlr_range``, ``q_range``, ``bulge_fraction_range``, ``sersic_n_range``.
    mag_range : (float, float)
        Bright and faint magnitude limits.
    rng : numpy.random.Generator
    pixel_scale : float
        Arcsec per pixel (``observed``: sizes are fitted in pixels).
    cosmos : CosmosSample, optional
        Required for ``cosmos``.
    population : ObservedPopulation, optional
        Required for ``observed`` (see :func:`fit_observed_population`).
    mag_design : comest_bayes.inject.design.MagnitudeDesign, optional
        Draw the magnitudes from this density (an adaptive batch) instead of
        uniformly in ``mag_range`` (not for ``observed``, whose magnitudes
        follow the image's counts).

    Returns
    -------
    dict of ndarray, shape (n,)
        ``mag``, ``hlr_arcsec``, ``q``, ``pa_deg``, ``bulge_fraction``,
        ``sersic_n`` (float, NaN where not applicable) and ``cosmos_index``
        (int, -1 unless ``cosmos``).
    """
    if kind not in KINDS:
        raise InputError(f"unknown source kind {kind!r}; use one of {KINDS}.")
    n = int(n)
    nan = np.full(n, np.nan)
    out = {"hlr_arcsec": nan.copy(), "q": nan.copy(), "pa_deg": nan.copy(), "bulge_fraction": nan.copy(),
           "sersic_n": nan.copy(), "cosmos_index": np.full(n, -1, dtype=np.int64)}
    if kind == "observed":
        if population is None:
            raise InputError("kind 'observed' needs the population fitted to the image's detection catalog: "
                             "pass observed_catalog= (see fit_observed_population).")
        out["mag"] = draw_magnitudes(n, mag_range, rng, slope=population.slope)
    elif mag_design is not None:
        out["mag"] = mag_design.sample(n, rng)
    else:
        out["mag"] = draw_magnitudes(n, mag_range, rng)

    if kind in ("buldisk", "sersic"):
        out["hlr_arcsec"] = rng.uniform(*config.hlr_range, n)
        out["q"] = rng.uniform(*config.q_range, n)
        out["pa_deg"] = rng.uniform(0.0, 180.0, n)
        if kind == "buldisk":
            out["bulge_fraction"] = rng.uniform(*config.bulge_fraction_range, n)
        else:
            out["sersic_n"] = rng.choice(sersic_index_grid(config.sersic_n_range), size=n)
    elif kind == "cosmos":
        if cosmos is None:
            raise InputError("kind 'cosmos' needs the COSMOS sample: pass cosmos=load_cosmos(config).")
        out["cosmos_index"] = rng.choice(cosmos.n, size=n, p=cosmos.probabilities).astype(np.int64)
        out["pa_deg"] = rng.uniform(0.0, 180.0, n)
    elif kind == "observed":
        hlr_pix, q = population.draw_shapes(out["mag"], rng, q_range=config.q_range)
        out["hlr_arcsec"] = hlr_pix * pixel_scale
        out["q"] = q
        out["pa_deg"] = rng.uniform(0.0, 180.0, n)
        out["sersic_n"] = rng.choice(sersic_index_grid(config.sersic_n_range), size=n)
    return out


# --------------------------------------------------------------------------- observed population


def fit_count_slope(mags, m_lo: float, m_hi: float) -> tuple[float, float]:
    """Maximum-likelihood slope of ``dN/dm ~ 10**(slope * m)`` on ``[m_lo, m_hi]``.

    Unbinned likelihood of the truncated exponential in ``t = m - m_lo``:
    ``p(t) = beta exp(beta t) / expm1(beta T)`` with ``beta = slope ln 10`` and
    ``T = m_hi - m_lo``.  The error is from the curvature of the
    log-likelihood.

    Parameters
    ----------
    mags : array_like
        Magnitudes inside ``[m_lo, m_hi]`` (others are ignored).
    m_lo, m_hi : float
        Fit range.

    Returns
    -------
    slope, slope_err : float
    """
    m = np.asarray(mags, dtype=float)
    m = m[(m >= m_lo) & (m <= m_hi)]
    if m.size < 2 or not m_hi > m_lo:
        raise InputError(f"cannot fit number counts: {m.size} magnitudes in [{m_lo}, {m_hi}].")
    t_sum = float(np.sum(m - m_lo))
    width = m_hi - m_lo
    nobj = m.size

    def nll(beta):
        if abs(beta * width) < 1e-8:
            return nobj * np.log(width) - beta * t_sum
        return -(nobj * np.log(beta / np.expm1(beta * width)) + beta * t_sum)

    res = minimize_scalar(nll, bounds=(-5.0, 5.0), method="bounded", options={"xatol": 1e-7})
    beta = float(res.x)
    h = 1e-3
    curv = (nll(beta + h) - 2.0 * nll(beta) + nll(beta - h)) / h ** 2
    err = 1.0 / np.sqrt(curv) if curv > 0 else np.inf
    return beta / np.log(10.0), float(err / np.log(10.0))


@dataclass
class ObservedPopulation:
    """Number counts and sizes fitted to an image's detection catalog.

    Attributes
    ----------
    slope, slope_err : float
        ``dN/dm ~ 10**(slope * m)`` fitted on ``[fit_mag_lo, fit_mag_hi]``.
    fit_mag_lo, fit_mag_hi : float
        Magnitude range of the fit (the well-detected range).
    n_fit : int
        Detections in the fit range.
    turnover_mag : float
        Peak of the (3-bin smoothed) magnitude histogram of all usable detections.
    size_mag_ref : float
        Reference magnitude of the size relation.
    size_intercept, size_slope : float
        Median ``log10(flux_radius / pix) = intercept + slope * (m - size_mag_ref)``.
    size_scatter_dex : float
        Scatter about it (1.4826 x median absolute deviation, median over bins), dex.
    log_r_max : float
        99th percentile of ``log10(flux_radius)`` of the fit sample; drawn sizes are capped there.
    psf_hlr_pix : float
        PSF half-light radius (pixels) subtracted in quadrature.
    q_values : ndarray
        PSF-deconvolved axis ratios of resolved detections (empty if fewer than 20).
    """

    slope: float
    slope_err: float
    fit_mag_lo: float
    fit_mag_hi: float
    n_fit: int
    turnover_mag: float
    size_mag_ref: float
    size_intercept: float
    size_slope: float
    size_scatter_dex: float
    log_r_max: float
    psf_hlr_pix: float
    q_values: np.ndarray = field(repr=False)

    def observed_radius_pix(self, mag) -> np.ndarray:
        """Median observed ``flux_radius`` (pixels) at magnitude ``mag`` (extrapolated linearly in log)."""
        return 10.0 ** (self.size_intercept + self.size_slope * (np.asarray(mag, dtype=float) - self.size_mag_ref))

    def draw_shapes(self, mags, rng: np.random.Generator, *, q_range=(0.4, 1.0)):
        """Intrinsic half-light radii (pixels) and axis ratios for magnitudes ``mags``.

        ``log10 r_obs`` = relation + scatter x N(0, 1), capped at
        ``log_r_max``; ``hlr = sqrt(r_obs^2 - psf_hlr^2)``, floored at
        ``0.1 psf_hlr``.  ``q`` is resampled from ``q_values`` (uniform in
        ``q_range`` when there are none) and clipped to ``[q_range[0], 1]``.

        Returns
        -------
        hlr_pix, q : ndarray, shape (n,)
        """
        mags = np.asarray(mags, dtype=float)
        logr = (self.size_intercept + self.size_slope * (mags - self.size_mag_ref)
                + self.size_scatter_dex * rng.standard_normal(mags.size))
        r_obs = 10.0 ** np.minimum(logr, self.log_r_max)
        floor = 0.1 * self.psf_hlr_pix
        hlr = np.sqrt(np.maximum(r_obs ** 2 - self.psf_hlr_pix ** 2, floor ** 2))
        if self.q_values.size:
            q = rng.choice(self.q_values, size=mags.size)
        else:
            q = rng.uniform(q_range[0], q_range[1], mags.size)
        return hlr, np.clip(q, q_range[0], 1.0)

    def meta(self) -> dict:
        """Scalar summary for table metadata."""
        return {"obs_slope": self.slope, "obs_slope_err": self.slope_err, "obs_fit_mag_lo": self.fit_mag_lo,
                "obs_fit_mag_hi": self.fit_mag_hi, "obs_n_fit": self.n_fit, "obs_turnover_mag": self.turnover_mag,
                "obs_size_mag_ref": self.size_mag_ref, "obs_size_intercept": self.size_intercept,
                "obs_size_slope": self.size_slope, "obs_size_scatter_dex": self.size_scatter_dex,
                "obs_psf_hlr_pix": self.psf_hlr_pix, "obs_n_q": int(self.q_values.size)}


#: Detection flags excluding a source from the fit: saturated, edge, truncated aperture, overflow.
OBSERVED_EXCLUDE_FLAGS = 4 | 8 | 16 | 64


def fit_observed_population(catalog, *, psf_hlr_pix: float, psf_sigma_pix: float, snr_min: float = 10.0,
                            bin_width: float = 0.25, fit_width: float = 4.0, turnover_offset: float = 0.5,
                            min_objects: int = 30, exclude_flags: int = OBSERVED_EXCLUDE_FLAGS
                            ) -> ObservedPopulation:
    """Fit number counts and the size-magnitude relation of a detection catalog.

    Usable detections have finite ``mag_auto``, positive ``flux_radius`` and
    none of ``exclude_flags``.  The fit range is the *well-detected* range:
    its faint end is the fainter-most magnitude both ``turnover_offset`` mag
    brighter than the turnover of the counts (where incompleteness sets in)
    and brighter than the first ``bin_width`` bin whose median ``snr_auto``
    is below ``snr_min``; its bright end is the brightest detection but at
    most ``fit_width`` mag brighter.  The slope is the unbinned maximum
    likelihood one (:func:`fit_count_slope`).  The size relation is a
    straight line through the medians of ``log10(flux_radius)`` in 0.5-mag
    bins (at least 5 detections with ``snr_auto >= snr_min``), weighted by
    sqrt(count).  Axis ratios are deconvolved as
    ``q = sqrt((b^2 - s^2) / (a^2 - s^2))`` with ``s = psf_sigma_pix`` for
    detections with ``a > sqrt(2) s``.

    Parameters
    ----------
    catalog : astropy.table.Table or mapping of arrays
        Columns ``mag_auto``, ``flux_radius`` (pix), ``snr_auto``, ``flags``, ``a``, ``b`` (pix).
    psf_hlr_pix, psf_sigma_pix : float
        PSF half-light radius and Gaussian-equivalent sigma (FWHM / 2.3548), pixels.
    snr_min, bin_width, fit_width, turnover_offset, min_objects, exclude_flags
        See above.

    Returns
    -------
    ObservedPopulation

    Raises
    ------
    InputError
        Missing columns or fewer than ``min_objects`` usable detections in the fit range.
    """
    needed = ("mag_auto", "flux_radius", "snr_auto", "flags", "a", "b")
    names = list(catalog.colnames) if hasattr(catalog, "colnames") else list(catalog.keys())
    missing = [c for c in needed if c not in names]
    if missing:
        raise InputError(f"kind 'observed' needs a detection catalog with columns {list(needed)}; "
                         f"missing {missing}.")
    mag = np.asarray(catalog["mag_auto"], dtype=float)
    rad = np.asarray(catalog["flux_radius"], dtype=float)
    snr = np.asarray(catalog["snr_auto"], dtype=float)
    flags = np.asarray(catalog["flags"], dtype=np.int64)
    a = np.asarray(catalog["a"], dtype=float)
    b = np.asarray(catalog["b"], dtype=float)
    good = np.isfinite(mag) & np.isfinite(rad) & (rad > 0) & ((flags & exclude_flags) == 0)
    if good.sum() < min_objects:
        raise InputError(f"kind 'observed' needs at least {min_objects} usable detections (finite mag_auto, "
                         f"flux_radius > 0, no flags {exclude_flags}); the catalog has {int(good.sum())}. "
                         f"Use another source kind for this image.")
    mag, rad, snr, a, b = mag[good], rad[good], snr[good], a[good], b[good]

    edges = np.arange(np.floor(mag.min() / bin_width) * bin_width, mag.max() + bin_width, bin_width)
    counts, _ = np.histogram(mag, edges)
    smooth = np.convolve(counts, np.ones(3) / 3.0, mode="same")
    k = int(np.argmax(smooth))
    turnover = 0.5 * (edges[k] + edges[k + 1])
    m_hi = turnover - turnover_offset
    idx = np.digitize(mag, edges) - 1
    for j in range(len(counts)):
        if counts[j] >= 3 and np.median(snr[idx == j]) < snr_min:
            m_hi = min(m_hi, edges[j])
            break
    m_lo = max(float(mag.min()), m_hi - fit_width)
    in_fit = (mag >= m_lo) & (mag <= m_hi)
    if in_fit.sum() < min_objects or not m_hi > m_lo:
        raise InputError(f"kind 'observed': only {int(in_fit.sum())} well-detected sources (magnitudes "
                         f"{m_lo:.2f}-{m_hi:.2f}, SNR >= {snr_min}) to fit the number counts; at least "
                         f"{min_objects} are needed. Use another source kind for this image.")
    slope, slope_err = fit_count_slope(mag[in_fit], m_lo, m_hi)

    sized = in_fit & (snr >= snr_min)
    logr = np.log10(rad[sized])
    msz = mag[sized]
    centres, medians, scatters, weights = [], [], [], []
    for lo in np.arange(m_lo, m_hi, 0.5):
        sel = (msz >= lo) & (msz < lo + 0.5)
        if sel.sum() >= 5:
            med = float(np.median(logr[sel]))
            centres.append(float(np.median(msz[sel])))
            medians.append(med)
            scatters.append(1.4826 * float(np.median(np.abs(logr[sel] - med))))
            weights.append(np.sqrt(sel.sum()))
    if len(centres) >= 2:
        size_slope, intercept = np.polyfit(np.array(centres) - m_hi, medians, 1, w=weights)
        scatter = float(np.median(scatters))
    else:
        size_slope = 0.0
        intercept = float(np.median(logr)) if logr.size else float(np.log10(max(psf_hlr_pix, 1e-3)))
        scatter = 1.4826 * float(np.median(np.abs(logr - intercept))) if logr.size else 0.0
    log_r_max = float(np.percentile(logr, 99)) if logr.size else float(intercept)

    s2 = psf_sigma_pix ** 2
    resolved = sized & (a ** 2 > 2.0 * s2)
    q_values = np.sqrt(np.maximum(b[resolved] ** 2 - s2, 0.0) / (a[resolved] ** 2 - s2))
    if q_values.size < 20:
        q_values = np.empty(0)
    return ObservedPopulation(slope=float(slope), slope_err=float(slope_err), fit_mag_lo=float(m_lo),
                              fit_mag_hi=float(m_hi), n_fit=int(in_fit.sum()), turnover_mag=float(turnover),
                              size_mag_ref=float(m_hi), size_intercept=float(intercept),
                              size_slope=float(size_slope), size_scatter_dex=float(scatter),
                              log_r_max=log_r_max, psf_hlr_pix=float(psf_hlr_pix),
                              q_values=np.clip(q_values, 0.0, 1.0))
