"""Source detection with SEP, keeping SExtractor's semantics.

The same function runs on the observed image and on every simulated image, so the
injection-recovery measurement uses an identical detector.  SEP is always called with
``filter_type="conv"`` and an explicit noise map (SExtractor's threshold); the threshold
semantics and the fast path for realizations: ``docs/detection.md``.
"""

from __future__ import annotations

import numpy as np
import sep

from comest_bayes.detect.catalog import (FLAG_APER_TRUNC, FLAG_BLENDED, FLAG_DEBLEND_OVERFLOW, FLAG_EDGE, FLAG_MASKED, FLAG_SATURATED, derived_columns, make_catalog)
from comest_bayes.config import DetectionConfig
from comest_bayes.detect.base import DEFAULT_CONV, DetectionResult, filter_kernel, given_background, given_noise, noise_map
from comest_bayes.errors import ConfigError, DetectionOverflowError, InputError
from comest_bayes.detect.sextractor import detect_sextractor

# DetectionResult, filter_kernel and noise_map live in detection_base (shared with the SExtractor backend)
# and are re-exported here, where users have always found them.
__all__ = ["DEFAULT_CONV", "DetectionResult", "detect", "detect_array", "detect_with_backend", "filter_kernel",
           "noise_map"]


def _extract(data_sub, noise, mask, config: DetectionConfig, kernel, segmentation: bool = True):
    """sep.extract with SExtractor semantics and overflow turned into a clear error.

    On a buffer overflow the limits are raised once (pixel stack to the image
    size, sub-object limit x4); a second overflow raises
    :class:`DetectionOverflowError` with the numbers.
    """
    limits = [(config.pixstack, config.sub_object_limit),
              (max(config.pixstack, data_sub.size), config.sub_object_limit * 4)]
    last = None
    for pixstack, sublimit in limits:
        # SEP keeps these per process: set them every time so that worker processes agree.
        sep.set_extract_pixstack(int(pixstack))
        sep.set_sub_object_limit(int(sublimit))
        try:
            return sep.extract(
                data_sub, config.thresh, err=noise, mask=mask, minarea=config.minarea,
                filter_kernel=kernel, filter_type="conv",
                deblend_nthresh=config.deblend_nthresh, deblend_cont=config.deblend_mincont,
                clean=config.clean, clean_param=config.clean_param, segmentation_map=segmentation,
            ), (pixstack, sublimit)
        except Exception as exc:  # SEP raises bare Exception for buffer overflows
            text = str(exc)
            if "buffer full" in text or "overflow" in text or "limit" in text:
                last = text
                continue
            raise
    raise DetectionOverflowError(
        f"SEP overflowed its buffers even with a pixel stack of {limits[-1][0]} and a sub-object limit "
        f"of {limits[-1][1]} ({last}). The image is too crowded for this configuration: raise "
        f"detection.thresh or detection.minarea, lower detection.deblend_nthresh, or raise "
        f"detection.pixstack / detection.sub_object_limit."
    )


