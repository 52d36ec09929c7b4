"""The effective PSF the injections are convolved with: a Moffat, Gaussian or Kolmogorov of the
image's FWHM (the fitted Moffat pixel-integrated), or a FITS PSF image checked for use
(``docs/sources.md``, "PSF").
"""

from __future__ import annotations

from pathlib import Path
import galsim
import numpy as np
from astropy.io import fits
from comest_bayes.config import InjectionConfig, PSF_KINDS
from comest_bayes.errors import InputError, InputFileError

__all__ = ['make_psf', 'read_psf_image', 'psf_image_fwhm_pix', 'psf_half_light_radius_pix', 'DEFAULT_MOFFAT_BETA']
#: Moffat beta injected when neither the configuration nor the image's stars give one.
DEFAULT_MOFFAT_BETA = 3.0


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


def psf_image_fwhm_pix(config: InjectionConfig, pixel_scale: float) -> float | None:
    """FWHM in image pixels of the PSF image ``config.psf`` names (as :func:`make_psf` reads it); None for an
    analytic PSF, whose size is the image's seeing."""
    if config.psf.strip().lower() in PSF_KINDS:
        return None
    return float(make_psf(config, None, pixel_scale).calculateFWHM()) / float(pixel_scale)


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
