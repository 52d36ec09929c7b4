"""The seeing FWHM, measured from the stars on the image, and the PSF that is injected.

:func:`estimate_fwhm` selects stars on the stellar locus, fits them with a pixel-integrated
Moffat and checks that they share one PSF; :func:`measure_seeing` falls back on the header
(:func:`seeing_from_header`); :func:`injection_psf` builds the injected PSF and
:func:`point_size_check` compares injections with stars.  Algorithm, keywords and the Moffat
profile: ``docs/detection.md`` ("Measuring the seeing").
"""

from __future__ import annotations

import math
import re
from dataclasses import asdict, dataclass, field
from typing import NamedTuple

import numpy as np
from scipy.optimize import least_squares

from comest_bayes.constants import FWHM_PER_SIGMA
from comest_bayes.detect.catalog import (FLAG_APER_TRUNC, FLAG_BLENDED, FLAG_DEBLEND_OVERFLOW, FLAG_EDGE, FLAG_MASKED, FLAG_SATURATED)
from comest_bayes.errors import InputError
from comest_bayes.inject.psfmodel import DEFAULT_MOFFAT_BETA, make_psf
from comest_bayes.inject.render import point_stamp_size

__all__ = ["FwhmEstimate", "estimate_fwhm", "select_stars", "fit_moffat", "moffat_image", "BAD_FLAGS",
           "BETA_RANGE", "HEADER_SEEING_KEYWORDS", "HeaderSeeing", "seeing_from_header", "measure_seeing",
           "injection_psf", "point_size_check", "empirical_psf"]

#: Catalog flags that disqualify a star candidate.
BAD_FLAGS = FLAG_MASKED | FLAG_BLENDED | FLAG_SATURATED | FLAG_EDGE | FLAG_APER_TRUNC | FLAG_DEBLEND_OVERFLOW
#: Range of the Moffat beta allowed in the fits.
BETA_RANGE = (1.5, 100.0)
#: Columns the star selection reads.
_COLUMNS = ("xwin", "ywin", "flux_radius", "snr_auto", "flags", "a", "b", "peak", "flux_auto")
#: Width (in ln flux_radius) of the kernel used to find the stellar locus.
_LOCUS_BANDWIDTH = 0.04
#: Half-width (in ln flux_radius) of the window searched around the locus.
_LOCUS_WINDOW = 0.15
#: Half-size of the stamps fitted, in units of the starting FWHM.  The fit's free constant sky
#: absorbs part of the wings in a small stamp and biases beta up when the wings are heavier than a
#: Moffat's; measured on the shared KiDS r image: median beta 2.17 at 3 FWHM, 2.10 at 4, 2.07 at 5,
#: 2.02 at 8 (FWHM 2.26-2.24 px), and injected point sources 5.4 %, 4.3 % and 3.8 % smaller than the
#: stars at 3, 4 and 5.  Larger stamps cost more than their area: least_squares' SVD of more than
#: ~1500 residuals runs multithreaded in OpenBLAS, 10-20 times slower on a busy machine.
_STAMP_HALF_FWHM = 4.0
#: Fitted FWHMs of stars agree within this (ln) half-width.
_FWHM_AGREEMENT = 0.03
#: Largest median deviation of the stars' ellipticities from their median: a floor for PSF
#: variation across the field plus a noise term times the median 1/SNR.
_ELL_SPREAD_FLOOR = 0.03
_ELL_SPREAD_NOISE = 1.2


@dataclass
class FwhmEstimate:
    """The measured seeing.

    Attributes
    ----------
    fwhm : float
        Seeing FWHM in pixels.
    fwhm_err : float
        Standard error of ``fwhm`` in pixels (that of a median:
        ``1.2533 * std / sqrt(nstars)``).
    nstars : int
        Number of stars whose fits entered the median.
    method : str
        One sentence saying how the stars were selected and fitted (stored
        in ``run.json`` and shown in reports).
    beta : float
        Median Moffat beta of the same stars (NaN when not measured).
    beta_at_bound : int
        How many of those stars' fitted beta lies at an end of
        :data:`BETA_RANGE` (within 1 %).
    star_flux_radius : float
        Median ``flux_radius`` (pixels, from the detection catalog) of those
        stars: the reference for the size of injected point sources
        (:func:`point_size_check`).
    star_rows : list of int
        Rows of the detection catalog of those stars.
    """

    fwhm: float
    fwhm_err: float
    nstars: int
    method: str
    beta: float = float("nan")
    beta_at_bound: int = 0
    star_flux_radius: float = float("nan")
    star_rows: list = field(default_factory=list)

    def as_dict(self) -> dict:
        """Plain-JSON form (NaN becomes None)."""
        out = asdict(self)
        out["fwhm"], out["fwhm_err"] = float(self.fwhm), float(self.fwhm_err)
        out["nstars"], out["beta_at_bound"] = int(self.nstars), int(self.beta_at_bound)
        out["star_rows"] = [int(r) for r in self.star_rows]
        for name in ("beta", "star_flux_radius"):
            value = float(getattr(self, name))
            out[name] = value if np.isfinite(value) else None
        return out


# ---------------------------------------------------------------------------------------------
# Moffat model
# ---------------------------------------------------------------------------------------------

def _subpixel_offsets(oversample: int) -> np.ndarray:
    return (np.arange(oversample) + 0.5) / oversample - 0.5


def moffat_image(shape, x0, y0, flux, fwhm, beta, sky=0.0, oversample: int = 3) -> np.ndarray:
    """A circular Moffat profile integrated over square pixels.

    Parameters
    ----------
    shape : (int, int)
        Stamp shape (ny, nx).
    x0, y0 : float
        Centre in pixel coordinates of the stamp (the centre of pixel
        ``[j, i]`` is ``(x, y) = (i, j)``).
    flux : float
        Total flux (image units).
    fwhm : float
        FWHM in pixels.
    beta : float
        Moffat beta (> 1).
    sky : float
        Constant added to every pixel.
    oversample : int
        Sub-pixels per pixel side of the midpoint-rule integration.

    Returns
    -------
    ndarray of float, shape ``shape``
        Pixel values (flux per pixel).
    """
    ny, nx = shape
    alpha2 = (fwhm / (2.0 * np.sqrt(2.0 ** (1.0 / beta) - 1.0))) ** 2
    amp = flux * (beta - 1.0) / (np.pi * alpha2)
    off = _subpixel_offsets(oversample)
    dy = (np.arange(ny)[:, None] + off[None, :]).ravel() - y0  # (ny*os,)
    dx = (np.arange(nx)[:, None] + off[None, :]).ravel() - x0  # (nx*os,)
    r2 = dy[:, None] ** 2 + dx[None, :] ** 2
    prof = amp * (1.0 + r2 / alpha2) ** (-beta)
    prof = prof.reshape(ny, oversample, nx, oversample).mean(axis=(1, 3))
    return prof + sky


