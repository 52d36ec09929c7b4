"""Reading an observed image and its companions (weight map, mask).

This is the I/O boundary of the pipeline: everything here validates, and
everything after it may assume a valid :class:`ImageData`.  Every check runs
before any output is written.

What is handled
---------------
* any HDU (``hdu=None`` picks the first HDU holding a 2-D image, so a
  tile-compressed image in HDU 1 is found);
* big-endian FITS data are converted to native-endian float32 (SEP refuses
  non-native byte order);
* NaN and infinite pixels are masked (and set to 0 so no NaN reaches SEP);
* a celestial WCS (TAN, TPV, ZPN, SIP, ... whatever astropy/wcslib reads); the
  pixel scale is measured from the WCS at the image centre, so distortion
  terms are included;
* zero point from ``zp=`` or the first of :data:`ZP_KEYWORDS` found in the
  image HDU's header, then the primary header; gain and saturation likewise;
* a weight map as inverse variance, RMS or variance, turned into a noise-sigma
  map; non-positive weights are masked;
* a mask file (non-zero = bad, or ``mask_bits`` to select bits).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from astropy.io import fits
from astropy.wcs import WCS, FITSFixedWarning

from .errors import InputError, InputFileError

__all__ = ["ImageData", "load_image", "ZP_KEYWORDS", "GAIN_KEYWORDS", "SATURATION_KEYWORDS"]

#: Header keywords searched for a photometric zero point, in this order.
ZP_KEYWORDS = ("MAGZERO", "MAGZPT", "MAGZP", "PHOTZP", "ZEROPOINT", "ZEROPT", "ZPMAG", "MZP", "ZPT", "ZP")
#: Header keywords searched for the gain in e-/ADU.
GAIN_KEYWORDS = ("GAIN", "CCDGAIN", "EGAIN", "GAINEFF")
#: Header keywords searched for the saturation level in image units.
SATURATION_KEYWORDS = ("SATURATE", "SATURATN", "SATLEVEL", "SATURAT")

WEIGHT_TYPES = ("ivar", "rms", "var")


@dataclass
class ImageData:
    """An observed image ready for detection.

    Attributes
    ----------
    data : ndarray, shape (ny, nx), float32
        Pixel values in image units, native byte order; masked pixels are 0.
    mask : ndarray, shape (ny, nx), bool
        True where a pixel is unusable (mask file, non-finite, zero weight).
    noise : ndarray or None, shape (ny, nx), float32
        1-sigma noise per pixel from the weight map (image units), or None.
        Masked pixels hold ``inf``.
    wcs : astropy.wcs.WCS or None
        Celestial WCS, or None when the header has none.
    header : astropy.io.fits.Header
        The image HDU's header (a copy).
    zeropoint : float
        Magnitude of a source giving one image unit of total flux:
        ``m = zeropoint - 2.5 log10(flux)``.
    pixel_scale : float
        Arcseconds per pixel (geometric mean, at the image centre).
    gain : float or None
        Electrons per image unit, for photon noise; None if unknown.
    saturation : float or None
        Saturation level in image units, or None.
    fwhm : float or None
        Seeing FWHM in pixels when given by the user; otherwise filled in by
        :func:`comest_bayes.psf.estimate_fwhm` later.
    provenance : dict
        Where each of zeropoint, pixel_scale, gain, saturation, fwhm came from.
    path, hdu : str, int
        The file read and the HDU index used.
    """

    data: np.ndarray
    mask: np.ndarray
    noise: np.ndarray | None
    wcs: WCS | None
    header: fits.Header
    zeropoint: float
    pixel_scale: float
    gain: float | None = None
    saturation: float | None = None
    fwhm: float | None = None
    provenance: dict = field(default_factory=dict)
    path: str = ""
    hdu: int = 0

    @property
    def shape(self) -> tuple[int, int]:
        return self.data.shape

    @property
    def unmasked_fraction(self) -> float:
        return float(1.0 - self.mask.mean())

    def facts(self) -> dict:
        """JSON-ready summary of the image and where each number came from."""
        return {
            "path": self.path,
            "hdu": self.hdu,
            "shape": list(self.shape),
            "zeropoint": self.zeropoint,
            "pixel_scale_arcsec": self.pixel_scale,
            "gain": self.gain,
            "saturation": self.saturation,
            "fwhm_pix": self.fwhm,
            "wcs": None if self.wcs is None else list(self.wcs.wcs.ctype),
            "masked_fraction": float(self.mask.mean()),
            "has_weight": self.noise is not None,
            "provenance": dict(self.provenance),
        }


def _open(path, what: str):
    path = Path(path)
    if not path.exists():
        raise InputFileError(f"{what} file {str(path)!r} does not exist; check the path.")
    if not path.is_file():
        raise InputFileError(f"{what} path {str(path)!r} is not a file.")
    try:
        return fits.open(path, memmap=False, lazy_load_hdus=False)
    except (OSError, ValueError, TypeError) as exc:
        raise InputError(f"{what} file {str(path)!r} is not a readable FITS file ({exc}).") from None


def _pick_hdu(hdul, hdu, path, what):
    if hdu is None:
        for i, h in enumerate(hdul):
            if getattr(h, "data", None) is not None and getattr(h.data, "ndim", 0) == 2 and h.is_image:
                return i
        raise InputError(
            f"{what} file {str(path)!r} holds no 2-D image in any of its {len(hdul)} HDUs; "
            f"is it a table or a cube? Pass --hdu to choose one."
        )
    if not (0 <= hdu < len(hdul)):
        raise InputError(f"{what} file {str(path)!r} has {len(hdul)} HDUs (0-{len(hdul) - 1}); got hdu={hdu}.")
    h = hdul[hdu]
    if getattr(h, "data", None) is None or not h.is_image or h.data.ndim != 2:
        shape = None if getattr(h, "data", None) is None else getattr(h.data, "shape", None)
        raise InputError(
            f"HDU {hdu} of {what} file {str(path)!r} is not a 2-D image (data shape {shape}); "
            f"pick another with --hdu."
        )
    return hdu


def _read_2d(path, hdu, what):
    with _open(path, what) as hdul:
        idx = _pick_hdu(hdul, hdu, path, what)
        data = np.asarray(hdul[idx].data, dtype=np.float32)  # native byte order, a copy
        header = hdul[idx].header.copy()
        primary = hdul[0].header.copy() if idx != 0 else None
    return data, header, primary, idx


def _header_value(keys, header, primary):
    for where, hdr in (("image header", header), ("primary header", primary)):
        if hdr is None:
            continue
        for key in keys:
            if key in hdr:
                try:
                    value = float(hdr[key])
                except (TypeError, ValueError):
                    continue
                if np.isfinite(value):
                    return value, f"{where} {key}"
    return None, None


def _celestial_wcs(header):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FITSFixedWarning)
        try:
            wcs = WCS(header)
        except Exception:  # astropy raises several types for broken WCS headers
            return None
    if not wcs.has_celestial:
        return None
    return wcs.celestial


def _wcs_pixel_scale(wcs, shape) -> float:
    """Arcsec per pixel from the WCS at the image centre, distortion included."""
    ny, nx = shape
    cx, cy = (nx - 1) / 2.0, (ny - 1) / 2.0
    pts = wcs.pixel_to_world([cx, cx + 1.0, cx], [cy, cy, cy + 1.0])
    dx = pts[0].separation(pts[1]).to_value("arcsec")
    dy = pts[0].separation(pts[2]).to_value("arcsec")
    pa = pts[0].position_angle(pts[1]).to_value("rad") - pts[0].position_angle(pts[2]).to_value("rad")
    area = dx * dy * abs(np.sin(pa))
    return float(np.sqrt(area))


def load_image(path, *, hdu: int | None = None, zp: float | None = None, pixel_scale: float | None = None,
               fwhm: float | None = None, gain: float | None = None, saturation: float | None = None,
               weight=None, weight_type: str = "ivar", weight_hdu: int | None = None,
               mask=None, mask_hdu: int | None = None, mask_bits: int | None = None) -> ImageData:
    """Read and validate an image, its weight map and mask.

    Parameters
    ----------
    path : str or Path
        FITS image.
    hdu : int, optional
        HDU index; default the first 2-D image HDU.
    zp : float, optional
        Photometric zero point; default from the header (:data:`ZP_KEYWORDS`).
    pixel_scale : float, optional
        Arcsec per pixel; default from the WCS.  Required when there is no WCS.
    fwhm : float, optional
        Seeing FWHM in *pixels*; default: estimated from stars later.
    gain, saturation : float, optional
        e-/image unit and saturation level; default from the header, if present.
    weight : str or Path, optional
        Weight map file of the same shape.
    weight_type : {"ivar", "rms", "var"}
        What the weight map holds: inverse variance, 1-sigma noise, variance.
    weight_hdu, mask_hdu : int, optional
        HDU of the weight / mask file; default the first 2-D image HDU.
    mask : str or Path, optional
        Mask file; pixels with non-zero values are bad.
    mask_bits : int, optional
        If given, only pixels with ``mask & mask_bits != 0`` are bad.

    Raises
    ------
    InputFileError
        A file is missing.
    InputError
        Unusable data: no 2-D image, shape mismatch, no WCS and no pixel scale,
        no zero point, everything masked, a constant image, bad parameters.
    """
    if weight_type not in WEIGHT_TYPES:
        raise InputError(f"weight_type={weight_type!r} is not one of {WEIGHT_TYPES}; "
                         f"use ivar (inverse variance), rms (sigma) or var (variance).")
    for name, value in (("pixel_scale", pixel_scale), ("fwhm", fwhm), ("gain", gain), ("saturation", saturation)):
        if value is not None and not (np.isfinite(value) and value > 0):
            raise InputError(f"{name}={value!r} must be a positive finite number.")
    if zp is not None and not np.isfinite(zp):
        raise InputError(f"zp={zp!r} must be a finite number.")

    data, header, primary, idx = _read_2d(path, hdu, "image")
    provenance = {}
    ny, nx = data.shape
    if ny < 16 or nx < 16:
        raise InputError(f"image {str(path)!r} is only {nx}x{ny} pixels; at least 16x16 is needed.")

    # Companions first, so every shape problem is reported before any work.
    noise = None
    bad = ~np.isfinite(data)
    if weight is not None:
        wdata, _, _, _ = _read_2d(weight, weight_hdu, "weight")
        if wdata.shape != data.shape:
            raise InputError(
                f"weight map {str(weight)!r} has shape {wdata.shape} but the image {str(path)!r} has "
                f"{data.shape}; give the weight map that belongs to this image (and HDU)."
            )
        with np.errstate(divide="ignore", invalid="ignore"):
            if weight_type == "ivar":
                noise = 1.0 / np.sqrt(wdata)
            elif weight_type == "var":
                noise = np.sqrt(wdata)
            else:
                noise = wdata.copy()
        badw = ~np.isfinite(noise) | (noise <= 0)
        noise = noise.astype(np.float32)
        noise[badw] = np.inf
        bad |= badw
        provenance["weight"] = f"{weight} ({weight_type})"
    if mask is not None:
        mdata, _, _, _ = _read_2d(mask, mask_hdu, "mask")
        if mdata.shape != data.shape:
            raise InputError(
                f"mask {str(mask)!r} has shape {mdata.shape} but the image {str(path)!r} has "
                f"{data.shape}; give the mask that belongs to this image (and HDU)."
            )
        if not np.all(np.isfinite(mdata)):
            mdata = np.where(np.isfinite(mdata), mdata, 1)
        if mask_bits is not None:
            bad |= (mdata.astype(np.int64) & int(mask_bits)) != 0
        else:
            bad |= mdata != 0
        provenance["mask"] = f"{mask}" + (f" (bits {mask_bits})" if mask_bits is not None else "")

    if bad.all():
        raise InputError(
            f"every pixel of {str(path)!r} is masked (non-finite, zero weight or flagged in the mask); "
            f"check the mask file and --mask-bits, or the weight map."
        )
    good = data[~bad]
    if good.size < 256:
        raise InputError(f"only {good.size} usable pixels in {str(path)!r}; at least 256 are needed.")
    if np.ptp(good) == 0:
        raise InputError(
            f"image {str(path)!r} is constant ({good[0]!r} in every unmasked pixel): there is no sky noise "
            f"to detect against. Is this the right HDU (--hdu) or a blank frame?"
        )

    wcs = _celestial_wcs(header)
    if pixel_scale is not None:
        provenance["pixel_scale"] = "--pixel-scale"
    elif wcs is not None:
        pixel_scale = _wcs_pixel_scale(wcs, data.shape)
        provenance["pixel_scale"] = f"WCS ({'/'.join(wcs.wcs.ctype)}) at the image centre"
    else:
        raise InputError(
            f"image {str(path)!r} has no celestial WCS in its header, so its pixel scale is unknown; "
            f"pass --pixel-scale ARCSEC_PER_PIXEL (e.g. --pixel-scale 0.2)."
        )

    if zp is not None:
        provenance["zeropoint"] = "--zp"
    else:
        zp, src = _header_value(ZP_KEYWORDS, header, primary)
        if zp is None:
            raise InputError(
                f"no photometric zero point for {str(path)!r}: none of the header keywords "
                f"{', '.join(ZP_KEYWORDS)} is present; pass --zp MAG (magnitude of one image unit)."
            )
        provenance["zeropoint"] = src

    if gain is not None:
        provenance["gain"] = "--gain"
    else:
        gain, src = _header_value(GAIN_KEYWORDS, header, primary)
        if gain is not None and gain <= 0:
            gain = None
        provenance["gain"] = src if gain is not None else "unknown (no photon noise on injections)"
    if saturation is not None:
        provenance["saturation"] = "--saturation"
    else:
        saturation, src = _header_value(SATURATION_KEYWORDS, header, primary)
        if saturation is not None and saturation <= 0:
            saturation = None
        provenance["saturation"] = src if saturation is not None else "unknown"
    if fwhm is not None:
        provenance["fwhm"] = "--fwhm"

    data[bad] = 0.0
    return ImageData(
        data=np.ascontiguousarray(data), mask=bad, noise=noise, wcs=wcs, header=header,
        zeropoint=float(zp), pixel_scale=float(pixel_scale), gain=gain, saturation=saturation,
        fwhm=fwhm, provenance=provenance, path=str(path), hdu=idx,
    )
