"""Reading an observed image and its companions (weight map, mask): the pipeline's I/O boundary.

Everything here validates, and everything after it may assume a valid :class:`ImageData`; every
check runs before any output is written.  What is handled: ``docs/detection.md`` ("Reading the
image"); the zero-point, gain and seeing rules: ``docs/usage.md`` ("Image facts").
"""

from __future__ import annotations

import math
import re
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np
from astropy.io import fits
from astropy.wcs import WCS

from comest_bayes.errors import InputError, InputFileError

__all__ = [
    "ImageData", "load_image", "parse_bunit", "sky_statistics", "decide_gain", "Units", "SkyStats",
    "GainDecision", "ZP_KEYWORDS", "GAIN_KEYWORDS", "SATURATION_KEYWORDS", "EXPTIME_KEYWORDS", "wcs_from_stored_header",
]

#: Header keywords searched for a photometric zero point, in this order.
ZP_KEYWORDS = ("MAGZERO", "MAGZPT", "MAGZP", "PHOTZP", "ZEROPOINT", "ZEROPT", "ZPMAG", "MZP", "ZPT", "ZP")
#: Header keywords searched for the gain in e-/ADU.
GAIN_KEYWORDS = ("GAIN", "CCDGAIN", "EGAIN", "GAINEFF")
#: Header keywords searched for the saturation level in image units.
SATURATION_KEYWORDS = ("SATURATE", "SATURATN", "SATLEVEL", "SATURAT")
#: Header keywords searched for the exposure time in seconds.
EXPTIME_KEYWORDS = ("EXPTIME", "EXPOSURE", "TEXPTIME")

WEIGHT_TYPES = ("ivar", "rms", "var")

#: Flux density of 0 AB mag, Jy.
AB_ZERO_JY = 3631.0
#: Speed of light in Angstrom per second (PHOTFLAM is per Angstrom).
C_ANGSTROM = 2.99792458e18
#: Steradians per square arcsecond.
SR_PER_ARCSEC2 = (math.pi / 648000.0) ** 2
#: Header zero points that differ by more than this (mag) are named in a warning.
ZP_AGREEMENT = 0.1
#: Plausible magnitude of one pixel's sky noise, zp - 2.5 log10(sigma) (mag).
PIXEL_DEPTH_RANGE = (10.0, 40.0)
#: Plausible zero point of an image in counts or electrons (mag).
COUNTS_ZP_RANGE = (10.0, 40.0)
#: Largest plausible difference between a zero point and the AB zero point of its flux unit (mag).
FLUX_ZP_TOLERANCE = 2.5
#: A sky level of at least this many sigma counts as not subtracted (its Poisson noise measures the gain).
SKY_MIN_SIGMAS = 10.0
#: A gain and the effective gain measured from the sky may differ by this factor at most.
GAIN_TOLERANCE = 4.0
#: The sky noise of one pixel is at least this many electrons for any real detector.
MIN_SKY_ELECTRONS = 1.0

# FITSFixedWarnings about metadata only (dates, units, obsolete keywords): not worth a line.
_HARMLESS_FIXES = ("'datfix'", "'unitfix'", "'obsfix'", "RADECSYS", "EPOCH")


def _num(value) -> str:
    """A number as plain text (never ``np.float32(...)``), 6 significant digits."""
    return f"{float(value):.6g}"


def _est(value) -> str:
    """A measured (noisy) number as plain text, 3 significant digits."""
    return f"{float(value):.3g}"


# --------------------------------------------------------------------------- units


class Units(NamedTuple):
    """What ``BUNIT`` says about the pixel values.

    Attributes
    ----------
    raw : str or None
        The keyword as written (None when absent).
    kind : {"counts", "electrons", "flux", "unknown"}
        ADU/DN/counts, electrons, a flux or surface-brightness unit, or not recognised.
    per_second : bool
        The unit is a rate (``.../s``, ``cps``).
    jy_per_unit : float or None
        Jansky per image unit for a flux density (per steradian when ``per_sr``).
    per_sr : bool
        A surface brightness (``MJy/sr``): needs the pixel solid angle.
    """

    raw: str | None
    kind: str
    per_second: bool = False
    jy_per_unit: float | None = None
    per_sr: bool = False

    def describe(self) -> str:
        return "no BUNIT" if self.raw is None else f"BUNIT {self.raw!r}"


_COUNTS = {"adu", "adus", "dn", "dns", "count", "counts", "ct", "cts", "datanumber", "datanumbers", "photon",
           "photons"}
_ELECTRONS = {"electron", "electrons", "e", "e-", "elec", "electron(s)"}
_JY_PREFIX = {"": 1.0, "m": 1e-3, "milli": 1e-3, "u": 1e-6, "µ": 1e-6, "μ": 1e-6, "micro": 1e-6, "n": 1e-9,
              "nano": 1e-9, "M": 1e6}
_MAGGIES = {"maggy": AB_ZERO_JY, "maggies": AB_ZERO_JY, "mgy": AB_ZERO_JY, "nanomaggy": AB_ZERO_JY * 1e-9,
            "nanomaggies": AB_ZERO_JY * 1e-9, "nmgy": AB_ZERO_JY * 1e-9, "nanomgy": AB_ZERO_JY * 1e-9}
_PER_SECOND = ("/s", "/sec", "/second", "s-1", "s^-1", "s**-1")


