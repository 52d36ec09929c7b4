"""Detection with the SExtractor binary, returning the same result as SEP.

The second detection backend (``detection.backend = "sextractor"``): :func:`detect_sextractor`
runs ``source-extractor`` (or ``sex``, or ``$COMEST_SEXTRACTOR``) in a private temporary
directory with a configuration generated from :class:`~comest_bayes.config.DetectionConfig`, and
returns the catalog and maps in the SEP backend's form.  Configuration mapping, noise modes,
masked pixels, catalog conversion and the measured differences from SEP: ``docs/detection.md``.
"""

from __future__ import annotations

import functools
import os
import re
import shutil
import subprocess
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
from astropy.io import fits

from comest_bayes.detect.catalog import FLAG_MASKED, derived_columns, make_catalog
from comest_bayes.config import DetectionConfig
from comest_bayes.detect.base import DetectionResult, filter_kernel, given_noise, noise_map
from comest_bayes.errors import BackendUnavailableError, ComestError, ConfigError, DetectionOverflowError, InputError

__all__ = ["SExtractorError", "ENV_VAR", "find_sextractor", "sextractor_version", "sextractor_config",
           "sextractor_noise_mode", "detect_sextractor"]

#: Environment variable that may hold the path (or command name) of the binary.
ENV_VAR = "COMEST_SEXTRACTOR"
#: Command names tried in order (Debian/Ubuntu and conda-forge install ``source-extractor``).
BINARY_NAMES = ("source-extractor", "sex")
#: Value written into masked pixels; SExtractor ignores pixels <= -BIG = -1e30 (define.h).
BLANK_VALUE = np.float32(-1e31)
#: RMS written on masked pixels of a MAP_RMS weight image, and the bad-pixel threshold (input units).
MASKED_RMS = np.float32(1e14)
WEIGHT_THRESH = 1e12
#: Saturation level used when none is known (SExtractor rejects values >= 1e30).
NO_SATURATION = 1e29

_INSTALL_HINT = (
    "Install it with 'apt-get install source-extractor' (Debian/Ubuntu) or "
    "'conda install -c conda-forge astromatic-source-extractor', or point the environment variable "
    f"{ENV_VAR} at the binary. The default detection.backend='sep' needs nothing extra."
)

_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")


class SExtractorError(ComestError, RuntimeError):
    """The SExtractor binary failed or wrote unreadable output."""


def find_sextractor() -> str:
    """Path of the SExtractor executable.

    ``$COMEST_SEXTRACTOR`` (a path or a command name) wins when set; otherwise
    ``source-extractor`` then ``sex`` are looked up on ``PATH``.

    Returns
    -------
    str
        Absolute path of the executable.

    Raises
    ------
    BackendUnavailableError
        When no binary is found, with installation instructions.
    """
    override = os.environ.get(ENV_VAR, "").strip()
    if override:
        found = shutil.which(override)
        if found is None:
            raise BackendUnavailableError(
                f"{ENV_VAR}={override!r} is not an executable SExtractor binary (no such file, or not "
                f"executable). Fix or unset {ENV_VAR}. {_INSTALL_HINT}"
            )
        return found
    for name in BINARY_NAMES:
        found = shutil.which(name)
        if found is not None:
            return found
    raise BackendUnavailableError(
        f"detection.backend='sextractor' needs the SExtractor binary, but neither "
        f"{' nor '.join(repr(n) for n in BINARY_NAMES)} is on PATH. {_INSTALL_HINT}"
    )


@functools.lru_cache(maxsize=8)
def _version_of(binary: str) -> str:
    try:
        out = subprocess.run([binary, "-v"], capture_output=True, text=True, errors="replace", timeout=60)
    except OSError as exc:
        raise BackendUnavailableError(f"cannot run the SExtractor binary {binary!r}: {exc}. "
                                      f"{_INSTALL_HINT}") from None
    m = re.search(r"version\s+(\S+)", out.stdout + out.stderr)
    return m.group(1) if m else "unknown"


