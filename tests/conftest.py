"""Shared test fixtures: synthetic images with known sources, FITS writing, real data.

Fixtures
--------
shared_data
    ``Path`` of the real-data directory ``<repo>/../shared/data``; the test is
    skipped (with the reason) when it is absent, as in a user's fresh checkout.
make_sky
    Factory ``make_sky(**kwargs) -> SyntheticSky``: a flat sky with Gaussian
    noise of known sigma and point sources of known position and flux.
write_fits
    Factory ``write_fits(name, data, header=None, **kwargs) -> Path`` writing
    into the test's ``tmp_path``.
synthetic_fits
    Factory ``synthetic_fits(name="image.fits", **kwargs) -> SyntheticFits``:
    a :class:`SyntheticSky` written to ``tmp_path`` with a TAN WCS and a
    zero point keyword.

The plain helpers (``render_point_sources``, ``make_synthetic_sky``,
``tan_header``, ``write_fits_file``, ``matched_snr``, ``crowded_field``, ``FWHM_PER_SIGMA``) are
also imported by the test modules (``from conftest import ...``; ``pythonpath`` in
pyproject.toml puts ``tests/`` on ``sys.path`` for the test files in its subfolders).  Everything is deterministic: every random draw
comes from a seed argument.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits
from scipy.special import erf

REPO_ROOT = Path(__file__).resolve().parents[1]
#: The real-data directory beside the repository (not part of it).
SHARED_DATA = REPO_ROOT / ".." / "shared" / "data"

def load_benchmark(name: str):
    """``benchmarks/<name>.py`` as a module (the benchmarks folder is no package), for the tests of
    the helpers a benchmark's figures rest on."""
    import importlib.util
    import sys

    bench_dir = REPO_ROOT / "benchmarks"
    if str(bench_dir) not in sys.path:  # a benchmark may import its sibling scripts
        sys.path.insert(0, str(bench_dir))
    spec = importlib.util.spec_from_file_location(f"{name}_for_tests", bench_dir / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


#: FWHM of a Gaussian in units of its sigma, 2 sqrt(2 ln 2).
FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))


# --------------------------------------------------------------------------- rendering


def _pixel_integrated_gaussian_1d(centre: float, n: int, sigma: float) -> np.ndarray:
    """Integral of a unit-flux 1-D Gaussian over each of ``n`` unit pixels (centres at 0..n-1)."""
    edges = np.arange(n + 1) - 0.5 - centre
    cdf = 0.5 * (1.0 + erf(edges / (sigma * np.sqrt(2.0))))
    return np.diff(cdf)


def render_point_sources(shape, x, y, flux, *, fwhm: float, psf: str = "gaussian",
                         beta: float = 3.0) -> np.ndarray:
    """Noise-free image of point sources, each integrated over the pixel area.

    Parameters
    ----------
    shape : (ny, nx)
        Image shape.
    x, y : array_like, shape (n,)
        0-based pixel positions (centre of the first pixel is 0.0).
    flux : array_like, shape (n,)
        Total flux of each source (image units); a Gaussian source contributes
        exactly this flux, up to the part falling off the image.
    fwhm : float
        PSF full width at half maximum in pixels.
    psf : {"gaussian", "moffat"}
        Gaussian: exact pixel integrals (separable erf differences).  Moffat:
        drawn with GalSim (pixel-convolved, ``beta``).
    beta : float
        Moffat beta.

    Returns
    -------
    ndarray, shape (ny, nx), float64
    """
    ny, nx = shape
    out = np.zeros(shape, dtype=np.float64)
    x = np.atleast_1d(np.asarray(x, dtype=float))
    y = np.atleast_1d(np.asarray(y, dtype=float))
    flux = np.atleast_1d(np.asarray(flux, dtype=float))
    if psf == "gaussian":
        sigma = fwhm / FWHM_PER_SIGMA
        for xi, yi, fi in zip(x, y, flux):
            out += fi * np.outer(_pixel_integrated_gaussian_1d(yi, ny, sigma),
                                 _pixel_integrated_gaussian_1d(xi, nx, sigma))
        return out
    if psf == "moffat":
        import galsim

        image = galsim.ImageD(nx, ny, scale=1.0)  # GalSim pixel (1, 1) is numpy [0, 0]
        for xi, yi, fi in zip(x, y, flux):
            profile = galsim.Moffat(beta=beta, fwhm=fwhm, flux=fi)
            profile.drawImage(image=image, add_to_image=True, method="auto",
                              center=galsim.PositionD(xi + 1.0, yi + 1.0))
        return image.array.copy()
    raise ValueError(f"unknown psf {psf!r}")