def parse_bunit(value) -> Units:
    """Classify a ``BUNIT`` value (see :class:`Units`); unknown strings give ``kind="unknown"``."""
    if value is None or not str(value).strip():
        return Units(None, "unknown")
    raw = str(value).strip()
    text = raw.replace(" ", "")
    low = text.lower()
    if low in _MAGGIES:
        return Units(raw, "flux", jy_per_unit=_MAGGIES[low])
    if low == "mjy/sr" and text[0] == "M":
        return Units(raw, "flux", jy_per_unit=1e6, per_sr=True)
    for suffix in ("", "/pix", "/pixel", "/pixels"):
        if low.endswith("jy" + suffix):
            prefix = text[: len(text) - len("jy" + suffix)]
            if prefix in _JY_PREFIX:
                return Units(raw, "flux", jy_per_unit=_JY_PREFIX[prefix])
    if any(word in low for word in ("jy", "erg", "w/m", "mag", "lsun")):
        return Units(raw, "flux")
    if low == "cps":
        return Units(raw, "counts", per_second=True)
    per_second = False
    for suffix in _PER_SECOND:
        if low.endswith(suffix) and len(low) > len(suffix):
            low, per_second = low[: -len(suffix)].rstrip("*."), True
            break
    if low in _ELECTRONS:
        return Units(raw, "electrons", per_second)
    if low in _COUNTS:
        return Units(raw, "counts", per_second)
    return Units(raw, "unknown")


# --------------------------------------------------------------------------- sky statistics


class SkyStats(NamedTuple):
    """Sky level and noise of an image from its unmasked pixels.

    ``level`` is the sigma-clipped median and ``sigma`` the standard deviation
    of the clipped pixels corrected for the clipping (3-sigma clipping around
    the median with a MAD-based width, until it converges), in image units;
    ``npix`` the pixels left after clipping.  The standard deviation, not the
    MAD, gives the final width because the MAD of integer-valued (Poisson)
    data is quantised: on Poisson(400) it is 7% low in variance.
    """

    level: float
    sigma: float
    npix: int


def sky_statistics(values, *, clip: float = 3.0, max_pixels: int = 1_000_000, iterations: int = 10) -> SkyStats:
    """Robust sky level and noise (:class:`SkyStats`) of the finite ``values``.

    At most ``max_pixels`` pixels are used (an even stride through the array,
    so the result is deterministic).  ``sigma`` is 0 when more than half the
    pixels share one value.
    """
    v = np.asarray(values).ravel()
    if v.size > max_pixels:
        v = v[:: int(math.ceil(v.size / max_pixels))]
    v = v[np.isfinite(v)].astype(np.float64)
    if v.size == 0:
        return SkyStats(float("nan"), 0.0, 0)
    full = v
    level, width = float(np.median(v)), 0.0
    for _ in range(iterations):
        level = float(np.median(v))
        width = 1.4826 * float(np.median(np.abs(v - level)))
        if width <= 0:
            return SkyStats(level, 0.0, int(v.size))
        keep = np.abs(full - level) < clip * width
        if keep.sum() == v.size:
            break
        v = full[keep]
    # variance of a normal distribution truncated at +-clip sigma, in units of sigma^2
    z = clip
    pdf = math.exp(-0.5 * z * z) / math.sqrt(2 * math.pi)
    kept = math.erf(z / math.sqrt(2))
    sigma = float(np.std(v)) / math.sqrt(1 - 2 * z * pdf / kept)
    return SkyStats(level, sigma, int(v.size))


# --------------------------------------------------------------------------- gain


@dataclass
class GainDecision:
    """Which gain the injections' photon noise uses, and why.

    Attributes
    ----------
    value : float or None
        Electrons per image unit; None adds no photon noise.
    source : str
        Where the value came from (``"--gain"``, ``"image header GAIN"``,
        ``"BUNIT 'electrons/s' x EXPTIME"``, ``"sky noise"``, ``"none"``).
    reason : str
        One sentence: why this value (and why not the header's).
    header_value, header_keyword : float or None, str or None
        The header gain and where it was found.
    measured : float or None
        Effective gain from the sky, ``level / sigma^2``, when the sky was not subtracted.
    contradicted : bool
        A given or header gain failed the checks against the image.
    """

    value: float | None
    source: str
    reason: str
    header_value: float | None = None
    header_keyword: str | None = None
    measured: float | None = None
    contradicted: bool = False

    def summary(self) -> str:
        """One log line: the gain used and why."""
        if self.value is None:
            return f"gain: none, no photon noise added to the injections ({self.reason})"
        return f"gain: {_num(self.value)} e- per image unit from {self.source} ({self.reason})"


