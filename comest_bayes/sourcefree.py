"""The source-free image (SFI) and the "bright and big" image (BnB).

Detected sources are replaced by draws of the sky, each segment grown by a radius set by the
seeing and the object's isophotal size, with the background and noise of the fill estimated
again without the sources.  The measurement behind the defaults: ``docs/sourcefree.md``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import sep
from scipy import ndimage

from comest_bayes.config import SourceFreeConfig
from comest_bayes.errors import InputError
from comest_bayes.io import layout
from comest_bayes.seeding import rng_for

__all__ = ["SourceFreeResult", "build_source_free", "removal_radii", "dilated_footprint", "judge_replacement",
           "format_percent", "BACKGROUND_SHIFT_WARN_SIGMA", "NOISE_RATIO_WARN"]

#: Background mesh used for the re-estimate when neither the configuration nor
#: the detection metadata gives one (SExtractor's BACK_SIZE default).
_DEFAULT_BACK_SIZE = 64
_DEFAULT_BACK_FILTERSIZE = 3
#: Normal-consistent scale of the median absolute deviation.
_MAD_TO_SIGMA = 1.482602218505602
#: Sky pixels used to recalibrate the noise level (a regular subsample beyond this).
_CALIBRATION_PIXELS = 4_000_000
#: SEP (as SExtractor) drops a background mesh holding less than this fraction of usable pixels and
#: fills it from its neighbours; with every mesh dropped its background is 0 and its RMS 1.
_MESH_MIN_GOOD = 0.5
#: The re-estimate needs at least this fraction of its meshes kept, else the detection's maps are used.
_MESHES_MIN_KEPT = 0.5
#: The fill's background level departs from the detection's by more than this many noise sigma: warned.
BACKGROUND_SHIFT_WARN_SIGMA = 0.3
#: The fill's noise departs from the detection's by more than this fraction: warned.
NOISE_RATIO_WARN = 0.2


@dataclass
class SourceFreeResult:
    """The source-free and bright-and-big images.

    Attributes
    ----------
    sfi : ndarray of float32, shape (ny, nx)
        Source-free image, sky level included like the input; masked pixels
        keep their input values.
    bnb : ndarray of float32, shape (ny, nx), or None
        Bright-and-big image: the input inside the (grown) footprints of the
        kept sources, the SFI elsewhere.  None when ``config.bnb`` is False.
    removed : ndarray of bool, shape (ny, nx)
        Pixels replaced by sky draws in the SFI (never a masked pixel).
    kept_ids : ndarray of int64
        Catalog ``id`` of the sources kept in the BnB image (sorted; empty
        without a BnB image).
    meta : dict
        Plain-JSON facts: removal radii (pixels), fractions of unmasked pixels
        replaced, the re-estimated background and noise levels, counts.
    """

    sfi: np.ndarray
    bnb: np.ndarray | None
    removed: np.ndarray
    kept_ids: np.ndarray
    meta: dict = field(default_factory=dict)


def removal_radii(areas, fwhm: float, config: SourceFreeConfig) -> np.ndarray:
    """Growth radius of each segment, in pixels.

    Parameters
    ----------
    areas : array_like of float, shape (n,)
        Segment areas in pixels.
    fwhm : float
        Seeing FWHM in pixels.
    config : SourceFreeConfig
        ``dilate``, ``dilate_min_pix`` and ``dilate_size`` are used.

    Returns
    -------
    ndarray of float, shape (n,)
        ``max(dilate * fwhm, dilate_min_pix) + dilate_size * sqrt(area / pi)``.
    """
    areas = np.asarray(areas, dtype=float)
    base = max(config.dilate * float(fwhm), float(config.dilate_min_pix))
    return base + config.dilate_size * np.sqrt(np.clip(areas, 0.0, None) / np.pi)


def dilated_footprint(segmentation: np.ndarray, ids, radii) -> np.ndarray:
    """Union of the segments ``ids``, each grown by its own radius.

    A pixel belongs to the grown segment of object ``i`` when its centre lies
    within ``radii[i]`` (Euclidean, pixels) of a pixel centre of the segment.
    Each object is grown in its own bounding box, so the cost scales with the
    objects' areas, not with the image size times the number of objects.

    Parameters
    ----------
    segmentation : ndarray of int, shape (ny, nx)
        0 for sky, the object id elsewhere.
    ids : array_like of int, shape (n,)
        Object ids to include (ids absent from the map are ignored).
    radii : array_like of float, shape (n,)
        Growth radius per object, pixels (0 keeps the segment as is).

    Returns
    -------
    ndarray of bool, shape (ny, nx)
    """
    seg = np.asarray(segmentation)
    out = np.zeros(seg.shape, dtype=bool)
    ids = np.asarray(ids, dtype=np.int64)
    radii = np.asarray(radii, dtype=float)
    if ids.size == 0 or seg.max(initial=0) <= 0:
        return out
    maxid = int(seg.max())
    slices = ndimage.find_objects(seg, max_label=maxid)
    ny, nx = seg.shape
    for oid, rad in zip(ids, radii):
        if oid < 1 or oid > maxid or slices[oid - 1] is None:
            continue
        sy, sx = slices[oid - 1]
        pad = int(np.floor(max(rad, 0.0)))
        y0, y1 = max(sy.start - pad, 0), min(sy.stop + pad, ny)
        x0, x1 = max(sx.start - pad, 0), min(sx.stop + pad, nx)
        own = seg[y0:y1, x0:x1] == oid
        if pad == 0:
            out[y0:y1, x0:x1] |= own
            continue
        # Distance of every pixel of the cut-out to the nearest pixel of this segment.  The
        # cut-out reaches floor(rad) beyond the segment's box, which holds every pixel within rad.
        dist = ndimage.distance_transform_edt(~own)
        out[y0:y1, x0:x1] |= dist <= rad
    return out


def _kron_ellipses(shape, catalog, ids, factor: float) -> np.ndarray:
    """Ellipses of ``factor`` x Kron radius (in units of a, b) of the objects ``ids``."""
    out = np.zeros(shape, dtype=bool)
    if factor <= 0 or len(ids) == 0:
        return out
    cat_ids = np.asarray(catalog["id"], dtype=np.int64)
    sel = np.isin(cat_ids, ids)
    x = np.asarray(catalog["x"], dtype=float)[sel]
    y = np.asarray(catalog["y"], dtype=float)[sel]
    a = np.asarray(catalog["a"], dtype=float)[sel]
    b = np.asarray(catalog["b"], dtype=float)[sel]
    # SEP's float32 angles can exceed pi/2 by one ulp in double precision, which its
    # aperture routines reject.
    theta = np.clip(np.asarray(catalog["theta"], dtype=float)[sel], -np.pi / 2, np.pi / 2)
    kron = np.asarray(catalog["kron_radius"], dtype=float)[sel]
    good = np.isfinite(x) & np.isfinite(y) & np.isfinite(a) & np.isfinite(b) & np.isfinite(theta) \
        & np.isfinite(kron) & (kron > 0) & (a > 0) & (b > 0)
    if good.any():
        sep.mask_ellipse(out, x[good], y[good], a[good], b[good], theta[good], r=factor * kron[good])
    return out


def _background_mesh(detection, config: SourceFreeConfig) -> tuple[int, int]:
    meta = getattr(detection, "meta", {}) or {}
    size = config.back_size or int(meta.get("back_size", meta.get("backsize", 0)) or 0) or _DEFAULT_BACK_SIZE
    filt = config.back_filtersize or int(meta.get("back_filtersize", meta.get("backfilt", 0)) or 0) \
        or _DEFAULT_BACK_FILTERSIZE
    return int(size), int(filt)


def _kept_mesh_fraction(usable: np.ndarray, size: int) -> float:
    """Fraction of the ``size`` x ``size`` background meshes whose usable pixels SEP would accept."""
    ny, nx = usable.shape
    fractions = []
    for y0 in range(0, ny, size):
        rows = usable[y0:y0 + size]
        counts = np.add.reduceat(rows.sum(axis=0), np.arange(0, nx, size))
        widths = np.diff(np.append(np.arange(0, nx, size), nx))
        fractions.append(counts / (widths * rows.shape[0]))
    return float(np.mean(np.concatenate(fractions) >= _MESH_MIN_GOOD))


def _rng(seed) -> np.random.Generator:
    if seed is None or isinstance(seed, bool):
        raise InputError(f"build_source_free needs a seed (an int, numpy SeedSequence or Generator); got {seed!r}. "
                         f"Pass e.g. seed=comest_bayes.seeding.seed_sequence(root_seed, Stream.SOURCEFREE).")
    if isinstance(seed, np.random.Generator):
        return seed
    if isinstance(seed, (np.random.SeedSequence, int, np.integer)):
        return rng_for(seed)  # the numbers of numpy.random.default_rng(seed)
    raise InputError(f"seed must be an int, numpy SeedSequence or Generator; got {type(seed).__name__}.")


def build_source_free(data, detection, *, mask, fwhm, config: SourceFreeConfig = SourceFreeConfig(),
                      seed) -> SourceFreeResult:
    """Replace the detected sources by sky noise.

    Parameters
    ----------
    data : ndarray, shape (ny, nx)
        Observed image *including* its sky, image units; masked pixels may hold
        anything finite (``load_image`` sets them to 0).
    detection : comest_bayes.detect.sep_backend.DetectionResult
        Detection on ``data``: ``catalog``, ``segmentation``, ``background``,
        ``rms``, ``noise`` (same shape as ``data``) and ``meta``.
    mask : ndarray of bool, shape (ny, nx), or None
        True for bad pixels; they are neither replaced nor used for the
        background and keep their input values.
    fwhm : float
        Seeing FWHM in pixels.
    config : SourceFreeConfig
        Growth radii, background re-estimate and BnB selection.
    seed : int, numpy.random.SeedSequence or numpy.random.Generator
        Source of the sky draws; the same seed gives the identical result.

    Returns
    -------
    SourceFreeResult

    Raises
    ------
    InputError
        On mismatched shapes, a non-positive FWHM, non-finite data or a missing
        seed.
    """
    data = np.asarray(data)
    if data.ndim != 2:
        raise InputError(f"data must be a 2-D image; got an array of shape {data.shape}.")
    shape = data.shape
    seg = np.asarray(detection.segmentation)
    if seg.shape != shape:
        raise InputError(f"the segmentation map has shape {seg.shape} but the image {shape}; pass the detection "
                         f"made on this image.")
    if mask is None:
        mask = np.zeros(shape, dtype=bool)
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != shape:
        raise InputError(f"the mask has shape {mask.shape} but the image {shape}.")
    try:
        fwhm = float(fwhm)
    except (TypeError, ValueError):
        raise InputError(f"fwhm must be a number of pixels; got {fwhm!r}.") from None
    if not np.isfinite(fwhm) or fwhm <= 0:
        raise InputError(f"fwhm must be a positive number of pixels; got {fwhm!r}. Estimate it with "
                         f"comest_bayes.detect.psf.estimate_fwhm or pass --fwhm.")
    data = np.ascontiguousarray(data, dtype=np.float32)
    if not np.all(np.isfinite(data[~mask])):
        raise InputError("the image holds NaN or infinite values in unmasked pixels; mask them first.")
    rng = _rng(seed)
    catalog = detection.catalog

    # ---- which pixels go --------------------------------------------------------------
    seg_ids = np.arange(1, int(seg.max(initial=0)) + 1)
    areas = np.bincount(seg.ravel(), minlength=seg_ids.size + 1)[1:] if seg_ids.size else np.zeros(0)
    present = areas > 0
    seg_ids, areas = seg_ids[present], areas[present]
    radii = removal_radii(areas, fwhm, config)
    cat_ids = np.asarray(catalog["id"], dtype=np.int64) if len(catalog) else np.zeros(0, dtype=np.int64)
    removed = dilated_footprint(seg, seg_ids, radii)
    removed |= _kron_ellipses(shape, catalog, cat_ids, config.kron_mask)
    removed &= ~mask

    # ---- the sky they are replaced with ----------------------------------------------------
    good = ~mask
    sky = good & ~removed
    back_size, back_filt = _background_mesh(detection, config)
    nsky = int(sky.sum())
    reestimated = bool(config.reestimate_background and nsky >= max(back_size * back_size, 1000))
    # SEP drops meshes with too few sky pixels and fills them from their neighbours; when most are
    # dropped (a crowded field), the re-estimate rests on a few meshes or none (a background of 0)
    meshes_kept = _kept_mesh_fraction(sky, back_size) if config.reestimate_background else None
    if reestimated and meshes_kept < _MESHES_MIN_KEPT:
        reestimated = False
    if reestimated:
        bkg = sep.Background(np.where(mask, 0.0, data).astype(np.float32), mask=~sky, bw=back_size, bh=back_size,
                             fw=back_filt, fh=back_filt)
        back = bkg.back(dtype=np.float32)
        rms = bkg.rms(dtype=np.float32)
    else:
        back = np.asarray(detection.background, dtype=np.float32)
        rms = np.asarray(detection.rms, dtype=np.float32)
    noise_mode = str((getattr(detection, "meta", {}) or {}).get("noisemod", "background"))
    if noise_mode == "weight":
        # A weight map knows the pixel-to-pixel shape of the noise better than the mesh RMS.
        shape_map = np.asarray(detection.noise, dtype=np.float32)
    else:
        shape_map = rms
    shape_map = np.where(np.isfinite(shape_map) & (shape_map > 0), shape_map,
                         float(np.median(shape_map[good])) if good.any() else 1.0).astype(np.float32)
    scale = 1.0
    if nsky >= 100:
        idx = np.flatnonzero(sky.ravel())
        if idx.size > _CALIBRATION_PIXELS:
            idx = idx[:: int(np.ceil(idx.size / _CALIBRATION_PIXELS))]
        z = (data.ravel()[idx] - back.ravel()[idx]) / shape_map.ravel()[idx]
        scale = float(_MAD_TO_SIGMA * np.median(np.abs(z - np.median(z))))
        if not np.isfinite(scale) or scale <= 0:
            scale = 1.0
    sigma = shape_map * np.float32(scale)

    sfi = data.copy()
    n_removed = int(removed.sum())
    draws = rng.standard_normal(n_removed, dtype=np.float32)
    sfi[removed] = back[removed] + sigma[removed] * draws

    # ---- bright and big -------------------------------------------------------------------
    bnb = None
    kept_ids = np.zeros(0, dtype=np.int64)
    bnb_frac = None
    if config.bnb and len(catalog):
        snr = np.asarray(catalog["snr_auto"], dtype=float)
        npix = np.asarray(catalog["npix"], dtype=float)
        keep = np.isfinite(snr) & (snr >= config.bnb_snr_min) & (npix >= config.bnb_area_min)
        kept_ids = np.sort(cat_ids[keep])
        in_seg = np.isin(seg_ids, kept_ids)
        keep_region = dilated_footprint(seg, seg_ids[in_seg], radii[in_seg])
        keep_region |= _kron_ellipses(shape, catalog, kept_ids, config.kron_mask)
        keep_region &= good
        bnb = np.where(keep_region, data, sfi).astype(np.float32)
        bnb_frac = float((removed & ~keep_region).sum() / max(int(good.sum()), 1))
    elif config.bnb:
        bnb = sfi.copy()
        bnb_frac = float(n_removed / max(int(good.sum()), 1))

    ngood = max(int(good.sum()), 1)
    det_noise = np.asarray(detection.noise, dtype=np.float32)
    det_back = np.asarray(detection.background, dtype=np.float32)
    valid = good & np.isfinite(det_noise) & (det_noise > 0)
    if valid.any():
        noise_ref = float(np.median(det_noise[valid]))
        shift_sigma = float(np.median((back[valid] - det_back[valid]) / det_noise[valid]))
        noise_ratio = float(np.median(sigma[valid]) / noise_ref)
    else:
        noise_ref = shift_sigma = noise_ratio = None
    meta = {
        "fwhm": fwhm,
        "dilate": float(config.dilate),
        "dilate_size": float(config.dilate_size),
        "dilate_min_pix": int(config.dilate_min_pix),
        "kron_mask": float(config.kron_mask),
        "radius_base_pix": float(max(config.dilate * fwhm, config.dilate_min_pix)),
        "radius_min_pix": float(radii.min()) if radii.size else None,
        "radius_median_pix": float(np.median(radii)) if radii.size else None,
        "radius_max_pix": float(radii.max()) if radii.size else None,
        "nsources_removed": int(seg_ids.size),
        "npix_replaced": n_removed,
        "fraction_replaced": float(n_removed / ngood),
        "background_reestimated": reestimated,
        "background_meshes_kept": meshes_kept,
        "back_size": back_size,
        "back_filtersize": back_filt,
        "background_median": float(np.median(back[good])) if good.any() else None,
        "background_shift": float(np.median((back - detection.background)[good])) if good.any() else None,
        "noise_source": "weight map" if noise_mode == "weight" else "background rms",
        "noise_scale": scale,
        "noise_median": float(np.median(sigma[good])) if good.any() else None,
        "detection_noise_median": noise_ref,
        "background_shift_sigma": shift_sigma,
        "noise_ratio": noise_ratio,
        "bnb": bool(config.bnb),
        "bnb_nkept": int(kept_ids.size),
        "bnb_fraction_replaced": bnb_frac,
    }
    return SourceFreeResult(sfi=sfi, bnb=bnb, removed=removed, kept_ids=kept_ids, meta=meta)


def format_percent(fraction: float) -> str:
    """A fraction as a percentage with one decimal, or as many as keep a fraction below 1 under 100%."""
    value = 100.0 * float(fraction)
    digits = 1
    while digits < 4 and value < 100.0 and round(value, digits) >= 100.0:
        digits += 1
    return f"{value:.{digits}f}%"


#: What each injection target is called in messages.
_TARGETS = {"sfi": "source-free image", "bnb": "bright-and-big image", "observed": "observed image"}


def judge_replacement(meta: dict, *, on: str = "sfi", warn_fraction: float = 0.5,
                      max_fraction: float = 0.9) -> dict:
    """How much of the image the injections land on is no longer the observed image, and whether to go on.

    The completeness is the observed image's only as far as the injections see
    its sky: where most of the unmasked pixels are replaced by draws of a fitted
    sky (a crowded field, or segments grown over each other), the detector
    works on a synthetic image whose background and noise are those of the fit.

    Parameters
    ----------
    meta : dict
        :attr:`SourceFreeResult.meta`.
    on : {"sfi", "bnb", "observed"}
        The image injected on (``injection.on``); the observed image has no
        pixel replaced.
    warn_fraction, max_fraction : float
        Fractions of the unmasked pixels replaced above which the run is
        warned about and refused (``sourcefree.warn_replaced`` and
        ``sourcefree.max_replaced``).

    Returns
    -------
    dict
        Plain JSON: ``injected_on``, ``fraction_replaced`` (of the image
        injected on), ``sfi_fraction_replaced``, ``bnb_fraction_replaced``
        (None without a BnB image), ``warn_fraction``, ``max_fraction``, the
        fill against the detection's maps (``background_shift_sigma``,
        ``noise_ratio``), ``warnings`` (lines) and ``refusal`` (the error
        message, or None when the run may go on).
    """
    sfi_frac = float(meta.get("fraction_replaced") or 0.0)
    bnb_frac = meta.get("bnb_fraction_replaced")
    frac = {"sfi": sfi_frac, "bnb": bnb_frac, "observed": 0.0}.get(on)
    if frac is None:
        frac = sfi_frac  # no BnB image was made; the pipeline refuses injection.on='bnb' then
    shift, ratio = meta.get("background_shift_sigma"), meta.get("noise_ratio")
    out = {"injected_on": on, "fraction_replaced": float(frac), "sfi_fraction_replaced": sfi_frac,
           "bnb_fraction_replaced": None if bnb_frac is None else float(bnb_frac),
           "warn_fraction": float(warn_fraction), "max_fraction": float(max_fraction),
           "background_shift_sigma": shift, "noise_ratio": ratio, "warnings": [], "refusal": None}
    if on == "observed":
        return out
    target = _TARGETS.get(on, on)
    pct = format_percent(frac)
    if frac > max_fraction:
        alternatives = ["inject on the observed image itself, as Balrog does (--set injection.on=observed: the "
                        "injections then meet the real sources, and blending with them counts in the completeness)"]
        if on != "bnb" and bnb_frac is not None and bnb_frac <= max_fraction:
            alternatives.append(f"inject on the bright-and-big image, which keeps the bright sources as observed and "
                                f"replaces {format_percent(bnb_frac)} (--set injection.on=bnb)")
        elif on != "bnb" and bnb_frac is None:
            alternatives.append("inject on the bright-and-big image (--set sourcefree.bnb=true "
                                "--set injection.on=bnb), which keeps the bright sources as observed")
        alternatives.append(f"accept the {target} anyway with --set sourcefree.max_replaced=1")
        out["refusal"] = (
            f"the {target} replaces {pct} of the unmasked pixels by draws of a fitted sky (more than "
            f"sourcefree.max_replaced = {100 * max_fraction:g}%): so little of the observed sky is left that the "
            f"completeness would be measured on the fit's background and noise, not the image's. Alternatives: "
            + "; or ".join(alternatives) + ". Nothing was written.")
        return out
    if frac > warn_fraction:
        out["warnings"].append(
            f"the {target} replaces {pct} of the unmasked pixels (more than sourcefree.warn_replaced = "
            f"{100 * warn_fraction:g}%): the completeness is measured mostly on draws of a fitted sky rather than "
            f"the observed noise; consider --set injection.on=observed (injecting on the observed image, as Balrog "
            f"does)" + (" or --set injection.on=bnb" if on == "sfi" and bnb_frac is not None and bnb_frac < frac
                        else ""))
    if shift is not None and abs(shift) > BACKGROUND_SHIFT_WARN_SIGMA:
        level = meta.get("background_median")
        out["warnings"].append(
            f"the sky drawn into the {target} lies {shift:+.2f} sigma from the detection's background map (more "
            f"than {BACKGROUND_SHIFT_WARN_SIGMA} sigma; its median level is "
            f"{'n/a' if level is None else f'{level:.4g}'}): the replaced "
            f"patches are {'fainter' if shift < 0 else 'brighter'} than the sky the detector measured; check "
            f"{layout.BACKGROUND} and {layout.SFI}")
    if ratio is not None and abs(ratio - 1.0) > NOISE_RATIO_WARN:
        out["warnings"].append(
            f"the noise drawn into the {target} is {ratio:.2f} times the detection's noise map (more than "
            f"{100 * NOISE_RATIO_WARN:g}% off): the injections see another noise than the image's; check {layout.RMS} "
            f"and {layout.SFI}")
    kept = meta.get("background_meshes_kept")
    if kept is not None and not meta.get("background_reestimated"):
        # then the fill is the detection's own background, so the shift check above compares it with itself
        out["warnings"].append(
            f"the sky under the removed sources could not be measured again: {format_percent(kept)} of the "
            f"background meshes keep enough sky pixels (at least {format_percent(_MESHES_MIN_KEPT)} are needed), so "
            f"the replaced patches are filled from the detection's background map, which carries the light of the "
            f"largest sources; a detection on the {target} inside a replaced patch may be that light (check "
            f"{layout.BACKGROUND}, {layout.SFI})")
    return out
