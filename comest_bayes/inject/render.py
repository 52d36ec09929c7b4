"""Injection: the truth table of one realization, and its rendering into an image.

:func:`make_truth` draws what goes where (columns :data:`TRUTH_COLUMNS`); :func:`render_truth`
draws those sources with GalSim (or batched in k-space with NumPy) into a copy of a base image,
with optional photon noise.  The truth table, stamp sizes, FFT drawing and photon noise:
``docs/injection.md`` ("The truth table and its rendering").
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, field

import galsim
import numpy as np
from astropy.table import Table

from comest_bayes.config import KINDS, InjectionConfig
from comest_bayes.errors import ComestError, InputError
from comest_bayes.inject.placement import PUBLISHED_DENSITY, draw_count, pixel_index, place_sized_sources, place_sources
from comest_bayes.constants import FWHM_PER_SIGMA
from comest_bayes.inject.cosmos import CosmosSample
from comest_bayes.inject.kspace import buldisk_k, buldisk_radius_per_hlr, devaucouleurs_k_table, kspace_quadratic_forms
from comest_bayes.inject.population import draw_parameters, fit_observed_population
from comest_bayes.inject.psfmodel import make_psf, psf_half_light_radius_pix
from comest_bayes.inject.profiles import sersic_radius_per_hlr, source_profile
from comest_bayes.seeding import rng_for

__all__ = ["TRUTH_COLUMNS", "FLAG_MASKED", "FLAG_OFF_IMAGE", "FLAG_DRAW_ERROR", "FLAG_CLEAN_ZONE", "MAX_FFT_SIZE",
           "make_truth", "render_truth", "SIZED_KINDS", "SEPARATION_HLR", "STAMP_FLUX_FRACTION",
           "separation_radius_pix", "stamp_half_pix", "radius_per_hlr", "psf_radius_pix", "placement_capacity", "sizing_rule", "local_jacobians", "psf_enclosed_radius_pix", "point_stamp_size", "StampRenderer",
           "KGrid", "fft_size", "MAX_PSF_RADIUS_PIX", "BATCH_CHUNK_ELEMENTS"]

FLAG_MASKED = 1
FLAG_OFF_IMAGE = 2
FLAG_DRAW_ERROR = 4
#: Set after detection (``matching.exclude_clean_zone``): within the cleaning reach of a brighter detected injection.
FLAG_CLEAN_ZONE = 8

#: Largest FFT (pixels on a side) used for one stamp; larger sources get flag 4.
MAX_FFT_SIZE = 4096
#: Largest PSF radius (pixels) a stamp is sized for; heavier wings are cut there, with a warning.
MAX_PSF_RADIUS_PIX = 256
#: Batched drawing works on chunks of about this many k-space values (16 bytes each).
BATCH_CHUNK_ELEMENTS = 1 << 18
#: Batched ``buldisk`` stamps need the de Vaucouleurs table up to |k| <= this (inverse half-light radii).
_MAX_BATCH_KAPPA = 4096.0

def _even_5smooth(limit: int) -> np.ndarray:
    vals = {2 ** a * 3 ** b * 5 ** c for a in range(1, 14) for b in range(9) for c in range(7)}
    return np.array(sorted(v for v in vals if v <= limit))


#: FFT sizes used for stamps: even numbers with no prime factor above 5 (fast for NumPy's pocketfft).
_FFT_SIZES = _even_5smooth(MAX_FFT_SIZE)


def fft_size(m: int) -> int:
    """Smallest size in :data:`_FFT_SIZES` >= ``m`` (raises beyond :data:`MAX_FFT_SIZE`)."""
    k = int(np.searchsorted(_FFT_SIZES, m))
    if k >= _FFT_SIZES.size:
        raise galsim.GalSimFFTSizeError(f"a stamp needs an FFT of {m} pixels (limit {MAX_FFT_SIZE})", m)
    return int(_FFT_SIZES[k])


#: name -> (numpy dtype, unit, description)
TRUTH_COLUMNS = {
    "injection_id": ("i8", None, "0..n-1, unique within the realization"),
    "kind": ("U8", None, "source kind: point, buldisk, sersic, cosmos or observed"),
    "x": ("f8", "pix", "0-based x of the light centroid, as drawn"),
    "y": ("f8", "pix", "0-based y of the light centroid, as drawn"),
    "ra": ("f8", "deg", "right ascension of (x, y); NaN without a WCS"),
    "dec": ("f8", "deg", "declination of (x, y); NaN without a WCS"),
    "mag": ("f8", "mag", "injected magnitude"),
    "flux": ("f8", None, "total flux in image units, 10**(-0.4 (mag - zeropoint))"),
    "hlr_arcsec": ("f8", "arcsec", "circularised half-light radius sqrt(ab); NaN for point and cosmos"),
    "q": ("f8", None, "axis ratio b/a; NaN for point and cosmos"),
    "pa_deg": ("f8", "deg", "major-axis angle counter-clockwise from +u (west) in the local world frame"),
    "bulge_fraction": ("f8", None, "bulge flux fraction (buldisk), else NaN"),
    "sersic_n": ("f8", None, "Sersic index (sersic, observed), else NaN"),
    "cosmos_index": ("i8", None, "COSMOS catalog row (cosmos), else -1"),
    "masked": ("?", None, "centre on a masked pixel: excluded from the ratios"),
    "flag": ("i8", None, "bits: 1 centre masked, 2 stamp (partly) off the image, 4 drawing failed, 8 within the clean "
                             "zone of a brighter detected injection (matching.exclude_clean_zone)"),
}
_LOCAL_NOISE = ("f8", None, "noise sigma at the centre pixel, image units")


# --------------------------------------------------------------------------- geometry


def local_jacobians(x, y, *, wcs=None, pixel_scale: float, step: float = 0.5) -> np.ndarray:
    """Local pixel-to-world Jacobians at each position, arcsec per pixel.

    ``J = [[du/dx, du/dy], [dv/dx, dv/dy]]`` with ``u`` towards the west
    (``-RA cos(Dec)``) and ``v`` towards the north, by central differences of
    ``step`` pixels through :meth:`astropy.wcs.WCS.all_pix2world` (distortion
    included).  Without a WCS, ``J = pixel_scale * I``.

    Parameters
    ----------
    x, y : array_like, shape (n,)
        0-based pixel positions.
    wcs : astropy.wcs.WCS, optional
        Celestial WCS of the image.
    pixel_scale : float
        Arcsec per pixel, used without a WCS.
    step : float
        Half-step of the differences, pixels.

    Returns
    -------
    ndarray, shape (n, 2, 2)
    """
    x = np.atleast_1d(np.asarray(x, dtype=float))
    y = np.atleast_1d(np.asarray(y, dtype=float))
    n = x.size
    jac = np.zeros((n, 2, 2))
    if wcs is None:
        jac[:, 0, 0] = jac[:, 1, 1] = pixel_scale
        return jac
    w = wcs.celestial if getattr(wcs, "naxis", 2) != 2 else wcs
    xs = np.concatenate([x + step, x - step, x, x])
    ys = np.concatenate([y, y, y + step, y - step])
    ra, dec = w.all_pix2world(xs, ys, 0)
    ra, dec = ra.reshape(4, n), dec.reshape(4, n)
    cosd = np.cos(np.deg2rad(0.5 * (dec[0] + dec[1])))
    dra_x = (ra[0] - ra[1] + 180.0) % 360.0 - 180.0
    dra_y = (ra[2] - ra[3] + 180.0) % 360.0 - 180.0
    scale = 3600.0 / (2.0 * step)
    jac[:, 0, 0] = -dra_x * cosd * scale
    jac[:, 0, 1] = -dra_y * cosd * scale
    jac[:, 1, 0] = (dec[0] - dec[1]) * scale
    jac[:, 1, 1] = (dec[2] - dec[3]) * scale
    return jac


def _sky_positions(x, y, wcs):
    if wcs is None or len(x) == 0:
        return np.full(len(x), np.nan), np.full(len(x), np.nan)
    w = wcs.celestial if getattr(wcs, "naxis", 2) != 2 else wcs
    ra, dec = w.all_pix2world(np.asarray(x, dtype=float), np.asarray(y, dtype=float), 0)
    return np.asarray(ra, dtype=float), np.asarray(dec, dtype=float)


# --------------------------------------------------------------------------- truth


#: Kinds placed source by source (:func:`comest_bayes.inject.placement.place_sized_sources`): each keeps
#: a separation that follows its own drawn size and lies where its whole stamp fits on the image.
#: ``cosmos`` and ``observed`` (and any kind with ``injection.placement = "grid"``) keep one separation for
#: all, :func:`min_separation_pix`.
SIZED_KINDS = ("buldisk", "sersic")
#: Separation radius of a sized galaxy in half-light radii: two galaxies are kept at least the sum of
#: their radii apart.  4 hlr holds 99.1% of an exponential disk's light.  The rule it replaces, one
#: separation of 8 x the largest half-light radius of the population for all, was set on the demo,
#: where 4 hlr_max allowed enough blends to hold the bright-end buldisk completeness at 0.99 and
#: 8 hlr_max gave 1; the pair of the largest galaxies still gets 8 hlr_max.
SEPARATION_HLR = 4.0
#: Light fraction the stamps are sized to hold (``render_truth``'s default ``flux_fraction``).
STAMP_FLUX_FRACTION = 0.995


def min_separation_pix(config: InjectionConfig, fwhm_pix: float | None, pixel_scale: float,
                       kind: str = "buldisk") -> float:
    """One minimum separation between all injections of a kind, pixels.

    ``config.min_sep`` in arcsec when positive; when 0 (the default) it is
    automatic: ``4 FWHM`` for point sources, ``max(4 FWHM, 8 hlr_max)`` for galaxies.  With 4 hlr_max, bright bulge+disk
    injections blended with a neighbouring injection often enough to hold the
    bright-end completeness of the demo at 0.99 (the neighbour's light entered
    the Kron aperture and pushed the measured magnitude outside the matching
    tolerance); at 8 hlr_max the plateau is 1.  For :data:`SIZED_KINDS` this
    is the separation of the pair of the largest galaxies only (each pair gets
    the sum of its :func:`separation_radius_pix`).
    """
    if config.min_sep > 0:
        return config.min_sep / pixel_scale
    fwhm_arcsec = (fwhm_pix or 0.0) * pixel_scale
    if kind == "point":
        return 4.0 * fwhm_arcsec / pixel_scale
    return max(4.0 * fwhm_arcsec, 8.0 * config.hlr_range[1]) / pixel_scale


def separation_radius_pix(config: InjectionConfig, fwhm_pix: float | None, pixel_scale: float,
                          hlr_arcsec) -> np.ndarray:
    """Per-source separation radius (pixels) of sized galaxies: pairs keep the sum of their radii.

    ``config.min_sep / 2`` when the user set one (every pair then keeps
    ``min_sep``); else ``max(2 FWHM, SEPARATION_HLR x hlr)``, the point
    sources' ``2 FWHM`` and the galaxy's own extent (two galaxies of the
    largest size keep :func:`min_separation_pix` apart, as before).
    """
    hlr = np.asarray(hlr_arcsec, dtype=float)
    if config.min_sep > 0:
        return np.full(hlr.shape, 0.5 * config.min_sep / pixel_scale)
    return np.maximum(2.0 * (fwhm_pix or 0.0), SEPARATION_HLR * hlr / pixel_scale)


def stamp_half_pix(kind: str, params: dict, pixel_scale: float, r_psf_pix: float,
                   fraction: float = STAMP_FLUX_FRACTION) -> np.ndarray:
    """Half-size (pixels) of the stamps :func:`render_truth` gives sources of ``kind``, plus a margin.

    ``ceil(hypot(r_src, r_psf) + 1)`` as in :func:`render_truth` (``r_src``: the
    major-axis radius holding ``fraction`` of the source's light, at the
    nominal ``pixel_scale``), plus 1 px and 2% for a WCS whose local scale
    differs from the nominal one.  ``params``: the columns of
    :func:`comest_bayes.inject.population.draw_parameters`.
    """
    hlr = np.asarray(params["hlr_arcsec"], dtype=float)
    q = np.asarray(params["q"], dtype=float)
    per_hlr = radius_per_hlr(kind, params, fraction)
    r_src = hlr * per_hlr / np.sqrt(np.where(q < 1.0, q, 1.0)) / pixel_scale
    half = np.maximum(2.0, np.ceil(np.hypot(r_src, r_psf_pix) + 1.0))
    return np.ceil(1.02 * half) + 1.0


def radius_per_hlr(kind: str, params: dict, fraction: float = STAMP_FLUX_FRACTION) -> np.ndarray:
    """Radius enclosing ``fraction`` of each circular source, in half-light radii (before ``1 / sqrt(q)``).

    The numbers :func:`comest_bayes.inject.profiles.source_profile` and the
    batched drawing use: ``buldisk`` from ``bulge_fraction``, ``sersic`` and
    ``observed`` from ``sersic_n``.
    """
    if kind == "buldisk":
        return buldisk_radius_per_hlr(params["bulge_fraction"], fraction)
    if kind in ("sersic", "observed"):
        n = np.asarray(params["sersic_n"], dtype=float)
        uniq, inv = np.unique(n, return_inverse=True)
        return np.array([sersic_radius_per_hlr(float(v), fraction) for v in uniq])[inv.ravel()]
    raise InputError(f"kind {kind!r} has no radius in half-light radii.")


def psf_radius_pix(psf, config: InjectionConfig, fwhm_pix, pixel_scale: float,
                   fraction: float = STAMP_FLUX_FRACTION) -> float:
    """Radius (pixels) holding ``fraction`` of the PSF's light (``psf``, else ``make_psf``; 0 without either)."""
    if psf is None and not fwhm_pix:
        return 0.0
    if psf is None:
        psf = make_psf(config, fwhm_pix, pixel_scale)
    return psf_enclosed_radius_pix(galsim.PixelScale(pixel_scale).toImage(psf), fraction)[0]