def decide_gain(*, units: Units, sky: SkyStats | None, header_gain: float | None = None,
                header_source: str | None = None, exptime: float | None = None,
                user_gain: float | None = None) -> GainDecision:
    """Choose the gain (electrons per image unit) by the rules in ``docs/usage.md`` ("Image facts").

    Parameters
    ----------
    units : Units
        From :func:`parse_bunit`.
    sky : SkyStats or None
        Sky level and noise of the image (image units).
    header_gain, header_source : float, str, optional
        The header's gain and where it was found (``"image header GAIN"``).
    exptime : float, optional
        Exposure time in seconds.
    user_gain : float, optional
        A gain given by the user: used as given, only checked.

    Returns
    -------
    GainDecision
    """
    keyword = header_source.split()[-1] if header_source else None
    sigma = sky.sigma if sky is not None and np.isfinite(sky.sigma) and sky.sigma > 0 else None
    measured = None
    sky_note = "the sky noise could not be measured"
    if sigma is not None:
        if sky.level >= SKY_MIN_SIGMAS * sigma:
            measured = sky.level / sigma**2
        else:
            sky_note = (f"the sky level {_est(sky.level)} is {sky.level / sigma:.1f} sigma, so the sky was subtracted "
                        f"and its noise cannot give the gain")
    common = dict(header_value=header_gain, header_keyword=keyword, measured=measured)

    # What the header (or the user) says, before checking it against the image.
    candidate = None  # (value, source, reason)
    rejected = None  # why a header gain cannot apply at all
    if user_gain is not None:
        candidate = (float(user_gain), "--gain", "given by the user")
    elif units.kind == "electrons":
        not_detector = (f"; the header {keyword} = {_num(header_gain)} is the detector's e-/ADU and does not apply"
                        if header_gain is not None else "")
        if not units.per_second:
            candidate = (1.0, f"BUNIT {units.raw!r}", "the image is in electrons" + not_detector)
        elif exptime:
            candidate = (float(exptime), f"BUNIT {units.raw!r} x EXPTIME",
                         f"the image is in electrons per second, so one image unit is EXPTIME = {_num(exptime)} "
                         f"electrons" + not_detector)
        else:
            rejected = "the image is in electrons per second but the header has no EXPTIME"
    elif units.kind == "counts":
        if header_gain is None:
            rejected = f"the image is in {units.raw} but the header has none of the keywords {', '.join(GAIN_KEYWORDS)}"
        elif not units.per_second:
            candidate = (header_gain, header_source, f"the image is in {units.raw}")
        elif exptime:
            candidate = (header_gain * exptime, f"{header_source} x EXPTIME",
                         f"the image is in {units.raw}, so one image unit is {keyword} x EXPTIME = "
                         f"{_num(header_gain)} x {_num(exptime)} electrons")
        else:
            rejected = f"the image is in {units.raw} (per second) but the header has no EXPTIME"
    elif units.kind == "flux":
        if header_gain is not None:
            candidate = (header_gain, header_source, "")
            rejected = (f"{units.describe()} is a flux unit, and the header {keyword} = {_num(header_gain)} is a "
                        f"detector gain in e-/ADU that does not convert it into electrons")
        else:
            rejected = f"{units.describe()} is a flux unit and no gain converts it into electrons"
    elif header_gain is not None:
        candidate = (header_gain, header_source, "no BUNIT: the image is taken to be in the units of the header gain")
    else:
        rejected = f"no BUNIT and none of the header keywords {', '.join(GAIN_KEYWORDS)}"

    if candidate is None:
        hint = (f"; the sky noise implies an effective gain of about {_est(measured)}: pass --gain {measured:.3g} to "
                f"add photon noise" if measured is not None else f"; {sky_note}")
        return GainDecision(None, "none", rejected + hint, **common)

    value, source, reason = candidate
    problems = [rejected] if rejected else []
    if sigma is not None and sigma * value < MIN_SKY_ELECTRONS:
        problems.append(f"it would put the sky noise of one pixel (sigma {_est(sigma)} image units) at "
                        f"{sigma * value:.2g} electrons, less than one electron, so it cannot belong to the "
                        f"image's units")
    elif measured is not None and not (1 / GAIN_TOLERANCE <= value / measured <= GAIN_TOLERANCE):
        problems.append(f"the sky noise implies an effective gain of {_est(measured)} (sky level "
                        f"{_est(sky.level)} / sigma^2, sigma {_est(sigma)}), a factor "
                        f"{max(value / measured, measured / value):.3g} away")
    if not problems:
        if measured is not None:
            reason += f"; consistent with the effective gain {_est(measured)} measured from the sky noise"
        return GainDecision(value, source, reason, **common)
    why = "; ".join(problems)
    if user_gain is not None:
        return GainDecision(value, source, f"given by the user, although {why}", contradicted=True, **common)
    if measured is not None:
        return GainDecision(measured, "sky noise",
                            f"{source} = {_num(value)} contradicts the image: {why}; the effective gain measured "
                            f"from the sky noise (level / sigma^2) is used instead", contradicted=True, **common)
    return GainDecision(None, "none", f"{source} = {_num(value)} was rejected: {why}; {sky_note}; pass --gain "
                                      f"E_PER_UNIT if you know the effective gain", contradicted=True, **common)