def sextractor_version(binary: str | None = None) -> str:
    """Version string of the binary (e.g. ``"2.25.0"``), ``"unknown"`` if unreadable."""
    return _version_of(binary or find_sextractor())


def sextractor_noise_mode(mode: str, has_weight: bool) -> str:
    """Resolve ``detection.noise`` to ``"global"``, ``"background"`` or ``"weight"``.

    Same rules as :func:`comest_bayes.detect.base.noise_map`: ``auto`` is
    ``weight`` when a weight map is given, else ``background``.
    """
    if mode == "auto":
        mode = "weight" if has_weight else "background"
    if mode == "weight" and not has_weight:
        raise ConfigError("detection.noise='weight' needs a weight map; pass --weight FILE or use "
                          "detection.noise=background.")
    if mode not in ("global", "background", "weight"):
        raise ConfigError(f"unknown detection.noise mode {mode!r}; expected auto, background, global or weight.")
    return mode


_WEIGHT_TYPES = {"global": "NONE", "background": "BACKGROUND", "weight": "MAP_RMS"}

#: Catalog parameters requested from SExtractor (the .param file); "{naper}" is filled in.
_PARAMS = ("NUMBER", "X_IMAGE", "Y_IMAGE", "XWIN_IMAGE", "YWIN_IMAGE", "XPEAK_IMAGE", "YPEAK_IMAGE",
           "A_IMAGE", "B_IMAGE", "THETA_IMAGE", "ISOAREA_IMAGE", "FLUX_MAX", "FLUX_ISO", "KRON_RADIUS",
           "FLUX_AUTO", "FLUXERR_AUTO", "FLUX_APER({naper})", "FLUXERR_APER({naper})", "FLUX_RADIUS",
           "BACKGROUND", "FLAGS")


def _fmt(value: float) -> str:
    return repr(float(value))


def sextractor_config(config: DetectionConfig, *, zeropoint: float, gain: float | None,
                      saturation: float | None, noise_mode: str, pixstack: int | None = None,
                      objstack: int = 3000) -> dict:
    """SExtractor keywords equivalent to a :class:`DetectionConfig` (pure function).

    Parameters
    ----------
    config : DetectionConfig
        Detection settings.
    zeropoint : float
        Magnitude zero point (MAG_ZEROPOINT).
    gain, saturation : float or None
        e-/ADU (0 when None) and saturation level in image units (1e29 when None).
    noise_mode : {"global", "background", "weight"}
        Resolved noise mode (:func:`sextractor_noise_mode`).
    pixstack : int, optional
        MEMORY_PIXSTACK; ``config.pixstack`` by default.
    objstack : int
        MEMORY_OBJSTACK (default 3000, SExtractor's).

    Returns
    -------
    dict of str -> str
        Keyword -> value, without the file names (catalog, param, filter,
        weight and check images), which :func:`detect_sextractor` adds.
    """
    kernel = filter_kernel(config.filter)
    kfact, rmin = config.phot_autoparams
    return {
        "CATALOG_TYPE": "FITS_1.0",
        "DETECT_TYPE": "CCD",
        "DETECT_MINAREA": str(int(config.minarea)),
        "DETECT_MAXAREA": "0",
        "THRESH_TYPE": "RELATIVE",
        "DETECT_THRESH": _fmt(config.thresh),
        "ANALYSIS_THRESH": _fmt(config.thresh),
        "FILTER": "N" if kernel is None else "Y",
        "DEBLEND_NTHRESH": str(int(config.deblend_nthresh)),
        "DEBLEND_MINCONT": _fmt(config.deblend_mincont),
        "CLEAN": "Y" if config.clean else "N",
        "CLEAN_PARAM": _fmt(config.clean_param),
        "MASK_TYPE": "CORRECT",
        "WEIGHT_TYPE": _WEIGHT_TYPES[noise_mode],
        "RESCALE_WEIGHTS": "N",
        "WEIGHT_GAIN": "N",
        "INTERP_TYPE": "NONE",
        **({"WEIGHT_THRESH": _fmt(WEIGHT_THRESH)} if noise_mode == "weight" else {}),
        "PHOT_APERTURES": ",".join(_fmt(d) for d in config.phot_apertures),
        "PHOT_AUTOPARAMS": f"{_fmt(kfact)},{_fmt(rmin)}",
        "PHOT_AUTOAPERS": "0.0,0.0",
        "PHOT_FLUXFRAC": _fmt(config.phot_fluxfrac),
        "SATUR_LEVEL": _fmt(NO_SATURATION if saturation is None else saturation),
        "MAG_ZEROPOINT": _fmt(zeropoint),
        "GAIN": _fmt(0.0 if gain is None else gain),
        "PIXEL_SCALE": "1.0",
        "BACK_TYPE": "AUTO",
        "BACK_SIZE": str(int(config.back_size)),
        "BACK_FILTERSIZE": str(int(config.back_filtersize)),
        "BACKPHOTO_TYPE": "GLOBAL",
        "BACK_FILTTHRESH": "0.0",
        "MEMORY_PIXSTACK": str(int(config.pixstack if pixstack is None else pixstack)),
        "MEMORY_OBJSTACK": str(int(objstack)),
        "VERBOSE_TYPE": "NORMAL",
        "WRITE_XML": "Y",
        "NTHREADS": "1",
    }


