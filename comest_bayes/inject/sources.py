"""Synthetic source populations: the drawn parameters and the GalSim profiles.

This module decides *what* is injected: it draws the parameters of each kind
of source from explicit random generators and turns one set of parameters
into a GalSim profile.  Rendering the profiles into an image is
:mod:`comest_bayes.inject.render`; positions are :mod:`comest_bayes.inject.placement`.
Everything here is a pure function of its arguments except :func:`load_cosmos`
and :func:`read_psf_image`, which read files by nature.

Units: sizes in arcsec unless a name ends in ``_pix``; angles in degrees;
fluxes in image units, ``flux = 10**(-0.4 * (mag - zeropoint))``; profiles are
built in *world* coordinates (arcsec) with their total flux.

Source kinds and their parameters
---------------------------------
Every kind draws ``mag`` uniformly in ``mag_range`` (given by the caller;
``injection.mag_range``), except ``observed`` which follows the image's own
number counts.  The position angle ``pa_deg`` is uniform in [0, 180) for
every extended kind: it is GalSim's shear angle ``beta``, the angle of the
major axis counter-clockwise from the +u axis of the local world frame
(u = west = -RA cos(Dec), v = north; without a WCS u = +x and v = +y).  The
axis ratio ``q = b/a`` is applied with ``shear(q=q)``, which preserves area, so
``hlr_arcsec`` is the *circularised* half-light radius ``sqrt(a b)``.

``point``
    The PSF alone.  No shape parameters (NaN in the truth).
``buldisk``
    A de Vaucouleurs bulge (:class:`galsim.DeVaucouleurs`, a Sersic n=4
    profile) plus an exponential disk (:class:`galsim.Exponential`) with the
    same half-light radius, axis ratio and position angle, so the sum has
    exactly that half-light radius.  Uniform in ``hlr_arcsec``
    (``injection.hlr_range``, default 0.35-0.75"), ``bulge_fraction`` (flux
    fraction of the bulge, ``bulge_fraction_range``, default 0-1), ``q``
    (``q_range``, default 0.4-1.0) and ``pa_deg``.
``sersic``
    One :class:`galsim.Sersic` with index ``sersic_n`` drawn uniformly from a
    grid of step 0.05 spanning ``sersic_n_range`` (default 0.5-4.0: 71 values;
    the step widens if needed to keep at most 80).  Each index's unit profile
    is built once per process (GalSim's Hankel tables cost 2-30 ms per index)
    and every source is a transformation of it.  Uniform ``hlr_arcsec``, ``q``
    and ``pa_deg`` as for ``buldisk``.
``cosmos``
    Real HST/ACS F814W galaxies from a GalSim RealGalaxyCatalog directory
    (``injection.cosmos_dir`` / ``cosmos_file``; load with
    :func:`load_cosmos`).  ``cosmos_index`` is drawn with probability
    proportional to the catalog's ``WEIGHT`` column (GalSim's selection
    weights; uniform when absent); the galaxy (deconvolved from the HST PSF by
    :class:`galsim.RealGalaxy`) is rescaled to the drawn magnitude with
    ``withFlux`` and rotated by ``pa_deg``.  It keeps the noise of its HST
    image, rescaled with the flux (so the galaxy's S/N in the HST image is
    unchanged; injecting much brighter than the catalog magnitudes makes that
    noise visible).  ``hlr_arcsec`` and ``q`` are NaN.
``observed``
    Magnitudes and sizes follow the image's own detection catalog (columns
    ``mag_auto``, ``flux_radius`` in pixels, ``snr_auto``, ``flags``, ``a``,
    ``b``; see :func:`fit_observed_population`): magnitudes follow the power
    law ``dN/dm ~ 10**(slope * m)`` fitted to the well-detected counts and
    extrapolated over the whole ``mag_range``; the half-light radius follows
    the fitted median ``log10(flux_radius)``-magnitude relation with its
    scatter, deconvolved from the PSF as ``hlr^2 = r_obs^2 - r_psf^2`` (floored
    at a tenth of the PSF half-light radius); the axis ratio is resampled from
    the PSF-deconvolved ``b/a`` of resolved detections; the profile is a Sersic
    with the index drawn as for ``sersic``.

Truncation
----------
Sersic profiles with large indices have so much light at large radii that no
practical stamp holds 99.5% of it (an untruncated de Vaucouleurs profile has
5.7% of its flux beyond 8 half-light radii).  Profiles whose untruncated light
beyond :data:`TRUNC_HLR` = 8 half-light radii exceeds :data:`TRUNC_TAIL` = 1e-4
(n >~ 1.1, the de Vaucouleurs bulge included) are therefore truncated there,
as the SDSS photometric pipeline truncates its de Vaucouleurs model near 8 r_e
(Stoughton et al. 2002, AJ 123, 485).  The truncated profile is normalised to
the requested flux and its half-light radius is the requested one
(``flux_untruncated=False``).  The exponential disk is never truncated.

Fourier transforms for batched drawing
--------------------------------------
:mod:`comest_bayes.inject.render` draws ``point`` and ``buldisk`` stamps in
batches with NumPy instead of one GalSim call per source
(:data:`BATCHED_KINDS`).  A circular bulge+disk of unit half-light radius
and unit flux has the radial transform
``F(k) = B F_deV(k) + (1 - B) F_exp(k)`` (``B`` the bulge fraction), with
GalSim's convention ``F(k) = int f(x) exp(-i k.x) d^2x``:

* the exponential disk's transform is analytic,
  ``F_exp(k) = (1 + (k r_s)^2)^(-3/2)`` with ``r_s`` the scale radius
  (``1 / 1.67835`` half-light radii) (e.g. GalSim's ``Exponential``
  documentation; the 2-D Fourier transform of ``exp(-r / r_s)``);
* the truncated de Vaucouleurs bulge's transform has no closed form: it is
  tabulated once per process from GalSim's own ``kValue`` on a uniform grid of
  step :data:`DEV_K_STEP` in ``k`` and interpolated linearly
  (:func:`devaucouleurs_k_table`; measured: within 2e-6 of GalSim's values).

An elliptical source with shear matrix ``S`` (:func:`shear_matrices`, GalSim's
``Shear.getMatrix``), half-light radius ``r`` (arcsec) and local WCS
Jacobian ``J`` (arcsec per pixel) has in pixel units the transform
``flux F(|M k|)`` with ``M = r S J^-T`` (:func:`kspace_quadratic_forms` returns
the quadratic form ``M^T M``), so a whole batch of stamps is a few array
operations on a shared ``k`` grid.

PSF
---
:func:`make_psf` returns the *effective* PSF (optics, atmosphere and pixel
response together) as a unit-flux GalSim profile in arcsec: a Moffat, Gaussian
or Kolmogorov of the image's FWHM, or a FITS PSF image.  The renderer samples
the PSF-convolved profile at pixel centres without convolving by the pixel
again (GalSim's ``method='no_pixel'``), so the profile must already hold the
pixel response:

* when the seeing was *fitted* on the image's stars
  (:func:`comest_bayes.detect.psf.estimate_fwhm` fits a Moffat integrated over the
  pixels, with free beta), the fitted Moffat (its FWHM and its beta) is
  convolved with the square pixel (``pixel_integrated=True``): the injected
  point sources are then the fitted star model, pixel for pixel, and their
  flux does not depend on where they fall within a pixel, even for a PSF
  narrower than a pixel;
* a FWHM given with ``--fwhm`` or read from a header keyword was measured on
  the pixelated image (SExtractor's ``FWHM_IMAGE``, the DECam pipeline's
  ``FWHM``), so the analytic profile of that FWHM is the effective PSF itself;
* PSF models sampled at the detector pixel (PSFEx, WebbPSF ``DET_SAMP``)
  include the pixel response.

How the PSF of a run is chosen and where each of its numbers came from is
decided by :func:`comest_bayes.detect.psf.injection_psf` and recorded in ``run.json``
(``psf``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import galsim
import numpy as np
from astropy.io import fits
from scipy.optimize import minimize_scalar
from scipy.special import gammainc, gammaincinv

from comest_bayes.constants import FWHM_PER_SIGMA as _FWHM_PER_SIGMA
from comest_bayes.config import InjectionConfig, KINDS, PSF_KINDS
from comest_bayes.errors import InputError, InputFileError

__all__ = [
    "TRUNC_HLR", "TRUNC_TAIL", "SERSIC_N_STEP", "MAX_SERSIC_INDICES", "FWHM_PER_SIGMA",
    "SourceProfile", "sersic_index_grid", "sersic_truncation", "sersic_enclosed_radius",
    "bulge_disk_components", "source_profile", "draw_magnitudes", "draw_parameters",
    "BATCHED_KINDS", "DEV_K_STEP", "RadialKTable", "devaucouleurs_k_table", "exponential_k", "buldisk_k",
    "buldisk_radius_per_hlr", "shear_matrices", "kspace_quadratic_forms",
    "make_psf", "read_psf_image", "psf_half_light_radius_pix", "DEFAULT_MOFFAT_BETA",
    "CosmosSample", "load_cosmos",
    "ObservedPopulation", "fit_count_slope", "fit_observed_population",
]

#: Sersic profiles are truncated at this many half-light radii (see the module docstring).
TRUNC_HLR = 8.0
#: ...when their untruncated light beyond it exceeds this fraction.
TRUNC_TAIL = 1e-4
#: Spacing of the Sersic index grid.
SERSIC_N_STEP = 0.05
#: Largest number of distinct Sersic indices (GalSim caches the tables of 100).
MAX_SERSIC_INDICES = 80
#: FWHM of a Gaussian in units of its sigma, 2 sqrt(2 ln 2).
FWHM_PER_SIGMA = _FWHM_PER_SIGMA  # re-exported: comest_bayes.constants is its home
#: Moffat beta injected when neither the configuration nor the image's stars give one.
DEFAULT_MOFFAT_BETA = 3.0

# Columns of a GalSim RealGalaxyCatalog naming files that must exist in its directory.
_COSMOS_FILE_COLUMNS = ("GAL_FILENAME", "PSF_FILENAME", "NOISE_FILENAME")


# --------------------------------------------------------------------------- Sersic helpers


def sersic_index_grid(n_range) -> np.ndarray:
    """Discrete Sersic indices spanning ``n_range``.

    Step :data:`SERSIC_N_STEP`, widened if needed to keep at most
    :data:`MAX_SERSIC_INDICES` values; both ends included.

    Parameters
    ----------
    n_range : (float, float)
        Lowest and highest index, within GalSim's 0.3-6.2.

    Returns
    -------
    ndarray of float, shape (k,)
    """
    lo, hi = float(n_range[0]), float(n_range[1])
    if hi <= lo:
        return np.array([lo])
    step = max(SERSIC_N_STEP, (hi - lo) / (MAX_SERSIC_INDICES - 1))
    k = int(np.floor((hi - lo) / step + 1e-9)) + 1
    grid = lo + step * np.arange(k)
    if hi - grid[-1] > 1e-9:
        grid = np.append(grid, hi)
    return np.round(grid, 6)


def _b_sersic(n: float) -> float:
    """b_n with I ~ exp(-b_n (r/r_e)^(1/n)) and r_e the half-light radius: P(2n, b_n) = 1/2."""
    return float(gammaincinv(2.0 * n, 0.5))


def sersic_truncation(n: float) -> float:
    """Truncation radius in half-light radii for index ``n`` (0 = untruncated).

    :data:`TRUNC_HLR` when the untruncated profile has more than
    :data:`TRUNC_TAIL` of its light beyond that radius, else 0.
    """
    tail = 1.0 - gammainc(2.0 * n, _b_sersic(n) * TRUNC_HLR ** (1.0 / n))
    return TRUNC_HLR if tail > TRUNC_TAIL else 0.0


def sersic_enclosed_radius(n: float, scale_radius: float, trunc: float, fraction: float) -> float:
    """Radius enclosing ``fraction`` of the flux of a (possibly truncated) circular Sersic profile.

    GalSim's Sersic is ``I(r) ~ exp(-(r / scale_radius)^(1/n))`` for
    ``r < trunc`` (``trunc = 0``: no truncation); the flux inside ``r`` is
    proportional to the regularised incomplete gamma function
    ``P(2n, (r/scale_radius)^(1/n))``.

    Parameters
    ----------
    n : float
        Sersic index.
    scale_radius, trunc : float
        GalSim's ``scale_radius`` and ``trunc`` (same units; the result has them too).
    fraction : float
        Enclosed flux fraction in (0, 1).
    """
    total = gammainc(2.0 * n, (trunc / scale_radius) ** (1.0 / n)) if trunc > 0 else 1.0
    return float(scale_radius * gammaincinv(2.0 * n, fraction * total) ** n)


@lru_cache(maxsize=256)
def _trunc_factor(n: float) -> float:
    return sersic_truncation(n)


@lru_cache(maxsize=256)
def _growth_curve(n: float) -> tuple[np.ndarray, np.ndarray]:
    """Enclosed-flux fraction of our (truncated) unit-half-light-radius Sersic of index ``n``.

    Scale-free: with the truncation a fixed multiple of the half-light radius,
    the curve in units of the half-light radius depends on ``n`` only.

    Returns
    -------
    x : ndarray
        Radii in half-light radii, 0 to 60 (fine steps).
    frac : ndarray
        Flux fraction inside each radius (1 at and beyond the truncation).
    """
    t = _trunc_factor(n)
    if t == 0.0:
        r0, total = 1.0 / _b_sersic(n) ** n, 1.0
    else:
        r0 = _unit_sersic(n).scale_radius
        total = gammainc(2.0 * n, (t / r0) ** (1.0 / n))
    x = np.linspace(0.0, 60.0, 6001)
    frac = np.minimum(gammainc(2.0 * n, (x / r0) ** (1.0 / n)) / total, 1.0)
    if t > 0:
        frac[x >= t] = 1.0
    return x, frac


def _radius_per_hlr(n: float, fraction: float) -> float:
    """Radius enclosing ``fraction`` of our (truncated) Sersic, in half-light radii."""
    x, frac = _growth_curve(float(n))
    k = min(int(np.searchsorted(frac, fraction)), x.size - 1)
    return float(x[k])


def _buldisk_radius_per_hlr(bulge_fraction: float, fraction: float) -> float:
    """Radius enclosing ``fraction`` of bulge + disk of equal half-light radius, in half-light radii."""
    x, fb = _growth_curve(4.0)
    _, fd = _growth_curve(1.0)
    combined = bulge_fraction * fb + (1.0 - bulge_fraction) * fd
    k = min(int(np.searchsorted(combined, fraction)), x.size - 1)
    return float(x[k])


@lru_cache(maxsize=512)
def _unit_sersic(n: float, devaucouleurs: bool = False):
    """Our (truncated) Sersic of index ``n`` with half-light radius 1 and flux 1, built once.

    Every source is a transformation (``dilate``, ``withFlux``, shear) of one
    of these, so all sources of an index share GalSim's Hankel tables: building
    profiles with new radii would make GalSim re-derive them whenever its
    100-entry cache misses, which costs ~0.5 ms per source with 71 indices.
    """
    t = _trunc_factor(n)
    if devaucouleurs:
        return galsim.DeVaucouleurs(half_light_radius=1.0, trunc=t, flux_untruncated=False)
    return galsim.Sersic(n=n, half_light_radius=1.0, trunc=t, flux_untruncated=False)


@lru_cache(maxsize=1)
def _unit_exponential():
    return galsim.Exponential(half_light_radius=1.0)


def _sersic(n: float, hlr: float, flux: float, *, devaucouleurs: bool = False):
    """Sersic of index ``n``, half-light radius ``hlr`` and total ``flux`` (see :func:`_unit_sersic`)."""
    return _unit_sersic(float(n), devaucouleurs).dilate(hlr).withFlux(flux)


@dataclass
class SourceProfile:
    """A source's GalSim profile and its extent.

    Attributes
    ----------
    profile : galsim.GSObject or None
        Intrinsic (not PSF-convolved) profile in arcsec with the source's total
        flux, centred on the origin; None for a point source.
    radius_arcsec : float
        Radius along the major axis enclosing at least the requested flux
        fraction of ``profile`` (0 for a point source).
    """

    profile: object
    radius_arcsec: float


def bulge_disk_components(hlr: float, bulge_fraction: float, flux: float = 1.0):
    """The circular bulge and disk of a ``buldisk`` source.

    Parameters
    ----------
    hlr : float
        Half-light radius shared by both components, arcsec.
    bulge_fraction : float
        Flux fraction of the bulge in [0, 1].
    flux : float
        Total flux.

    Returns
    -------
    bulge : galsim.Transformation
        A :class:`galsim.DeVaucouleurs` (Sersic n=4, ``bulge.original``)
        truncated at :data:`TRUNC_HLR` half-light radii, dilated to ``hlr``,
        flux ``bulge_fraction * flux``.
    disk : galsim.Transformation
        A :class:`galsim.Exponential` (``disk.original``) dilated to ``hlr``,
        flux ``(1 - bulge_fraction) * flux``.
    """
    bulge = _sersic(4.0, hlr, bulge_fraction * flux, devaucouleurs=True)
    disk = _unit_exponential().dilate(hlr).withFlux((1.0 - bulge_fraction) * flux)
    return bulge, disk


def source_profile(kind: str, *, flux: float, hlr_arcsec: float = np.nan, q: float = np.nan,
                   pa_deg: float = np.nan, bulge_fraction: float = np.nan, sersic_n: float = np.nan,
                   cosmos_index: int = -1, cosmos: "CosmosSample | None" = None,
                   fraction: float = 0.995) -> SourceProfile:
    """The GalSim profile of one source from its truth parameters.

    Parameters
    ----------
    kind : str
        One of ``point``, ``buldisk``, ``sersic``, ``cosmos``, ``observed``.
    flux : float
        Total flux, image units.
    hlr_arcsec, q, pa_deg, bulge_fraction, sersic_n, cosmos_index
        The truth columns of the same names (see the module docstring).
    cosmos : CosmosSample, optional
        Required for ``kind="cosmos"``.
    fraction : float
        Flux fraction the returned radius must enclose.

    Returns
    -------
    SourceProfile
    """
    if kind == "point":
        return SourceProfile(None, 0.0)
    if kind == "cosmos":
        if cosmos is None:
            raise InputError("kind 'cosmos' needs the COSMOS sample: pass cosmos=load_cosmos(config).")
        base = cosmos.galaxy(int(cosmos_index))
        prof = base.withFlux(flux).rotate(pa_deg * galsim.degrees)
        # the galaxy lives on its postage stamp: pi/stepk is the stamp half-size GalSim uses
        return SourceProfile(prof, float(np.pi / base.stepk))
    if kind == "buldisk":
        bulge, disk = bulge_disk_components(hlr_arcsec, bulge_fraction, flux)
        radius = hlr_arcsec * _buldisk_radius_per_hlr(bulge_fraction, fraction)
        prof = galsim.Add([bulge, disk])
    elif kind in ("sersic", "observed"):
        prof = _sersic(sersic_n, hlr_arcsec, flux)
        radius = hlr_arcsec * _radius_per_hlr(float(sersic_n), fraction)
    else:
        raise InputError(f"unknown source kind {kind!r}; use one of {KINDS}.")
    if q < 1.0:
        prof = prof.shear(q=q, beta=pa_deg * galsim.degrees)
        radius /= np.sqrt(q)  # area-preserving shear: the major axis grows by 1/sqrt(q)
    return SourceProfile(prof, float(radius))


# --------------------------------------------------------------------------- Fourier transforms (batched drawing)

#: Kinds whose stamps are drawn in batches from the transforms below (others: one GalSim call each).
BATCHED_KINDS = ("point", "buldisk")
#: Grid step of the tabulated de Vaucouleurs transform, in inverse half-light radii.
DEV_K_STEP = 0.0025
#: The table always reaches at least this |k| (inverse half-light radii); larger on demand.
_DEV_K_MIN_EXTENT = 64.0


@dataclass(frozen=True)
class RadialKTable:
    """A radial Fourier transform tabulated on a uniform grid, interpolated linearly.

    Attributes
    ----------
    step : float
        Grid step in ``|k|``.
    values : ndarray of float64, shape (m,)
        ``F(i * step)`` for ``i = 0 .. m-1``.
    """

    step: float
    values: np.ndarray = field(repr=False)

    @property
    def kmax(self) -> float:
        """Largest ``|k|`` the table covers."""
        return self.step * (self.values.size - 1)

    def __call__(self, k: np.ndarray) -> np.ndarray:
        """``F(k)`` by linear interpolation; ``k`` must lie in ``[0, kmax]`` (any shape)."""
        x = np.multiply(k, 1.0 / self.step)
        i = x.astype(np.intp)
        np.minimum(i, self.values.size - 2, out=i)
        x -= i  # fractional part
        lo = self.values[i]
        hi = self.values[i + 1]
        hi -= lo
        hi *= x
        hi += lo
        return hi


@lru_cache(maxsize=4)
def _dev_k_table(kmax: float) -> RadialKTable:
    m = int(np.ceil(kmax / DEV_K_STEP)) + 2
    kimage = galsim.ImageCD(galsim.BoundsI(0, m - 1, 0, 0), scale=DEV_K_STEP)  # kx = i * step, ky = 0
    _unit_sersic(4.0, True).drawKImage(image=kimage, recenter=False)
    values = np.ascontiguousarray(kimage.array[0].real, dtype=np.float64)
    values.setflags(write=False)
    return RadialKTable(DEV_K_STEP, values)


def devaucouleurs_k_table(kmax: float = _DEV_K_MIN_EXTENT) -> RadialKTable:
    """Radial Fourier transform of the unit ``buldisk`` bulge, tabulated from GalSim.

    The bulge is our de Vaucouleurs profile (:func:`bulge_disk_components`:
    truncated at :data:`TRUNC_HLR` half-light radii) with half-light radius 1
    and flux 1; its transform is real and depends on ``|k|`` only.  Tables are
    built once per process for extents rounded up to a power of two times
    64 (about 14 ms and 200 kB for the smallest).

    Parameters
    ----------
    kmax : float
        Largest ``|k|`` needed, in inverse half-light radii.

    Returns
    -------
    RadialKTable
        Step :data:`DEV_K_STEP`, extent >= ``kmax``.
    """
    extent = _DEV_K_MIN_EXTENT
    while extent < kmax:
        extent *= 2.0
    return _dev_k_table(extent)


def exponential_k(ksq: np.ndarray) -> np.ndarray:
    """Fourier transform of the unit-flux exponential disk of half-light radius 1.

    ``(1 + ksq r_s^2)^(-3/2)`` with ``r_s`` GalSim's scale radius of
    :class:`galsim.Exponential` (half_light_radius=1).

    Parameters
    ----------
    ksq : ndarray
        Squared wavenumbers ``|k|^2`` in inverse half-light radii squared (any shape).

    Returns
    -------
    ndarray of float64, same shape
    """
    r_s = _unit_exponential().scale_radius
    t = np.multiply(ksq, r_s * r_s)
    t += 1.0
    root = np.sqrt(t)
    t *= root
    return np.reciprocal(t, out=t)


def buldisk_k(ksq: np.ndarray, bulge_fraction, table: RadialKTable | None = None) -> np.ndarray:
    """Fourier transform of a circular unit ``buldisk`` source (half-light radius 1, flux 1).

    ``B F_deV(k) + (1 - B) F_exp(k)`` (see the module docstring).

    Parameters
    ----------
    ksq : ndarray
        ``|k|^2`` in inverse half-light radii squared, any shape broadcasting
        against ``bulge_fraction``.
    bulge_fraction : float or ndarray
        Bulge flux fraction ``B`` in [0, 1].
    table : RadialKTable, optional
        De Vaucouleurs table (:func:`devaucouleurs_k_table`); built to cover
        ``ksq`` when not given.

    Returns
    -------
    ndarray of float64, the broadcast shape
    """
    ksq = np.asarray(ksq, dtype=float)
    bulge_fraction = np.asarray(bulge_fraction, dtype=float)
    shape = np.broadcast_shapes(ksq.shape, bulge_fraction.shape)
    if ksq.shape != shape:
        ksq = np.broadcast_to(ksq, shape)
    kmax = float(np.sqrt(ksq.max())) if ksq.size else 0.0
    if table is None or table.kmax < kmax:
        table = devaucouleurs_k_table(kmax)
    disk = exponential_k(ksq)
    bulge = table(np.sqrt(ksq))
    # B F_deV + (1 - B) F_exp = F_exp + B (F_deV - F_exp), in place
    bulge -= disk
    bulge *= bulge_fraction
    bulge += disk
    return bulge


def buldisk_radius_per_hlr(bulge_fraction, fraction: float = 0.995) -> np.ndarray:
    """Radius enclosing ``fraction`` of circular bulge + disk sources, in half-light radii.

    The same numbers as the scalar helper behind :func:`source_profile` (the
    first radius of a 0.01-step grid where the combined growth curve reaches
    ``fraction``), for many bulge fractions at once.

    Parameters
    ----------
    bulge_fraction : array_like, shape (n,)
        Bulge flux fractions in [0, 1].
    fraction : float
        Enclosed flux fraction in (0, 1).

    Returns
    -------
    ndarray, shape (n,)
    """
    bf = np.atleast_1d(np.asarray(bulge_fraction, dtype=float))
    x, fb = _growth_curve(4.0)
    _, fd = _growth_curve(1.0)
    # vectorised binary search for the first index with bf * fb + (1 - bf) * fd >= fraction: the
    # combined curve is non-decreasing, so this is np.searchsorted(combined, fraction) per source
    lo = np.zeros(bf.shape, dtype=np.intp)
    hi = np.full(bf.shape, x.size, dtype=np.intp)
    while True:
        active = lo < hi
        if not active.any():
            break
        mid = (lo + hi) // 2
        midc = np.minimum(mid, x.size - 1)
        below = (bf * fb[midc] + (1.0 - bf) * fd[midc]) < fraction
        lo = np.where(active & below, mid + 1, lo)
        hi = np.where(active & ~below, mid, hi)
    return x[np.minimum(lo, x.size - 1)]


def shear_matrices(q, pa_deg) -> np.ndarray:
    """GalSim's shear matrices for axis ratios ``q`` and position angles ``pa_deg``.

    ``galsim.Shear(q=q, beta=pa_deg * degrees).getMatrix()``:
    ``(1 - g^2)^(-1/2) [[1 + g1, g2], [g2, 1 - g1]]`` with
    ``g = (1 - q) / (1 + q)``, ``g1 = g cos 2 beta``, ``g2 = g sin 2 beta``
    (area-preserving, symmetric).

    Parameters
    ----------
    q, pa_deg : array_like, shape (n,)
        Axis ratio in (0, 1] and angle in degrees.

    Returns
    -------
    ndarray, shape (n, 2, 2)
    """
    q = np.atleast_1d(np.asarray(q, dtype=float))
    beta = np.deg2rad(np.atleast_1d(np.asarray(pa_deg, dtype=float)))
    g = (1.0 - q) / (1.0 + q)
    g1, g2 = g * np.cos(2.0 * beta), g * np.sin(2.0 * beta)
    norm = 1.0 / np.sqrt(1.0 - g * g)
    out = np.empty(q.shape + (2, 2))
    out[:, 0, 0] = norm * (1.0 + g1)
    out[:, 1, 1] = norm * (1.0 - g1)
    out[:, 0, 1] = out[:, 1, 0] = norm * g2
    return out


def kspace_quadratic_forms(hlr_arcsec, q, pa_deg, jacobians) -> np.ndarray:
    """Quadratic forms giving each source's unit-profile ``|k|^2`` from pixel wavenumbers.

    A source of half-light radius ``r``, shear ``S`` (:func:`shear_matrices`)
    mapped to pixels by the local Jacobian ``J`` (arcsec per pixel, see
    :func:`comest_bayes.inject.render.local_jacobians`) has the transform
    ``flux F_unit(M k)`` with ``M = r S J^-T`` and ``k`` in radians per pixel.
    Returns ``Q = M^T M``, so that ``|M k|^2 = k^T Q k``.

    Parameters
    ----------
    hlr_arcsec, q, pa_deg : array_like, shape (n,)
        Circularised half-light radius (arcsec), axis ratio, position angle (deg).
    jacobians : ndarray, shape (n, 2, 2)
        Local pixel-to-world Jacobians, arcsec per pixel.

    Returns
    -------
    ndarray, shape (n, 2, 2)
        Symmetric positive definite, in pixels squared.
    """
    hlr = np.atleast_1d(np.asarray(hlr_arcsec, dtype=float))
    shear = shear_matrices(q, pa_deg)
    jinv_t = np.linalg.inv(np.asarray(jacobians, dtype=float)).transpose(0, 2, 1)
    m = hlr[:, None, None] * (shear @ jinv_t)
    return m.transpose(0, 2, 1) @ m


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
        Source kind (see the module docstring).
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


# --------------------------------------------------------------------------- PSF


def read_psf_image(path) -> tuple[np.ndarray, float | None]:
    """The first 2-D image of a FITS file, checked for use as a PSF.

    Returns
    -------
    data : ndarray, float64
        The image.
    header_scale : float or None
        Its pixel scale in arcsec from the ``PIXELSCL`` keyword (written by
        WebbPSF/POPPY) of that HDU or the primary one, or None.

    Raises
    ------
    InputFileError
        The file does not exist or is not FITS.
    InputError
        No 2-D image, non-finite values, or a non-positive sum.
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"injection.psf = {str(path)!r} is neither one of {PSF_KINDS} nor an existing "
                             f"FITS file; give an analytic PSF name or the path of a PSF image.")
    header_scale = None
    try:
        with fits.open(path) as hdul:
            hdu = next((h for h in hdul if h.data is not None and np.ndim(h.data) == 2), None)
            data = None if hdu is None else np.array(hdu.data, dtype=np.float64)
            if hdu is not None:
                value = hdu.header.get("PIXELSCL", hdul[0].header.get("PIXELSCL"))
                if isinstance(value, (int, float)) and value > 0:
                    header_scale = float(value)
    except OSError as exc:
        raise InputFileError(f"cannot read the PSF image {str(path)!r} as FITS: {exc}.") from None
    if data is None:
        raise InputError(f"the PSF file {str(path)!r} holds no 2-D image HDU.")
    if not np.all(np.isfinite(data)):
        raise InputError(f"the PSF image {str(path)!r} has {int((~np.isfinite(data)).sum())} non-finite pixels; "
                         f"replace them (e.g. with 0) before use.")
    if not data.sum() > 0:
        raise InputError(f"the PSF image {str(path)!r} sums to {data.sum()!r}; a PSF image must have "
                         f"positive total flux.")
    return data, header_scale


