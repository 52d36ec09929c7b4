"""Predicted detection probability of a point source on white Gaussian noise.

A pure-numerics module: functions of arrays and parameters, no I/O.  The peak-pixel closed form
(:func:`detection_probability`), its Monte Carlo extension to other pixels, MINAREA and
correlated noise (:func:`detection_probability_mc`), for a Gaussian or Moffat PSF.  The
derivation, its assumptions and the measured size of each correction: ``docs/analytic.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage, optimize, signal, special

from comest_bayes.constants import FWHM_PER_SIGMA
from comest_bayes.errors import InputError
from comest_bayes.seeding import Stream, rng_for

__all__ = [
    "AnalyticPrediction",
    "PSF_SHAPES",
    "DEFAULT_MOFFAT_BETA",
    "MOFFAT_STAMP_FRACTION",
    "MAX_HALF_SIZE",
    "kernel_norm",
    "moffat_alpha",
    "enclosed_flux",
    "default_half_size",
    "psf_image",
    "filtered_peak",
    "filtered_noise_covariance",
    "peak_probability",
    "detection_probability",
    "detection_probability_mc",
    "noise_autocorrelation",
    "correlated_noise_kernel",
    "predicted_m50",
    "predict",
]

_FWHM_TO_SIGMA = 1.0 / FWHM_PER_SIGMA

#: PSF profiles the prediction knows: ``psf=`` of the public functions.
PSF_SHAPES = ("gaussian", "moffat")
#: Moffat beta used when none is given: the beta a run injects when the image's stars give none
#: (:data:`comest_bayes.inject.psfmodel.DEFAULT_MOFFAT_BETA`; a run records the beta it used in
#: ``run.json``, ``psf.beta``).
DEFAULT_MOFFAT_BETA = 3.0
#: A default Moffat stamp's inscribed circle holds at least this fraction of the flux.
MOFFAT_STAMP_FRACTION = 0.999
#: Largest default stamp half-size, pixels (the injector's ``MAX_PSF_RADIUS_PIX``); a Moffat of
#: FWHM 3 px reaches it for beta < ~1.7.
MAX_HALF_SIZE = 256
#: Gauss-Legendre points per axis of a pixel for the pixel-integrated Moffat (relative error < 1e-10
#: for FWHM >= 1 px; measured against 64 points).
_PIXEL_QUADRATURE = 12


def _kernel(kernel) -> np.ndarray:
    """The kernel as a float64 array normalised to unit sum (a delta for None)."""
    if kernel is None:
        return np.ones((1, 1))
    k = np.asarray(kernel, dtype=np.float64)
    if k.ndim != 2 or k.shape[0] % 2 == 0 or k.shape[1] % 2 == 0:
        raise InputError(f"the filter kernel must be a 2-D array with odd sides, got shape {k.shape}.")
    total = k.sum()
    if not (np.all(np.isfinite(k)) and total > 0):
        raise InputError(f"the filter kernel must be finite with a positive sum, got sum {total}.")
    return k / total


def _check_positive(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = math.nan
    if not (math.isfinite(v) and v > 0):
        raise InputError(f"{name} must be a finite positive number, got {value!r}.")
    return v


def _check_psf(psf, moffat_beta) -> tuple[str, float]:
    """The validated ``(psf, moffat_beta)``; beta is checked only for a Moffat."""
    name = psf.strip().lower() if isinstance(psf, str) else psf
    if name not in PSF_SHAPES:
        raise InputError(f"psf must be one of {PSF_SHAPES}, got {psf!r}; pass the run's injection.psf "
                         f"('moffat' in a default run, with moffat_beta = injection.moffat_beta).")
    if name == "gaussian":
        return name, float("nan")
    try:
        beta = float(moffat_beta)
    except (TypeError, ValueError):
        beta = math.nan
    if not (math.isfinite(beta) and beta > 1.1):
        raise InputError(f"moffat_beta must be a finite number > 1.1 (as injection.moffat_beta; GalSim needs a "
                         f"truncation below), got {moffat_beta!r}; use the run's injection.moffat_beta, "
                         f"default {DEFAULT_MOFFAT_BETA}.")
    return name, beta


def moffat_alpha(fwhm_pix: float, beta: float) -> float:
    """Core radius ``alpha`` of a Moffat profile of the given FWHM (GalSim's ``scale_radius``).

    Parameters
    ----------
    fwhm_pix : float
        FWHM, pixels.
    beta : float
        Moffat index (> 1.1).

    Returns
    -------
    float
        ``alpha = FWHM / (2 sqrt(2^(1/beta) - 1))``, pixels (2.942 px for FWHM 3 px, beta 3).
    """
    fwhm = _check_positive("fwhm_pix", fwhm_pix)
    _, b = _check_psf("moffat", beta)
    return fwhm / (2.0 * math.sqrt(2.0 ** (1.0 / b) - 1.0))


def enclosed_flux(radius_pix, fwhm_pix: float, *, psf: str = "gaussian",
                  moffat_beta: float = DEFAULT_MOFFAT_BETA) -> np.ndarray:
    """Fraction of a unit-flux PSF's light inside a circle about its centre.

    Parameters
    ----------
    radius_pix : float or array_like
        Radii, pixels (>= 0).
    fwhm_pix : float
        FWHM of the PSF, pixels.
    psf : {"gaussian", "moffat"}, default "gaussian"
        Profile (see :func:`psf_image`).
    moffat_beta : float, default :data:`DEFAULT_MOFFAT_BETA`
        Moffat index; ignored for the Gaussian.

    Returns
    -------
    ndarray, shape of ``radius_pix``
        Gaussian ``1 - exp(-R^2 / (2 s^2))``; Moffat ``1 - (1 + (R / alpha)^2)^(1 - beta)``
        (of the continuous, untruncated profile).
    """
    shape, beta = _check_psf(psf, moffat_beta)
    fwhm = _check_positive("fwhm_pix", fwhm_pix)
    r = np.asarray(radius_pix, dtype=np.float64)
    if not np.all(np.isfinite(r) & (r >= 0)):
        raise InputError("radius_pix must be finite and >= 0 (pixels).")
    if shape == "gaussian":
        s = fwhm * _FWHM_TO_SIGMA
        return -np.expm1(-0.5 * (r / s) ** 2)
    a = moffat_alpha(fwhm, beta)
    return -np.expm1((1.0 - beta) * np.log1p((r / a) ** 2))


def default_half_size(fwhm_pix: float, *, psf: str = "gaussian", moffat_beta: float = DEFAULT_MOFFAT_BETA) -> int:
    """Half-size ``h`` of the ``(2 h + 1)^2`` stamp of :func:`psf_image` when none is given.

    Gaussian: ``ceil(4 FWHM) + 2`` (the stamp holds all but ~1e-19 of the flux).
    Moffat: the larger of that and ``ceil(R)``, with ``R`` the radius enclosing
    :data:`MOFFAT_STAMP_FRACTION` (0.999) of the flux,
    ``R = alpha sqrt((1 - 0.999)^(1 / (1 - beta)) - 1)``; ``R`` is capped at
    :data:`MAX_HALF_SIZE` pixels (reached for beta < ~1.7 at FWHM 3 px, where
    the stamp holds less: :func:`enclosed_flux` of ``h`` gives the fraction).
    For FWHM 3 px: beta 3 -> ``h = 17`` (16.3 px holds 0.999); beta 2.5 -> 27;
    beta 4.5 -> 14 (the Gaussian's ``ceil(4 FWHM) + 2``).

    Parameters
    ----------
    fwhm_pix : float
        FWHM, pixels.
    psf, moffat_beta
        As for :func:`enclosed_flux`.

    Returns
    -------
    int
        Pixels.
    """
    shape, beta = _check_psf(psf, moffat_beta)
    fwhm = _check_positive("fwhm_pix", fwhm_pix)
    h = int(math.ceil(4.0 * fwhm) + 2)
    if shape == "moffat":
        e = math.log1p(-MOFFAT_STAMP_FRACTION) / (1.0 - beta)  # log(1 + (R / alpha)^2)
        radius = moffat_alpha(fwhm, beta) * math.sqrt(math.expm1(e)) if e < 700.0 else math.inf
        h = max(h, int(math.ceil(min(radius, MAX_HALF_SIZE))))
    return h


def kernel_norm(kernel) -> float:
    """``||k||_2`` of the unit-sum kernel: the filtered noise sigma of unit white noise.

    Parameters
    ----------
    kernel : array_like, shape (ky, kx), or None
        Detection kernel (any positive normalisation; it is rescaled to unit
        sum as SEP and SExtractor do).  None means no filtering (norm 1).

    Returns
    -------
    float
        0.375 for SExtractor's 3x3 ``default.conv``.
    """
    k = _kernel(kernel)
    return float(np.sqrt(np.sum(k * k)))


def psf_image(fwhm_pix: float, dx: float = 0.0, dy: float = 0.0, *, half_size: int | None = None,
              pixel_integrated: bool = False, psf: str = "gaussian",
              moffat_beta: float = DEFAULT_MOFFAT_BETA) -> np.ndarray:
    """Unit-flux circular PSF (Gaussian or Moffat) on a pixel grid.

    Parameters
    ----------
    fwhm_pix : float
        FWHM of the PSF, pixels.
    dx, dy : float
        Offset of the source centre from the centre of the middle pixel, pixels.
    half_size : int, optional
        The grid is ``2 h + 1`` pixels on a side; default
        :func:`default_half_size`: ``ceil(4 FWHM) + 2`` for the Gaussian, and
        for the Moffat at least the radius holding 99.9% of the flux (h = 17
        for FWHM 3 px and beta 3), at most 256.
    pixel_integrated : bool, default False
        False: the profile sampled at pixel centres (GalSim ``no_pixel``, as
        :mod:`comest_bayes.inject.render` renders an effective PSF); True: the
        profile integrated over each pixel (exact for the Gaussian; for the
        Moffat a 12 x 12-point Gauss-Legendre rule per pixel, relative error
        < 1e-10 for FWHM >= 1 px).
    psf : {"gaussian", "moffat"}, default "gaussian"
        ``"gaussian"``: ``exp(-r^2 / (2 s^2)) / (2 pi s^2)``,
        ``s = FWHM / (2 sqrt(2 ln 2))``.  ``"moffat"``: the profile of
        ``galsim.Moffat(beta=moffat_beta, fwhm=fwhm_pix)`` as
        :func:`comest_bayes.inject.psfmodel.make_psf` builds it for a default run,
        ``(beta - 1) / (pi alpha^2) (1 + (r / alpha)^2)^(-beta)`` with
        ``alpha`` = :func:`moffat_alpha`: unit flux *of the untruncated
        profile* (GalSim's ``trunc=0``; the stamp is not renormalised, so it
        sums to the fraction of the light it holds, >= 0.999 with the default
        half-size, less when ``half_size`` is given smaller).
    moffat_beta : float, default :data:`DEFAULT_MOFFAT_BETA` (3.0; a run's is ``psf.beta`` in its ``run.json``)
        Moffat index (> 1.1); ignored for the Gaussian.

    Returns
    -------
    ndarray, shape (2 h + 1, 2 h + 1), float64
        Rows are y, columns x; pixel values are flux per pixel for unit total
        flux (pixel^-1 when sampled).

    Notes
    -----
    The sampled Moffat equals GalSim's ``drawImage(method="no_pixel")`` of the
    same profile to < 1e-14 of the peak within GalSim's ``maxR`` (its
    real-space drawing sets pixels to zero beyond the radius outside which
    1e-5 of the flux lies: 52 px for FWHM 3 px and beta 3, 19 px for beta
    4.5, where the profile is < 1e-6 of the peak).  The injector
    (:class:`comest_bayes.inject.render.StampRenderer`) computes the same samples
    by FFT from GalSim's transform of the untruncated Moffat, which GalSim
    cuts at ``maxk`` (``maxk_threshold`` 1e-3), and crops them to a stamp
    holding 99.5% of the flux: its point-source stamps differ from these
    samples by < 1.5e-3 of the peak and their filtered peak by < 3e-4
    (0.0003 mag) for beta 2.5-4.5 at FWHM 3 px.  The pixel-integrated Moffat
    equals GalSim's ``method="real_space"`` drawing to < 1e-12 of the peak.
    """
    shape, beta = _check_psf(psf, moffat_beta)
    fwhm = _check_positive("fwhm_pix", fwhm_pix)
    if half_size is None:
        h = default_half_size(fwhm, psf=shape, moffat_beta=beta)
    else:
        h = int(half_size)
        if h < 0 or h != half_size:
            raise InputError(f"half_size must be a non-negative integer (pixels), got {half_size!r}.")
    dx, dy = float(dx), float(dy)
    if not (math.isfinite(dx) and math.isfinite(dy)):
        raise InputError(f"dx and dy must be finite offsets in pixels, got {dx!r}, {dy!r}.")
    r = np.arange(-h, h + 1, dtype=np.float64)
    if shape == "moffat":
        a = moffat_alpha(fwhm, beta)
        norm = (beta - 1.0) / (math.pi * a * a)
        if pixel_integrated:
            # Gauss-Legendre nodes t in (-1/2, 1/2) and weights summing to 1 per axis
            t, w = np.polynomial.legendre.leggauss(_PIXEL_QUADRATURE)
            t, w = 0.5 * t, 0.5 * w
            u = ((r[:, None] + t[None, :] - dx) / a) ** 2  # (2h+1, n): x of the nodes
            v = ((r[:, None] + t[None, :] - dy) / a) ** 2  # (2h+1, n): y of the nodes
            out = np.zeros((r.size, r.size))
            for i in range(t.size):  # one y node at a time: (2h+1)^2 n values in memory
                out += w[i] * ((1.0 + v[:, i, None, None] + u[None, :, :]) ** (-beta) @ w)
            return norm * out
        u = ((r - dx) / a) ** 2
        v = ((r - dy) / a) ** 2
        return norm * (1.0 + v[:, None] + u[None, :]) ** (-beta)
    s = fwhm * _FWHM_TO_SIGMA
    if pixel_integrated:
        def axis(off):
            return special.ndtr((r + 0.5 - off) / s) - special.ndtr((r - 0.5 - off) / s)
    else:
        def axis(off):
            return np.exp(-0.5 * ((r - off) / s) ** 2) / (math.sqrt(2.0 * math.pi) * s)
    return np.outer(axis(dy), axis(dx))


def _filtered(fwhm_pix, kernel, dx, dy, pixel_integrated, half_size=None, psf="gaussian",
              moffat_beta=DEFAULT_MOFFAT_BETA) -> np.ndarray:
    img = psf_image(fwhm_pix, dx, dy, half_size=half_size, pixel_integrated=pixel_integrated, psf=psf,
                    moffat_beta=moffat_beta)
    return signal.convolve2d(img, _kernel(kernel), mode="same")


def _peak_half_size(fwhm_pix, kernel, psf) -> int | None:
    """Stamp half-size for :func:`filtered_peak` (None: :func:`psf_image`'s default).

    The Moffat's default stamp can be large (513^2 for beta < ~1.7 at FWHM 3 px);
    the filtered values within ``ceil(4 FWHM) + 2`` pixels of the centre, where
    the peak is, only need the profile within the kernel's half-width more.
    """
    if psf != "moffat":
        return None
    k = _kernel(kernel)
    return int(math.ceil(4.0 * float(fwhm_pix)) + 2) + max(k.shape) // 2


def filtered_peak(fwhm_pix: float, kernel, dx: float = 0.0, dy: float = 0.0, *,
                  pixel_integrated: bool = False, psf: str = "gaussian",
                  moffat_beta: float = DEFAULT_MOFFAT_BETA) -> float:
    """``S(c)``: the largest pixel of the filtered image of a unit-flux point source.

    Parameters
    ----------
    fwhm_pix : float
        PSF FWHM, pixels.
    kernel : array_like or None
        Detection kernel (normalised to unit sum here).
    dx, dy : float
        Sub-pixel offset of the source centre, pixels.
    pixel_integrated : bool
        See :func:`psf_image`.
    psf : {"gaussian", "moffat"}, default "gaussian"
        PSF profile (see :func:`psf_image`).
    moffat_beta : float, default :data:`DEFAULT_MOFFAT_BETA`
        Moffat index; ignored for the Gaussian.

    Returns
    -------
    float
        Image units per unit flux (pixel^-1).  For FWHM 3 px and the default
        3x3 kernel, centred: 0.0738 (Gaussian), 0.0547 (Moffat, beta 3: more
        of its light is in the wings).
    """
    shape, beta = _check_psf(psf, moffat_beta)
    h = _peak_half_size(fwhm_pix, kernel, shape)
    return float(_filtered(fwhm_pix, kernel, dx, dy, pixel_integrated, half_size=h, psf=shape,
                           moffat_beta=beta).max())


def filtered_noise_covariance(kernel, offsets) -> np.ndarray:
    """Covariance of unit white noise after convolution with the kernel, between pixels.

    Parameters
    ----------
    kernel : array_like or None
        Detection kernel (unit sum).
    offsets : array_like of int, shape (K, 2)
        Pixel positions ``(dy, dx)``.

    Returns
    -------
    ndarray, shape (K, K)
        ``C[i, j] = sum_a k(a) k(a + o_i - o_j)`` (the kernel's
        autocorrelation at the lag between the pixels); ``C[i, i] = ||k||^2``.
    """
    k = _kernel(kernel)
    auto = signal.correlate2d(k, k, mode="full")
    cy, cx = k.shape[0] - 1, k.shape[1] - 1
    o = np.asarray(offsets, dtype=np.int64).reshape(-1, 2)
    lag = o[:, None, :] - o[None, :, :]
    iy, ix = lag[..., 0] + cy, lag[..., 1] + cx
    inside = (iy >= 0) & (iy < auto.shape[0]) & (ix >= 0) & (ix < auto.shape[1])
    out = np.zeros(lag.shape[:2])
    out[inside] = auto[iy[inside], ix[inside]]
    return out


def _offset_grid(n_sub: int, symmetric: bool) -> tuple[np.ndarray, np.ndarray]:
    """Midpoint grid of sub-pixel offsets (flattened dx, dy), uniform over the pixel.

    With a kernel symmetric under x -> -x, y -> -y and x <-> y reflections the
    quadrant ``[0, 1/2]^2`` represents the whole pixel.
    """
    if n_sub < 1:
        raise InputError(f"n_sub must be a positive integer, got {n_sub!r}.")
    if symmetric:
        g = (np.arange(n_sub) + 0.5) / (2.0 * n_sub)
    else:
        g = (np.arange(n_sub) + 0.5) / n_sub - 0.5
    dx, dy = np.meshgrid(g, g)
    return dx.ravel(), dy.ravel()


def _is_symmetric(kernel) -> bool:
    k = _kernel(kernel)
    return bool(np.allclose(k, k[::-1, :]) and np.allclose(k, k[:, ::-1]) and
                (k.shape[0] != k.shape[1] or np.allclose(k, k.T)))


def _mags(mag) -> np.ndarray:
    m = np.asarray(mag, dtype=np.float64)
    if not np.all(np.isfinite(m)):
        raise InputError("magnitudes must be finite.")
    return m


def peak_probability(mag, *, zeropoint: float, sigma: float, fwhm_pix: float, kernel, thresh: float,
                     dx: float = 0.0, dy: float = 0.0, pixel_integrated: bool = False, psf: str = "gaussian",
                     moffat_beta: float = DEFAULT_MOFFAT_BETA) -> np.ndarray:
    r"""Closed-form peak-pixel detection probability for one sub-pixel position.

    ``p = Phi(F S(c) / (sigma ||k||) - thresh / ||k||)`` with
    ``F = 10**(-0.4 (m - zeropoint))``.

    Parameters
    ----------
    mag : float or array_like
        Magnitudes.
    zeropoint : float
        Magnitude zero point.
    sigma : float
        White-noise standard deviation per pixel, image units.
    fwhm_pix : float
        PSF FWHM, pixels.
    kernel : array_like or None
        Detection kernel (unit sum after normalisation).
    thresh : float
        DETECT_THRESH (units of the unfiltered sigma).
    dx, dy : float
        Sub-pixel offset of the source centre.
    pixel_integrated : bool
        See :func:`psf_image`.
    psf : {"gaussian", "moffat"}, default "gaussian"
        PSF profile (see :func:`psf_image`); ``"moffat"`` for a default run.
    moffat_beta : float, default :data:`DEFAULT_MOFFAT_BETA`
        Moffat index (the run's ``injection.moffat_beta``); ignored for the Gaussian.

    Returns
    -------
    ndarray, shape of ``mag``
    """
    m = _mags(mag)
    sig = _check_positive("sigma", sigma)
    t = _check_positive("thresh", thresh)
    kn = kernel_norm(kernel)
    s = filtered_peak(fwhm_pix, kernel, dx, dy, pixel_integrated=pixel_integrated, psf=psf,
                      moffat_beta=moffat_beta)
    flux = 10.0 ** (-0.4 * (m - zeropoint))
    return special.ndtr(flux * s / (sig * kn) - t / kn)


def detection_probability(mag, *, zeropoint: float, sigma: float, fwhm_pix: float, kernel, thresh: float,
                          n_sub: int = 8, pixel_integrated: bool = False, psf: str = "gaussian",
                          moffat_beta: float = DEFAULT_MOFFAT_BETA) -> np.ndarray:
    """Peak-pixel detection probability averaged over a uniform sub-pixel centre.

    Parameters
    ----------
    mag : float or array_like
        Magnitudes.
    zeropoint, sigma, fwhm_pix, kernel, thresh, pixel_integrated, psf, moffat_beta
        As for :func:`peak_probability`.
    n_sub : int, default 8
        Midpoints per axis of the sub-pixel grid (over a quadrant of the pixel
        when the kernel is symmetric, else the whole pixel).  The average
        changes by < 1e-4 between 8 and 16 for FWHM >= 1.5 px.

    Returns
    -------
    ndarray, shape of ``mag``
    """
    m = _mags(mag)
    sig = _check_positive("sigma", sigma)
    t = _check_positive("thresh", thresh)
    kn = kernel_norm(kernel)
    dxs, dys = _offset_grid(int(n_sub), _is_symmetric(kernel))
    peaks = np.array([filtered_peak(fwhm_pix, kernel, a, b, pixel_integrated=pixel_integrated, psf=psf,
                                    moffat_beta=moffat_beta)
                      for a, b in zip(dxs, dys)])
    flux = 10.0 ** (-0.4 * (m - zeropoint))
    nu = flux[..., None] * peaks / (sig * kn)
    return special.ndtr(nu - t / kn).mean(axis=-1)


def noise_autocorrelation(residual, good=None, *, max_lag: int = 3) -> np.ndarray:
    """Normalised autocorrelation of an image's pixel noise, for lags up to ``max_lag`` pixels.

    Parameters
    ----------
    residual : ndarray, shape (ny, nx)
        Background-subtracted image, image units.
    good : ndarray of bool, shape (ny, nx), optional
        Pixels that hold only noise (e.g. unmasked, outside every detection's
        segment); default every finite pixel.
    max_lag : int
        Largest lag along each axis, pixels.

    Returns
    -------
    ndarray, shape (2 max_lag + 1, 2 max_lag + 1)
        ``acf[max_lag + dy, max_lag + dx]`` = mean of ``r(p) r(p + (dy, dx))``
        over pairs of good pixels, divided by the mean of ``r(p)^2``; 1 at
        the centre, symmetric through it.  White noise gives 0 elsewhere
        (within ``1 / sqrt(npairs)``).
    """
    r = np.asarray(residual, dtype=float)
    if r.ndim != 2:
        raise InputError(f"residual must be a 2-D image; got shape {r.shape}.")
    g = np.isfinite(r) if good is None else (np.asarray(good, dtype=bool) & np.isfinite(r))
    if g.shape != r.shape:
        raise InputError(f"good has shape {g.shape} but the residual {r.shape}.")
    L = int(max_lag)
    if L < 1 or 2 * L + 1 > min(r.shape):
        raise InputError(f"max_lag = {max_lag!r} must be >= 1 and leave the image wider than 2 max_lag + 1.")
    if g.sum() < 100:
        raise InputError(f"only {int(g.sum())} noise pixels: too few to measure the noise correlation.")
    r = np.where(g, r, 0.0)
    gf = g.astype(float)
    ny, nx = r.shape
    var = float(np.sum(r * r) / gf.sum())
    acf = np.zeros((2 * L + 1, 2 * L + 1))
    for dy in range(0, L + 1):
        for dx in range(-L, L + 1):
            if dy == 0 and dx < 0:
                continue
            ys = slice(dy, ny), slice(0, ny - dy)
            xs = (slice(dx, nx), slice(0, nx - dx)) if dx >= 0 else (slice(0, nx + dx), slice(-dx, nx))
            a, b = r[ys[0], xs[0]], r[ys[1], xs[1]]
            n = float(np.sum(gf[ys[0], xs[0]] * gf[ys[1], xs[1]]))
            value = float(np.sum(a * b) / n / var) if n > 0 else 0.0
            acf[L + dy, L + dx] = acf[L - dy, L - dx] = value
    acf[L, L] = 1.0
    return acf


def correlated_noise_kernel(acf) -> np.ndarray:
    """A kernel ``c`` whose white-noise convolution has the autocorrelation ``acf`` (unit variance).

    ``c`` is the real, centred inverse Fourier transform of the square root of
    the power spectrum of ``acf`` (negative powers, from measurement noise,
    set to 0), on a grid twice the size of ``acf``, normalised to
    ``sum(c^2) = 1``; white noise convolved with it has the autocorrelation
    ``acf`` up to the lags ``acf`` covers.

    Parameters
    ----------
    acf : ndarray, shape (2 L + 1, 2 L + 1)
        Normalised autocorrelation (1 at the centre), e.g. from
        :func:`noise_autocorrelation`.

    Returns
    -------
    ndarray, shape (4 L + 1, 4 L + 1)
    """
    a = np.asarray(acf, dtype=float)
    if a.ndim != 2 or a.shape[0] != a.shape[1] or a.shape[0] % 2 != 1:
        raise InputError(f"acf must be a square array of odd size; got shape {a.shape}.")
    L = a.shape[0] // 2
    n = 4 * L + 1
    grid = np.zeros((n, n))
    grid[L:L + 2 * L + 1, L:L + 2 * L + 1] = a
    power = np.fft.fft2(np.fft.ifftshift(grid)).real
    root = np.sqrt(np.clip(power, 0.0, None))
    c = np.fft.fftshift(np.fft.ifft2(root).real)
    norm = math.sqrt(float(np.sum(c * c)))
    if not norm > 0:
        raise InputError("acf has no positive power: it is not an autocorrelation.")
    return c / norm


def detection_probability_mc(mag, *, zeropoint: float, sigma: float, fwhm_pix: float, kernel, thresh: float,
                             minarea: int = 1, seed: int, nsamples: int = 4000, n_sub: int = 4,
                             radius: float = 1.5, patch: int = 4, pixel_integrated: bool = False,
                             psf: str = "gaussian", moffat_beta: float = DEFAULT_MOFFAT_BETA,
                             noise_acf=None) -> np.ndarray:
    """Detection probability with every pixel and DETECT_MINAREA, by Monte Carlo over the noise.

    The event: on the filtered image (source plus filtered white noise), a
    group of 8-connected pixels above ``thresh * sigma`` with at least
    ``minarea`` pixels contains a pixel within ``radius`` pixels of the source
    centre.  Evaluated on a ``(2 patch + 1)^2`` patch around the pixel holding
    the centre (groups are cut at the patch edge, which only matters for
    ``minarea`` comparable to the patch), averaged over a sub-pixel grid.

    Parameters
    ----------
    mag : float or array_like
        Magnitudes.
    zeropoint, sigma, fwhm_pix, kernel, thresh, pixel_integrated, psf, moffat_beta
        As for :func:`peak_probability`.
    minarea : int, default 1
        DETECT_MINAREA.
    seed : int
        Seed of the noise draws (one set of ``nsamples`` filtered-noise
        patches shared by every magnitude and offset: common random numbers).
    nsamples : int, default 4000
        Noise patches; the standard error of a probability is
        ``sqrt(p (1 - p) / nsamples)`` at most (0.008 at 4000).
    n_sub : int, default 4
        Sub-pixel grid points per axis (see :func:`detection_probability`).
    radius : float, default 1.5
        Pixels within this distance (pixels) of the source centre count as
        "at the source" (a detection there is matched to the injection).
    patch : int, default 4
        Half-size of the patch, pixels.
    noise_acf : ndarray, optional
        Normalised autocorrelation of the pixel noise
        (:func:`noise_autocorrelation`); default white noise.  The per-pixel
        standard deviation stays ``sigma``, and so does the threshold.

    Returns
    -------
    ndarray, shape of ``mag``
    """

    m = _mags(mag)
    sig = _check_positive("sigma", sigma)
    t = _check_positive("thresh", thresh)
    fwhm = _check_positive("fwhm_pix", fwhm_pix)
    shape, beta = _check_psf(psf, moffat_beta)
    if int(minarea) < 1:
        raise InputError(f"minarea must be >= 1, got {minarea!r}.")
    if int(nsamples) < 10:
        raise InputError(f"nsamples must be >= 10, got {nsamples!r}.")
    k = _kernel(kernel)
    h = int(patch)
    # white noise on a patch padded by the kernel half-width, convolved: exact filtered noise on the patch
    ky, kx = k.shape[0] // 2, k.shape[1] // 2
    rng = rng_for(seed, Stream.ANALYTIC_NOISE)
    if noise_acf is None:
        white = rng.standard_normal((int(nsamples), 2 * (h + ky) + 1, 2 * (h + kx) + 1))
        noise = np.stack([signal.convolve2d(w, k, mode="valid") for w in white])  # (n, 2h+1, 2h+1), unit sigma
    else:  # correlated pixel noise of unit sigma, then the detection filter
        c = correlated_noise_kernel(noise_acf)
        cy = c.shape[0] // 2
        white = rng.standard_normal((int(nsamples), 2 * (h + ky + cy) + 1, 2 * (h + kx + cy) + 1))
        noise = np.stack([signal.convolve2d(signal.convolve2d(w, c, mode="valid"), k, mode="valid")
                          for w in white])
    dxs, dys = _offset_grid(int(n_sub), _is_symmetric(kernel))
    r = np.arange(-h, h + 1, dtype=np.float64)
    flux = np.atleast_1d(10.0 ** (-0.4 * (m - zeropoint))).ravel()
    structure = np.zeros((3, 3, 3), bool)
    structure[1] = True  # 8-connectivity within a patch, none across samples
    out = np.zeros(flux.size)
    # the filtered profile on the patch needs the PSF within the kernel's reach of it (exact samples;
    # the Moffat's wings beyond do not enter)
    half = max(int(math.ceil(4.0 * fwhm) + 2), ky + 1, kx + 1) + h
    for a, b in zip(dxs, dys):
        prof = _filtered(fwhm, k, a, b, pixel_integrated, half_size=half, psf=shape, moffat_beta=beta)
        c = prof.shape[0] // 2
        prof = prof[c - h:c + h + 1, c - h:c + h + 1] / sig  # per unit flux, in units of sigma
        near = (r[:, None] - b) ** 2 + (r[None, :] - a) ** 2 <= radius ** 2
        for i, f in enumerate(flux):
            above = (f * prof)[None] + noise > t
            if minarea == 1:
                hit = (above & near[None]).any(axis=(1, 2))
            else:
                labels, nlab = ndimage.label(above, structure=structure)
                sizes = np.bincount(labels.ravel(), minlength=nlab + 1)
                big = sizes >= int(minarea)
                big[0] = False
                hit = (big[labels] & near[None]).any(axis=(1, 2))
            out[i] += hit.mean()
    out /= len(dxs)
    return out.reshape(m.shape)


def predicted_m50(prob, *, lo: float, hi: float, level: float = 0.5, xtol: float = 1e-4) -> float:
    """Magnitude where a decreasing probability curve crosses ``level``.

    Parameters
    ----------
    prob : callable
        ``prob(m: float) -> float``, decreasing in ``m``.
    lo, hi : float
        Bracket: ``prob(lo) > level > prob(hi)``.
    level : float, default 0.5
    xtol : float, default 1e-4
        Tolerance in magnitude.

    Raises
    ------
    InputError
        When the bracket does not contain the crossing.
    """
    a, b = float(prob(lo)) - level, float(prob(hi)) - level
    if not (a > 0 > b):
        raise InputError(f"the probability curve does not cross {level} between m = {lo} ({a + level:.3g}) "
                         f"and m = {hi} ({b + level:.3g}); widen the bracket.")
    return float(optimize.brentq(lambda x: float(prob(x)) - level, lo, hi, xtol=xtol))


@dataclass(frozen=True)
class AnalyticPrediction:
    """Predicted completeness of a point source on white noise (see :func:`predict`).

    Attributes
    ----------
    m50_centred : float
        Closed form for a source centred on a pixel: ``ZP - 2.5 log10(t sigma / S(0))``.
    m50_peak : float
        Peak-pixel formula averaged over sub-pixel positions.
    m50_mc : float or None
        Monte Carlo with every pixel near the source and ``minarea`` (None when not computed).
    width_mag : float
        Probit width of the centred closed form linearised at m50: ``2.5 / (ln 10 nu_t)`` mag,
        ``nu_t = thresh / ||k||``.
    nu_thresh : float
        Threshold in units of the filtered noise, ``thresh / ||k||``.
    kernel_norm : float
        ``||k||_2``.
    peak_centred : float
        ``S(0)``, filtered peak per unit flux of a centred source.
    psf : str
        PSF profile of the prediction, ``"gaussian"`` or ``"moffat"``.
    moffat_beta : float or None
        Moffat index (None for the Gaussian).
    """

    m50_centred: float
    m50_peak: float
    m50_mc: float | None
    width_mag: float
    nu_thresh: float
    kernel_norm: float
    peak_centred: float
    psf: str = "gaussian"
    moffat_beta: float | None = None


def predict(*, zeropoint: float, sigma: float, fwhm_pix: float, kernel, thresh: float, minarea: int = 1,
            mc: bool = True, seed: int = 0, nsamples: int = 4000, radius: float = 1.5,
            pixel_integrated: bool = False, psf: str = "gaussian",
            moffat_beta: float = DEFAULT_MOFFAT_BETA, noise_acf=None) -> AnalyticPrediction:
    """The three m50 predictions of a point-source set-up (centred, peak-averaged, Monte Carlo).

    Parameters are those of :func:`detection_probability_mc`; ``mc=False``
    skips the Monte Carlo (``m50_mc`` is then None).  For a default run pass
    ``psf="moffat"`` (and ``moffat_beta`` = the run's
    ``injection.moffat_beta`` if it is not 3): at FWHM 3 px, the default
    kernel and thresh 1.5 the beta = 3 Moffat's m50 is 0.32 mag (closed
    form) and 0.29 mag (Monte Carlo, minarea 5) brighter than the Gaussian's
    (``docs/analytic.md``).

    Returns
    -------
    AnalyticPrediction
    """
    shape, beta = _check_psf(psf, moffat_beta)
    kn = kernel_norm(kernel)
    s0 = filtered_peak(fwhm_pix, kernel, pixel_integrated=pixel_integrated, psf=shape, moffat_beta=beta)
    sig = _check_positive("sigma", sigma)
    t = _check_positive("thresh", thresh)
    m_c = zeropoint - 2.5 * math.log10(t * sig / s0)
    common = dict(zeropoint=zeropoint, sigma=sig, fwhm_pix=fwhm_pix, kernel=kernel, thresh=t,
                  pixel_integrated=pixel_integrated, psf=shape, moffat_beta=beta)
    m_p = predicted_m50(lambda x: detection_probability(x, **common), lo=m_c - 3.0, hi=m_c + 3.0)
    m_mc = None
    if mc:
        m_mc = predicted_m50(lambda x: detection_probability_mc(x, minarea=minarea, seed=seed, nsamples=nsamples,
                                                                radius=radius, noise_acf=noise_acf, **common),
                             lo=m_c - 3.0, hi=m_c + 3.0, xtol=1e-3)
    nu_t = t / kn
    return AnalyticPrediction(m50_centred=float(m_c), m50_peak=float(m_p), m50_mc=m_mc,
                              width_mag=2.5 / (math.log(10.0) * nu_t), nu_thresh=float(nu_t), kernel_norm=kn,
                              peak_centred=float(s0), psf=shape,
                              moffat_beta=None if shape == "gaussian" else beta)