# --------------------------------------------------------------------------- the image


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
        Electrons per image unit, for photon noise; None if unknown (see
        :attr:`gain_decision`).
    saturation : float or None
        Saturation level in image units, or None.
    fwhm : float or None
        Seeing FWHM in pixels when given by the user; otherwise filled in by
        :func:`comest_bayes.detect.psf.estimate_fwhm` later.
    provenance : dict
        Where each of zeropoint, pixel_scale, gain, saturation, fwhm came from.
    path, hdu : str, int
        The file read and the HDU index used.
    bunit, exptime : str or None, float or None
        The header's ``BUNIT`` and exposure time (s).
    zeropoint_convention : str
        How the zero point follows from its keyword (per image unit, per
        second times EXPTIME, AB from the flux unit, given by the user).
    gain_decision : dict
        :class:`GainDecision` as a dict: value, source, reason, header and
        measured gains.
    sky_level, sky_sigma : float or None
        Clipped median and robust sigma of the unmasked pixels (image units).
    wcs_note : str or None
        What was done to the header's WCS (TNX/ZPX distortion ignored, fixes).
    warnings : list of str
        The warnings load_image issued, one line each.
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
    bunit: str | None = None
    exptime: float | None = None
    zeropoint_convention: str = ""
    gain_decision: dict = field(default_factory=dict)
    sky_level: float | None = None
    sky_sigma: float | None = None
    wcs_note: str | None = None
    warnings: list = field(default_factory=list)

    @property
    def shape(self) -> tuple[int, int]:
        return self.data.shape

    @property
    def unmasked_fraction(self) -> float:
        return float(1.0 - self.mask.mean())

    def gain_summary(self) -> str:
        """One log line: the gain used for the injections' photon noise and why."""
        if not self.gain_decision:
            return f"gain: {'none' if self.gain is None else _num(self.gain)} ({self.provenance.get('gain', '?')})"
        return GainDecision(**self.gain_decision).summary()

    def facts(self) -> dict:
        """JSON-ready summary of the image and where each number came from."""
        return {
            "path": self.path,
            "hdu": self.hdu,
            "shape": list(self.shape),
            "zeropoint": self.zeropoint,
            "zeropoint_convention": self.zeropoint_convention,
            "pixel_scale_arcsec": self.pixel_scale,
            "gain": self.gain,
            "gain_decision": dict(self.gain_decision),
            "bunit": self.bunit,
            "exptime": self.exptime,
            "sky_level": self.sky_level,
            "sky_sigma": self.sky_sigma,
            "saturation": self.saturation,
            "fwhm_pix": self.fwhm,
            "wcs": None if self.wcs is None else list(self.wcs.wcs.ctype),
            "wcs_note": self.wcs_note,
            "masked_fraction": float(self.mask.mean()),
            "has_weight": self.noise is not None,
            "provenance": dict(self.provenance),
            "warnings": list(self.warnings),
        }


# --------------------------------------------------------------------------- reading


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


def _shape(h):
    data = getattr(h, "data", None)
    return None if data is None else getattr(data, "shape", None)


def _plane_shape(h):
    """(ny, nx) when the HDU is an image with two axes of length > 1 and every other axis of length 1."""
    shape = _shape(h)
    if not h.is_image or shape is None or len(shape) < 2:
        return None
    if len(shape) > 2 and any(n != 1 for n in shape[:-2]):
        return None
    return tuple(shape[-2:])


def _cube_advice(path, shape) -> str:
    return (f"comest-bayes measures one 2-D image and --hdu chooses an HDU, not a plane of a cube: extract the "
            f"plane you want into its own file first, e.g. python -c \"from astropy.io import fits; "
            f"d, h = fits.getdata({str(path)!r}, header=True); fits.writeto('plane.fits', d[0], h)\" "
            f"(d[0] is the first of the {shape[0]} planes)")


#: The command-line option that chooses the HDU of each input file.
_HDU_OPTION = {"image": "--hdu", "weight": "--weight-hdu", "mask": "--mask-hdu"}


def _pick_hdu(hdul, hdu, path, what):
    if hdu is None:
        for i, h in enumerate(hdul):
            if _plane_shape(h) is not None:
                return i
        cubes = [(i, _shape(h)) for i, h in enumerate(hdul) if h.is_image and _shape(h) is not None
                 and len(_shape(h)) > 2]
        if cubes:
            i, shape = cubes[0]
            raise InputError(f"{what} file {str(path)!r} holds no 2-D image: HDU {i} is a {len(shape)}-D cube of "
                             f"shape {shape}. {_cube_advice(path, shape)}.")
        raise InputError(
            f"{what} file {str(path)!r} holds no 2-D image in any of its {len(hdul)} HDUs; "
            f"is it a table? Pass {_HDU_OPTION.get(what, '--hdu')} to choose an image HDU."
        )
    if not (0 <= hdu < len(hdul)):
        raise InputError(f"{what} file {str(path)!r} has {len(hdul)} HDUs (0-{len(hdul) - 1}); got hdu={hdu}.")
    h = hdul[hdu]
    if _plane_shape(h) is None:
        shape = _shape(h)
        if h.is_image and shape is not None and len(shape) > 2:
            raise InputError(f"HDU {hdu} of {what} file {str(path)!r} is a {len(shape)}-D cube of shape {shape}, "
                             f"not a 2-D image. {_cube_advice(path, shape)}.")
        images = [i for i, other in enumerate(hdul) if _plane_shape(other) is not None]
        where = (f"HDU {images[0]} holds one" if len(images) == 1 else
                 f"HDUs {', '.join(map(str, images))} hold one" if images else "no HDU of it holds one")
        raise InputError(
            f"HDU {hdu} of {what} file {str(path)!r} is not a 2-D image (data shape {shape}); {where}: "
            f"pick another with {_HDU_OPTION.get(what, '--hdu')}."
        )
    return hdu


def _read_2d(path, hdu, what):
    """Data (float32, native), header, primary header (None for HDU 0), HDU index, astropy's warnings."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with _open(path, what) as hdul:
            try:  # fix broken cards now (so nothing later trips on them), their warnings caught here
                hdul.verify("fix+warn")
            except Exception:  # an unfixable header still gets its chance below
                pass
            idx = _pick_hdu(hdul, hdu, path, what)
            data = np.asarray(hdul[idx].data, dtype=np.float32)  # native byte order, a copy
            data = data.reshape(data.shape[-2:])  # (1, ny, nx) -> (ny, nx)
            header = hdul[idx].header.copy()
            primary = hdul[0].header.copy() if idx != 0 else None
    return data, header, primary, idx, _messages(caught)


# astropy's framing lines around the messages that matter
_BOILERPLATE = re.compile(r"^(Verification reported errors:|HDU \d+:|Card \d+:|Note: astropy\.io\.fits uses zero-based "
                          r"indexing\.)$")


def _messages(caught) -> list[str]:
    """The distinct warning texts, each on one line, without astropy's framing lines."""
    out = []
    for w in caught:
        text = " ".join(str(w.message).split())
        if text and text not in out and not _BOILERPLATE.match(text):
            out.append(text)
    return out


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