def psf_effective_area(fwhm: float, psf: str = "gaussian", beta: float = 3.0) -> float:
    """Noise-equivalent area ``1 / integral(p^2)`` of a unit-flux PSF, in pixels.

    Gaussian: ``4 pi sigma^2``.  Moffat: ``pi alpha^2 (2 beta - 1) / (beta - 1)^2`` with
    ``alpha = fwhm / (2 sqrt(2^(1/beta) - 1))`` (pixelisation neglected).
    """
    if psf == "gaussian":
        return 4.0 * np.pi * (fwhm / FWHM_PER_SIGMA) ** 2
    if psf == "moffat":
        alpha = fwhm / (2.0 * np.sqrt(2.0 ** (1.0 / beta) - 1.0))
        return np.pi * alpha**2 * (2.0 * beta - 1.0) / (beta - 1.0) ** 2
    raise ValueError(f"unknown psf {psf!r}")


def matched_snr(flux, fwhm: float, sigma_noise: float, psf: str = "gaussian", beta: float = 3.0):
    """Matched-filter SNR of a point source on white noise: ``flux / (sigma_noise sqrt(area))``.

    The best SNR any linear measurement can reach; ``area`` is
    :func:`psf_effective_area`.
    """
    return np.asarray(flux, dtype=float) / (sigma_noise * np.sqrt(psf_effective_area(fwhm, psf, beta)))


@dataclass
class SyntheticSky:
    """A synthetic image and its truth.

    Attributes
    ----------
    data : ndarray, shape (ny, nx), float32
        Sky + sources + noise.
    model : ndarray, shape (ny, nx), float64
        Sources only, no sky, no noise.
    x, y, flux : ndarray, shape (n,)
        True 0-based positions and total fluxes.
    sky, sigma : float
        Sky level and noise sigma (image units).
    fwhm : float
        PSF FWHM in pixels.
    psf : str
        ``"gaussian"`` or ``"moffat"``.
    beta : float
        Moffat beta (unused for the Gaussian).
    """

    data: np.ndarray
    model: np.ndarray
    x: np.ndarray
    y: np.ndarray
    flux: np.ndarray
    sky: float
    sigma: float
    fwhm: float
    psf: str
    beta: float = 3.0

    @property
    def snr(self) -> np.ndarray:
        """Matched-filter SNR of every source (:func:`matched_snr`)."""
        return matched_snr(self.flux, self.fwhm, self.sigma, self.psf, self.beta)


def jittered_grid(shape, spacing: float, border: float, rng: np.random.Generator, jitter: float = 0.25):
    """Positions on a square grid of ``spacing`` pixels, each moved by up to ``jitter*spacing``.

    Neighbours stay at least ``spacing * (1 - 2 * jitter)`` apart, so sources
    are isolated when ``spacing`` is several FWHM.
    """
    ny, nx = shape
    gx = np.arange(border, nx - border + 1e-9, spacing)
    gy = np.arange(border, ny - border + 1e-9, spacing)
    xx, yy = np.meshgrid(gx, gy)
    xx = xx.ravel() + rng.uniform(-jitter, jitter, xx.size) * spacing
    yy = yy.ravel() + rng.uniform(-jitter, jitter, yy.size) * spacing
    return xx, yy