def _write_conv(kernel: np.ndarray, path: Path) -> None:
    """Write a kernel as a SExtractor ``.conv`` file, unnormalised (it already sums to 1)."""
    lines = ["CONV NONORM", f"# comest-bayes detection kernel, {kernel.shape[0]}x{kernel.shape[1]}, sum 1"]
    lines += [" ".join(f"{v:.9g}" for v in row) for row in kernel]
    path.write_text("\n".join(lines) + "\n")


def _write_fits(path: Path, array: np.ndarray) -> None:
    fits.PrimaryHDU(np.ascontiguousarray(array, dtype=np.float32)).writeto(path)


def _read_image(path: Path, dtype) -> np.ndarray:
    with fits.open(path, memmap=False) as hdul:
        return np.asarray(hdul[0].data, dtype=dtype)


def _read_xml(path: Path) -> dict:
    """Version and per-image statistics from SExtractor's XML (VOTable) report."""
    out: dict = {}
    root = ET.parse(path).getroot()
    for param in root.iter("PARAM"):
        if param.get("name") == "Version" and "version" not in out:
            out["version"] = param.get("value", "unknown")
    for table in root.iter("TABLE"):
        if table.get("ID") != "Extension_Data":
            continue
        names = [f.get("name") for f in table.findall("FIELD")]
        row = next(table.iter("TR"), None)
        if row is not None:
            values = [td.text or "" for td in row.findall("TD")]
            out.update(zip(names, values))
    return out


def _tail(text: str, nlines: int = 12) -> str:
    lines = [ln.strip().lstrip(">").strip() for ln in _ANSI.sub("\n", text).splitlines()]
    lines = [ln for ln in lines if ln] or ["(no output)"]
    return "\n    ".join(lines[-nlines:])


def _run(binary: str, tmp: Path, keys: dict) -> str:
    """Write ``keys`` as the configuration file and run SExtractor on ``image.fits`` in ``tmp``.

    Returns its combined output; raises :class:`SExtractorError` on a non-zero exit.
    """
    (tmp / "comest.sex").write_text("".join(f"{k:<18} {v}\n" for k, v in keys.items()))
    try:
        proc = subprocess.run([binary, "image.fits", "-c", "comest.sex"], cwd=tmp, capture_output=True,
                              text=True, errors="replace")
    except OSError as exc:
        raise BackendUnavailableError(f"cannot run the SExtractor binary {binary!r}: {exc}. "
                                      f"{_INSTALL_HINT}") from None
    log = proc.stdout + proc.stderr
    if proc.returncode != 0:
        raise SExtractorError(f"SExtractor ({binary}) exited with status {proc.returncode}. Its last output "
                              f"lines:\n    {_tail(log)}")
    return log