def _sized(kind: str, config: InjectionConfig) -> bool:
    return kind in SIZED_KINDS and config.placement != "grid"


def sizing_rule(kind: str, config: InjectionConfig) -> dict:
    """How injections of ``kind`` are spaced and where they may sit (recorded in ``run.json``)."""
    if not _sized(kind, config):
        sep = ("injection.min_sep as given" if config.min_sep > 0 else
               "4 FWHM" if kind == "point" else "max(4 FWHM, 8 x the largest half-light radius of injection.hlr_range)")
        return {"separation": f"one for all: {sep}", "stamp": f"radius holding {100 * STAMP_FLUX_FRACTION:.1f}% of "
                "the light, plus 1 px; an injection whose stamp runs off the image is unusable (flag 2)",
                "per_source": False}
    sep = ("injection.min_sep as given" if config.min_sep > 0 else
           f"per source: a pair keeps the sum of the radii max(2 FWHM, {SEPARATION_HLR:g} hlr) of its two galaxies")
    return {"separation": sep, "stamp": f"per source: the PSF-convolved major-axis radius holding "
            f"{100 * STAMP_FLUX_FRACTION:.1f}% of the galaxy's light, plus 1 px; each galaxy is placed where its whole "
            f"stamp lies on the image (its size drawn before its position)", "per_source": True}