def make_synthetic_sky(*, shape=(256, 256), spacing: float = 32.0, border: float = 20.0,
                       snr_range=(5.0, 300.0), fwhm: float = 3.0, psf: str = "gaussian",
                       beta: float = 3.0, sky: float = 100.0, sigma: float = 5.0,
                       seed: int = 1) -> SyntheticSky:
    """Isolated point sources on a jittered grid, flat sky, white Gaussian noise.

    Fluxes are log-uniform between the fluxes giving matched-filter SNRs
    ``snr_range`` (see :func:`matched_snr`).  All draws come from
    ``np.random.default_rng(seed)``.
    """
    rng = np.random.default_rng(seed)
    x, y = jittered_grid(shape, spacing, border, rng)
    unit_snr = float(matched_snr(1.0, fwhm, sigma, psf, beta))
    lo, hi = np.log(snr_range[0] / unit_snr), np.log(snr_range[1] / unit_snr)
    flux = np.exp(rng.uniform(lo, hi, x.size))
    model = render_point_sources(shape, x, y, flux, fwhm=fwhm, psf=psf, beta=beta)
    data = (sky + model + rng.normal(0.0, sigma, shape)).astype(np.float32)
    return SyntheticSky(data=data, model=model, x=x, y=y, flux=flux, sky=sky, sigma=sigma, fwhm=fwhm, psf=psf,
                        beta=beta)


# --------------------------------------------------------------------------- FITS


def crowded_field(n: int = 256, nstars: int = 600, mags=(16.0, 24.0), seed: int = 1, zp: float = 30.0):
    """Gaussian stars (FWHM 3 px) at random positions, dN/dm ~ 10^(0.3 m), on a flat sky 100 with noise 10
    (magnitudes with zero point ``zp``).

    600 stars of 16-24 mag on 256^2 (half the density of 20,000 stars on 1024^2) leave a seventh of
    the pixels outside the grown segments, and no 64-px background mesh with half its pixels free.
    """
    rng = np.random.default_rng(seed)
    a = 0.3
    lo, hi = 10 ** (a * mags[0]), 10 ** (a * mags[1])
    m = np.log10(lo + rng.uniform(size=nstars) * (hi - lo)) / a
    x, y = rng.uniform(0, n, nstars), rng.uniform(0, n, nstars)
    model = render_point_sources((n, n), x, y, 10 ** (-0.4 * (m - zp)), fwhm=3.0)
    return (model + 100.0 + rng.normal(0.0, 10.0, (n, n))).astype(np.float32)


def tan_header(shape, pixel_scale: float = 0.2, rotation_deg: float = 0.0, crval=(150.1, 2.2),
               crpix=None) -> fits.Header:
    """A TAN WCS header with square pixels of ``pixel_scale`` arcsec, rotated by ``rotation_deg``.

    East is to the left (CD1_1 < 0 for no rotation), as on the sky.
    """
    ny, nx = shape
    s = pixel_scale / 3600.0
    t = np.deg2rad(rotation_deg)
    cd = s * np.array([[-np.cos(t), np.sin(t)], [np.sin(t), np.cos(t)]])
    header = fits.Header()
    header["CTYPE1"], header["CTYPE2"] = "RA---TAN", "DEC--TAN"
    header["CUNIT1"], header["CUNIT2"] = "deg", "deg"
    header["CRVAL1"], header["CRVAL2"] = crval
    cx, cy = crpix if crpix is not None else ((nx + 1) / 2.0, (ny + 1) / 2.0)
    header["CRPIX1"], header["CRPIX2"] = cx, cy
    if rotation_deg == 0.0:
        header["CDELT1"], header["CDELT2"] = -s, s
    else:
        header["CD1_1"], header["CD1_2"] = cd[0]
        header["CD2_1"], header["CD2_2"] = cd[1]
    return header


