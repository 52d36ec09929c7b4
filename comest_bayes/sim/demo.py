"""Built-in demo data: a synthetic but realistic observed r-band tile, drawn with GalSim.

A rotated TAN WCS, a sky level, noise that varies across the field with its weight map, a chip
gap, galaxy and star populations, saturated stars with bleed trails, and a truth table; a pure
function of its parameters and the root seed (only :func:`write_demo_tile` does I/O).  The sky
model, its numbers and their sources are described in ``docs/demo.md``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import galsim
import numpy as np
from astropy.io import fits
from astropy.table import Column, Table
from astropy.wcs import WCS
from scipy import ndimage
from scipy import stats

from comest_bayes.errors import InputError, RunDirectoryError
from comest_bayes.inject.profiles import sersic_b
from comest_bayes.io.rundir import atomic_path
from comest_bayes.seeding import Stream, rng_for

__all__ = [
    "DemoTile",
    "make_demo_tile",
    "demo_truth_catalog",
    "write_demo_tile",
    "demo_seeing_pix",
    "noise_factor_map",
    "galaxy_number_density",
    "star_number_density",
    "median_hlr_arcsec",
    "MASK_GAP",
    "MASK_SATURATED",
    "DEMO_FILES",
]

#: Mask bit of the chip gap (no data).
MASK_GAP = 1
#: Mask bit of saturated pixels and their bleed trails.
MASK_SATURATED = 2
#: File names written by :func:`write_demo_tile`, by role.
DEMO_FILES = {"image": "demo_image.fits", "weight": "demo_weight.fits", "mask": "demo_mask.fits",
              "truth": "demo_truth.fits"}

# --- galaxy counts (LSST Science Book 2009, eq. 3.7; see docs/demo.md) ---
GAL_CUMULATIVE_ARCMIN2_AT_I25 = 46.0
GAL_FAINT_SLOPE = 0.31
GAL_R_MINUS_I = 0.4
GAL_BREAK_MAG = 20.0
GAL_BRIGHT_SLOPE = 0.45
# --- star counts (chosen, see docs/demo.md) ---
STAR_DENSITY_AT_R20 = 250.0
STAR_SLOPE = 0.10
STAR_MAG_BRIGHT = 16.0
SATURATED_STAR_MAGS = (12.0, 15.0)
# --- sizes (Miller et al. 2013, appendix B1) ---
SIZE_LN_RD_AT_I23 = -1.145
SIZE_LN_SLOPE = -0.269
EXP_HLR_OVER_SCALE = 1.6783469900166612  # b_1: the half-light radius of an exponential in scale lengths
SIZE_GAMMA_SHAPE = 1.5                   # (r/a)^(4/3) ~ Gamma(2 / (4/3))
HLR_MIN_ARCSEC = 0.03
HLR_MAX_OVER_MEDIAN = 4.0
# --- morphology mixture: (fraction, bulge_frac low, bulge_frac high) ---
MORPHOLOGY_MIX = ((0.6, 0.0, 0.0), (0.3, 0.05, 0.4), (0.1, 0.6, 1.0))
SHEAR_RAYLEIGH_SCALE = 0.25
SHEAR_MAX = 0.8
BULGE_TRUNC_HLR = 5.0
# --- drawing ---
PSF_TRUNC_FWHM = 8.0
PSF_STAMP_FLUX_FRACTION = 0.995
STAMP_SB_FRACTION = 0.01
MAX_STAMP_HALF = 400
def _sersic_k(n: float) -> float:
    # with k_n = n e^{b_n} Gamma(2n) / b_n^{2n} the total flux is 2 pi r_e^2 I_e k_n (Graham & Driver 2005)
    b = sersic_b(n)
    return n * math.exp(b) * math.gamma(2 * n) / b ** (2 * n)


@dataclass(frozen=True)
class _Spec:
    """Validated parameters of a demo tile (see ``docs/demo.md``)."""

    size: int = 3000
    pixel_scale: float = 0.26
    zeropoint: float = 30.0
    fwhm_arcsec: float = 0.9
    moffat_beta: float = 3.0
    sky_level: float = 300.0
    gain: float = 15.0
    read_noise: float = 5.0
    saturation: float = 30000.0
    exptime: float = 900.0
    depth_gradient: float = 1.6
    shallow_quadrant: float = 1.3
    gap_width: int = 40
    n_saturated_stars: int = 4
    galaxy_density: float = 1.0
    star_density: float = 1.0
    mag_bright: float = 17.0
    faint_margin: float = 2.0
    ra_center: float = 150.1
    dec_center: float = 2.2
    rotation_deg: float = 10.0
    galaxy_counts: tuple | None = None
    star_counts: tuple | None = None

    def __post_init__(self):
        def need(ok, name, fix):
            if not ok:
                raise InputError(f"demo parameter {name}={getattr(self, name)!r} is invalid: {fix}.")

        need(isinstance(self.size, (int, np.integer)) and self.size >= 64, "size",
             "use an integer number of pixels >= 64, e.g. 3000")
        for name in ("pixel_scale", "fwhm_arcsec", "gain", "exptime"):
            value = getattr(self, name)
            need(np.isfinite(value) and value > 0, name, "use a positive finite number")
        need(np.isfinite(self.zeropoint), "zeropoint", "use a finite magnitude, e.g. 30")
        need(self.moffat_beta > 1.5, "moffat_beta", "use a Moffat index > 1.5, e.g. 3")
        need(self.sky_level > 0, "sky_level", "use a positive sky level in ADU per pixel, e.g. 300")
        need(self.read_noise >= 0, "read_noise", "use a read noise >= 0 electrons")
        need(self.saturation > self.sky_level, "saturation",
             f"the saturation level (ADU, sky included) must exceed the sky level {self.sky_level}")
        need(self.depth_gradient >= 1, "depth_gradient", "use a sigma ratio >= 1, e.g. 1.6")
        need(self.shallow_quadrant >= 1, "shallow_quadrant", "use a sigma factor >= 1 (1 disables it)")
        need(0 <= self.gap_width <= self.size // 4, "gap_width",
             f"use 0 (no gap) up to a quarter of the tile ({self.size // 4} px)")
        need(0 <= self.n_saturated_stars <= 50, "n_saturated_stars", "use 0 to 50")
        need(self.galaxy_density >= 0, "galaxy_density", "use a non-negative multiplier")
        need(self.star_density >= 0, "star_density", "use a non-negative multiplier")
        need(self.faint_margin > -5, "faint_margin", "use a margin in magnitudes, e.g. 2")
        need(-90 < self.dec_center < 90, "dec_center", "use a declination strictly between -90 and 90 deg")
        for name in ("galaxy_counts", "star_counts"):
            value = getattr(self, name)
            if value is not None:
                ok = (isinstance(value, (tuple, list)) and len(value) == 3
                      and all(isinstance(v, (int, float)) and np.isfinite(v) for v in value) and value[0] > 0)
                need(ok, name, "use (n_ref, slope, m_ref): a positive density in deg^-2 mag^-1 at m_ref, a slope "
                               "d log10 N / dm and a reference magnitude, e.g. (2e4, 0.3, 23.0)")
                object.__setattr__(self, name, tuple(float(v) for v in value))

    @property
    def fwhm_pix(self) -> float:
        return self.fwhm_arcsec / self.pixel_scale

    @property
    def sigma0(self) -> float:
        return math.sqrt(self.sky_level / self.gain + (self.read_noise / self.gain) ** 2)

    @property
    def area_deg2(self) -> float:
        return (self.size * self.pixel_scale / 3600.0) ** 2

    @property
    def gap(self) -> tuple[int, int]:
        if self.gap_width == 0:
            return 0, 0
        x0 = int(round(0.62 * self.size))
        return x0, x0 + int(self.gap_width)

    def psf(self, truncated: bool, gsparams=None) -> galsim.GSObject:
        trunc = PSF_TRUNC_FWHM * self.fwhm_pix if truncated else 0.0
        return galsim.Moffat(beta=self.moffat_beta, fwhm=self.fwhm_pix, trunc=trunc, gsparams=gsparams)

    def neff_pix(self) -> float:
        """Noise-equivalent area (pixels) of the pixelised PSF, 1 / sum(p^2)."""
        half = int(math.ceil(10 * self.fwhm_pix))
        img = self.psf(False).drawImage(nx=2 * half + 1, ny=2 * half + 1, scale=1.0).array.astype(np.float64)
        p = img / img.sum()
        return float(1.0 / np.sum(p * p))

    def depth5(self, factor: float = 1.0) -> float:
        """5-sigma point-source magnitude where the noise sigma is ``factor * sigma0``."""
        return self.zeropoint - 2.5 * math.log10(5.0 * self.sigma0 * factor * math.sqrt(self.neff_pix()))


# ---------------------------------------------------------------------------------------------
# Population models (pure functions of magnitude)
# ---------------------------------------------------------------------------------------------

def _gal_faint_norm() -> float:
    """Differential galaxy density (deg^-2 mag^-1) at r = GAL_BREAK_MAG on the faint branch."""
    return (GAL_FAINT_SLOPE * math.log(10.0) * GAL_CUMULATIVE_ARCMIN2_AT_I25 * 3600.0
            * 10.0 ** (GAL_FAINT_SLOPE * (GAL_BREAK_MAG - GAL_R_MINUS_I - 25.0)))


def galaxy_number_density(mag) -> np.ndarray:
    """Differential galaxy counts in r, per deg^2 per mag (see ``docs/demo.md``).

    Parameters
    ----------
    mag : float or array_like
        r-band AB magnitude.

    Returns
    -------
    ndarray
        ``dN/dm`` in deg^-2 mag^-1, same shape as ``mag``.
    """
    mag = np.asarray(mag, dtype=float)
    n0 = _gal_faint_norm()
    slope = np.where(mag >= GAL_BREAK_MAG, GAL_FAINT_SLOPE, GAL_BRIGHT_SLOPE)
    return n0 * 10.0 ** (slope * (mag - GAL_BREAK_MAG))


def star_number_density(mag) -> np.ndarray:
    """Differential star counts in r, per deg^2 per mag: ``250 x 10**(0.1 (r - 20))``."""
    mag = np.asarray(mag, dtype=float)
    return STAR_DENSITY_AT_R20 * 10.0 ** (STAR_SLOPE * (mag - 20.0))


def median_hlr_arcsec(mag) -> np.ndarray:
    """Median galaxy half-light radius (arcsec) at r magnitude ``mag`` (Miller et al. 2013)."""
    mag = np.asarray(mag, dtype=float)
    i_mag = mag - GAL_R_MINUS_I
    return EXP_HLR_OVER_SCALE * np.exp(SIZE_LN_RD_AT_I23 + SIZE_LN_SLOPE * (i_mag - 23.0))


def noise_factor_map(shape: tuple[int, int], depth_gradient: float = 1.6,
                     shallow_quadrant: float = 1.3) -> np.ndarray:
    """Relative sky-noise sigma across the tile.

    Parameters
    ----------
    shape : (ny, nx)
        Tile shape.
    depth_gradient : float
        Sigma at ``x = nx - 1`` over sigma at ``x = 0``; linear in x between.
    shallow_quadrant : float
        Extra factor for ``x < nx/2`` and ``y >= ny/2``.

    Returns
    -------
    ndarray of float64, shape (ny, nx)
        ``f >= 1``; the sky-noise sigma is ``sigma0 * f``.
    """
    ny, nx = shape
    return _noise_factor_at(np.arange(nx)[None, :], np.arange(ny)[:, None], shape, depth_gradient,
                            shallow_quadrant) * np.ones((ny, 1))


def _noise_factor_at(ix, iy, shape, depth_gradient: float, shallow_quadrant: float) -> np.ndarray:
    """:func:`noise_factor_map` at integer pixels ``(ix, iy)`` (broadcasting arrays)."""
    ny, nx = shape
    ix = np.asarray(ix)
    iy = np.asarray(iy)
    f = 1.0 + (depth_gradient - 1.0) * ix / max(nx - 1, 1)
    return np.where((ix < nx // 2) & (iy >= ny // 2), f * shallow_quadrant, f)


def _sample_power_law(rng, n0: float, slope: float, m0: float, lo: float, hi: float, area: float):
    """Poisson number and magnitudes for ``dN/dm = n0 10**(slope (m - m0))`` on [lo, hi)."""
    if hi <= lo or n0 <= 0:
        return np.zeros(0)
    expected = area * n0 / (slope * math.log(10.0)) * (10.0 ** (slope * (hi - m0)) - 10.0 ** (slope * (lo - m0)))
    n = int(rng.poisson(expected))
    u = rng.random(n)
    return lo + np.log10(1.0 + u * (10.0 ** (slope * (hi - lo)) - 1.0)) / slope


def _sample_galaxy_mags(rng, spec: _Spec, mag_faint: float) -> np.ndarray:
    area = spec.area_deg2 * spec.galaxy_density
    if spec.galaxy_counts is not None:
        n_ref, slope, m_ref = spec.galaxy_counts
        return _sample_power_law(rng, n_ref, slope, m_ref, spec.mag_bright, mag_faint, area)
    n0 = _gal_faint_norm()
    bright = _sample_power_law(rng, n0, GAL_BRIGHT_SLOPE, GAL_BREAK_MAG, spec.mag_bright,
                               min(GAL_BREAK_MAG, mag_faint), area)
    faint = _sample_power_law(rng, n0, GAL_FAINT_SLOPE, GAL_BREAK_MAG, max(GAL_BREAK_MAG, spec.mag_bright),
                              mag_faint, area)
    return np.concatenate([bright, faint])


def _sample_positions(rng, n: int, size: int) -> tuple[np.ndarray, np.ndarray]:
    # Centres anywhere on the tile: pixel centres are at 0..size-1, pixel edges at -0.5 and size-0.5.
    x = rng.uniform(-0.5, size - 0.5, n)
    y = rng.uniform(-0.5, size - 0.5, n)
    return x, y


def _galaxy_catalog(spec: _Spec, seed: int, mag_faint: float) -> dict:
    rng = rng_for(seed, Stream.DEMO, Stream.DEMO_GALAXIES)
    mag = _sample_galaxy_mags(rng, spec, mag_faint)
    n = mag.size
    x, y = _sample_positions(rng, n, spec.size)
    # Sizes: (r/a)^(4/3) ~ Gamma(1.5), with a chosen so that the median is the Miller et al. relation.
    med = median_hlr_arcsec(mag)
    t_med = stats.gamma.ppf(0.5, SIZE_GAMMA_SHAPE)
    t = rng.gamma(SIZE_GAMMA_SHAPE, 1.0, n)
    hlr = med * (t / t_med) ** 0.75
    hlr = np.clip(hlr, HLR_MIN_ARCSEC, HLR_MAX_OVER_MEDIAN * med)
    # Morphology mixture.
    fractions = np.array([m[0] for m in MORPHOLOGY_MIX])
    kind = rng.choice(len(MORPHOLOGY_MIX), size=n, p=fractions / fractions.sum())
    lo = np.array([m[1] for m in MORPHOLOGY_MIX])[kind]
    hi = np.array([m[2] for m in MORPHOLOGY_MIX])[kind]
    bulge_frac = lo + (hi - lo) * rng.random(n)
    # Shapes: truncated Rayleigh shear, uniform angle.
    s = SHEAR_RAYLEIGH_SCALE
    cmax = 1.0 - math.exp(-SHEAR_MAX ** 2 / (2 * s * s))
    g = s * np.sqrt(-2.0 * np.log1p(-rng.random(n) * cmax))
    q = (1.0 - g) / (1.0 + g)
    beta = rng.uniform(0.0, 180.0, n)
    return {"kind": np.full(n, "galaxy"), "x": x, "y": y, "mag": mag, "hlr_arcsec": hlr,
            "bulge_frac": bulge_frac, "q": q, "beta": beta}


def _star_catalog(spec: _Spec, seed: int, mag_faint: float) -> dict:
    rng = rng_for(seed, Stream.DEMO, Stream.DEMO_STARS)
    n_ref, slope, m_ref = spec.star_counts if spec.star_counts is not None else (STAR_DENSITY_AT_R20, STAR_SLOPE,
                                                                               20.0)
    mag = _sample_power_law(rng, n_ref, slope, m_ref, STAR_MAG_BRIGHT, mag_faint, spec.area_deg2 * spec.star_density)
    x, y = _sample_positions(rng, mag.size, spec.size)
    # Bright, saturated stars, kept away from the edges and the chip gap.
    rng_b = rng_for(seed, Stream.DEMO, Stream.DEMO_BRIGHT_STARS)
    nb = spec.n_saturated_stars
    margin = min(100.0, spec.size / 6.0)
    gx0, gx1 = spec.gap
    # Uniform in the tile minus the edges and the gap (+-60 px), and at least
    # size / (2 sqrt(n)) apart so their halos do not pile up: candidates are drawn
    # in turn and rejected if too close (a fixed number of tries keeps it deterministic).
    min_sep = spec.size / (2.0 * math.sqrt(max(nb, 1)))
    xb, yb = [], []
    for _ in range(200 * nb):
        if len(xb) == nb:
            break
        cx, cy = margin + rng_b.random(2) * (spec.size - 1 - 2 * margin)
        if spec.gap_width and gx0 - 60 <= cx < gx1 + 60:
            continue
        if xb and np.min(np.hypot(np.array(xb) - cx, np.array(yb) - cy)) < min_sep:
            continue
        xb.append(cx)
        yb.append(cy)
    nb = len(xb)
    xb, yb = np.array(xb, dtype=float), np.array(yb, dtype=float)
    mb = rng_b.uniform(*SATURATED_STAR_MAGS, nb)
    mag = np.concatenate([mag, mb])
    x = np.concatenate([x, xb])
    y = np.concatenate([y, yb])
    n = mag.size
    return {"kind": np.full(n, "star"), "x": x, "y": y, "mag": mag, "hlr_arcsec": np.full(n, np.nan),
            "bulge_frac": np.full(n, np.nan), "q": np.ones(n), "beta": np.zeros(n)}


def _make_wcs(spec: _Spec) -> WCS:
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    w.wcs.crval = [spec.ra_center, spec.dec_center]
    w.wcs.crpix = [(spec.size + 1) / 2.0, (spec.size + 1) / 2.0]
    s = spec.pixel_scale / 3600.0
    r = math.radians(spec.rotation_deg)
    # East to the left (RA decreases with x) before rotation; north along (sin r, cos r).
    w.wcs.cd = np.array([[-s * math.cos(r), s * math.sin(r)], [s * math.sin(r), s * math.cos(r)]])
    w.wcs.radesys = "ICRS"
    w.wcs.equinox = 2000.0
    w.wcs.set()
    return w


def _truth_table(spec: _Spec, seed: int) -> tuple[Table, dict]:
    depth_deep = spec.depth5(1.0)
    shape = (spec.size, spec.size)
    corners = _noise_factor_at(np.array([spec.size - 1, spec.size // 2 - 1]), np.array([0, spec.size - 1]),
                               shape, spec.depth_gradient, spec.shallow_quadrant)
    fmax = float(corners.max())
    mag_faint = depth_deep + spec.faint_margin
    gal = _galaxy_catalog(spec, seed, mag_faint)
    star = _star_catalog(spec, seed, mag_faint)
    cols = {k: np.concatenate([gal[k], star[k]]) for k in gal}
    n = len(cols["mag"])
    wcs = _make_wcs(spec)
    ra, dec = wcs.all_pix2world(cols["x"], cols["y"], 0) if n else (np.zeros(0), np.zeros(0))
    gx0, gx1 = spec.gap
    ix = np.clip(np.rint(cols["x"]).astype(int), 0, spec.size - 1)
    iy = np.clip(np.rint(cols["y"]).astype(int), 0, spec.size - 1)
    f = _noise_factor_at(ix, iy, shape, spec.depth_gradient, spec.shallow_quadrant)
    table = Table()
    table["id"] = np.arange(1, n + 1, dtype=np.int64)
    table["kind"] = cols["kind"].astype("U6")
    table["x"] = cols["x"]
    table["y"] = cols["y"]
    table["ra"] = np.asarray(ra, dtype=float)
    table["dec"] = np.asarray(dec, dtype=float)
    table["mag"] = cols["mag"]
    table["flux"] = 10.0 ** (-0.4 * (cols["mag"] - spec.zeropoint))
    table["hlr_arcsec"] = cols["hlr_arcsec"]
    table["bulge_frac"] = cols["bulge_frac"]
    table["q"] = cols["q"]
    table["beta"] = cols["beta"]
    table["sigma_local"] = spec.sigma0 * f
    table["in_gap"] = (ix >= gx0) & (ix < gx1)
    table["saturated"] = np.zeros(n, dtype=bool)
    table["masked"] = table["in_gap"].copy()
    units = {"x": "pix", "y": "pix", "ra": "deg", "dec": "deg", "mag": "mag", "hlr_arcsec": "arcsec",
             "beta": "deg"}
    desc = {
        "id": "1-based source number",
        "kind": "'star' or 'galaxy'",
        "x": "true centre x, 0-based pixel", "y": "true centre y, 0-based pixel",
        "ra": "right ascension of (x, y) through the tile WCS", "dec": "declination of (x, y)",
        "mag": "true total AB magnitude (r)", "flux": "true total flux, image units (ADU)",
        "hlr_arcsec": "circularised half-light radius before the PSF (NaN for stars)",
        "bulge_frac": "de Vaucouleurs bulge-to-total flux ratio (NaN for stars)",
        "q": "axis ratio b/a (1 for stars)",
        "beta": "major-axis angle, counter-clockwise from +x in the pixel frame",
        "sigma_local": "1-sigma sky noise at the centre pixel, ADU",
        "in_gap": "centre in the chip gap (no data)",
        "saturated": "a saturated or bled pixel within 1 px of the centre",
        "masked": "centre pixel masked (gap or saturation)",
    }
    for name in table.colnames:
        if name in units:
            table[name].unit = units[name]
        table[name].description = desc[name]
    info = {"mag_faint": mag_faint, "depth5_deep": depth_deep, "depth5_shallow": spec.depth5(fmax),
            "noise_factor_max": fmax, "n_galaxies": int(len(gal["mag"])), "n_stars": int(len(star["mag"]))}
    table.meta.update({"ZEROPT": spec.zeropoint, "PIXSCALE": spec.pixel_scale, "SEED": seed,
                       "MAGFAINT": round(mag_faint, 4), "NGAL": info["n_galaxies"], "NSTAR": info["n_stars"]})
    return table, info


def demo_truth_catalog(seed: int = 0, **params) -> Table:
    """The truth catalog of the demo tile, without rendering it.

    Takes the same parameters as :func:`make_demo_tile` and returns exactly
    the sources it would draw (same ids, positions, magnitudes, shapes), but
    the columns that depend on the pixels are missing (``flux_in_tile``) or
    not filled in (``saturated``, and ``masked`` beyond the chip gap).  Fast,
    so population statistics can be checked on large tiles.

    Columns: ``id`` (1-based), ``kind`` ('star'/'galaxy'), ``x``, ``y``
    (0-based pixels), ``ra``, ``dec`` (deg), ``mag`` (AB r), ``flux`` (ADU),
    ``hlr_arcsec`` (circularised, before the PSF; NaN for stars),
    ``bulge_frac`` (NaN for stars), ``q``, ``beta`` (deg, counter-clockwise
    from +x), ``sigma_local`` (sky sigma at the centre, ADU), ``in_gap``,
    ``saturated``, ``masked``.
    """
    table, _ = _truth_table(_Spec(**params), seed)
    return table


# ---------------------------------------------------------------------------------------------
# Rendering
# ---------------------------------------------------------------------------------------------

def _moffat_radius(spec: _Spec, flux: float, threshold: float) -> float:
    """Radius (px) where a Moffat of ``flux`` falls to ``threshold`` ADU per pixel."""
    b = spec.moffat_beta
    alpha = spec.fwhm_pix / (2.0 * math.sqrt(2.0 ** (1.0 / b) - 1.0))
    i0 = flux * (b - 1.0) / (math.pi * alpha * alpha)
    if i0 <= threshold:
        return 0.0
    return alpha * math.sqrt((i0 / threshold) ** (1.0 / b) - 1.0)


def _sersic_radius(n: float, flux: float, hlr: float, q: float, threshold: float) -> float:
    """Major-axis radius (px) where a sheared Sersic of ``flux`` falls to ``threshold`` ADU/px."""
    if flux <= 0:
        return 0.0
    b = sersic_b(n)
    i_e = flux / (2.0 * math.pi * hlr * hlr * _sersic_k(n))
    r_major = hlr / math.sqrt(q)
    if i_e * math.exp(b) <= threshold:  # even the centre is below the threshold
        return 0.0
    return r_major * max(1.0 + math.log(i_e / threshold) / b, 0.0) ** n


def _moffat_enclosing(spec: _Spec, fraction: float) -> float:
    """Radius (px) of the circle holding ``fraction`` of the Moffat PSF's flux."""
    b = spec.moffat_beta
    alpha = spec.fwhm_pix / (2.0 * math.sqrt(2.0 ** (1.0 / b) - 1.0))
    # Flux outside r is (1 + r^2/alpha^2)^(1 - beta).
    return alpha * math.sqrt((1.0 - fraction) ** (1.0 / (1.0 - b)) - 1.0)