def make_psf(config: InjectionConfig, fwhm_pix: float | None, pixel_scale: float, *,
             beta: float | None = None, pixel_integrated: bool = False):
    """The effective PSF as a unit-flux GalSim profile in arcsec.

    Parameters
    ----------
    config : InjectionConfig
        ``psf`` (``moffat``, ``gaussian``, ``kolmogorov`` or a FITS path),
        ``moffat_beta`` and ``psf_pixel_scale``.
    fwhm_pix : float or None
        The image's seeing FWHM in pixels (analytic PSFs; ignored for a file).
    pixel_scale : float
        Arcsec per pixel of the image.
    beta : float, optional
        Moffat beta.  Default: ``config.moffat_beta`` when it is positive,
        else :data:`DEFAULT_MOFFAT_BETA` (the pipeline passes the beta fitted
        on the image's stars; see :func:`comest_bayes.detect.psf.injection_psf`).
    pixel_integrated : bool
        True when ``fwhm_pix`` (and ``beta``) describe the profile *before*
        the detector pixel, as :func:`comest_bayes.detect.psf.estimate_fwhm` fits
        it: the analytic profile is then convolved with the square pixel, so
        that the effective PSF is the fitted one.  False (default): the
        analytic profile is itself the effective PSF (a FWHM measured on the
        image, e.g. by SExtractor, or given with ``--fwhm``).  Ignored for a
        FITS PSF image.

    Returns
    -------
    galsim.GSObject
        Flux 1, centred on the origin, sizes in arcsec.  A FITS image (the
        first 2-D HDU) becomes a :class:`galsim.InterpolatedImage` with pixel
        scale ``config.psf_pixel_scale``, or when that is 0 the ``PIXELSCL``
        header keyword (WebbPSF/POPPY), or else the image's; it is normalised
        to unit flux and shifted so that its flux-weighted centroid is at the
        origin (so injected positions are light centroids).  It is used as the
        *effective* PSF: an oversampled model of the optics alone (WebbPSF's
        ``OVERSAMP`` extension, the first HDU of its files) lacks the detector
        pixel response and should be replaced by its detector-sampled
        (``DET_SAMP``) version.

    Raises
    ------
    InputError
        Missing or non-positive FWHM for an analytic PSF, bad pixel scale.
    InputFileError
        ``config.psf`` is neither an analytic name nor an existing file.
    """
    if not (pixel_scale and pixel_scale > 0 and np.isfinite(pixel_scale)):
        raise InputError(f"pixel scale must be a positive number of arcsec/pixel, got {pixel_scale!r}.")
    name = config.psf.strip()
    if name.lower() in PSF_KINDS:
        if fwhm_pix is None or not np.isfinite(fwhm_pix) or fwhm_pix <= 0:
            raise InputError(f"an analytic PSF ({name}) needs the seeing FWHM in pixels, got {fwhm_pix!r}; "
                             f"give --fwhm or let the pipeline measure it.")
        fwhm = float(fwhm_pix) * float(pixel_scale)
        kind = name.lower()
        if kind == "moffat":
            if beta is None:
                beta = config.moffat_beta if config.moffat_beta > 0 else DEFAULT_MOFFAT_BETA
            if not (np.isfinite(beta) and beta > 1.1):
                raise InputError(f"a Moffat PSF needs a finite beta > 1.1, got {beta!r}.")
            profile = galsim.Moffat(beta=float(beta), fwhm=fwhm)
        elif kind == "gaussian":
            profile = galsim.Gaussian(fwhm=fwhm)
        else:
            profile = galsim.Kolmogorov(fwhm=fwhm)
        if pixel_integrated:
            return galsim.Convolve(profile, galsim.Pixel(float(pixel_scale)))
        return profile
    data, header_scale = read_psf_image(name)
    if config.psf_pixel_scale > 0:
        scale = float(config.psf_pixel_scale)
    elif header_scale is not None:
        scale = header_scale
    else:
        scale = float(pixel_scale)
    ny, nx = data.shape
    total = data.sum()
    yy, xx = np.mgrid[0:ny, 0:nx]
    cx = float((xx * data).sum() / total - (nx - 1) / 2.0)
    cy = float((yy * data).sum() / total - (ny - 1) / 2.0)
    psf = galsim.InterpolatedImage(galsim.ImageD(data, scale=scale), flux=1.0)
    return psf.shift(-cx * scale, -cy * scale)