def _auto_ellipse_touches_mask(mask: np.ndarray, x, y, a, b, theta, scale) -> np.ndarray:
    """True where the ellipse ``scale * (a, b, theta)`` centred on (x, y) holds a masked pixel centre.

    Arrays of shape (n,); 0-based coordinates, theta in radians.  A summed-area
    table rejects objects whose bounding box holds no masked pixel, so only the
    few near masks are tested pixel by pixel.
    """
    n = len(x)
    out = np.zeros(n, dtype=bool)
    if n == 0 or not mask.any():
        return out
    ny, nx = mask.shape
    sat = np.zeros((ny + 1, nx + 1), dtype=np.int64)
    sat[1:, 1:] = np.cumsum(np.cumsum(mask, axis=0), axis=1)
    rad = np.asarray(scale, float) * np.asarray(a, float)  # semi-major axis bounds the ellipse
    x0 = np.clip(np.floor(x - rad), 0, nx - 1).astype(int)
    x1 = np.clip(np.ceil(x + rad), 0, nx - 1).astype(int)
    y0 = np.clip(np.floor(y - rad), 0, ny - 1).astype(int)
    y1 = np.clip(np.ceil(y + rad), 0, ny - 1).astype(int)
    inbox = sat[y1 + 1, x1 + 1] - sat[y0, x1 + 1] - sat[y1 + 1, x0] + sat[y0, x0]
    for i in np.flatnonzero((inbox > 0) & (rad > 0)):
        yy, xx = np.mgrid[y0[i]:y1[i] + 1, x0[i]:x1[i] + 1]
        dx, dy = xx - x[i], yy - y[i]
        c, s = np.cos(theta[i]), np.sin(theta[i])
        u = (dx * c + dy * s) / (scale[i] * a[i])
        v = (-dx * s + dy * c) / (scale[i] * max(b[i], 1e-3))
        out[i] = bool(np.any(mask[y0[i]:y1[i] + 1, x0[i]:x1[i] + 1] & (u * u + v * v <= 1.0)))
    return out


def _column(table: dict, name: str, n: int, width: int | None = None) -> np.ndarray:
    """Column ``name`` as float64, shape (n,) or (n, width); zero rows when ``n == 0``."""
    if n == 0:
        return np.zeros((0,) if width is None else (0, width))
    values = np.asarray(table[name], dtype=float)
    if width is not None:
        return values.reshape(n, width)
    return values[:, 0] if values.ndim > 1 else values  # FLUX_RADIUS is a vector for several fractions