def _stamp_half(spec: _Spec, row, threshold: float) -> int:
    """Half-size (px) of a source's stamp: it holds >= 99.5% of the flux of a star, the whole truncated
    bulge and >= 99.8% of a disk (5 hlr), and reaches 1% of the sky noise for bright sources."""
    flux = float(row["flux"])
    r = max(_moffat_radius(spec, flux, threshold), _moffat_enclosing(spec, PSF_STAMP_FLUX_FRACTION))
    if row["kind"] != "star":
        hlr = float(row["hlr_arcsec"]) / spec.pixel_scale
        q = float(row["q"])
        # The bulge ends at BULGE_TRUNC_HLR hlr; a bright disk may stay above the threshold further out.
        r_disk = _sersic_radius(1.0, flux * (1.0 - float(row["bulge_frac"])), hlr, q, threshold)
        r = max(r, max(r_disk, BULGE_TRUNC_HLR * hlr / math.sqrt(q)) + 1.5 * spec.fwhm_pix)
    return int(min(math.ceil(r), MAX_STAMP_HALF))


def _galaxy_profile(spec: _Spec, row, psf) -> galsim.GSObject:
    hlr = float(row["hlr_arcsec"]) / spec.pixel_scale
    bt = float(row["bulge_frac"])
    parts = []
    if bt < 1.0:
        parts.append(galsim.Exponential(half_light_radius=hlr, flux=1.0 - bt))
    if bt > 0.0:
        # Truncated at BULGE_TRUNC_HLR half-light radii; hlr and flux refer to the truncated profile.
        parts.append(galsim.DeVaucouleurs(half_light_radius=hlr, flux=bt, trunc=BULGE_TRUNC_HLR * hlr,
                                          flux_untruncated=False))
    gal = parts[0] if len(parts) == 1 else galsim.Add(parts)
    gal = gal.shear(q=float(row["q"]), beta=float(row["beta"]) * galsim.degrees).withFlux(float(row["flux"]))
    return galsim.Convolve(gal, psf)