def psf_half_light_radius_pix(psf, pixel_scale: float) -> float:
    """Half-light radius of a (unit-flux, arcsec) PSF profile, in pixels.

    Analytic profiles report it exactly; others are drawn (``no_pixel``) at
    a quarter of the image's pixel scale and measured
    (:meth:`galsim.Image.calculateHLR`).
    """
    hlr = getattr(psf, "half_light_radius", None)
    if hlr is None:
        scale = pixel_scale / 4.0
        size = min(max(psf.getGoodImageSize(scale), 64), 2048)
        image = psf.drawImage(nx=size, ny=size, scale=scale, method="no_pixel")
        hlr = image.calculateHLR(flux=psf.flux)
    return float(hlr) / float(pixel_scale)


# --------------------------------------------------------------------------- COSMOS


@dataclass
class CosmosSample:
    """A validated GalSim RealGalaxyCatalog (see :func:`load_cosmos`).

    Picklable: the open catalog and the galaxies built from it are dropped
    when pickled and rebuilt on first use in the receiving process.

    Attributes
    ----------
    directory : str
        Directory holding the catalog and its image files.
    file_name : str
        Catalog file name inside ``directory``.
    n : int
        Number of galaxies.
    probabilities : ndarray, shape (n,)
        Selection probability of each galaxy (normalised ``WEIGHT`` column, or uniform).
    mag : ndarray, shape (n,)
        Catalog F814W magnitudes (for reference; injected magnitudes are drawn).
    """

    directory: str
    file_name: str
    n: int
    probabilities: np.ndarray = field(repr=False)
    mag: np.ndarray = field(repr=False)
    _catalog: object = field(default=None, repr=False, compare=False)
    _galaxies: dict = field(default_factory=dict, repr=False, compare=False)

    def catalog(self):
        """The :class:`galsim.RealGalaxyCatalog` (opened on first use)."""
        if self._catalog is None:
            self._catalog = galsim.RealGalaxyCatalog(self.file_name, dir=self.directory)
        return self._catalog

    def galaxy(self, index: int):
        """The :class:`galsim.RealGalaxy` of row ``index`` (built once, then cached)."""
        index = int(index)
        if not 0 <= index < self.n:
            raise InputError(f"COSMOS index {index} is outside the catalog's 0..{self.n - 1}.")
        gal = self._galaxies.get(index)
        if gal is None:
            try:
                # The deviate only feeds noise padding, which is off (noise_pad_size=0); fixing it
                # keeps GalSim from seeding one from the clock.
                gal = galsim.RealGalaxy(self.catalog(), index=index, rng=galsim.BaseDeviate(index + 1))
            except OSError as exc:
                raise InputError(f"cannot read COSMOS galaxy {index} from {self.directory!r}: {exc}.") from None
            self._galaxies[index] = gal
        return gal

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_catalog"] = None
        state["_galaxies"] = {}
        return state