def _header_text(key, header, primary):
    for hdr in (header, primary):
        if hdr is not None and key in hdr and isinstance(hdr[key], str):
            return hdr[key]
    return None


# --------------------------------------------------------------------------- WCS


_IRAF_DISTORTED = {"TNX": "TAN", "ZPX": "ZPN"}


def _celestial_wcs(header):
    """Read the celestial WCS.

    Returns
    -------
    wcs : WCS or None
    note : str or None
        A warning for the user (TNX/ZPX distortion ignored, astropy's fixes).
    error : str or None
        Why a WCS present in the header could not be read.
    """
    header = header.copy()
    notes = []
    ctypes = [str(header.get(f"CTYPE{i}", "")) for i in (1, 2)]
    iraf = sorted({c[-3:] for c in ctypes if c[-4:-3] == "-" and c[-3:] in _IRAF_DISTORTED})
    if iraf:
        for i in (1, 2):
            c = ctypes[i - 1]
            if c[-3:] in _IRAF_DISTORTED:
                header[f"CTYPE{i}"] = c[:-3] + _IRAF_DISTORTED[c[-3:]]
        for key in [k for k in header if k.startswith(("WAT1_", "WAT2_"))]:
            del header[key]  # wcslib's WAT parser fails on many of them; the terms are ignored anyway
        names = "/".join(iraf)
        plain = "/".join(_IRAF_DISTORTED[p] for p in iraf)
        notes.append(f"the WCS is IRAF {names} ({plain} plus polynomial distortion terms in WAT keywords), whose "
                     f"distortion astropy cannot evaluate: it is read as plain {plain}, so the ra/dec of catalog "
                     f"entries can be off by up to arcseconds away from the reference pixel (pixel positions, "
                     f"magnitudes and completeness are unaffected); re-fit the astrometry as TPV or SIP if you "
                     f"need exact sky positions")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            wcs = WCS(header)
        except Exception as exc:  # astropy raises several types for broken WCS headers
            first = " ".join(str(exc).split()) or type(exc).__name__
            return None, None, first[:200]
    fixes = [m for m in _messages(caught) if not any(h in m for h in _HARMLESS_FIXES)]
    if fixes:
        notes.append("astropy had to fix the WCS header: " + "; ".join(fixes))
    if not wcs.has_celestial:
        return None, "; ".join(notes) or None, None
    try:
        celestial = wcs.celestial
    except Exception as exc:  # wcslib cannot take the sub-image of some distorted WCSs (TPV in a 1-plane cube)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                celestial = WCS(header, naxis=2)  # the first two axes, which the image's plane spans
        except Exception:
            celestial = None
        if celestial is None or not celestial.has_celestial:
            first = " ".join(str(exc).split()) or type(exc).__name__
            return None, None, first[:200]
    return celestial, "; ".join(notes) or None, None


def wcs_from_stored_header(text: str) -> WCS:
    """The WCS of an image header a run stored as text, rebuilt without repeating astropy's fixes.

    Astropy's fixes to the header (e.g. 'obsfix' setting OBSGEO-B/L/H on a JWST image) were judged
    once, when the run read the image (:func:`load_image`: the harmless ones dropped, the others a
    line in the run's log); every later rebuild (a realization's injection, the fit's maps) would
    only print them again.
    """
    from astropy.wcs import FITSFixedWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FITSFixedWarning)
        return WCS(fits.Header.fromstring(text), relax=True)


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


# --------------------------------------------------------------------------- zero point


class _ZP(NamedTuple):
    value: float
    source: str  # provenance: where it came from
    convention: str  # how it follows from its keyword


def _pixel_solid_angle(header, primary, pixel_scale):
    """Pixel solid angle in sr and where it came from, or (None, None)."""
    value, src = _header_value(("PIXAR_SR",), header, primary)
    if value is not None and value > 0:
        return value, src
    value, src = _header_value(("PIXAR_A2",), header, primary)
    if value is not None and value > 0:
        return value * SR_PER_ARCSEC2, f"{src} (arcsec^2)"
    if pixel_scale is not None:
        return pixel_scale**2 * SR_PER_ARCSEC2, f"the pixel scale {pixel_scale:.5g}\" squared"
    return None, None


def _ab_from_jy(jy: float) -> float:
    return 2.5 * math.log10(AB_ZERO_JY / jy)


