"""GalSim profiles of the synthetic sources: Sersic (truncated at 8 half-light radii when its tail
is heavy), bulge + disk, and the profile of one source from its truth parameters.

Sizes in arcsec, fluxes in image units, profiles in world coordinates.  The source kinds and the
truncation rule are described in ``docs/sources.md``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
import galsim
import numpy as np
from scipy.special import gammainc, gammaincinv
from comest_bayes.config import KINDS
from comest_bayes.errors import InputError
from comest_bayes.inject.cosmos import CosmosSample

__all__ = ["sersic_b", 'TRUNC_HLR', 'TRUNC_TAIL', 'SERSIC_N_STEP', 'MAX_SERSIC_INDICES', 'SourceProfile', 'sersic_index_grid', 'sersic_truncation', 'sersic_enclosed_radius', 'sersic_radius_per_hlr', 'bulge_disk_components', 'source_profile']

#: Sersic profiles are truncated at this many half-light radii (see ``docs/sources.md``).
TRUNC_HLR = 8.0
#: ...when their untruncated light beyond it exceeds this fraction.
TRUNC_TAIL = 1e-4
#: Spacing of the Sersic index grid.
SERSIC_N_STEP = 0.05
#: Largest number of distinct Sersic indices (GalSim caches the tables of 100).
MAX_SERSIC_INDICES = 80


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


def sersic_b(n: float) -> float:
    """b_n with I ~ exp(-b_n (r/r_e)^(1/n)) and r_e the half-light radius: P(2n, b_n) = 1/2."""
    return float(gammaincinv(2.0 * n, 0.5))


def sersic_truncation(n: float) -> float:
    """Truncation radius in half-light radii for index ``n`` (0 = untruncated).

    :data:`TRUNC_HLR` when the untruncated profile has more than
    :data:`TRUNC_TAIL` of its light beyond that radius, else 0.
    """
    tail = 1.0 - gammainc(2.0 * n, sersic_b(n) * TRUNC_HLR ** (1.0 / n))
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
def growth_curve(n: float) -> tuple[np.ndarray, np.ndarray]:
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
        r0, total = 1.0 / sersic_b(n) ** n, 1.0
    else:
        r0 = unit_sersic(n).scale_radius
        total = gammainc(2.0 * n, (t / r0) ** (1.0 / n))
    x = np.linspace(0.0, 60.0, 6001)
    frac = np.minimum(gammainc(2.0 * n, (x / r0) ** (1.0 / n)) / total, 1.0)
    if t > 0:
        frac[x >= t] = 1.0
    return x, frac


def sersic_radius_per_hlr(n: float, fraction: float) -> float:
    """Radius enclosing ``fraction`` of our (truncated) Sersic, in half-light radii."""
    x, frac = growth_curve(float(n))
    k = min(int(np.searchsorted(frac, fraction)), x.size - 1)
    return float(x[k])


def _buldisk_radius_per_hlr(bulge_fraction: float, fraction: float) -> float:
    """Radius enclosing ``fraction`` of bulge + disk of equal half-light radius, in half-light radii."""
    x, fb = growth_curve(4.0)
    _, fd = growth_curve(1.0)
    combined = bulge_fraction * fb + (1.0 - bulge_fraction) * fd
    k = min(int(np.searchsorted(combined, fraction)), x.size - 1)
    return float(x[k])


@lru_cache(maxsize=512)
def unit_sersic(n: float, devaucouleurs: bool = False):
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
def unit_exponential():
    return galsim.Exponential(half_light_radius=1.0)


def _sersic(n: float, hlr: float, flux: float, *, devaucouleurs: bool = False):
    """Sersic of index ``n``, half-light radius ``hlr`` and total ``flux`` (see :func:`unit_sersic`)."""
    return unit_sersic(float(n), devaucouleurs).dilate(hlr).withFlux(flux)


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
    disk = unit_exponential().dilate(hlr).withFlux((1.0 - bulge_fraction) * flux)
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
        The truth columns of the same names (see ``docs/injection.md``).
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
        radius = hlr_arcsec * sersic_radius_per_hlr(float(sersic_n), fraction)
    else:
        raise InputError(f"unknown source kind {kind!r}; use one of {KINDS}.")
    if q < 1.0:
        prof = prof.shear(q=q, beta=pa_deg * galsim.degrees)
        radius /= np.sqrt(q)  # area-preserving shear: the major axis grows by 1/sqrt(q)
    return SourceProfile(prof, float(radius))