def _star_profile(spec: _Spec, flux: float, threshold: float, cache: dict) -> galsim.GSObject:
    # GalSim's default folding threshold (5e-3 of the flux wraps around the FFT box) is fine for faint
    # stars; for bright ones keep the aliased light per pixel well below the threshold.
    folding = 5e-3
    if flux > 1e4:
        folding = float(np.clip(threshold * 1e4 / flux, 1e-6, 5e-3))
        folding = 10.0 ** math.floor(math.log10(folding))  # few distinct values -> GalSim caches tables
    if folding not in cache:
        cache[folding] = spec.psf(False, galsim.GSParams(folding_threshold=folding))
    return cache[folding].withFlux(flux)


def _draw_sources(spec: _Spec, truth: Table, progress=None) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free source image (ADU, float64, shape (size, size)) and the flux each source put in it.

    ``progress(done, total)``, when given, is called about 200 times as the sources are drawn.
    """
    src = np.zeros((spec.size, spec.size), dtype=np.float64)
    drawn = np.zeros(len(truth))
    canvas = galsim.Image(src, xmin=1, ymin=1, scale=1.0)  # a view: drawing writes into ``src``
    threshold = STAMP_SB_FRACTION * spec.sigma0
    psf_gal = spec.psf(True)
    star_cache: dict = {}
    total = len(truth)
    every = max(1, total // 200)
    for k, row in enumerate(truth):
        if progress is not None and k % every == 0:
            progress(k, total)
        x, y = float(row["x"]), float(row["y"])
        half = _stamp_half(spec, row, threshold)
        ix, iy = int(round(x)) + 1, int(round(y)) + 1  # GalSim pixels are 1-based
        bounds = galsim.BoundsI(ix - half, ix + half, iy - half, iy + half) & canvas.bounds
        if not bounds.isDefined():
            continue
        if row["kind"] == "star":
            prof = _star_profile(spec, float(row["flux"]), threshold, star_cache)
        else:
            prof = _galaxy_profile(spec, row, psf_gal)
        stamp = canvas[bounds]
        before = stamp.array.sum()
        prof.drawImage(image=stamp, add_to_image=True, center=galsim.PositionD(x + 1.0, y + 1.0), method="auto")
        drawn[k] = stamp.array.sum() - before
    if progress is not None:
        progress(total, total)
    return src, drawn


def _bleed(sat: np.ndarray, excess: np.ndarray, capacity: float) -> np.ndarray:
    """Saturated pixels plus bleed trails along columns (axis 0).

    Parameters
    ----------
    sat : ndarray of bool, shape (ny, nx)
        Pixels at or above saturation.
    excess : ndarray, shape (ny, nx)
        Noise-free charge above saturation (ADU).
    capacity : float
        Charge (ADU) one bled pixel absorbs (saturation minus sky).
    """
    out = sat.copy()
    ny = sat.shape[0]
    labels, nlab = ndimage.label(sat)
    for k, (sy, sx) in enumerate(ndimage.find_objects(labels), start=1):
        region = labels[sy, sx] == k
        for j in range(region.shape[1]):
            col = region[:, j]
            if not col.any():
                continue
            rows = np.nonzero(col)[0]
            lo, hi = sy.start + rows.min(), sy.start + rows.max()
            c = sx.start + j
            charge = float(excess[sy, c][col].sum())
            extra = int(math.ceil(charge / capacity / 2.0))
            out[max(lo - extra, 0): min(hi + extra + 1, ny), c] = True
    return out


@dataclass
class DemoTile:
    """A synthetic observed tile and its truth.

    Attributes
    ----------
    image : ndarray of float32, shape (ny, nx)
        Pixel values in ADU, sky included; 0 in the chip gap; saturated and
        bled pixels hold exactly ``header['SATURATE']``.
    weight : ndarray of float32, shape (ny, nx)
        Inverse variance of the sky noise (ADU^-2); 0 in the chip gap.
    mask : ndarray of uint8, shape (ny, nx)
        0 good; bit :data:`MASK_GAP` (1) chip gap; bit
        :data:`MASK_SATURATED` (2) saturated or bled pixel.
    header : astropy.io.fits.Header
        TAN WCS and MAGZERO, GAIN, SATURATE, EXPTIME, PIXSCALE, SEEING, ...
    truth : astropy.table.Table
        Every rendered source (see :func:`demo_truth_catalog` for columns).
    params : dict
        The generating parameters and derived numbers (JSON-ready).
    model : ndarray of float32 or None
        Noise-free sky + sources (ADU), before saturation clipping and the
        chip gap; only with ``make_demo_tile(..., keep_model=True)``.
    """

    image: np.ndarray
    weight: np.ndarray
    mask: np.ndarray
    header: fits.Header
    truth: Table
    params: dict
    model: np.ndarray | None = None

    @property
    def sigma(self) -> np.ndarray:
        """1-sigma sky noise map (ADU), ``inf`` where the weight is 0."""
        with np.errstate(divide="ignore"):
            return (1.0 / np.sqrt(self.weight.astype(np.float64))).astype(np.float32)


def _wcs_header(wcs: WCS) -> fits.Header:
    """A celestial WCS as FITS cards, with an explicit CD matrix (what most survey tiles carry)."""
    hdr = wcs.to_header()
    if not wcs.wcs.has_cd():
        wcs = wcs.deepcopy()
        wcs.wcs.cd = wcs.wcs.get_pc() * wcs.wcs.get_cdelt()[:, None]
    for key in ("PC1_1", "PC1_2", "PC2_1", "PC2_2", "CDELT1", "CDELT2", "MJDREF"):
        hdr.remove(key, ignore_missing=True)
    for i in range(2):
        for j in range(2):
            hdr[f"CD{i + 1}_{j + 1}"] = (float(wcs.wcs.cd[i, j]), "linear transformation matrix, deg/pix")
    return hdr


def _header(spec: _Spec, seed: int, info: dict) -> fits.Header:
    hdr = _wcs_header(_make_wcs(spec))
    cards = [
        ("MAGZERO", spec.zeropoint, "AB mag of 1 ADU total flux"),
        ("GAIN", spec.gain, "e-/ADU (deepest region)"),
        ("SATURATE", spec.saturation, "saturation level, ADU, sky included"),
        ("EXPTIME", spec.exptime, "nominal exposure time, s"),
        ("PIXSCALE", spec.pixel_scale, "arcsec / pixel"),
        ("SEEING", spec.fwhm_arcsec, "PSF FWHM, arcsec (Moffat)"),
        ("MOFFBETA", spec.moffat_beta, "Moffat beta of the PSF"),
        ("SKYLEVEL", spec.sky_level, "sky level, ADU / pixel"),
        ("SKYSIG", round(spec.sigma0, 6), "sky noise sigma in the deepest region, ADU"),
        ("RDNOISE", spec.read_noise, "read noise, e-"),
        ("DEPTH5", round(info["depth5_deep"], 4), "5-sigma PSF depth, deepest region, mag"),
        ("BUNIT", "ADU", "pixel unit"),
        ("FILTER", "r", "synthetic r band"),
        ("DEMOSEED", int(seed), "root seed of comest_bayes.sim.demo"),
    ]
    for key, value, comment in cards:
        hdr[key] = (value, comment)
    hdr.add_comment("SYNTHETIC IMAGE made by comest_bayes.sim.demo (GalSim).")
    hdr.add_comment("It is not an observation.  Truth: demo_truth.fits.")
    hdr.add_comment("Stars: Moffat PSF; galaxies: exp. disk + de Vaucouleurs bulge.")
    hdr.add_comment("Mask bits: 1 = chip gap (no data), 2 = saturated or bleed.")
    return hdr


def make_demo_tile(seed: int = 0, *, size: int = 3000, pixel_scale: float = 0.26, zeropoint: float = 30.0,
                   fwhm_arcsec: float = 0.9, moffat_beta: float = 3.0, sky_level: float = 300.0,
                   gain: float = 15.0, read_noise: float = 5.0, saturation: float = 30000.0,
                   exptime: float = 900.0, depth_gradient: float = 1.6, shallow_quadrant: float = 1.3,
                   gap_width: int = 40, n_saturated_stars: int = 4, galaxy_density: float = 1.0,
                   star_density: float = 1.0, mag_bright: float = 17.0, faint_margin: float = 2.0,
                   ra_center: float = 150.1, dec_center: float = 2.2, rotation_deg: float = 10.0,
                   keep_model: bool = False, galaxy_counts: tuple | None = None,
                   star_counts: tuple | None = None, progress=None) -> DemoTile:
    """Synthesize the demo tile.

    The defaults make
    a 3000 x 3000 DECam-like r-band tile (13 arcmin, 0.9" seeing, 5-sigma
    point-source depth r = 24.54 in its deepest part) with ~17500 galaxies
    and ~215 stars, in about 11 s on one core.

    ``keep_model=True`` also returns the noise-free model (sky + sources,
    before saturation and the gap) as ``DemoTile.model``, e.g. to check a
    source-free image against the truth.

    ``progress``, a callable ``progress(done, total)``, is told how many of
    the sources are drawn (about 200 times, the last with ``done == total``);
    drawing them is most of the time a large tile takes.

    Parameters
    ----------
    seed : int, default 0
        Root seed.  Independent streams ``("demo", "galaxies")``,
        ``("demo", "stars")``, ``("demo", "bright_stars")`` and
        ``("demo", "noise")`` come from :func:`comest_bayes.seeding.rng_for`,
        so e.g. changing the star density does not move any galaxy.
    size : int, default 3000
        The tile is ``size x size`` pixels (3000 px = 13 arcmin at 0.26"/px).
    pixel_scale : float, default 0.26
        Arcsec per pixel (DECam-like).
    zeropoint : float, default 30.0
        AB magnitude of a source with a total flux of one image unit (ADU):
        ``m = zeropoint - 2.5 log10(flux)``.  Written as ``MAGZERO``.
    fwhm_arcsec : float, default 0.9
        Seeing FWHM of the Moffat PSF, arcsec (``SEEING``).
    moffat_beta : float, default 3.0
        Moffat index of the PSF.
    sky_level : float, default 300.0
        Sky in ADU per pixel (~20.9 r mag/arcsec^2 for the defaults, a dark sky).
    gain : float, default 15.0
        Electrons per ADU (``GAIN``), at the deepest part of the tile.
    read_noise : float, default 5.0
        Read noise in electrons.
    saturation : float, default 30000.0
        Saturation level in ADU, sky included (``SATURATE``).
    exptime : float, default 900.0
        Nominal exposure time in seconds (``EXPTIME``); informational only.
    depth_gradient : float, default 1.6
        Ratio of the sky-noise sigma at the right edge (x = size-1) to that at
        the left edge (x = 0); the sigma grows linearly in x between them.
    shallow_quadrant : float, default 1.3
        Extra factor on the noise sigma in the upper-left quadrant
        (``x < size/2`` and ``y >= size/2``), a step in depth as left by a
        missing exposure in a coadd.  1 disables it.
    gap_width : int, default 40
        Width in pixels of a vertical chip gap starting at ``x = round(0.62 size)``:
        image 0, weight 0, mask bit 1.  0 disables it.
    n_saturated_stars : int, default 4
        Bright stars (r = 12-15) placed on purpose; they saturate.
    galaxy_density, star_density : float, default 1.0
        Multipliers of the galaxy and star number counts below (e.g. a high
        ``star_density`` gives tests many isolated stars; 0 removes a population).
    mag_bright : float, default 17.0
        Brightest galaxy magnitude drawn.
    faint_margin : float, default 2.0
        Sources are drawn down to ``mag_faint = depth5_deep + faint_margin``,
        i.e. 2 mag below the 5-sigma point-source limit of the deepest region,
        so the undetected faint population that sets the confusion background is
        there too.
    ra_center, dec_center : float, default 150.1, 2.2
        Tangent point (deg) at the tile centre (the COSMOS field).
    rotation_deg : float, default 10.0
        Rotation of the pixel grid: north points along ``(sin r, cos r)`` in
        pixel coordinates (east to the left of north), so code that assumes
        north = +y is exercised.
    keep_model : bool, default False
        Also return the noise-free model (sky + sources) as ``DemoTile.model``.
    galaxy_counts, star_counts : (n_ref, slope, m_ref) or None, default None
        Replace the galaxy (or star) number counts below by one power law
        ``dN/dm = n_ref 10**(slope (m - m_ref))`` deg^-2 mag^-1 (before the
        ``galaxy_density`` / ``star_density`` multiplier), over ``mag_bright``
        (galaxies) or r = 16 (stars) to ``mag_faint``: mock populations of known
        counts, e.g. for :mod:`comest_bayes.lf.fit`.  None (the default) keeps the
        populations of ``docs/demo.md``; the ``n_saturated_stars`` are added either way.
    progress : callable, optional
        ``progress(done, total)``, see above.

    Returns
    -------
    DemoTile

    Raises
    ------
    InputError
        A parameter is out of range.
    """
    spec = _Spec(size=size, pixel_scale=pixel_scale, zeropoint=zeropoint, fwhm_arcsec=fwhm_arcsec,
                 moffat_beta=moffat_beta, sky_level=sky_level, gain=gain, read_noise=read_noise,
                 saturation=saturation, exptime=exptime, depth_gradient=depth_gradient,
                 shallow_quadrant=shallow_quadrant, gap_width=gap_width, n_saturated_stars=n_saturated_stars,
                 galaxy_density=galaxy_density, star_density=star_density, mag_bright=mag_bright,
                 faint_margin=faint_margin, ra_center=ra_center, dec_center=dec_center,
                 rotation_deg=rotation_deg, galaxy_counts=galaxy_counts, star_counts=star_counts)
    truth, info = _truth_table(spec, seed)
    shape = (spec.size, spec.size)

    src, drawn = _draw_sources(spec, truth, progress)
    truth.add_column(Column(drawn, name="flux_in_tile",
                            description="flux drawn into the tile, ADU (>= 99.7% of flux unless cut by the edge)"),
                     index=truth.colnames.index("flux") + 1)
    f = noise_factor_map(shape, spec.depth_gradient, spec.shallow_quadrant)
    sigma = spec.sigma0 * f
    rng = rng_for(seed, Stream.DEMO, Stream.DEMO_NOISE)
    # Sky noise (sigma0 f)^2 plus source photon noise S f^2 / gain, in place to limit memory.
    var = np.maximum(src, 0.0)
    var *= f * f / spec.gain
    var += sigma * sigma
    np.sqrt(var, out=var)
    noise = rng.standard_normal(shape)
    noise *= var
    del var
    model = src
    model += spec.sky_level          # ``src`` becomes the noise-free model
    image = model + noise
    del noise

    sat = image >= spec.saturation
    excess = np.maximum(model - spec.saturation, 0.0)
    satmask = _bleed(sat, excess, spec.saturation - spec.sky_level) if sat.any() else sat
    del excess
    model = model.astype(np.float32) if keep_model else None
    image[satmask] = spec.saturation

    mask = np.zeros(shape, dtype=np.uint8)
    mask[satmask] = MASK_SATURATED
    weight = 1.0 / (sigma * sigma)
    gx0, gx1 = spec.gap
    if gx1 > gx0:
        image[:, gx0:gx1] = 0.0
        weight[:, gx0:gx1] = 0.0
        mask[:, gx0:gx1] |= MASK_GAP

    # Pixel-dependent truth columns.
    ix = np.clip(np.rint(truth["x"]).astype(int), 0, spec.size - 1)
    iy = np.clip(np.rint(truth["y"]).astype(int), 0, spec.size - 1)
    near = ndimage.maximum_filter(satmask, size=3, mode="constant", cval=False)
    truth["saturated"] = near[iy, ix]
    truth["masked"] = mask[iy, ix] != 0

    params = asdict(spec)
    for name in ("galaxy_counts", "star_counts"):  # recorded only when used, so default params are unchanged
        if params[name] is None:
            params.pop(name)
        else:
            params[name] = list(params[name])
    params.update({
        "seed": int(seed),
        "sigma_sky": spec.sigma0,
        "fwhm_pix": spec.fwhm_pix,
        "neff_pix": spec.neff_pix(),
        "gap_x": [int(gx0), int(gx1)],
        "mask_bits": {"gap": MASK_GAP, "saturated": MASK_SATURATED},
        "n_saturated_pixels": int(satmask.sum()),
        "n_saturated_sources": int(np.count_nonzero(truth["saturated"])),
        **{k: (float(v) if isinstance(v, float) else v) for k, v in info.items()},
    })
    return DemoTile(image=image.astype(np.float32), weight=weight.astype(np.float32), mask=mask,
                    header=_header(spec, seed, info), truth=truth, params=params, model=model)


# ---------------------------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------------------------

def demo_seeing_pix(image_path) -> float:
    """Seeing FWHM in pixels that a demo tile was drawn with (header ``SEEING`` / ``PIXSCALE``).

    Raises
    ------
    InputError
        The file is not a demo tile (no such keywords).
    """
    header = fits.getheader(image_path)
    try:
        return float(header["SEEING"]) / float(header["PIXSCALE"])
    except (KeyError, TypeError, ValueError, ZeroDivisionError):
        raise InputError(f"{str(image_path)!r} is not a demo tile: its header lacks SEEING and PIXSCALE.") from None


def write_demo_tile(tile: DemoTile, directory) -> dict[str, Path]:
    """Write the tile as FITS files into ``directory`` (created if needed).

    Files: ``demo_image.fits`` (image + full header), ``demo_weight.fits``
    (inverse variance, same WCS), ``demo_mask.fits`` (uint8 bits, same WCS)
    and ``demo_truth.fits`` (the truth table).  Each is written to a
    temporary name in the same directory and moved into place with
    :func:`os.replace`, so a reader never sees a half-written file; existing
    files of these names are replaced (the caller decides whether to call).

    Returns
    -------
    dict
        ``{"image": Path, "weight": Path, "mask": Path, "truth": Path}``.

    Raises
    ------
    RunDirectoryError
        The directory cannot be created or written.
    """
    directory = Path(directory)
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RunDirectoryError(f"cannot create the demo directory {str(directory)!r} ({exc}).") from None
    wcs_hdr = _wcs_header(WCS(tile.header))

    weight_hdr = wcs_hdr.copy()
    weight_hdr["BUNIT"] = ("ADU-2", "inverse variance of the sky noise")
    weight_hdr.add_comment("SYNTHETIC: weight map of demo_image.fits (inverse variance; 0 = no data).")
    mask_hdr = wcs_hdr.copy()
    mask_hdr.add_comment("SYNTHETIC: mask of demo_image.fits. Bits: 1 = chip gap, 2 = saturated/bleed.")
    truth_hdu = fits.table_to_hdu(tile.truth)
    truth_hdu.header.add_comment("SYNTHETIC: every source rendered in demo_image.fits; x, y are 0-based.")

    hdus = {
        "image": fits.HDUList([fits.PrimaryHDU(tile.image, header=tile.header)]),
        "weight": fits.HDUList([fits.PrimaryHDU(tile.weight, header=weight_hdr)]),
        "mask": fits.HDUList([fits.PrimaryHDU(tile.mask, header=mask_hdr)]),
        "truth": fits.HDUList([fits.PrimaryHDU(), truth_hdu]),
    }
    paths = {}
    for role, hdul in hdus.items():
        path = directory / DEMO_FILES[role]
        with atomic_path(path) as tmp:
            hdul.writeto(tmp, overwrite=False, output_verify="exception")
        paths[role] = path
    return paths