def _zeropoint_candidates(header, primary, units: Units, exptime, pixel_scale):
    """Zero points the header gives, in order of preference, and keywords present but not numbers."""
    cands, not_numbers = [], []
    rate = units.per_second or units.kind == "flux"
    for where, hdr in (("image header", header), ("primary header", primary)):
        if hdr is None:
            continue
        for key in ZP_KEYWORDS:
            if key not in hdr:
                continue
            raw = hdr[key]
            try:
                value = float(raw)
            except (TypeError, ValueError):
                value = float("nan")
            if not np.isfinite(value) or isinstance(raw, bool):
                not_numbers.append(f"{key} = {raw!r} in the {where}")
                continue
            src = f"{where} {key}"
            if key == "MAGZPT" and not rate and exptime:
                zp = value + 2.5 * math.log10(exptime)
                cands.append(_ZP(zp, f"{src} (per second) + 2.5 log10(EXPTIME)",
                                 f"MAGZPT = {_num(value)} is per second (UKIDSS/VISTA/DECam convention) and the image "
                                 f"is not per second, so zp = MAGZPT + 2.5 log10(EXPTIME = {_num(exptime)} s) = "
                                 f"{zp:.4f}"))
            elif key == "MAGZPT" and not rate:
                cands.append(_ZP(value, src, "MAGZPT taken per image unit: it is per second in UKIDSS/VISTA/DECam "
                                             "headers, but there is no EXPTIME to convert it"))
            else:
                cands.append(_ZP(value, src, f"{key} per image unit (m = zp - 2.5 log10(flux in image units))"))

    area, area_src = _pixel_solid_angle(header, primary, pixel_scale) if units.per_sr or units.kind == "counts" \
        else (None, None)
    if units.kind == "flux" and units.jy_per_unit is not None:
        if not units.per_sr:
            zp = _ab_from_jy(units.jy_per_unit)
            cands.append(_ZP(zp, f"BUNIT {units.raw!r}", f"AB: one image unit is {_num(units.jy_per_unit)} Jy and "
                                                          f"3631 Jy is 0 mag, so zp = {zp:.4f}"))
        elif area is not None:
            zp = _ab_from_jy(units.jy_per_unit * area)
            cands.append(_ZP(zp, f"BUNIT {units.raw!r} and {area_src}",
                             f"AB: 1 MJy/sr over a pixel of {_num(area)} sr is {_num(1e6 * area)} Jy and 3631 Jy is "
                             f"0 mag, so zp = -2.5 log10({_num(area)} x 1e6 / 3631) = {zp:.4f}"))
    photmjsr, mjsr_src = _header_value(("PHOTMJSR",), header, primary)
    if units.kind == "counts" and units.per_second and photmjsr and photmjsr > 0 and area is not None:
        zp = _ab_from_jy(photmjsr * 1e6 * area)
        cands.append(_ZP(zp, f"{mjsr_src} and {area_src}",
                         f"AB: one {units.raw} is PHOTMJSR = {_num(photmjsr)} MJy/sr, over a pixel of {_num(area)} sr, "
                         f"so zp = -2.5 log10(PHOTMJSR x {_num(area)} x 1e6 / 3631) = {zp:.4f}"))
    photflam, flam_src = _header_value(("PHOTFLAM",), header, primary)
    photplam, _ = _header_value(("PHOTPLAM",), header, primary)
    if photflam and photplam and photflam > 0 and photplam > 0 and units.kind != "flux":
        per_s = -2.5 * math.log10(photflam * photplam**2 / C_ANGSTROM) - 48.6
        if units.per_second or units.kind == "unknown":
            cands.append(_ZP(per_s, f"{flam_src} and PHOTPLAM",
                             f"AB zero point of one count per second from PHOTFLAM and PHOTPLAM ({_num(per_s)}); the "
                             f"image is taken to be per second ({units.describe()})"))
        elif exptime:
            zp = per_s + 2.5 * math.log10(exptime)
            cands.append(_ZP(zp, f"{flam_src} and PHOTPLAM + 2.5 log10(EXPTIME)",
                             f"AB zero point of one count per second from PHOTFLAM and PHOTPLAM ({per_s:.4f}) plus "
                             f"2.5 log10(EXPTIME = {_num(exptime)} s) for an image in {units.raw}: {zp:.4f}"))
    return cands, not_numbers


def _zeropoint_checks(zp: float, units: Units, sky: SkyStats | None, unit_zp: float | None) -> list[str]:
    """Reasons a zero point is implausible (empty when it is fine); rules in ``docs/usage.md``."""
    out = []
    if sky is not None and np.isfinite(sky.sigma) and sky.sigma > 0:
        depth = zp - 2.5 * math.log10(sky.sigma)
        lo, hi = PIXEL_DEPTH_RANGE
        if not lo <= depth <= hi:
            out.append(f"it puts the sky noise of one pixel (sigma {_est(sky.sigma)} image units) at {depth:.1f} mag, "
                       f"while real images lie between {lo:g} and {hi:g} mag")
    if units.kind in ("counts", "electrons") and not COUNTS_ZP_RANGE[0] <= zp <= COUNTS_ZP_RANGE[1]:
        out.append(f"the image is in {units.raw}, whose zero points lie between {COUNTS_ZP_RANGE[0]:g} and "
                   f"{COUNTS_ZP_RANGE[1]:g}")
    if unit_zp is not None and abs(zp - unit_zp) > FLUX_ZP_TOLERANCE:
        out.append(f"{units.describe()} gives an AB zero point of {unit_zp:.3f}, {abs(zp - unit_zp):.1f} mag away")
    return out