def load_cosmos(config: InjectionConfig | None = None, *, directory=None, file_name=None) -> CosmosSample:
    """Open and validate a GalSim RealGalaxyCatalog directory.

    Every galaxy, PSF and noise file named by the catalog must exist in the
    directory; a missing one is reported by name (the GalSim example catalog
    ships without ``real_galaxy_images.fits``, for instance).  One galaxy is
    built as a final check.

    Parameters
    ----------
    config : InjectionConfig, optional
        Supplies ``cosmos_dir`` and ``cosmos_file``.
    directory, file_name : str, optional
        Override the config's values.

    Returns
    -------
    CosmosSample

    Raises
    ------
    InputError
        Directory not set or missing, catalog unreadable or missing columns, or
        image files missing.
    """
    directory = directory if directory is not None else (config.cosmos_dir if config is not None else "")
    file_name = file_name if file_name is not None else (config.cosmos_file if config is not None
                                                         else InjectionConfig().cosmos_file)
    if not directory:
        raise InputError("kind 'cosmos' needs injection.cosmos_dir: the directory of a GalSim "
                         "RealGalaxyCatalog (catalog FITS file plus its galaxy and PSF image files).")
    dpath = Path(directory)
    if not dpath.is_dir():
        raise InputError(f"injection.cosmos_dir = {str(directory)!r} is not a directory; point it to a GalSim "
                         f"RealGalaxyCatalog directory.")
    cpath = dpath / file_name
    if not cpath.is_file():
        present = sorted(p.name for p in dpath.glob("*.fits"))
        raise InputError(f"the COSMOS catalog file {file_name!r} is not in {str(directory)!r} (FITS files there: "
                         f"{present}); set injection.cosmos_file to the catalog's name.")
    try:
        with fits.open(cpath) as hdul:
            table = hdul[1].data
            names = [c.upper() for c in table.columns.names]
            columns = {c.upper(): np.asarray(table[c]) for c in table.columns.names}
    except (OSError, IndexError, AttributeError) as exc:
        raise InputError(f"cannot read the COSMOS catalog {str(cpath)!r} as a FITS table: {exc}.") from None
    required = ("GAL_FILENAME", "PSF_FILENAME", "GAL_HDU", "PSF_HDU", "PIXEL_SCALE")
    missing_cols = [c for c in required if c not in names]
    if missing_cols:
        raise InputError(f"{str(cpath)!r} is not a GalSim RealGalaxyCatalog: columns {missing_cols} are missing.")
    needed = sorted({str(f).strip() for col in _COSMOS_FILE_COLUMNS if col in columns for f in columns[col]})
    absent = [f for f in needed if not (dpath / f).is_file()]
    if absent:
        raise InputError(f"the COSMOS catalog {file_name!r} in {str(directory)!r} needs image file(s) that are "
                         f"missing: {', '.join(absent)}. Download the complete sample (e.g. "
                         f"galsim_download_cosmos) or point injection.cosmos_dir to a complete one.")
    n = len(columns["GAL_FILENAME"])
    if n == 0:
        raise InputError(f"the COSMOS catalog {str(cpath)!r} has no rows.")
    weight = columns.get("WEIGHT")
    if weight is not None and np.all(np.isfinite(weight)) and np.all(weight >= 0) and weight.sum() > 0:
        prob = np.asarray(weight, dtype=float) / float(np.sum(weight))
    else:
        prob = np.full(n, 1.0 / n)
    mag = np.asarray(columns["MAG"], dtype=float) if "MAG" in columns else np.full(n, np.nan)
    sample = CosmosSample(directory=str(dpath), file_name=str(file_name), n=n, probabilities=prob, mag=mag)
    sample.galaxy(0)
    return sample


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