def detect_array(data: np.ndarray, *, mask: np.ndarray | None = None, weight_noise: np.ndarray | None = None,
                 zeropoint: float, gain: float | None = None, saturation: float | None = None, wcs=None,
                 config: DetectionConfig = DetectionConfig(), segmentation: bool = True, inplace: bool = False,
                 check_finite: bool = True, threshold_noise: np.ndarray | None = None,
                 threshold_background: np.ndarray | None = None) -> DetectionResult:
    """Detect and measure sources on an image array.

    Parameters
    ----------
    data : ndarray, shape (ny, nx)
        Image *with* its sky (the background is estimated here, as SExtractor
        does); masked pixels may hold anything finite (anything at all with
        ``inplace=True``: they are set to 0 before use).
    mask : ndarray of bool, optional
        True for bad pixels.
    weight_noise : ndarray, optional
        1-sigma noise from a weight map (``ImageData.noise``).
    zeropoint : float
        Magnitude zero point.
    gain, saturation : float, optional
        e-/unit (adds Poisson noise to flux errors) and saturation level.
    wcs : astropy.wcs.WCS, optional
        For the ``ra``/``dec`` columns.
    config : DetectionConfig
        Detection settings (SExtractor meaning).
    segmentation : bool
        Build the segmentation map (default).  False leaves
        ``DetectionResult.segmentation`` None and saves SEP the work.
    inplace : bool
        False (default): ``data`` is not modified.  True: ``data`` is the work
        buffer when it is a writeable C-contiguous float32 array (else a copy
        is made as usual): its masked pixels are set to 0 and the background
        is subtracted in it, so on return it holds the background-subtracted
        image.  In ``background`` noise mode the RMS map is also the noise map
        (``result.noise is result.rms``, masked pixels filled), and in
        ``weight`` mode the rescaled map is built in one buffer.
    check_finite : bool
        Check that unmasked pixels are finite (default).  Pass False only when
        the caller has checked (e.g. once on the base image of many
        realizations).
    threshold_noise : ndarray, shape (ny, nx), optional
        The per-pixel sigma of the threshold and of the flux errors, used as
        given instead of one derived from this image (``detection.noise`` is
        then not applied and ``weight_noise`` is ignored): the observed image's
        noise map when injected images are re-detected with
        ``detection.noise_level = "observed"``.  Must be finite and positive
        on unmasked pixels; masked pixels are filled with the median.  The
        background *level* is still measured on ``data`` unless
        ``threshold_background`` is given too.
    threshold_background : ndarray, shape (ny, nx), optional
        The background level map subtracted, used as given instead of one
        measured on ``data`` (``detection.background_level = "observed"``:
        the observed image's).  With both given maps no background mesh is
        measured at all and ``DetectionResult.rms`` is the given noise.

    Returns
    -------
    DetectionResult
        The catalog does not depend on ``segmentation``, ``inplace`` or
        ``check_finite``.
    """
    if config.backend != "sep":
        raise ConfigError("detect_array runs SEP; use comest_bayes.detect.sextractor.detect_sextractor for "
                          "detection.backend='sextractor' (or call comest_bayes.detect.sep_backend.detect).")
    data = np.ascontiguousarray(data, dtype=np.float32)
    if inplace and not data.flags.writeable:
        data = data.copy()
    if mask is None:
        mask = np.zeros(data.shape, dtype=bool)
    mask = np.ascontiguousarray(mask, dtype=bool)
    if mask.shape != data.shape:
        raise InputError(f"the mask has shape {mask.shape} but the image {data.shape}; pass a mask of the "
                         f"image's shape.")
    masked = bool(mask.any())
    if check_finite and (~np.isfinite(data) & ~mask).any():
        raise InputError("the image holds NaN or infinite values in unmasked pixels; mask them first "
                         "(load_image does this).")
    if masked:
        if inplace:
            np.putmask(data, mask, np.float32(0.0))
        else:
            data = np.where(mask, np.float32(0.0), data)

    if threshold_background is not None and threshold_noise is not None:
        # both maps given (the observed image's): nothing is measured on this image
        back = given_background(threshold_background, mask)
        noise, mode = given_noise(threshold_noise, mask), "given"
        rms = noise
        globback, globrms = float(np.median(back)), float(np.median(noise))
    else:
        bkg = sep.Background(data, mask=mask, bw=config.back_size, bh=config.back_size,
                             fw=config.back_filtersize, fh=config.back_filtersize)
        back = bkg.back(dtype=np.float32) if threshold_background is None else given_background(threshold_background, mask)
        rms = bkg.rms(dtype=np.float32)
        globback, globrms = float(bkg.globalback), float(bkg.globalrms)
        if threshold_noise is None:
            noise, mode = noise_map(config.noise, rms, globrms, weight_noise, mask, copy=not inplace)
        else:
            noise, mode = given_noise(threshold_noise, mask), "given"
    if inplace:
        data_sub = np.subtract(data, back, out=data)
    else:
        data_sub = data - back
    if masked:
        np.putmask(data_sub, mask, np.float32(0.0))

    kernel = filter_kernel(config.filter)
    found, limits = _extract(data_sub, noise, mask, config, kernel, segmentation)
    if segmentation:
        objs, seg = found
        seg = seg.astype(np.int32, copy=False)
    else:
        objs, seg = found, None
    columns = measure(data_sub, objs, noise=noise, mask=mask, back=back, config=config,
                      zeropoint=zeropoint, gain=gain, saturation=saturation, wcs=wcs)
    meta = {
        "BACKEND": "sep", "SEPVER": sep.__version__, "ZEROPT": zeropoint, "THRESH": config.thresh,
        "NOISEMOD": mode, "GLOBBACK": globback, "GLOBRMS": globrms,
        "PIXSTACK": int(limits[0]), "SUBOBJ": int(limits[1]), "BACKSIZE": config.back_size,
        "BACKFILT": config.back_filtersize,
    }
    catalog = make_catalog(columns, len(config.phot_apertures), meta=meta)
    return DetectionResult(catalog=catalog, segmentation=seg, background=back, rms=rms, noise=noise,
                           meta={k.lower(): v for k, v in meta.items()} | {"nobj": len(catalog)})