def _resolve_zeropoint(zp, header, primary, units, exptime, pixel_scale, path):
    """(zp, provenance, convention, warnings, problem): problem is the error text when there is no zero point."""
    cands, not_numbers = _zeropoint_candidates(header, primary, units, exptime, pixel_scale)
    notes = []
    if zp is not None:
        zp, source, convention = float(zp), "--zp", "given by the user (--zp): per image unit"
    elif cands:
        zp, source, convention = cands[0]
        if not_numbers:
            notes.append(f"the zero-point keyword {' and '.join(not_numbers)} is present but not a number; using "
                         f"{source} = {zp:.4f}")
        # keywords of the other header may describe another image (a multi-extension file's primary): not compared
        where = " ".join(source.split()[:2])
        others = [f"{c.source} gives {c.value:.3f}" for c in cands[1:] if abs(c.value - zp) > ZP_AGREEMENT
                  and (c.source.startswith(where) or not c.source.startswith(("image header", "primary header")))]
        if others:
            notes.append(f"the header's zero points disagree: {source} gives {zp:.3f} but {'; '.join(others)}; "
                         f"using {source} (pass --zp to choose)")
        if source.endswith("MAGZPT") and "no EXPTIME" in convention:
            notes.append(f"{source} = {zp:.4f} is taken per image unit, but MAGZPT is per second in UKIDSS/VISTA/"
                         f"DECam headers and there is no EXPTIME to convert it; pass --zp if the image is not per "
                         f"second")
    else:
        if not_numbers:
            found = (f"the header has {' and '.join(not_numbers)}, which is present but not a number, and none of "
                     f"the other keywords {', '.join(ZP_KEYWORDS)} nor a flux BUNIT")
        else:
            found = f"none of the header keywords {', '.join(ZP_KEYWORDS)} is present" + (
                "" if units.raw is None else f", and BUNIT {units.raw!r} does not give one")
        return None, None, None, notes, (f"no photometric zero point for {str(path)!r}: {found}; pass --zp MAG "
                                         f"(magnitude of one image unit)")
    return zp, source, convention, notes, None