@dataclass
class MoffatFit:
    """Result of one star's fit (pixel units of the full image)."""

    x: float
    y: float
    flux: float
    fwhm: float
    beta: float
    sky: float
    ok: bool
    reason: str = ""
    ellipticity: complex = complex(np.nan, np.nan)


def fit_moffat(stamp, x0, y0, fwhm0, *, valid=None, oversample: int = 3) -> MoffatFit:
    """Least-squares fit of :func:`moffat_image` to one stamp.

    Parameters
    ----------
    stamp : ndarray, shape (ny, nx)
        Background-subtracted pixels around the star.
    x0, y0 : float
        Starting centre in stamp pixel coordinates.
    fwhm0 : float
        Starting FWHM in pixels; the fit is bounded to [0.3, 3] times it.
    valid : ndarray of bool, shape (ny, nx), optional
        Pixels to fit (False: masked or belonging to a neighbour).
    oversample : int
        Sub-pixel sampling of the model.

    Returns
    -------
    MoffatFit
        Centre in stamp coordinates; ``ok`` False with a ``reason`` when the
        fit failed or ended on a bound.
    """
    stamp = np.asarray(stamp, dtype=float)
    valid = np.ones(stamp.shape, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    valid = valid & np.isfinite(stamp)
    total = float(np.sum(stamp[valid]))
    if not np.isfinite(total) or total <= 0:
        return MoffatFit(x0, y0, total, np.nan, np.nan, 0.0, False, "non-positive stamp flux")
    # Work in units of the stamp's flux: the optimiser's tolerances are absolute, and
    # images come in any unit (1e-9 maggies or 1e5 ADU).
    stamp = stamp / total
    flux0 = 1.0
    lo = np.array([x0 - 2.0, y0 - 2.0, 0.0, 0.3 * fwhm0, BETA_RANGE[0], -np.inf])
    hi = np.array([x0 + 2.0, y0 + 2.0, 10.0 * flux0, 3.0 * fwhm0, BETA_RANGE[1], np.inf])
    start = np.array([x0, y0, flux0, fwhm0, 3.0, 0.0])
    data = stamp[valid]

    def resid(p):
        return moffat_image(stamp.shape, *p, oversample=oversample)[valid] - data

    try:
        res = least_squares(resid, start, bounds=(lo, hi), x_scale="jac", method="trf", max_nfev=400)
    except (ValueError, FloatingPointError) as exc:  # degenerate stamp
        return MoffatFit(x0, y0, total, np.nan, np.nan, 0.0, False, f"fit error: {exc}")
    x, y, flux, fwhm, beta, sky = res.x
    flux, sky = flux * total, sky * total
    ok, reason = bool(res.success), "" if res.success else "no convergence"
    if ok and (fwhm <= 1.01 * lo[3] or fwhm >= 0.99 * hi[3]):
        ok, reason = False, "FWHM at a bound"
    if ok and (abs(x - x0) >= 1.99 or abs(y - y0) >= 1.99):
        ok, reason = False, "centre moved by 2 pixels"
    ell = _weighted_ellipticity(stamp - sky / total, valid, x, y, fwhm) if ok else complex(np.nan, np.nan)
    return MoffatFit(float(x), float(y), float(flux), float(fwhm), float(beta), float(sky), ok, reason, ell)


def _weighted_ellipticity(stamp, valid, x0, y0, fwhm) -> complex:
    """``((Qxx - Qyy) + 2i Qxy) / (Qxx + Qyy)`` of second moments with a circular Gaussian weight of this FWHM.

    All stars share the PSF's value (up to noise); galaxies scatter about it.
    """
    ny, nx = stamp.shape
    yy, xx = np.mgrid[0:ny, 0:nx]
    dx, dy = xx - x0, yy - y0
    sig = fwhm / FWHM_PER_SIGMA
    w = np.exp(-0.5 * (dx * dx + dy * dy) / (sig * sig)) * valid * stamp
    norm = w.sum()
    if not np.isfinite(norm) or norm <= 0:
        return complex(np.nan, np.nan)
    qxx, qyy, qxy = (w * dx * dx).sum() / norm, (w * dy * dy).sum() / norm, (w * dx * dy).sum() / norm
    trace = qxx + qyy
    return complex(qxx - qyy, 2.0 * qxy) / trace if trace > 0 else complex(np.nan, np.nan)


# ---------------------------------------------------------------------------------------------
# Star selection
# ---------------------------------------------------------------------------------------------

@dataclass
class StarSelection:
    """Indices of the star candidates and the locus they were taken from."""

    index: np.ndarray       # rows of the catalog, brightest first
    locus_radius: float     # flux_radius of the stellar locus, pixels
    locus_width: float      # robust scatter of ln(flux_radius) about it
    nbright: int            # sources that passed the flag / SNR / shape cuts
    snr_min: float
    max_ellipticity: float


def _locus_peak(logr: np.ndarray, min_members: int) -> float | None:
    """Centre (in ln r) of the smallest-radius significant peak of the ln r distribution."""
    grid = np.arange(logr.min() - 3 * _LOCUS_BANDWIDTH, logr.max() + 3 * _LOCUS_BANDWIDTH, 0.005)
    dens = np.exp(-0.5 * ((grid[:, None] - logr[None, :]) / _LOCUS_BANDWIDTH) ** 2).sum(axis=1)
    top = dens.max()
    is_peak = np.r_[False, (dens[1:-1] >= dens[:-2]) & (dens[1:-1] > dens[2:]), False]
    for k in np.flatnonzero(is_peak):  # ascending radius
        if dens[k] < 0.25 * top:
            continue
        members = np.abs(logr - grid[k]) <= 2.0 * _LOCUS_BANDWIDTH
        if members.sum() >= min_members:
            return float(grid[k])
    return None


def select_stars(catalog, *, shape=None, saturation_flagged: bool = True, snr_min: float = 20.0,
                 max_ellipticity: float = 0.3, min_stars: int = 5) -> StarSelection:
    """Star candidates of a detection catalog (see ``docs/detection.md``, "Measuring the seeing").

    Parameters
    ----------
    catalog : astropy.table.Table
        Detection catalog with the columns of
        :data:`comest_bayes.detect.catalog.DETECTION_COLUMNS`.
    shape : (int, int), optional
        Image shape; candidates closer than 3 pixels to the border are dropped.
    saturation_flagged : bool
        True when the catalog's saturation flag is reliable (the saturation
        level was known).  When False, sources with a peak above 70 % of the
        catalog's highest peak are dropped as possibly saturated.
    snr_min : float
        Minimum AUTO signal-to-noise.
    max_ellipticity : float
        Maximum ``1 - b/a`` of the isophotal shape.
    min_stars : int
        Minimum number of sources on the locus.

    Returns
    -------
    StarSelection
        ``index`` is empty when no stellar locus with ``min_stars`` members exists.
    """
    missing = [c for c in _COLUMNS if c not in catalog.colnames]
    if missing:
        raise InputError(f"the catalog lacks the columns {missing} needed to select stars; pass a detection "
                         f"catalog (comest_bayes.detect.sep_backend.detect_array(...).catalog).")
    col = {c: np.asarray(catalog[c], dtype=float) for c in _COLUMNS}
    n = len(catalog)
    flags = np.asarray(catalog["flags"], dtype=np.int64) if n else np.zeros(0, dtype=np.int64)
    finite = np.all([np.isfinite(col[c]) for c in _COLUMNS], axis=0) if n else np.zeros(0, dtype=bool)
    with np.errstate(invalid="ignore", divide="ignore"):
        ell = 1.0 - col["b"] / col["a"]
        ok = finite & ((flags & BAD_FLAGS) == 0) & (col["snr_auto"] >= snr_min) & (ell <= max_ellipticity) \
            & (col["flux_radius"] >= 0.5) & (col["peak"] > 0) & (col["flux_auto"] > 0)
    if shape is not None and n:
        ny, nx = shape
        ok &= (col["xwin"] >= 3) & (col["xwin"] <= nx - 4) & (col["ywin"] >= 3) & (col["ywin"] <= ny - 4)
    if not saturation_flagged and n and np.isfinite(col["peak"]).any():
        ok &= col["peak"] < 0.7 * np.nanmax(col["peak"])
    nbright = int(ok.sum())
    empty = StarSelection(np.zeros(0, dtype=np.int64), np.nan, np.nan, nbright, snr_min, max_ellipticity)
    if nbright < min_stars:
        return empty
    idx = np.flatnonzero(ok)
    logr = np.log(col["flux_radius"][idx])
    peak = _locus_peak(logr, min_stars)
    if peak is None:
        return empty
    near = np.abs(logr - peak) <= _LOCUS_WINDOW
    centre = float(np.median(logr[near]))
    width = float(1.4826 * np.median(np.abs(logr[near] - centre)))
    half = min(max(3.0 * width, 0.05), _LOCUS_WINDOW)
    on_locus = np.abs(logr - centre) <= half
    members = idx[on_locus]
    if members.size < min_stars:
        return empty
    members = members[np.argsort(-col["snr_auto"][members], kind="stable")]
    return StarSelection(members, float(np.exp(centre)), width, nbright, snr_min, max_ellipticity)


# ---------------------------------------------------------------------------------------------
# The estimate
# ---------------------------------------------------------------------------------------------

def _clipped_median(values: np.ndarray, nsigma: float = 3.0, maxiter: int = 10):
    """Median and standard deviation after iterative clipping about the median (MAD scale)."""
    keep = np.isfinite(values)
    for _ in range(maxiter):
        v = values[keep]
        med = np.median(v)
        # A floor of 1 % of the median: differences below that are immaterial and the
        # scatter of very bright stars alone would otherwise clip good fits.
        scale = max(1.4826 * np.median(np.abs(v - med)), 0.01 * abs(med))
        if scale <= 0:
            break
        new = keep & (np.abs(values - med) <= nsigma * scale)
        if new.sum() == keep.sum():
            break
        keep = new
    v = values[keep]
    return float(np.median(v)), float(np.std(v, ddof=1)) if v.size > 1 else 0.0, keep


def estimate_fwhm(data_sub, catalog, *, mask=None, saturation_flagged: bool = True, max_stars: int = 200,
                  min_stars: int = 5, snr_min: float = 20.0, max_ellipticity: float = 0.3) -> FwhmEstimate:
    """Seeing FWHM from Moffat fits to the stars of an image.

    Parameters
    ----------
    data_sub : ndarray, shape (ny, nx)
        Background-subtracted image (``data - detection.background``), image
        units.
    catalog : astropy.table.Table
        Detection catalog of that image (:data:`~comest_bayes.detect.catalog.DETECTION_COLUMNS`).
    mask : ndarray of bool, shape (ny, nx), optional
        True for bad pixels, left out of the fits.
    saturation_flagged : bool
        Whether the catalog's saturation flag can be trusted (the saturation
        level was known); if not, the sources with the highest peaks are
        skipped.  Default True.
    max_stars : int
        At most this many stars (the highest-SNR ones) are fitted; default 200.
    min_stars : int
        Fewer usable stars raise :class:`~comest_bayes.errors.InputError`;
        default 5.
    snr_min, max_ellipticity : float
        Star candidates need AUTO SNR >= ``snr_min`` (default 20) and
        ``1 - b/a <= max_ellipticity`` (default 0.3).

    Returns
    -------
    FwhmEstimate

    Raises
    ------
    InputError
        When fewer than ``min_stars`` stars could be measured, or the fitted
        candidates do not behave like stars (FWHMs or shapes disagree): the
        message asks for ``--fwhm``.
    """
    data_sub = np.asarray(data_sub, dtype=float)
    if data_sub.ndim != 2:
        raise InputError(f"data_sub must be a 2-D image; got shape {data_sub.shape}.")
    if mask is None:
        mask = np.zeros(data_sub.shape, dtype=bool)
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != data_sub.shape:
        raise InputError(f"the mask has shape {mask.shape} but the image {data_sub.shape}.")
    if max_stars < 1 or min_stars < 1:
        raise InputError(f"max_stars and min_stars must be >= 1; got {max_stars} and {min_stars}.")
    ny, nx = data_sub.shape

    sel = select_stars(catalog, shape=data_sub.shape, saturation_flagged=saturation_flagged, snr_min=snr_min,
                       max_ellipticity=max_ellipticity, min_stars=min_stars)
    if sel.index.size < min_stars:
        raise InputError(
            f"cannot measure the seeing: only {sel.index.size} star candidates found (need {min_stars}) among "
            f"{len(catalog)} detections ({sel.nbright} unflagged with SNR >= {snr_min:g} and ellipticity <= "
            f"{max_ellipticity:g}, but no tight stellar locus of flux_radius). Pass the seeing FWHM in pixels "
            f"with --fwhm (or ImageOptions(fwhm=...))."
        )

    # Moffat FWHM / half-light radius is 1.58 at beta = 3 and 2.0 for a Gaussian.
    fwhm0 = 1.8 * sel.locus_radius
    half = int(max(5, np.ceil(_STAMP_HALF_FWHM * fwhm0)))
    oversample = int(np.clip(np.ceil(10.0 / fwhm0), 1, 5))
    x_all = np.asarray(catalog["xwin"], dtype=float)
    y_all = np.asarray(catalog["ywin"], dtype=float)
    a_all = np.asarray(catalog["a"], dtype=float)
    r_all = np.asarray(catalog["flux_radius"], dtype=float)

    snr_all = np.asarray(catalog["snr_auto"], dtype=float)
    fits = []
    fit_snr = []
    fit_rows = []
    reasons: dict[str, int] = {}
    for row in sel.index[:max_stars]:
        xc, yc = x_all[row], y_all[row]
        ix, iy = int(round(xc)), int(round(yc))
        x0, x1 = max(ix - half, 0), min(ix + half + 1, nx)
        y0, y1 = max(iy - half, 0), min(iy + half + 1, ny)
        stamp = data_sub[y0:y1, x0:x1]
        valid = ~mask[y0:y1, x0:x1] & np.isfinite(stamp)
        # Leave out the pixels of neighbours: within max(2, 3 a, 2 flux_radius) of their centres.
        yy, xx = np.mgrid[y0:y1, x0:x1]
        near = np.flatnonzero((np.abs(x_all - xc) < half + 30) & (np.abs(y_all - yc) < half + 30))
        core_hit = False
        for j in near:
            if j == row:
                continue
            rad = max(2.0, 3.0 * a_all[j], 2.0 * r_all[j]) if np.isfinite(a_all[j]) else 2.0
            hit = (xx - x_all[j]) ** 2 + (yy - y_all[j]) ** 2 <= rad * rad
            if hit.any():
                valid &= ~hit
                if np.any(hit & ((xx - xc) ** 2 + (yy - yc) ** 2 <= fwhm0 ** 2)):
                    core_hit = True
        if core_hit:
            reasons["neighbour on the core"] = reasons.get("neighbour on the core", 0) + 1
            continue
        core = (xx - xc) ** 2 + (yy - yc) ** 2 <= fwhm0 ** 2
        if valid.sum() < 0.7 * valid.size or not valid[core].all():
            reasons["masked pixels"] = reasons.get("masked pixels", 0) + 1
            continue
        fit = fit_moffat(stamp, xc - x0, yc - y0, fwhm0, valid=valid, oversample=oversample)
        if fit.ok:
            fits.append(fit)
            fit_snr.append(snr_all[row])
            fit_rows.append(row)
        else:
            reasons[fit.reason] = reasons.get(fit.reason, 0) + 1

    if len(fits) < min_stars:
        why = ", ".join(f"{k}: {v}" for k, v in reasons.items()) or "none fitted"
        raise InputError(
            f"cannot measure the seeing: only {len(fits)} of {min(sel.index.size, max_stars)} star candidates "
            f"gave a good Moffat fit (need {min_stars}; rejected - {why}). Pass the seeing FWHM in pixels "
            f"with --fwhm (or ImageOptions(fwhm=...))."
        )
    fwhms = np.array([f.fwhm for f in fits])
    fit_snr = np.array(fit_snr)
    betas = np.array([f.beta for f in fits])
    # Stars share one PSF, so their fitted FWHMs agree to a few per cent; galaxies that happen
    # to sit on a size "locus" do not.  Centre on the densest +-3 % cluster of the fitted FWHMs
    # (ties: the smaller FWHM) and require min_stars in it.
    logf = np.log(fwhms)
    counts = (np.abs(logf[:, None] - logf[None, :]) <= _FWHM_AGREEMENT).sum(axis=1)
    best = int(np.lexsort((fwhms, -counts))[0])
    if counts[best] < min_stars:
        spread = 1.4826 * np.median(np.abs(logf - np.median(logf)))
        raise InputError(
            f"cannot measure the seeing: the {len(fits)} Moffat fits to star candidates do not agree (at most "
            f"{counts[best]} within +-{100 * _FWHM_AGREEMENT:.0f} % of each other, need {min_stars}; FWHM scatter "
            f"{100 * spread:.0f} %), so the candidates are probably not stars. Pass the seeing FWHM in pixels "
            f"with --fwhm (or ImageOptions(fwhm=...))."
        )
    around = np.abs(logf - logf[best]) <= _LOCUS_WINDOW
    fwhm, std, keep_around = _clipped_median(fwhms[around])
    keep = np.zeros(fwhms.size, dtype=bool)
    keep[np.flatnonzero(around)[keep_around]] = True
    nused = int(keep.sum())
    # Second test: all stars share the PSF's ellipticity (up to noise, which scales as 1/SNR
    # and is ~0.6/SNR for these weighted moments); galaxies scatter about any common value.
    ells = np.array([f.ellipticity for f in fits])[keep]
    snrs = fit_snr[keep]
    ell_centre = complex(np.nanmedian(ells.real), np.nanmedian(ells.imag))
    ell_spread = float(np.nanmedian(np.abs(ells - ell_centre)))
    ell_limit = _ELL_SPREAD_FLOOR + _ELL_SPREAD_NOISE * float(np.median(1.0 / snrs))
    if not ell_spread <= ell_limit:
        raise InputError(
            f"cannot measure the seeing: the {nused} star candidates with agreeing FWHMs do not share one PSF "
            f"shape (ellipticity scatter {ell_spread:.3f}, at most {ell_limit:.3f} expected from noise), so they "
            f"are probably compact galaxies, not stars. Pass the seeing FWHM in pixels with --fwhm (or "
            f"ImageOptions(fwhm=...))."
        )
    err = 1.2533 * std / np.sqrt(nused) if nused > 1 else np.nan
    beta = float(np.median(betas[keep]))
    at_bound = int(np.sum((betas[keep] <= 1.01 * BETA_RANGE[0]) | (betas[keep] >= 0.99 * BETA_RANGE[1])))
    star_rows = np.asarray(fit_rows, dtype=np.int64)[keep]
    star_radius = float(np.median(r_all[star_rows]))
    method = (
        f"sigma-clipped median of circular Moffat fits (free centre, flux, FWHM, beta; pixel-integrated) to "
        f"{nused} stars: unflagged sources with SNR >= {snr_min:g} and ellipticity <= {max_ellipticity:g} on "
        f"the stellar locus flux_radius = {sel.locus_radius:.2f} px (scatter {100 * sel.locus_width:.0f} %); "
        f"median beta {beta:.1f}, ellipticity scatter {ell_spread:.3f}"
    )
    return FwhmEstimate(fwhm=fwhm, fwhm_err=float(err), nstars=nused, method=method, beta=beta,
                        beta_at_bound=at_bound, star_flux_radius=star_radius, star_rows=star_rows.tolist())


# ---------------------------------------------------------------------------------------------
# Header keywords: the fallback when the stars cannot be measured
# ---------------------------------------------------------------------------------------------

#: Header keywords that may hold the seeing FWHM, in the order they are tried, each with the unit
#: taken when the keyword's comment names none (None: used only when the comment names the unit,
#: or for ``SEEING`` in data processed by CASU, whose convention is pixels).
HEADER_SEEING_KEYWORDS = (
    ("FWHM", "pixel"),        # DECam / NOAO community pipeline: "Median FWHM in pixels"
    ("SEEING", None),         # CASU (UKIDSS WFCAM, VISTA): "[pixels] Average FWHM"; elsewhere often arcsec
    ("PSF_FWHM", None),
    ("FWHM_IMAGE", "pixel"),  # SExtractor's parameter name: pixels
    ("FWHM_WORLD", "deg"),    # SExtractor's parameter name: degrees
)
#: A header FWHM outside this range (pixels) is not a seeing.
HEADER_FWHM_RANGE = (0.7, 100.0)
#: A point source of FWHM F has flux_radius between 0.5 F (Gaussian) and 0.8 F (Moffat beta 2);
#: a header FWHM is refused when even the compact bright detections are twice as large as that.
_POINT_RADIUS_PER_FWHM = 0.8
_UNIT_PATTERNS = (
    ("pixel", re.compile(r"\bpix(?:el)?s?\b|\bpx\b", re.IGNORECASE)),
    ("arcsec", re.compile(r"arc\s*-?\s*sec|\basec\b|\"", re.IGNORECASE)),
    ("deg", re.compile(r"\bdeg(?:ree)?s?\b", re.IGNORECASE)),
)
_ARCSEC_PER_UNIT = {"arcsec": 1.0, "deg": 3600.0}


def _unit_of_comment(comment: str) -> str | None:
    """The unit a header comment names first (``pixel``, ``arcsec`` or ``deg``), or None."""
    found = [(m.start(), unit) for unit, pattern in _UNIT_PATTERNS if (m := pattern.search(comment or ""))]
    return min(found)[1] if found else None


def _is_casu(headers) -> bool:
    """True for data processed by CASU (UKIRT/WFCAM, VISTA/VIRCAM), whose ``SEEING`` is in pixels."""
    for header in headers:
        names = {str(header.get(k, "")).strip().upper() for k in ("INSTRUME", "TELESCOP")}
        if names & {"WFCAM", "UKIRT", "VIRCAM", "VISTA"} or "CASUVERS" in header:
            return True
    return False


def _compact_radius(catalog, min_sources: int = 5) -> tuple[float, int]:
    """10th percentile of ``flux_radius`` of the unflagged detections with SNR >= 20 (NaN if too few)."""
    if catalog is None or len(catalog) == 0 or not {"flux_radius", "snr_auto", "flags"} <= set(catalog.colnames):
        return float("nan"), 0
    radius = np.asarray(catalog["flux_radius"], dtype=float)
    snr = np.asarray(catalog["snr_auto"], dtype=float)
    flags = np.asarray(catalog["flags"], dtype=np.int64)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(radius) & (radius > 0) & (snr >= 20.0) & ((flags & BAD_FLAGS) == 0)
    n = int(ok.sum())
    return (float(np.percentile(radius[ok], 10)) if n >= min_sources else float("nan")), n


class HeaderSeeing(NamedTuple):
    """The seeing read from header keywords (:func:`seeing_from_header`).

    Attributes
    ----------
    fwhm : float or None
        FWHM in pixels, None when no keyword gave a usable one.
    keyword : str or None
        The keyword used.
    source : str
        One sentence: the keyword, its value, its unit and why that unit.
    tried : list of str
        What each keyword gave, in the order tried (absent, refused and why, or used).
    """

    fwhm: float | None
    keyword: str | None
    source: str
    tried: list


def seeing_from_header(headers, pixel_scale: float, *, catalog=None) -> HeaderSeeing:
    """The seeing FWHM in pixels from the first usable keyword of :data:`HEADER_SEEING_KEYWORDS`.

    Parameters
    ----------
    headers : sequence of astropy.io.fits.Header
        The image HDU's header, then the primary header (a keyword is taken
        from the first header holding it).
    pixel_scale : float
        Arcsec per pixel, to convert a FWHM in arcsec or degrees.
    catalog : astropy.table.Table, optional
        Detection catalog of the image.  When it holds at least 5 unflagged
        detections with SNR >= 20, a header FWHM is refused if the 10th
        percentile of their ``flux_radius`` exceeds twice the largest
        ``flux_radius`` a point source of that FWHM has (0.8 FWHM, a Moffat of
        beta 2): the keyword does not describe this image (another binning,
        another unit than its comment says).

    Returns
    -------
    HeaderSeeing

    Notes
    -----
    The unit is the one the keyword's comment names ("Median FWHM in
    pixels", "[arcsec]"); without one, ``FWHM`` and ``FWHM_IMAGE`` are in
    pixels (the DECam community pipeline's and SExtractor's conventions),
    ``FWHM_WORLD`` in degrees (SExtractor), ``SEEING`` in pixels for data
    processed by CASU (UKIDSS WFCAM, VISTA: ``[pixels] Average FWHM``) and
    ambiguous otherwise, as is ``PSF_FWHM``: an ambiguous keyword is not used.
    """
    headers = [h for h in headers if h is not None]
    casu = _is_casu(headers)
    compact, ncompact = _compact_radius(catalog)
    tried = []
    for keyword, default_unit in HEADER_SEEING_KEYWORDS:
        holder = next((h for h in headers if keyword in h), None)
        if holder is None:
            tried.append(f"{keyword}: absent")
            continue
        value, comment = holder[keyword], str(holder.comments[keyword] or "")
        shown = f"{keyword} = {value!r}" + (f" / {comment}" if comment else "")
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value <= 0:
            tried.append(f"{shown}: not a positive number")
            continue
        unit = _unit_of_comment(comment)
        if unit is not None:
            why = "as its comment says"
        elif keyword == "SEEING" and casu:
            unit, why = "pixel", "the CASU convention (UKIDSS WFCAM, VISTA)"
        elif default_unit is not None:
            unit, why = default_unit, f"the usual convention for {keyword}"
        else:
            tried.append(f"{shown}: refused, its comment names no unit (pixels or arcsec)")
            continue
        fwhm = float(value) if unit == "pixel" else float(value) * _ARCSEC_PER_UNIT[unit] / float(pixel_scale)
        if not HEADER_FWHM_RANGE[0] <= fwhm <= HEADER_FWHM_RANGE[1]:
            tried.append(f"{shown}: refused, {fwhm:.3g} pixels (in {unit}s, {why}) is outside the "
                         f"{HEADER_FWHM_RANGE[0]:g}-{HEADER_FWHM_RANGE[1]:g} pixels a seeing FWHM can have")
            continue
        if np.isfinite(compact) and compact > 2.0 * _POINT_RADIUS_PER_FWHM * fwhm:
            tried.append(f"{shown}: refused, {fwhm:.3g} pixels does not describe this image: a point source of "
                         f"that FWHM has flux_radius <= {_POINT_RADIUS_PER_FWHM * fwhm:.2f} px, but 90 % of the "
                         f"{ncompact} bright unflagged detections are larger than {compact:.2f} px")
            continue
        source = f"header keyword {keyword} = {value:g} ({unit}s, {why}" + \
            (f"; {fwhm:.3g} pixels at {pixel_scale:.4g} arcsec/pixel)" if unit != "pixel" else ")")
        tried.append(f"{shown}: used")
        return HeaderSeeing(fwhm, keyword, source, tried)
    return HeaderSeeing(None, None, "no usable header keyword", tried)


# ---------------------------------------------------------------------------------------------
# The seeing of a run, and the PSF its injections use
# ---------------------------------------------------------------------------------------------

def _without_advice(message: str) -> str:
    """An :func:`estimate_fwhm` error without its closing advice (the caller gives its own)."""
    message = message.split(" Pass the seeing FWHM")[0].rstrip(". ")
    return message.removeprefix("cannot measure the seeing: ")


def measure_seeing(data_sub, catalog, *, mask=None, saturation_flagged: bool = True, headers=(),
                   pixel_scale: float | None = None, user_fwhm: float | None = None,
                   fallback: tuple | None = None) -> dict:
    """The seeing FWHM of an image, the Moffat beta of its stars, and where each came from.

    In order: the user's FWHM (``--fwhm``); else the Moffat fits to the
    stars (:func:`estimate_fwhm`); else the header keywords
    (:func:`seeing_from_header`); else ``fallback``.  The stars are fitted in
    every case, for their beta (and the sizes that
    :func:`point_size_check` compares the injections with).

    Parameters
    ----------
    data_sub, catalog, mask, saturation_flagged
        As for :func:`estimate_fwhm`.
    headers : sequence of astropy.io.fits.Header
        Image HDU header, then primary header (see :func:`seeing_from_header`).
    pixel_scale : float, optional
        Arcsec per pixel (needed to read a FWHM given in arcsec).
    user_fwhm : float, optional
        The FWHM in pixels given by the user.
    fallback : (float, str), optional
        A FWHM in pixels and where it comes from, used when all else fails.

    Returns
    -------
    dict
        ``fwhm``, ``fwhm_err``, ``nstars`` and ``method`` (as
        :meth:`FwhmEstimate.as_dict`), ``source`` (``"user"``, ``"fitted"``,
        ``"header"`` or ``"fallback"``), ``fwhm_source`` (one sentence),
        ``beta``, ``beta_at_bound``, ``star_flux_radius`` and ``star_rows`` of the star fits
        (None when they failed), ``stars`` (what the star fits gave: ``"fitted"``
        or their error), and ``tried`` (every attempt, in order).

    Raises
    ------
    InputError
        When neither the user, the stars, the header nor ``fallback`` give a
        FWHM; the message lists everything that was tried.
    """
    tried = []
    try:
        est = estimate_fwhm(data_sub, catalog, mask=mask, saturation_flagged=saturation_flagged)
        stars = est.as_dict()
        stars_said = "fitted"
        tried.append(f"Moffat fits to the image's stars: FWHM {est.fwhm:.3f} px, beta {est.beta:.2f} from "
                     f"{est.nstars} stars")
    except InputError as exc:
        est, stars = None, {}
        stars_said = _without_advice(str(exc))
        tried.append(f"Moffat fits to the image's stars: {stars_said}")
    out = {"fwhm_err": 0.0, "nstars": int(stars.get("nstars", 0)), "beta": stars.get("beta"),
           "beta_at_bound": int(stars.get("beta_at_bound", 0)), "star_flux_radius": stars.get("star_flux_radius"),
           "star_rows": list(stars.get("star_rows", [])),
           "stars": stars_said, "tried": tried}
    if user_fwhm is not None:
        out.update(fwhm=float(user_fwhm), method="given by the user (--fwhm)", source="user",
                   fwhm_source="user --fwhm")
        return out
    if est is not None:
        out.update(fwhm=float(est.fwhm), fwhm_err=float(est.fwhm_err), method=est.method, source="fitted",
                   fwhm_source=f"fitted from {est.nstars} stars")
        return out
    head = seeing_from_header(headers, pixel_scale, catalog=catalog) if pixel_scale else \
        HeaderSeeing(None, None, "", ["not read: the pixel scale is unknown"])
    tried.append("header keywords: " + "; ".join(head.tried))
    if head.fwhm is not None:
        out.update(fwhm=float(head.fwhm), method=f"{head.source}; the stars could not be measured ({stars_said})",
                   source="header", fwhm_source=head.source)
        return out
    if fallback is not None:
        out.update(fwhm=float(fallback[0]), method=str(fallback[1]), source="fallback", fwhm_source=str(fallback[1]))
        return out
    raise InputError(
        "cannot determine the seeing FWHM of this image. Tried: "
        + "; ".join(f"({i + 1}) {t}" for i, t in enumerate(tried))
        + ". Pass the seeing FWHM in pixels with --fwhm (or ImageOptions(fwhm=...))."
    )


def injection_psf(injection, seeing: dict, *, pixel_scale: float | None = None) -> dict:
    """The PSF the injections use, and where each of its numbers came from.

    Parameters
    ----------
    injection : comest_bayes.config.InjectionConfig
        ``psf`` and ``moffat_beta`` (0: the stars' beta).
    seeing : dict
        From :func:`measure_seeing`.
    pixel_scale : float, optional
        Arcsec per pixel; when given, the point-source stamp size is decided
        here too (``stamp``, :func:`comest_bayes.inject.render.point_stamp_size`)
        and named in ``description``.

    Returns
    -------
    dict
        ``model`` (``moffat``, ``gaussian``, ``kolmogorov`` or the FITS file),
        ``fwhm_pix`` and ``fwhm_source``, ``beta`` and ``beta_source``
        (Moffat only; else None), ``pixel_integrated`` (the profile is
        convolved with the pixel: the FWHM and beta were fitted with a
        pixel-integrated model), ``description`` (one sentence),
        ``warnings`` (e.g. a fitted beta at a bound of :data:`BETA_RANGE`)
        and, with ``pixel_scale``, ``stamp`` (the point-source stamp and why).

    Notes
    -----
    The Moffat beta is ``injection.moffat_beta`` when set (> 0); else the
    median beta fitted on the image's stars; else
    :data:`~comest_bayes.inject.psfmodel.DEFAULT_MOFFAT_BETA` (3), with the reason the
    stars gave none.  A FITS PSF image ignores both.
    """

    model = injection.psf.strip()
    analytic = model.lower() in ("moffat", "gaussian", "kolmogorov")
    fwhm = float(seeing["fwhm"])
    out = {"model": model.lower() if analytic else model, "fwhm_pix": fwhm,
           "fwhm_source": seeing.get("fwhm_source", seeing.get("method", "?")), "beta": None, "beta_source": None,
           "pixel_integrated": bool(analytic and seeing.get("source") == "fitted"), "warnings": []}
    warn = out["warnings"]
    if model.lower() == "moffat":
        fitted = seeing.get("beta")
        if injection.moffat_beta > 0:
            out["beta"], out["beta_source"] = float(injection.moffat_beta), "injection.moffat_beta (configuration)"
        elif fitted is not None and np.isfinite(fitted):
            out["beta"] = float(fitted)
            out["beta_source"] = f"fitted from {seeing.get('nstars', 0)} stars (median)"
            nbound = int(seeing.get("beta_at_bound", 0))
            lo, hi = BETA_RANGE
            if fitted <= 1.01 * lo or fitted >= 0.99 * hi:
                side = "lower" if fitted <= 1.01 * lo else "upper"
                meaning = ("the stars' wings are at least this heavy (crowding, a halo or a background error can "
                           "also drive it there); stamps then reach far" if side == "lower" else
                           "the stars' profile is Gaussian-like, narrower in the wings than any Moffat allowed")
                warn.append(f"the fitted Moffat beta {fitted:.3g} sits at the {side} bound of its range "
                            f"[{lo:g}, {hi:g}] ({nbound} of {seeing.get('nstars', 0)} stars at a bound): {meaning}; "
                            f"injected with beta = {fitted:.3g}. Check the stars, or set injection.moffat_beta.")
        else:
            out["beta"] = DEFAULT_MOFFAT_BETA
            why = seeing.get("stars") or "the stars were not fitted"
            out["beta_source"] = f"default {DEFAULT_MOFFAT_BETA:g}: not measured ({why})"
    if analytic:
        shape = {"moffat": f"Moffat (FWHM {fwhm:.3f} px, beta {out['beta']:.3g})" if out["beta"] is not None else "",
                 "gaussian": f"Gaussian (FWHM {fwhm:.3f} px)",
                 "kolmogorov": f"Kolmogorov (FWHM {fwhm:.3f} px)"}[out["model"]]
        out["description"] = shape + (" integrated over the pixel, as fitted on the stars"
                                      if out["pixel_integrated"] else " as the effective PSF (sampled at pixel centres)")
    else:
        out["description"] = f"PSF image {model} (the effective PSF, sampled at pixel centres)"
        out["fwhm_source"] += " (used for the matching radius and separations only)"
    if pixel_scale is not None:

        profile = make_psf(injection, fwhm, pixel_scale, beta=out["beta"], pixel_integrated=out["pixel_integrated"])
        out["stamp"] = point_stamp_size(profile, pixel_scale)
        half = out["stamp"]["half_size_pix"]
        out["description"] += (f"; point-source stamps {2 * half + 1}x{2 * half + 1} px "
                               f"({100 * out['stamp']['enclosed_fraction']:.1f}% of the light)")
        if out["stamp"]["capped"]:
            warn.append(f"the PSF's wings need stamps wider than {2 * half + 1} px: they hold only "
                        f"{100 * out['stamp']['enclosed_fraction']:.1f}% of a point source's light")
    return out


def point_size_check(star_radius, injected_radius, *, tolerance: float = 0.05, min_sources: int = 5,
                     star_snr=None, injected_snr=None) -> dict:
    """Do injected point sources look as large as the image's stars?

    Compares the median ``flux_radius`` measured by the detector on the real
    stars and on detected point-source injections.

    Parameters
    ----------
    star_radius, injected_radius : array_like of float
        ``flux_radius`` (pixels) of the stars and of the detected injections
        (select both by the same signal-to-noise cut).
    tolerance : float
        Largest accepted relative difference of the medians (default 5 %).
    min_sources : int
        Fewer values on either side give ``status = "not enough"``.
    star_snr, injected_snr : array_like of float, optional
        Signal-to-noise of each star and injection (same order as the radii).
        SEP's ``flux_radius`` grows with the signal-to-noise (on the shared
        KiDS image from 1.64 px at SNR 20-40 to 1.83 px above 1000, for stars
        and injections alike), and the stars are usually brighter than the
        injections, so the plain medians compare unlike with unlike.  When
        given, ``matched`` also compares them at the same signal-to-noise.

    Returns
    -------
    dict
        ``stars`` and ``injected`` (median flux_radius in pixels, or None),
        ``nstars``, ``ninjected``, ``ratio`` (injected / stars), ``ratio_err``
        (from the standard errors of both medians, ``1.2533 std / sqrt(n)``),
        ``tolerance`` and ``status``: ``"agree"`` (the ratio is within the
        tolerance of 1), ``"disagree"`` (it differs from 1 by more than the
        tolerance and by more than 3 ``ratio_err``), ``"uncertain"`` (by more
        than the tolerance, but within 3 ``ratio_err``: too few or too
        scattered sources to tell) or ``"not enough"``.  With the
        signal-to-noise values, ``matched``: the same comparison within the
        signal-to-noise range both cover, the injections weighted to the
        stars' distribution over bins of a factor 2 in signal-to-noise
        (``ratio``, ``ratio_err``, ``stars``, ``injected``, ``nstars``,
        ``ninjected``, ``snr_range``, ``status``), or None when fewer than
        ``min_sources`` of either fall in the common range.
    """
    def clean(values, snr=None):
        values = np.asarray(values, dtype=float)
        ok = np.isfinite(values) & (values > 0)
        if snr is None:
            return values[ok], None
        snr = np.asarray(snr, dtype=float)
        if snr.shape != values.shape:
            raise InputError(f"the signal-to-noise values ({snr.shape}) do not match the radii ({values.shape}).")
        ok &= np.isfinite(snr) & (snr > 0)
        return values[ok], snr[ok]

    def verdict(ratio, err):
        off = abs(ratio - 1.0)
        if off <= tolerance:
            return "agree"
        return "disagree" if off > 3.0 * err else "uncertain"

    matched_wanted = star_snr is not None and injected_snr is not None
    stars, s_snr = clean(star_radius, star_snr if matched_wanted else None)
    injected, i_snr = clean(injected_radius, injected_snr if matched_wanted else None)
    out = {"nstars": int(stars.size), "ninjected": int(injected.size), "stars": None, "injected": None,
           "ratio": None, "ratio_err": None, "tolerance": float(tolerance), "status": "not enough"}
    if matched_wanted:
        out["matched"] = None
    if stars.size < min_sources or injected.size < min_sources:
        return out
    ms, mi = float(np.median(stars)), float(np.median(injected))
    es = 1.2533 * float(np.std(stars, ddof=1)) / np.sqrt(stars.size)
    ei = 1.2533 * float(np.std(injected, ddof=1)) / np.sqrt(injected.size)
    ratio = mi / ms
    err = ratio * float(np.hypot(es / ms, ei / mi))
    out.update(stars=ms, injected=mi, ratio=ratio, ratio_err=err, status=verdict(ratio, err))
    if matched_wanted:
        out["matched"] = _matched_size_check(stars, s_snr, injected, i_snr, min_sources, verdict)
    return out


def _weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    order = np.argsort(values, kind="stable")
    cum = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cum, 0.5 * cum[-1])])