def placement_capacity(kind: str, *, shape, pixel_scale: float, fwhm_pix: float | None, config: InjectionConfig,
                       n_try: int, psf=None, seed: int = 0, r_psf_pix: float | None = None) -> tuple[int, int]:
    """How many sized galaxies of ``kind`` the placement of :func:`make_truth` holds on an image.

    Draws ``n_try`` sources of the population (a fixed ``seed``: the answer is
    a property of the image and the configuration) and places them as a
    realization does (``r_psf_pix``: the PSF's radius holding
    :data:`STAMP_FLUX_FRACTION`, :func:`psf_radius_pix`, when known).  Returns ``(placed, n_try)``: fewer placed than tried
    means the placement is full near ``placed``; all placed, that it holds at
    least ``n_try``.
    """
    rng = rng_for(seed)
    n_try = int(n_try)
    params = draw_parameters(kind, n_try, config=config, mag_range=(20.0, 21.0), rng=rng, pixel_scale=pixel_scale)
    r_psf = psf_radius_pix(psf, config, fwhm_pix, pixel_scale) if r_psf_pix is None else float(r_psf_pix)
    radius = separation_radius_pix(config, fwhm_pix, pixel_scale, params["hlr_arcsec"])
    half = stamp_half_pix(kind, params, pixel_scale, r_psf)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        placement = place_sized_sources(radius, half, shape, rng, method=config.placement)
    return placement.n, n_try