def detect_sextractor(data: np.ndarray, *, mask: np.ndarray | None = None,
                      weight_noise: np.ndarray | None = None, zeropoint: float, gain: float | None = None,
                      saturation: float | None = None, wcs=None, config: DetectionConfig = DetectionConfig(),
                      workdir: str | os.PathLike | None = None,
                      threshold_noise: np.ndarray | None = None,
                      threshold_background: np.ndarray | None = None) -> DetectionResult:
    """Detect and measure sources with the SExtractor binary.

    Same semantics as :func:`comest_bayes.detect.sep_backend.detect_array`.

    Parameters
    ----------
    data : ndarray, shape (ny, nx)
        Image *with* its sky (SExtractor estimates the background with
        ``config.back_size`` / ``config.back_filtersize``); masked pixels may
        hold anything, including NaN.
    mask : ndarray of bool, shape (ny, nx), optional
        True for bad pixels; these are never detected nor used.
    weight_noise : ndarray, shape (ny, nx), optional
        1-sigma noise from a weight map (``ImageData.noise``); non-finite or
        non-positive values count as masked.
    zeropoint : float
        Magnitude zero point.
    gain, saturation : float, optional
        e-/ADU (adds the sources' Poisson noise to flux errors) and
        saturation level in image units.
    wcs : astropy.wcs.WCS, optional
        For the ``ra``/``dec`` columns (of ``xwin``, ``ywin``).
    config : DetectionConfig
        Detection settings (SExtractor meaning); ``config.backend`` is not
        looked at, so the same configuration can be run through both backends.
    workdir : path-like, optional
        Directory under which the private temporary directory is made
        (created if missing); the system's temporary directory by default.
    threshold_noise : ndarray, shape (ny, nx), optional
        A noise sigma map used as it is (``detection.noise_level =
        "observed"``): SExtractor is given it as a ``MAP_RMS`` weight image,
        whose values it takes in absolute units with ``RESCALE_WEIGHTS N``, so
        neither the weight map's rescaling pass nor the background RMS of this
        image enters the threshold (``detection.noise`` and ``weight_noise``
        are then not used).  The background level is still measured here.
    threshold_background : None
        Not supported: SExtractor always measures its own background map
        (``BACK_TYPE MANUAL`` takes one constant, not a map), so
        ``detection.background_level = "observed"`` needs the SEP backend;
        anything but None raises :class:`~comest_bayes.errors.ConfigError`.

    Returns
    -------
    DetectionResult
        ``catalog`` (DETECTION_COLUMNS), ``segmentation`` (int32, 0 = sky,
        else the ``id``), ``background``, ``rms`` (SExtractor's check images,
        float32), ``noise`` (float32, the sigma the threshold was relative to;
        masked pixels hold the median) and ``meta``.

    Raises
    ------
    BackendUnavailableError
        No SExtractor binary.
    InputError
        Arrays of wrong dimension or shape, non-finite unmasked pixels, or
        everything masked.
    SExtractorError
        SExtractor exited with an error (its last output lines are quoted).
    DetectionOverflowError
        SExtractor's pixel or object stack overflowed even after one retry
        with larger stacks.
    """
    if threshold_background is not None:
        raise ConfigError("detection.background_level='observed' needs detection.backend='sep': SExtractor "
                          "measures its own background map (BACK_TYPE MANUAL takes one constant, not a map).")
    binary = find_sextractor()
    data = np.asarray(data)
    if data.ndim != 2:
        raise InputError(f"the image must be 2-D; received an array of shape {data.shape}.")
    shape = data.shape
    if mask is None:
        mask = np.zeros(shape, dtype=bool)
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != shape:
        raise InputError(f"the mask has shape {mask.shape} but the image has shape {shape}; "
                         f"give a mask of the image's shape.")
    if weight_noise is not None:
        weight_noise = np.ascontiguousarray(weight_noise, dtype=np.float32)
        if weight_noise.shape != shape:
            raise InputError(f"the weight noise map has shape {weight_noise.shape} but the image has shape "
                             f"{shape}; give a map of the image's shape.")
    given = None
    if threshold_noise is not None:
        given = given_noise(threshold_noise, mask)
        mode = "weight"  # SExtractor reads the given map as MAP_RMS, like a rescaled weight map
    else:
        mode = sextractor_noise_mode(config.noise, weight_noise is not None)
    if mode == "weight" and given is None:
        mask = mask | ~np.isfinite(weight_noise) | (weight_noise <= 0)
    if mask.all():
        raise InputError("every pixel of the image is masked; nothing can be detected.")
    image = np.asarray(data, dtype=np.float32)
    if not np.all(np.isfinite(image[~mask])):
        raise InputError("the image holds NaN or infinite values in unmasked pixels; mask them first "
                         "(load_image does this).")
    image = np.where(mask, BLANK_VALUE, image).astype(np.float32)
    kernel = filter_kernel(config.filter)

    if workdir is not None:
        Path(workdir).mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="comest-sextractor-", dir=workdir) as tmp:
        tmp = Path(tmp)
        _write_fits(tmp / "image.fits", image)
        del image
        files = {
            "CATALOG_NAME": "catalog.fits",
            "PARAMETERS_NAME": "catalog.param",
            "CHECKIMAGE_TYPE": "SEGMENTATION,BACKGROUND,BACKGROUND_RMS",
            "CHECKIMAGE_NAME": "segmentation.fits,background.fits,rms.fits",
            "XML_NAME": "report.xml",
        }
        naper = len(config.phot_apertures)
        (tmp / "catalog.param").write_text("\n".join(p.format(naper=naper) for p in _PARAMS) + "\n")
        if kernel is not None:
            _write_conv(kernel, tmp / "detection.conv")
            files["FILTER_NAME"] = "detection.conv"
        noise = None
        if given is not None:
            noise = given
            _write_fits(tmp / "weight.fits", np.where(mask, MASKED_RMS, noise))
            files["WEIGHT_IMAGE"] = "weight.fits"
        elif mode == "weight":
            # Pass 1, no detection: SExtractor's background-RMS map, to which the weight map is scaled.
            keys = sextractor_config(config, zeropoint=zeropoint, gain=gain, saturation=saturation,
                                     noise_mode="global") | files | {
                "CATALOG_TYPE": "NONE", "FILTER": "N", "DETECT_THRESH": "1e6", "ANALYSIS_THRESH": "1e6",
                "CHECKIMAGE_TYPE": "BACKGROUND_RMS", "CHECKIMAGE_NAME": "rms_pass1.fits", "WRITE_XML": "N"}
            keys.pop("FILTER_NAME", None)
            _run(binary, tmp, keys)
            noise, _ = noise_map("weight", _read_image(tmp / "rms_pass1.fits", np.float32), float("nan"),
                                 weight_noise, mask)
            _write_fits(tmp / "weight.fits", np.where(mask, MASKED_RMS, noise))
            files["WEIGHT_IMAGE"] = "weight.fits"

        attempts = [(config.pixstack, 3000), (max(config.pixstack, mask.size), 12000)]
        for pixstack, objstack in attempts:
            keys = sextractor_config(config, zeropoint=zeropoint, gain=gain, saturation=saturation,
                                     noise_mode=mode, pixstack=pixstack, objstack=objstack) | files
            log = _run(binary, tmp, keys)
            overflow = re.search(r"Pixel stack overflow|increase MEMORY_OBJSTACK", log)
            if overflow is None:
                break
        else:
            raise DetectionOverflowError(
                f"SExtractor overflowed its buffers ('{overflow.group(0)}') even with MEMORY_PIXSTACK "
                f"{attempts[-1][0]} and MEMORY_OBJSTACK {attempts[-1][1]}. The image is too crowded for this "
                f"configuration: raise detection.thresh or detection.minarea, lower "
                f"detection.deblend_nthresh, or raise detection.pixstack."
            )

        try:
            report = _read_xml(tmp / "report.xml")
            with fits.open(tmp / "catalog.fits", memmap=False) as hdul:
                table = hdul[1].data
                n = 0 if table is None else len(table)
                cat = {name: np.array(table[name]) for name in table.columns.names} if n else {}
            seg = _read_image(tmp / "segmentation.fits", np.int32)
            back = _read_image(tmp / "background.fits", np.float32)
            rms = _read_image(tmp / "rms.fits", np.float32)
        except (OSError, KeyError, IndexError, ET.ParseError) as exc:
            raise SExtractorError(
                f"SExtractor ({binary}) ran but its output could not be read ({exc}). Its last output "
                f"lines:\n    {_tail(log)}"
            ) from None

    globback = float(report.get("Background_Mean", "nan"))
    globrms = float(report.get("Background_StDev", "nan"))
    if mode == "global":
        noise = np.full(shape, globrms, dtype=np.float32)
    elif mode == "background":
        noise = rms.copy()
        if mask.any():
            noise[mask] = float(np.median(noise[~mask]))
    # weight mode: ``noise`` is the map SExtractor was given (masked pixels already hold the median)

    columns = _catalog_columns(cat, n, naper=naper, shape=shape, mask=mask, noise=noise,
                               zeropoint=zeropoint, wcs=wcs)
    version = report.get("version") or sextractor_version(binary)
    meta = {
        "BACKEND": "sextractor", "SEXVER": version, "ZEROPT": zeropoint, "THRESH": config.thresh,
        "NOISEMOD": "given" if given is not None else mode, "GLOBBACK": globback, "GLOBRMS": globrms,
        "PIXSTACK": int(pixstack), "OBJSTACK": int(objstack), "BACKSIZE": config.back_size, "BACKFILT": config.back_filtersize,
    }
    catalog = make_catalog(columns, naper, meta=meta)
    return DetectionResult(catalog=catalog, segmentation=seg, background=back, rms=rms, noise=noise,
                           meta={k.lower(): v for k, v in meta.items()}
                           | {"nobj": len(catalog), "binary": binary})