def _matched_size_check(stars, s_snr, injected, i_snr, min_sources, verdict):
    """Stars and injections compared at the same signal-to-noise (see :func:`point_size_check`)."""
    lo, hi = max(s_snr.min(), i_snr.min()), min(s_snr.max(), i_snr.max())
    if not hi > lo:
        return None
    edges = lo * 2.0 ** np.arange(0, np.ceil(np.log2(hi / lo)) + 1)
    edges[-1] = max(edges[-1], hi)
    sb = np.digitize(s_snr, edges) - 1
    ib = np.digitize(i_snr, edges) - 1
    sb[s_snr == hi] = ib[i_snr == hi] = len(edges) - 2
    nb = len(edges) - 1
    s_count = np.bincount(sb[(sb >= 0) & (sb < nb)], minlength=nb)
    i_count = np.bincount(ib[(ib >= 0) & (ib < nb)], minlength=nb)
    both = (s_count > 0) & (i_count > 0)
    s_in = (sb >= 0) & (sb < nb) & both[np.clip(sb, 0, nb - 1)]
    i_in = (ib >= 0) & (ib < nb) & both[np.clip(ib, 0, nb - 1)]
    if s_in.sum() < min_sources or i_in.sum() < min_sources:
        return None
    star_r = stars[s_in]
    inj_r = injected[i_in]
    w = (s_count[ib[i_in]] / i_count[ib[i_in]]).astype(float)  # injections weighted to the stars' SNR mix
    ms = float(np.median(star_r))
    mi = _weighted_median(inj_r, w)
    n_eff = float(w.sum() ** 2 / np.sum(w * w))
    es = 1.2533 * float(np.std(star_r, ddof=1)) / np.sqrt(star_r.size)
    ei = 1.2533 * float(np.sqrt(np.cov(inj_r, aweights=w))) / np.sqrt(n_eff)
    ratio = mi / ms
    err = ratio * float(np.hypot(es / ms, ei / mi))
    return {"ratio": ratio, "ratio_err": err, "stars": ms, "injected": mi, "nstars": int(star_r.size),
            "ninjected": int(inj_r.size), "snr_range": [float(lo), float(hi)], "status": verdict(ratio, err)}