def make_truth(kind: str, *, shape, mask=None, pixel_scale: float, fwhm_pix: float | None,
               config: InjectionConfig, mag_range=None, rng: np.random.Generator, wcs=None,
               zeropoint: float, observed_catalog=None, cosmos: CosmosSample | None = None, psf=None,
               noise=None, n: int | None = None, border_pix: float = 0.0, mag_design=None) -> Table:
    """Draw the injections of one realization.

    Random draws, in this order, all from ``rng``: the count
    (``Poisson(config.density * area)``, :func:`comest_bayes.inject.placement.draw_count`;
    skipped when ``n`` is given; an automatic ``config.density`` of 0 that the run has not
    resolved per kind, :func:`comest_bayes.pipeline.preflight.choose_density`, draws at the published
    :data:`~comest_bayes.inject.placement.PUBLISHED_DENSITY`), the positions
    (:func:`comest_bayes.inject.placement.place_sources` with ``config.placement`` and
    ``config.min_sep`` converted to pixels), then the magnitudes and shapes
    (:func:`comest_bayes.inject.population.draw_parameters`).

    Parameters
    ----------
    kind : str
        Source kind (:data:`comest_bayes.config.KINDS`).
    shape : (ny, nx)
        Image shape.
    mask : ndarray of bool, shape (ny, nx), optional
        True on unusable pixels; injections centred there get ``masked`` and flag 1.
    pixel_scale : float
        Arcsec per pixel.
    fwhm_pix : float or None
        Seeing FWHM in pixels (``observed``: PSF size to deconvolve; may be
        None when ``psf`` is given).
    config : InjectionConfig
        Density, placement, ranges (see ``docs/sources.md``).
    mag_range : (float, float), optional
        Bright and faint limits; default ``config.mag_range`` (must then be set).
    rng : numpy.random.Generator
        The only source of randomness.
    wcs : astropy.wcs.WCS, optional
        For ``ra``, ``dec``.
    zeropoint : float
        Magnitude of one image unit of flux.
    observed_catalog : astropy.table.Table, optional
        The image's detection catalog (required for ``observed``).
    cosmos : CosmosSample, optional
        Required for ``cosmos`` (:func:`comest_bayes.inject.cosmos.load_cosmos`).
    psf : galsim.GSObject, optional
        The effective PSF in arcsec (``observed``: its half-light radius is
        deconvolved); default ``make_psf(config, fwhm_pix, pixel_scale)``.
    noise : ndarray, shape (ny, nx), optional
        Noise sigma map; adds the ``local_noise`` column.
    n : int, optional
        Number of injections instead of the Poisson draw.
    border_pix : float
        Edge strip without injections, pixels.
    mag_design : comest_bayes.inject.design.MagnitudeDesign, optional
        The magnitudes' density (an adaptive batch); default uniform in ``mag_range``.

    Returns
    -------
    astropy.table.Table
        One row per injection, columns :data:`TRUTH_COLUMNS` (+ ``local_noise``).
    """
    if kind not in KINDS:
        raise InputError(f"unknown source kind {kind!r}; use one of {KINDS}.")
    shape = tuple(int(v) for v in shape)
    if len(shape) != 2 or min(shape) < 1:
        raise InputError(f"image shape must be (ny, nx) with positive sizes, got {shape!r}.")
    if not (pixel_scale and np.isfinite(pixel_scale) and pixel_scale > 0):
        raise InputError(f"pixel scale must be a positive number of arcsec/pixel, got {pixel_scale!r}.")
    if zeropoint is None or not np.isfinite(zeropoint):
        raise InputError(f"a finite zero point is needed to turn magnitudes into fluxes, got {zeropoint!r}.")
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != shape:
            raise InputError(f"mask shape {mask.shape} differs from the image shape {shape}.")
    if noise is not None and np.shape(noise) != shape:
        raise InputError(f"noise map shape {np.shape(noise)} differs from the image shape {shape}.")
    if mag_range is None or len(mag_range) == 0:
        mag_range = config.mag_range

    population = None
    if kind == "observed":
        if observed_catalog is None:
            raise InputError("kind 'observed' needs the image's detection catalog: pass observed_catalog=.")
        if psf is None:
            psf = make_psf(config, fwhm_pix, pixel_scale)
        psf_hlr = psf_half_light_radius_pix(psf, pixel_scale)
        sigma = fwhm_pix / FWHM_PER_SIGMA if fwhm_pix else psf_hlr / np.sqrt(2.0 * np.log(2.0))
        population = fit_observed_population(observed_catalog, psf_hlr_pix=psf_hlr, psf_sigma_pix=sigma)
    if kind == "cosmos" and cosmos is None:
        raise InputError("kind 'cosmos' needs the COSMOS sample: pass cosmos=load_cosmos(config).")

    if n is None:
        n = draw_count(config.density or PUBLISHED_DENSITY, shape, pixel_scale, rng, border_pix=border_pix)
    sized = _sized(kind, config)
    if sized:
        # sizes before positions: each galaxy keeps its own separation and lies where its stamp fits
        params = draw_parameters(kind, n, config=config, mag_range=mag_range, rng=rng, pixel_scale=pixel_scale,
                                 cosmos=cosmos, population=population, mag_design=mag_design)
        r_psf = psf_radius_pix(psf, config, fwhm_pix, pixel_scale)
        radius = separation_radius_pix(config, fwhm_pix, pixel_scale, params["hlr_arcsec"])
        half = np.maximum(stamp_half_pix(kind, params, pixel_scale, r_psf), border_pix)
        placement = place_sized_sources(radius, half, shape, rng, mask=mask, method=config.placement)
        params = {k: v[placement.index] for k, v in params.items()}
    else:
        placement = place_sources(n, shape, rng, mask=mask, method=config.placement,
                                  min_sep_pix=min_separation_pix(config, fwhm_pix, pixel_scale, kind),
                                  border_pix=border_pix)
        params = draw_parameters(kind, placement.n, config=config, mag_range=mag_range, rng=rng,
                                 pixel_scale=pixel_scale, cosmos=cosmos, population=population, mag_design=mag_design)
    m = placement.n
    ra, dec = _sky_positions(placement.x, placement.y, wcs)
    cols = {
        "injection_id": np.arange(m, dtype=np.int64),
        "kind": np.full(m, kind, dtype="U8"),
        "x": placement.x,
        "y": placement.y,
        "ra": ra,
        "dec": dec,
        "mag": params["mag"],
        "flux": 10.0 ** (-0.4 * (params["mag"] - zeropoint)),
        "hlr_arcsec": params["hlr_arcsec"],
        "q": params["q"],
        "pa_deg": params["pa_deg"],
        "bulge_fraction": params["bulge_fraction"],
        "sersic_n": params["sersic_n"],
        "cosmos_index": params["cosmos_index"],
        "masked": placement.masked,
        "flag": np.where(placement.masked, FLAG_MASKED, 0).astype(np.int64),
    }
    meta = {
        "kind": kind, "n_requested": int(n), "n_placed": m, "placement": placement.method,
        "placement_complete": bool(placement.complete), "placement_message": placement.message,
        "min_sep_pix": float(placement.min_sep_pix), "border_pix": float(border_pix),
        "mag_bright": float(mag_range[0]), "mag_faint": float(mag_range[1]), "zeropoint": float(zeropoint),
        "pixel_scale": float(pixel_scale), "fwhm_pix": float(fwhm_pix) if fwhm_pix else 0.0,
        "density": float(config.density or PUBLISHED_DENSITY), "psf": config.psf,
        "per_source_separation": bool(sized),
    }
    if sized:
        meta.update({"n_unplaced": int(n - m),
                     "sep_radius_pix_min": float(radius.min()) if n else 0.0,
                     "sep_radius_pix_max": float(radius.max()) if n else 0.0,
                     "stamp_half_pix_min": float(half.min()) if n else 0.0,
                     "stamp_half_pix_max": float(half.max()) if n else 0.0})
    if population is not None:
        meta.update(population.meta())
    table = Table(meta=meta)
    for name, (dtype, unit, desc) in TRUTH_COLUMNS.items():
        table[name] = np.asarray(cols[name], dtype=dtype)
        table[name].unit = unit
        table[name].description = desc
    if noise is not None:
        ix, iy = pixel_index(placement.x, placement.y, shape)
        table["local_noise"] = np.asarray(noise, dtype=float)[iy, ix] if m else np.zeros(0)
        table["local_noise"].unit = _LOCAL_NOISE[1]
        table["local_noise"].description = _LOCAL_NOISE[2]
    return table


# --------------------------------------------------------------------------- rendering


