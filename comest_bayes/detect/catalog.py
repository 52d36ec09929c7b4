"""The detection catalog: one column schema (:data:`DETECTION_COLUMNS`) for every detection backend.

Both backends produce an :class:`astropy.table.Table` with exactly these columns, so everything
downstream is written once.  Conventions (0-based pixels, NaN magnitudes, SExtractor's flag
bits): ``docs/detection.md``.
"""

from __future__ import annotations

import re
import warnings

import numpy as np
from astropy.table import Table

__all__ = ["DETECTION_COLUMNS", "FLAG_MASKED", "FLAG_BLENDED", "FLAG_SATURATED", "FLAG_EDGE",
           "FLAG_APER_TRUNC", "FLAG_DEBLEND_OVERFLOW", "IMAGE_UNIT_COLUMNS", "make_catalog", "flux_to_mag",
           "derived_columns", "fits_unit", "set_image_units"]

FLAG_MASKED = 1
FLAG_BLENDED = 2
FLAG_SATURATED = 4
FLAG_EDGE = 8
FLAG_APER_TRUNC = 16
FLAG_DEBLEND_OVERFLOW = 64

#: name -> (numpy dtype, unit, description).  "flux" is the image's unit.
DETECTION_COLUMNS = {
    "id": ("i8", None, "1-based object number; equals the object's value in the segmentation map"),
    "x": ("f8", "pix", "barycentre x, 0-based (X_IMAGE - 1)"),
    "y": ("f8", "pix", "barycentre y, 0-based (Y_IMAGE - 1)"),
    "xwin": ("f8", "pix", "windowed centroid x, 0-based (XWIN_IMAGE - 1)"),
    "ywin": ("f8", "pix", "windowed centroid y, 0-based (YWIN_IMAGE - 1)"),
    "ra": ("f8", "deg", "right ascension of (xwin, ywin); NaN without a WCS"),
    "dec": ("f8", "deg", "declination of (xwin, ywin); NaN without a WCS"),
    "a": ("f8", "pix", "isophotal semi-major axis (A_IMAGE)"),
    "b": ("f8", "pix", "isophotal semi-minor axis (B_IMAGE)"),
    "theta": ("f8", "rad", "position angle of a, counter-clockwise from +x (THETA_IMAGE in radians)"),
    "npix": ("i8", "pix2", "isophotal area above the threshold (ISOAREA_IMAGE)"),
    "peak": ("f8", None, "peak pixel value above the background (FLUX_MAX), image units"),
    "flux_iso": ("f8", None, "isophotal flux (FLUX_ISO), image units"),
    "kron_radius": ("f8", None, "AUTO aperture scale in units of a and b: max(k * Kron radius, r_min) as SExtractor's KRON_RADIUS; 0 if undefined"),
    "flux_auto": ("f8", None, "flux in the Kron ellipse (FLUX_AUTO), image units"),
    "fluxerr_auto": ("f8", None, "1-sigma error of flux_auto (FLUXERR_AUTO), image units"),
    "mag_auto": ("f8", "mag", "zeropoint - 2.5 log10(flux_auto) (MAG_AUTO)"),
    "magerr_auto": ("f8", "mag", "1.0857 fluxerr_auto / flux_auto (MAGERR_AUTO)"),
    "snr_auto": ("f8", None, "flux_auto / fluxerr_auto"),
    "flux_aper": ("f8", None, "fluxes in circular apertures of the configured diameters (FLUX_APER)"),
    "fluxerr_aper": ("f8", None, "1-sigma errors of flux_aper (FLUXERR_APER)"),
    "mag_aper": ("f8", "mag", "aperture magnitudes (MAG_APER)"),
    "magerr_aper": ("f8", "mag", "aperture magnitude errors (MAGERR_APER)"),
    "flux_radius": ("f8", "pix", "radius enclosing phot_fluxfrac of flux_auto (FLUX_RADIUS)"),
    "background": ("f8", None, "local background at the peak pixel (BACKGROUND), image units"),
    "noise": ("f8", None, "noise sigma the threshold was relative to, at the peak pixel, image units"),
    "flags": ("i8", None, "SExtractor-style FLAGS bits (see comest_bayes.detect.catalog)"),
}


#: Columns in the image's own unit (its ``BUNIT``), in the detection catalog, the injected truth and the
#: outcome tables; a ``det_`` prefix (measured columns next to an injection) counts too.
IMAGE_UNIT_COLUMNS = ("peak", "flux_iso", "flux_auto", "fluxerr_auto", "flux_aper", "fluxerr_aper", "background",
                      "noise", "flux", "local_noise")