def empirical_psf(data_sub, catalog, star_rows, *, half_size: int, mask=None, min_stars: int = 10):
    """The effective PSF of an image, stacked from its own stars.

    A fitted Moffat describes a star's core but not always its outer wings
    (on the shared KiDS r image the stars hold 87 % of their light within
    5 px against 92 % for the fitted Moffat of beta 2.1).  This stacks the
    stars instead: each isolated star's stamp is shifted (cubic spline) so
    that its centroid falls on the centre of the middle pixel, divided by
    its flux within the stamp, and the stamps are combined pixel by pixel
    with a 3-sigma clipped mean.  The result is the effective PSF sampled at
    pixel centres, for ``injection.psf = <FITS file>`` (write it with
    :func:`astropy.io.fits.writeto`; :func:`comest_bayes.inject.psfmodel.make_psf`
    reads it at the image's pixel scale).  It assumes the PSF does not vary
    over the image and is sampled well enough for the sub-pixel shift (FWHM
    above about 2 px).

    Parameters
    ----------
    data_sub : ndarray, shape (ny, nx)
        Background-subtracted image.
    catalog : astropy.table.Table
        Its detection catalog (``xwin``, ``ywin``, ``a``, ``flux_radius``).
    star_rows : sequence of int
        Rows of the stars (e.g. ``run.json`` -> ``stages.fwhm.estimate.star_rows``).
    half_size : int
        The stamp is ``2 half_size + 1`` pixels on a side.
    mask : ndarray of bool, optional
        Bad pixels; a star with one in its stamp is skipped.
    min_stars : int
        Fewer isolated stars raise :class:`~comest_bayes.errors.InputError`.

    Returns
    -------
    psf : ndarray, shape (2 half_size + 1, 2 half_size + 1), float64
        Unit sum.
    nstars : int
        Stars stacked.
    """
    from scipy import ndimage

    data_sub = np.asarray(data_sub, dtype=float)
    h = int(half_size)
    if h < 2:
        raise InputError(f"half_size must be >= 2 pixels, got {half_size!r}.")
    ny, nx = data_sub.shape
    mask = np.zeros(data_sub.shape, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    x_all = np.asarray(catalog["xwin"], dtype=float)
    y_all = np.asarray(catalog["ywin"], dtype=float)
    reach = np.maximum(3.0 * np.asarray(catalog["a"], dtype=float), 2.0 * np.asarray(catalog["flux_radius"], float))
    reach = np.where(np.isfinite(reach), reach, 3.0)
    pad = h + 3
    stamps = []
    for row in np.asarray(star_rows, dtype=np.int64):
        xc, yc = x_all[row], y_all[row]
        ix, iy = int(round(xc)), int(round(yc))
        if ix - pad < 0 or iy - pad < 0 or ix + pad >= nx or iy + pad >= ny:
            continue
        # isolated: no other detection whose light reaches into the stamp
        d = np.hypot(x_all - xc, y_all - yc)
        d[row] = np.inf
        if np.any(d - reach < h * math.sqrt(2.0)):
            continue
        cut = (slice(iy - pad, iy + pad + 1), slice(ix - pad, ix + pad + 1))
        if mask[cut].any() or not np.all(np.isfinite(data_sub[cut])):
            continue
        shifted = ndimage.shift(data_sub[cut], (iy - yc, ix - xc), order=3, mode="nearest")[3:-3, 3:-3]
        total = shifted.sum()
        if total > 0:
            stamps.append(shifted / total)
    if len(stamps) < min_stars:
        raise InputError(f"only {len(stamps)} isolated, unmasked stars with whole stamps of {2 * h + 1} px (need "
                         f"{min_stars}) to build an empirical PSF; use the fitted Moffat instead.")
    cube = np.array(stamps)
    keep = np.ones(cube.shape, dtype=bool)
    for _ in range(5):
        mean = np.sum(cube * keep, axis=0) / np.maximum(keep.sum(axis=0), 1)
        var = np.sum(((cube - mean) ** 2) * keep, axis=0) / np.maximum(keep.sum(axis=0) - 1, 1)
        new = np.abs(cube - mean) <= 3.0 * np.sqrt(var) + 1e-300
        if np.array_equal(new, keep):
            break
        keep = new
    psf = np.sum(cube * keep, axis=0) / np.maximum(keep.sum(axis=0), 1)
    return psf / psf.sum(), len(stamps)