def psf_enclosed_radius_pix(psf_pix, fraction: float = 0.995,
                            max_radius: float = MAX_PSF_RADIUS_PIX) -> tuple[float, float]:
    """Radius (pixels) enclosing ``fraction`` of a unit-flux PSF given in pixel units.

    The growth curve is that of the continuous profile, measured on drawings
    (``no_pixel``) centred on a sample:

    * the core on a grid of step ``1 / k`` pixel, with ``k`` the smallest
      integer that samples the profile at half GalSim's Nyquist scale (at
      most :data:`_ENCLOSED_MAX_OVERSAMPLE`), out to the radius where the
      fine grid reaches :data:`_ENCLOSED_MAX_SAMPLES` samples on a side;
    * beyond that, if needed, the wings on the pixel grid, where they are
      smooth on the scale of a pixel, added to the core's flux.

    Sampling a profile narrower than a pixel at pixel centres gives sums of
    samples that are not its flux (a Moffat of FWHM 1.4 px drawn on a grid
    centred between pixels sums to 0.987), so the growth curve of such a
    drawing never reaches 99.5 % and would wrongly call the wings extended.

    Returns
    -------
    radius : float
        The radius, at most ``max_radius``.
    enclosed : float
        Flux fraction inside ``radius`` (below ``fraction`` only when capped,
        e.g. for a Moffat with beta near 1).
    """
    flux = float(psf_pix.flux)
    k = int(min(max(np.ceil(2.0 / psf_pix.nyquist_scale), 1), _ENCLOSED_MAX_OVERSAMPLE))
    step = 1.0 / k
    # fine grid: half-size m samples (odd side 2m + 1), grown until the radius fits or the cap
    m_cap = min(int(np.ceil(max_radius * k)) + 1, _ENCLOSED_MAX_SAMPLES // 2)
    m = min(max(psf_pix.getGoodImageSize(step), 64 * k) // 2, m_cap)
    while True:
        r_sorted, cum = growth_curve(psf_pix, m, step, flux)
        trusted = min(m * step, max_radius)  # whole circles inside the drawing
        usable = int(np.searchsorted(r_sorted, trusted, side="right"))
        i = int(np.searchsorted(cum[:usable], fraction))
        if i < usable:
            return float(r_sorted[i]), float(cum[i])
        if trusted >= max_radius:
            return float(max_radius), float(cum[usable - 1])
        if m >= m_cap:
            break
        m = min(2 * m, m_cap)
    # wings: pixel-grid samples beyond the core radius, added to the core's flux
    r_core, core = trusted, float(cum[usable - 1])
    m = max(int(np.ceil(2.0 * r_core)), 32)
    m_cap = int(np.ceil(max_radius)) + 1
    while True:
        r_sorted, cum = growth_curve(psf_pix, m, 1.0, flux, inner=r_core)
        cum = core + cum
        trusted = min(float(m), max_radius)
        usable = int(np.searchsorted(r_sorted, trusted, side="right"))
        i = int(np.searchsorted(cum[:usable], fraction))
        if i < usable:
            return float(r_sorted[i]), float(cum[i])
        if trusted >= max_radius or m >= m_cap:
            return float(max_radius), float(cum[usable - 1]) if usable else core
        m = min(2 * m, m_cap)


#: Finest sampling of the PSF's growth curve: samples per pixel side.
_ENCLOSED_MAX_OVERSAMPLE = 16
#: Largest side (samples) of the fine grid of the PSF's growth curve.
_ENCLOSED_MAX_SAMPLES = 2049


def point_stamp_size(psf, pixel_scale: float, flux_fraction: float = 0.995) -> dict:
    """The stamp a point source gets from :func:`render_truth`, and why (recorded in ``run.json``).

    Parameters
    ----------
    psf : galsim.GSObject
        Unit-flux effective PSF in arcsec (:func:`comest_bayes.inject.psfmodel.make_psf`).
    pixel_scale : float
        Arcsec per pixel.
    flux_fraction : float
        Light fraction the stamps are sized to enclose (``render_truth``'s default 0.995).

    Returns
    -------
    dict
        ``half_size_pix`` (the point-source stamp is ``2 half_size + 1`` pixels
        on a side), ``psf_radius_pix`` and ``enclosed_fraction`` (of the
        continuous profile within that radius), ``flux_fraction`` (requested),
        ``capped`` (the radius hit :data:`MAX_PSF_RADIUS_PIX`) and ``source``
        (one sentence).  Galaxy stamps add the galaxy's own extent to the
        PSF radius.
    """
    r_psf, enclosed = psf_enclosed_radius_pix(galsim.PixelScale(pixel_scale).toImage(psf), flux_fraction)
    half = max(2, int(math.ceil(r_psf + 1.0)))
    capped = bool(enclosed < flux_fraction - 1e-6)
    source = (f"radius enclosing {100 * flux_fraction:.1f}% of the injected PSF's light, measured on its growth "
              f"curve, plus 1 px")
    if capped:
        source += f" (capped at {MAX_PSF_RADIUS_PIX} px: the stamp holds {100 * enclosed:.1f}%)"
    return {"half_size_pix": half, "psf_radius_pix": float(r_psf), "enclosed_fraction": float(enclosed),
            "flux_fraction": float(flux_fraction), "capped": capped, "source": source}


def growth_curve(psf_pix, m: int, step: float, flux: float, inner: float = 0.0):
    """Radii (pixels) of the samples of a ``(2m + 1)^2`` drawing of step ``step`` and their cumulative flux.

    Sorted by radius; only samples beyond ``inner`` pixels are kept.  The
    profile is centred on the central sample, and each sample carries the
    flux of its cell (GalSim's ``no_pixel`` drawing times the cell area).
    """
    side = 2 * m + 1
    image = psf_pix.drawImage(nx=side, ny=side, scale=step, method="no_pixel", dtype=np.float64).array
    off = (np.arange(side) - m) * step
    r = np.hypot(off[None, :], off[:, None]).ravel()
    values = image.ravel()
    if inner > 0:
        keep = r > inner
        r, values = r[keep], values[keep]
    order = np.argsort(r, kind="stable")
    return r[order], np.cumsum(values[order]) / flux


@dataclass(frozen=True)
class KGrid:
    """The half-plane ``k`` grid of batched drawing for one FFT size ``N``.

    Rows are in FFT order (``ky = 0 .. N/2-1, -N/2 .. -1``) followed by one
    extra row at ``ky = +N/2``, which is folded onto ``-N/2`` as GalSim's
    :meth:`galsim.Image.wrap` folds it; columns are ``kx = 0 .. N/2``, and the
    ``kx = N/2`` column also receives the (Hermitian) ``kx = -N/2`` values,
    as ``wrap(..., hermitian='x')`` does.
    Wavenumbers are in radians per pixel (spacing ``2 pi / N``).

    Attributes
    ----------
    nfft : int
        ``N``.
    kx : ndarray, shape (N/2+1,)
    ky : ndarray, shape (N+1,)
    kx2, kxy, ky2 : ndarray, shape (N+1, N/2+1)
        ``kx^2``, ``kx ky`` and ``ky^2`` on the grid.
    ky_mirror : ndarray of intp, shape (N+1,)
        Row holding ``-ky`` of each row (for folding the ``kx = N/2`` column).
    kmax : float
        Largest ``|k|`` on the grid.
    psf : ndarray of complex128, shape (N+1, N/2+1)
        The PSF's transform on the grid.
    sign_x, sign_y : ndarray, shapes (N/2+1,) and (N+1,)
        ``(-1)^i`` of each column and row: the phase of a shift by ``N/2``
        pixels, which puts the source at the centre of the inverse transform.
    """

    nfft: int
    kx: np.ndarray = field(repr=False)
    ky: np.ndarray = field(repr=False)
    kx2: np.ndarray = field(repr=False)
    kxy: np.ndarray = field(repr=False)
    ky2: np.ndarray = field(repr=False)
    ky_mirror: np.ndarray = field(repr=False)
    kmax: float
    psf: np.ndarray = field(repr=False)
    sign_x: np.ndarray = field(repr=False)
    sign_y: np.ndarray = field(repr=False)


class StampRenderer:
    """Draws PSF-convolved sources into stamps, reusing the PSF's Fourier transform.

    Per FFT size ``N`` (:func:`fft_size`: the smallest even 5-smooth number
    >= ``2 h + 2`` for a stamp of half-size ``h``) the PSF's
    transform is drawn once on the half-plane k grid GalSim's ``drawFFT``
    uses (spacing ``2 pi / N`` per pixel; extended and later wrapped when the
    PSF has power beyond the Nyquist frequency, so aliasing is treated as
    GalSim does).  Per source: the source's transform
    (:meth:`galsim.GSObject.drawKImage`), times the PSF's, times the phase of
    the sub-pixel shift, wrapped to ``N x N`` (:meth:`galsim.Image.wrap`),
    inverse real FFT (NumPy).

    Parameters
    ----------
    psf_pix : galsim.GSObject
        Unit-flux effective PSF in *pixel* units.
    """

    def __init__(self, psf_pix):
        self.psf = psf_pix
        self._kcache: dict[int, tuple] = {}
        self._bcache: dict[int, KGrid | None] = {}

    def _grid(self, nfft: int):
        cached = self._kcache.get(nfft)
        if cached is None:
            dk = 2.0 * np.pi / nfft
            maxk = self.psf.maxk
            nk = nfft if np.pi > maxk else 2 * int(np.ceil(maxk / dk))
            bounds = galsim.BoundsI(0, nk // 2, -(nk // 2), nk // 2)
            kimage = galsim.ImageCD(bounds, scale=dk)
            self.psf.drawKImage(image=kimage, recenter=False)
            kx = dk * np.arange(0, nk // 2 + 1)
            ky = dk * np.arange(-(nk // 2), nk // 2 + 1)
            wrap = galsim.BoundsI(0, nfft // 2, -(nfft // 2), nfft // 2 - 1)
            cached = (bounds, dk, kimage.array.copy(), kx, ky, wrap)
            self._kcache[nfft] = cached
        return cached

    def draw(self, profile_pix, flux: float, dx: float, dy: float, half_size: int) -> np.ndarray:
        """The PSF-convolved source, sampled at pixel centres (GalSim's ``no_pixel``).

        Parameters
        ----------
        profile_pix : galsim.GSObject or None
            Source in pixel units with its flux, centred on the origin; None
            for a point source.
        flux : float
            Total flux (used only for a point source).
        dx, dy : float
            Offset of the source centre from the centre of the stamp's middle pixel, pixels.
        half_size : int
            The stamp is ``2 half_size + 1`` pixels on a side.

        Returns
        -------
        ndarray, shape (2 half_size + 1, 2 half_size + 1), float64
        """
        h = int(half_size)
        nfft = fft_size(2 * h + 2)
        bounds, dk, psf_k, kx, ky, wrap = self._grid(nfft)
        kimage = galsim.ImageCD(bounds, scale=dk)
        arr = kimage.array
        # shift theorem with GalSim's convention F(k) = int f(x) exp(-i k.x) d^2x
        phase = np.exp(-1j * dy * ky)[:, None] * np.exp(-1j * dx * kx)[None, :]
        if profile_pix is None:
            np.multiply(psf_k, phase * flux, out=arr)
        else:
            profile_pix.drawKImage(image=kimage, recenter=False)
            arr *= psf_k
            arr *= phase
        folded = kimage.wrap(wrap, hermitian="x").array  # rows ky = -N/2 .. N/2-1, columns kx = 0 .. N/2
        real = np.fft.irfft2(np.fft.ifftshift(folded, axes=0), s=(nfft, nfft))
        idx = np.arange(-h, h + 1) % nfft  # real[0, 0] is the profile's origin
        return real[np.ix_(idx, idx)]

    def batch_grid(self, nfft: int) -> KGrid | None:
        """The grid of :meth:`draw_batch` for FFT size ``nfft`` (cached).

        None when the PSF has power beyond the Nyquist frequency (its ``k``
        image is wider than ``nfft``): those stamps need GalSim's general
        folding and take :meth:`draw`.
        """
        cache = self._bcache
        if nfft in cache:
            return cache[nfft]
        bounds, dk, psf_k, kx, ky_rows, wrap = self._grid(nfft)
        if psf_k.shape[0] != nfft + 1:
            cache[nfft] = None
            return None
        half = nfft // 2
        # _grid's rows are ky = -N/2 .. N/2; reorder to FFT order plus the extra +N/2 row
        order = np.r_[half:nfft, 0:half, nfft]
        ky = ky_rows[order]
        rows = np.r_[0:half, -half:0, half]  # ky / dk
        position = {int(v): r for r, v in enumerate(rows)}
        mirror = np.array([position[int(-v)] for v in rows], dtype=np.intp)
        grid = KGrid(
            nfft=nfft, kx=kx, ky=ky, kx2=np.broadcast_to(kx * kx, (nfft + 1, kx.size)).copy(),
            kxy=np.multiply.outer(ky, kx), ky2=np.broadcast_to((ky * ky)[:, None], (nfft + 1, kx.size)).copy(),
            ky_mirror=mirror,
            kmax=float(np.hypot(kx.max(), np.abs(ky).max())), psf=np.ascontiguousarray(psf_k[order]),
            sign_x=np.where(np.arange(kx.size) % 2 == 0, 1.0, -1.0), sign_y=np.where(rows % 2 == 0, 1.0, -1.0))
        cache[nfft] = grid
        return grid

    def draw_batch(self, grid: KGrid, source_k: np.ndarray, dx, dy) -> np.ndarray:
        """PSF-convolved sources of one FFT size, sampled at pixel centres.

        Parameters
        ----------
        grid : KGrid
            From :meth:`batch_grid`.
        source_k : ndarray, shape (B, N+1, N/2+1) or (B, 1, 1)
            Each source's transform on the grid (flux included, centred on
            the origin); (B, 1, 1) for point sources (their flux).
        dx, dy : array_like, shape (B,)
            Offsets of the source centres from the centre of the stamps'
            middle pixel, pixels.

        Returns
        -------
        ndarray, shape (B, N, N), float64
            Source ``b`` is centred at pixel ``(N/2 + dy[b], N/2 + dx[b])``
            (row, column); the stamp of half-size ``h`` is
            ``[:, N/2-h : N/2+h+1, N/2-h : N/2+h+1]``.
        """
        n = grid.nfft
        dx = np.asarray(dx, dtype=float)[:, None]
        dy = np.asarray(dy, dtype=float)[:, None]
        fk = np.multiply(source_k, grid.psf, dtype=complex)
        # shift theorem, F(k) exp(-i k.d), with GalSim's sign convention; the signs move the
        # origin to the middle of the array
        phase_y = np.exp(-1j * dy * grid.ky)
        phase_y *= grid.sign_y
        phase_x = np.exp(-1j * dx * grid.kx)
        phase_x *= grid.sign_x
        fk *= phase_y[:, :, None]
        fk *= phase_x[:, None, :]
        # fold as Image.wrap(hermitian='x'): the kx = N/2 column gains the kx = -N/2 one, which is
        # F(-N/2, ky) = conj F(N/2, -ky) for a real image; then the ky = +N/2 row folds onto -N/2
        fk[:, :, -1] += np.conj(fk[:, grid.ky_mirror, -1])
        fk[:, n // 2, :] += fk[:, n, :]
        return np.fft.irfft2(fk[:, :n, :], s=(n, n))


def _deposit(image, stamp, x0: int, y0: int, noise_rng, gain) -> None:
    """Add ``stamp`` (corner at pixel ``(y0, x0)``) to ``image``, clipped, with photon noise if asked.

    ``noise_rng`` None: no noise; else each pixel gets ``Poisson(gain s) / gain - s``
    (``s`` clipped at 0 for the Poisson mean).
    """
    ny, nx = image.shape
    sy, sx = stamp.shape
    cx0, cx1, cy0, cy1 = max(x0, 0), min(x0 + sx, nx), max(y0, 0), min(y0 + sy, ny)
    sub = stamp[cy0 - y0:cy1 - y0, cx0 - x0:cx1 - x0]
    if noise_rng is not None:
        lam = np.multiply(sub, gain)
        np.maximum(lam, 0.0, out=lam)
        shot = np.subtract(noise_rng.poisson(lam), lam, out=lam)  # counts - mean, in the mean's buffer
        shot /= gain
        shot += sub
        sub = shot
    image[cy0:cy1, cx0:cx1] += sub


def render_truth(base_image, truth: Table, *, psf, config: InjectionConfig, pixel_scale: float,
                 rng_seed, zeropoint: float | None = None, gain: float | None = None,
                 cosmos: CosmosSample | None = None, wcs=None, flux_fraction: float = 0.995,
                 batched: bool = True):
    """Add the sources of ``truth`` to a copy of ``base_image``.

    Parameters
    ----------
    base_image : ndarray, shape (ny, nx)
        Image the sources are added to (not modified).
    truth : astropy.table.Table
        From :func:`make_truth` (columns :data:`TRUTH_COLUMNS`).
    psf : galsim.GSObject
        Unit-flux effective PSF in arcsec (:func:`comest_bayes.inject.psfmodel.make_psf`).
    config : InjectionConfig
        ``photon_noise``.
    pixel_scale : float
        Arcsec per pixel: the PSF is converted to pixels with it, and so are
        the sources when there is no WCS.
    zeropoint : float, optional
        When given, checked against the truth's ``mag`` and ``flux``.
    gain : float, optional
        Electrons per image unit; photon noise is added only when given (and
        ``config.photon_noise``).
    rng_seed : comest_bayes.seeding.Seed
        Seed of the photon noise (the only randomness here): a non-negative int or a SeedSequence.
    cosmos : CosmosSample, optional
        Required for ``cosmos`` rows.
    wcs : astropy.wcs.WCS, optional
        Sources are mapped to pixels with its local Jacobian at each position.
    flux_fraction : float
        Light fraction the stamps are sized to enclose.
    batched : bool
        Draw ``point`` and ``buldisk`` stamps in batches (default; see
        ``docs/injection.md``).  False draws every stamp with GalSim, one by one.

    Returns
    -------
    image : ndarray, shape (ny, nx), float32
        ``base_image + sources``.
    truth : astropy.table.Table
        A copy of ``truth`` with ``flag`` updated (2: stamp off the image, 4:
        drawing failed) and rendering statistics in ``meta``
        (``render_seconds``, ``n_drawn``, ``n_batched`` (drawn in batches),
        ``n_off_image``, ``n_draw_errors``, ``draw_errors`` (the first five
        messages), ``photon_noise``, ``gain`` (0 when not given),
        ``flux_fraction``, ``psf_radius_pix``, ``psf_enclosed_fraction``).

    Warns
    -----
    UserWarning
        When the PSF needs a radius beyond :data:`MAX_PSF_RADIUS_PIX` pixels
        to enclose ``flux_fraction``; stamps are then cut there.
    """
    t_start = time.perf_counter()
    image = np.array(base_image, dtype=np.float32, copy=True)
    if image.ndim != 2:
        raise InputError(f"the base image must be 2-D, got shape {image.shape}.")
    if not (pixel_scale and np.isfinite(pixel_scale) and pixel_scale > 0):
        raise InputError(f"pixel scale must be a positive number of arcsec/pixel, got {pixel_scale!r}.")
    if not 0.5 < flux_fraction < 1.0:
        raise InputError(f"flux_fraction must be in (0.5, 1), got {flux_fraction!r}.")
    missing = [c for c in ("x", "y", "flux", "kind", "flag") if c not in truth.colnames]
    if missing:
        raise InputError(f"the truth table lacks columns {missing}; build it with make_truth.")
    out = truth.copy(copy_data=True)
    if zeropoint is not None and len(out) and "mag" in out.colnames:
        expected = 10.0 ** (-0.4 * (np.asarray(out["mag"], dtype=float) - zeropoint))
        if not np.allclose(expected, np.asarray(out["flux"], dtype=float), rtol=1e-6, atol=0):
            raise InputError(f"the truth fluxes do not follow its magnitudes with zero point {zeropoint}; "
                             f"the truth was made with another zero point.")
    use_noise = bool(config.photon_noise) and gain is not None and np.isfinite(gain) and gain > 0
    noise_rng = rng_for(rng_seed) if use_noise else None  # the numbers of numpy.random.default_rng(rng_seed)

    ny, nx = image.shape
    psf_pix = galsim.PixelScale(pixel_scale).toImage(psf)
    r_psf, psf_enclosed = psf_enclosed_radius_pix(psf_pix, flux_fraction)
    if psf_enclosed < flux_fraction - 1e-6:
        warnings.warn(f"the PSF's wings are so extended that stamps of radius {r_psf:.0f} pixels hold only "
                      f"{100 * psf_enclosed:.1f}% of a point source's light (requested "
                      f"{100 * flux_fraction:.1f}%); injected sources lack the rest", UserWarning, stacklevel=2)
    renderer = StampRenderer(psf_pix)

    n = len(out)
    x = np.asarray(out["x"], dtype=float)
    y = np.asarray(out["y"], dtype=float)
    flux = np.asarray(out["flux"], dtype=float)
    kinds = np.asarray(out["kind"]).astype(str)
    flag = np.asarray(out["flag"], dtype=np.int64).copy()
    flag &= ~(FLAG_OFF_IMAGE | FLAG_DRAW_ERROR)  # recomputed here

    def col(name, fill):
        return np.asarray(out[name], dtype=float) if name in out.colnames else np.full(n, fill)

    hlr, q, pa = col("hlr_arcsec", np.nan), col("q", np.nan), col("pa_deg", 0.0)
    bf, sn = col("bulge_fraction", np.nan), col("sersic_n", np.nan)
    cidx = np.asarray(out["cosmos_index"], dtype=np.int64) if "cosmos_index" in out.colnames \
        else np.full(n, -1)
    jac = local_jacobians(x, y, wcs=wcs, pixel_scale=pixel_scale)
    # smallest singular value: arcsec per pixel along the most compressed direction
    smin = np.linalg.svd(jac, compute_uv=False)[:, -1] if n else np.zeros(0)

    errors = []
    finite = np.isfinite(x) & np.isfinite(y) & np.isfinite(flux)
    for i in np.flatnonzero(~finite):
        flag[i] |= FLAG_DRAW_ERROR
        errors.append(f"{i}: non-finite position or flux")
    ixs = np.floor(np.where(finite, x, 0.0) + 0.5).astype(np.int64)
    iys = np.floor(np.where(finite, y, 0.0) + 0.5).astype(np.int64)

    drawn = np.zeros(n, dtype=bool)
    in_batch = np.zeros(n, dtype=bool)
    if batched and n:
        in_batch = _draw_batched(image, renderer, kinds=kinds, finite=finite, flux=flux, x=x, y=y, ix=ixs, iy=iys,
                                 hlr=hlr, q=q, pa=pa, bf=bf, jac=jac, smin=smin, r_psf=r_psf,
                                 flux_fraction=flux_fraction, flag=flag, drawn=drawn, noise_rng=noise_rng,
                                 gain=gain)

    for i in np.flatnonzero(finite & ~in_batch):
        xi, yi, ix, iy = x[i], y[i], int(ixs[i]), int(iys[i])
        try:
            sp = source_profile(kinds[i], flux=flux[i], hlr_arcsec=hlr[i], q=q[i], pa_deg=pa[i],
                                bulge_fraction=bf[i], sersic_n=sn[i], cosmos_index=cidx[i], cosmos=cosmos,
                                fraction=flux_fraction)
            if sp.profile is None:
                prof = None
                r_src = 0.0
            else:
                j = jac[i]
                prof = galsim.JacobianWCS(j[0, 0], j[0, 1], j[1, 0], j[1, 1]).toImage(sp.profile)
                r_src = sp.radius_arcsec / smin[i]
            h = max(2, int(math.ceil(math.hypot(r_src, r_psf) + 1.0)))
            x0, x1, y0, y1 = ix - h, ix + h + 1, iy - h, iy + h + 1
            if max(x0, 0) >= min(x1, nx) or max(y0, 0) >= min(y1, ny):
                flag[i] |= FLAG_OFF_IMAGE
                continue
            if x0 < 0 or y0 < 0 or x1 > nx or y1 > ny:
                flag[i] |= FLAG_OFF_IMAGE
            stamp = renderer.draw(prof, flux[i], xi - ix, yi - iy, h)
            _deposit(image, stamp, x0, y0, noise_rng, gain)
            drawn[i] = True
        except ComestError:
            raise
        except (galsim.GalSimError, ValueError, RuntimeError, MemoryError, ArithmeticError) as exc:
            flag[i] |= FLAG_DRAW_ERROR
            errors.append(f"{i}: {type(exc).__name__}: {exc}")

    out["flag"] = flag
    out.meta.update({
        "render_seconds": time.perf_counter() - t_start, "n_drawn": int(drawn.sum()),
        "n_batched": int((drawn & in_batch).sum()),
        "n_off_image": int(((flag & FLAG_OFF_IMAGE) != 0).sum()),
        "n_draw_errors": int(((flag & FLAG_DRAW_ERROR) != 0).sum()),
        "draw_errors": "; ".join(errors[:5]) + (f"; ... ({len(errors)} in all)" if len(errors) > 5 else ""),
        "photon_noise": use_noise, "gain": float(gain) if gain is not None else 0.0,
        "flux_fraction": float(flux_fraction), "psf_radius_pix": float(r_psf),
        "psf_enclosed_fraction": float(psf_enclosed),
    })
    return image, out


def _draw_batched(image, renderer: StampRenderer, *, kinds, finite, flux, x, y, ix, iy, hlr, q, pa, bf, jac, smin,
                  r_psf: float, flux_fraction: float, flag, drawn, noise_rng, gain) -> np.ndarray:
    """Draw the batchable sources (see ``docs/injection.md``); returns which rows it took.

    Updates ``flag`` (off-image bit), ``drawn`` and ``image`` in place.  Rows
    it does not take (other kinds, parameters outside the model's domain,
    FFTs beyond :data:`MAX_FFT_SIZE`, PSFs with power beyond Nyquist) are
    left for the per-source path.
    """
    ny, nx = image.shape
    n = len(kinds)
    point = finite & (kinds == "point")
    with np.errstate(invalid="ignore"):
        buldisk = (finite & (kinds == "buldisk") & np.isfinite(hlr) & (hlr > 0) & (q > 0) & (q <= 1)
                   & np.isfinite(pa) & (bf >= 0) & (bf <= 1) & np.isfinite(smin) & (smin > 0))
    take = point | buldisk  # the kinds of BATCHED_KINDS
    if not take.any():
        return take
    r_src = np.zeros(n)
    quad = np.zeros((n, 2, 2))
    if buldisk.any():
        b = np.flatnonzero(buldisk)
        radius = hlr[b] * buldisk_radius_per_hlr(bf[b], flux_fraction)
        radius = np.where(q[b] < 1.0, radius / np.sqrt(q[b]), radius)  # as source_profile
        r_src[b] = radius / smin[b]
        quad[b] = kspace_quadratic_forms(hlr[b], q[b], pa[b], jac[b])
    half = np.maximum(2, np.ceil(np.hypot(r_src, r_psf) + 1.0)).astype(np.int64)
    need = 2 * half + 2
    take &= need <= _FFT_SIZES[-1]  # larger: the per-source path flags them
    nfft = np.zeros(n, dtype=np.int64)
    nfft[take] = _FFT_SIZES[np.searchsorted(_FFT_SIZES, need[take])]
    # largest unit-profile |k| on the grid: sqrt of Q's largest eigenvalue times the grid's largest |k|
    a, c, bxy = quad[:, 0, 0], quad[:, 1, 1], quad[:, 0, 1]
    lam_max = 0.5 * (a + c) + np.sqrt((0.5 * (a - c)) ** 2 + bxy ** 2)
    take &= ~buldisk | (np.sqrt(lam_max) * np.pi * np.sqrt(2.0) <= _MAX_BATCH_KAPPA)
    x0, y0 = ix - half, iy - half
    x1, y1 = x0 + 2 * half + 1, y0 + 2 * half + 1
    off = (np.maximum(x0, 0) >= np.minimum(x1, nx)) | (np.maximum(y0, 0) >= np.minimum(y1, ny))
    partial = (x0 < 0) | (y0 < 0) | (x1 > nx) | (y1 > ny)
    for size in np.unique(nfft[take]):
        grid = renderer.batch_grid(int(size))
        rows = np.flatnonzero(take & (nfft == size))
        if grid is None:
            take[rows] = False
            continue
        flag[rows[partial[rows]]] |= FLAG_OFF_IMAGE
        rows = rows[~off[rows]]
        centre = int(size) // 2
        chunk = max(1, BATCH_CHUNK_ELEMENTS // grid.psf.size)
        for start in range(0, rows.size, chunk):
            idx = rows[start:start + chunk]
            bulge_disk = buldisk[idx]
            if not bulge_disk.any():
                src = flux[idx][:, None, None]  # point sources: the PSF times the flux
            else:
                j = idx[bulge_disk]
                ksq = quad[j, 0, 0][:, None, None] * grid.kx2
                ksq += (2.0 * quad[j, 0, 1])[:, None, None] * grid.kxy
                ksq += quad[j, 1, 1][:, None, None] * grid.ky2
                table = devaucouleurs_k_table(float(np.sqrt(lam_max[j].max())) * grid.kmax)
                kvalues = buldisk_k(ksq, bf[j][:, None, None], table)
                kvalues *= flux[j][:, None, None]
                if bulge_disk.all():
                    src = kvalues
                else:
                    src = np.empty((idx.size,) + grid.psf.shape)
                    src[:] = flux[idx][:, None, None]
                    src[bulge_disk] = kvalues
            real = renderer.draw_batch(grid, src, x[idx] - ix[idx], y[idx] - iy[idx])
            for k, i in enumerate(idx):
                h = int(half[i])
                stamp = real[k, centre - h:centre + h + 1, centre - h:centre + h + 1]
                _deposit(image, stamp, int(x0[i]), int(y0[i]), noise_rng, gain)
                drawn[i] = True
    return take
