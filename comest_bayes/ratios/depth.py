"""Depth references that injection-recovery completeness is compared with.

Signal-to-noise limiting magnitudes (:func:`limiting_magnitude`, :func:`point_source_depth`), the
number-count histogram completeness (:func:`histogram_completeness`) and the predicted offset of
point-source m50 from the 5-sigma depth (:func:`m50_depth_offset`).  Formulas and sources:
``docs/depth.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from astropy.stats import poisson_conf_interval
from scipy.optimize import minimize_scalar
from scipy.special import ndtri

from comest_bayes.constants import FWHM_PER_SIGMA
from comest_bayes.errors import InputError
from comest_bayes.ratios.binned import first_crossing
from comest_bayes.sim.analytic import kernel_norm, predict, psf_image

__all__ = ["DepthOffset", "m50_depth_offset", "noise_equivalent_area", "point_source_depth_nea", "isophote_radius_pix", "limiting_magnitude", "point_source_depth", "HistogramCompleteness", "histogram_completeness"]

_LN10 = math.log(10.0)


def _positive(name, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = float("nan")
    if not (np.isfinite(v) and v > 0):
        raise InputError(f"{name} = {value!r} must be a positive, finite number.")
    return v


def limiting_magnitude(noise_sigma, zeropoint: float, *, aperture_diameter_pix: float, nsigma: float = 5.0,
                       reduce: str | None = None):
    """Magnitude of a source at ``nsigma`` times the noise in a circular aperture.

    ``m = zeropoint - 2.5 log10(nsigma * sigma * sqrt(pi) * d / 2)``; see
    ``docs/depth.md``.

    Parameters
    ----------
    noise_sigma : float or array_like
        Per-pixel noise standard deviation, image units (e.g.
        ``ImageData.noise`` or a background RMS map).  Non-positive or
        non-finite map pixels give NaN.
    zeropoint : float
        Magnitude zero point (mag of a flux of 1 image unit).
    aperture_diameter_pix : float
        Aperture diameter, pixels.
    nsigma : float
        Signal-to-noise ratio of the limit (default 5).
    reduce : {None, "median"}
        For a map: ``None`` returns the map of limiting magnitudes,
        ``"median"`` its median over valid pixels.

    Returns
    -------
    float or ndarray
        Limiting magnitude (a float for a scalar sigma or ``reduce="median"``;
        otherwise an array of the shape of ``noise_sigma``).
    """
    d = _positive("aperture_diameter_pix", aperture_diameter_pix)
    nsigma = _positive("nsigma", nsigma)
    zp = float(zeropoint)
    if not np.isfinite(zp):
        raise InputError(f"zeropoint = {zeropoint!r} must be finite; give the image a zero point (e.g. MAGZERO).")
    if reduce not in (None, "median"):
        raise InputError(f"reduce = {reduce!r} must be None (return the map) or 'median'.")
    sigma = np.asarray(noise_sigma, dtype=float)
    valid = np.isfinite(sigma) & (sigma > 0)
    if not np.any(valid):
        raise InputError("noise_sigma has no positive, finite value; pass the per-pixel noise standard deviation "
                         "(image units), e.g. the background RMS.")
    mag = np.full(sigma.shape, np.nan)
    mag[valid] = zp - 2.5 * np.log10(nsigma * sigma[valid] * math.sqrt(math.pi) * d / 2.0)
    if sigma.ndim == 0:
        return float(mag)
    if reduce == "median":
        return float(np.median(mag[valid]))
    return mag


def point_source_depth(sigma, zeropoint: float, fwhm_pix: float, nsigma: float = 5.0, *,
                       reduce: str | None = None):
    """Point-source limiting magnitude for optimal (PSF-fitting) photometry.

    Uses the noise-equivalent area ``4 pi sigma_psf**2`` of a Gaussian PSF,
    ``sigma_psf = fwhm_pix / (2 sqrt(2 ln 2))``:
    ``m = zeropoint - 2.5 log10(nsigma * sigma * 2 sqrt(pi) * sigma_psf)``.

    Parameters
    ----------
    sigma : float or array_like
        Per-pixel noise standard deviation, image units.
    zeropoint : float
        Magnitude zero point.
    fwhm_pix : float
        Seeing FWHM, pixels.
    nsigma : float
        Signal-to-noise ratio of the limit (default 5).
    reduce : {None, "median"}
        As in :func:`limiting_magnitude`.

    Returns
    -------
    float or ndarray
        The depth (e.g. the 5-sigma point-source depth m5).
    """
    fwhm = _positive("fwhm_pix", fwhm_pix)
    sigma_psf = fwhm / FWHM_PER_SIGMA
    # sqrt(4 pi) sigma_psf = sqrt(pi) d / 2 with d = 4 sigma_psf
    return limiting_magnitude(sigma, zeropoint, aperture_diameter_pix=4.0 * sigma_psf, nsigma=nsigma,
                              reduce=reduce)


def noise_equivalent_area(psf_image) -> float:
    """Noise-equivalent area ``1 / sum(p**2)`` of a pixelised PSF ``p`` (normalised here to unit sum).

    The optimal (PSF-weighted) flux of a point source on white noise of
    per-pixel sigma has error ``sigma * sqrt(NEA)``; for a Gaussian PSF
    ``NEA = 4 pi sigma_psf**2`` (the value :func:`point_source_depth` assumes).
    """
    p = np.asarray(psf_image, dtype=float)
    total = p.sum()
    if not np.isfinite(total) or total <= 0:
        raise ValueError("the PSF image must have a positive, finite sum")
    p = p / total
    return float(1.0 / np.sum(p * p))


def point_source_depth_nea(sigma, zeropoint: float, nea: float, nsigma: float = 5.0) -> float:
    """Point-source limiting magnitude ``zeropoint - 2.5 log10(nsigma * sigma * sqrt(nea))``.

    ``nea`` is the PSF's noise-equivalent area in pixels (:func:`noise_equivalent_area`);
    ``sigma`` a scalar per-pixel noise.
    """
    return float(zeropoint - 2.5 * np.log10(nsigma * float(sigma) * np.sqrt(_positive("nea", nea))))


def isophote_radius_pix(psf_image, flux, sigma: float, thresh: float, kernel=None) -> np.ndarray | float:
    """Radius (pixels) of the detection isophote of a point source: ``sqrt(npix / pi)``.

    ``npix`` counts the pixels where the source's image, filtered with the
    detection ``kernel`` (SEP's ``filter_type="conv"``; None for no filter),
    reaches ``thresh x sigma`` on flat noise ``sigma``: the area SEP gives the
    object on its own.  ``psf_image`` is the pixelised PSF, normalised here to
    unit sum; it must be large enough to hold the isophote (a radius at its
    edge is a lower bound).  ``flux`` may be an array.
    """
    p = np.asarray(psf_image, dtype=float)
    total = p.sum()
    if p.ndim != 2 or not np.isfinite(total) or total <= 0:
        raise ValueError("the PSF image must be 2-D with a positive, finite sum")
    p = p / total
    if kernel is not None:
        from scipy.signal import fftconvolve

        k = np.asarray(kernel, dtype=float)
        p = fftconvolve(p, k / k.sum(), mode="same")
    level = np.sort(p.ravel())[::-1]  # the profile's values, brightest first
    f = np.atleast_1d(np.asarray(flux, dtype=float))
    # pixels above thresh * sigma / flux, by a search in the descending profile
    npix = np.searchsorted(-level, -(_positive("thresh", thresh) * _positive("sigma", sigma) / f), side="right")
    out = np.sqrt(npix / np.pi)
    return out if np.ndim(flux) else float(out[0])


class DepthOffset(NamedTuple):
    """How far the point-source m50 of a detection set-up lies from the N-sigma optimal depth (mag).

    All terms are magnitudes; positive means m50 is *brighter* than the depth.
    They do not depend on the noise level or the zero point (both move m50
    and the depth together).  See ``docs/depth.md``.

    Attributes
    ----------
    total : float
        ``m_depth - m50``: the sum of the three terms below.
    filter_threshold : float
        ``m_depth - m50_centred``: a source centred on a pixel whose filtered
        peak pixel sits exactly at the threshold, against the optimal depth.
        ``2.5 log10(nsigma ||k|| / nu_t_opt)`` with the filter's efficiency
        ``S(0) sqrt(NEA) / ||k||`` (:attr:`filter_efficiency`).
    subpixel : float
        ``m50_centred - m50_peak``: injections fall anywhere within a pixel,
        and an off-centre source has a lower filtered peak.
    minarea : float
        ``m50_peak - m50_mc``: the Monte Carlo with every pixel near the
        source and ``DETECT_MINAREA`` (positive: the area cut costs depth;
        negative with ``minarea = 1``, where neighbours add chances).
    filter_efficiency : float
        Signal-to-noise of the filtered peak pixel over that of optimal (PSF-
        weighted) photometry, ``S(0) sqrt(NEA) / ||k||`` (1 for the matched
        filter, ~0.9 for the 3x3 default kernel at FWHM 3 px).
    nea_pix : float
        Noise-equivalent area of the PSF, pixels.
    """

    total: float
    filter_threshold: float
    subpixel: float
    minarea: float
    filter_efficiency: float
    nea_pix: float


def m50_depth_offset(*, fwhm_pix: float, kernel, thresh: float, minarea: int, nsigma: float = 5.0,
                     psf: str = "moffat", moffat_beta: float = 3.0, pixel_integrated: bool = False,
                     noise_acf=None, seed: int = 0, nsamples: int = 4000) -> DepthOffset:
    """Predicted ``m_depth - m50`` of point sources on white noise, split into its causes.

    ``m_depth`` is the ``nsigma`` optimal-photometry point-source depth that a
    run reports (``summary.json`` ``depth.point_source_5sigma``: the
    noise-equivalent area of the injected PSF, :func:`point_source_depth_nea`);
    m50 is where the detector (filter ``kernel``, ``thresh``, ``minarea``)
    finds half the point sources, predicted by
    :func:`comest_bayes.sim.analytic.predict`.  Both scale with the noise and the
    zero point in the same way, so their difference depends only on the PSF
    and the detection settings.

    Parameters
    ----------
    fwhm_pix, kernel, thresh, minarea, psf, moffat_beta, pixel_integrated, noise_acf, seed, nsamples
        As for :func:`comest_bayes.sim.analytic.predict` (``psf="moffat"``,
        beta 3 by default: what a run injects without fitted stars).
    nsigma : float
        Signal-to-noise of the depth (default 5).

    Returns
    -------
    DepthOffset
    """

    nsigma = _positive("nsigma", nsigma)
    fwhm = _positive("fwhm_pix", fwhm_pix)
    beta = float(moffat_beta)
    zp, sigma = 30.0, 1.0  # any: the offset does not depend on them
    pred = predict(zeropoint=zp, sigma=sigma, fwhm_pix=fwhm, kernel=kernel, thresh=thresh, minarea=minarea,
                   seed=seed, nsamples=nsamples, pixel_integrated=pixel_integrated, psf=psf, moffat_beta=beta,
                   noise_acf=noise_acf)
    nea = noise_equivalent_area(psf_image(fwhm, pixel_integrated=pixel_integrated, psf=psf, moffat_beta=beta))
    m_depth = point_source_depth_nea(sigma, zp, nea, nsigma)
    efficiency = pred.peak_centred * math.sqrt(nea) / kernel_norm(kernel)
    return DepthOffset(total=float(m_depth - pred.m50_mc), filter_threshold=float(m_depth - pred.m50_centred),
                       subpixel=float(pred.m50_centred - pred.m50_peak), minarea=float(pred.m50_peak - pred.m50_mc),
                       filter_efficiency=float(efficiency), nea_pix=float(nea))


@dataclass(frozen=True)
class HistogramCompleteness:
    """Completeness from the number-count histogram (:func:`histogram_completeness`).

    Attributes
    ----------
    slope, intercept : float
        ``b`` and ``a`` of ``log10 N(m) = a + b m``, with ``N`` the number of
        sources per magnitude (``b`` in dex per mag).
    slope_err, intercept_err : float
        One-sigma errors from the Fisher information of the Poisson fit.
    covariance : ndarray, shape (2, 2)
        Covariance of ``(intercept, slope)`` (inverse Fisher information);
        the variance of ``log10 n_model`` at magnitude ``m`` is
        ``[1, m] @ covariance @ [1, m]``.
    fit_range : (float, float)
        Magnitude range whose bins (by centre) were fitted.
    turnover : float
        Centre of the most populated bin, mag.
    edges : ndarray, shape (nbin + 1,)
        Bin edges, mag.
    centers : ndarray, shape (nbin,)
        Bin centres, mag.
    n_obs : ndarray of int64, shape (nbin,)
        Observed counts per bin.
    n_model : ndarray, shape (nbin,)
        Power-law counts per bin (the model integrated over the bin).
    completeness : ndarray, shape (nbin,)
        ``n_obs / n_model``, *not* clipped: noise (and a poor fit) can give
        values above 1 in the fit range.
    lower, upper : ndarray, shape (nbin,)
        Poisson interval of ``n_obs`` (frequentist-confidence) divided by
        ``n_model``; the model's own uncertainty is not included.
    fit_mask : ndarray of bool, shape (nbin,)
        Bins used in the fit.
    confidence : float
        Probability content of the interval.
    """

    slope: float
    intercept: float
    slope_err: float
    intercept_err: float
    covariance: np.ndarray
    fit_range: tuple
    turnover: float
    edges: np.ndarray
    centers: np.ndarray
    n_obs: np.ndarray
    n_model: np.ndarray
    completeness: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    fit_mask: np.ndarray
    confidence: float

    def magnitude_at(self, level: float = 0.5) -> float:
        """Magnitude where the completeness first drops below ``level`` (NaN if never)."""
        return first_crossing(self.centers, self.completeness, level)


def _log_bin_integral(b: float, lo: np.ndarray, hi: np.ndarray):
    """ln of the integral of 10**(b m) over [lo, hi], and its derivative in b.

    Written as ``ln w + b ln10 c + ln(sinh(x)/x)`` with ``x = b ln10 w / 2``
    (``c`` centre, ``w`` width), which is stable at ``b = 0``.
    """
    w = hi - lo
    c = 0.5 * (hi + lo)
    x = 0.5 * b * _LN10 * w
    ax = np.abs(x)
    small = ax < 1e-4
    xs = np.where(small, 1.0, x)
    # ln(sinh(x)/x) = |x| + ln((1 - exp(-2|x|)) / (2|x|)), overflow-free
    axs = np.abs(xs)
    log_sinhc = np.where(small, x * x / 6.0, axs + np.log(-np.expm1(-2.0 * axs) / (2.0 * axs)))
    # d/dx ln(sinh(x)/x) = coth(x) - 1/x
    dlog_sinhc = np.where(small, x / 3.0, 1.0 / np.tanh(xs) - 1.0 / xs)
    value = np.log(w) + b * _LN10 * c + log_sinhc
    deriv = _LN10 * c + 0.5 * _LN10 * w * dlog_sinhc
    return value, deriv


def histogram_completeness(mags, edges, *, fit_range=None, turnover_offset: float = 1.0,
                           confidence: float = 0.6827) -> HistogramCompleteness:
    """Completeness from the detected number counts and a power-law extrapolation.

    The counts per bin ``n_obs`` are fitted by Poisson maximum likelihood
    with ``N(m) = 10**(a + b m)`` per magnitude, integrated over each bin,
    using the bins whose centres lie in ``fit_range``.  The completeness is
    ``n_obs / n_model`` in every bin.

    Parameters
    ----------
    mags : array_like, shape (N,)
        Measured magnitudes of the detected sources (non-finite ones are
        ignored).
    edges : array_like, shape (nbin + 1,)
        Magnitude bin edges.
    fit_range : (float, float), optional
        Magnitudes where the counts are complete.  Default: from the first
        bin edge to ``turnover_offset`` magnitudes brighter than the centre
        of the most populated bin (the turnover of the counts).
    turnover_offset : float
        See ``fit_range`` (default 1.0 mag).  A steep completeness roll-off
        tolerates a small offset; a gradual one needs a larger offset or an
        explicit ``fit_range``, because incompleteness inside the fit range
        flattens the slope.
    confidence : float
        Probability content of the Poisson intervals (default 0.6827).

    Returns
    -------
    HistogramCompleteness

    Raises
    ------
    InputError
        Fewer than 3 bins, or fewer than 10 sources, in the fit range.
    """
    e = np.asarray(edges, dtype=float)
    if e.ndim != 1 or e.size < 4 or not np.all(np.isfinite(e)) or np.any(np.diff(e) <= 0):
        raise InputError(f"edges must be at least 4 finite, strictly increasing magnitudes, got {np.asarray(edges)!r}.")
    m = np.asarray(mags, dtype=float)
    if m.ndim != 1:
        raise InputError(f"mags must be a 1-d array of magnitudes, got shape {m.shape}.")
    if not 0.0 < float(confidence) < 1.0:
        raise InputError(f"confidence = {confidence!r} must be a probability in (0, 1).")
    turnover_offset = float(turnover_offset)
    if not (np.isfinite(turnover_offset) and turnover_offset >= 0):
        raise InputError(f"turnover_offset = {turnover_offset!r} must be a non-negative number of magnitudes.")

    n_obs = np.histogram(m[np.isfinite(m)], bins=e)[0].astype(np.int64)
    centers = 0.5 * (e[:-1] + e[1:])
    turnover = float(centers[int(np.argmax(n_obs))])
    if fit_range is None:
        lo_fit, hi_fit = float(e[0]), turnover - turnover_offset
    else:
        try:
            lo_fit, hi_fit = (float(v) for v in fit_range)
        except (TypeError, ValueError):
            raise InputError(f"fit_range must be (bright, faint) magnitudes, got {fit_range!r}.") from None
        if not lo_fit < hi_fit:
            raise InputError(f"fit_range = {fit_range!r} must have bright < faint.")
    fit = (centers >= lo_fit) & (centers <= hi_fit)
    if fit.sum() < 3 or n_obs[fit].sum() < 10:
        raise InputError(
            f"the number-count fit range ({lo_fit:.2f}, {hi_fit:.2f}) holds {int(fit.sum())} bins and "
            f"{int(n_obs[fit].sum())} sources; at least 3 bins and 10 sources are needed.  Give a wider "
            f"fit_range, finer edges, or a smaller turnover_offset.")

    lo, hi, nf = e[:-1][fit], e[1:][fit], n_obs[fit].astype(float)
    total = nf.sum()

    def profile_nll(b):
        # With a profiled out (sum of model = sum of counts), the Poisson
        # -log L is, up to a constant, N ln(sum F_i) - sum n_i ln F_i.
        lf, _ = _log_bin_integral(b, lo, hi)
        top = lf.max()
        return total * (top + np.log(np.exp(lf - top).sum())) - np.dot(nf, lf)

    res = minimize_scalar(profile_nll, bounds=(-3.0, 3.0), method="bounded", options={"xatol": 1e-10})
    b = float(res.x)
    lf, dlf = _log_bin_integral(b, lo, hi)
    top = lf.max()
    log10_a = (math.log(total) - top - math.log(np.exp(lf - top).sum())) / _LN10
    a = float(log10_a)

    # Fisher information of Poisson counts: I = sum mu g g^T with
    # g = d ln mu / d(a, b) = (ln 10, d ln F / d b).
    mu = np.exp(a * _LN10 + lf)
    g = np.vstack([np.full_like(dlf, _LN10), dlf])
    fisher = (g * mu) @ g.T
    try:
        cov = np.linalg.inv(fisher)
    except np.linalg.LinAlgError:
        cov = np.full((2, 2), np.nan)
    a_err, b_err = float(np.sqrt(cov[0, 0])), float(np.sqrt(cov[1, 1]))

    lf_all, _ = _log_bin_integral(b, e[:-1], e[1:])
    n_model = np.exp(a * _LN10 + lf_all)
    sigma = float(ndtri(0.5 + 0.5 * float(confidence)))
    lo_hi = poisson_conf_interval(n_obs, interval="frequentist-confidence", sigma=sigma)
    comp = n_obs / n_model
    return HistogramCompleteness(
        slope=b, intercept=a, slope_err=b_err, intercept_err=a_err, covariance=cov, fit_range=(lo_fit, hi_fit),
        turnover=turnover, edges=e, centers=centers, n_obs=n_obs, n_model=n_model, completeness=comp,
        lower=lo_hi[0] / n_model, upper=lo_hi[1] / n_model, fit_mask=fit, confidence=float(confidence))