def write_fits_file(path, data, header=None, *, extension: bool = False, compressed: bool = False,
                    primary_header=None, extra_hdus=()) -> Path:
    """Write ``data`` as a FITS image; returns the path.

    Parameters
    ----------
    path : str or Path
    data : ndarray, shape (ny, nx)
    header : fits.Header, optional
        Keywords of the image HDU.
    extension : bool
        Put the image in HDU 1 (primary HDU empty) instead of HDU 0.
    compressed : bool
        Write HDU 1 as a tile-compressed image (lossless GZIP, no quantization);
        implies ``extension``.
    primary_header : fits.Header, optional
        Keywords of the primary HDU when the image is in an extension.
    extra_hdus : sequence of HDU
        Appended after the image.
    """
    path = Path(path)
    data = np.asarray(data)  # FITS stores it big-endian; astropy reads it back as '>f4'
    header = fits.Header() if header is None else header.copy()
    if compressed:
        primary = fits.PrimaryHDU(header=primary_header)
        image = fits.CompImageHDU(data=data, header=header, compression_type="GZIP_1", quantize_level=0)
        hdus = [primary, image]
    elif extension:
        hdus = [fits.PrimaryHDU(header=primary_header), fits.ImageHDU(data=data, header=header)]
    else:
        hdus = [fits.PrimaryHDU(data=data, header=header)]
    fits.HDUList(hdus + list(extra_hdus)).writeto(path, overwrite=True)
    return path


@dataclass
class SyntheticFits:
    """A synthetic image on disk with its truth (see :class:`SyntheticSky`)."""

    path: Path
    sky: SyntheticSky
    header: fits.Header
    pixel_scale: float
    zeropoint: float


# --------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The real-data directory ``<repo>/../shared/data``, or skip when it is absent."""
    path = SHARED_DATA.resolve()
    if not (path / "README.md").is_file():
        pytest.skip(f"real data not available: {path} does not exist (it sits beside the repository, "
                    f"as ../shared/data; a fresh checkout does not have it)")
    return path


@pytest.fixture
def make_sky():
    """Factory for :class:`SyntheticSky` (keyword arguments of ``make_synthetic_sky``)."""
    return make_synthetic_sky


@pytest.fixture
def write_fits(tmp_path):
    """Factory ``write_fits(name, data, header=None, **kw) -> Path`` inside ``tmp_path``."""

    def _write(name, data, header=None, **kwargs):
        return write_fits_file(tmp_path / name, data, header, **kwargs)

    return _write


@pytest.fixture
def synthetic_fits(tmp_path):
    """Factory writing a small synthetic image with known sources, a TAN WCS and MAGZERO.

    ``synthetic_fits(name="image.fits", pixel_scale=0.2, zeropoint=27.0,
    rotation_deg=0.0, header_extra=None, **sky_kwargs) -> SyntheticFits``
    (``sky_kwargs`` go to :func:`make_synthetic_sky`; a 128x128 image by default).
    """

    def _make(name="image.fits", *, pixel_scale=0.2, zeropoint=27.0, rotation_deg=0.0,
              header_extra=None, **sky_kwargs):
        sky_kwargs.setdefault("shape", (128, 128))
        sky = make_synthetic_sky(**sky_kwargs)
        header = tan_header(sky.data.shape, pixel_scale, rotation_deg)
        header["MAGZERO"] = zeropoint
        for key, value in (header_extra or {}).items():
            header[key] = value
        path = write_fits_file(tmp_path / name, sky.data, header)
        return SyntheticFits(path=path, sky=sky, header=header, pixel_scale=pixel_scale, zeropoint=zeropoint)

    return _make


def pytest_collection_modifyitems(config, items):
    """Every test that uses ``shared_data`` carries the ``realdata`` marker (``-m "not realdata"`` skips them all)."""
    for item in items:
        if "shared_data" in getattr(item, "fixturenames", ()) and item.get_closest_marker("realdata") is None:
            item.add_marker(pytest.mark.realdata)