def measure(data_sub, objs, *, noise, mask, back, config: DetectionConfig, zeropoint, gain, saturation, wcs):
    """Photometry and shape columns for SEP objects (Kron/AUTO, apertures, FLUX_RADIUS, windowed centroid)."""
    n = len(objs)
    ny, nx = data_sub.shape
    x = objs["x"].astype(float)
    y = objs["y"].astype(float)
    a, b, theta = (objs[k].astype(float) for k in ("a", "b", "theta"))
    # a faint object's second moments can be negative (noise): SEP then gives a NaN axis, which its
    # apertures refuse ("invalid aperture parameters").  Such an object is measured in the circle of
    # its own area (radius sqrt(npix / pi)), and its catalog shape is that circle.
    shapeless = ~(np.isfinite(a) & np.isfinite(b) & np.isfinite(theta))
    if shapeless.any():
        radius = np.sqrt(objs["npix"][shapeless] / np.pi)
        a[shapeless], b[shapeless], theta[shapeless] = radius, radius, 0.0
    a = np.maximum(a, 1e-3)
    b = np.maximum(b, 1e-3)
    # float32(pi/2) exceeds pi/2 in float64, which sep.sum_ellipse rejects ("invalid aperture
    # parameters") for objects aligned with the y axis; clip back to SEP's range.
    theta = np.clip(theta, -np.pi / 2, np.pi / 2)
    flags = np.zeros(n, dtype=np.int64)
    flags[(objs["flag"] & sep.OBJ_MERGED) != 0] |= FLAG_BLENDED
    flags[(objs["flag"] & sep.OBJ_DOVERFLOW) != 0] |= FLAG_DEBLEND_OVERFLOW
    edge = (objs["xmin"] <= 0) | (objs["ymin"] <= 0) | (objs["xmax"] >= nx - 1) | (objs["ymax"] >= ny - 1)
    flags[edge] |= FLAG_EDGE
    xp = np.clip(objs["xpeak"], 0, nx - 1)
    yp = np.clip(objs["ypeak"], 0, ny - 1)
    if saturation is not None and n:
        flags[(objs["peak"] + back[yp, xp]) >= saturation] |= FLAG_SATURATED

    kfact, rmin = config.phot_autoparams
    naper = len(config.phot_apertures)
    if n:
        kron, kflag = sep.kron_radius(data_sub, x, y, a, b, theta, 6.0, mask=mask)
        kron = np.where(np.isfinite(kron) & (kron > 0), kron, 0.0)
        # SExtractor's AUTO ellipse: kfact * Kron radius, never below rmin (both in units of a, b).
        scale = np.maximum(kfact * kron, rmin)
        flux_auto, fluxerr_auto, aflag = sep.sum_ellipse(data_sub, x, y, a, b, theta, scale, err=noise,
                                                         gain=gain, mask=mask, subpix=1)
        flags[(aflag & sep.APER_HASMASKED) != 0] |= FLAG_MASKED
        flags[(aflag & sep.APER_TRUNC) != 0] |= FLAG_APER_TRUNC
        flux_aper = np.empty((n, naper))
        fluxerr_aper = np.empty((n, naper))
        for j, diam in enumerate(config.phot_apertures):
            f, fe, fl = sep.sum_circle(data_sub, x, y, diam / 2.0, err=noise, gain=gain, mask=mask, subpix=5)
            flux_aper[:, j], fluxerr_aper[:, j] = f, fe
        rmax = np.maximum(6.0 * a, scale * a)
        normflux = np.where(flux_auto > 0, flux_auto, objs["flux"])
        flux_radius, _ = sep.flux_radius(data_sub, x, y, rmax, config.phot_fluxfrac, normflux=normflux,
                                         mask=mask, subpix=5)
        flux_radius = np.where(np.isfinite(flux_radius) & (flux_radius > 0), flux_radius, np.sqrt(a * b))
        sig = 2.0 / 2.35 * flux_radius
        xwin, ywin, wflag = sep.winpos(data_sub, x, y, sig, mask=mask)
        # A windowed centroid that wandered beyond the object's isophotal scale was pulled by a
        # neighbour (FLUX_RADIUS, hence the window, is inflated by nearby light): keep the barycentre.
        badwin = ~np.isfinite(xwin) | ~np.isfinite(ywin) | (np.hypot(xwin - x, ywin - y) > np.maximum(1.0, np.sqrt(a * b)))
        xwin = np.where(badwin, x, xwin)
        ywin = np.where(badwin, y, ywin)
    else:
        kron = flux_auto = fluxerr_auto = flux_radius = xwin = ywin = np.zeros(0)
        flux_aper = fluxerr_aper = np.zeros((0, naper))
    derived = derived_columns(flux_auto, fluxerr_auto, flux_aper, fluxerr_aper, xwin, ywin, zeropoint=zeropoint,
                              wcs=wcs)
    mag_auto, magerr_auto, snr = derived["mag_auto"], derived["magerr_auto"], derived["snr_auto"]
    mag_aper, magerr_aper, ra, dec = derived["mag_aper"], derived["magerr_aper"], derived["ra"], derived["dec"]
    return {
        "id": np.arange(1, n + 1), "x": x, "y": y, "xwin": xwin, "ywin": ywin, "ra": ra, "dec": dec,
        "a": a, "b": b, "theta": theta, "npix": objs["tnpix"], "peak": objs["peak"],
        "flux_iso": objs["flux"], "kron_radius": np.where(kron > 0, scale, 0.0) if n else kron, "flux_auto": flux_auto, "fluxerr_auto": fluxerr_auto,
        "mag_auto": mag_auto, "magerr_auto": magerr_auto, "snr_auto": snr, "flux_aper": flux_aper,
        "fluxerr_aper": fluxerr_aper, "mag_aper": mag_aper, "magerr_aper": magerr_aper,
        "flux_radius": flux_radius, "background": back[yp, xp] if n else np.zeros(0),
        "noise": noise[yp, xp] if n else np.zeros(0), "flags": flags,
    }