# --------------------------------------------------------------------------- load_image


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
        Photometric zero point; default from the header and units (rules in
        ``docs/usage.md``).  Warned about when implausible.
    pixel_scale : float, optional
        Arcsec per pixel; default from the WCS.  Required when there is no WCS.
    fwhm : float, optional
        Seeing FWHM in *pixels*; default: estimated from stars later.
    gain : float, optional
        Electrons per image unit; default from the header and units, checked
        against the sky noise (rules in ``docs/usage.md``).
    saturation : float, optional
        Saturation level; default from the header, if present.
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
        Every problem found is listed in one error.

    Warns
    -----
    UserWarning
        One line each: an implausible zero point, header zero points that
        disagree, a rejected or replaced gain, a TNX/ZPX WCS, astropy's
        header fixes.  The same lines are in :attr:`ImageData.warnings`.
    """
    if weight_type not in WEIGHT_TYPES:
        raise InputError(f"weight_type={weight_type!r} is not one of {WEIGHT_TYPES}; "
                         f"use ivar (inverse variance), rms (sigma) or var (variance).")
    def number(name, value):
        try:
            return None if value is None else float(value)
        except (TypeError, ValueError):
            raise InputError(f"{name}={value!r} must be a number.") from None

    pixel_scale, fwhm, gain, saturation, zp = (number(n, v) for n, v in (
        ("pixel_scale", pixel_scale), ("fwhm", fwhm), ("gain", gain), ("saturation", saturation), ("zp", zp)))
    for name, value in (("pixel_scale", pixel_scale), ("fwhm", fwhm), ("gain", gain), ("saturation", saturation)):
        if value is not None and not (np.isfinite(value) and value > 0):
            raise InputError(f"{name}={value!r} must be a positive finite number.")
    if zp is not None and not np.isfinite(zp):
        raise InputError(f"zp={zp!r} must be a finite number.")

    data, header, primary, idx, read_warnings = _read_2d(path, hdu, "image")
    notes = []
    if read_warnings:
        notes.append(f"astropy reported {len(read_warnings)} problem(s) reading the header of {str(path)!r} and "
                     f"fixed or ignored them: {'; '.join(read_warnings)[:300]}")
    provenance = {}
    problems = []
    ny, nx = data.shape
    if ny < 16 or nx < 16:
        raise InputError(f"image {str(path)!r} is only {nx}x{ny} pixels; at least 16x16 is needed.")

    # Companions first, so every shape problem is reported before any work.
    noise = None
    bad = ~np.isfinite(data)
    causes = [(bad.copy(), "NaN or infinite in the image", "is this the right HDU (--hdu)?")]
    if weight is not None:
        wdata, _, _, _, _ = _read_2d(weight, weight_hdu, "weight")
        if wdata.shape != data.shape:
            problems.append(
                f"weight map {str(weight)!r} has shape {wdata.shape} but the image {str(path)!r} has "
                f"{data.shape}; give the weight map that belongs to this image (and HDU)"
            )
        else:
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
            causes.append((badw, f"zero, negative or non-finite in the weight map (read as {weight_type})",
                           "check --weight-type and --weight-hdu"))
            provenance["weight"] = f"{weight} ({weight_type})"
    if mask is not None:
        mdata, _, _, _, _ = _read_2d(mask, mask_hdu, "mask")
        if mdata.shape != data.shape:
            problems.append(
                f"mask {str(mask)!r} has shape {mdata.shape} but the image {str(path)!r} has "
                f"{data.shape}; give the mask that belongs to this image (and HDU)"
            )
        else:
            if not np.all(np.isfinite(mdata)):
                mdata = np.where(np.isfinite(mdata), mdata, 1)
            flagged = (mdata.astype(np.int64) & int(mask_bits)) != 0 if mask_bits is not None else mdata != 0
            bad |= flagged
            causes.append((flagged, "flagged in the mask" + (f" (bits {mask_bits})" if mask_bits is not None else ""),
                           "check that the mask's bad pixels are the non-zero ones, and --mask-bits"))
            provenance["mask"] = f"{mask}" + (f" (bits {mask_bits})" if mask_bits is not None else "")

    good = None
    if not problems:  # the mask is only right when the companions fit
        if bad.all():
            # name each cause with its share, and the advice of the ones that take the whole image
            shares = [f"{np.mean(where):.0%} {what}" for where, what, _ in causes if where.any()]
            advice = [fix for where, _, fix in causes if where.all()] or [fix for where, _, fix in causes if where.any()]
            problems.append(f"every pixel of {str(path)!r} is unusable ({'; '.join(shares)}): {' '.join(advice)}")
        else:
            good = data[~bad]
            if good.size < 256:
                problems.append(f"only {good.size} usable pixels in {str(path)!r}; at least 256 are needed")
                good = None
            elif np.ptp(good) == 0:
                problems.append(
                    f"image {str(path)!r} is constant ({float(good[0])!r} in every unmasked pixel): there is no sky "
                    f"noise to detect against. Is this the right HDU (--hdu) or a blank frame?"
                )
                good = None

    wcs, wcs_note, wcs_error = _celestial_wcs(header)
    unreadable = f"the WCS in the header of {str(path)!r} cannot be read ({wcs_error})"
    if pixel_scale is not None:
        provenance["pixel_scale"] = "--pixel-scale"
        if wcs_error is not None:
            notes.append(f"{unreadable}; it is ignored, so the catalogs have no sky positions")
    elif wcs is not None:
        pixel_scale = _wcs_pixel_scale(wcs, data.shape)
        provenance["pixel_scale"] = f"WCS ({'/'.join(wcs.wcs.ctype)}) at the image centre"
        if wcs_note and "IRAF" in wcs_note:
            provenance["pixel_scale"] += " (IRAF distortion terms ignored)"
    elif wcs_error is not None:
        problems.append(f"{unreadable}, so its pixel scale is unknown; fix the WCS keywords or pass --pixel-scale "
                        f"ARCSEC_PER_PIXEL (e.g. --pixel-scale 0.2)")
    else:
        problems.append(
            f"image {str(path)!r} has no celestial WCS in its header, so its pixel scale is unknown; "
            f"pass --pixel-scale ARCSEC_PER_PIXEL (e.g. --pixel-scale 0.2)"
        )
    if wcs_note:
        notes.append(f"{str(path)!r}: {wcs_note}")

    bunit = _header_text("BUNIT", header, primary)
    units = parse_bunit(bunit)
    exptime, _ = _header_value(EXPTIME_KEYWORDS, header, primary)
    if exptime is not None and exptime <= 0:
        exptime = None
    zp, zp_source, convention, zp_notes, zp_problem = _resolve_zeropoint(zp, header, primary, units, exptime,
                                                                         pixel_scale, path)
    notes.extend(zp_notes)
    if zp_problem:
        problems.append(zp_problem)
    else:
        provenance["zeropoint"] = zp_source

    if len(problems) == 1:
        raise InputError(problems[0] + ("" if problems[0].endswith(("?", ".")) else "."))
    if problems:
        raise InputError(f"{len(problems)} problems with image {str(path)!r}: "
                         + "; ".join(f"({i}) {p}" for i, p in enumerate(problems, 1)) + ".")

    sky = sky_statistics(good)
    implausible = _zeropoint_checks(zp, units, sky, _unit_zeropoint(units, header, primary, pixel_scale))
    if implausible:
        notes.append(f"the zero point {_num(zp)} ({zp_source}) looks implausible: {'; '.join(implausible)}. Check it: "
                     f"it is the magnitude of a source of one image unit in total, typically 20-35 for counts, "
                     f"22.5 for nanomaggies, 8.90 for Jy and 0 for maggies")

    header_gain, header_gain_src = _header_value(GAIN_KEYWORDS, header, primary)
    if header_gain is not None and header_gain <= 0:  # a zero gain means "unknown", not "infinite photon noise"
        header_gain, header_gain_src = None, None
    decision = decide_gain(units=units, sky=sky, header_gain=header_gain, header_source=header_gain_src,
                           exptime=exptime, user_gain=gain)
    gain = decision.value
    provenance["gain"] = decision.source if gain is not None else "unknown (no photon noise on injections)"
    provenance["gain"] += f": {decision.reason}"
    if decision.contradicted:
        notes.append(f"{str(path)!r}: " + decision.summary())

    if saturation is not None:
        provenance["saturation"] = "--saturation"
    else:
        saturation, src = _header_value(SATURATION_KEYWORDS, header, primary)
        if saturation is not None and saturation <= 0:
            saturation = None
        provenance["saturation"] = src if saturation is not None else "unknown"
    if fwhm is not None:
        provenance["fwhm"] = "--fwhm"

    for note in notes:
        warnings.warn(note, UserWarning, stacklevel=2)
    data[bad] = 0.0
    return ImageData(
        data=np.ascontiguousarray(data), mask=bad, noise=noise, wcs=wcs, header=header,
        zeropoint=float(zp), pixel_scale=float(pixel_scale), gain=gain, saturation=saturation,
        fwhm=fwhm, provenance=provenance, path=str(path), hdu=idx, bunit=bunit, exptime=exptime,
        zeropoint_convention=convention, gain_decision=asdict(decision),
        sky_level=float(sky.level) if sky.npix else None, sky_sigma=float(sky.sigma) if sky.npix else None,
        wcs_note=wcs_note, warnings=notes,
    )


def _unit_zeropoint(units: Units, header, primary, pixel_scale) -> float | None:
    """AB zero point implied by a flux BUNIT alone, or None."""
    if units.kind != "flux" or units.jy_per_unit is None:
        return None
    if not units.per_sr:
        return _ab_from_jy(units.jy_per_unit)
    area, _ = _pixel_solid_angle(header, primary, pixel_scale)
    return None if area is None else _ab_from_jy(units.jy_per_unit * area)