#: Common ``BUNIT`` words that are not FITS unit names, and the FITS unit they mean (case-insensitive).
_BUNIT_ALIASES = {"adu": "adu", "counts": "count", "cts": "count", "s": "s", "sec": "s"}


def fits_unit(bunit):
    """The astropy unit a FITS ``BUNIT`` names, or None when it names none the FITS standard knows.

    ``MJy/sr``, ``ct/s`` and ``Jy/pix`` are FITS units, and so are the common
    spellings ``ADU`` and ``COUNTS/S`` once read as ``adu`` and ``count/s``;
    electrons, ``DN`` and nanomaggies have no FITS unit (a column given one
    makes astropy warn on every write or read).
    """

    import astropy.units as u

    if not isinstance(bunit, str) or not bunit.strip():
        return None
    text = re.sub(r"[A-Za-z]+-?", lambda m: _BUNIT_ALIASES.get(m.group(0).lower(), m.group(0)), bunit.strip())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            unit = u.Unit(text, format="fits")
        except (ValueError, TypeError):
            return None
    return None if isinstance(unit, u.UnrecognizedUnit) else unit


def set_image_units(table: Table, bunit) -> Table:
    """Give the image-unit columns (:data:`IMAGE_UNIT_COLUMNS`) of ``table`` the image's ``BUNIT``, in place.

    A ``BUNIT`` that is not a FITS unit (see :func:`fits_unit`) leaves them
    without one; either way the raw ``BUNIT`` is kept as ``table.meta["IMGUNIT"]``
    so that a reader of the file knows what "image units" means.  Returns
    ``table``.
    """
    if not isinstance(bunit, str) or not bunit.strip():
        return table
    unit = fits_unit(bunit)
    if unit is not None:
        for name in table.colnames:
            if name in IMAGE_UNIT_COLUMNS or (name.startswith("det_") and name[4:] in IMAGE_UNIT_COLUMNS):
                table[name].unit = unit
    table.meta["IMGUNIT"] = bunit.strip()
    return table


def flux_to_mag(flux, fluxerr, zeropoint):
    """Magnitude and its error; NaN where the flux is not positive."""
    flux = np.asarray(flux, dtype=float)
    fluxerr = np.asarray(fluxerr, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        pos = flux > 0
        mag = np.where(pos, zeropoint - 2.5 * np.log10(np.where(pos, flux, 1.0)), np.nan)
        magerr = np.where(pos, 2.5 / np.log(10.0) * fluxerr / np.where(pos, flux, 1.0), np.nan)
    return mag, magerr


def derived_columns(flux_auto, fluxerr_auto, flux_aper, fluxerr_aper, xwin, ywin, *, zeropoint, wcs=None) -> dict:
    """The columns every backend derives the same way: magnitudes, AUTO SNR and sky coordinates."""
    mag_auto, magerr_auto = flux_to_mag(flux_auto, fluxerr_auto, zeropoint)
    mag_aper, magerr_aper = flux_to_mag(flux_aper, fluxerr_aper, zeropoint)
    flux_auto = np.asarray(flux_auto, dtype=float)
    fluxerr_auto = np.asarray(fluxerr_auto, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        snr = np.where(fluxerr_auto > 0, flux_auto / fluxerr_auto, np.nan)
    n = len(flux_auto)
    if wcs is not None and n:
        ra, dec = wcs.all_pix2world(np.asarray(xwin, float), np.asarray(ywin, float), 0)
    else:
        ra = dec = np.full(n, np.nan)
    return {"mag_auto": mag_auto, "magerr_auto": magerr_auto, "mag_aper": mag_aper, "magerr_aper": magerr_aper,
            "snr_auto": snr, "ra": ra, "dec": dec}


def make_catalog(columns: dict, naper: int, meta: dict | None = None) -> Table:
    """Assemble a catalog table with the standard schema.

    Parameters
    ----------
    columns : dict
        Arrays for every key of :data:`DETECTION_COLUMNS`; the aperture columns
        have shape (n, naper).
    naper : int
        Number of circular apertures.
    meta : dict, optional
        Table metadata (zero point, backend, threshold...).
    """
    missing = set(DETECTION_COLUMNS) - set(columns)
    if missing:
        raise KeyError(f"catalog is missing columns {sorted(missing)}")
    n = len(columns["id"])
    table = Table(meta=dict(meta or {}))
    for name, (dtype, unit, desc) in DETECTION_COLUMNS.items():
        values = np.asarray(columns[name], dtype=dtype)
        if name.endswith("_aper"):
            values = values.reshape(n, naper)
        table[name] = values
        table[name].unit = unit
        table[name].description = desc
    return table
