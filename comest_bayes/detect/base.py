"""What both detection backends share: the result type, the filter kernel and the noise map.

:mod:`comest_bayes.detect.sep_backend` (SEP) and :mod:`comest_bayes.detect.sextractor` (the
SExtractor binary) both return a :class:`DetectionResult`, filter with
:func:`filter_kernel` and put the threshold on :func:`noise_map`; these live
here so that neither backend imports the other (``detection`` still
re-exports them).  Nothing here depends on SEP or on the binary.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from comest_bayes.constants import FWHM_PER_SIGMA
from comest_bayes.errors import ConfigError, InputError

__all__ = ["DEFAULT_CONV", "DetectionResult", "filter_kernel", "given_background", "given_noise", "noise_map",
           "weight_agreement"]

#: SExtractor's ``default.conv``: 3x3 "all-ground" kernel with FWHM = 2 pixels.
DEFAULT_CONV = np.array([[1, 2, 1], [2, 4, 2], [1, 2, 1]], dtype=np.float32)


@dataclass
class DetectionResult:
    """Output of one detection run.

    Attributes
    ----------
    catalog : astropy.table.Table
        Columns of :data:`comest_bayes.detect.catalog.DETECTION_COLUMNS`.
    segmentation : ndarray of int32, shape (ny, nx), or None
        0 for sky, ``id`` of the object elsewhere; None when not requested
        (``detect_array(..., segmentation=False)``).
    background : ndarray of float32
        Background level map (image units).
    rms : ndarray of float32
        Background RMS map from the mesh (image units).
    noise : ndarray of float32
        Noise sigma the threshold was relative to (equals ``rms`` unless a
        weight map or the global mode was used; with ``inplace=True`` in the
        ``background`` mode it *is* ``rms``, with masked pixels filled).
    meta : dict
        Backend, threshold mode, global background and RMS, counts.
    """

    catalog: object
    segmentation: np.ndarray | None
    background: np.ndarray
    rms: np.ndarray
    noise: np.ndarray
    meta: dict


def filter_kernel(name: str) -> np.ndarray | None:
    """The detection kernel for a ``detection.filter`` value, normalised to unit sum.

    ``"default"`` is SExtractor's 3x3 default.conv; ``"gauss_F_NxN"`` is a
    Gaussian of FWHM ``F`` pixels sampled on an N x N grid; ``"none"`` disables
    filtering; anything else is read as a SExtractor ``.conv`` file.
    """
    if name in ("none", "None", ""):
        return None
    if name == "default":
        kernel = DEFAULT_CONV.copy()
    else:
        m = re.fullmatch(r"gauss_(\d+(?:\.\d+)?)_(\d+)x(\d+)", name)
        if m:
            fwhm, n1, n2 = float(m.group(1)), int(m.group(2)), int(m.group(3))
            if n1 != n2 or n1 % 2 == 0 or fwhm <= 0:
                raise ConfigError(f"detection.filter={name!r}: use an odd square size, e.g. gauss_2.0_5x5.")
            sig = fwhm / FWHM_PER_SIGMA
            r = np.arange(n1) - n1 // 2
            g = np.exp(-0.5 * (r / sig) ** 2)
            kernel = np.outer(g, g).astype(np.float32)
        else:
            path = Path(name)
            if not path.is_file():
                raise ConfigError(
                    f"detection.filter={name!r} is neither 'default', 'none', 'gauss_<fwhm>_<n>x<n>' "
                    f"nor an existing SExtractor .conv file."
                )
            rows = []
            for line in path.read_text().splitlines():
                line = line.split("#", 1)[0].strip()
                if not line or line.upper().startswith("CONV"):
                    continue
                rows.append([float(v) for v in line.split()])
            if not rows or len({len(r) for r in rows}) != 1:
                raise ConfigError(f"filter file {name!r} does not hold a rectangular kernel.")
            kernel = np.array(rows, dtype=np.float32)
    total = kernel.sum()
    if total <= 0:
        raise ConfigError(f"detection filter {name!r} sums to {total}; it cannot be normalised.")
    return np.ascontiguousarray(kernel / total)


def noise_map(mode: str, rms: np.ndarray, global_rms: float, weight_noise: np.ndarray | None,
              mask: np.ndarray, *, copy: bool = True) -> tuple[np.ndarray, str]:
    """The per-pixel sigma the detection threshold is relative to.

    For ``weight`` mode the weight-map sigma is rescaled so that its median over
    unmasked pixels equals that of the measured background RMS, as SExtractor
    does for ``MAP_WEIGHT``: a weight map fixes the *shape* of the noise, the
    image fixes its level.  Masked pixels get the median so no infinity
    reaches the photometry.

    Parameters
    ----------
    mode : {'auto', 'weight', 'background', 'global'}
        ``auto`` is ``weight`` when ``weight_noise`` is given, else ``background``.
    rms : ndarray of float32, shape (ny, nx)
        Background RMS map.
    global_rms : float
        The mesh's global RMS (``global`` mode).
    weight_noise : ndarray, shape (ny, nx), or None
        1-sigma noise from a weight map; never modified.
    mask : ndarray of bool, shape (ny, nx)
        True on bad pixels.
    copy : bool
        True (default): ``rms`` is left untouched.  False: in ``background``
        mode ``rms`` itself is returned (its masked or non-finite pixels
        filled in place), and in ``weight`` mode (float32 maps) the buffer of
        the per-pixel ratios is reused for the result, so one full-size array
        is allocated, plus the good pixels' ratios when some are masked.  The
        values are the same either way.

    Returns
    -------
    noise : ndarray of float32, shape (ny, nx)
    mode : str
        The mode used (``auto`` resolved).
    """
    if mode == "auto":
        mode = "weight" if weight_noise is not None else "background"
    if mode == "weight":
        if weight_noise is None:
            raise ConfigError("detection.noise='weight' needs a weight map; pass --weight FILE or use "
                              "detection.noise=background.")
        good = ~mask & np.isfinite(weight_noise) & (weight_noise > 0)
        if not copy and np.result_type(rms, weight_noise) == np.float32:
            # the same ratios in the same order as below, in one buffer that the result reuses
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = np.divide(rms, weight_noise)
            sample = ratio if good.all() else ratio[good]
            scale = float(np.median(sample, overwrite_input=True))
            out = np.multiply(weight_noise, scale, out=ratio)
        else:
            # median of per-pixel ratios: robust when the weight map has several depth levels
            scale = float(np.median(rms[good] / weight_noise[good]))
            out = (weight_noise * scale).astype(np.float32)
    elif mode == "global":
        out = np.full(rms.shape, global_rms, dtype=np.float32)
    elif mode == "background":
        out = rms.astype(np.float32, copy=copy)
    else:  # pragma: no cover - guarded by DetectionConfig
        raise ConfigError(f"unknown detection.noise mode {mode!r}")
    out = np.ascontiguousarray(out, dtype=np.float32)
    bad = mask | ~np.isfinite(out)
    if bad.any():
        # the fill value only needs to be typical: a median over a regular subsample of the good
        # pixels costs a fraction of one over all of them on large images
        step = max(1, out.size // 1_000_000)
        flat_good = ~bad.ravel()[::step]
        sample = out.ravel()[::step][flat_good]
        fill = float(np.median(sample)) if sample.size else (float(np.median(out[~bad])) if (~bad).any() else 1.0)
        out[bad] = fill
    return out, mode


def _given_map(what: str, values: np.ndarray, mask: np.ndarray, *, positive: bool) -> np.ndarray:
    """``values`` as a float32 C-contiguous copy, checked on the unmasked pixels (finite, and > 0 if ``positive``)."""
    values = np.asarray(values)
    if values.shape != mask.shape:
        raise InputError(f"the given {what} map has shape {values.shape} but the image {mask.shape}; pass the "
                         f"observed detection's {what} map of the same run.")
    out = np.array(values, dtype=np.float32, order="C", copy=True)
    bad = ~np.isfinite(out) | (out <= 0) if positive else ~np.isfinite(out)
    if (bad & ~mask).any():
        need = "finite and positive" if positive else "finite"
        raise InputError(f"the given {what} map is not {need} on {int((bad & ~mask).sum())} unmasked pixels; it "
                         f"must be a {what} level wherever the image is used.")
    return out


def given_noise(noise: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """A noise map given as it is (``detection.noise_level = "observed"``), checked and made contiguous.

    The threshold of an injected image is then relative to the observed image's
    noise map rather than to one measured again on the injected image.  Masked
    pixels get the median of the others, as :func:`noise_map` does.

    Parameters
    ----------
    noise : ndarray, shape (ny, nx)
        1-sigma noise per pixel (image units); never modified.
    mask : ndarray of bool, shape (ny, nx)
        True on bad pixels.

    Returns
    -------
    ndarray of float32, shape (ny, nx)

    Raises
    ------
    InputError
        A map of another shape, or one that is not finite and positive on
        every unmasked pixel.
    """
    out = _given_map("noise", noise, mask, positive=True)
    bad = mask | ~np.isfinite(out) | (out <= 0)
    if bad.any():
        out[bad] = float(np.median(out[~bad])) if (~bad).any() else 1.0
    return out


def given_background(background: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """A background level map given as it is (``detection.background_level = "observed"``).

    Parameters
    ----------
    background : ndarray, shape (ny, nx)
        Background level per pixel (image units); never modified.
    mask : ndarray of bool, shape (ny, nx)
        True on bad pixels; they get 0 (the detection zeroes them anyway).

    Returns
    -------
    ndarray of float32, shape (ny, nx)

    Raises
    ------
    InputError
        A map of another shape, or one not finite on every unmasked pixel.
    """
    out = _given_map("background", background, mask, positive=False)
    out[mask] = 0.0
    return out


def weight_agreement(weight_noise: np.ndarray, rms: np.ndarray, mask: np.ndarray, mesh: int) -> dict | None:
    """Does the noise a weight map implies rise where the image's own measured noise rises?

    The medians of the weight map's sigma and of the measured background RMS over the unmasked
    pixels of each ``mesh`` x ``mesh`` block (blocks at least half unmasked), and the Spearman rank
    correlation of the two over the blocks.  A weight map read as the wrong type (an error map as
    inverse variance, for example) reverses the ranks: on the shared JWST cutout its error map gives
    r = +0.68 over 100 meshes read as rms and -0.68 read as ivar; the DECam cutouts' inverse-variance
    maps +0.41 to +0.97 read as ivar.

    Returns
    -------
    dict or None
        ``spearman``, ``p`` (two-sided, no correlation) and ``meshes``; None with fewer than 10
        blocks or when either map is constant over them.
    """
    from scipy import stats

    ny, nx = rms.shape
    good = ~np.asarray(mask, bool) & np.isfinite(weight_noise) & (weight_noise > 0) & np.isfinite(rms)
    a, b = [], []
    for y in range(0, ny - mesh + 1, mesh):
        for x in range(0, nx - mesh + 1, mesh):
            g = good[y:y + mesh, x:x + mesh]
            if g.mean() >= 0.5:
                a.append(np.median(weight_noise[y:y + mesh, x:x + mesh][g]))
                b.append(np.median(rms[y:y + mesh, x:x + mesh][g]))
    if len(a) < 10 or np.ptp(a) == 0 or np.ptp(b) == 0:
        return None
    res = stats.spearmanr(a, b)
    return {"spearman": float(res.statistic), "p": float(res.pvalue), "meshes": len(a)}