def detect_with_backend(data: np.ndarray, *, config: DetectionConfig = DetectionConfig(), workdir=None,
                        segmentation: bool = True, inplace: bool = False, check_finite: bool = True,
                        threshold_noise: np.ndarray | None = None, threshold_background: np.ndarray | None = None,
                        **kwargs) -> DetectionResult:
    """:func:`detect_array` or the SExtractor binary, as ``config.backend`` says (same arguments).

    ``workdir`` is where the SExtractor backend writes its temporary files
    (a private temporary directory by default).  ``segmentation``,
    ``inplace`` and ``check_finite`` are SEP's fast-path options (see
    :func:`detect_array`); the SExtractor backend ignores them: it reads the
    image from a file it writes, never modifies ``data``, and always returns
    its segmentation map.  ``threshold_noise`` and ``threshold_background``
    (fixed noise and background maps, e.g. the observed image's under
    ``detection.noise_level`` / ``detection.background_level = "observed"``)
    are used by both backends.
    """
    if config.backend == "sextractor":

        return detect_sextractor(data, workdir=workdir, config=config, threshold_noise=threshold_noise,
                                 threshold_background=threshold_background, **kwargs)
    return detect_array(data, config=config, segmentation=segmentation, inplace=inplace,
                        check_finite=check_finite, threshold_noise=threshold_noise,
                        threshold_background=threshold_background, **kwargs)


def detect(image, config: DetectionConfig = DetectionConfig(), workdir=None) -> DetectionResult:
    """Detect sources on an :class:`~comest_bayes.io.image.ImageData` with the configured backend."""
    return detect_with_backend(image.data, config=config, workdir=workdir, mask=image.mask, weight_noise=image.noise,
                               zeropoint=image.zeropoint, gain=image.gain, saturation=image.saturation,
                               wcs=image.wcs)
