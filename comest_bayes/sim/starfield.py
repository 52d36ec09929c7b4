"""Synthetic star fields of any crowding: Gaussian stars on white noise, with power-law counts.

Used to test and measure what confusion does to a run (``benchmarks/bench_confusion.py``,
``tests/integration/test_confused_range.py``): the star counts rise as ``10^(slope m)`` up to two
magnitudes below the 5-sigma point-source depth m5, and ``density`` sets how many stars per
arcmin^2 are brighter than m5.
"""

from __future__ import annotations

import math

import numpy as np
from astropy.io import fits
from scipy.special import ndtr

from comest_bayes.constants import FWHM_PER_SIGMA
from comest_bayes.seeding import rng_for

__all__ = ["gaussian_m5", "star_field"]


def gaussian_m5(fwhm_pix: float, sigma: float, zeropoint: float) -> float:
    """5-sigma depth of a Gaussian point source on white noise (noise-equivalent area ``4 pi s^2``)."""
    s = fwhm_pix / FWHM_PER_SIGMA
    return zeropoint - 2.5 * math.log10(5.0 * sigma * math.sqrt(4.0 * math.pi * s * s))


def star_field(shape: tuple[int, int], density: float, *, pixel_scale: float = 0.5, fwhm_pix: float = 3.0,
               sigma: float = 10.0, zeropoint: float = 30.0, slope: float = 0.3, span: float = 12.0,
               seed: int = 0) -> tuple[fits.PrimaryHDU, dict]:
    """A star field as a FITS HDU (TAN WCS, ``MAGZERO``), and its facts.

    Stars are uniform in position, with magnitudes from ``m5 - span`` to ``m5 + 2`` whose counts
    rise as ``10^(slope m)``; ``density`` of them per arcmin^2 are brighter than m5.  Each is a
    circular Gaussian of ``fwhm_pix``, integrated exactly over its pixels; the noise is white of
    ``sigma``.  Returns ``(hdu, {"m5", "nstars", "mags"})``.
    """
    ny, nx = (int(v) for v in shape)
    rng = rng_for(seed)
    m5 = gaussian_m5(fwhm_pix, sigma, zeropoint)
    area = nx * ny * (pixel_scale / 60.0) ** 2
    lo, hi = m5 - span, m5 + 2.0
    n = int(rng.poisson(density * area * 10.0 ** (slope * (hi - m5))))
    u = rng.uniform(10.0 ** (slope * (lo - hi)), 1.0, n)  # inverse CDF of N(< m) ~ 10^(slope m) on [lo, hi]
    mags = hi + np.log10(u) / slope
    x, y = rng.uniform(-0.5, nx - 0.5, n), rng.uniform(-0.5, ny - 0.5, n)
    img = rng.normal(0.0, sigma, (ny, nx))
    s = fwhm_pix / FWHM_PER_SIGMA
    half = int(math.ceil(5.0 * s)) + 1
    edges = np.arange(-half, half + 2) - 0.5
    for xi, yi, flux in zip(x, y, 10.0 ** (-0.4 * (mags - zeropoint))):
        ix, iy = int(round(xi)), int(round(yi))
        px = np.diff(ndtr((edges + ix - xi) / s))  # pixel-integrated profile along each axis
        py = np.diff(ndtr((edges + iy - yi) / s))
        x0, x1, y0, y1 = max(ix - half, 0), min(ix + half + 1, nx), max(iy - half, 0), min(iy + half + 1, ny)
        img[y0:y1, x0:x1] += flux * np.outer(py[y0 - iy + half:y1 - iy + half], px[x0 - ix + half:x1 - ix + half])
    header = fits.Header()
    header.update(CTYPE1="RA---TAN", CTYPE2="DEC--TAN", CRVAL1=150.0, CRVAL2=2.0, CRPIX1=nx / 2.0, CRPIX2=ny / 2.0,
                  CDELT1=-pixel_scale / 3600.0, CDELT2=pixel_scale / 3600.0, CUNIT1="deg", CUNIT2="deg",
                  MAGZERO=zeropoint)
    return fits.PrimaryHDU(img.astype(np.float32), header), {"m5": m5, "nstars": n, "mags": mags}