def _catalog_columns(cat: dict, n: int, *, naper: int, shape, mask, noise, zeropoint, wcs) -> dict:
    """Convert SExtractor's FITS_1.0 columns to :data:`DETECTION_COLUMNS` arrays."""
    ny, nx = shape

    def col(name, width=None):
        return _column(cat, name, n, width)

    x, y = col("X_IMAGE") - 1.0, col("Y_IMAGE") - 1.0
    xwin, ywin = col("XWIN_IMAGE") - 1.0, col("YWIN_IMAGE") - 1.0
    xp = np.clip(col("XPEAK_IMAGE").astype(int) - 1, 0, nx - 1)
    yp = np.clip(col("YPEAK_IMAGE").astype(int) - 1, 0, ny - 1)
    a, b = col("A_IMAGE"), col("B_IMAGE")
    theta = np.clip(np.deg2rad(col("THETA_IMAGE")), -np.pi / 2, np.pi / 2)  # float32 degrees may overshoot
    kron = col("KRON_RADIUS")
    flux_auto, fluxerr_auto = col("FLUX_AUTO"), col("FLUXERR_AUTO")
    flux_aper, fluxerr_aper = col("FLUX_APER", naper), col("FLUXERR_APER", naper)
    flags = col("FLAGS").astype(np.int64)
    flags[_auto_ellipse_touches_mask(mask, x, y, a, b, theta, kron)] |= FLAG_MASKED
    derived = derived_columns(flux_auto, fluxerr_auto, flux_aper, fluxerr_aper, xwin, ywin, zeropoint=zeropoint,
                              wcs=wcs)
    mag_auto, magerr_auto, snr = derived["mag_auto"], derived["magerr_auto"], derived["snr_auto"]
    mag_aper, magerr_aper, ra, dec = derived["mag_aper"], derived["magerr_aper"], derived["ra"], derived["dec"]
    return {
        "id": col("NUMBER").astype(np.int64), "x": x, "y": y, "xwin": xwin, "ywin": ywin, "ra": ra, "dec": dec,
        "a": a, "b": b, "theta": theta, "npix": col("ISOAREA_IMAGE").astype(np.int64), "peak": col("FLUX_MAX"),
        "flux_iso": col("FLUX_ISO"), "kron_radius": kron, "flux_auto": flux_auto, "fluxerr_auto": fluxerr_auto,
        "mag_auto": mag_auto, "magerr_auto": magerr_auto, "snr_auto": snr, "flux_aper": flux_aper,
        "fluxerr_aper": fluxerr_aper, "mag_aper": mag_aper, "magerr_aper": magerr_aper,
        "flux_radius": col("FLUX_RADIUS"), "background": col("BACKGROUND"), "noise": noise[yp, xp],
        "flags": flags,
    }
